"""The self-audit of a certificate (``audit_every``): re-render poses inside every segment of its plan
through the same imaging model and check every bound the certificate used
(:mod:`pws_ros.core.audit`, its own distance code)."""
from __future__ import annotations

from typing import Any, Callable

from ..core.cloud import Cloud
from ..core.result import Certificate


def audit_certificate(cert: Certificate, cloud: Cloud, imaging: Any, plan: Any, *, device: str, num_anchors: int,
                      audit_poses: int, log: Callable[[str, str], None]) -> None:
    """Re-render ``audit_poses`` poses inside every segment of ``plan`` and check every bound ``cert``
    used (its anchors, or ``num_anchors`` evenly placed ones for coverage anchors). Recorded in
    ``cert.bounds['audit']``; a violation makes the axis ERROR, an audit that cannot run says so."""
    from ..core.audit import audit_bounds
    from ..core.coverage import anchor_indices
    from ..core.imaging import make_renderer, segment_bounds

    try:
        renderer = make_renderer(cloud, imaging, plan.axis, device=device)
        values = segment_bounds(renderer, cloud, imaging, plan.alphas)
        anchors = cert.bounds.get("anchors")
        if anchors is None and cert.coverage == "anchors":
            anchors = plan.alphas[anchor_indices(plan.num_partitions, num_anchors)]
        report = audit_bounds(renderer, plan.alphas, values, anchor_alphas=anchors,
                              poses_per_segment=int(audit_poses), seed=int(cert.seed or 0))
    except Exception as exc:  # an audit that cannot run says so; it never passes silently
        log("error", f"self-audit of {plan.axis} failed to run: {type(exc).__name__}: {exc}")
        cert.bounds["audit"] = {"error": f"{type(exc).__name__}: {exc}"}
        return
    cert.bounds["audit"] = {"poses": report.poses_checked, "violations": len(report.violations),
                            "worst_ratio": report.worst_ratio, "seconds": report.seconds}
    log("info", f"self-audit {plan.axis}: {report.poses_checked} poses re-rendered in {plan.num_partitions - 1} "
                f"segments, {len(report.violations)} bound violation(s), worst measured/bound "
                f"{report.worst_ratio:.6g}, {report.seconds:.1f} s")
    if report.violations:
        v = report.violations[0]
        log("error", f"self-audit of {plan.axis}: {len(report.violations)} bound violation(s), e.g. segment "
                     f"{v.segment} alpha={v.alpha!r}: {v.measured:.6g} > {v.bound:.6g}")
        cert.status, cert.certified, cert.radius = "error", False, 0.0
        cert.reason = (f"self-audit found {len(report.violations)} bound violation(s) in {report.poses_checked} "
                       f"re-rendered poses: the certificate is withdrawn")


__all__ = ["audit_certificate"]

"""``pws audit``: re-render poses densely inside every segment of a plan and check every bound directly."""
from __future__ import annotations

import math

from ..core.audit import DEFAULT_POSES_PER_SEGMENT, audit_bounds
from ..core.certify import CertifyConfig
from ..core.coverage import anchor_indices
from ..core.imaging import make_imaging, make_renderer, plan_for, segment_bounds
from ..core.motion import UNITS
from .common import add_imaging_size_arg, add_output_args, add_plan_args, add_scene_args, add_drawing_args, emit, load_scene, positive_int, volume_from_args, background_from_args, add_background_arg
from . import SUMMARIES

MAX_LISTED = 20


def register(sub) -> None:
    d = CertifyConfig()
    p = sub.add_parser("audit", help=SUMMARIES["audit"],
                       description="Plan the grid as `pws certify` does, compute the per-segment bounds the certificate "
                                   "rests on (pair bound B_i of the paper and pairwise rules, anchor distances D_i of the "
                                   "anchors rule), then re-render poses inside every segment (its ends, their float "
                                   "neighbours and random interior poses) through the same renderer and check, with "
                                   "independent code, that no measured distance exceeds its bound. Exit status 0 if no "
                                   "bound is violated, 1 if any is (each violation is listed), 2 on bad input.")
    add_scene_args(p)
    add_plan_args(p)
    add_imaging_size_arg(p)
    p.add_argument("--poses-per-segment", type=positive_int, default=DEFAULT_POSES_PER_SEGMENT, metavar="K",
                   help=f"re-rendered poses per segment, ends included (default {DEFAULT_POSES_PER_SEGMENT}; raised "
                        "where needed to reach --min-poses)")
    p.add_argument("--min-poses", type=positive_int, default=1000, metavar="N",
                   help="check at least N poses in all (default 1000)")
    p.add_argument("--anchors", type=positive_int, default=d.num_anchors, dest="num_anchors", metavar="K",
                   help=f"anchor frames whose distance bounds are checked, as --coverage anchors uses them "
                        f"(default {d.num_anchors})")
    add_background_arg(p)
    add_drawing_args(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the random interior poses (default 0)")
    p.add_argument("--device", default=d.device, help="torch device: cpu or cuda[:N] (default cpu)")
    add_output_args(p, "print the audit report as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    cloud, intr = load_scene(args)
    CertifyConfig(background=background_from_args(args)).validate()
    im = make_imaging(args.imaging, intr, args.size, background=background_from_args(args), border=args.border, cloud=cloud,
                      radii={args.axis: args.radius}, render_factor=args.render_factor, uncovered=args.uncovered, volume=volume_from_args(args))
    plan = plan_for(cloud, im, args.axis, args.radius, args.method, step_px=args.step_px, delta=args.delta,
                    max_partitions=args.max_partitions, min_partitions=args.min_partitions)
    renderer = make_renderer(cloud, im, plan.axis, device=args.device)
    values = segment_bounds(renderer, cloud, im, plan.alphas)
    nseg = plan.num_partitions - 1
    per_segment = max(int(args.poses_per_segment), math.ceil(args.min_poses / nseg))
    anchors = plan.alphas[anchor_indices(plan.num_partitions, args.num_anchors)]
    report = audit_bounds(renderer, plan.alphas, values, anchor_alphas=anchors, poses_per_segment=per_segment,
                          seed=args.seed)
    d = {"axis": plan.axis, "unit": UNITS[plan.axis], "method": plan.method, "imaging": im.kind, "radius": plan.radius,
         "num_partitions": plan.num_partitions, "poses_per_segment": per_segment,
         "anchor_alphas": [float(a) for a in anchors], **report.to_dict()}
    lines = [f"audit {plan.method} {plan.axis} ±{plan.radius:g} {UNITS[plan.axis]} ({im.kind} imaging): "
             + ("OK, no bound violated" if report.ok else f"{len(report.violations)} VIOLATIONS"),
             f"{'partitions':18s}{plan.num_partitions} ({nseg} segments, {per_segment} poses each)",
             f"{'poses checked':18s}{report.poses_checked} ({report.checks} distance checks: pair bound + "
             f"{len(anchors)} anchors)",
             f"{'worst ratio':18s}{report.worst_ratio:.9g} (measured / bound, <= 1 when sound)",
             f"{'seconds':18s}{report.seconds:.2f}"]
    for v in report.violations[:MAX_LISTED]:
        what = "pair bound" if v.kind == "pair" else f"anchor {v.anchor} distance"
        lines.append(f"  VIOLATION segment {v.segment} alpha={v.alpha!r}: {what} {v.measured:.9g} > {v.bound:.9g}")
    if len(report.violations) > MAX_LISTED:
        lines.append(f"  ... and {len(report.violations) - MAX_LISTED} more (--json lists all)")
    emit(d, args.json, lines)
    return 0 if report.ok else 1

"""Certificates -> ``diagnostic_msgs/DiagnosticArray`` and back, the ``certified_label`` message of a frame
certified on every axis, RViz/Foxglove text markers, and the ``/diagnostics`` health status of a node (builders take the ``types`` namespace of
:mod:`pws_ros.bridge.msgtypes`).

Certification schema (``diagnostic_msgs/DiagnosticArray`` on ``certification``): header = the
source header; one ``DiagnosticStatus`` per axis named ``pws/<axis>`` with ``hardware_id`` = the
source frame id, ``level`` OK = certified, WARN = not certified or abstained, ERROR = could not
certify (``message`` says why), and ``values`` with exactly these keys first, in this order
(:data:`DIAGNOSTIC_KEYS`)::

    label class_name certified radius unit p_a_lower sigma n alpha frame_alpha num_partitions
    classifier_calls latency_ms compute_ms

followed by :data:`DIAGNOSTIC_EXTRA_KEYS`. ``p_a_lower`` is the smallest lower bound used.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..core.errors import require
from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_ERROR, STATUS_NOT_CERTIFIED, Certificate
from .msgtypes import identity_pose, make, make_header

DIAGNOSTIC_KEYS: tuple[str, ...] = (
    "label", "class_name", "certified", "radius", "unit", "p_a_lower", "sigma", "n", "alpha", "frame_alpha",
    "num_partitions", "classifier_calls", "latency_ms", "compute_ms",
)
DIAGNOSTIC_EXTRA_KEYS: tuple[str, ...] = (
    "status", "requested_radius", "method", "coverage", "n0", "delta_alpha", "num_bounds",
    "frames_rendered", "imaging", "filled_points", "working_volume", "reason", "node",
)
STATUS_NAME_PREFIX = "pws/"


# ---- certification ------------------------------------------------------------------------

LEVEL_FOR_STATUS = {STATUS_CERTIFIED: "OK", STATUS_NOT_CERTIFIED: "WARN", STATUS_ABSTAIN: "WARN", STATUS_ERROR: "ERROR"}


def level_value(types: Any, name: str) -> Any:
    """The class constant ``DiagnosticStatus.<name>`` (rclpy: a 1-byte ``bytes``; rosbags: int)."""
    return getattr(types.DiagnosticStatus, name)


def level_to_int(level: Any) -> int:
    if isinstance(level, (bytes, bytearray)):
        return int(level[0]) if len(level) else 0
    return int(level)


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return f"{v:.9g}"
    return str(v)


def _per_cert(value: Any, i: int, cert: Certificate, default: float) -> float:
    if value is None:
        return default
    if isinstance(value, dict):
        return float(value.get(cert.axis, default))
    if isinstance(value, (list, tuple, np.ndarray)):
        return float(value[i])
    return float(value)


def certificate_message(cert: Certificate) -> str:
    """The one-line ``DiagnosticStatus.message`` of a certificate."""
    if cert.status == STATUS_ERROR:
        return f"could not certify: {cert.reason or 'unknown error'}"
    if cert.status == STATUS_ABSTAIN:
        return "abstained: no class has p_A > 1/2 at the original pose" + (f" ({cert.reason})" if cert.reason else "")
    head = (f"{cert.class_name or cert.label} certified for ±{cert.requested_radius:.6g} {cert.unit}"
            if cert.certified else
            f"{cert.class_name or cert.label} not certified for ±{cert.requested_radius:.6g} {cert.unit} "
            f"(covered ±{cert.radius:.6g} {cert.unit})")
    return head + (f"; {cert.reason}" if cert.reason and not cert.certified else "")


def certificate_values(cert: Certificate, *, latency_ms: float, compute_ms: float, node_name: str = "") -> list[tuple[str, str]]:
    """The ``(key, value)`` pairs of one status: :data:`DIAGNOSTIC_KEYS` then the extras."""
    vals: list[tuple[str, Any]] = [
        ("label", int(cert.label)),
        ("class_name", cert.class_name),
        ("certified", bool(cert.certified)),
        ("radius", float(cert.radius)),
        ("unit", cert.unit),
        ("p_a_lower", float(cert.min_p_a_lower)),
        ("sigma", float(cert.sigma)),
        ("n", int(cert.n)),
        ("alpha", float(cert.alpha)),
        ("frame_alpha", float(cert.frame_alpha if cert.frame_alpha is not None else cert.alpha)),
        ("num_partitions", int(cert.num_partitions)),
        ("classifier_calls", int(cert.classifier_calls)),
        ("latency_ms", float(latency_ms)),
        ("compute_ms", float(compute_ms)),
        ("status", cert.status),
        ("requested_radius", float(cert.requested_radius)),
        ("method", cert.method),
        ("coverage", cert.coverage),
        ("n0", int(cert.n0)),
        ("delta_alpha", float(cert.delta_alpha)),
        ("num_bounds", int(cert.num_bounds)),
        ("frames_rendered", int(cert.frames_rendered)),
        ("imaging", cert.imaging),
        ("filled_points", int(cert.filled_points)),
        ("working_volume", cert.working_volume or "none"),
        ("reason", " ".join(str(cert.reason).split())),
        ("node", node_name),
    ]
    return [(k, _fmt(v)) for k, v in vals]


def certificates_to_diagnostic_array(header: Any, certs: Sequence[Certificate], *, node_name: str, types: Any,
                                     latency_ms: float, compute_ms: Any = None) -> Any:
    """The ``certification`` message of one input frame (see the module docstring for the schema).

    ``header``: the source header (its ``frame_id`` becomes every status' ``hardware_id``);
    ``latency_ms``: node clock now minus the source stamp; ``compute_ms``: a number, a per-axis
    dict or sequence, or None for each certificate's ``timings['total']``.
    """
    statuses = []
    frame = str(getattr(header, "frame_id", "") or "")
    for i, cert in enumerate(certs):
        default_compute = 1000.0 * float(cert.timings.get("total", float("nan"))) if cert.timings else float("nan")
        cm = _per_cert(compute_ms, i, cert, default_compute)
        values = [make(types.KeyValue, key=k, value=v)
                  for k, v in certificate_values(cert, latency_ms=float(latency_ms), compute_ms=cm, node_name=node_name)]
        statuses.append(make(types.DiagnosticStatus, level=level_value(types, LEVEL_FOR_STATUS.get(cert.status, "ERROR")),
                             name=STATUS_NAME_PREFIX + cert.axis, message=certificate_message(cert),
                             hardware_id=frame, values=values))
    return make(types.DiagnosticArray, header=header, status=statuses)


def diagnostic_array_to_dicts(msg: Any) -> list[dict[str, Any]]:
    """Parse a DiagnosticArray: one dict per status with ``name``, ``level`` (int), ``message``,
    ``hardware_id``, ``keys`` (in message order) and ``values`` (key -> string)."""
    out = []
    for st in list(msg.status):
        keys = [str(kv.key) for kv in st.values]
        out.append({
            "name": str(st.name),
            "level": level_to_int(st.level),
            "message": str(st.message),
            "hardware_id": str(st.hardware_id),
            "keys": keys,
            "values": {str(kv.key): str(kv.value) for kv in st.values},
        })
    return out


def parse_certification(msg: Any) -> dict[str, dict[str, Any]]:
    """A ``certification`` message as ``{axis: {key: typed value}}`` (checks the key schema)."""
    out: dict[str, dict[str, Any]] = {}
    for st in diagnostic_array_to_dicts(msg):
        require(st["name"].startswith(STATUS_NAME_PREFIX), f"status {st['name']!r} is not a pws certification status")
        require(tuple(st["keys"][: len(DIAGNOSTIC_KEYS)]) == DIAGNOSTIC_KEYS,
                f"status {st['name']!r} keys {st['keys'][:len(DIAGNOSTIC_KEYS)]} do not follow the schema {list(DIAGNOSTIC_KEYS)}")
        v = st["values"]
        typed: dict[str, Any] = dict(v)
        for k in ("label", "n", "num_partitions", "classifier_calls", "n0", "num_bounds", "frames_rendered"):
            if k in v:
                typed[k] = int(v[k])
        for k in ("radius", "p_a_lower", "sigma", "alpha", "frame_alpha", "latency_ms", "compute_ms", "requested_radius",
                  "delta_alpha"):
            if k in v:
                typed[k] = float(v[k])
        typed["certified"] = v["certified"] == "true"
        typed["level"] = st["level"]
        typed["message"] = st["message"]
        typed["hardware_id"] = st["hardware_id"]
        out[st["name"][len(STATUS_NAME_PREFIX):]] = typed
    return out


# ---- the certified label ------------------------------------------------------------------

CERTIFIED_LABEL_STATUS = "pws/certified_label"
CERTIFIED_LABEL_KEYS: tuple[str, ...] = ("label", "class_name", "p_a_lower", "frame_alpha", "axes")


def certified_label(certs: Sequence[Certificate]) -> Certificate | None:
    """The certificate of the frame's label when the frame is certified on **every** axis at its requested
    radius with **one** label (the first axis' certificate), else None (no axis, one not certified,
    abstained or failed, or axes that certified different labels)."""
    if not certs or any(c.status != STATUS_CERTIFIED or not c.certified for c in certs):
        return None
    return certs[0] if len({int(c.label) for c in certs}) == 1 else None


def certified_label_array(header: Any, certs: Sequence[Certificate], *, node_name: str, types: Any) -> Any:
    """The ``certified_label`` message of a frame certified on every axis (:func:`certified_label`), else None.

    Header = the source header; one ``DiagnosticStatus`` named :data:`CERTIFIED_LABEL_STATUS`, level OK,
    ``message`` = the class name (the label index when the model has no names), ``hardware_id`` = the
    source frame id, ``values``: :data:`CERTIFIED_LABEL_KEYS` (``p_a_lower`` the least over the axes,
    ``frame_alpha`` the risk of the whole statement, ``axes`` comma-separated), then ``radius.<axis>``
    (the certified radius, m or rad) per axis in axis order, then ``node``.
    """
    cert = certified_label(certs)
    if cert is None:
        return None
    pairs: list[tuple[str, Any]] = [
        ("label", int(cert.label)), ("class_name", cert.class_name), ("p_a_lower", min(c.min_p_a_lower for c in certs)),
        ("frame_alpha", float(cert.frame_alpha if cert.frame_alpha is not None else cert.alpha)),
        ("axes", ",".join(c.axis for c in certs)),
        *((f"radius.{c.axis}", float(c.radius)) for c in certs), ("node", node_name),
    ]
    st = make(types.DiagnosticStatus, level=level_value(types, "OK"), name=CERTIFIED_LABEL_STATUS,
              message=cert.class_name or str(int(cert.label)), hardware_id=str(getattr(header, "frame_id", "") or ""),
              values=[make(types.KeyValue, key=k, value=_fmt(v)) for k, v in pairs])
    return make(types.DiagnosticArray, header=header, status=[st])


# ---- RViz / Foxglove markers --------------------------------------------------------------

_LEVEL_COLORS = {"OK": (0.1, 0.9, 0.1), "WARN": (1.0, 0.8, 0.0), "ERROR": (1.0, 0.15, 0.15)}


def marker_text(cert: Certificate) -> str:
    if cert.status == STATUS_ERROR:
        return f"{cert.axis}: error ({cert.reason[:60]})"
    if cert.status == STATUS_ABSTAIN:
        return f"{cert.axis}: abstain"
    mark = "OK" if cert.certified else "NOT certified"
    return f"{cert.axis} ±{cert.requested_radius:.4g} {cert.unit}: {cert.class_name or cert.label} {mark} (p_A≥{cert.min_p_a_lower:.3f})"


def markers_for(header: Any, certs: Sequence[Certificate], types: Any, *, ns: str = "pws", text_height: float = 0.05,
                distance: float = 1.0, lifetime_s: float = 0.0) -> Any:
    """A ``MarkerArray`` of ``TEXT_VIEW_FACING`` markers (one line per axis, stacked downwards,
    ``distance`` metres in front of the camera in the source optical frame), coloured by level."""
    markers = []
    life = make(types.Duration, sec=int(lifetime_s), nanosec=int(round((lifetime_s % 1.0) * 1e9)))
    for i, cert in enumerate(certs):
        r, g, b = _LEVEL_COLORS[LEVEL_FOR_STATUS.get(cert.status, "ERROR")]
        kw: dict[str, Any] = dict(
            header=header, ns=ns, id=i, type=int(types.Marker.TEXT_VIEW_FACING), action=int(types.Marker.ADD),
            pose=identity_pose(types, (0.0, -0.2 + 1.5 * text_height * i, float(distance))),
            scale=make(types.Vector3, x=0.0, y=0.0, z=float(text_height)),
            color=make(types.ColorRGBA, r=r, g=g, b=b, a=1.0), lifetime=life, frame_locked=False,
            points=[], colors=[], texture_resource="", uv_coordinates=[], text=marker_text(cert),
            mesh_resource="", mesh_use_embedded_materials=False,
        )
        if hasattr(types, "CompressedImage"):
            kw["texture"] = make(types.CompressedImage, header=make_header(types, 0, ""), format="", data=types.u8(np.zeros(0, np.uint8)))
        if hasattr(types, "MeshFile"):
            kw["mesh_file"] = make(types.MeshFile, filename="", data=types.u8(np.zeros(0, np.uint8)))
        markers.append(make(types.Marker, **kw))
    return make(types.MarkerArray, markers=markers)


# ---- health -------------------------------------------------------------------------------

def health_status(header: Any, *, node_name: str, types: Any, rate_hz: float, frames_in: int, frames_processed: int,
                  frames_dropped: int, device: str, last_error: str = "", warning: str = "",
                  extra: dict[str, Any] | None = None, activity: str = "processed") -> Any:
    """A ``/diagnostics`` DiagnosticArray with one status ``<node_name>: health``.

    Level ERROR when ``last_error`` is set, WARN when ``warning`` is set, else OK with the message
    ``"<frames_processed> frames <activity>, <frames_dropped> dropped"`` (activity: what the node does
    to a frame: certified, converted, planned, rendered). Keys: rate_hz, frames_in,
    frames_processed, frames_dropped, device, last_error, then ``extra``.
    """
    if last_error:
        level, message = "ERROR", " ".join(str(last_error).split())
    elif warning:
        level, message = "WARN", " ".join(str(warning).split())
    else:
        level, message = "OK", f"{frames_processed} frames {activity}, {frames_dropped} dropped"
    pairs: list[tuple[str, Any]] = [
        ("rate_hz", float(rate_hz)), ("frames_in", int(frames_in)), ("frames_processed", int(frames_processed)),
        ("frames_dropped", int(frames_dropped)), ("device", str(device)), ("last_error", " ".join(str(last_error).split())),
    ]
    pairs += list((extra or {}).items())
    values = [make(types.KeyValue, key=str(k), value=_fmt(v)) for k, v in pairs]
    st = make(types.DiagnosticStatus, level=level_value(types, level), name=f"{node_name}: health", message=message,
              hardware_id=str(getattr(header, "frame_id", "") or ""), values=values)
    return make(types.DiagnosticArray, header=header, status=[st])


__all__ = ["CERTIFIED_LABEL_KEYS", "CERTIFIED_LABEL_STATUS", "DIAGNOSTIC_EXTRA_KEYS", "DIAGNOSTIC_KEYS", "LEVEL_FOR_STATUS",
           "STATUS_NAME_PREFIX", "certificate_message", "certificate_values", "certificates_to_diagnostic_array", "certified_label",
           "certified_label_array", "diagnostic_array_to_dicts", "health_status", "level_to_int", "level_value", "marker_text",
           "markers_for", "parse_certification"]

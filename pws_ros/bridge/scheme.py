"""The wire scheme of the four-process mode (common_interfaces types only).

Per input frame (source stamp ``S`` in ns, source optical frame ``F``):

``plan/cloud`` — ``sensor_msgs/PointCloud2``, header ``(S, F)``: the one-frame cloud that was planned,
    handed on by the planner just before its ``plan`` (the projector renders from it; the camera
    outruns planning, so it must not be looked up among the newer clouds on ``cloud``).
``plan`` — ``std_msgs/String`` (JSON, :func:`plan_bundle_to_json`)
    ``{"format": "pws_ros/plan-bundle/1", "stamp_ns": S, "frame_id": F, "method": ..., "axes": [...],
    "camera": {...render intrinsics...}, "plans": {axis: Plan.to_dict()}, "errors": {axis: reason}}``.
    One message per input frame lists every configured axis: a plan, or the reason it could not be
    planned. The certifier knows from it which axes and how many frames to expect.
``plan/poses/<axis>`` — ``geometry_msgs/PoseArray``, header ``(S, F)``: the camera poses in partition
    order (for RViz / Foxglove; the plan JSON is authoritative).
``rendered/frames`` — ``sensor_msgs/Image`` ``32FC3`` (values in [0, 1], exactly the float32 frame the
    noise is added to), ``header.stamp = S`` and ``header.frame_id = "S/<axis>/<index>/<count>"``
    (:func:`frame_tag`): every frame names its input frame, axis, partition index and the set size, so a
    lost, duplicate or out-of-range frame is detected. Frames of one axis are published in index order.
``rendered/bounds`` — ``std_msgs/Float64MultiArray`` after the last frame of an axis. ``layout.dim``:
    ``[0]`` label ``"pws_bounds/S/<axis>/<count>"``, size ``count - 1``: the per-segment bounds
    ``pair_bound_sq``; ``[1]`` label ``"extra"``, size ``E``, stride ``5 E``: the sparse extra pixel
    values as rows ``(segment, pixel, r, g, b)``; ``[2]`` label ``"shape"``, size 2: ``(H, W)``.
    ``data`` is the concatenation of the three sections (all exact in float64).
``rendered/errors`` — ``std_msgs/String`` JSON ``{"format": "pws_ros/render-error/1", "stamp_ns": S,
    "axis": a, "reason": "..."}`` when the projector could not render an axis (the certifier then
    reports that axis as ERROR at once instead of waiting for frames that will not come).
``rendered/preview`` — ``sensor_msgs/Image`` ``rgb8``, header ``(S, F)``: every k-th frame, for humans.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import PwsError, require
from ..core.jsonable import jsonable
from ..core.motion import parse_axis
from .msgbuild import image_from_numpy
from .msgtypes import make, make_header
from .msgconv import header_stamp_ns, image_to_numpy

PLAN_FORMAT = "pws_ros/plan-bundle/1"
RENDER_ERROR_FORMAT = "pws_ros/render-error/1"
BOUNDS_PREFIX = "pws_bounds"


# ---- frame tags ---------------------------------------------------------------------------

@dataclass(frozen=True)
class FrameTag:
    stamp_ns: int
    axis: str
    index: int
    count: int

    def __str__(self) -> str:
        return f"{self.stamp_ns}/{self.axis}/{self.index}/{self.count}"


def frame_tag(stamp_ns: int, axis: str, index: int, count: int) -> str:
    """``"<stamp_ns>/<axis>/<index>/<count>"``."""
    return str(FrameTag(int(stamp_ns), axis, int(index), int(count)))


def parse_frame_tag(text: str) -> FrameTag:
    parts = str(text).split("/")
    require(len(parts) == 4, f"frame tag {text!r} is not '<stamp_ns>/<axis>/<index>/<count>'")
    try:
        stamp, index, count = int(parts[0]), int(parts[2]), int(parts[3])
    except ValueError:
        raise PwsError(f"frame tag {text!r} has a non-integer stamp, index or count") from None
    require(stamp >= 0 and count >= 1, f"frame tag {text!r}: stamp must be >= 0 and count >= 1")
    return FrameTag(stamp, parse_axis(parts[1]), index, count)


# ---- plan bundle --------------------------------------------------------------------------

@dataclass
class PlanBundle:
    """Every axis' plan (or planning error) for one input frame, and the camera they render with."""

    stamp_ns: int
    frame_id: str
    method: str
    camera: CameraIntrinsics
    axes: list[str]
    plans: dict[str, Any] = field(default_factory=dict)    # axis -> core.partition.Plan
    errors: dict[str, str] = field(default_factory=dict)   # axis -> reason
    imaging: Any = None                                    # core.imaging.Imaging (None: paper imaging at ``camera``)

    def expected(self) -> dict[str, int | str]:
        """``{axis: frame count or error}`` for :meth:`PartitionAssembler.expect`."""
        out: dict[str, int | str] = {}
        for a in self.axes:
            out[a] = self.errors[a] if a in self.errors else int(len(self.plans[a].alphas))
        return out


def _camera_dict(c: CameraIntrinsics) -> dict[str, Any]:
    return {"width": int(c.width), "height": int(c.height), "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "frame_id": c.frame_id}


def plan_bundle_to_json(bundle: PlanBundle) -> str:
    return json.dumps({
        "format": PLAN_FORMAT,
        "stamp_ns": int(bundle.stamp_ns),
        "frame_id": bundle.frame_id,
        "method": bundle.method,
        "axes": list(bundle.axes),
        "camera": _camera_dict(bundle.camera),
        "plans": {a: jsonable(p.to_dict(), inf="string") for a, p in bundle.plans.items()},
        "errors": dict(bundle.errors),
        "imaging": bundle.imaging.to_dict() if bundle.imaging is not None else None,
    }, allow_nan=False)


def plan_bundle_from_json(text: str) -> PlanBundle:
    from ..core.imaging import Imaging
    from ..core.partition import Plan

    try:
        d = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise PwsError(f"plan message is not JSON: {exc}") from None
    require(isinstance(d, dict) and d.get("format") == PLAN_FORMAT, f"plan message is not a {PLAN_FORMAT} bundle")
    try:
        cam = CameraIntrinsics.from_dict(d["camera"], source="plan camera")
        cam = CameraIntrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, str(d["camera"].get("frame_id", "")))
        axes = [parse_axis(a) for a in d["axes"]]
        plans = {parse_axis(a): Plan.from_dict(p) for a, p in d.get("plans", {}).items()}
        errors = {parse_axis(a): str(e) for a, e in d.get("errors", {}).items()}
        imaging = Imaging.from_dict(d["imaging"], cam) if d.get("imaging") else None
        bundle = PlanBundle(int(d["stamp_ns"]), str(d["frame_id"]), str(d["method"]), cam, axes, plans, errors, imaging)
    except KeyError as exc:
        raise PwsError(f"plan message lacks field {exc.args[0]!r}") from None
    for a in bundle.axes:
        require((a in bundle.plans) != (a in bundle.errors), f"plan message must give axis {a} either a plan or an error")
    return bundle


def plan_bundle_message(bundle: PlanBundle, types: Any) -> Any:
    return make(types.String, data=plan_bundle_to_json(bundle))


def parse_plan_bundle_message(msg: Any) -> PlanBundle:
    return plan_bundle_from_json(str(msg.data))


def render_error_message(stamp_ns: int, axis: str, reason: str, types: Any) -> Any:
    return make(types.String, data=json.dumps({"format": RENDER_ERROR_FORMAT, "stamp_ns": int(stamp_ns), "axis": axis,
                                               "reason": " ".join(str(reason).split())}))


def parse_render_error(msg: Any) -> tuple[int, str, str]:
    """``(stamp_ns, axis, reason)`` of a ``rendered/errors`` message."""
    try:
        d = json.loads(str(msg.data))
        require(isinstance(d, dict) and d.get("format") == RENDER_ERROR_FORMAT, f"not a {RENDER_ERROR_FORMAT} message")
        return int(d["stamp_ns"]), parse_axis(d["axis"]), str(d["reason"])
    except (ValueError, KeyError, TypeError) as exc:
        raise PwsError(f"malformed render error message: {exc}") from None


# ---- frames -------------------------------------------------------------------------------

def frame_message(stamp_ns: int, axis: str, index: int, count: int, frame: Any, types: Any) -> Any:
    """A rendered frame ``(H, W, 3)`` as a 32FC3 Image tagged ``S/<axis>/<index>/<count>``."""
    if hasattr(frame, "detach"):
        frame = frame.detach().cpu().numpy()
    frame = np.asarray(frame, dtype=np.float32)
    require(frame.ndim == 3 and frame.shape[2] == 3, f"a rendered frame must be (H, W, 3), got {frame.shape}")
    return image_from_numpy(make_header(types, stamp_ns, frame_tag(stamp_ns, axis, index, count)), frame, types, encoding="32FC3")


def parse_frame_message(msg: Any) -> tuple[FrameTag, np.ndarray]:
    tag = parse_frame_tag(msg.header.frame_id)
    require(header_stamp_ns(msg) == tag.stamp_ns, f"frame {tag} has header stamp {header_stamp_ns(msg)} different from its tag")
    require(str(msg.encoding) == "32FC3", f"rendered frame {tag} has encoding {msg.encoding!r}, expected 32FC3")
    return tag, image_to_numpy(msg)


# ---- bounds -------------------------------------------------------------------------------

@dataclass
class BoundsPayload:
    stamp_ns: int
    axis: str
    count: int
    pair_bound_sq: np.ndarray   # (count - 1,) float64
    seg: np.ndarray             # (E,) int64
    pix: np.ndarray             # (E,) int64
    val: np.ndarray             # (E, 3) float32
    shape: tuple[int, int]


def bounds_message(stamp_ns: int, axis: str, rendered: Any, types: Any) -> Any:
    """The bounds of a :class:`~pws_ros.core.bounds.RenderedPlan` as a Float64MultiArray (see module doc)."""
    pair = np.asarray(rendered.pair_bound_sq, dtype=np.float64).reshape(-1)
    v = rendered.values
    seg = np.asarray(v.seg, dtype=np.int64).reshape(-1)
    pix = np.asarray(v.pix, dtype=np.int64).reshape(-1)
    val = np.asarray(v.val, dtype=np.float32).reshape(-1, 3)
    require(len(seg) == len(pix) == len(val), "segment values have inconsistent lengths")
    count = int(len(rendered.alphas))
    require(len(pair) == count - 1, f"{len(pair)} pair bounds for {count} frames")
    H, W = (int(s) for s in v.shape)
    extra = np.column_stack([seg.astype(np.float64), pix.astype(np.float64), val.astype(np.float64)]) if len(seg) else np.zeros((0, 5))
    data = np.concatenate([pair, extra.reshape(-1), np.array([H, W], dtype=np.float64)])
    dims = [
        make(types.MultiArrayDimension, label=f"{BOUNDS_PREFIX}/{int(stamp_ns)}/{axis}/{count}", size=len(pair), stride=len(pair)),
        make(types.MultiArrayDimension, label="extra", size=len(seg), stride=5 * len(seg)),
        make(types.MultiArrayDimension, label="shape", size=2, stride=2),
    ]
    return make(types.Float64MultiArray, layout=make(types.MultiArrayLayout, dim=dims, data_offset=0), data=types.f64(data))


def parse_bounds_message(msg: Any) -> BoundsPayload:
    dims = list(msg.layout.dim)
    require(len(dims) == 3 and [d.label for d in dims[1:]] == ["extra", "shape"], "bounds message does not follow the pws_bounds layout")
    parts = str(dims[0].label).split("/")
    require(len(parts) == 4 and parts[0] == BOUNDS_PREFIX, f"bounds label {dims[0].label!r} is not '{BOUNDS_PREFIX}/<stamp_ns>/<axis>/<count>'")
    try:
        stamp, count = int(parts[1]), int(parts[3])
    except ValueError:
        raise PwsError(f"bounds label {dims[0].label!r} has a non-integer stamp or count") from None
    axis = parse_axis(parts[2])
    npair, nextra = int(dims[0].size), int(dims[1].size)
    data = np.asarray(msg.data, dtype=np.float64).reshape(-1)
    require(npair == count - 1, f"bounds for {count} frames must hold {count - 1} pair bounds, got {npair}")
    require(len(data) == npair + 5 * nextra + 2, f"bounds message holds {len(data)} numbers, expected {npair + 5 * nextra + 2}")
    pair = data[:npair].copy()
    extra = data[npair: npair + 5 * nextra].reshape(nextra, 5)
    H, W = (int(x) for x in data[-2:])
    return BoundsPayload(stamp, axis, count, pair, extra[:, 0].astype(np.int64), extra[:, 1].astype(np.int64),
                         extra[:, 2:].astype(np.float32), (H, W))


def rendered_plan_from_parts(plan: Any, frames: list[np.ndarray], bounds: BoundsPayload) -> Any:
    """Rebuild a :class:`~pws_ros.core.bounds.RenderedPlan` from what crossed the topics."""
    import torch

    from ..core.bounds import RenderedPlan, SegmentValues

    n = len(plan.alphas)
    require(len(frames) == n, f"{len(frames)} frames for a plan of {n}")
    require(bounds.count == n, f"bounds for {bounds.count} frames, plan has {n}")
    stack = np.stack([np.asarray(f, dtype=np.float32) for f in frames])
    require(stack.shape[1:3] == tuple(bounds.shape), f"frames are {stack.shape[2]}x{stack.shape[1]} but bounds are for {bounds.shape[1]}x{bounds.shape[0]}")
    values = SegmentValues(np.asarray(plan.alphas, dtype=np.float64), bounds.seg, bounds.pix, bounds.val, tuple(bounds.shape))
    return RenderedPlan(plan, torch.from_numpy(stack), bounds.pair_bound_sq, values, 0.0)


def preview_image(frame: Any) -> np.ndarray:
    """A float frame in [0, 1] as uint8 RGB for ``rendered/preview``."""
    if hasattr(frame, "detach"):
        frame = frame.detach().cpu().numpy()
    return np.clip(np.rint(np.asarray(frame, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


__all__ = ["BOUNDS_PREFIX", "BoundsPayload", "FrameTag", "PLAN_FORMAT", "PlanBundle", "bounds_message", "frame_message",
           "frame_tag", "parse_bounds_message", "parse_frame_message", "parse_frame_tag", "parse_plan_bundle_message",
           "plan_bundle_from_json", "plan_bundle_message", "plan_bundle_to_json", "preview_image", "parse_render_error",
           "render_error_message", "rendered_plan_from_parts", "RENDER_ERROR_FORMAT"]

"""The wire scheme of the four-process mode (common_interfaces types only).

Per input frame (source stamp ``S`` in ns, source optical frame ``F``):

``plan/cloud`` — ``sensor_msgs/PointCloud2``, header ``(S, F)``: the one-frame cloud that was planned,
    handed on by the planner just before its ``plan`` (the projector renders from it; the camera
    outruns planning, so it must not be looked up among the newer clouds on ``cloud``).
``plan`` — ``std_msgs/String`` (JSON, :func:`plan_bundle_to_json`)
    ``{"format": "pws_ros/plan-bundle/1", "stamp_ns": S, "frame_id": F, "method": ..., "axes": [...],
    "camera": {...render intrinsics...}, "plans": {axis: Plan.to_dict()}, "errors": {axis: reason},
    "imaging": {...}, "filled_points": K}`` (K: points of the cloud with filled depth, 0 when absent).
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
``cloud/errors`` — ``std_msgs/String`` JSON ``{"format": "pws_ros/input-error/1", "stamp_ns": S, "frame_id": F,
    "reason": "..."}`` when ``cloud_listener`` could not make a cloud of an input frame (bad input): the
    planner answers it with a plan that gives every axis that reason, so the certifier publishes the
    frame's ERROR certification, as the pipeline node does for bad input.

A plan whose axes are all errors may carry ``"camera": null`` (the input had no valid camera).

One module on purpose (about 480 lines): it is the wire protocol of the four processes, one section per
topic above, each message's writer beside its parser and both on the same validators (stamps, counts,
frame tags, sizes); split, a writer and the parser that must accept exactly what it writes would drift.
"""
from __future__ import annotations

import json
import math
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
INPUT_ERROR_FORMAT = "pws_ros/input-error/1"
BOUNDS_PREFIX = "pws_bounds"

# Any process on a ROS graph can publish on these topics: every parser below checks sizes, counts and
# indices against the message's own data and the caller's limits before it builds an array, and
# raises PwsError (one line) for anything malformed; nothing else escapes.
MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999   # builtin_interfaces/Time: int32 sec
MIN_STAMP_NS = -(2**31) * 1_000_000_000
MAX_FRAME_SIDE = 1 << 15                                     # a rendered frame side (px): far above any model input
_SHOWN = 60                                                  # characters of a bad value quoted in a message


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= _SHOWN else text[:_SHOWN] + "..."


def _int_value(value: Any, what: str) -> int:
    """``value`` as an int: a JSON integer or an integer-valued text (not a bool, float or anything else)."""
    if isinstance(value, bool):
        raise PwsError(f"{what} must be an integer, got {_shown(value)}")
    if isinstance(value, int):
        return value
    if isinstance(value, str) and len(value) <= 24:
        try:
            return int(value)
        except ValueError:
            pass
    raise PwsError(f"{what} must be an integer, got {_shown(value)}")


def check_stamp(stamp_ns: int, what: str) -> int:
    """A stamp in the range of ``builtin_interfaces/Time`` (negative stamps are valid ROS times)."""
    require(MIN_STAMP_NS <= stamp_ns <= MAX_STAMP_NS, f"{what}: stamp {stamp_ns} ns is outside the range of a ROS time")
    return int(stamp_ns)


def check_count(count: int, what: str, max_count: int | None) -> int:
    """A partition count: >= 1 and, with ``max_count`` (the receiver's ``max_partitions``), at most that."""
    require(count >= 1, f"{what}: count must be >= 1, got {count}")
    require(max_count is None or count <= int(max_count),
            f"{what}: {count} frames, more than max_partitions {max_count} (a plan never has more)")
    return int(count)


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


def parse_frame_tag(text: str, max_count: int | None = None) -> FrameTag:
    """The tag of a rendered frame; PwsError when malformed, when ``index`` is outside ``[0, count)`` or
    when ``count`` exceeds ``max_count`` (the receiver's ``max_partitions``)."""
    text = str(text)
    parts = text.split("/")
    require(len(parts) == 4 and len(text) <= 80, f"frame tag {_shown(text)} is not '<stamp_ns>/<axis>/<index>/<count>'")
    try:
        stamp, index, count = int(parts[0]), int(parts[2]), int(parts[3])
    except ValueError:
        raise PwsError(f"frame tag {text!r} has a non-integer stamp, index or count") from None
    check_stamp(stamp, f"frame tag {text!r}")
    check_count(count, f"frame tag {text!r}", max_count)
    require(0 <= index < count, f"frame tag {text!r}: index {index} is outside [0, {count})")
    return FrameTag(stamp, parse_axis(parts[1]), index, count)


def tag_owner(text: Any) -> tuple[int, str] | None:
    """``(stamp_ns, axis)`` a frame tag or bounds label names, if it names them validly (None
    otherwise), even when the rest of it is malformed: a malformed message that names its input frame
    makes that frame's axis an ERROR instead of vanishing."""
    parts = str(text).split("/")
    if len(parts) != 4 or len(str(text)) > 80:
        return None
    if parts[0] == BOUNDS_PREFIX:
        parts = parts[1:] + [""]
    try:
        return check_stamp(int(parts[0]), "tag"), parse_axis(parts[1])
    except (PwsError, ValueError):
        return None


# ---- plan bundle --------------------------------------------------------------------------

@dataclass
class PlanBundle:
    """Every axis' plan (or planning error) for one input frame, and the camera they render with."""

    stamp_ns: int
    frame_id: str
    method: str
    camera: CameraIntrinsics | None                        # None only when every axis is an error
    axes: list[str]
    plans: dict[str, Any] = field(default_factory=dict)    # axis -> core.partition.Plan
    errors: dict[str, str] = field(default_factory=dict)   # axis -> reason
    imaging: Any = None                                    # core.imaging.Imaging (None: paper imaging at ``camera``)
    filled_points: int = 0                                 # points of the planned cloud with filled depth (the certificates say it)

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
        "camera": _camera_dict(bundle.camera) if bundle.camera is not None else None,
        "plans": {a: jsonable(p.to_dict(), inf="string") for a, p in bundle.plans.items()},
        "errors": dict(bundle.errors),
        "imaging": bundle.imaging.to_dict() if bundle.imaging is not None else None,
        "filled_points": int(bundle.filled_points),
    }, allow_nan=False)


def _plan_dict(text: Any) -> dict[str, Any]:
    try:
        d = json.loads(text)
    except (TypeError, ValueError, RecursionError) as exc:
        raise PwsError(f"plan message is not JSON: {' '.join(str(exc).split())[:120]}") from None
    require(isinstance(d, dict) and d.get("format") == PLAN_FORMAT, f"plan message is not a {PLAN_FORMAT} bundle")
    return d


def plan_bundle_stamp(text: Any) -> int | None:
    """The stamp a plan message names, when it names a valid one (None otherwise): a malformed plan of
    a known stamp is answered with an ERROR certification of that frame."""
    try:
        return check_stamp(_int_value(_plan_dict(text).get("stamp_ns"), "plan stamp_ns"), "plan message")
    except PwsError:
        return None


def plan_bundle_from_json(text: str, max_count: int | None = None) -> PlanBundle:
    """The :class:`PlanBundle` of a ``plan`` message; PwsError naming what is malformed (any field of
    the wrong type, an unknown or repeated axis, a plan of more than ``max_count`` frames ...)."""
    from ..core.imaging import Imaging
    from ..core.partition import Plan

    d = _plan_dict(text)
    try:
        stamp = check_stamp(_int_value(d["stamp_ns"], "plan stamp_ns"), "plan message")
        for key in ("frame_id", "method"):
            require(isinstance(d[key], str), f"plan {key} must be a string, got {_shown(d[key])}")
        raw_axes = d["axes"]
        require(isinstance(raw_axes, list) and 1 <= len(raw_axes) <= 6 and all(isinstance(a, str) for a in raw_axes),
                f"plan axes must be a list of 1 to 6 axis names, got {_shown(raw_axes)}")
        axes = [parse_axis(a) for a in raw_axes]
        require(len(set(axes)) == len(axes), f"plan lists an axis twice: {axes}")
        raw_cam = d["camera"]
        raw_plans, raw_errors = d.get("plans", {}), d.get("errors", {})
        require(isinstance(raw_plans, dict) and isinstance(raw_errors, dict), "plan plans and errors must be mappings")
        cam = None
        if raw_cam is not None or raw_plans:
            require(isinstance(raw_cam, dict), f"plan camera must be a mapping, got {_shown(raw_cam)}")
            cam = CameraIntrinsics.from_dict(raw_cam, source="plan camera")
            frame = raw_cam.get("frame_id", "")
            require(isinstance(frame, str), f"plan camera frame_id must be a string, got {_shown(frame)}")
            cam = CameraIntrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, frame)
        plans: dict[str, Any] = {}
        for a, p in raw_plans.items():
            a = parse_axis(a)
            require(isinstance(p, dict), f"plan for axis {a} must be a mapping")
            n = p.get("alphas")
            require(isinstance(n, list), f"plan for axis {a} has no list of alphas")
            check_count(len(n), f"plan for axis {a}", max_count)
            plans[a] = Plan.from_dict(p)
            require(plans[a].axis == a, f"plan listed under axis {a} is for axis {plans[a].axis}")
        errors = {parse_axis(a): " ".join(str(e).split())[:500] for a, e in raw_errors.items()}
        raw_im = d.get("imaging")
        require(raw_im is None or isinstance(raw_im, dict), f"plan imaging must be a mapping or null, got {_shown(raw_im)}")
        imaging = Imaging.from_dict(raw_im, cam) if raw_im and cam is not None else None
        filled = d.get("filled_points", 0)
        require(isinstance(filled, int) and not isinstance(filled, bool) and 0 <= filled < 2**63,
                f"plan filled_points must be a non-negative integer, got {_shown(filled)}")
        bundle = PlanBundle(stamp, d["frame_id"], d["method"], cam, axes, plans, errors, imaging, filled)
    except KeyError as exc:
        raise PwsError(f"plan message lacks field {exc.args[0]!r}") from None
    except PwsError:
        raise
    except Exception as exc:  # any other malformed value (a wrong type deep inside a plan or the imaging)
        raise PwsError(f"malformed plan message ({type(exc).__name__}: {' '.join(str(exc).split())[:120]})") from None
    for a in bundle.axes:
        require((a in bundle.plans) != (a in bundle.errors), f"plan message must give axis {a} either a plan or an error")
    extra = sorted((set(bundle.plans) | set(bundle.errors)) - set(bundle.axes))
    require(not extra, f"plan message has plans or errors for axes it does not list: {', '.join(extra)}")
    return bundle


def plan_bundle_message(bundle: PlanBundle, types: Any) -> Any:
    return make(types.String, data=plan_bundle_to_json(bundle))


def parse_plan_bundle_message(msg: Any, max_count: int | None = None) -> PlanBundle:
    return plan_bundle_from_json(_text_of(msg), max_count)


def _text_of(msg: Any) -> str:
    data = getattr(msg, "data", None)
    require(isinstance(data, str), f"a std_msgs/String was expected, its data is {type(data).__name__}")
    return data


def render_error_message(stamp_ns: int, axis: str, reason: str, types: Any) -> Any:
    return make(types.String, data=json.dumps({"format": RENDER_ERROR_FORMAT, "stamp_ns": int(stamp_ns), "axis": axis,
                                               "reason": " ".join(str(reason).split())}))


def parse_render_error(msg: Any) -> tuple[int, str, str]:
    """``(stamp_ns, axis, reason)`` of a ``rendered/errors`` message."""
    try:
        d = json.loads(_text_of(msg))
        require(isinstance(d, dict) and d.get("format") == RENDER_ERROR_FORMAT, f"not a {RENDER_ERROR_FORMAT} message")
        stamp = check_stamp(_int_value(d["stamp_ns"], "stamp_ns"), "render error")
        require(isinstance(d["axis"], str), f"axis must be a string, got {_shown(d['axis'])}")
        return stamp, parse_axis(d["axis"]), " ".join(str(d["reason"]).split())[:500]
    except PwsError as exc:
        raise PwsError(f"malformed render error message: {exc}") from None
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise PwsError(f"malformed render error message: {type(exc).__name__}: {' '.join(str(exc).split())[:120]}") from None


def input_error_message(stamp_ns: int, frame_id: str, reason: str, types: Any) -> Any:
    """``cloud/errors``: ``cloud_listener`` could not make a cloud of input frame ``stamp_ns``."""
    return make(types.String, data=json.dumps({"format": INPUT_ERROR_FORMAT, "stamp_ns": int(stamp_ns), "frame_id": str(frame_id),
                                               "reason": " ".join(str(reason).split())[:500]}))


def parse_input_error(msg: Any) -> tuple[int, str, str]:
    """``(stamp_ns, frame_id, reason)`` of a ``cloud/errors`` message."""
    try:
        d = json.loads(_text_of(msg))
        require(isinstance(d, dict) and d.get("format") == INPUT_ERROR_FORMAT, f"not a {INPUT_ERROR_FORMAT} message")
        stamp = check_stamp(_int_value(d["stamp_ns"], "stamp_ns"), "input error")
        require(isinstance(d.get("frame_id", ""), str), "frame_id must be a string")
        return stamp, d.get("frame_id", ""), " ".join(str(d["reason"]).split())[:500]
    except PwsError as exc:
        raise PwsError(f"malformed input error message: {exc}") from None
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise PwsError(f"malformed input error message: {type(exc).__name__}: {' '.join(str(exc).split())[:120]}") from None


# ---- frames -------------------------------------------------------------------------------

def frame_message(stamp_ns: int, axis: str, index: int, count: int, frame: Any, types: Any) -> Any:
    """A rendered frame ``(H, W, 3)`` as a 32FC3 Image tagged ``S/<axis>/<index>/<count>``."""
    if hasattr(frame, "detach"):
        frame = frame.detach().cpu().numpy()
    frame = np.asarray(frame, dtype=np.float32)
    require(frame.ndim == 3 and frame.shape[2] == 3, f"a rendered frame must be (H, W, 3), got {frame.shape}")
    return image_from_numpy(make_header(types, stamp_ns, frame_tag(stamp_ns, axis, index, count)), frame, types, encoding="32FC3")


def parse_frame_message(msg: Any, max_count: int | None = None) -> tuple[FrameTag, np.ndarray]:
    """``(tag, frame)`` of a ``rendered/frames`` Image (PwsError when malformed; check the tag first with
    :func:`frame_message_tag` to tie a malformed frame to its input frame)."""
    tag = frame_message_tag(msg, max_count)
    return tag, frame_message_array(msg, tag)


def frame_message_tag(msg: Any, max_count: int | None = None) -> FrameTag:
    """The tag of a ``rendered/frames`` Image, checked against its header stamp."""
    tag = parse_frame_tag(msg.header.frame_id, max_count)
    require(header_stamp_ns(msg) == tag.stamp_ns, f"frame {tag} has header stamp {header_stamp_ns(msg)} different from its tag")
    return tag


def frame_message_array(msg: Any, tag: Any, shape: tuple[int, int] | None = None, max_bytes: int | None = None) -> np.ndarray:
    """The ``(H, W, 3)`` float32 frame of a ``rendered/frames`` Image: its size checked against ``shape``
    (the plan's, when known) and ``max_bytes`` before it is decoded, its values finite."""
    require(str(msg.encoding) == "32FC3", f"rendered frame {tag} has encoding {_shown(str(msg.encoding))}, expected 32FC3")
    try:
        w, h = int(msg.width), int(msg.height)
    except (TypeError, ValueError, OverflowError):
        raise PwsError(f"rendered frame {tag} has a malformed size") from None
    require(0 < w <= MAX_FRAME_SIDE and 0 < h <= MAX_FRAME_SIDE, f"rendered frame {tag} is {w}x{h}: not a frame size")
    if shape is not None:
        require((h, w) == tuple(shape), f"rendered frame {tag} is {w}x{h} but the plan renders {shape[1]}x{shape[0]}")
    if max_bytes is not None:
        require(12 * w * h <= max_bytes, f"rendered frame {tag} ({w}x{h}) needs {12 * w * h / 2**20:.1f} MiB, above the "
                                         f"memory ceiling of {max_bytes / 2**20:.0f} MiB")
    frame = image_to_numpy(msg)
    require(bool(np.isfinite(frame).all()), f"rendered frame {tag} holds NaN or inf values")
    return frame


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


def bounds_label(msg: Any, max_count: int | None = None) -> tuple[int, str, int]:
    """``(stamp_ns, axis, count)`` of a ``rendered/bounds`` message (its first dimension's label): what
    ties a malformed payload to its input frame and axis."""
    try:
        dims = list(msg.layout.dim)
        label = str(dims[0].label) if dims else ""
    except (AttributeError, TypeError):
        raise PwsError("bounds message has no layout") from None
    parts = label.split("/")
    require(len(parts) == 4 and parts[0] == BOUNDS_PREFIX and len(label) <= 80,
            f"bounds label {_shown(label)} is not '{BOUNDS_PREFIX}/<stamp_ns>/<axis>/<count>'")
    try:
        stamp, count = int(parts[1]), int(parts[3])
    except ValueError:
        raise PwsError(f"bounds label {label!r} has a non-integer stamp or count") from None
    check_stamp(stamp, f"bounds label {label!r}")
    check_count(count, f"bounds label {label!r}", max_count)
    return stamp, parse_axis(parts[2]), count


def parse_bounds_message(msg: Any, max_count: int | None = None, max_bytes: int | None = None,
                         shape: tuple[int, int] | None = None) -> BoundsPayload:
    """The payload of a ``rendered/bounds`` message. Every size is checked against the message's own
    data (and ``max_bytes``, the receiver's memory ceiling) before an array is built; the shape
    ``(H, W)`` must be positive integers (the plan's ``shape`` when given), every extra value's segment
    and pixel index within range, every number finite (pair bounds >= 0)."""
    stamp, axis, count = bounds_label(msg, max_count)
    where = f"bounds of {stamp}/{axis}"
    dims = list(msg.layout.dim)
    require(len(dims) == 3 and [str(d.label) for d in dims[1:]] == ["extra", "shape"], f"{where} do not follow the pws_bounds layout")
    try:
        npair, nextra, nshape = int(dims[0].size), int(dims[1].size), int(dims[2].size)
        ndata = len(msg.data)
    except (TypeError, ValueError, OverflowError):
        raise PwsError(f"{where}: malformed layout sizes") from None
    require(npair == count - 1, f"{where}: {count} frames must have {count - 1} pair bounds, got {npair}")
    require(0 <= nextra and nshape == 2, f"{where}: malformed layout sizes (extra {nextra}, shape {nshape})")
    require(ndata == npair + 5 * nextra + 2, f"{where}: the message holds {ndata} numbers, expected {npair + 5 * nextra + 2}")
    if max_bytes is not None:
        need = 8 * ndata + 36 * nextra
        require(need <= max_bytes, f"{where} need {need / 2**20:.1f} MiB, above the memory ceiling of {max_bytes / 2**20:.0f} MiB")
    try:
        data = np.asarray(msg.data, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise PwsError(f"{where}: data is not a sequence of numbers") from None
    require(len(data) == ndata, f"{where}: malformed data")
    h, w = (float(x) for x in data[-2:])
    require(all(math.isfinite(v) and v == int(v) and 1 <= v <= MAX_FRAME_SIDE for v in (h, w)),
            f"{where}: frame shape {h!r} x {w!r} is not two positive integers")
    H, W = int(h), int(w)
    if shape is not None:
        require((H, W) == tuple(shape), f"{where} are for {W}x{H} frames but the plan renders {shape[1]}x{shape[0]}")
    pair = data[:npair].copy()
    require(bool(np.all(np.isfinite(pair) & (pair >= 0))), f"{where}: a pair bound is negative, NaN or inf")
    extra = data[npair: npair + 5 * nextra].reshape(nextra, 5)
    require(bool(np.isfinite(extra).all()), f"{where}: an extra value is NaN or inf")
    seg, pix = extra[:, 0], extra[:, 1]
    require(bool(np.all((seg == np.floor(seg)) & (seg >= 0) & (seg < max(0, count - 1)))),
            f"{where}: a segment index is not an integer in [0, {count - 1})")
    require(bool(np.all((pix == np.floor(pix)) & (pix >= 0) & (pix < H * W))), f"{where}: a pixel index is not an integer in [0, {H * W})")
    return BoundsPayload(stamp, axis, count, pair, seg.astype(np.int64), pix.astype(np.int64), extra[:, 2:].astype(np.float32), (H, W))


def rendered_plan_from_parts(plan: Any, frames: list[np.ndarray], bounds: BoundsPayload) -> Any:
    """Rebuild a :class:`~pws_ros.core.bounds.RenderedPlan` from what crossed the topics."""
    import torch

    from ..core.bounds import RenderedPlan, SegmentValues

    n = len(plan.alphas)
    require(len(frames) == n, f"{len(frames)} frames for a plan of {n}")
    require(bounds.count == n, f"bounds for {bounds.count} frames, plan has {n}")
    shapes = {np.shape(f) for f in frames}
    require(len(shapes) == 1 and len(next(iter(shapes))) == 3 and next(iter(shapes))[2] == 3,
            f"the rendered frames differ in shape: {sorted(shapes)[:3]}")
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
           "frame_tag", "bounds_label", "check_count", "check_stamp", "frame_message_array", "frame_message_tag",
           "parse_bounds_message", "plan_bundle_stamp", "tag_owner", "INPUT_ERROR_FORMAT", "input_error_message", "parse_input_error", "parse_frame_message", "parse_frame_tag", "parse_plan_bundle_message",
           "plan_bundle_from_json", "plan_bundle_message", "plan_bundle_to_json", "preview_image", "parse_render_error",
           "render_error_message", "rendered_plan_from_parts", "RENDER_ERROR_FORMAT"]

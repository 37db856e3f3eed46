"""The parameter table of the node suite: ONE table (:data:`PARAMS`) with names, defaults,
descriptions, ranges or choices, the read-only flag and the nodes that read each parameter, and the
validation of a value against it (:func:`validate_param`).

The nodes declare their ROS parameters from :data:`PARAMS` (description, FloatingPointRange /
IntegerRange, read-only flag) and validate every change with :func:`validate_param`; the validated
values live in :class:`pws_ros.bridge.config.PwsConfig` (built from this table), and ``docs/ros2.md``
and ``config/pws.yaml`` are generated from it (:mod:`pws_ros.bridge.paramdoc`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

from ..core.errors import PwsError, require
from ..core.motion import AXES, PAPER_RADIUS, UNITS

from ..core.certify import COVERAGES, METHODS  # the certification core owns these lists
from ..core.imaging import DEFAULT_RENDER_FACTOR, IMAGING_KINDS, UNCOVERED
from ..core.partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX
from ..core.sequential import FIRST_LOOK

INPUT_MODES = ("auto", "pointcloud2", "rgbd")
QOS_PROFILES = ("sensor_data", "reliable", "best_effort", "system_default")
INFO_SYNC = ("latest", "stamp")
DEMO_MODEL = "bags/models/classifier_sigma0.50.pt"
NODES = ("cloud_listener", "partition_planner", "projector", "certifier", "pipeline")
_ALL = NODES
_PLAN = ("partition_planner", "projector", "certifier", "pipeline")
_CERT = ("certifier", "pipeline")
_ANCHOR = ("partition_planner", "certifier", "pipeline")   # also the planner: it refines the grid for the anchors
_IN = ("cloud_listener", "pipeline")


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: ``name`` (dotted), ``default`` (its type is the parameter's type),
    ``description``, numeric ``range`` (lo, hi) inclusive or ``choices``, ``read_only`` (fixed after
    start: changing it would need reloading a model or re-subscribing), ``nodes`` that use it."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False
    nodes: tuple[str, ...] = _ALL
    unit: str = ""

    @property
    def kind(self) -> str:
        d = self.default
        if isinstance(d, bool):
            return "bool"
        if isinstance(d, int):
            return "int"
        if isinstance(d, float):
            return "float"
        if isinstance(d, str):
            return "str"
        if isinstance(d, (list, tuple)):
            return "str_list" if all(isinstance(v, str) for v in d) else ("int_list" if all(isinstance(v, int) and not isinstance(v, bool) for v in d) else "float_list")
        raise TypeError(f"unsupported default for {self.name}: {d!r}")  # pragma: no cover

    @property
    def attr(self) -> str:
        """The :class:`PwsConfig` attribute name (dots become underscores)."""
        return self.name.replace(".", "_")


def _radius_spec(axis: str) -> ParamSpec:
    hi = 1.0 if UNITS[axis] == "m" else math.pi / 2
    return ParamSpec(f"radius.{axis}", float(PAPER_RADIUS[axis]),
                     f"requested certification radius b for axis {axis} ({UNITS[axis]}); the interval is [-b, b]",
                     range=(1e-9, hi), nodes=_PLAN, unit=UNITS[axis])


PARAMS: tuple[ParamSpec, ...] = (
    # -- what to certify --
    ParamSpec("axes", ["tz", "ry"], "motion axes to certify for each frame (any of tx, ty, tz, rx, ry, rz), one DiagnosticStatus each",
              choices=AXES, nodes=_PLAN),
    *(_radius_spec(a) for a in AXES),
    ParamSpec("method", "pws_of", "partitioning method: pws (needs dense_cloud_path), pws_l, pws_of (one-frame cloud), or the cms baseline",
              choices=METHODS, nodes=_PLAN),
    ParamSpec("imaging", "surfel", "imaging model: surfel (each point is the patch its depth pixel saw, rendered at the camera's "
              "resolution on a centred crop and block-averaged to the model's input; no sampling holes) or paper (one point "
              "paints one pixel at the model's size, the paper's model)", choices=IMAGING_KINDS, nodes=_PLAN),
    ParamSpec("border", -1, "surfel imaging: output pixels masked (set to background) along the left/right and top/bottom "
              "edges in every frame and in the classifier's input; -1 = computed from the radii (what can enter from "
              "beyond the recorded image)", range=(-1, 4096), nodes=_PLAN, unit="px"),
    ParamSpec("render_factor", DEFAULT_RENDER_FACTOR, "surfel imaging: frames are rendered at this many times the model's "
              "input size, then block-averaged to it; below the camera's resolution its pixels are binned into one surfel "
              "per rendered pixel (2: a 640x480 camera and a 160x90 model render at 320x180, about 4x faster than "
              "0 = the camera's full resolution, with about the same radii)", range=(0, 64), nodes=_PLAN),
    ParamSpec("step_px", float(DEFAULT_STEP_PX), "surfel imaging: the plan's step moves no point more than this many rendered "
              "pixels (finer = tighter bounds, more frames)", range=(1e-3, 100.0), nodes=_PLAN, unit="px"),
    ParamSpec("coverage", "anchors", "coverage rule: anchors (p_A at a few anchor frames only; with surfel imaging they are "
              "placed from the distance bounds, at most num_anchors, on a grid refined for them: by the planner node in the four-process "
              "mode), pairwise (p_A at every partition, per segment), paper "
              "(max M < min R); ignored by cms",
              choices=COVERAGES, nodes=_ANCHOR),
    ParamSpec("delta", 0.0, "PwS-OF delta-convexity constant in pixels; 0 = the core's default", range=(0.0, 100.0), nodes=_PLAN, unit="px"),
    ParamSpec("max_partitions", DEFAULT_FRAME_BUDGET, "most partitions (frames) per axis: a plan needing more is made coarser (fewer frames, "
              "looser bounds, maybe a smaller certified radius), never refused", range=(3, 1_000_000), nodes=_PLAN),
    ParamSpec("max_memory_mb", 2048.0, "memory ceiling of one axis' certificate: the per-segment bounds and frames "
              "take at most half of it (the adaptive grid stays coarser to fit; a larger plan is an ERROR), the "
              "renderer streams within the rest", range=(64.0, 1e7), nodes=_PLAN, unit="MiB"),
    ParamSpec("min_partitions", 0, "refine each plan to at least this many partitions (still sound; tightens the bounds where the method "
              "plans only a few frames, e.g. sub-pixel motions); 0 = as planned", range=(0, 1_000_000), nodes=_PLAN),
    ParamSpec("dense_cloud_path", "", "prior dense cloud (.npz with points, colors in the camera optical frame) for method pws; empty otherwise",
              read_only=True, nodes=_PLAN),
    ParamSpec("background", -1.0, "pixel value of the masked border, and where no point is drawn (paper imaging; surfel "
              "imaging with uncovered: background; outside the working volume); -1 = automatic: 0.5 (mid-grey) with a "
              "working volume, else 0", range=(-1.0, 1.0), nodes=_PLAN),
    ParamSpec("uncovered", "frame", "surfel imaging: what a pixel that no surfel covers shows (a disocclusion, what the "
              "recording never saw): frame = the colour the alpha = 0 frame has at that pixel, fixed for the whole motion "
              "(the least spurious contrast; background where nothing covers it at alpha = 0 either); background = the "
              "background value", choices=UNCOVERED, nodes=_PLAN),
    ParamSpec("working_volume.far", 0.0, "surfel imaging: the far face of the working volume, the part of the one-frame cloud "
              "that is drawn (the robot's working range: a hand, an object in reach, not the room behind): only points with "
              "near <= z <= far (and inside the x/y limits that are set) at alpha = 0 are drawn, moving with the camera as "
              "usual; pixels no drawn point covers show their uncovered value (background outside the volume); a frame with "
              "no measured point inside is an ERROR; 0 = no working volume (every point is drawn)", range=(0.0, 1e6),
              nodes=_PLAN, unit="m"),
    ParamSpec("working_volume.near", 0.0, "surfel imaging: the near face of the working volume (points nearer than this, "
              "along the optical axis z, are not drawn)", range=(0.0, 1e6), nodes=_PLAN, unit="m"),
    *(ParamSpec(f"working_volume.{axis}_{end}", 0.0, f"surfel imaging: the working volume's {end}imum {axis} (camera optical "
                f"frame: x right, y down); {axis}_min = {axis}_max = 0: no limit along {axis}", range=(-1e6, 1e6), nodes=_PLAN,
                unit="m") for axis in ("x", "y") for end in ("min", "max")),
    ParamSpec("working_volume.window", 0.0, "surfel imaging, with a working volume: > 0 = per frame only its nearest "
              "`window` metres behind its subject (the largest depth-connected cluster of the volume's points that does "
              "not span the view from edge to opposite edge: e.g. a hand and arm, not a wall or floor; docs/imaging.md 4b) "
              "are drawn, in a camera window around the subject (the smallest crop of the input's aspect, at most the "
              "whole frame's, that holds it, widened by 15%): chosen once at alpha = 0 from the depth; 0 = the whole "
              "volume, centred crop", range=(0.0, 1e6), nodes=_PLAN, unit="m"),
    ParamSpec("render_width", 0, "paper imaging: rendered frame width; 0 = the model's declared input size (else the camera's)", range=(0, 8192), read_only=True, nodes=_PLAN, unit="px"),
    ParamSpec("render_height", 0, "paper imaging: rendered frame height; 0 = the model's declared input size (else the camera's)", range=(0, 8192), read_only=True, nodes=_PLAN, unit="px"),
    # -- smoothing and statistics --
    ParamSpec("model_path", DEMO_MODEL, "TorchScript classifier (relative paths: current directory, then the package share directory)",
              read_only=True, nodes=_PLAN),
    ParamSpec("classes_path", "", "class-names file (one per line); empty = beside the model or in its metadata", read_only=True, nodes=_CERT),
    ParamSpec("denoiser_path", "", "optional TorchScript denoiser applied to noisy images before the classifier", read_only=True, nodes=_CERT),
    ParamSpec("device", "cpu", "torch device: cpu or cuda:N (falls back to cpu with a WARN when CUDA is missing)", read_only=True, nodes=_PLAN),
    ParamSpec("sigma", 0.5, "pixel noise standard deviation of the smoothed classifier (images in [0, 1])", range=(1e-6, 10.0), nodes=_ANCHOR),
    ParamSpec("n0", 64, "noise samples to select the top class (at the original pose)", range=(1, 10_000_000), nodes=_ANCHOR),
    ParamSpec("n", 256, "noise samples per bound to estimate p_A", range=(1, 100_000_000), nodes=_ANCHOR),
    ParamSpec("alpha", 0.01, "risk of a frame's certificate: the probability that any statement about the frame (all its axes "
              "together) is wrong; split evenly over the axes, then over every bound each uses (Bonferroni)", range=(1e-12, 0.5), nodes=_ANCHOR),
    ParamSpec("seed", 0, "random seed; each frame and axis draws from its own stream derived from (seed, stamp, axis): "
              "deterministic for equal inputs, independent across frames and axes", range=(0, 2**31 - 1), nodes=_CERT),
    ParamSpec("batch_size", 256, "images per classifier call, the most (the certificates do not depend on it; on a CPU a "
              "large model is often faster per image in small calls: the certifier times 4 against it once at start and "
              "uses 4 when that is at least 1.25x as fast)",
              range=(1, 1_000_000), nodes=_CERT),
    ParamSpec("n_first", FIRST_LOOK, "noise samples of the anchors' joint first look (coverage=anchors with surfel imaging; "
              "docs/certificate.md): where the selection samples are (nearly) unanimous, the anchors share n_first noise "
              "draws and one bound on the rate at which all of them keep the label bounds each (no division of alpha by "
              "the anchors), so they are placed for what n_first samples certify, up to num_anchors * n / n_first of them; "
              "an anchor left short of the radius it was placed for gets the rest of its n samples (its own bound); 90% of "
              "the risk goes to the first look, the rest to the second. 0: n samples each at alpha / K",
              range=(0, 100_000_000), nodes=_ANCHOR),
    ParamSpec("num_anchors", 24, "anchor frames for coverage=anchors (surfel imaging: the estimation budget in anchors of n "
              "samples, i.e. at most n0 + num_anchors * n classifier calls per axis; with the joint first look up to "
              "num_anchors * n / n_first anchors are placed; a frame needing more gets a smaller radius)", range=(1, 100_000), nodes=_ANCHOR),
    ParamSpec("time_budget_s", 0.0, "time budget per frame, split evenly over its axes (what an axis leaves unused goes to the axes after it): the certifier measures what a "
              "classifier call and the geometry cost on this machine (a warm-up, then every axis) and sizes n0, num_anchors, n and "
              "max_partitions of each axis (never above the configured ones) before it draws any sample, so that the axis "
              "finishes within its share; a frame that needs more gets a smaller radius, never more time; where even the least "
              "work does not fit, the geometry is coarsened (render factor 1, fewer frontier rounds) and the axis still answers, "
              "flagged over budget with the time it took; start-up work is not charged to a frame; 0 = off (the configured sizes)", range=(0.0, 86400.0), nodes=("pipeline",), unit="s"),
    ParamSpec("axis_threads", 0, "axes of a frame certified at the same time, each in a thread of its own (the pipeline: "
              "a frame's latency; each axis keeps its own renderer and noise seed, so the certificates are the same as one "
              "after another, and memory is up to this many times max_memory_mb); 0 = automatic: one per axis, at most "
              "torch's intra-op threads (the cores, or fewer per worker with several workers), one with a time budget "
              "(its axes share the frame's time in turn); 1 = one after another", range=(0, 64), nodes=("pipeline",)),
    ParamSpec("audit_every", 0, "self-audit every k-th frame: re-render poses inside every segment of each certified axis "
              "(audit_poses per segment) and check every bound the certificate used; a violation turns that axis to "
              "ERROR; 0 = off (the pipeline node: the four-process certifier has no cloud to re-render)", range=(0, 1_000_000),
              nodes=("pipeline",)),
    ParamSpec("audit_poses", 8, "poses re-rendered per segment by the self-audit (ends and their float neighbours included)",
              range=(2, 100_000), nodes=("pipeline",)),
    ParamSpec("cms_sigma", 0.0, "motion-space sigma of the cms baseline; 0 = the per-axis default", range=(0.0, 10.0), nodes=_CERT),
    # -- inputs --
    ParamSpec("input_mode", "auto", "input: pointcloud2, rgbd (depth + colour + CameraInfo), or auto (the first that arrives)",
              choices=INPUT_MODES, read_only=True, nodes=_IN),
    ParamSpec("points_topic", "/camera/depth/color/points", "sensor_msgs/PointCloud2 input (organized or not; xyz + optional packed rgb)", read_only=True, nodes=_IN),
    ParamSpec("depth_topic", "/camera/aligned_depth_to_color/image_raw", "depth Image registered to the colour camera (16UC1 mm or 32FC1 m)", read_only=True, nodes=_IN),
    ParamSpec("color_topic", "/camera/color/image_raw", "colour Image (rgb8, bgr8, rgba8, bgra8, mono8)", read_only=True, nodes=_IN),
    ParamSpec("camera_info_topic", "/camera/color/camera_info", "CameraInfo of the colour camera (also used with an organized or unorganized PointCloud2)",
              read_only=True, nodes=_IN),
    ParamSpec("depth_camera_info_topic", "auto", "CameraInfo of the depth stream: depth whose intrinsics differ from the colour camera's "
              "is refused (not registered); auto = the camera_info beside depth_topic (e.g. /camera/aligned_depth_to_color/camera_info), "
              "empty = no such check", read_only=True, nodes=_IN),
    ParamSpec("camera_info_file", "", "camera_calibration YAML used when no CameraInfo arrives (unorganized clouds)", read_only=True, nodes=_IN),
    ParamSpec("camera_info_sync", "latest", "CameraInfo pairing: latest (last one received) or stamp (matched like the images)",
              choices=INFO_SYNC, read_only=True, nodes=_IN),
    ParamSpec("sync_tolerance_s", 0.02, "depth, colour (and CameraInfo) whose stamps differ by at most this are one frame, matched immediately",
              range=(0.0, 10.0), nodes=_IN, unit="s"),
    ParamSpec("sync_max_skew_s", 0.2, "unsynchronised drivers (depth and colour at their own rates): a pair farther apart than "
              "sync_tolerance_s but within this is matched when neither has a nearer partner (as message_filters' ApproximateTime), "
              "or at the end of a recording, and logged as a WARN with its skew (the cloud's geometry and colour are then that far "
              "apart in time); 0 = only sync_tolerance_s", range=(0.0, 10.0), nodes=_IN, unit="s"),
    ParamSpec("sync_queue_size", 10, "messages buffered per input stream for stamp matching", range=(1, 1000), read_only=True,
              nodes=_IN + ("partition_planner",)),
    ParamSpec("depth_fill", "row", "invalid depth (0, NaN, out of range) where the camera measured a colour: row = each such "
              "pixel gets the depth of the farther of its nearest valid neighbours in its row (then column), so the frame has "
              "no black holes and a filled point never occludes a measured one; the certificate is then about the cloud "
              "with filled depth and counts the filled points; off = only measured pixels become points",
              choices=("row", "off"), nodes=_IN),
    ParamSpec("max_depth_m", 0.0, "depth farther than this is invalid, as a driver's no return (e.g. a saturated 65535 of a "
              "uint16 image, or a sensor's range): filled by depth_fill like any invalid pixel and not counted as valid by "
              "min_valid_depth; applied to the depth image (before registration) or to the organized cloud's z; 0 = no limit",
              range=(0.0, 1e6), nodes=_IN, unit="m"),
    ParamSpec("min_valid_depth", 0.1, "least share of an input frame's pixels with a valid depth (organized clouds, depth "
              "images); below it the frame is an ERROR (too little is measured to describe a scene)", range=(0.0, 1.0), nodes=_IN),
    ParamSpec("require_same_frame", True, "refuse depth and colour with different non-empty frame ids (not registered)", nodes=_IN),
    ParamSpec("num_workers", 1, "pipeline processes sharing one input stream (launch: workers:=N starts them): each "
              "certifies only the frames whose stamp is assigned to it (worker_period_s), with its own latest-only policy "
              "and cores / num_workers torch threads; no coordinator", range=(1, 1024), read_only=True, nodes=("pipeline",)),
    ParamSpec("worker_index", 0, "this pipeline's index among num_workers (0 .. num_workers - 1)", range=(0, 1023),
              read_only=True, nodes=("pipeline",)),
    ParamSpec("worker_period_s", 0.0, "how stamps are assigned to workers: 0 = a hash of the stamp (any camera rate); > 0 = "
              "round robin on the camera period (stamp // period) mod num_workers; either way every stamp goes to exactly "
              "one worker", range=(0.0, 3600.0), read_only=True, nodes=("pipeline",), unit="s"),
    ParamSpec("min_period_s", 0.0, "skip input frames closer than this to the last accepted one (0 = take every frame the worker can)",
              range=(0.0, 3600.0), nodes=_IN, unit="s"),
    # -- QoS --
    ParamSpec("input_qos", "sensor_data", "QoS of camera inputs: sensor_data (best effort, matches every driver), reliable, best_effort, system_default",
              choices=QOS_PROFILES, read_only=True, nodes=_IN),
    ParamSpec("input_qos_depth", 5, "history depth of input subscriptions", range=(1, 10000), read_only=True, nodes=_IN),
    ParamSpec("output_qos", "reliable", "QoS of results (certification, plans, clouds)", choices=QOS_PROFILES, read_only=True, nodes=_ALL),
    ParamSpec("output_qos_depth", 10, "history depth of result publishers", range=(1, 10000), read_only=True, nodes=_ALL),
    ParamSpec("frames_qos_depth", 4096, "history depth (reliable) of rendered/frames in the four-process mode; must hold one burst",
              range=(1, 1_000_000), read_only=True, nodes=("projector", "certifier")),
    # -- outputs --
    ParamSpec("publish_cloud", True, "publish the one-frame cloud on 'cloud' (PointCloud2 xyz + rgb, source header; the "
              "cloud_listener always does: the planner reads it)", nodes=("pipeline",)),
    ParamSpec("publish_poses", True, "publish each plan's camera poses on 'plan/poses/<axis>' (PoseArray)",
              nodes=("partition_planner", "pipeline")),
    ParamSpec("publish_markers", True, "publish 'certification/markers' (MarkerArray text for RViz/Foxglove)", nodes=_CERT),
    ParamSpec("publish_preview", True, "publish a decimated 'rendered/preview' Image (rgb8) for humans", nodes=("projector", "pipeline")),
    ParamSpec("preview_every", 25, "publish every k-th rendered frame of a plan on rendered/preview (the alpha = 0 frame always)",
              range=(1, 1_000_000), nodes=("projector", "pipeline")),
    ParamSpec("publish_overlay", False, "publish 'certification/overlay' (Image rgb8, the frame's header): the classifier's "
              "alpha = 0 view scaled up, its label, p_A and one bar per axis (the certified share of the requested radius, "
              "green OK, orange WARN, red ERROR), for rviz2 or any image viewer; drawn by a thread of its own after the "
              "certification is out, the newest frame only (skipped, never queued, when it is behind)", nodes=_CERT),
    ParamSpec("certified_label_timeout_s", 10.0, "the /diagnostics health status WARNs when no frame has been certified on "
              "every axis (no 'certified_label') for longer than this, wall time since the last one (or since the first "
              "frame); 0 = never", range=(0.0, 86400.0), nodes=_CERT, unit="s"),
    ParamSpec("certification_to_diagnostics", False, "also publish each frame's certification (the statuses pws/<axis>) on "
              "/diagnostics, beside the health statuses, for diagnostic_aggregator and rqt_robot_monitor "
              "(config/diagnostic_aggregator.yaml groups both in one tree); off: /diagnostics holds the health statuses only",
              nodes=_CERT),
    ParamSpec("health_period_s", 1.0, "period of the /diagnostics health status", range=(0.05, 3600.0), read_only=True, nodes=_ALL, unit="s"),
    ParamSpec("assembly_timeout_s", 30.0, "four-process mode: time to wait for every frame of a plan before declaring it incomplete",
              range=(0.01, 86400.0), nodes=("certifier",), unit="s"),
    ParamSpec("max_pending_frames", 2, "four-process mode: input frames held while their rendered frames arrive",
              range=(1, 64), read_only=True, nodes=("certifier", "projector")),
)

SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


def spec_table(nodes: Sequence[str] | None = None) -> list[ParamSpec]:
    """The specs a node declares (all when ``nodes`` is None)."""
    if nodes is None:
        return list(PARAMS)
    return [p for p in PARAMS if any(n in p.nodes for n in nodes)]


# ---- validation ---------------------------------------------------------------------------

def _num(value: Any, spec: ParamSpec, integer: bool) -> float | int:
    if isinstance(value, bool):
        raise PwsError(f"parameter {spec.name} must be {'an integer' if integer else 'a number'}, got {value!r}")
    if integer:
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        require(isinstance(value, int), f"parameter {spec.name} must be an integer, got {value!r}")
        out: float | int = int(value)
    else:
        require(isinstance(value, (int, float)), f"parameter {spec.name} must be a number, got {value!r}")
        out = float(value)
        require(math.isfinite(out), f"parameter {spec.name} must be finite, got {value!r}")
    if spec.range is not None:
        lo, hi = spec.range
        require(lo <= out <= hi, f"parameter {spec.name}={out!r} is out of range [{lo:g}, {hi:g}]")
    return out


def validate_param(name: str, value: Any) -> Any:
    """The validated (normalised) value of parameter ``name``; PwsError naming what is wrong."""
    spec = SPECS.get(name)
    if spec is None:
        raise PwsError(f"unknown parameter {name!r}" + _suggest(name))
    kind = spec.kind
    if kind == "bool":
        require(isinstance(value, bool), f"parameter {name} must be true or false, got {value!r}")
        return value
    if kind == "int":
        return _num(value, spec, integer=True)
    if kind == "float":
        return _num(value, spec, integer=False)
    if kind == "str":
        require(isinstance(value, str), f"parameter {name} must be a string, got {value!r}")
        value = value.strip()
        if spec.choices is not None:
            require(value in spec.choices, f"parameter {name}={value!r} is not one of {', '.join(spec.choices)}")
        return value
    if kind == "str_list":
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split() if v]
        require(isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value),
                f"parameter {name} must be a list of strings, got {value!r}")
        items = [v.strip().lower() if spec.choices == AXES else v.strip() for v in value]
        if spec.choices is not None:
            bad = [v for v in items if v not in spec.choices]
            require(not bad, f"parameter {name}: {', '.join(map(repr, bad))} not in {', '.join(spec.choices)}")
        require(len(items) > 0, f"parameter {name} must not be empty")
        require(len(set(items)) == len(items), f"parameter {name} lists an entry twice: {items}")
        return tuple(items)
    raise PwsError(f"parameter {name} has an unsupported type")  # pragma: no cover


def validate_params(params: dict[str, Any]) -> dict[str, Any]:
    return {k: validate_param(k, v) for k, v in params.items()}


def _suggest(name: str) -> str:
    import difflib

    close = difflib.get_close_matches(name, list(SPECS), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


__all__ = ["COVERAGES", "DEMO_MODEL", "INFO_SYNC", "INPUT_MODES", "METHODS", "NODES", "PARAMS", "ParamSpec", "QOS_PROFILES",
           "SPECS", "spec_table", "validate_param", "validate_params"]

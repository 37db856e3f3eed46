"""The parameters of the node suite: ONE table (:data:`PARAMS`) with defaults, descriptions and
ranges, the validated :class:`PwsConfig` dataclass, and loading of ``config/pws.yaml``.

The nodes declare their ROS parameters from :data:`PARAMS` (description, FloatingPointRange /
IntegerRange, read-only flag) and validate every change with :func:`validate_param`, so the table
is the single source of truth for names, defaults, ranges and documentation (``docs/ros2.md`` and
``config/pws.yaml`` list the same entries; a test checks they agree).

``config/pws.yaml`` uses the ROS 2 parameter-file layout::

    /**:                      # every node (wildcard), or a node name such as "pipeline"
      ros__parameters:
        axes: [tz, ry]
        radius:
          tz: 0.010           # nested keys become dotted parameter names: radius.tz
        ...

Sections are merged in file order with node-specific sections (``pipeline``, ``/pws/pipeline`` ...)
overriding the wildcards when ``node_name`` is given.
"""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

import yaml

from ..core.errors import PwsError, require
from ..core.motion import AXES, PAPER_RADIUS, UNITS

from ..core.certify import COVERAGES, METHODS  # the certification core owns these lists
from ..core.imaging import DEFAULT_RENDER_FACTOR, IMAGING_KINDS
from ..core.partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX

INPUT_MODES = ("auto", "pointcloud2", "rgbd")
QOS_PROFILES = ("sensor_data", "reliable", "best_effort", "system_default")
INFO_SYNC = ("latest", "stamp")
DEMO_MODEL = "bags/models/classifier_sigma0.50.pt"
NODES = ("cloud_listener", "partition_planner", "projector", "certifier", "pipeline")
_ALL = NODES
_PLAN = ("partition_planner", "projector", "certifier", "pipeline")
_CERT = ("certifier", "pipeline")
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
              "placed from the distance bounds, at most num_anchors), pairwise (p_A at every partition, per segment), paper "
              "(max M < min R); ignored by cms",
              choices=COVERAGES, nodes=_CERT),
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
    ParamSpec("background", 0.0, "pixel value where no point is drawn (invalid depth, disocclusions, the masked border)", range=(0.0, 1.0), nodes=_PLAN),
    ParamSpec("render_width", 0, "paper imaging: rendered frame width; 0 = the model's declared input size (else the camera's)", range=(0, 8192), read_only=True, nodes=_PLAN, unit="px"),
    ParamSpec("render_height", 0, "paper imaging: rendered frame height; 0 = the model's declared input size (else the camera's)", range=(0, 8192), read_only=True, nodes=_PLAN, unit="px"),
    # -- smoothing and statistics --
    ParamSpec("model_path", DEMO_MODEL, "TorchScript classifier (relative paths: current directory, then the package share directory)",
              read_only=True, nodes=_PLAN),
    ParamSpec("classes_path", "", "class-names file (one per line); empty = beside the model or in its metadata", read_only=True, nodes=_CERT),
    ParamSpec("denoiser_path", "", "optional TorchScript denoiser applied to noisy images before the classifier", read_only=True, nodes=_CERT),
    ParamSpec("device", "cpu", "torch device: cpu or cuda:N (falls back to cpu with a WARN when CUDA is missing)", read_only=True, nodes=_PLAN),
    ParamSpec("sigma", 0.5, "pixel noise standard deviation of the smoothed classifier (images in [0, 1])", range=(1e-6, 10.0), nodes=_CERT),
    ParamSpec("n0", 64, "noise samples to select the top class (at the original pose)", range=(1, 10_000_000), nodes=_CERT),
    ParamSpec("n", 256, "noise samples per bound to estimate p_A", range=(1, 100_000_000), nodes=_CERT),
    ParamSpec("alpha", 0.01, "risk of a frame's certificate: the probability that any statement about the frame (all its axes "
              "together) is wrong; split evenly over the axes, then over every bound each uses (Bonferroni)", range=(1e-12, 0.5), nodes=_CERT),
    ParamSpec("seed", 0, "random seed; each frame and axis draws from its own stream derived from (seed, stamp, axis): "
              "deterministic for equal inputs, independent across frames and axes", range=(0, 2**31 - 1), nodes=_CERT),
    ParamSpec("batch_size", 256, "images per classifier call", range=(1, 1_000_000), nodes=_CERT),
    ParamSpec("num_anchors", 24, "anchor frames for coverage=anchors (surfel imaging: the most anchors, i.e. a budget of "
              "n0 + num_anchors * n classifier calls per axis; a frame needing more gets a smaller radius)", range=(1, 100_000), nodes=_CERT),
    ParamSpec("audit_every", 0, "self-audit every k-th frame: re-render poses inside every segment of each certified axis "
              "(audit_poses per segment) and check every bound the certificate used; a violation turns that axis to "
              "ERROR; 0 = off", range=(0, 1_000_000), nodes=_CERT),
    ParamSpec("audit_poses", 8, "poses re-rendered per segment by the self-audit (ends and their float neighbours included)",
              range=(2, 100_000), nodes=_CERT),
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
    ParamSpec("sync_tolerance_s", 0.02, "largest stamp difference between depth, colour (and CameraInfo) of one frame", range=(0.0, 10.0), nodes=_IN, unit="s"),
    ParamSpec("sync_queue_size", 10, "messages buffered per input stream for stamp matching", range=(1, 1000), read_only=True, nodes=_IN),
    ParamSpec("require_same_frame", True, "refuse depth and colour with different non-empty frame ids (not registered)", nodes=_IN),
    ParamSpec("min_period_s", 0.0, "skip input frames closer than this to the last accepted one (0 = take every frame the worker can)",
              range=(0.0, 3600.0), nodes=_IN, unit="s"),
    # -- QoS --
    ParamSpec("input_qos", "sensor_data", "QoS of camera inputs: sensor_data (best effort, matches every driver), reliable, best_effort, system_default",
              choices=QOS_PROFILES, read_only=True, nodes=_ALL),
    ParamSpec("input_qos_depth", 5, "history depth of input subscriptions", range=(1, 10000), read_only=True, nodes=_ALL),
    ParamSpec("output_qos", "reliable", "QoS of results (certification, plans, clouds)", choices=QOS_PROFILES, read_only=True, nodes=_ALL),
    ParamSpec("output_qos_depth", 10, "history depth of result publishers", range=(1, 10000), read_only=True, nodes=_ALL),
    ParamSpec("frames_qos_depth", 4096, "history depth (reliable) of rendered/frames in the four-process mode; must hold one burst",
              range=(1, 1_000_000), read_only=True, nodes=("projector", "certifier")),
    # -- outputs --
    ParamSpec("publish_cloud", True, "publish the one-frame cloud on 'cloud' (PointCloud2 xyz + rgb, source header)", nodes=_IN),
    ParamSpec("publish_poses", True, "publish each plan's camera poses on 'plan/poses/<axis>' (PoseArray)", nodes=_PLAN),
    ParamSpec("publish_markers", True, "publish 'certification/markers' (MarkerArray text for RViz/Foxglove)", nodes=_CERT),
    ParamSpec("publish_preview", True, "publish a decimated 'rendered/preview' Image (rgb8) for humans", nodes=("projector", "pipeline")),
    ParamSpec("preview_every", 25, "publish every k-th rendered frame of a plan on rendered/preview (the alpha = 0 frame always)",
              range=(1, 1_000_000), nodes=("projector", "pipeline")),
    ParamSpec("health_period_s", 1.0, "period of the /diagnostics health status", range=(0.05, 3600.0), read_only=True, nodes=_ALL, unit="s"),
    ParamSpec("assembly_timeout_s", 30.0, "four-process mode: time to wait for every frame of a plan before declaring it incomplete",
              range=(0.01, 86400.0), nodes=("certifier",), unit="s"),
    ParamSpec("max_pending_frames", 2, "four-process mode: input frames held while their rendered frames arrive",
              range=(1, 64), read_only=True, nodes=("certifier", "projector")),
)

SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}


@dataclass(frozen=True)
class PwsConfig:
    """Validated parameter values (attribute = parameter name with dots as underscores)."""

    axes: tuple[str, ...] = ("tz", "ry")
    radius_tx: float = PAPER_RADIUS["tx"]
    radius_ty: float = PAPER_RADIUS["ty"]
    radius_tz: float = PAPER_RADIUS["tz"]
    radius_rx: float = PAPER_RADIUS["rx"]
    radius_ry: float = PAPER_RADIUS["ry"]
    radius_rz: float = PAPER_RADIUS["rz"]
    method: str = "pws_of"
    imaging: str = "surfel"
    border: int = -1
    render_factor: int = DEFAULT_RENDER_FACTOR
    step_px: float = DEFAULT_STEP_PX
    coverage: str = "anchors"
    delta: float = 0.0
    max_partitions: int = DEFAULT_FRAME_BUDGET
    max_memory_mb: float = 2048.0
    min_partitions: int = 0
    dense_cloud_path: str = ""
    background: float = 0.0
    render_width: int = 0
    render_height: int = 0
    model_path: str = DEMO_MODEL
    classes_path: str = ""
    denoiser_path: str = ""
    device: str = "cpu"
    sigma: float = 0.5
    n0: int = 64
    n: int = 256
    alpha: float = 0.01
    seed: int = 0
    batch_size: int = 256
    num_anchors: int = 24
    audit_every: int = 0
    audit_poses: int = 8
    cms_sigma: float = 0.0
    input_mode: str = "auto"
    points_topic: str = "/camera/depth/color/points"
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    color_topic: str = "/camera/color/image_raw"
    camera_info_topic: str = "/camera/color/camera_info"
    depth_camera_info_topic: str = "auto"
    camera_info_file: str = ""
    camera_info_sync: str = "latest"
    sync_tolerance_s: float = 0.02
    sync_queue_size: int = 10
    require_same_frame: bool = True
    min_period_s: float = 0.0
    input_qos: str = "sensor_data"
    input_qos_depth: int = 5
    output_qos: str = "reliable"
    output_qos_depth: int = 10
    frames_qos_depth: int = 4096
    publish_cloud: bool = True
    publish_poses: bool = True
    publish_markers: bool = True
    publish_preview: bool = True
    preview_every: int = 25
    health_period_s: float = 1.0
    assembly_timeout_s: float = 30.0
    max_pending_frames: int = 2

    def radius_for(self, axis: str) -> float:
        return float(getattr(self, f"radius_{axis}"))

    @property
    def radii(self) -> dict[str, float]:
        return {a: self.radius_for(a) for a in self.axes}

    def to_params(self) -> dict[str, Any]:
        """``{dotted name: value}`` with list-valued parameters as lists (ROS parameter values)."""
        out = {}
        for spec in PARAMS:
            v = getattr(self, spec.attr)
            out[spec.name] = list(v) if isinstance(v, tuple) else v
        return out

    def with_params(self, params: dict[str, Any]) -> "PwsConfig":
        """A copy with some parameters changed (validated)."""
        return replace(self, **{SPECS[k].attr: v for k, v in validate_params(params).items()})

    def certify_config(self):
        """The core's ``CertifyConfig`` for these parameters."""
        from ..core.certify import CertifyConfig

        return CertifyConfig(sigma=self.sigma, n0=self.n0, n=self.n, alpha=self.alpha, seed=self.seed, device=self.device,
                             batch_size=self.batch_size, coverage=self.coverage, num_anchors=self.num_anchors,
                             background=self.background, max_partitions=self.max_partitions,
                             min_partitions=self.min_partitions, imaging=self.imaging, border=self.border,
                             step_px=self.step_px, max_memory_mb=self.max_memory_mb, render_factor=self.render_factor,
                             delta=self.delta if self.delta > 0 else None,
                             cms_sigma=self.cms_sigma if self.cms_sigma > 0 else None)


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


def check_consistency(cfg: PwsConfig) -> None:
    """Cross-parameter rules (PwsError): pws needs a dense cloud; render size given in full."""
    require(not (cfg.method == "pws" and not cfg.dense_cloud_path),
            "method pws needs the entire scene cloud: set dense_cloud_path (or use pws_of / pws_l with the one-frame cloud)")
    require((cfg.render_width == 0) == (cfg.render_height == 0),
            f"render_width and render_height must both be 0 or both set, got {cfg.render_width}x{cfg.render_height}")
    require(not (cfg.method == "pws" and cfg.imaging == "surfel"),
            "method pws plans on the entire scene cloud, which has no depth pixels to make surfels of: set imaging: paper "
            "(or use pws_of / pws_l with the one-frame cloud)")


def config_from_params(params: dict[str, Any] | None = None, *, check: bool = True, ignore_unknown: Iterable[str] = ("use_sim_time",)) -> PwsConfig:
    """A :class:`PwsConfig` from ``{dotted name: value}`` (missing = default)."""
    params = dict(params or {})
    for k in list(params):
        if k in ignore_unknown or k.startswith("qos_overrides."):
            params.pop(k)
    cfg = PwsConfig().with_params(params)
    if check:
        check_consistency(cfg)
    return cfg


def _suggest(name: str) -> str:
    import difflib

    close = difflib.get_close_matches(name, list(SPECS), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


# ---- YAML ---------------------------------------------------------------------------------

def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> dotted keys (ROS parameter-file semantics)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _node_matches(section: str, node_name: str | None) -> bool:
    if section in ("/**", "**"):
        return True
    if node_name is None:
        return False
    s = section.strip("/")
    return s == node_name or s.endswith("/" + node_name) or s in (f"**/{node_name}",)


def params_from_yaml_dict(data: Any, node_name: str | None = None, source: str = "config") -> dict[str, Any]:
    """Parameters of ``node_name`` from a ROS 2 parameter-file mapping (wildcard sections first,
    then the node's own sections). Also accepts a bare ``{ros__parameters: {...}}`` or a flat mapping."""
    require(isinstance(data, dict), f"{source}: expected a mapping at the top level")
    if "ros__parameters" in data:
        require(isinstance(data["ros__parameters"], dict), f"{source}: ros__parameters must be a mapping")
        return flatten(data["ros__parameters"])
    sections = [(k, v) for k, v in data.items() if isinstance(v, dict) and "ros__parameters" in v]
    if not sections:  # a flat mapping of parameters
        return flatten(data)
    merged: dict[str, Any] = {}
    wild = [(k, v) for k, v in sections if str(k) in ("/**", "**")]
    own = [(k, v) for k, v in sections if str(k) not in ("/**", "**") and _node_matches(str(k), node_name)]
    for k, v in wild + own:
        body = v["ros__parameters"]
        require(isinstance(body, dict), f"{source}: {k}.ros__parameters must be a mapping")
        merged.update(flatten(body))
    return merged


def load_config(path: str | Path, node_name: str | None = None, overrides: dict[str, Any] | None = None,
                check: bool = True) -> PwsConfig:
    """Read a parameter file (``config/pws.yaml`` layout) into a validated :class:`PwsConfig`."""
    path = Path(path)
    require(path.is_file(), f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise PwsError(f"config file {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    params = params_from_yaml_dict(data or {}, node_name, source=f"config file {path}")
    params.update(overrides or {})
    try:
        return config_from_params(params, check=check)
    except PwsError as exc:
        raise PwsError(f"config file {path}: {exc}") from None


# ---- paths --------------------------------------------------------------------------------

def package_share_dirs() -> list[Path]:
    """Where shipped files may live: the ament share directory (if ROS is installed) and the source
    checkout (for ``pip install -e`` and tests)."""
    dirs: list[Path] = []
    try:  # ament_index_python is plain Python (no rclpy)
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        dirs.append(Path(get_package_share_directory("pws_ros")))
    except Exception:
        pass
    env = os.environ.get("PWS_ROS_SHARE")
    if env:
        dirs.append(Path(env))
    dirs.append(Path(sys.prefix) / "share" / "pws_ros")  # data_files of a pip install
    dirs.append(Path(__file__).resolve().parents[2])
    return dirs


def depth_info_topic(config: PwsConfig) -> str:
    """The depth stream's CameraInfo topic: ``depth_camera_info_topic``, where ``auto`` names the
    ``camera_info`` beside ``depth_topic`` (the image_transport convention), and "" means none."""
    name = config.depth_camera_info_topic
    if name != "auto":
        return name
    base, _, _ = config.depth_topic.rpartition("/")
    return f"{base}/camera_info" if base or config.depth_topic.startswith("/") else "camera_info"


def resolve_path(path: str | Path, what: str = "file") -> Path:
    """An existing file: absolute, relative to the current directory, or to a package share directory.

    PwsError naming every place looked at when none holds it.
    """
    p = Path(os.path.expanduser(str(path)))
    require(str(path).strip() != "", f"{what} path is empty")
    if p.is_absolute():
        require(p.exists(), f"{what} not found: {p}")
        return p
    tried = [Path.cwd() / p] + [d / p for d in package_share_dirs()]
    for cand in tried:
        if cand.exists():
            return cand
    raise PwsError(f"{what} not found: {path} (looked in {', '.join(str(t.parent) for t in tried)})")


def default_config_path() -> Path:
    return resolve_path("config/pws.yaml", "config file")


def spec_table(nodes: Sequence[str] | None = None) -> list[ParamSpec]:
    """The specs a node declares (all when ``nodes`` is None)."""
    if nodes is None:
        return list(PARAMS)
    return [p for p in PARAMS if any(n in p.nodes for n in nodes)]


def _yaml_value(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return yaml.safe_dump(v, default_style='"').strip() if (v == "" or any(c in v for c in ":#{}[],&*?|<>=!%@`'\"")) else v
    return str(v)


def _range_text(spec: ParamSpec) -> str:
    if spec.choices is not None:
        return "one of: " + ", ".join(spec.choices) if spec.kind == "str" else "each of: " + ", ".join(spec.choices)
    if spec.range is not None:
        lo, hi = spec.range
        return f"range [{lo:g}, {hi:g}]" + (f" {spec.unit}" if spec.unit else "")
    return ""


def render_params_yaml(config: PwsConfig | None = None) -> str:
    """``config/pws.yaml``: every parameter under ``/**: ros__parameters`` with its description,
    range or choices, and which nodes read it (values from ``config``, default the table's)."""
    cfg = config or PwsConfig()
    lines = [
        "# pws_ros parameters (ROS 2 parameter file). Generated from pws_ros/bridge/config.py PARAMS:",
        "# the table is the single source of truth for names, defaults, ranges and descriptions.",
        "# '/**' applies to every node; add a section named after a node (e.g. 'certifier:') to override",
        "# a value for that node only. (ro) = read-only once the node runs; others can be set at run time",
        "# with 'ros2 param set' and are validated.",
        "/**:",
        "  ros__parameters:",
    ]
    params = cfg.to_params()
    done_radius = False
    for spec in PARAMS:
        extra = _range_text(spec)
        meta = "; ".join(x for x in (extra, "(ro)" if spec.read_only else "", "nodes: " + ", ".join(spec.nodes)) if x)
        if spec.name.startswith("radius."):
            if not done_radius:
                lines.append("    # requested certification radius b per axis: the motion range is [-b, b]")
                lines.append("    radius:")
                done_radius = True
            axis = spec.name.split(".", 1)[1]
            lines.append(f"      # {spec.description}; {meta}")
            lines.append(f"      {axis}: {_yaml_value(params[spec.name])}")
            continue
        lines.append(f"    # {spec.description}; {meta}")
        lines.append(f"    {spec.name}: {_yaml_value(params[spec.name])}")
    return "\n".join(lines) + "\n"


def render_params_markdown() -> str:
    """The parameter table of ``docs/ros2.md`` (name, default, range or choices, nodes, description)."""
    rows = ["| parameter | default | range / choices | nodes | description |", "|---|---|---|---|---|"]
    short = {"cloud_listener": "L", "partition_planner": "Pl", "projector": "Pr", "certifier": "C", "pipeline": "P"}
    for spec in PARAMS:
        d = spec.default
        default = ", ".join(d) if isinstance(d, (list, tuple)) else ("" if d == "" else _yaml_value(d))
        rng = _range_text(spec).replace("one of: ", "").replace("each of: ", "")
        nodes = " ".join(short[n] for n in spec.nodes)
        ro = " (read-only)" if spec.read_only else ""
        rows.append(f"| `{spec.name}` | `{default}` | {rng} | {nodes} | {spec.description}{ro} |".replace("``", "(empty)"))
    return "\n".join(rows) + "\n"


def _check_table() -> None:
    names = {f.name for f in fields(PwsConfig)}
    attrs = {p.attr for p in PARAMS}
    assert names == attrs, f"PwsConfig and PARAMS disagree: {sorted(names ^ attrs)}"
    base = PwsConfig()
    for p in PARAMS:
        v = getattr(base, p.attr)
        d = tuple(p.default) if isinstance(p.default, list) else p.default
        assert v == d, f"default of {p.name} differs: {v!r} vs {d!r}"


_check_table()

__all__ = ["COVERAGES", "DEMO_MODEL", "INPUT_MODES", "METHODS", "NODES", "PARAMS", "ParamSpec", "PwsConfig", "QOS_PROFILES",
           "SPECS", "check_consistency", "config_from_params", "default_config_path", "flatten", "load_config",
           "params_from_yaml_dict", "depth_info_topic", "render_params_markdown", "render_params_yaml", "resolve_path", "spec_table", "validate_param", "validate_params"]

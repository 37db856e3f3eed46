"""What ``pws replay`` takes and returns: options, the camera input of a bag, ground-truth rows, the result."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..bridge.config import PwsConfig
from ..core.errors import PwsError
from ..core.registration import Extrinsic
from .progress_log import DEFAULT_INTERVAL_S
from .report import FrameRecord, format_table
from .video import DEFAULT_FPS

NODE_NAME = "pws_replay"
GROUND_TRUTH_TOPIC = "/pws/ground_truth"
T_POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
T_IMAGE = "sensor_msgs/msg/Image"
T_CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
T_DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
T_TRANSFORM = "geometry_msgs/msg/Transform"
T_TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
# the RealSense SDK recorder: /device_<d>/sensor_<s>/<Stream>_<i>/tf/<group> holds the extrinsic from
# the group's reference stream to that stream (P_stream = R P_reference + t)
REALSENSE_STREAM = re.compile(r"^(/device_\d+/sensor_\d+/[A-Za-z]+_\d+)/")
DEPTH_ENCODINGS = {"16uc1", "mono16", "32fc1"}
COLOR_ENCODINGS = {"rgb8", "bgr8", "rgba8", "bgra8", "mono8"}
SIM_DENSE_MARKER = "(regenerated per frame by pws_ros.sim from the ground truth)"

LogFn = Callable[[str, str], None]


# ---- options and results ------------------------------------------------------------------

@dataclass
class ReplayOptions:
    """Everything ``pws replay`` needs (the command line fills it)."""

    bag: Path
    config: PwsConfig = field(default_factory=PwsConfig)
    out: Path | None = None                 # None: <bag>_pws next to the bag
    overwrite: bool = False
    write_output: bool = True
    topics: dict[str, str] = field(default_factory=dict)   # cloud, depth, color, info, depth_info, truth
    max_frames: int | None = None
    realtime: bool = False
    copy_inputs: bool = False
    write_cloud: bool = False
    preview: bool = False
    markers: bool = True
    poses: bool = True
    namespace: str = ""
    compress: bool = True
    report_dir: Path | None = None
    video: Path | None = None               # --video: the overlay picture of every frame (.mp4, .avi or a PNG folder)
    video_fps: float = DEFAULT_FPS          # --video-fps: frames per second of a video file
    quiet: bool = False
    progress: bool | None = None            # None: a bar on a terminal, else log lines; False: none (also --quiet)
    progress_interval_s: float = DEFAULT_INTERVAL_S   # seconds between progress log lines (not on a terminal)
    log: LogFn | None = None
    label: str = "pws replay"               # the prefix of log lines and progress (the command that runs the replay)
    model: Any = None                       # a LoadedModel (tests); else config.model_path
    denoiser: Any = None
    cost_fn: Callable[[FrameRecord], float] | None = None   # realtime only: seconds a frame "takes" (tests)


@dataclass
class InputTopics:
    """The camera input of a bag: ``mode`` pointcloud2 | rgbd | auto (both: the first complete wins)."""

    mode: str
    points: str = ""
    depth: str = ""
    color: str = ""
    info: str = ""
    depth_info: str = ""
    truth: str = ""
    notes: list[str] = field(default_factory=list)
    extrinsic: Extrinsic | None = None      # depth -> colour, set when depth and colour are not registered
    extrinsic_from: str = ""                # where it was read (topic and frames)

    def roles(self) -> dict[str, str]:
        return {k: v for k, v in (("points", self.points), ("depth", self.depth), ("color", self.color), ("info", self.info),
                                  ("depth_info", self.depth_info), ("truth", self.truth)) if v}

    def describe(self) -> str:
        parts = []
        if self.mode in ("pointcloud2", "auto") and self.points:
            parts.append(f"cloud {self.points}")
        if self.mode in ("rgbd", "auto") and self.depth:
            parts.append(f"depth {self.depth} + colour {self.color}")
        if self.info:
            parts.append(f"camera info {self.info}")
        if self.depth_info:
            parts.append(f"depth camera info {self.depth_info}")
        if self.truth:
            parts.append(f"ground truth {self.truth}")
        if self.extrinsic is not None and self.mode != "pointcloud2":
            parts.append(f"depth registered into the colour camera with the depth -> colour extrinsic from {self.extrinsic_from} "
                         f"({self.extrinsic.describe()})")
        return f"input ({self.mode}): " + ", ".join(parts)


@dataclass
class GroundTruth:
    stamp_ns: int
    label: int | None
    class_name: str
    values: dict[str, str]


@dataclass
class ReplayResult:
    records: list[FrameRecord]
    summary: dict[str, Any]
    out: Path | None
    exit_code: int
    message: str = ""
    warnings: list[str] = field(default_factory=list)
    report_files: list[Path] = field(default_factory=list)
    output_counts: dict[str, int] = field(default_factory=dict)

    def table(self) -> str:
        return format_table(self.summary)


# ---- configuration ------------------------------------------------------------------------

def load_replay_config(path: str | Path | None = None) -> PwsConfig:
    """The parameters of a replay before any command-line override: the ROS 2 parameter file ``path``
    read as the ``pipeline`` node's, or ``config/pws.yaml`` when none is given and it is found, else the
    built-in defaults (``pws replay`` and ``python -m pws_ros.bench.frame_timing``)."""
    from ..bridge.config import default_config_path, load_config

    if path:
        return load_config(path, node_name="pipeline", check=False)
    try:
        found = default_config_path()
    except PwsError:
        found = None
    return load_config(found, node_name="pipeline", check=False) if found is not None else PwsConfig()


def override_config(cfg: PwsConfig, params: dict[str, Any]) -> PwsConfig:
    """``cfg`` with command-line overrides (parameter name -> value), validated; an error names the
    option/parameter."""
    try:
        return cfg.with_params(params)
    except PwsError as exc:
        raise PwsError(str(exc).replace("parameter ", "option/parameter ")) from None


# ---- helpers ------------------------------------------------------------------------------

def default_out(bag: Path) -> Path:
    """``<bag>_pws`` next to the bag (``talker.mcap`` -> ``talker_pws``)."""
    bag = Path(bag)
    name = bag.name if bag.is_dir() else bag.stem
    return bag.resolve().parent / f"{name}_pws"


def topic_name(namespace: str, rel: str) -> str:
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{rel}"


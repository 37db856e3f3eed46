"""Certify a rosbag2 recording offline, exactly as the live ``pipeline`` node would, and write the
results as a bag (``pws replay``).

1. :class:`~pws_ros.bagio.BagReader` opens the recording (MCAP or sqlite3, directory or bare file,
   split, zstd, damaged files up to the damage).
2. :func:`discover_inputs` finds the camera input by message type (an organized ``PointCloud2``, or
   a depth ``Image`` + colour ``Image`` + ``CameraInfo``), unless topics are given; the ground truth
   of the procedural world (``/pws/ground_truth``) is read when present.
3. The input messages go, in header-stamp order, through the live nodes' front end
   (:class:`~pws_ros.bridge.inputs.InputAssembler`: stamp matching, CameraInfo pairing, source
   locking) and every complete frame through :func:`~pws_ros.bridge.inputs.convert` and
   :meth:`~pws_ros.bridge.engine.FrameCertifier.process` (plan, render, certify each axis).
   Default: every frame is certified (deterministic for a seed). ``realtime=True`` applies the live
   node's online policy on the recorded stamps: a frame that arrives while the (measured)
   certification of an earlier one would still run waits in a one-frame slot and is replaced (dropped)
   by a newer one, exactly as :class:`~pws_ros.bridge.sync.LatestSlot` does live.
4. Every processed frame is written as the ``pipeline`` node publishes it (the same list, in the same
   order, from :func:`pws_ros.bridge.outputs.frame_outputs`), with log time = the source stamp: ``certification``
   (DiagnosticArray), ``certification/markers`` (MarkerArray), ``plan/poses/<axis>`` (PoseArray);
   optionally ``cloud`` + ``cloud/camera_info``, ``rendered/preview`` and the input topics themselves.
   A frame's messages are written together once it is done, and the bag is flushed after each
   frame (:meth:`~pws_ros.bagio.BagWriter.flush`). SIGINT and SIGTERM stop the run cleanly
   (:mod:`pws_ros.interrupt`): the frame in flight is dropped whole, the bag is closed (complete and
   readable up to the last finished frame), and the summary and report cover the frames done, with
   ``interrupted`` set and exit status 130 (SIGINT) or 143 (SIGTERM).

Method ``pws`` needs the entire scene cloud: ``dense_cloud_path`` from the config (a static scene), or,
for recordings of the procedural world, the cloud regenerated per frame by :mod:`pws_ros.sim` from
the ground truth's ``scene_seed`` / ``view_index``; otherwise the method is refused.
"""
from __future__ import annotations

import bisect
import heapq
import math
import re
import sys
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from .bagio import BagMessage, BagReader, BagWriter, prepare_output
from .bridge import msgbuild, msgconv, outputs
from .bridge.config import PwsConfig, depth_info_topic
from .bridge.inputs import InputAssembler, RawFrame, convert
from .core.errors import PwsError, require
from .core.motion import UNITS
from .core.registration import Extrinsic, chain_transform
from .core.result import STATUS_ERROR, Certificate
from .interrupt import Interrupted, StopSignals
from .progress_log import DEFAULT_INTERVAL_S, Progress
from .report import FrameRecord, format_table, summarize, write_report

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
    quiet: bool = False
    progress: bool | None = None            # None: a bar on a terminal, else log lines; False: none (also --quiet)
    progress_interval_s: float = DEFAULT_INTERVAL_S   # seconds between progress log lines (not on a terminal)
    log: LogFn | None = None
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


# ---- helpers ------------------------------------------------------------------------------

def default_out(bag: Path) -> Path:
    """``<bag>_pws`` next to the bag (``talker.mcap`` -> ``talker_pws``)."""
    bag = Path(bag)
    name = bag.name if bag.is_dir() else bag.stem
    return bag.resolve().parent / f"{name}_pws"


def topic_name(namespace: str, rel: str) -> str:
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{rel}"


def _path_parts(topic: str) -> list[str]:
    return [p for p in topic.split("/") if p]


def _common_prefix(a: str, b: str) -> int:
    n = 0
    for x, y in zip(_path_parts(a), _path_parts(b)):
        if x != y:
            break
        n += 1
    return n


def _resolve_topic(bag: BagReader, name: str, msgtype: str, flag: str) -> str:
    cand = [name, "/" + name.lstrip("/")]
    found = next((c for c in cand if c in bag.topics), None)
    require(found is not None, f"{flag} {name}: no such topic in {bag.path} (it holds: {bag.describe()})")
    info = bag.topics[found]
    require(info.msgtype == msgtype, f"{flag} {found} is a {info.msgtype} topic, expected {msgtype}")
    require(info.decodable, f"{flag} {found} cannot be decoded: {info.skip_reason}")
    return found


def _config_topic(bag: BagReader, name: str, msgtype: str) -> str:
    """A config topic name if the bag has it with that type (relative names match the root namespace)."""
    if not name:
        return ""
    for c in (name, "/" + name.lstrip("/")):
        info = bag.topics.get(c)
        if info is not None and info.msgtype == msgtype and info.decodable:
            return c
    return ""


def discover_inputs(bag: BagReader, config: PwsConfig, overrides: dict[str, str] | None = None) -> InputTopics:
    """Choose the camera topics of ``bag``: ``overrides`` (``cloud``, ``depth``, ``color``, ``info``,
    ``depth_info``, ``truth``) first, then the config's topic names when the bag has them, then by
    message type (an organized PointCloud2; a depth + colour Image pair, preferring registered /
    aligned depth of the colour's size; the CameraInfo closest to the colour topic by name; a separate
    depth CameraInfo; for depth that is not registered, the depth -> colour extrinsic from the
    RealSense recorder's ``.../tf/<group>`` topics or ``/tf_static``, without which it is refused). An
    empty ``depth_info`` override, or an empty ``depth_camera_info_topic`` in the config, turns that check
    off (no depth CameraInfo)."""
    ov = {k: v for k, v in (overrides or {}).items() if v}
    no_depth_info = (overrides or {}).get("depth_info") == "" or ("depth_info" not in ov and config.depth_camera_info_topic == "")
    flags = {"cloud": "--cloud-topic", "depth": "--depth-topic", "color": "--color-topic", "info": "--info-topic",
             "depth_info": "--depth-info-topic", "truth": "--truth-topic"}
    types = {"cloud": T_POINTCLOUD2, "depth": T_IMAGE, "color": T_IMAGE, "info": T_CAMERA_INFO, "depth_info": T_CAMERA_INFO,
             "truth": T_DIAGNOSTIC_ARRAY}
    chosen: dict[str, str] = {}
    for role, name in ov.items():
        require(role in flags, f"unknown input role {role!r}")
        chosen[role] = _resolve_topic(bag, name, types[role], flags[role])
    notes: list[str] = []
    for role, name in (("cloud", config.points_topic), ("depth", config.depth_topic), ("color", config.color_topic),
                       ("info", config.camera_info_topic), ("depth_info", depth_info_topic(config))):
        if role not in chosen and not (role == "depth_info" and no_depth_info):
            t = _config_topic(bag, name, types[role])
            if t:
                chosen[role] = t
    if "cloud" in ov:
        mode = "pointcloud2"
    elif "depth" in ov or "color" in ov:
        mode = "rgbd"
    else:
        mode = config.input_mode

    clouds = bag.topics_of_type(T_POINTCLOUD2)
    images = bag.topics_of_type(T_IMAGE)
    infos = bag.topics_of_type(T_CAMERA_INFO)
    images = [t for t in images if not t.endswith("/" + outputs.PREVIEW)]
    peek_topics = [t for t in clouds + images + infos if bag.topics[t].count != 0]
    first = bag.first_messages(peek_topics, max_scan=20_000) if peek_topics else {}
    decoded: dict[str, Any] = {}
    for t, msgs in first.items():
        if msgs:
            try:
                decoded[t] = bag.deserialize(msgs[0])
            except PwsError as exc:
                notes.append(f"cannot decode the first message of {t}: {exc}")

    def size(t: str) -> tuple[int, int] | None:
        m = decoded.get(t)
        return (int(m.height), int(m.width)) if m is not None else None

    # -- point clouds --
    if "cloud" not in chosen and mode in ("auto", "pointcloud2"):
        organized = [t for t in clouds if t in decoded and int(decoded[t].height) > 1]

        def cscore(t: str) -> tuple:
            name = t.lower()
            return (-("registered" in name) - ("points" in name) - ("depth" in name), t)

        if organized:
            chosen["cloud"] = sorted(organized, key=cscore)[0]
            if len(organized) > 1:
                notes.append(f"several organized PointCloud2 topics ({', '.join(organized)}): using {chosen['cloud']} (--cloud-topic to choose)")
        elif mode == "pointcloud2" and clouds:
            chosen["cloud"] = sorted(clouds)[0]
            notes.append(f"no organized PointCloud2: using the unorganized {chosen['cloud']} (needs a CameraInfo)")

    # -- depth + colour --
    def encoding(t: str) -> str:
        m = decoded.get(t)
        return str(getattr(m, "encoding", "")).lower() if m is not None else ""

    if mode in ("auto", "rgbd") and not ("depth" in chosen and "color" in chosen):
        depths = [t for t in images if encoding(t) in DEPTH_ENCODINGS]
        colors = [t for t in images if encoding(t) in COLOR_ENCODINGS]
        if "depth" in chosen:
            depths = [chosen["depth"]]
        if "color" in chosen:
            colors = [chosen["color"]]
        best = None
        for d in depths:
            for c in colors:
                if d == c:
                    continue
                name = d.lower()
                score = (4 * (size(d) == size(c) and size(d) is not None) + 2 * ("aligned" in name or "registered" in name)
                         + 0.01 * _common_prefix(d, c))
                key = (-score, d, c)
                if best is None or key < best[0]:
                    best = (key, d, c)
        if best is not None:
            chosen.setdefault("depth", best[1])
            chosen.setdefault("color", best[2])
        elif mode == "rgbd" or not chosen.get("cloud"):
            if depths and not colors:
                notes.append(f"depth image {depths[0]} has no colour image topic beside it")
            elif colors and not depths:
                notes.append(f"colour image {colors[0]} has no depth image topic beside it")

    # -- camera info --
    ref = chosen.get("color") or chosen.get("cloud", "")
    if "info" not in chosen and ref and infos:
        want = size(ref)
        cands = [t for t in infos if t != chosen.get("depth_info")]
        cands.sort(key=lambda t: (-(size(t) == want and want is not None), -_common_prefix(t, ref), t))
        if cands and (chosen.get("color") or size(cands[0]) == want):
            chosen["info"] = cands[0]
        elif cands:
            notes.append(f"no CameraInfo of the cloud's size {want[1] if want else '?'}x{want[0] if want else '?'}: "
                         f"intrinsics are estimated from the organized cloud")
    if "depth_info" not in chosen and chosen.get("depth") and chosen.get("info") and not no_depth_info:
        d, c = chosen["depth"], chosen["color"]
        cands = [t for t in infos if t != chosen["info"] and _common_prefix(t, d) > _common_prefix(t, c)]
        cands.sort(key=lambda t: (-_common_prefix(t, d), t))
        if cands:
            chosen["depth_info"] = cands[0]

    # -- depth -> colour extrinsic, for depth that is not registered --
    extrinsic, extrinsic_from = None, ""
    if mode != "pointcloud2" and all(chosen.get(k) in decoded for k in ("depth", "color", "info")):
        extrinsic, extrinsic_from = _find_extrinsic(bag, chosen, decoded, config, notes)

    # -- ground truth --
    if "truth" not in chosen:
        diag = bag.topics_of_type(T_DIAGNOSTIC_ARRAY)
        if GROUND_TRUTH_TOPIC in diag:
            chosen["truth"] = GROUND_TRUTH_TOPIC
        else:
            gt = [t for t in diag if t.rstrip("/").endswith("ground_truth")]
            if gt:
                chosen["truth"] = gt[0]

    has_cloud = bool(chosen.get("cloud"))
    has_rgbd = bool(chosen.get("depth") and chosen.get("color"))
    if mode == "auto":
        mode = "auto" if (has_cloud and has_rgbd) else ("pointcloud2" if has_cloud else "rgbd")
    if mode == "pointcloud2":
        require(has_cloud, _no_input_message(bag, "no PointCloud2 topic", notes))
    else:
        require(has_rgbd or has_cloud, _no_input_message(bag, "no organized PointCloud2 and no depth + colour Image pair", notes))
        require(has_rgbd, _no_input_message(bag, "no depth + colour Image pair", notes))
        require(bool(chosen.get("info")), f"no sensor_msgs/CameraInfo for the colour camera {chosen['color']} in {bag.path} "
                                          f"(it holds: {bag.describe()}); give one with --info-topic")
    return InputTopics(mode, chosen.get("cloud", ""), chosen.get("depth", "") if mode != "pointcloud2" else "",
                       chosen.get("color", "") if mode != "pointcloud2" else "", chosen.get("info", ""),
                       chosen.get("depth_info", "") if mode != "pointcloud2" else "", chosen.get("truth", ""), notes,
                       extrinsic, extrinsic_from)


def _find_extrinsic(bag: BagReader, chosen: dict[str, str], decoded: dict[str, Any], config: PwsConfig,
                    notes: list[str]) -> tuple[Extrinsic | None, str]:
    """The depth -> colour extrinsic when the first depth + colour pair is not registered: from the
    RealSense recorder's ``.../tf/<group>`` topics of both streams, else from ``/tf_static`` between
    the two images' frame ids. ``(None, "")`` when the pair is registered or nothing is found."""
    d, c = chosen["depth"], chosen["color"]
    dinfo = decoded.get(chosen.get("depth_info", ""))
    try:
        problem = msgconv.registration_problem(decoded[d], decoded[c], decoded[chosen["info"]], dinfo,
                                               require_same_frame=config.require_same_frame)
    except PwsError:
        return None, ""   # a bad CameraInfo: the input check says so
    if not problem:
        return None, ""
    if dinfo is None:
        notes.append(f"{problem}; registering it needs the depth camera's CameraInfo: none was found (--depth-info-topic)")
        return None, ""
    tried = []
    md, mc = REALSENSE_STREAM.match(d), REALSENSE_STREAM.match(c)
    if md and mc:
        tf_topics = set(bag.topics_of_type(T_TRANSFORM))
        for t_d in sorted(t for t in tf_topics if t.startswith(md.group(1) + "/tf/")):
            t_c = mc.group(1) + "/tf/" + t_d.rsplit("/", 1)[1]
            if t_c not in tf_topics:
                continue
            first = bag.first_messages([t_d, t_c], max_scan=20_000)
            try:
                ref_to_d, ref_to_c = (msgconv.extrinsic_from_transform(bag.deserialize(first[t][0])) for t in (t_d, t_c))
            except (PwsError, KeyError, IndexError) as exc:
                notes.append(f"cannot read the extrinsics {t_d} / {t_c}: {exc}")
                continue
            return ref_to_d.inverse().then(ref_to_c), f"{t_d} and {t_c} (RealSense recorder)"
        tried.append(f"no {md.group(1)}/tf/N + {mc.group(1)}/tf/N topics")
    dframe = str(decoded[d].header.frame_id or "").lstrip("/")
    cframe = str(decoded[c].header.frame_id or "").lstrip("/")
    if not (dframe and cframe and dframe != cframe):
        tried.append(f"the images' frame ids {dframe!r} and {cframe!r} do not name two frames to look up in TF")
    elif TF_STATIC_TOPIC not in bag.topics_of_type(T_TF_MESSAGE):
        tried.append(f"no {TF_STATIC_TOPIC} topic")
    else:
        edges = []
        for m in bag.messages([TF_STATIC_TOPIC]):
            try:
                edges += msgconv.transforms_from_tf_message(bag.deserialize(m))
            except (PwsError, AttributeError) as exc:
                notes.append(f"skipping a {TF_STATIC_TOPIC} message: {exc}")
        found = chain_transform(edges, dframe, cframe) if edges else None
        if found is not None:
            return found, f"{TF_STATIC_TOPIC} ({dframe!r} -> {cframe!r})"
        tried.append(f"no transform between {dframe!r} and {cframe!r} on {TF_STATIC_TOPIC}")
    notes.append(f"{problem}, and no depth -> colour extrinsic was found to register it ({'; '.join(tried)})")
    return None, ""


def _no_input_message(bag: BagReader, what: str, notes: list[str]) -> str:
    extra = f" ({'; '.join(notes)})" if notes else ""
    return (f"no camera input in {bag.path}: {what}{extra}; expected an organized sensor_msgs/PointCloud2, or a depth Image "
            f"(16UC1/mono16/32FC1) + a colour Image + a CameraInfo; the bag holds: {bag.describe()} "
            f"(choose topics with --cloud-topic, or --depth-topic --color-topic --info-topic)")


def load_ground_truth(bag: BagReader, topic: str, warn: Callable[[str], None]) -> dict[int, GroundTruth]:
    """``stamp_ns -> GroundTruth`` from a ``/pws/ground_truth`` DiagnosticArray topic."""
    out: dict[int, GroundTruth] = {}
    bad = 0
    for m in bag.messages([topic]):
        try:
            msg = bag.deserialize(m)
            status = list(msg.status)
            require(len(status) > 0, "empty DiagnosticArray")
            st = next((s for s in status if str(s.name) == "ground_truth"), status[0])
            values = {str(kv.key): str(kv.value) for kv in st.values}
            label = int(values["label"]) if values.get("label", "").lstrip("-").isdigit() else None
            stamp = msgconv.header_stamp_ns(msg)
            out[stamp] = GroundTruth(stamp, label, values.get("class_name", ""), values)
        except (PwsError, AttributeError, ValueError) as exc:
            bad += 1
            if bad == 1:
                warn(f"ground truth on {topic}: a message could not be read ({exc}); such frames have no ground truth")
    return out


class RealtimeScheduler:
    """The live node's online policy on recorded time: one worker and a one-item slot (LatestSlot).

    ``arrive(item, t)``: the worker, if free at ``t``, starts on ``item`` at once; if busy, ``item``
    waits in the slot, replacing (dropping) an older waiting item. ``process(item, start)`` runs an
    item and returns how long it took (seconds); the worker is busy until ``start + duration``.
    """

    def __init__(self, process: Callable[[Any, float], float], on_drop: Callable[[Any], None] | None = None):
        self.process = process
        self.on_drop = on_drop
        self.t_free = -math.inf
        self.pending: tuple[Any, float] | None = None
        self.dropped = 0
        self.processed = 0

    def _run(self, item: Any, start: float) -> None:
        self.processed += 1
        self.t_free = start + max(0.0, float(self.process(item, start)))

    def arrive(self, item: Any, t: float) -> None:
        if self.pending is not None and self.t_free <= t:
            waiting, t0 = self.pending
            self.pending = None
            self._run(waiting, max(self.t_free, t0))
        if self.t_free <= t and self.pending is None:
            self._run(item, t)
            return
        if self.pending is not None:
            self.dropped += 1
            if self.on_drop is not None:
                self.on_drop(self.pending[0])
        self.pending = (item, t)

    def finish(self) -> None:
        if self.pending is not None:
            waiting, t0 = self.pending
            self.pending = None
            self._run(waiting, max(self.t_free, t0))


def _stamp_of(msg: Any, log_time: int) -> int:
    header = getattr(msg, "header", None)
    if header is not None and getattr(header, "stamp", None) is not None:
        return msgconv.header_stamp_ns(msg)
    return int(log_time)


def stamp_ordered(bag: BagReader, roles: dict[str, str], warn: Callable[[str], None], *, window_ns: int = 500_000_000,
                  cap: int = 64, copy: Callable[[BagMessage], None] | None = None):
    """``(role, BagMessage, decoded, stamp_ns)`` of the input topics in header-stamp order.

    A bounded reorder buffer (stamps older than the newest seen minus ``window_ns`` or more than
    ``cap`` messages are released) sorts by (stamp, role priority, log time): at equal stamps
    CameraInfo goes before images, so a frame finds its CameraInfo. Undecodable messages are
    skipped with one warning per topic.
    """
    prio = {"truth": 0, "info": 1, "depth_info": 1, "color": 2, "depth": 3, "points": 4}
    by_topic: dict[str, list[str]] = {}
    for role, t in roles.items():
        by_topic.setdefault(t, []).append(role)
    heap: list[tuple] = []
    newest = -(2**63)
    seq = 0
    bad: Counter = Counter()
    for m in bag.messages(by_topic):
        if copy is not None:
            copy(m)
        try:
            msg = bag.deserialize(m)
        except PwsError as exc:
            bad[m.topic] += 1
            if bad[m.topic] == 1:
                warn(f"skipping undecodable message(s) on {m.topic}: {exc}")
            continue
        stamp = _stamp_of(msg, m.log_time_ns)
        for role in by_topic[m.topic]:
            heapq.heappush(heap, (stamp, prio.get(role, 9), m.log_time_ns, seq, role, m, msg))
            seq += 1
        newest = max(newest, stamp)
        while heap and (len(heap) > cap or heap[0][0] < newest - window_ns):
            item = heapq.heappop(heap)
            yield item[4], item[5], item[6], item[0]
    while heap:
        item = heapq.heappop(heap)
        yield item[4], item[5], item[6], item[0]


def _closest_gap_ms(a: list[int], b: list[int]) -> float | None:
    if not a or not b:
        return None
    b = sorted(b)
    best = math.inf
    for x in a:
        i = bisect.bisect_left(b, x)
        for j in (i - 1, i):
            if 0 <= j < len(b):
                best = min(best, abs(b[j] - x))
    return best / 1e6


# ---- the replay ---------------------------------------------------------------------------

class Replay:
    """One replay run (use :func:`replay`)."""

    def __init__(self, opts: ReplayOptions):
        self.opts = opts
        self.warnings: list[str] = []
        self.records: list[FrameRecord] = []
        self.bar: Any = None
        self._log_fn = opts.log
        self._seen_warn: Counter = Counter()
        self.problems: list[str] = []         # input problems (pre-flight checks, assembly errors)
        self.frames_seen = 0
        self.stamps: dict[str, list[int]] = {"depth": [], "color": [], "points": []}
        self.writer: BagWriter | None = None
        self.truth: dict[int, GroundTruth] = {}
        self._truth_stamps: list[int] = []
        self.stop = StopSignals()               # entered around the frame loop
        self._out_pending: list[tuple[str, Any, int]] = []   # the messages of the frame in flight
        self._committed = 0                     # records whose messages are in the bag

    # ---- logging ----
    def log(self, level: str, message: str) -> None:
        if level == "warn":
            self.warnings.append(message)
        if self._log_fn is not None:
            self._log_fn(level, message)
            return
        if level == "info" and self.opts.quiet:
            return
        if self.bar is not None:
            self.bar.clear()
        prefix = {"info": "pws replay: ", "warn": "pws replay: warning: ", "error": "pws replay: error: "}.get(level, "")
        print(prefix + message, file=sys.stderr, flush=True)

    def warn(self, message: str) -> None:
        self.log("warn", message)

    def warn_once(self, key: str, message: str) -> None:
        self._seen_warn[key] += 1
        if self._seen_warn[key] == 1:
            self.warn(message)

    # ---- set-up ----
    def _engine(self, config: PwsConfig, truth_ok: bool) -> Any:
        from .bridge.engine import FrameCertifier

        def engine_log(level: str, message: str) -> None:
            self.log(level if level in ("info", "warn", "error") else "info", message)

        self.regenerate = False
        if config.method == "pws" and not config.dense_cloud_path:
            try:
                from .sim import dense_cloud_for  # noqa: F401
            except ImportError:
                raise PwsError("method pws needs the entire scene cloud: set dense_cloud_path in the config "
                               "(pws_ros.sim, which regenerates it for recordings of the procedural world, is not available)") from None
            require(truth_ok, "method pws needs the entire scene cloud: this bag has no ground truth with scene_seed and view_index "
                              f"on {GROUND_TRUTH_TOPIC} to regenerate it and the config sets no dense_cloud_path; "
                              "use --method pws_of or pws_l (they need only the recorded frame)")
            config = replace(config, dense_cloud_path=SIM_DENSE_MARKER)
            self.regenerate = True
        engine = FrameCertifier(config, log=engine_log, model=self.opts.model, denoiser=self.opts.denoiser,
                                load=not self.regenerate)
        if self.regenerate:
            engine.model  # noqa: B018 - load the model now (a bad path fails before any work)
            engine.denoiser  # noqa: B018
        return engine

    def _truth_for(self, stamp: int) -> GroundTruth | None:
        if not self.truth:
            return None
        g = self.truth.get(stamp)
        if g is not None:
            return g
        tol = int(round(self.config.sync_tolerance_s * 1e9))
        i = bisect.bisect_left(self._truth_stamps, stamp)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(self._truth_stamps):
                d = abs(self._truth_stamps[j] - stamp)
                if d <= tol and (best is None or d < best[0]):
                    best = (d, self._truth_stamps[j])
        return self.truth[best[1]] if best else None

    def _dense_cloud(self, truth: GroundTruth | None) -> Any:
        from .sim import dense_cloud_for

        require(truth is not None, f"method pws: no ground truth for this frame on {GROUND_TRUTH_TOPIC} (scene_seed, view_index needed)")
        v = truth.values
        try:
            seed, view = int(v["scene_seed"]), int(v["view_index"])
            kw = {}
            if "width" in v and "height" in v:
                kw.update(width=int(v["width"]), height=int(v["height"]))
            if "samples_per_pixel" in v:
                kw["samples_per_pixel"] = float(v["samples_per_pixel"])
        except (KeyError, ValueError) as exc:
            raise PwsError(f"method pws: the ground truth lacks a valid {exc} to regenerate the scene cloud") from None
        return dense_cloud_for(seed, view, **kw)

    def _preflight(self, bag: BagReader, inputs: InputTopics) -> None:
        """Convert the first depth + colour pair to catch what would fail every frame (unregistered
        depth, different sizes) with one clear message up front."""
        if not (inputs.depth and inputs.color and inputs.info):
            return
        want = [t for t in (inputs.depth, inputs.color, inputs.info, inputs.depth_info) if t]
        first = bag.first_messages(want, max_scan=20_000)
        try:
            msgs = {t: bag.deserialize(v[0]) for t, v in first.items() if v}
        except PwsError as exc:
            self.problems.append(str(exc))
            return
        if not all(t in msgs for t in (inputs.depth, inputs.color, inputs.info)):
            return
        try:
            msgconv.cloud_from_rgbd(msgs[inputs.depth], msgs[inputs.color], msgs[inputs.info],
                                    msgs.get(inputs.depth_info) if inputs.depth_info else None,
                                    require_same_frame=self.config.require_same_frame, extrinsic=inputs.extrinsic)
        except PwsError as exc:
            self.problems.append(str(exc))
            self.warn(f"input check on the first depth + colour pair: {exc}")

    def _error_cert(self, axis: str, reason: str) -> Certificate:
        make = getattr(self.engine, "error_for", None) or getattr(self.engine, "_error")
        return make(axis, reason)

    # ---- output ----
    def _topic(self, rel: str) -> str:
        return topic_name(self.opts.namespace, rel)

    def _write(self, rel: str, msg: Any, stamp_ns: int) -> None:
        """Queue a message of the frame in flight (written by :meth:`_commit` when the frame is done)."""
        if self.writer is not None:
            self._out_pending.append((self._topic(rel), msg, max(0, int(stamp_ns))))

    def _commit(self) -> None:
        """Write the finished frame's messages and flush the bag, safe from SIGINT/SIGTERM."""
        with self.stop.section():
            if self.writer is not None:
                for topic, msg, stamp in self._out_pending:
                    self.writer.write(topic, msg, stamp)
                self.writer.flush()
            self._out_pending.clear()
            self._committed = len(self.records)

    def switches(self) -> outputs.OutputSwitches:
        """What the pipeline node would publish, less what the options leave out."""
        cfg, o = self.config, self.opts
        return outputs.OutputSwitches(cloud=o.write_cloud, markers=o.markers and cfg.publish_markers,
                                      poses=o.poses and cfg.publish_poses, preview=o.preview)

    def _emit(self, header: Any, certs: list[Certificate], stamp_ns: int, *, latency_ms: float, compute_ms: Any,
              frame: Any = None, result: Any = None) -> None:
        """Write one frame's outputs (:func:`~pws_ros.bridge.outputs.frame_outputs`) with log time = the source stamp."""
        for rel, msg in outputs.frame_outputs(self.types, header, certs, node_name=NODE_NAME, latency_ms=latency_ms,
                                              compute_ms=compute_ms, switches=self.switches(), frame=frame, result=result):
            self._write(rel, msg, stamp_ns)

    # ---- one frame ----
    def process(self, raw: RawFrame, start_s: float | None = None) -> tuple[FrameRecord, float]:
        """Convert and certify one frame, write its outputs; returns the record and the compute seconds."""
        cfg, T, engine = self.config, self.types, self.engine
        truth = self._truth_for(raw.stamp_ns)
        index = len(self.records)
        header = msgbuild.copy_header(T, raw.header)
        frame_id = str(getattr(raw.header, "frame_id", "") or "")
        dense = None
        dense_error = ""
        if self.regenerate:
            try:
                dense = self._dense_cloud(truth)
            except PwsError as exc:
                dense_error = str(exc)
        t0 = time.perf_counter()
        try:
            try:
                frame = convert(raw, cfg, self.assembler.fallback)
            except PwsError:
                raise
            except Exception as exc:  # a malformed message must not stop the replay
                raise PwsError(f"unexpected {type(exc).__name__} converting the frame: {' '.join(str(exc).split())[:160]}") from None
        except PwsError as exc:
            duration = time.perf_counter() - t0
            reason = f"input: {exc}"
            self.warn_once("input:" + str(exc), f"frame {raw.stamp_ns}: {reason}")
            certs = [self._error_cert(a, reason) for a in cfg.axes]
            rec = FrameRecord(index, raw.stamp_ns, frame_id, raw.source, certs, {a: 0.0 for a in cfg.axes},
                              1000.0 * duration, 1000.0 * duration, input_error=str(exc))
            self._finish_record(rec, truth)
            self._emit(header, certs, raw.stamp_ns, latency_ms=rec.latency_ms, compute_ms=0.0)
            return rec, duration
        if dense_error:
            duration = time.perf_counter() - t0
            certs = [self._error_cert(a, dense_error) for a in cfg.axes]
            result = None
        else:
            result = engine.process(frame.cloud, frame.intrinsics, raw.stamp_ns, dense_cloud=dense, frame_id=frame_id,
                                    preview_every=cfg.preview_every if self.opts.preview else 0)
            duration = time.perf_counter() - t0
            certs = result.certificates
        compute = result.compute_ms if result is not None else {a: 0.0 for a in cfg.axes}
        rec = FrameRecord(index, raw.stamp_ns, frame_id, raw.source, certs, dict(compute), 1000.0 * duration, 1000.0 * duration)
        if start_s is not None:  # realtime: published when the worker finishes
            cost = self.opts.cost_fn(rec) if self.opts.cost_fn is not None else duration
            duration = cost
            rec.latency_ms = 1000.0 * (start_s + cost - raw.stamp_ns / 1e9)
        self._finish_record(rec, truth)
        self._emit(header, certs, raw.stamp_ns, latency_ms=rec.latency_ms, compute_ms=compute, frame=frame, result=result)
        return rec, duration

    def _finish_record(self, rec: FrameRecord, truth: GroundTruth | None) -> None:
        if truth is not None:
            rec.truth_label, rec.truth_class = truth.label, truth.class_name
            names = set(getattr(self.engine.model, "class_names", []) or [])
            for c in rec.certificates:
                if c.status == STATUS_ERROR:
                    rec.correct[c.axis] = False
                elif truth.class_name and truth.class_name in names:
                    rec.correct[c.axis] = c.class_name == truth.class_name
                else:
                    rec.correct[c.axis] = truth.label is not None and int(c.label) == int(truth.label)
        self.records.append(rec)
        if self.bar is not None:
            self.bar.set_note(self._note(rec))  # drawn with the next update

    @staticmethod
    def _note(rec: FrameRecord) -> str:
        parts = []
        for c in rec.certificates:
            word = {"certified": "ok", "not_certified": "not cert.", "abstain": "abstain", "error": "error"}.get(c.status, c.status)
            parts.append(f"{c.axis} {word}")
        return "last: " + ", ".join(parts)

    # ---- run ----
    def run(self) -> ReplayResult:
        opts = self.opts
        t_wall = time.perf_counter()
        cfg = opts.config
        require(opts.max_frames is None or opts.max_frames >= 1, f"--max-frames must be >= 1, got {opts.max_frames}")
        bag_path = Path(opts.bag)
        require(bag_path.exists(), f"bag not found: {bag_path}")
        out = None
        if opts.write_output:
            out = Path(opts.out) if opts.out is not None else default_out(bag_path)
            require(out.resolve() != bag_path.resolve(), f"--out {out} is the input bag itself")
            require(not out.resolve().is_relative_to(bag_path.resolve()) if bag_path.is_dir() else True,
                    f"--out {out} lies inside the input bag directory")
            require(opts.overwrite or not out.exists(), f"output {out} already exists: choose another --out or pass --overwrite")
        with BagReader(bag_path, warn=self.warn) as bag:
            require(bool(bag.topics), f"bag {bag_path} is empty: it has no topics")
            require(bag.message_count != 0, f"bag {bag_path} holds no messages (topics: {bag.describe()})")
            inputs = discover_inputs(bag, cfg, opts.topics)
            for n in inputs.notes:
                self.warn(n)
            self.log("info", f"{bag_path}: {bag.storage}, {len(bag.topics)} topics, "
                             f"{bag.message_count if bag.message_count is not None else '?'} messages; {inputs.describe()}")
            cfg = replace(cfg, input_mode=inputs.mode if inputs.mode != "auto" else "auto",
                          depth_camera_info_topic=inputs.depth_info)
            self.config = cfg
            if inputs.truth:
                self.truth = load_ground_truth(bag, inputs.truth, self.warn)
                self._truth_stamps = sorted(self.truth)
            truth_ok = any("scene_seed" in g.values and "view_index" in g.values for g in self.truth.values())
            self.engine = self._engine(cfg, truth_ok)
            self.types = msgbuild.rosbags_types()
            self._preflight(bag, inputs)
            if self.problems and inputs.mode == "auto" and inputs.points:
                self.warn(f"depth + colour cannot be used ({self.problems[-1]}); using the point cloud {inputs.points} instead")
                inputs = replace(inputs, mode="pointcloud2", depth="", color="", depth_info="")
                cfg = replace(cfg, input_mode="pointcloud2", depth_camera_info_topic="")
                self.config = cfg
                self.problems.clear()
            self.assembler = InputAssembler(cfg)
            self.assembler.set_extrinsic(inputs.extrinsic)
            if out is not None:
                prepare_output(out, opts.overwrite)
                self.writer = BagWriter(out, compress=opts.compress, typestore=self.types.typestore).open()
            interrupted = ""
            with self.stop:  # until the bag is closed: a second signal cannot cut the clean-up
                try:
                    scheduler = self._loop(bag, inputs)
                except KeyboardInterrupt as exc:
                    interrupted = exc.signame if isinstance(exc, Interrupted) else "SIGINT"
                    scheduler = None
                    # the frame in flight is dropped whole: its record goes with its unwritten messages
                    del self.records[self._committed:]
                    self._out_pending.clear()
                    self.warn(f"interrupted ({interrupted}): the frame in flight is dropped; closing the bag with the "
                              f"{len(self.records)} frame(s) done")
                finally:
                    with self.stop.section():
                        if self.bar is not None:
                            self.bar.close()
                        counts = {}
                        if self.writer is not None:
                            counts = dict(self.writer.counts)
                            self.writer.close()
                            if not counts:
                                import shutil

                                shutil.rmtree(out, ignore_errors=True)
                                out = None
            dropped = scheduler.dropped if scheduler is not None else 0
            extra_frames = {"unmatched_inputs": self.assembler.dropped, "ignored_inputs": self.assembler.ignored}
            bag_info = {"path": str(bag_path), "storage": bag.storage, "layout": bag.layout, "backend": bag.backend,
                        "messages": bag.message_count, "recovered_files": bag.recovered}
        wall = time.perf_counter() - t_wall
        summary = self._summary(inputs, out, dropped, wall, extra_frames, bag_info, counts)
        exit_code, message = self._verdict(inputs)
        summary["interrupted"] = interrupted or None
        if interrupted:
            summary["title"] += f" (interrupted by {interrupted})"
            exit_code = Interrupted(interrupted).exit_code
            message = f"stopped by {interrupted} after {len(self.records)} frame(s); the output and summary cover those"
        summary["exit_code"] = exit_code
        if message:
            summary["message"] = message
        result = ReplayResult(self.records, summary, out, exit_code, message, list(self.warnings), output_counts=counts)
        if opts.report_dir is not None:
            result.report_files = write_report(opts.report_dir, self.records, summary, cfg.axes)
        return result

    def _loop(self, bag: BagReader, inputs: InputTopics) -> RealtimeScheduler | None:
        opts = self.opts
        roles = inputs.roles()
        roles.pop("truth", None)
        if inputs.mode == "rgbd":
            roles.pop("points", None)
        total_topic = inputs.color if inputs.mode in ("rgbd", "auto") else inputs.points
        total = bag.topics[total_topic].count if total_topic in bag.topics else None
        if opts.max_frames is not None:
            total = min(total, opts.max_frames) if total else opts.max_frames
        mode = None if opts.progress is None else ("bar" if opts.progress else "off")
        if opts.quiet or (opts.log is not None and mode is None):
            mode = "off" if opts.quiet else "log"
        self.bar = Progress(total, label="pws replay", mode=mode, interval_s=opts.progress_interval_s,
                            emit=lambda line: self.log("info", line))

        scheduler = None
        if opts.realtime:
            def run_one(raw: RawFrame, start: float) -> float:
                _rec, duration = self.process(raw, start_s=start)
                self._commit()
                return duration

            scheduler = RealtimeScheduler(run_one, on_drop=lambda raw: None)

        copy = None
        if opts.copy_inputs and self.writer is not None:
            copy_topics = set(inputs.roles().values())

            def copy(m: BagMessage) -> None:
                if m.topic in copy_topics:
                    with self.stop.section():
                        self.writer.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, bag.typestore_for(m.msgtype))

            if inputs.truth:  # the ground truth is not an input of the loop: copy it here
                for m in bag.messages([inputs.truth]):
                    copy(m)

        handlers = {"points": self.assembler.on_points, "depth": self.assembler.on_depth, "color": self.assembler.on_color,
                    "info": self.assembler.on_info, "depth_info": self.assembler.on_depth_info}
        for role, m, msg, stamp in stamp_ordered(bag, roles, self.warn, copy=copy):
            if role in self.stamps:
                self.stamps[role].append(stamp)
            try:
                raw = handlers[role](msg)
            except PwsError as exc:
                self.problems.append(str(exc))
                self.warn_once("assemble:" + str(exc), f"input: {exc}")
                continue
            if raw is None:
                continue
            self.frames_seen += 1
            if self.assembler.locked_source and total_topic and inputs.mode == "auto":
                t = inputs.points if self.assembler.locked_source == "pointcloud2" else inputs.color
                if t in bag.topics and bag.topics[t].count:
                    self.bar.set_total(min(bag.topics[t].count, opts.max_frames or bag.topics[t].count))
            if scheduler is not None:
                scheduler.arrive(raw, raw.stamp_ns / 1e9)
            else:
                self.process(raw)
                self._commit()
            self.bar.update(1)
            if opts.max_frames is not None and self.frames_seen >= opts.max_frames:
                break
        if scheduler is not None:
            scheduler.finish()
        return scheduler

    def _summary(self, inputs: InputTopics, out: Path | None, dropped: int, wall: float, extra_frames: dict,
                 bag_info: dict, counts: dict) -> dict[str, Any]:
        cfg = self.config
        axes = list(cfg.axes)
        s = summarize(self.records, axes=axes, units={a: UNITS[a] for a in axes}, requested={a: cfg.radius_for(a) for a in axes},
                      frames_seen=self.frames_seen, dropped=dropped, wall_s=wall)
        s["frames"].update(extra_frames)
        s["title"] = f"pws replay {bag_info['path']}" + (f" -> {out}" if out else " (no output bag)")
        coverage = f"coverage {cfg.coverage}, " if cfg.method != "cms" else ""  # cms has no coverage rule
        s["setup"] = (f"method {cfg.method}, {coverage}imaging {cfg.imaging}, sigma {cfg.sigma:g}, n0 {cfg.n0}, n {cfg.n}, "
                      f"risk alpha {cfg.alpha:g} per frame ({cfg.alpha / max(1, len(axes)):g} per axis), "
                      f"seed {cfg.seed}, device {self.engine.device}, {'realtime policy' if self.opts.realtime else 'every frame'}; "
                      + inputs.describe())
        s["bag"] = bag_info
        s["out"] = str(out) if out else None
        s["output_topics"] = counts
        s["inputs"] = {"mode": inputs.mode, **inputs.roles()}
        s["config"] = {"method": cfg.method, "coverage": cfg.coverage if cfg.method != "cms" else None, "axes": axes, "radius": {a: cfg.radius_for(a) for a in axes},
                       "imaging": cfg.imaging, "sigma": cfg.sigma, "n0": cfg.n0, "n": cfg.n, "alpha": cfg.alpha,
                       # the risk of each frame's whole statement (all axes), and what each axis spends of it
                       "frame_alpha": cfg.alpha, "alpha_per_axis": cfg.alpha / max(1, len(axes)),
                       "num_anchors": cfg.num_anchors, "seed": cfg.seed, "device": self.engine.device,
                       "batch_size": cfg.batch_size, "model_path": cfg.model_path, "realtime": self.opts.realtime,
                       "dense_cloud": cfg.dense_cloud_path if cfg.method == "pws" else None}
        s["warnings"] = list(self.warnings)
        return s

    def _verdict(self, inputs: InputTopics) -> tuple[int, str]:
        done = any(c.status != STATUS_ERROR for r in self.records for c in r.certificates)
        if done:
            return 0, ""
        problems = list(dict.fromkeys(self.problems))
        if not self.records:
            why = []
            if problems:
                why.append(problems[0])
            if inputs.mode in ("rgbd", "auto") and inputs.depth:
                gap = _closest_gap_ms(self.stamps["depth"], self.stamps["color"])
                tol = self.config.sync_tolerance_s * 1000.0
                if not self.stamps["depth"] or not self.stamps["color"]:
                    why.append(f"no {'depth' if not self.stamps['depth'] else 'colour'} message could be read")
                elif gap is not None and gap > tol:
                    why.append(f"depth and colour stamps never came within sync_tolerance_s = {self.config.sync_tolerance_s:g} s "
                               f"(closest pair {gap:.1f} ms apart; see --sync-tolerance)")
            if inputs.mode in ("pointcloud2", "auto") and inputs.points and not self.stamps["points"]:
                why.append(f"no message on {inputs.points} could be read")
            return 2, "nothing could be certified: no complete input frame" + (": " + "; ".join(why) if why else "")
        reasons = Counter(c.reason for r in self.records for c in r.certificates)
        top, n = reasons.most_common(1)[0]
        head = problems[0] if problems and all(r.input_error for r in self.records) else top
        return 2, f"nothing could be certified: every frame failed ({len(self.records)} frame(s)): {head}"


def replay(options: ReplayOptions) -> ReplayResult:
    """Run a replay (see the module docstring). PwsError for what stops it before any frame."""
    return Replay(options).run()


__all__ = ["GroundTruth", "InputTopics", "RealtimeScheduler", "ReplayOptions", "ReplayResult", "default_out",
           "discover_inputs", "load_ground_truth", "replay", "stamp_ordered", "topic_name"]

"""Pieces shared by the node modules. No rclpy import at module level: rclpy enters only through
:mod:`._ros`, imported inside :func:`start`, so every node module imports where ROS is absent.
:mod:`._ros` itself imports only :mod:`._base` (no import circle)."""
from __future__ import annotations

import importlib.util
import sys
import time
from typing import Any, Callable, NoReturn

from ..bridge import msgbuild, msgconv, outputs
from ..bridge.config import depth_info_topic
from ..bridge.inputs import InputAssembler, RawFrame
from ..core.errors import PwsError
from ..core.registration import Extrinsic, chain_transform
from ._base import TF_MESSAGE_TYPE, ShutdownSafePublisher, Worker, WorkerNode, still_running_workers  # noqa: F401 - re-exported

ROS_MISSING = ("rclpy (ROS 2 Jazzy) is not importable: install ROS 2 Jazzy and `source /opt/ros/jazzy/setup.bash` "
               "(then build this package with colcon); without ROS use the `pws` command")


def rclpy_available() -> bool:
    return importlib.util.find_spec("rclpy") is not None


def start(node_name: str, logic_class: Callable[..., Any], args: list[str] | None = None) -> int:
    """Run a node (``logic_class(ctx)`` around a :class:`._ros.NodeContext`); exit status 2 with a
    clear message when rclpy is missing or the start-up fails with PwsError."""
    if not rclpy_available():
        print(f"{node_name}: {ROS_MISSING}", file=sys.stderr)
        return 2
    from . import _ros

    return _ros.run(node_name, lambda node: logic_class(_ros.NodeContext(node, node_name)), args)


def entry_point(node_name: str, logic_class: Callable[..., Any]) -> Callable[[list[str] | None], NoReturn]:
    """A node's console script (setup.py's ``<node> = pws_ros.nodes.<node>:main``): runs
    :func:`start` and exits with its status."""
    def main(args: list[str] | None = None) -> NoReturn:
        sys.exit(start(node_name, logic_class, args))

    main.__doc__ = f"Run the {node_name} node (exit status 2 on a start-up error)."
    return main


class PosePublishers:
    """The ``plan/poses/<axis>`` publishers, created for the configured axes up front and on a
    parameter change (in executor callbacks), never from a worker thread, which may still run
    after shutdown began (creating a publisher then fails)."""

    def __init__(self, ctx: Any):
        self.ctx = ctx
        self.pubs: dict[str, Any] = {}
        self.update(ctx.config)

    def update(self, cfg: Any) -> None:
        for axis in cfg.axes:
            if axis not in self.pubs:
                self.pubs[axis] = self.ctx.publisher(self.ctx.types.PoseArray, f"plan/poses/{axis}")

    def publish(self, axis: str, msg: Any) -> None:
        pub = self.pubs.get(axis)
        if pub is not None:
            pub.publish(msg)


def stage_engine(ctx: Any, *, input_size: bool = False) -> Any:
    """The FrameCertifier of a four-process stage that needs no classifier: what the stage reads is read
    now (the model's input size with ``input_size``, the dense cloud of method pws), so a bad file is a
    PwsError at start-up (exit 2)."""
    from ..bridge.engine import FrameCertifier

    engine = FrameCertifier(ctx.config, log=ctx.log, load=False)
    if input_size:
        engine.render_size  # noqa: B018
    if ctx.config.method == "pws":
        engine.dense_cloud  # noqa: B018
    return engine


def jump_logger(ctx: Any) -> Callable[[str], None]:
    """The ``on_time_jump`` callback of the bridge's matchers: one WARN per jump back in time."""
    return lambda text: ctx.log("warn", text)


class Throttle:
    """Log a repeated message at most once per ``period`` seconds (with the number suppressed)."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self._last: dict[str, float] = {}
        self._count: dict[str, int] = {}

    def __call__(self, log: Callable[[str, str], None], level: str, message: str, key: str | None = None) -> None:
        key = key or message
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period:
            n = self._count.pop(key, 0)
            log(level, message + (f" (and {n} more like it)" if n else ""))
            self._last[key] = now
        else:
            self._count[key] = self._count.get(key, 0) + 1


def guarded(ctx: Any, throttle: "Throttle", topic: str, fn: Callable[[Any], None],
            on_bad: Callable[[Any, str], None] | None = None) -> Callable[[Any], None]:
    """A subscription callback that never raises: a malformed message (PwsError) or any other failure
    of ``fn`` is one throttled WARN naming the topic and the problem (a failure that is not a PwsError
    also names its type: a bug to report), then ``on_bad(msg, text)`` (e.g. count it). Any process on
    the graph may publish on a node's topics; a callback that raises would end the node's spin."""
    def cb(msg: Any) -> None:
        try:
            fn(msg)
            return
        except PwsError as exc:
            text = " ".join(str(exc).split())
        except Exception as exc:  # noqa: BLE001 - keep the node alive, and say what happened
            text = f"unexpected {type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
        try:
            throttle(ctx.log, "warn", f"{topic}: ignoring a message: {text}", key=f"bad:{topic}")
            if on_bad is not None:
                on_bad(msg, text)
        except Exception:  # noqa: BLE001 - a failing logger must not end the spin either
            pass
    return cb


TF_STATIC_TOPIC = "/tf_static"


class StaticExtrinsic:
    """The depth -> colour extrinsic from ``/tf_static`` for depth that is not registered to the
    colour camera (a RealSense driver without ``align_depth``): the transform between the two images'
    frame ids through the static TF tree, handed to the assembler, which then registers depth into
    the colour camera (:func:`~pws_ros.core.registration.register_depth`). As in tf2's static buffer,
    the newest transform of each child frame replaces the older one. Said once in the log (and again
    if it changes); while none is known, unregistered depth is refused as before."""

    def __init__(self, assembler: InputAssembler, log: Callable[[str, str], None]):
        self.assembler = assembler
        self.log = log
        self.edges: dict[str, tuple[str, Extrinsic]] = {}   # child frame -> (parent frame, child -> parent)
        self.frames = {"depth": "", "color": ""}
        self.extrinsic: Extrinsic | None = None
        self.messages = 0

    def on_tf_static(self, msg: Any) -> None:
        self.messages += 1
        for parent, child, T in msgconv.transforms_from_tf_message(msg):  # PwsError when malformed
            self.edges[child] = (parent, T)
        self._resolve()

    def saw(self, stream: str, msg: Any) -> None:
        """Note the frame id of a depth or colour image (looked up again when it changes)."""
        frame = str(msg.header.frame_id or "").lstrip("/")
        if frame != self.frames[stream]:
            self.frames[stream] = frame
            self._resolve()

    def _resolve(self) -> None:
        d, c = self.frames["depth"], self.frames["color"]
        if not (d and c and d != c and self.edges):
            return
        found = chain_transform([(p, child, T) for child, (p, T) in self.edges.items()], d, c)
        if found is None or (self.extrinsic is not None and self._same(found, self.extrinsic)):
            return
        found = Extrinsic(found.rotation, found.translation, f"{TF_STATIC_TOPIC}: {d!r} -> {c!r}")
        self.extrinsic = found
        self.assembler.set_extrinsic(found)
        self.log("info", f"depth frame {d!r} is not the colour frame {c!r}: depth is registered into the colour camera "
                         f"with the extrinsic {found.describe()}")

    @staticmethod
    def _same(a: Extrinsic, b: Extrinsic) -> bool:
        return bool((a.rotation == b.rotation).all() and (a.translation == b.translation).all())


class HealthPublisher:
    """Publishes ``<node>: health`` on ``/diagnostics`` every ``health_period_s``. A certifying node
    (``certifying``) tells it each frame it published (:meth:`published`): its ``labels``
    (:class:`~pws_ros.bridge.outputs.CertifiedLabelWatch`) give a WARN past ``certified_label_timeout_s``
    and their keys; with ``certification_to_diagnostics`` the frame's certification also goes out on
    ``/diagnostics``. ``overlay`` (:class:`OverlayOutput`) adds its keys."""

    def __init__(self, ctx: Any, counters: Callable[[], dict[str, Any]], *, certifying: bool = False, overlay: Any = None):
        self.ctx = ctx
        self.counters = counters
        self.labels = outputs.CertifiedLabelWatch() if certifying else None
        self.overlay = overlay
        self.pub = ctx.publisher(ctx.types.DiagnosticArray, "/diagnostics", kind="reliable", depth=10)
        self.timer = ctx.timer(ctx.config.health_period_s, self.publish)

    def published(self, frame_outputs: list[tuple[str, Any]]) -> None:
        """A frame's :func:`~pws_ros.bridge.outputs.frame_outputs`, just published."""
        if self.labels is not None:
            self.labels.saw(frame_outputs)
        if self.ctx.config.certification_to_diagnostics:
            for rel, msg in frame_outputs:
                if rel == outputs.CERTIFICATION:
                    self.pub.publish(msg)

    def publish(self) -> None:
        c = dict(self.counters())
        extra = c.pop("extra", {})
        if self.labels is not None:
            late = self.labels.warning(self.ctx.config.certified_label_timeout_s)
            c["warning"] = "; ".join(t for t in (c.get("warning", ""), late) if t)
            extra = {**extra, **self.labels.counters()}
        if self.overlay is not None:
            extra = {**extra, **self.overlay.counters()}
        extra = {**extra, "qos_incompatible_events": self.ctx.qos_events}
        hdr = msgbuild.make_header(self.ctx.types, max(0, self.ctx.now_ns()), "")
        msg = msgbuild.health_status(hdr, node_name=self.ctx.name, types=self.ctx.types, extra=extra, **c)
        self.pub.publish(msg)


class OverlayOutput:
    """``certification/overlay`` (``publish_overlay``): the overlay picture of each certified frame
    (:func:`~pws_ros.bridge.overlay.draw_overlay`: the classifier's α = 0 view, label, p_A, a bar per axis),
    drawn and published at the frame's header by a :class:`Worker` of its own after the frame's
    certification is out. Its slot holds the newest frame only: a frame whose overlay is not drawn before
    the next certification comes is skipped (``overlays_skipped``), never queued, and the certification
    worker never waits for it. The publisher and the thread are made when the parameter is first on (at
    start or on a change, in a callback), never from a worker thread."""

    def __init__(self, ctx: Any):
        self.ctx = ctx
        self.pub: Any = None
        self.worker: Worker | None = None
        self.failed = 0
        self.update(ctx.config)

    def update(self, cfg: Any) -> None:
        if cfg.publish_overlay and self.pub is None:
            from ..bridge.overlay import draw_overlay

            draw_overlay(None, [])   # OpenCV's first drawing (about 50 ms) now, not beside the first frame
            self.pub = self.ctx.publisher(self.ctx.types.Image, outputs.OVERLAY)
            self.worker = Worker("pws-overlay", self._draw, self.ctx.log)

    def submit(self, header: Any, stamp_ns: int, certificates: list[Any], view: Callable[[], Any]) -> None:
        """Hand a published frame over: ``view()`` (called in the overlay thread) gives its α = 0 frame or None."""
        if self.worker is not None and self.ctx.config.publish_overlay:
            self.worker.submit((header, int(stamp_ns), list(certificates), view))

    def _draw(self, job: tuple[Any, int, list[Any], Callable[[], Any]]) -> None:
        from ..bridge.overlay import draw_overlay

        header, stamp_ns, certs, view = job
        try:
            image = view()
        except Exception as exc:  # noqa: BLE001 - the picture goes out without its view, the reason in the log
            self.failed += 1
            image = None
            self.ctx.log("warn", f"overlay of frame {stamp_ns}: no view ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})")
        self.pub.publish(msgbuild.image_from_numpy(header, draw_overlay(image, certs, stamp_ns), self.ctx.types))

    def counters(self) -> dict[str, Any]:
        """The health status' keys (when the overlay was ever on)."""
        if self.worker is None:
            return {}
        return {"overlays_published": self.worker.processed, "overlays_skipped": self.worker.slot.dropped}

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()


class InputFrontend:
    """Subscribes to the configured camera inputs and hands each complete :class:`RawFrame` to
    ``on_frame`` (callbacks only buffer; conversion happens in the consumer's worker)."""

    def __init__(self, ctx: Any, on_frame: Callable[[RawFrame], None]):
        self.ctx = ctx
        self.on_frame = on_frame
        cfg = ctx.config
        self.assembler = InputAssembler(cfg)
        self.assembler.matcher.on_time_jump = jump_logger(ctx)
        self.throttle = Throttle()
        self.received = 0
        self._distortion_noted: set[tuple[str, str]] = set()
        T = ctx.types
        self.subs = []
        mode = cfg.input_mode
        if mode in ("auto", "pointcloud2"):
            self.subs.append(ctx.subscription(T.PointCloud2, cfg.points_topic, self._wrap(self.assembler.on_points, topic=cfg.points_topic)))
        self.static_tf = StaticExtrinsic(self.assembler, ctx.log)
        if mode in ("auto", "rgbd"):
            self.subs.append(ctx.subscription(T.Image, cfg.depth_topic, self._wrap(self.assembler.on_depth, "depth", cfg.depth_topic)))
            self.subs.append(ctx.subscription(T.Image, cfg.color_topic, self._wrap(self.assembler.on_color, "color", cfg.color_topic)))
            # the depth -> colour extrinsic of unregistered depth (latched: reliable, transient local);
            # rclpy_types always has TFMessage, an in-memory test context may leave it out
            if getattr(T, "TFMessage", None) is not None:
                self.subs.append(ctx.subscription(T.TFMessage, TF_STATIC_TOPIC, self._on_tf_static, kind="tf_static", depth=100))
            elif getattr(T, "flavour", "") == "rclpy":
                ctx.log("warn", f"tf2_msgs is not installed: {TF_STATIC_TOPIC} is not read, so depth not registered to the colour "
                                "camera cannot be registered from its extrinsic (install ros-jazzy-tf2-msgs)")
        # CameraInfo is needed by both modes (optional for organized clouds)
        self.subs.append(ctx.subscription(T.CameraInfo, cfg.camera_info_topic,
                                          self._wrap(self.assembler.on_info, topic=cfg.camera_info_topic, info=True)))
        dinfo = depth_info_topic(cfg) if mode in ("auto", "rgbd") else ""
        if dinfo:  # refuses depth whose camera is not the colour camera's (not registered)
            self.subs.append(ctx.subscription(T.CameraInfo, dinfo, self._wrap(self.assembler.on_depth_info, topic=dinfo, info=True)))
        topics = ([cfg.points_topic] if mode != "rgbd" else []) + ([cfg.depth_topic, cfg.color_topic] if mode != "pointcloud2" else [])
        ctx.log("info", f"input mode {mode}: listening on {', '.join(ctx.resolve(t) for t in topics)} "
                        f"+ {ctx.resolve(cfg.camera_info_topic)}" + (f" (depth camera info {ctx.resolve(dinfo)})" if dinfo else ""))

    def _on_tf_static(self, msg: Any) -> None:
        try:
            self.static_tf.on_tf_static(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed /tf_static message must not end the spin
            text = str(exc) if isinstance(exc, PwsError) else f"unexpected {type(exc).__name__}: {exc}"
            self.throttle(self.ctx.log, "warn", f"{TF_STATIC_TOPIC}: {text}", key=TF_STATIC_TOPIC)

    def _note_camera_info(self, topic: str, msg: Any) -> None:
        """Say once per topic and distortion model what the imaging does with a CameraInfo's distortion."""
        note = msgconv.distortion_note(msg)
        key = (topic, str(getattr(msg, "distortion_model", "")))
        if note and key not in self._distortion_noted and len(self._distortion_noted) < 64:
            self._distortion_noted.add(key)
            self.ctx.log("warn", f"{topic}: {note}")

    def _wrap(self, handler: Callable[[Any], RawFrame | None], image: str = "", topic: str = "input",
              info: bool = False) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            self.received += 1
            try:
                if image:
                    self.static_tf.saw(image, msg)
                if info:
                    self._note_camera_info(topic, msg)
                frame = handler(msg)
            except Exception as exc:  # noqa: BLE001 - a malformed message must never end the spin
                text = str(exc) if isinstance(exc, PwsError) else f"unexpected {type(exc).__name__}: {exc}"
                self.throttle(self.ctx.log, "warn", f"{topic}: ignoring a message: {text}", key=f"input:{topic}")
                return
            if frame is None and image and self.assembler.waiting_for_info:
                self.throttle(self.ctx.log, "warn", f"input: a depth + colour pair waits for {self.assembler.waiting_for()}; "
                                                    "nothing is certified until it arrives", key="waiting_for_info")
            if frame is not None:
                if self.assembler.frames == 1:
                    self.ctx.log("info", f"first input frame from {frame.source}")
                skew = self.assembler.skew_warning(frame)
                if skew:
                    self.throttle(self.ctx.log, "warn", f"input: {skew}", key="sync_skew")
                self.on_frame(frame)
        return cb

    @property
    def dropped(self) -> int:
        return self.assembler.dropped

    @property
    def time_jumps(self) -> int:
        return self.assembler.matcher.time_jumps

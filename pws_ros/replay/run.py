"""One replay run: set-up, the frame loop, one frame's outputs, interruption (see :mod:`pws_ros.replay`)."""
from __future__ import annotations

import sys
import time
from importlib import import_module
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from ..bagio import BagMessage, BagReader, BagWriter, prepare_output
from ..bridge import msgbuild, msgconv, outputs
from ..bridge.config import PwsConfig
from ..bridge.inputs import InputAssembler, RawFrame, convert
from ..core.errors import PwsError, require
from ..core.result import STATUS_ERROR, Certificate
from .interrupt import Interrupted, StopSignals
from .progress_log import Progress
from .report import FrameRecord, write_report
from .discovery import discover_inputs
from .options import GROUND_TRUTH_TOPIC, NODE_NAME, SIM_DENSE_MARKER, GroundTruth, InputTopics, ReplayOptions, ReplayResult, \
    default_out, topic_name
from .schedule import RealtimeScheduler, stamp_ordered
from .summary import replay_summary, replay_verdict
from .truth import dense_cloud_of, load_ground_truth, truth_near
from .video import OverlayVideo, overlay_picture


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
        self.video: OverlayVideo | None = None  # --video: the overlay picture of every frame

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
        label = self.opts.label
        prefix = {"info": f"{label}: ", "warn": f"{label}: warning: ", "error": f"{label}: error: "}.get(level, "")
        print(prefix + message, file=sys.stderr, flush=True)

    def warn(self, message: str) -> None:
        self.log("warn", message)

    def warn_once(self, key: str, message: str) -> None:
        self._seen_warn[key] += 1
        if self._seen_warn[key] == 1:
            self.warn(message)

    # ---- set-up ----
    def _engine(self, config: PwsConfig, truth_ok: bool) -> Any:
        from ..bridge.engine import FrameCertifier

        def engine_log(level: str, message: str) -> None:
            self.log(level if level in ("info", "warn", "error") else "info", message)

        self.regenerate = False
        if config.method == "pws" and not config.dense_cloud_path:
            try:
                import_module("pws_ros.sim")
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
        return truth_near(self.truth, self._truth_stamps, stamp, self.config.sync_tolerance_s)

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
            if self.video is not None:
                self.video.commit()
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
                dense = dense_cloud_of(truth)
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
            self._hold_overlay(certs, raw.stamp_ns)
            return rec, duration
        if dense_error:
            duration = time.perf_counter() - t0
            certs = [self._error_cert(a, dense_error) for a in cfg.axes]
            result = None
        else:
            result = engine.process(frame.cloud, frame.intrinsics, raw.stamp_ns, dense_cloud=dense, frame_id=frame_id,
                                    preview_every=cfg.preview_every if self.opts.preview else 0)
            duration = time.perf_counter() - t0 - result.timings.get("startup", 0.0)   # start-up work is not the frame's
            certs = result.certificates
        compute = result.compute_ms if result is not None else {a: 0.0 for a in cfg.axes}
        rec = FrameRecord(index, raw.stamp_ns, frame_id, raw.source, certs, dict(compute), 1000.0 * duration, 1000.0 * duration)
        rec.startup_ms = 1000.0 * result.timings.get("startup", 0.0) if result is not None else 0.0
        if start_s is not None:  # realtime: published when the worker finishes
            cost = self.opts.cost_fn(rec) if self.opts.cost_fn is not None else duration
            duration = cost
            rec.latency_ms = 1000.0 * (start_s + cost - raw.stamp_ns / 1e9)
        self._finish_record(rec, truth)
        self._emit(header, certs, raw.stamp_ns, latency_ms=rec.latency_ms, compute_ms=compute, frame=frame, result=result)
        self._hold_overlay(certs, raw.stamp_ns, result, frame.cloud, dense)
        return rec, duration

    def _hold_overlay(self, certs: list[Certificate], stamp_ns: int, result: Any = None, cloud: Any = None, dense: Any = None) -> None:
        """``--video``: the frame's overlay picture, written with its messages (:meth:`_commit`)."""
        if self.video is not None:
            self.video.hold(overlay_picture(self.engine, certs, stamp_ns, result, cloud, dense, self.warn_once), stamp_ns)

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
        if opts.video is not None:
            self.video = OverlayVideo(opts.video, overwrite=opts.overwrite, fps=opts.video_fps)
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
                    if self.video is not None:
                        self.video.discard()
                    self.warn(f"interrupted ({interrupted}): the frame in flight is dropped; "
                              + ("closing the bag with the " if self.writer is not None else "")
                              + f"{len(self.records)} frame(s) done")
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
                        video = self.video.close() if self.video is not None else None
            dropped = scheduler.dropped if scheduler is not None else 0
            extra_frames = {"unmatched_inputs": self.assembler.dropped, "ignored_inputs": self.assembler.ignored}
            bag_info = {"path": str(bag_path), "storage": bag.storage, "layout": bag.layout, "backend": bag.backend,
                        "messages": bag.message_count, "recovered_files": bag.recovered}
        wall = time.perf_counter() - t_wall
        summary = self._summary(inputs, out, dropped, wall, extra_frames, bag_info, counts)
        exit_code, message = self._verdict(inputs)
        summary["interrupted"] = interrupted or None
        if self.video is not None:
            summary["video"] = {"path": str(video) if video is not None else None, "frames": self.video.frames}
        if interrupted:
            summary["title"] += f" (interrupted by {interrupted})"
            exit_code = Interrupted(interrupted).exit_code
            message = (f"stopped by {interrupted} after {len(self.records)} frame(s); "
                       + ("the output and summary cover those" if out is not None else "the summary covers those"))
        summary["exit_code"] = exit_code
        if message:
            summary["message"] = message
        result = ReplayResult(self.records, summary, out, exit_code, message, list(self.warnings), output_counts=counts)
        if opts.report_dir is not None:
            try:
                result.report_files = write_report(opts.report_dir, self.records, summary, cfg.axes)
            except OSError as exc:   # (checked before the run; a disk that filled up since): the results stay
                self.warn(f"--report {opts.report_dir}: the report could not be written: {exc}")
                result.warnings = list(self.warnings)
                if result.exit_code == 0:
                    result.exit_code, result.message = 2, f"the report could not be written to {opts.report_dir}"
        return result

    def _loop(self, bag: BagReader, inputs: InputTopics) -> RealtimeScheduler | None:
        opts = self.opts
        scheduler = None
        if opts.realtime:
            def run_one(raw: RawFrame, start: float) -> float:
                _rec, duration = self.process(raw, start_s=start)
                self._commit()
                return duration

            scheduler = RealtimeScheduler(run_one, on_drop=lambda raw: None)

        for raw in self._frames(bag, inputs):
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

    def _frames(self, bag: BagReader, inputs: InputTopics):
        """The progress bar, then the assembled input frames of the bag in stamp order (input problems are
        recorded and warned about here; the caller stops after ``max_frames``)."""
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
        self.bar = Progress(total, label=opts.label, mode=mode, interval_s=opts.progress_interval_s,
                            emit=lambda line: self.log("info", line))

        copy: Callable[[BagMessage], None] | None = None
        if opts.copy_inputs and self.writer is not None:
            copy_topics = set(inputs.roles().values())

            def copy_input(m: BagMessage) -> None:
                if m.topic in copy_topics:
                    with self.stop.section():
                        self.writer.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, bag.typestore_for(m.msgtype))

            copy = copy_input
            if inputs.truth:  # the ground truth is not an input of the loop: copy it here
                for m in bag.messages([inputs.truth]):
                    copy(m)

        handlers = {"points": self.assembler.on_points, "depth": self.assembler.on_depth, "color": self.assembler.on_color,
                    "info": self.assembler.on_info, "depth_info": self.assembler.on_depth_info}
        def messages():
            for role, m, msg, stamp in stamp_ordered(bag, roles, self.warn, copy=copy):
                if role in self.stamps:
                    self.stamps[role].append(stamp)
                yield handlers[role], msg
            yield (lambda _none: self.assembler.flush()), None   # the end: a pair that waited to be settled

        for handler, msg in messages():
            try:
                raw = handler(msg)
            except PwsError as exc:
                self.problems.append(str(exc))
                self.warn_once("assemble:" + str(exc), f"input: {exc}")
                continue
            if raw is None:
                continue
            skew = self.assembler.skew_warning(raw)
            if skew:
                self.warn_once("sync-skew", f"frame {raw.stamp_ns}: {skew}")
            self.frames_seen += 1
            if self.assembler.locked_source and total_topic and inputs.mode == "auto":
                t = inputs.points if self.assembler.locked_source == "pointcloud2" else inputs.color
                if t in bag.topics and bag.topics[t].count:
                    self.bar.set_total(min(bag.topics[t].count, opts.max_frames or bag.topics[t].count))
            yield raw

    def _summary(self, inputs: InputTopics, out: Path | None, dropped: int, wall: float, extra_frames: dict,
                 bag_info: dict, counts: dict) -> dict[str, Any]:
        return replay_summary(self, inputs, out, dropped, wall, extra_frames, bag_info, counts)

    def _verdict(self, inputs: InputTopics) -> tuple[int, str]:
        return replay_verdict(self, inputs)


def replay(options: ReplayOptions) -> ReplayResult:
    """Run a replay (see the module docstring). PwsError for what stops it before any frame."""
    return Replay(options).run()

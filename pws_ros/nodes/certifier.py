"""``certifier``: certifies each input frame from its rendered frames and bounds (four-process mode).

Subscribes (reliable): ``plan`` (plan bundles), ``rendered/frames`` (history ``frames_qos_depth``),
``rendered/bounds`` and ``rendered/errors``. Every frame carries ``"<stamp>/<axis>/<index>/<count>"``,
so a :class:`~pws_ros.bridge.sync.PartitionAssembler` ties it to its plan and detects a lost,
duplicate or out-of-range frame; an incomplete partition set is never certified (that axis is
reported as ERROR with the reason). The newest assembled frame is certified by a worker thread
(older ones are dropped and counted).

Anyone on the graph may publish on these topics. Every message is checked before anything is built
from it (counts against ``max_partitions``, frame sizes against the plan's, frames and bounds against
half of ``max_memory_mb``); a malformed one is a throttled WARN naming the topic and the problem, and
when it names its input frame (a plan's stamp, a frame tag, a bounds label) that frame's axis (every
axis, for a plan) is an ERROR in the frame's one certification message.

Publishes (reliable): ``certification`` (DiagnosticArray, one per input frame: header = source
stamp + frame id, one status ``pws/<axis>`` per axis; key schema in :mod:`pws_ros.bridge.msgbuild`),
``certified_label`` (DiagnosticArray, only for a frame certified on every axis), ``certification/markers``
(MarkerArray), ``certification/overlay`` (Image rgb8, ``publish_overlay``: the α = 0 frame of the
received plan) and ``/diagnostics`` (health: rate, drops, device, time since the last certified label).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace
from typing import Any

from ..bridge import msgbuild, outputs, scheme
from ..bridge.assembly import AssembledFrame, PartitionAssembler
from ..bridge.preview import assembled_alpha0
from ..core.errors import PwsError
from ._common import HealthPublisher, OverlayOutput, Throttle, Worker, guarded, jump_logger, entry_point, WorkerNode

NODE_NAME = "certifier"
POLL_S = 0.05
MAX_BUNDLES = 16


class CertifierNode(WorkerNode):
    def __init__(self, ctx: Any):
        from ..bridge.engine import FrameCertifier

        self.ctx = ctx
        ctx.on_change = self._on_change
        T = ctx.types
        cfg = ctx.config
        self.engine = FrameCertifier(cfg, log=ctx.log)  # loads the model now (PwsError -> exit 2)
        self.assembler = PartitionAssembler(timeout_s=cfg.assembly_timeout_s, max_pending=cfg.max_pending_frames,
                                            on_time_jump=jump_logger(ctx), max_count=cfg.max_partitions,
                                            max_bytes=self._max_bytes(cfg))
        self.bundles: OrderedDict[int, scheme.PlanBundle] = OrderedDict()
        self.replanned: set[int] = set()  # released stamps planned again, not yet flowing
        self.throttle = Throttle()
        self.certified = 0
        self.bad_messages = 0
        self.last_frame_error = ""
        self.pubs = outputs.OutputPublishers(ctx, (outputs.CERTIFICATION, outputs.CERTIFIED_LABEL, outputs.MARKERS))
        self.overlay = OverlayOutput(ctx)
        self.worker = Worker("pws-certifier", self._process, ctx.log)
        frames_depth = cfg.frames_qos_depth
        def sub(msg_type: Any, topic: str, fn: Any, depth: int, kind: str = "reliable") -> Any:
            cb = guarded(ctx, self.throttle, topic, fn, on_bad=lambda _m, _t: self._count_bad())
            return ctx.subscription(msg_type, topic, cb, kind=kind, depth=depth)

        self.subs = [
            # the planner publishes plan with output_qos (as the projector reads it): a reliable reader of a best-effort
            # writer would never match (an incompatible-QoS warning and no certification)
            sub(T.String, "plan", self._on_plan, max(10, cfg.output_qos_depth), kind=cfg.output_qos),
            sub(T.Image, "rendered/frames", self._on_frame, frames_depth),
            sub(T.Float64MultiArray, "rendered/bounds", self._on_bounds, max(10, cfg.output_qos_depth)),
            sub(T.String, "rendered/errors", self._on_error, max(10, cfg.output_qos_depth)),
        ]
        self.timer = ctx.timer(POLL_S, self._poll)
        self.health = HealthPublisher(ctx, self._counters, certifying=True, overlay=self.overlay)

    def _on_change(self, cfg: Any) -> None:
        self.assembler.timeout_s = cfg.assembly_timeout_s
        self.assembler.max_count = cfg.max_partitions
        self.assembler.max_bytes = self._max_bytes(cfg)
        self.overlay.update(cfg)

    @staticmethod
    def _max_bytes(cfg: Any) -> int:
        """The most bytes of frames (or of one bounds message) of one axis: half of ``max_memory_mb``, the
        share the planner gives them (the rest is the certifier's own working memory)."""
        return int(cfg.max_memory_mb * 2**20) // 2

    # -- inputs --
    def _count_bad(self) -> None:
        self.bad_messages += 1

    def _malformed(self, owner: tuple[int, str] | None, what: str, exc: Exception) -> None:
        """A malformed message that names its input frame (``owner`` = (stamp, axis)): that axis is an ERROR
        in the frame's certification; raised on, so that the guard logs and counts it."""
        if owner is not None:
            stamp, axis = owner
            self._start(stamp)
            self.assembler.fail(stamp, axis, f"malformed {what}: {exc}")
        raise exc

    def _fail_frame(self, stamp_ns: int, reason: str) -> None:
        """Every axis of input frame ``stamp_ns`` is an ERROR (a malformed plan named it): the axes of its
        plan, or the configured ones; nothing for a frame already certified (its one certification is out)."""
        bundle = self.bundles.pop(stamp_ns, None)
        axes = list(bundle.axes) if bundle is not None else list(self.ctx.config.axes)
        if self.assembler.fail_frame(stamp_ns, axes, reason):
            self._poll()

    def _expected_shape(self, stamp_ns: int) -> tuple[int, int] | None:
        """(H, W) of the frames the plan of ``stamp_ns`` renders, when that plan is known."""
        bundle = self.bundles.get(stamp_ns)
        if bundle is None:
            return None
        return tuple(bundle.imaging.out_shape) if bundle.imaging is not None else bundle.camera.shape

    def _start(self, stamp_ns: int) -> None:
        """Tell the assembler what to expect once data for ``stamp_ns`` starts flowing (a plan the
        projector dropped by its online policy never opens a set that would time out as an ERROR)."""
        bundle = self.bundles.get(stamp_ns)
        if bundle is not None and (not self.assembler.knows(stamp_ns) or stamp_ns in self.replanned):
            self.replanned.discard(stamp_ns)
            self.assembler.expect(stamp_ns, bundle.expected(), info=bundle)  # a released stamp planned again: a new pass

    def _on_plan(self, msg: Any) -> None:
        try:
            bundle = scheme.parse_plan_bundle_message(msg, self.ctx.config.max_partitions)
        except PwsError as exc:
            stamp = scheme.plan_bundle_stamp(getattr(msg, "data", None))
            if stamp is not None:
                self._fail_frame(stamp, f"malformed plan message: {exc}")
            raise
        S = bundle.stamp_ns
        if not bundle.plans:  # nothing will be rendered: report now (through the assembler: one certification per frame)
            self.assembler.expect(S, bundle.expected(), info=bundle)
            self._poll()
            return
        self.bundles[S] = bundle
        while len(self.bundles) > MAX_BUNDLES:
            self.replanned.discard(self.bundles.popitem(last=False)[0])
        if S in self.assembler.pending():  # frames arrived before their plan
            self.assembler.expect(S, bundle.expected(), info=bundle)
        elif self.assembler.knows(S):  # released before: the stamp came again (a looped bag), once its data flows
            self.replanned.add(S)

    def _on_frame(self, msg: Any) -> None:
        cfg = self.ctx.config
        frame_id = getattr(getattr(msg, "header", None), "frame_id", "")
        try:
            tag = scheme.frame_message_tag(msg, cfg.max_partitions)
            frame = scheme.frame_message_array(msg, tag, self._expected_shape(tag.stamp_ns), self._max_bytes(cfg))
        except PwsError as exc:
            self._malformed(scheme.tag_owner(frame_id), "rendered frame", exc)
        self._start(tag.stamp_ns)
        self.assembler.add_frame(tag.stamp_ns, tag.axis, tag.index, tag.count, frame)

    def _on_bounds(self, msg: Any) -> None:
        cfg = self.ctx.config
        try:
            stamp, _axis, _count = scheme.bounds_label(msg, cfg.max_partitions)
            b = scheme.parse_bounds_message(msg, cfg.max_partitions, self._max_bytes(cfg), self._expected_shape(stamp))
        except PwsError as exc:
            label = msg.layout.dim[0].label if getattr(getattr(msg, "layout", None), "dim", None) else ""
            self._malformed(scheme.tag_owner(label), "bounds message", exc)
        self._start(b.stamp_ns)
        self.assembler.add_bounds(b.stamp_ns, b.axis, b.count, b)

    def _on_error(self, msg: Any) -> None:
        stamp, axis, reason = scheme.parse_render_error(msg)
        self._start(stamp)
        self.assembler.fail(stamp, axis, f"projector: {reason}")

    def _poll(self) -> None:
        for frame in self.assembler.pop_ready():
            self.bundles.pop(frame.stamp_ns, None)
            if any(a.ok for a in frame.axes):
                self.worker.submit(frame)
                continue
            # nothing to certify: its ERROR certification goes out now, so that a burst of failed (or forged)
            # frames never displaces a frame the worker is about to certify (its slot holds the newest only)
            try:
                self._process(frame)
            except Exception as exc:  # noqa: BLE001 - a timer callback must not raise
                self.throttle(self.ctx.log, "error", f"publishing the ERROR certification of frame {frame.stamp_ns} failed: "
                                                     f"{type(exc).__name__}: {exc}", key="error-publish")

    # -- certification --
    def _process(self, frame: AssembledFrame) -> None:
        self.engine.config = cfg = self.ctx.config
        result = self.engine.certify_assembled(frame)
        self._publish(result, cfg)
        if cfg.publish_overlay:   # the α = 0 frame taken now (not the whole assembled frame held for the overlay)
            view = assembled_alpha0(frame)
            self.overlay.submit(msgbuild.make_header(self.ctx.types, result.stamp_ns, result.frame_id), result.stamp_ns,
                                result.certificates, lambda: view)
        self.certified += 1
        self.last_frame_error = outputs.frame_error(result.certificates)
        self.ctx.log("info", outputs.summary_line(frame.stamp_ns, result.certificates))

    def _publish(self, result: Any, cfg: Any) -> None:
        """Publish one frame's markers, certified label and certification (the other nodes publish its cloud, poses
        and previews)."""
        T = self.ctx.types
        switches = replace(outputs.OutputSwitches.from_config(cfg), cloud=False, poses=False, preview=False)
        out = outputs.frame_outputs(
            T, msgbuild.make_header(T, result.stamp_ns, result.frame_id), result.certificates, node_name=self.ctx.name,
            latency_ms=(self.ctx.now_ns() - result.stamp_ns) / 1e6, compute_ms=result.compute_ms, switches=switches,
            result=result)
        self.pubs.publish(out)
        self.health.published(out)

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {"activity": "certified", "rate_hz": w.rate.rate(), "frames_in": w.slot.accepted, "frames_processed": self.certified,
                "frames_dropped": w.slot.dropped, "device": self.engine.device, "last_error": self.last_frame_error,
                "warning": self.engine.device_warning,
                "extra": {"pending_frames": len(self.assembler.pending()), "incomplete_axis_sets": self.assembler.failed,
                          "late_messages": self.assembler.late, "bad_messages": self.bad_messages,
                          "time_jumps_back": self.assembler.time_jumps}}


main = entry_point(NODE_NAME, CertifierNode)


if __name__ == "__main__":
    main()

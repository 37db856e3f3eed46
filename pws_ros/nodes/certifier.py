"""``certifier``: certifies each input frame from its rendered frames and bounds (four-process mode).

Subscribes (reliable): ``plan`` (plan bundles), ``rendered/frames`` (history ``frames_qos_depth``),
``rendered/bounds`` and ``rendered/errors``. Every frame carries ``"<stamp>/<axis>/<index>/<count>"``,
so a :class:`~pws_ros.bridge.sync.PartitionAssembler` ties it to its plan and detects a lost,
duplicate or out-of-range frame; an incomplete partition set is never certified (that axis is
reported as ERROR with the reason). The newest assembled frame is certified by a worker thread
(older ones are dropped and counted).

Publishes (reliable): ``certification`` (DiagnosticArray, one per input frame: header = source
stamp + frame id, one status ``pws/<axis>`` per axis; key schema in :mod:`pws_ros.bridge.msgbuild`),
``certification/markers`` (MarkerArray) and ``/diagnostics`` (health: rate, drops, device).
"""
from __future__ import annotations

import sys
from collections import OrderedDict
from dataclasses import replace
from typing import Any

from ..bridge import msgbuild, outputs, scheme
from ..bridge.assembly import AssembledFrame, AxisSet, PartitionAssembler
from ..core.errors import PwsError
from ._common import HealthPublisher, Throttle, Worker, jump_logger, start

NODE_NAME = "certifier"
POLL_S = 0.05
MAX_BUNDLES = 16


class CertifierNode:
    def __init__(self, ctx: Any):
        from ..bridge.engine import FrameCertifier

        self.ctx = ctx
        ctx.on_change = self._on_change
        T = ctx.types
        cfg = ctx.config
        self.engine = FrameCertifier(cfg, log=ctx.log)  # loads the model now (PwsError -> exit 2)
        self.assembler = PartitionAssembler(timeout_s=cfg.assembly_timeout_s, max_pending=cfg.max_pending_frames,
                                            on_time_jump=jump_logger(ctx))
        self.bundles: OrderedDict[int, scheme.PlanBundle] = OrderedDict()
        self.replanned: set[int] = set()  # released stamps planned again, not yet flowing
        self.throttle = Throttle()
        self.certified = 0
        self.bad_messages = 0
        self.last_frame_error = ""
        self.pubs = outputs.OutputPublishers(ctx, (outputs.CERTIFICATION, outputs.MARKERS))
        self.worker = Worker("pws-certifier", self._process, ctx.log)
        frames_depth = cfg.frames_qos_depth
        self.subs = [
            ctx.subscription(T.String, "plan", self._on_plan, kind="reliable", depth=max(10, cfg.output_qos_depth)),
            ctx.subscription(T.Image, "rendered/frames", self._on_frame, kind="reliable", depth=frames_depth),
            ctx.subscription(T.Float64MultiArray, "rendered/bounds", self._on_bounds, kind="reliable", depth=max(10, cfg.output_qos_depth)),
            ctx.subscription(T.String, "rendered/errors", self._on_error, kind="reliable", depth=max(10, cfg.output_qos_depth)),
        ]
        self.timer = ctx.timer(POLL_S, self._poll)
        self.health = HealthPublisher(ctx, self._counters)

    def _on_change(self, cfg: Any) -> None:
        self.assembler.timeout_s = cfg.assembly_timeout_s

    # -- inputs --
    def _bad(self, what: str, exc: PwsError) -> None:
        self.bad_messages += 1
        self.throttle(self.ctx.log, "warn", f"ignoring {what}: {exc}", key=what)

    def _start(self, stamp_ns: int) -> None:
        """Tell the assembler what to expect once data for ``stamp_ns`` starts flowing (a plan the
        projector dropped by its online policy never opens a set that would time out as an ERROR)."""
        bundle = self.bundles.get(stamp_ns)
        if bundle is not None and (not self.assembler.knows(stamp_ns) or stamp_ns in self.replanned):
            self.replanned.discard(stamp_ns)
            self.assembler.expect(stamp_ns, bundle.expected(), info=bundle)  # a released stamp planned again: a new pass

    def _on_plan(self, msg: Any) -> None:
        try:
            bundle = scheme.parse_plan_bundle_message(msg)
        except PwsError as exc:
            self._bad("plan message", exc)
            return
        S = bundle.stamp_ns
        if not bundle.plans:  # nothing will be rendered: report now
            axes = [AxisSet(S, a, 0, None, None, None, bundle.errors.get(a, "no plan")) for a in bundle.axes]
            self.worker.submit(AssembledFrame(S, axes, bundle))
            return
        self.bundles[S] = bundle
        while len(self.bundles) > MAX_BUNDLES:
            self.replanned.discard(self.bundles.popitem(last=False)[0])
        if S in self.assembler.pending():  # frames arrived before their plan
            self.assembler.expect(S, bundle.expected(), info=bundle)
        elif self.assembler.knows(S):  # released before: the stamp came again (a looped bag), once its data flows
            self.replanned.add(S)

    def _on_frame(self, msg: Any) -> None:
        try:
            tag, frame = scheme.parse_frame_message(msg)
        except PwsError as exc:
            self._bad("rendered frame", exc)
            return
        self._start(tag.stamp_ns)
        self.assembler.add_frame(tag.stamp_ns, tag.axis, tag.index, tag.count, frame)

    def _on_bounds(self, msg: Any) -> None:
        try:
            b = scheme.parse_bounds_message(msg)
        except PwsError as exc:
            self._bad("bounds message", exc)
            return
        self._start(b.stamp_ns)
        self.assembler.add_bounds(b.stamp_ns, b.axis, b.count, b)

    def _on_error(self, msg: Any) -> None:
        try:
            stamp, axis, reason = scheme.parse_render_error(msg)
        except PwsError as exc:
            self._bad("render error message", exc)
            return
        self._start(stamp)
        self.assembler.fail(stamp, axis, f"projector: {reason}")

    def _poll(self) -> None:
        for frame in self.assembler.pop_ready():
            self.bundles.pop(frame.stamp_ns, None)
            self.worker.submit(frame)

    # -- certification --
    def _process(self, frame: AssembledFrame) -> None:
        self.engine.config = cfg = self.ctx.config
        result = self.engine.certify_assembled(frame)
        self._publish(result, cfg)
        self.certified += 1
        self.last_frame_error = outputs.frame_error(result.certificates)
        self.ctx.log("info", outputs.summary_line(frame.stamp_ns, result.certificates))

    def _publish(self, result: Any, cfg: Any) -> None:
        """Publish one frame's markers and certification (the other nodes publish its cloud, poses and previews)."""
        T = self.ctx.types
        switches = replace(outputs.OutputSwitches.from_config(cfg), cloud=False, poses=False, preview=False)
        self.pubs.publish(outputs.frame_outputs(
            T, msgbuild.make_header(T, result.stamp_ns, result.frame_id), result.certificates, node_name=self.ctx.name,
            latency_ms=(self.ctx.now_ns() - result.stamp_ns) / 1e6, compute_ms=result.compute_ms, switches=switches,
            result=result))

    def _counters(self) -> dict[str, Any]:
        w = self.worker
        return {"activity": "certified", "rate_hz": w.rate.rate(), "frames_in": w.slot.accepted, "frames_processed": self.certified,
                "frames_dropped": w.slot.dropped, "device": self.engine.device, "last_error": self.last_frame_error,
                "warning": self.engine.device_warning,
                "extra": {"pending_frames": len(self.assembler.pending()), "incomplete_axis_sets": self.assembler.failed,
                          "late_messages": self.assembler.late, "bad_messages": self.bad_messages,
                          "time_jumps_back": self.assembler.time_jumps}}

    def close(self) -> None:
        self.worker.close()


def main(args: list[str] | None = None) -> None:
    sys.exit(start(NODE_NAME, CertifierNode, args))


if __name__ == "__main__":
    main()

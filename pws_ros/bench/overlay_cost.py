"""What ``publish_overlay`` costs the pipeline node, measured side by side on a recording.

    python -m pws_ros.bench.overlay_cost [bags/demo] [--rounds 2] [--no-preview] [--json]

The ``pipeline`` node's own logic (:class:`pws_ros.nodes.pipeline.PipelineNode`, its worker and overlay
threads) runs on an in-process context (no ROS, no serialisation) with the configuration of
``config/pws.yaml``; the recording's frames are handed to its input callbacks one at a time, the next as
soon as the previous one's ``certification`` is out, so the overlay of a frame is drawn while the next one
is certified, as live. Per frame: the seconds from its input to its certification. Runs alternate, overlay
off then on, ``--rounds`` times each, every round over every frame of the recording (the same frames, so
the same certificates), and the mean time per frame of each side is compared, and the CPU seconds the
process spends per frame (every thread; less sensitive to the machine's load than the wall time). Also the
time one overlay takes in its own thread. ``--no-preview`` turns ``publish_preview`` off, so the overlay renders its
α = 0 view itself instead of taking it from the previews. Timings on a shared machine vary: the load is
printed.
"""
from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

from ..nodes.live import REPO


class _Context:
    """The node-context interface (``pws_ros.nodes._ros.NodeContext``) in process: subscriptions kept by
    topic, publications timed."""

    def __init__(self, config: Any, types: Any):
        self.name, self.types, self.config = "pipeline", types, config
        self.on_change = None
        self.qos_events = 0
        self.subs: dict[str, list] = {}
        self.published: list[tuple[float, str, Any]] = []
        self.cond = threading.Condition()

    def log(self, level: str, message: str) -> None:
        if level != "info":
            print(f"[{level}] {message}")

    def now_ns(self) -> int:
        return time.time_ns()

    def resolve(self, topic: str) -> str:
        return topic

    def publisher(self, msg_type: Any, topic: str, *, kind: str | None = None, depth: int | None = None) -> Any:
        ctx = self

        class Pub:
            def publish(self, msg: Any) -> None:
                with ctx.cond:
                    ctx.published.append((time.perf_counter(), topic, msg))
                    ctx.cond.notify_all()

        return Pub()

    def subscription(self, msg_type: Any, topic: str, callback: Any, *, kind: str | None = None, depth: int | None = None) -> None:
        self.subs.setdefault(topic, []).append(callback)

    def timer(self, period: float, callback: Any) -> Any:
        return callback

    def count(self, topic: str) -> int:
        return sum(1 for _t, tp, _m in self.published if tp == topic)


def _cpu_s() -> float:
    """CPU seconds of this process so far (every thread: the worker's, torch's, the overlay's)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_side(config: Any, frames: list, overlay: bool, stamp0: int) -> dict[str, Any]:
    """One run over ``frames`` (``demo_frames`` builders) with ``publish_overlay = overlay``."""
    from ..bridge import msgbuild
    from ..nodes.pipeline import PipelineNode

    ctx = _Context(config.with_params({"publish_overlay": overlay}), msgbuild.rosbags_types())
    node = PipelineNode(ctx)
    draw_s: list[float] = []
    if overlay:
        draw = node.overlay.worker.fn

        def timed(job: Any) -> None:
            t0 = time.perf_counter()
            draw(job)
            draw_s.append(time.perf_counter() - t0)

        node.overlay.worker.fn = timed
    per_frame = []
    cpu0 = _cpu_s()
    try:
        for k, build in enumerate(frames):
            msgs = build(stamp0 + k * 100_000_000)
            done = ctx.count("certification")
            t0 = time.perf_counter()
            for topic, msg in sorted(msgs, key=lambda tm: "image" in tm[0]):   # camera infos first
                for cb in ctx.subs.get(topic, []):
                    cb(msg)
            with ctx.cond:
                ctx.cond.wait_for(lambda: ctx.count("certification") > done, timeout=600)
            t1 = next(t for t, tp, _m in reversed(ctx.published) if tp == "certification")
            per_frame.append(t1 - t0)
        if overlay:   # the last frame's overlay, drawn after its certification
            end = time.monotonic() + 60
            while node.overlay.worker.processed + node.overlay.worker.slot.dropped < len(frames) and time.monotonic() < end:
                time.sleep(0.01)
        cpu = _cpu_s() - cpu0
    finally:
        node.close()
    return {"overlay": overlay, "per_frame_s": per_frame, "mean_s": sum(per_frame) / len(per_frame),
            "cpu_s_per_frame": cpu / len(frames),
            "overlays": ctx.count("certification/overlay"), "overlay_draw_s": draw_s,
            "certified_labels": ctx.count("certified_label")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.overlay_cost", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", nargs="?", default=str(REPO / "bags" / "demo"))
    p.add_argument("--rounds", type=int, default=2, help="runs per side (off, on, off, on, ...)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--no-preview", action="store_true", help="publish_preview false: the overlay renders its view itself")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    from ..bridge import msgbuild
    from ..nodes.live import demo_frames
    from ..replay.options import load_replay_config

    cfg = load_replay_config(None)
    model = Path(cfg.model_path)
    cfg = cfg.with_params({"model_path": str(model if model.is_absolute() else REPO / model), "input_mode": "rgbd",
                           "publish_preview": not args.no_preview})
    frames = [build for build, _label in demo_frames(msgbuild.rosbags_types(), Path(args.bag))][: args.max_frames]
    load0 = os.getloadavg()
    runs = []
    for r in range(args.rounds):
        for overlay in (False, True):
            runs.append(run_side(cfg, frames, overlay, 1_900_000_000 * 10**9))   # the same stamps: the same certificates
            if not args.json:
                run = runs[-1]
                print(f"round {r} overlay {'on ' if overlay else 'off'}: {1000 * run['mean_s']:.0f} ms per frame, "
                      f"{run['cpu_s_per_frame']:.2f} CPU s "
                      f"({len(frames)} frames, {run['overlays']} overlays)", flush=True)
    load1 = os.getloadavg()
    mean = {side: sum(x["mean_s"] for x in runs if x["overlay"] == side) / args.rounds for side in (False, True)}
    cpu = {side: sum(x["cpu_s_per_frame"] for x in runs if x["overlay"] == side) / args.rounds for side in (False, True)}
    draws = [d for x in runs for d in x["overlay_draw_s"]]
    out = {"bag": args.bag, "frames": len(frames), "rounds": args.rounds, "publish_preview": not args.no_preview,
           "mean_s_off": mean[False], "mean_s_on": mean[True], "added": mean[True] / mean[False] - 1.0,
           "cpu_s_per_frame_off": cpu[False], "cpu_s_per_frame_on": cpu[True], "cpu_added": cpu[True] / cpu[False] - 1.0,
           "overlay_draw_ms_mean": 1000 * sum(draws) / max(1, len(draws)), "loadavg": [round(v, 2) for v in load0 + load1],
           "runs": runs}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"time per frame: {1000 * mean[False]:.0f} ms without the overlay, {1000 * mean[True]:.0f} ms with it "
              f"({100 * out['added']:+.1f} %); CPU per frame {cpu[False]:.2f} s and {cpu[True]:.2f} s "
              f"({100 * out['cpu_added']:+.1f} %); one overlay {out['overlay_draw_ms_mean']:.1f} ms in its own thread; "
              f"load {out['loadavg']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Throughput of the live scheme without ROS, and a time budget against none, side by side.

    python -m pws_ros.bench.throughput [bags/demo] [--workers 1,2] [--loops 2] [--budget 6] [--json]
    python -m pws_ros.bench.throughput --live [--workers 1,2] [--seconds 90]     # ROS 2 sourced

1. **Workers.** The recording's frames (looped ``--loops`` times, each loop's stamps shifted past the
   last, as ``ros2 bag play --loop`` with a new timeline) are certified by W worker processes at once,
   each keeping the stamps :class:`~pws_ros.bridge.workers.StampAssignment` gives it (the pipeline
   node's rule; ``worker_period_s`` = the recording's frame period) and using ``cores // W`` torch
   threads, as ``workers:=W`` does. Reported per W: wall time from a common start (models loaded
   before), frames per minute, the speed-up over one worker, the rate if every worker stayed busy (W x
   frames / the workers' summed busy time: live, each always has a newest frame of its own, so an
   unlucky split of slow frames does not idle the others) and whether every stamp's certificates equal
   the one-worker run's. Every frame is certified (no latest-only drops: this measures capacity).
2. **Budget.** The first frames certified with ``time_budget_s`` 0 and ``--budget``: per axis the share,
   the time spent, the sizes (anchors, n, grid), the classifier calls and the radius.

Also the machine: cores, load average before and after (timings on a shared machine vary).

``--live`` measures the same on the real graph instead (:mod:`pws_ros.nodes.live`): ``pws.launch.py
workers:=W`` for each W in turn, the recording looped at 10 Hz by an rclpy player (the same stamps every
run; the online policy drops what the workers cannot take), certifications per minute over ``--seconds``
once every worker certified a frame, and the certificates of the stamps two runs both certified compared.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path
from typing import Any


def bag_frames(bag: Path, config: Any, max_frames: int | None = None) -> list[tuple[int, Any, Any, str]]:
    """(stamp, cloud, camera, frame id) of a recording's frames, assembled and converted as ``pws replay``
    does (the serial replay's frame loop, nothing certified)."""
    from ..bridge.inputs import convert
    from ..replay.options import ReplayOptions
    from ..replay.run import Replay

    frames: list[tuple[int, Any, Any, str]] = []

    class Collect(Replay):
        def _loop(self, bag_reader, inputs):
            for raw in self._frames(bag_reader, inputs):
                frame = convert(raw, self.config, self.assembler.fallback)
                frames.append((int(raw.stamp_ns), frame.cloud, frame.intrinsics, str(raw.header.frame_id)))
                self.bar.update(1)
                if max_frames is not None and len(frames) >= max_frames:
                    break
            return None

    Collect(ReplayOptions(bag=Path(bag), config=config, write_output=False, quiet=True, log=lambda *a: None)).run()
    return frames


def looped(frames: list, loops: int) -> list:
    """``frames`` repeated, each loop's stamps shifted by the recording's span plus one period."""
    stamps = [f[0] for f in frames]
    period = (stamps[-1] - stamps[0]) // max(1, len(stamps) - 1) if len(stamps) > 1 else 100_000_000
    span = stamps[-1] - stamps[0] + period
    return [(s + k * span, c, i, fid) for k in range(loops) for (s, c, i, fid) in frames]


def _worker(config: Any, frames: list, workers: int, index: int, period_ns: int, barrier: Any, out: Any) -> None:
    from ..bridge.engine import FrameCertifier
    from ..bridge.workers import StampAssignment, set_torch_threads

    set_torch_threads(workers)
    import torch

    engine = FrameCertifier(config, log=lambda *a: None)
    mine = StampAssignment(workers, index, period_ns)
    barrier.wait()
    t0 = time.perf_counter()
    certs = {}
    for stamp, cloud, intr, fid in frames:
        if mine.mine(stamp):
            res = engine.process(cloud, intr, stamp, frame_id=fid)
            certs[stamp] = [{k: v for k, v in c.to_dict().items() if k != "timings"} for c in res.certificates]
    out.put((index, time.perf_counter() - t0, torch.get_num_threads(), certs))


def run_workers(config: Any, frames: list, workers: int, period_ns: int) -> dict[str, Any]:
    """Certify ``frames`` with ``workers`` processes at once (spawned; the models load before the clock starts)."""
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(workers + 1)
    out = ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(config, frames, workers, i, period_ns, barrier, out)) for i in range(workers)]
    for p in procs:
        p.start()
    barrier.wait()
    t0 = time.perf_counter()
    results = [out.get() for _ in procs]
    wall = time.perf_counter() - t0
    for p in procs:
        p.join()
    certs: dict[int, Any] = {}
    for _i, _w, _t, c in results:
        overlap = set(certs) & set(c)
        if overlap:
            raise RuntimeError(f"stamps certified by two workers: {sorted(overlap)[:3]}")
        certs.update(c)
    busy = sum(w for _i, w, _t, _c in results)
    return {"workers": workers, "wall_s": wall, "frames": len(certs), "frames_per_min": 60.0 * len(certs) / wall,
            # live, every worker always has a newest frame of its own: the rate when all stay busy
            "busy_frames_per_min": 60.0 * workers * len(certs) / busy if busy > 0 else float("nan"),
            "per_worker": sorted((i, round(w, 2), len([s for s in c]), t) for i, w, t, c in results), "certs": certs}


def budget_rows(config: Any, frames: list, budget: float) -> list[dict[str, Any]]:
    """Per frame and axis: unbudgeted and budgeted certificates side by side."""
    from ..bridge.engine import FrameCertifier

    rows = []
    engines = {0.0: FrameCertifier(config, log=lambda *a: None),
               budget: FrameCertifier(config.with_params({"time_budget_s": float(budget)}), log=lambda *a: None)}
    for stamp, cloud, intr, fid in frames:
        out = {}
        for b, eng in engines.items():
            t0 = time.perf_counter()
            res = eng.process(cloud, intr, stamp, frame_id=fid)
            out[b] = (res, time.perf_counter() - t0 - res.timings.get("startup", 0.0))   # start-up work is not the frame's
        for k, axis in enumerate(config.axes):
            row = {"stamp": stamp, "axis": axis}
            for b, (res, wall) in out.items():
                c = res.certificates[k]
                tb = c.bounds.get("time_budget", {})
                key = "budget" if b else "none"
                row[key] = {"frame_s": round(wall, 3), "share_s": tb.get("share_s"), "spent_s": round(res.timings.get(axis, float("nan")), 3),
                            "anchors": int(c.num_bounds), "n": int(c.n), "grid": int(c.num_partitions),
                            "calls": int(c.classifier_calls), "radius": float(c.radius), "of": float(c.requested_radius),
                            "status": c.status}
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.throughput", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", nargs="?", default="bags/demo", help="rosbag2 recording (default: bags/demo)")
    p.add_argument("--workers", default="1,2", help="worker counts to compare (default 1,2)")
    p.add_argument("--loops", type=int, default=2, help="times the recording is looped for the worker runs (default 2)")
    p.add_argument("--budget", type=float, default=6.0, help="time_budget_s of the budget comparison (default 6 s per frame; 0: no budget comparison)")
    p.add_argument("--budget-frames", type=int, default=4, help="frames of the budget comparison (default 4)")
    p.add_argument("--config", default=None, help="parameter file (default: config/pws.yaml)")
    p.add_argument("--json", action="store_true", help="print the measurements as JSON")
    p.add_argument("--live", action="store_true",
                   help="instead: the live ROS 2 graph (rclpy; source ROS 2 Jazzy first): pws.launch.py workers:=W for each "
                        "--workers count in turn on the recording looped at its 10 Hz, certifications counted for --seconds "
                        "once every worker certified a frame; certificates compared per stamp across the runs")
    p.add_argument("--seconds", type=float, default=90.0, help="--live: measuring window per worker count (default 90 s)")
    args = p.parse_args(argv)
    if args.live:
        return live_main(args)

    from ..bridge.workers import available_cores
    from ..replay.options import load_replay_config

    if not args.budget >= 0:
        print(f"--budget must be >= 0 s (0: no budget comparison), got {args.budget:g}", file=sys.stderr)
        return 2
    config = load_replay_config(args.config)
    frames = bag_frames(Path(args.bag), config)
    if not frames:
        print(f"no frames in {args.bag}", file=sys.stderr)
        return 2
    stamps = [f[0] for f in frames]
    period = (stamps[-1] - stamps[0]) // max(1, len(stamps) - 1) if len(stamps) > 1 else 100_000_000
    load0 = os.getloadavg()
    runs = [run_workers(config, looped(frames, args.loops), int(w), period) for w in args.workers.split(",")]
    base = runs[0]
    for r in runs:
        r["speedup"] = base["wall_s"] / r["wall_s"]
        r["busy_speedup"] = r["busy_frames_per_min"] / base["busy_frames_per_min"]
        r["equal_to_first"] = r["certs"] == base["certs"]
    rows = budget_rows(config, frames[: args.budget_frames], args.budget) if args.budget > 0 else []
    load1 = os.getloadavg()
    machine = {"cores": available_cores(), "loadavg_before": [round(x, 2) for x in load0],
               "loadavg_after": [round(x, 2) for x in load1]}
    if args.json:
        print(json.dumps({"machine": machine, "workers": [{k: v for k, v in r.items() if k != "certs"} for r in runs],
                          "budget": rows}, indent=2, default=str))
        return 0
    print(f"{args.bag}: {len(frames)} frames x {args.loops} loops; {machine['cores']} cores; load average "
          f"{machine['loadavg_before']} before, {machine['loadavg_after']} after")
    print(f"{'workers':>7}  {'wall s':>7}  {'frames':>6}  {'frames/min':>10}  {'speed-up':>8}  {'all busy/min':>12}  {'speed-up':>8}  "
          f"{'equal certs':>11}  per worker (index, s, frames, threads)")
    for r in runs:
        print(f"{r['workers']:>7}  {r['wall_s']:>7.1f}  {r['frames']:>6}  {r['frames_per_min']:>10.1f}  {r['speedup']:>7.2f}x  "
              f"{r['busy_frames_per_min']:>12.1f}  {r['busy_speedup']:>7.2f}x  {'yes' if r['equal_to_first'] else 'NO':>11}  {r['per_worker']}")
    print("(all busy: W x frames / the workers' summed busy time, the rate when every worker always has a frame of its own, "
          "as live under the latest-only policy)")
    if not rows:
        return 0
    print(f"\ntime budget {args.budget:g} s per frame vs none (first {len(rows) // max(1, len(config.axes))} frames):")
    print(f"{'frame':>5} {'axis':>4} | {'none: s':>7} {'calls':>5} {'anch':>4} {'n':>4} {'grid':>4} {'radius':>9} | "
          f"{'share s':>7} {'spent s':>7} {'calls':>5} {'anch':>4} {'n':>4} {'grid':>4} {'radius':>9} {'of':>9}")
    for k, r in enumerate(rows):
        a, b = r["none"], r["budget"]
        print(f"{k // max(1, len(config.axes)):>5} {r['axis']:>4} | {a['spent_s']:>7.2f} {a['calls']:>5} {a['anchors']:>4} {a['n']:>4} "
              f"{a['grid']:>4} {a['radius']:>9.4g} | {b['share_s'] or 0:>7.2f} {b['spent_s']:>7.2f} {b['calls']:>5} {b['anchors']:>4} "
              f"{b['n']:>4} {b['grid']:>4} {b['radius']:>9.4g} {b['of']:>9.4g}")
    frames_b = {}
    for r in rows:
        frames_b.setdefault(r["stamp"], r["budget"]["frame_s"])
    print(f"budgeted frames: {', '.join(f'{v:.2f}' for v in frames_b.values())} s (budget {args.budget:g} s)")
    return 0


def live_main(args: argparse.Namespace) -> int:
    """``--live``: :func:`pws_ros.nodes.live.live_throughput` (rclpy lives in the nodes package only)."""
    from ..nodes._common import ROS_MISSING, rclpy_available

    if not rclpy_available():
        print(f"--live: {ROS_MISSING}", file=sys.stderr)
        return 2
    from ..bridge.workers import available_cores
    from ..nodes.live import live_throughput

    res = live_throughput([int(w) for w in args.workers.split(",")], args.seconds, Path(args.config) if args.config else None,
                          Path(args.bag))
    if args.json:
        print(json.dumps({"cores": available_cores(), **res, "runs": [{k: v for k, v in r.items() if k != "certs"} for r in res["runs"]]},
                         indent=2, default=str))
        return 0
    print(f"live: pws.launch.py workers:=W on {args.bag} looped at 10 Hz; {available_cores()} cores; config {res['config']}")
    print(f"{'workers':>7}  {'window s':>8}  {'certified':>9}  {'frames/min':>10}  {'speed-up':>8}  {'common stamps':>13}  "
          f"{'equal certs':>11}  {'published':>9}  load average (before 1/5/15, after 1/5/15)  per worker")
    for r in res["runs"]:
        print(f"{r['workers']:>7}  {r['window_s']:>8.1f}  {r['certified']:>9}  {r['frames_per_min']:>10.1f}  {r['speedup']:>7.2f}x  "
              f"{r['common_stamps']:>13}  {r['equal_certificates']:>11}  {r['frames_published']:>9}  {r['loadavg']}  {r['per_worker']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Time per frame of the shipped defaults on a recording, split by stage, next to pure inference.

    python -m pws_ros.bench.frame_timing bags/demo [--max-frames N] [--sync-tolerance S] [--json]

Replays the recording with the configuration of ``config/pws.yaml`` (no output bag), then prints per
frame and axis: status, certified radius of the requested one, anchors, classifier calls and the
seconds spent planning, bounding (the sweep of the imaging model), rendering, in inference and in
statistics; per frame the total next to the seconds the same number of classifier calls take alone
(the model on batches of the same size, no geometry), and the ratio of everything but inference to
inference. Also the peak resident memory and the machine's load: timings on a shared machine vary.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

STAGES = ("plan", "bounds", "render", "inference", "statistics")


def pure_inference_seconds(model, calls: int, batch_size: int, shape: tuple[int, int]) -> float:
    """Seconds ``calls`` classifier evaluations take on their own (batches of ``batch_size``)."""
    import torch

    x = torch.rand((min(batch_size, max(1, calls)), 3) + tuple(shape), generator=torch.Generator().manual_seed(0))
    done, t0 = 0, time.perf_counter()
    with torch.no_grad():
        while done < calls:
            b = min(batch_size, calls - done)
            model(x[:b])
            done += b
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.frame_timing", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="rosbag2 recording (directory or .mcap/.db3)")
    p.add_argument("--max-frames", type=int, default=None, help="frames to certify (default: all)")
    p.add_argument("--config", default=None, help="parameter file (default: config/pws.yaml)")
    p.add_argument("--sync-tolerance", type=float, default=None, help="depth/colour stamp tolerance in seconds")
    p.add_argument("--json", action="store_true", help="print the measurements as JSON")
    args = p.parse_args(argv)
    from ..core.errors import PwsError
    from ..replay import ReplayOptions, replay
    from ..replay.options import load_replay_config, override_config

    try:
        cfg = load_replay_config(args.config)  # as pws replay reads it: --config, else config/pws.yaml
        if args.sync_tolerance is not None:
            cfg = override_config(cfg, {"sync_tolerance_s": args.sync_tolerance})
        opts = ReplayOptions(bag=Path(args.bag), config=cfg, write_output=False, quiet=True, max_frames=args.max_frames)
        t0 = time.perf_counter()
        result = replay(opts)
        wall = time.perf_counter() - t0
    except PwsError as exc:
        print(f"frame_timing: error: {exc}", file=sys.stderr)
        return 2
    from ..core.model import load_model
    from ..bridge.config import resolve_path

    cfg = opts.config
    model = load_model(resolve_path(cfg.model_path, "model file"))
    shape = tuple(model.input_size) if model.input_size else (90, 160)
    rows, frames = [], []
    for rec in result.records:
        calls = sum(int(c.classifier_calls) for c in rec.certificates)
        stage = {s: sum(float(c.timings.get(s, 0.0)) for c in rec.certificates) for s in STAGES}
        total = sum(float(c.timings.get("total", 0.0)) for c in rec.certificates)
        pure = pure_inference_seconds(model, calls, int(cfg.batch_size), shape)
        frames.append({"frame": rec.index, "seconds": total, **{f"{s}_s": v for s, v in stage.items()},
                       "classifier_calls": calls, "pure_inference_s": pure,
                       "non_inference_over_inference": (total - stage["inference"]) / max(stage["inference"], 1e-9)})
        for c in rec.certificates:
            rows.append({"frame": rec.index, "axis": c.axis, "status": c.status, "radius": c.radius,
                         "requested": c.requested_radius, "anchors": len(c.bounds.get("anchors", [])),
                         "partitions": c.num_partitions, "calls": c.classifier_calls,
                         **{f"{s}_s": float(c.timings.get(s, 0.0)) for s in STAGES},
                         "total_s": float(c.timings.get("total", 0.0)), "reason": c.reason})
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out = {"bag": str(Path(args.bag)), "frames": frames, "axes": rows, "wall_s": wall, "peak_rss_mb": peak_mb,
           "load_avg": os.getloadavg(), "cpus": os.cpu_count(), "imaging": cfg.imaging}
    if args.json:
        json.dump(out, sys.stdout, indent=1)
        print()
        return 0
    print(f"{args.bag}: {len(frames)} frame(s), imaging {cfg.imaging}, wall {wall:.1f} s, peak RSS {peak_mb:.0f} MB, "
          f"load {', '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} cores")
    print(f"{'frame':>5} {'axis':>4} {'status':>13} {'radius/requested':>22} {'anch':>4} {'N':>4} {'calls':>6} "
          + " ".join(f"{s:>9}" for s in STAGES) + f" {'total':>7}")
    for r in rows:
        print(f"{r['frame']:>5} {r['axis']:>4} {r['status']:>13} {r['radius']:>10.5g}/{r['requested']:<11.5g} "
              f"{r['anchors']:>4} {r['partitions']:>4} {r['calls']:>6} "
              + " ".join(f"{r[s + '_s']:>9.2f}" for s in STAGES) + f" {r['total_s']:>7.2f}")
    print(f"{'frame':>5} {'total s':>8} {'inference s':>12} {'pure inference s':>17} {'(rest)/inference':>17}")
    for f in frames:
        print(f"{f['frame']:>5} {f['seconds']:>8.2f} {f['inference_s']:>12.2f} {f['pure_inference_s']:>17.2f} "
              f"{f['non_inference_over_inference']:>17.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Frames per second on a CUDA device beside the same machine's CPU (issue 34, item 5).

One short script for a lent GPU machine: every case runs with ``device: cpu`` and ``device: cuda`` on
the same machine, in one process, after a warm-up frame (CUDA's start and the model's load are never
charged to a frame), and prints per certificate the seconds spent in each stage (plan, render, bounds,
inference, statistics) and the radius:

* **geometry** -- the never-changing classifier (``pws ceiling --no-model``) at 160x90 on the recordings
  given: the classifier costs nothing, so the time is the imaging model's, and the radii must be
  *identical* on both devices (the bounds are float64 on the renderer's device; a difference is a defect
  of the CUDA kernels, printed as such);
* **demo** -- ``pws replay bags/demo``, shipped model and defaults, every frame;
* **224x224** -- a 224x224 model file (e.g. EfficientNet-Lite0, ``pws export-model``) at ``--sigma-224`` on
  the recordings given (render + bounds + inference at 448x448 rendered, the shipped render factor 2).

The noise of the smoothing is drawn by a generator on the model's device, so the classifier's votes and
hence radii may differ between devices by sampling; the geometry case has no noise to differ by.

Usage (on the device machine; the recordings and the model are copied beside the repository):
    python3 -m pws_ros.bench.gpu --recording kinect=DIR --recording realsense=DIR --model-224 M.pt --out OUT

Writes ``OUT/gpu.json`` (every certificate) and ``OUT/gpu.md`` (the table docs/timings.md quotes).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

STAGES = ("plan", "render", "bounds", "inference", "statistics", "total")


def _machine(torch) -> dict:
    info = {"python": platform.python_version(), "torch": torch.__version__, "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "load_1min": os.getloadavg()[0]}
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info.update(gpu=p.name, gpu_memory_gb=round(p.total_memory / 2**30, 1), cuda=torch.version.cuda)
    return info


def _rows(result, case: str, device: str, wall_s: float) -> list[dict]:
    rows = []
    for rec in result.records:
        for c in rec.certificates:
            row = {"case": case, "device": device, "frame": rec.index, "axis": c.axis, "status": c.status,
                   "label": getattr(c, "label", None), "share": round(c.radius / c.requested_radius, 4),
                   "calls": c.classifier_calls, "anchors": c.num_bounds}
            row.update({k: round(float(c.timings.get(k, 0.0)), 3) for k in STAGES})
            rows.append(row)
    for row in rows:
        row["case_wall_s"] = round(wall_s, 2)
    return rows


def _run(case: str, device: str, opts, *, size=None, frames: int | None = None) -> list[dict]:
    """One warm-up frame, then the timed run."""
    import torch

    from ..replay.ceiling import ceiling
    from ..replay.run import replay

    cfg = replace(opts.config, device=device)
    o = replace(opts, config=cfg, write_output=False, quiet=True)

    def go(max_frames):
        oo = replace(o, max_frames=max_frames)
        if size is not None:
            _, top, _ = ceiling(oo, None, input_size=size)
            return top
        return replay(oo)

    go(1)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    res = go(frames)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return _rows(res, case, device, time.perf_counter() - t)


def _summary(rows: list[dict]) -> list[str]:
    out = ["| case | device | certificates | s per certificate (median) | render | bounds | inference | frames/s | radius share (median) |",
           "|---|---|---|---|---|---|---|---|---|"]
    keys = []
    for r in rows:
        k = (r["case"], r["device"])
        if k not in keys:
            keys.append(k)
    for case, dev in keys:
        rs = [r for r in rows if r["case"] == case and r["device"] == dev]
        nframes = len({r["frame"] for r in rs})
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        out.append(f"| {case} | {dev} | {len(rs)} | {med('total'):.2f} | {med('render'):.2f} | {med('bounds'):.2f} | "
                   f"{med('inference'):.2f} | {nframes / rs[0]['case_wall_s']:.2f} | {med('share'):.2f} |")
    return out


def _compare(rows: list[dict], case: str) -> list[str]:
    """The certificates of one case on cpu against cuda: same status and radius?"""
    by = {}
    for r in rows:
        if r["case"] == case:
            by.setdefault((r["frame"], r["axis"]), {})[r["device"]] = r
    diff = [(k, v["cpu"]["share"], v["cuda"]["share"]) for k, v in sorted(by.items())
            if "cpu" in v and "cuda" in v and (v["cpu"]["share"] != v["cuda"]["share"] or v["cpu"]["status"] != v["cuda"]["status"])]
    same = sum(1 for v in by.values() if "cpu" in v and "cuda" in v) - len(diff)
    line = f"{case}: {same} certificates identical on cpu and cuda, {len(diff)} differ"
    return [line] + [f"  frame {k[0]} {k[1]}: cpu {a} cuda {b}" for k, a, b in diff]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python3 -m pws_ros.bench.gpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", action="append", default=[], metavar="NAME=DIR",
                    help="a real recording (geometry and 224x224 cases), repeatable")
    ap.add_argument("--demo", default="bags/demo", help="the demo recording (default bags/demo; '' skips it)")
    ap.add_argument("--model-224", default="", help="a 224x224 model file ('' skips the 224x224 case)")
    ap.add_argument("--sigma-224", type=float, default=0.12)
    ap.add_argument("--devices", default="cpu,cuda")
    ap.add_argument("--cases", default="geometry,demo,224")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)

    import torch

    from ..bridge.config import PwsConfig
    from ..replay import ReplayOptions

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    devices = [d for d in a.devices.split(",") if d and (not d.startswith("cuda") or torch.cuda.is_available())]
    cases = a.cases.split(",")
    recs = [tuple(s.split("=", 1)) for s in a.recording]
    machine = _machine(torch)
    print(json.dumps(machine), flush=True)
    rows: list[dict] = []

    def note(new):
        rows.extend(new)
        for r in new:
            print(json.dumps(r), flush=True)
        (out / "gpu.json").write_text(json.dumps({"machine": machine, "rows": rows}, indent=1))

    for dev in devices:
        if "geometry" in cases:
            for name, path in recs:
                note(_run(f"geometry {name} 160x90", dev, ReplayOptions(bag=Path(path), config=PwsConfig()),
                          size=(90, 160), frames=1))
        if "demo" in cases and a.demo:
            note(_run("demo", dev, ReplayOptions(bag=Path(a.demo), config=PwsConfig())))
        if "224" in cases and a.model_224:
            cfg = PwsConfig(model_path=a.model_224, sigma=a.sigma_224)
            for name, path in recs:
                note(_run(f"224x224 {name}", dev, ReplayOptions(bag=Path(path), config=cfg), frames=1))
    lines = [f"machine: {json.dumps(machine)}", ""] + _summary(rows) + [""]
    for case in dict.fromkeys(r["case"] for r in rows):
        lines += _compare(rows, case)
    (out / "gpu.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

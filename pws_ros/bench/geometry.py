"""What the geometry of an axis costs, and whether a change kept the certificates (issue 34, item 3).

Run: the never-changing classifier (``pws ceiling --no-model``: the classifier costs nothing, so an axis'
time is its imaging and placement) on the first frames of each recording, one warm-up frame first (the
start is not charged), one torch thread by default, the axes one after another (``axis_threads`` 1); per certificate the seconds of each stage and the
whole certificate (every field but its timings) go to ``--out``:

    python3 -m pws_ros.bench.geometry --recording rs=../shared/data/realsense_single_rgbd --out now.json

Compare: two such files, field by field and with the time ratio per axis. A speed-up must keep the
certificates (radius, anchors, p_A bounds, every ``bounds`` entry):

    python3 -m pws_ros.bench.geometry --compare before.json now.json

Side by side with another version of the code: run this file from each checkout in turn, alternating,
with the load each run reports. An older checkout without it runs this very file against its own package
(``PYTHONPATH=OLD python3 pws_ros/bench/geometry.py ...``: its imports are absolute). Timings on a shared
machine vary by 20-30 % between runs of the same code, so compare rounds, never one pair. Nothing is
asserted about time.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

STAGES = ("plan", "render", "bounds", "inference", "statistics", "total")


def measure(recordings: list[tuple[str, str]], size: tuple[int, int], frames: int = 1, config=None) -> list[dict]:
    """One row per frame and axis of each recording: ``{"recording", "frame", "axis", "certificate", "timings",
    "load"}`` (``config``: a PwsConfig, default the shipped one)."""
    # absolute imports: this file can be run as a script against another checkout's package (module doc)
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.replay import ReplayOptions
    from pws_ros.replay.ceiling import ceiling

    config = config or PwsConfig()
    if hasattr(config, "axis_threads"):   # each axis alone, as it would run on its own (an older checkout has no such key)
        config = config.with_params({"axis_threads": 1})
    rows = []
    for name, path in recordings:
        opts = ReplayOptions(bag=Path(path), config=config, write_output=False, quiet=True,
                             max_frames=int(frames))
        ceiling(replace(opts, max_frames=1), None, input_size=size)   # warm-up: lazy imports, first allocations
        _, top, _ = ceiling(opts, None, input_size=size)
        load = os.getloadavg()[0]
        for rec in top.records:
            for c in rec.certificates:
                d = c.to_dict()
                timings = d.pop("timings")
                rows.append({"recording": name, "frame": rec.index, "axis": c.axis, "certificate": d,
                             "timings": {k: round(float(timings.get(k, 0.0)), 4) for k in STAGES}, "load": load})
    return rows


def compare(before: list[dict], after: list[dict]) -> tuple[list[str], int]:
    """Lines (one per frame and axis: same or which fields differ, and the time ratio) and the number of
    certificates that differ or are missing on one side. The seed is not compared (it names the run)."""
    key = lambda r: (r["recording"], r["frame"], r["axis"])  # noqa: E731
    a, b = {key(r): r for r in before}, {key(r): r for r in after}
    lines, bad = [], 0
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            lines.append(f"{k[0]} frame {k[1]} {k[2]}: only in {'the second' if k not in a else 'the first'} file")
            bad += 1
            continue
        ca, cb = a[k]["certificate"], b[k]["certificate"]
        diff = sorted(f for f in set(ca) | set(cb) if f != "seed" and ca.get(f) != cb.get(f))
        ta, tb = a[k]["timings"]["total"], b[k]["timings"]["total"]
        ratio = f"{ta / tb:.2f}x" if tb > 0 else "-"
        lines.append(f"{k[0]} frame {k[1]} {k[2]}: {'same certificate' if not diff else 'DIFFERS in ' + ', '.join(diff)}; "
                     f"{ta:.2f} s -> {tb:.2f} s ({ratio})")
        bad += bool(diff)
    lines.append(f"{bad} of {len(set(a) | set(b))} certificates differ")
    return lines, bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python3 -m pws_ros.bench.geometry", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", action="append", default=[], metavar="NAME=DIR", help="a recording, repeatable")
    ap.add_argument("--size", default="90x160", metavar="HxW", help="the classifier's input size (default 90x160)")
    ap.add_argument("--frames", type=int, default=1, help="frames per recording (default 1)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--out", help="write the rows here (JSON)")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), help="compare two files written by --out")
    a = ap.parse_args(argv)
    if a.compare:
        lines, bad = compare(*(json.loads(Path(p).read_text())["rows"] for p in a.compare))
        print("\n".join(lines))
        return 1 if bad else 0
    if not a.recording or not a.out:
        ap.error("give --recording NAME=DIR (one or more) and --out FILE, or --compare BEFORE AFTER")
    recs = []
    for spec in a.recording:
        name, sep, path = spec.partition("=")
        if not sep or not Path(path).exists():
            ap.error(f"--recording {spec!r}: expected NAME=DIR of an existing recording")
        recs.append((name, path))
    try:
        h, w = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size {a.size!r}: expected HxW, e.g. 90x160")
    import torch

    torch.set_num_threads(max(1, int(a.threads)))
    t0 = time.perf_counter()
    rows = measure(recs, (h, w), a.frames)
    for r in rows:
        t = r["timings"]
        print(f"{r['recording']} frame {r['frame']} {r['axis']}: {r['certificate']['status']}, "
              f"{r['certificate']['radius'] / r['certificate']['requested_radius']:.1%} of the radius, "
              + ", ".join(f"{k} {t[k]:.2f} s" for k in STAGES) + f" (load {r['load']:.2f})", flush=True)
    out = Path(a.out)
    tmp = out.with_name(out.name + ".part")
    tmp.write_text(json.dumps({"size": [h, w], "threads": int(a.threads), "wall_s": round(time.perf_counter() - t0, 2),
                               "rows": rows}, indent=1))
    tmp.replace(out)   # nothing half written when the run is killed
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

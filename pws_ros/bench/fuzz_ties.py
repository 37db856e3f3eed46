"""Fuzz the paper imaging model's per-segment bounds with depth ties: ``python -m pws_ros.bench.fuzz_ties``.

Tiny clouds on a 6x4 camera, full of near-duplicate depths: copies of a point scaled by 1-3 ulps along
its ray (nearly the same depth, same pixel), exact duplicates with another colour (equal depths) and
equal-depth neighbours (a flat wall), in random index order. For every cloud and every axis, a
uniform grid moving the scene by about one to three pixels is rendered by the production renderer (the
imaging model under test) and :func:`pws_ros.core.audit.audit_bounds` re-renders poses densely inside
every segment and compares the distances it measures itself with the reported bounds
(``pair_bound_sq`` and ``anchor_dist_sq`` of :func:`pws_ros.core.bounds.segment_values`).

Prints the number of (cloud, axis) cases with a violated bound (expected 0), the violations, the poses
checked, the time and the machine load.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from ..core.audit import audit_bounds
from ..core.bounds import segment_values
from ..core.camera import CameraIntrinsics
from ..core.cloud import Cloud
from ..core.errors import PwsError
from ..core.motion import AXES, parse_axis
from ..core.partition import make_grid
from ..core.render import Renderer

CAMERA = CameraIntrinsics(width=6, height=4, fx=5.0, fy=5.0, cx=2.5, cy=1.5)
# motion that moves a point at ~1.5 m by about one pixel of CAMERA
PIXEL_MOTION = {"tx": 0.3, "ty": 0.3, "tz": 0.5, "rx": 0.2, "ry": 0.2, "rz": 0.4}


def ulp_scaled(p: np.ndarray, k: int) -> np.ndarray:
    """``p`` scaled by ``1 + k`` ulps of 1 (the same ray, a depth ``k`` ulps or so farther or nearer)."""
    return p * (1.0 + k * np.finfo(np.float64).eps)


def tie_cloud(rng: np.random.Generator, intr: CameraIntrinsics = CAMERA) -> Cloud:
    """A tiny cloud with near-duplicate and equal depths (see the module doc)."""
    n = int(rng.integers(2, 7))
    depths = rng.choice([1.0, 1.5, 2.0, 0.1 * 13], n) if rng.random() < 0.5 else rng.uniform(0.8, 2.5, n)
    u = rng.integers(0, intr.width, n) + (0.5 if rng.random() < 0.5 else rng.random(n))
    v = rng.integers(0, intr.height, n) + (0.5 if rng.random() < 0.5 else rng.random(n))
    pts = np.stack([(u - 0.5 - intr.cx) / intr.fx * depths, (v - 0.5 - intr.cy) / intr.fy * depths, depths], axis=1)
    extra = []
    for p in pts:
        for _ in range(int(rng.integers(0, 3))):
            kind = rng.integers(0, 3)
            if kind == 0:
                extra.append(ulp_scaled(p, int(rng.choice([-3, -2, -1, 1, 2, 3]))))
            elif kind == 1:
                extra.append(p.copy())
            else:  # an equal-depth neighbour one pixel to the side (a flat wall)
                q = p.copy()
                q[int(rng.integers(0, 2))] += (1 if rng.random() < 0.5 else -1) * p[2] / intr.fx
                extra.append(q)
    if extra:
        pts = np.concatenate([pts, np.array(extra)])
    pts = pts[rng.permutation(len(pts))]
    cols = rng.integers(0, 2, (len(pts), 3)).astype(np.float32)
    return Cloud(pts, cols)


def fuzz_case(rng: np.random.Generator, axis: str, cloud: Cloud, poses_per_segment: int = 64, device: str = "cpu"):
    """Audit one (cloud, axis) case; returns the :class:`~pws_ros.core.audit.AuditReport`."""
    radius = PIXEL_MOTION[axis] * rng.uniform(0.5, 3.0)
    alphas = make_grid(radius, radius / int(rng.integers(1, 5)))
    background = float(rng.choice([0.0, 1.0]))
    values = segment_values(cloud, CAMERA, axis, alphas, background)
    renderer = Renderer(cloud, CAMERA, axis, background=background, device=device)
    anchors = alphas[[0, len(alphas) // 2, -1]]
    return audit_bounds(renderer, alphas, values, anchor_alphas=anchors, poses_per_segment=poses_per_segment,
                        seed=int(rng.integers(0, 2**31)))


def run_fuzz(num_clouds: int, seed: int = 0, poses_per_segment: int = 64, axes=AXES, device: str = "cpu") -> dict:
    """Fuzz ``num_clouds`` clouds on every axis of ``axes``; a summary dict."""
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    failing: dict[str, int] = {a: 0 for a in axes}
    examples = []
    poses = violations = 0
    worst = 0.0
    for c in range(num_clouds):
        cloud = tie_cloud(rng)
        for axis in axes:
            rep = fuzz_case(rng, axis, cloud, poses_per_segment, device)
            poses += rep.poses_checked
            worst = max(worst, rep.worst_ratio)
            if rep.violations:
                failing[axis] += 1
                violations += len(rep.violations)
                if len(examples) < 5:
                    v = rep.violations[0]
                    examples.append({"cloud": c, "axis": axis, "alpha": v.alpha, "kind": v.kind, "segment": v.segment,
                                     "measured": v.measured, "bound": v.bound})
    return {"clouds": num_clouds, "cases": num_clouds * len(axes), "failing_cases": sum(failing.values()),
            "failing_cases_per_axis": failing, "violations": violations, "poses_checked": poses,
            "worst_ratio": worst, "examples": examples, "seconds": time.perf_counter() - t0,
            "device": device, "loadavg": list(os.getloadavg())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.fuzz_ties", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clouds", type=int, default=1000, help="number of fuzzed clouds, each on every axis (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="fuzz seed (default 0)")
    p.add_argument("--poses-per-segment", type=int, default=64, help="re-rendered poses per segment (default 64)")
    p.add_argument("--axes", default=",".join(AXES), help="comma-separated axes (default all six)")
    p.add_argument("--device", default="cpu", help="torch device of the renderer: cpu or cuda[:N] (default cpu)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = p.parse_args(argv)
    try:
        axes = [parse_axis(a) for a in args.axes.split(",") if a.strip()]
        out = run_fuzz(args.clouds, args.seed, args.poses_per_segment, axes, args.device)
    except PwsError as exc:
        print(f"fuzz_ties: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        per_axis = ", ".join(f"{a} {n}" for a, n in out["failing_cases_per_axis"].items())
        print(f"fuzz_ties: {out['failing_cases']} of {out['cases']} (cloud, axis) cases violate a bound ({per_axis}); "
              f"{out['violations']} violating poses of {out['poses_checked']} checked; worst measured/bound "
              f"{out['worst_ratio']:.6g}")
        for e in out["examples"]:
            print(f"  e.g. cloud {e['cloud']} {e['axis']} alpha={e['alpha']!r} {e['kind']} segment {e['segment']}: "
                  f"{e['measured']:.6g} > {e['bound']:.6g}")
        print(f"time {out['seconds']:.1f} s on {out['device']}, load average {', '.join(f'{x:.2f}' for x in out['loadavg'])} (1/5/15 min)")
    return 1 if out["failing_cases"] else 0


if __name__ == "__main__":
    sys.exit(main())

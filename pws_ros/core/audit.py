"""Self-audit of per-segment bounds: re-render poses inside every segment and check each bound directly.

A certificate rests on two kinds of bound for every segment ``[alpha_i, alpha_{i+1}]`` of a plan:

* ``pair_bound_sq[i] >= |x(alpha) - x_i|^2 + |x(alpha) - x_{i+1}|^2`` (paper and pairwise coverage), and
* ``anchor_dist_sq(y)[i] >= |x(alpha) - y|^2`` for every anchor frame ``y`` (anchor coverage),

for every ``alpha`` in the segment. :func:`audit_bounds` samples ``alpha`` densely in each segment (its
ends, the float neighbours of its ends, and uniform random interior points), renders those poses through
the same imaging model (any object with ``render_batch(alphas) -> (B, H, W, 3)``), measures the distances
with its own plain float64 code and reports every pose where a measured distance exceeds its bound.
It knows nothing of how the bounds were computed: ``bounds`` only needs the two methods of
:class:`.bounds.SegmentValues` (``pair_bound_sq(frames, k0)`` and ``anchor_dist_sq(frames, anchor, k0)``).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .errors import require

DEFAULT_POSES_PER_SEGMENT = 64
# float neighbours of each segment end that are checked (1 and 2 ulps inside the segment)
END_NEIGHBOURS = 2
POSE_CHUNK = 64  # poses rendered at a time


@dataclass
class Violation:
    """A pose where a measured squared distance exceeds its bound: ``kind`` is ``pair`` or ``anchor``
    (then ``anchor`` is the anchor's index in ``anchor_alphas``)."""

    kind: str
    segment: int
    alpha: float
    measured: float
    bound: float
    anchor: int | None = None


@dataclass
class AuditReport:
    """Result of :func:`audit_bounds`: poses rendered and checked, the largest measured / bound ratio over
    every check (``inf`` if a bound of 0 was exceeded), and every violation."""

    segments: int
    poses_checked: int
    checks: int
    worst_ratio: float
    violations: list[Violation] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.violations

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["ok"] = self.ok
        d["num_violations"] = len(self.violations)
        return d


def segment_poses(a0: float, a1: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` motion values in ``[a0, a1]``: both ends, up to ``END_NEIGHBOURS`` float neighbours of each
    end inside the segment, the rest uniform random interior points (sorted, possibly repeated)."""
    a0, a1 = float(a0), float(a1)
    out = [a0, a1]
    up, down = a0, a1
    for _ in range(END_NEIGHBOURS):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        out += [min(up, a1), max(down, a0)]
    out = out[:count]
    rest = count - len(out)
    if rest > 0:
        out += list(np.minimum(a0 + rng.random(rest) * (a1 - a0), a1))
    return np.sort(np.asarray(out, dtype=np.float64))


def _frames(renderer, alphas) -> np.ndarray:
    fr = renderer.render_batch(np.asarray(alphas, dtype=np.float64))
    if hasattr(fr, "detach"):
        fr = fr.detach().cpu().numpy()
    return np.asarray(fr, dtype=np.float64)


def _sq_dist(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per frame ``sum over pixels and channels of (x - y)^2`` in float64."""
    return ((x - y) ** 2).reshape(len(x), -1).sum(axis=1)


def audit_bounds(renderer, alphas, bounds, anchor_alphas=None, poses_per_segment: int = DEFAULT_POSES_PER_SEGMENT,
                 seed: int = 0, segments_per_block: int = 16) -> AuditReport:
    """Check ``bounds`` on ``poses_per_segment`` re-rendered poses inside every segment of the grid ``alphas``.

    ``renderer.render_batch(alphas)`` renders frames (torch or numpy, ``(B, H, W, 3)``); ``bounds`` has
    ``pair_bound_sq(frames, k0)`` and ``anchor_dist_sq(frames, anchor, k0)``; ``anchor_alphas`` (optional)
    are the poses whose frames serve as anchors. Segments are processed ``segments_per_block`` at a time
    (memory stays bounded).
    """
    t_start = time.perf_counter()
    alphas = np.asarray(alphas, dtype=np.float64).reshape(-1)
    require(len(alphas) >= 2, f"an audit needs a grid of at least 2 motion values, got {len(alphas)}")
    require(bool(np.all(np.isfinite(alphas))) and bool(np.all(np.diff(alphas) > 0)),
            "the grid must be finite and strictly increasing")
    require(int(poses_per_segment) >= 2, f"poses_per_segment must be >= 2, got {poses_per_segment}")
    rng = np.random.default_rng(seed)
    anchor_alphas = np.zeros(0) if anchor_alphas is None else np.asarray(anchor_alphas, dtype=np.float64).reshape(-1)
    anchors = _frames(renderer, anchor_alphas) if len(anchor_alphas) else np.zeros((0,))
    nseg = len(alphas) - 1
    violations: list[Violation] = []
    worst = 0.0
    poses = checks = 0

    def check(kind, k, a, measured, bound, anchor=None):
        nonlocal worst
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(measured > 0, measured / bound, 0.0)
        worst = max(worst, float(ratio.max()))
        for j in np.nonzero(measured > bound)[0]:
            violations.append(Violation(kind, int(k), float(a[j]), float(measured[j]), float(bound), anchor))

    for k0 in range(0, nseg, segments_per_block):
        k1 = min(nseg, k0 + segments_per_block)
        ends = _frames(renderer, alphas[k0 : k1 + 1])
        pair = np.asarray(bounds.pair_bound_sq(ends, k0), dtype=np.float64)
        require(pair.shape == (k1 - k0,), f"pair_bound_sq returned shape {pair.shape}, expected ({k1 - k0},)")
        dist = [np.asarray(bounds.anchor_dist_sq(ends, y, k0), dtype=np.float64) for y in anchors]
        for k in range(k0, k1):
            i = k - k0
            poses_k = segment_poses(alphas[k], alphas[k + 1], int(poses_per_segment), rng)
            for s in range(0, len(poses_k), POSE_CHUNK):
                a = poses_k[s : s + POSE_CHUNK]
                x = _frames(renderer, a)
                poses += len(a)
                check("pair", k, a, _sq_dist(x, ends[i][None]) + _sq_dist(x, ends[i + 1][None]), pair[i])
                checks += len(a)
                for j, y in enumerate(anchors):
                    check("anchor", k, a, _sq_dist(x, y[None]), dist[j][i], anchor=j)
                    checks += len(a)
    return AuditReport(nseg, poses, checks, worst, violations, time.perf_counter() - t_start)

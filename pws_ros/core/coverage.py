"""Coverage rules: which segments of the plan the p_A bounds cover, hence the certified radius.

Every rule reads the same two things: the Cohen radii ``R`` of the p_A lower bounds it estimated (one
per *estimation frame*: at the Bonferroni level ``alpha / K`` with ``K`` = the number of those frames, or for the
adaptive anchors the levels of their looks, :mod:`.sequential`)
and sound per-segment distance bounds of the imaging model (:class:`.surfel_bounds.HullValues`,
:class:`.bounds.SegmentValues`). Segment ``i`` joins grid points ``i`` and ``i + 1``; the centre
``alphas[centre]`` is 0. A rule returns which segments it covers; the radius is the symmetric run of
covered segments around 0 (:func:`symmetric_reach` on a grid symmetric about 0, :func:`covered_radius`
on any grid).

* :class:`PaperRule` (the paper's Theorem 1, with sound bounds): p_A at every frame (``K = N``);
  ``[-b_j, b_j]`` is covered when ``max sqrt(B_i / 2) < min R`` over its segments and frames, ``B_i``
  bounding ``|x - x_i|^2 + |x - x_{i+1}|^2`` for every frame ``x`` of segment ``i``.
* :class:`PairwiseRule`: p_A at every frame (``K = N``); segment ``i`` is covered when
  ``B_i < R_i^2 + R_{i+1}^2`` (every ``x`` of it is then within ``R_i`` of ``x_i`` or within ``R_{i+1}``
  of ``x_{i+1}``).
* :class:`AnchorsRule`: p_A at ``K`` anchor frames only; segment ``i`` is covered by any anchor ``a``
  with ``D_i(x_a) < R_a`` (every ``x`` of it within ``R_a`` of ``x_a``); the ``K`` anchors are evenly
  spread (:func:`anchor_indices`), fixed before any sample is drawn.
* :class:`AdaptiveAnchorsRule` (``anchors`` with surfel imaging): the anchors rule on at most
  ``num_anchors`` anchors placed from the distance bounds and the ``n0`` selection samples (``K`` = the
  anchors placed, ``<= num_anchors``); the set is fixed before the estimation samples are drawn, so the
  ``K`` bounds at ``alpha / K`` stay valid (:mod:`.anchors`). The radius is the covered run around 0
  on the refined grid, extended by :func:`frontier_reach` where it stops inside a grid segment.

Every rule covers a segment only if every frame of it lies strictly within the Cohen radius of an
estimated frame, so the smoothed prediction is constant on the covered interval with probability at
least ``1 - alpha`` (Bonferroni over the ``K`` bounds). :func:`packing_bound` is a lower bound on the
anchors any rule with given radii needs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .smoothing import cohen_radius

COVERAGES = ("paper", "pairwise", "anchors")   # the coverage settings, in the order the bench reports them


def cohen_radii(p_a_lower, sigma: float) -> np.ndarray:
    """Cohen radii ``R_i`` of the p_A lower bounds (0 where p_A <= 1/2; finite where p_A = 1)."""
    R = np.asarray(cohen_radius(np.asarray(p_a_lower, dtype=np.float64), sigma), dtype=np.float64).reshape(-1)
    return np.where(np.isfinite(R), R, np.finfo(np.float64).max)


def anchor_indices(num_partitions: int, num_anchors: int) -> np.ndarray:
    """``K`` anchors evenly spread over the grid, always including the centre (``alpha = 0``)."""
    m = num_partitions // 2
    k = max(1, min(int(num_anchors), num_partitions))
    idx = np.unique(np.round(np.linspace(0, num_partitions - 1, k)).astype(np.int64))
    return np.unique(np.concatenate([idx, [m]]))


def symmetric_reach(covered: np.ndarray, centre: int) -> int:
    """Largest ``j`` such that segments ``centre-j .. centre+j-1`` are all covered."""
    nseg = len(covered)
    j = 0
    while j < centre and centre + j < nseg and covered[centre - j - 1] and covered[centre + j]:
        j += 1
    return j


def covered_run(covered: np.ndarray, alphas: np.ndarray, centre: int) -> tuple[float, float]:
    """``(alpha_lo, alpha_hi)``: the run of covered segments around the grid point ``centre`` (alpha = 0)."""
    hi = centre
    while hi < len(covered) and covered[hi]:
        hi += 1
    lo = centre - 1
    while lo >= 0 and covered[lo]:
        lo -= 1
    return float(alphas[lo + 1]), float(alphas[hi])


def covered_radius(covered: np.ndarray, alphas: np.ndarray, centre: int) -> float:
    """Largest ``r`` such that every segment inside ``[-r, r]`` is covered (the grid need not be symmetric):
    the smaller of the covered runs from ``alpha = 0`` to the right and to the left."""
    lo, hi = covered_run(covered, alphas, centre)
    return min(hi, -lo)


def paper_reach(pair_bound_sq: np.ndarray, R: np.ndarray, centre: int) -> int:
    """Largest ``j`` with ``max sqrt(B / 2) < min R`` over segments ``centre-j .. centre+j-1`` and partitions
    ``centre-j .. centre+j`` (the paper's rule on each symmetric sub-interval)."""
    Mseg = np.sqrt(np.asarray(pair_bound_sq, dtype=np.float64) / 2)
    j = 0
    while j < centre and Mseg[centre - j - 1 : centre + j + 1].max() < R[centre - j - 1 : centre + j + 2].min():
        j += 1
    return j


def packing_bound(frames: np.ndarray, radius: float) -> int:
    """A lower bound on the anchors of radius at most ``radius`` that cover ``frames``: the size of a set of
    them pairwise at least ``2 radius`` apart (picked greedily in order), since one anchor ``a`` covers
    ``x`` and ``y`` only if ``|x - y| <= |x - x_a| + |x_a - y| < 2 R_a``."""
    picked: list[tuple[np.ndarray, float]] = []   # a picked frame and its distance from the first frame
    lim = (2.0 * radius) ** 2
    ref = None
    for x in frames:
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        ref = x if ref is None else ref
        nx = math.sqrt(float(np.sum((x - ref) ** 2)))
        if all(_apart(x, nx, y, ny, lim) for y, ny in picked):
            picked.append((x, nx))
    return len(picked)


PACKING_SLACK = 1e-9   # relative rounding of a sum of squares of up to 10^6 float64 terms (n u), with room


def _apart(x: np.ndarray, nx: float, y: np.ndarray, ny: float, lim: float) -> bool:
    """``float(np.sum((x - y) ** 2)) >= lim`` (:func:`packing_bound`'s test), its sum skipped where the triangle
    inequality through the first frame ``z`` proves it: ``|x - y| >= ||x - z| - |y - z||``, with ``nx``, ``ny`` those
    distances as computed (relative error below ``PACKING_SLACK``; the sum of squares too), so the test comes out as
    the sum's would."""
    gap = abs(nx - ny) - PACKING_SLACK * (nx + ny)
    if gap > 0 and gap * gap >= lim * (1.0 + 2.0 * PACKING_SLACK):
        return True
    return float(np.sum((x - y) ** 2)) >= lim


FRONTIER_PARTS = 4     # the first uncovered segment is cut into this many parts per round (frontier_reach; one batch of bounds)
FRONTIER_ROUNDS = 4    # rounds per side: the frontier is resolved to 1 / 4^4 of the segment


def frontier_reach(covers: Callable[[np.ndarray], np.ndarray], alphas: np.ndarray, covered: np.ndarray, centre: int,
                   parts: int = FRONTIER_PARTS, rounds: int = FRONTIER_ROUNDS) -> tuple[float, list[float]]:
    """The covered radius after refining the first segments the grid leaves uncovered.

    ``covers(g)`` says, for each segment ``[g[k], g[k+1]]`` of an increasing grid ``g``, whether some
    estimated frame is within its Cohen radius of every frame of it (sound bounds of those segments; one
    call bounds a whole batch). On the right, the first uncovered grid segment ``[a, b]`` is cut into
    ``parts`` equal parts: the covered run grows over the covered ones from ``a`` and the first uncovered
    part is cut next (if every part is covered the run reaches ``b`` and goes on along the grid);
    likewise on the left, at most ``rounds`` times a side. The side whose run is shorter is refined first
    (the radius is the smaller run; the other side only once it limits). Returns (the symmetric covered
    radius on the grid with the new points, those points).

    Why it may run after the estimation samples: the ``K`` p_A bounds are fixed (and their Bonferroni
    level) before any sample is drawn; whether a segment is covered is then a deterministic fact of the
    sound distance bounds, true on the event that all ``K`` bounds hold, whatever grid it is checked on.
    So a grid chosen from the estimated radii keeps the frame's risk at ``alpha``.
    """
    S = len(covered)
    points: list[float] = []

    def scan_right(i: int):
        while i < S and covered[i]:
            i += 1
        return float(alphas[i]), ((float(alphas[i]), float(alphas[i + 1]), i) if i < S else None)

    def scan_left(i: int):
        while i >= 0 and covered[i]:
            i -= 1
        return -float(alphas[i + 1]), ((float(alphas[i]), float(alphas[i + 1]), i) if i >= 0 else None)

    right, r_open = scan_right(centre)
    left, l_open = scan_left(centre - 1)
    used = {"r": 0, "l": 0}
    while True:
        side = "r" if right <= left else "l"
        seg = r_open if side == "r" else l_open
        if seg is None or used[side] >= int(rounds):
            break          # the limiting side cannot grow: the radius is final
        a, b, i = seg
        g = a + (b - a) * np.arange(int(parts) + 1) / int(parts)
        g[0], g[-1] = a, b
        if not np.all(np.diff(g) > 0):   # float resolution reached
            if side == "r":
                r_open = None
            else:
                l_open = None
            continue
        used[side] += 1
        points.extend(float(x) for x in g[1:-1])
        cov = np.asarray(covers(g), dtype=bool)
        if side == "r":
            k = int(np.argmin(cov)) if not cov.all() else len(cov)   # covered parts from a
            if k == len(cov):
                right, r_open = scan_right(i + 1)
            else:
                right, r_open = float(g[k]), (float(g[k]), float(g[k + 1]), i)
        else:
            rev = cov[::-1]                                            # covered parts from b
            k = int(np.argmin(rev)) if not rev.all() else len(rev)
            if k == len(rev):
                left, l_open = scan_left(i - 1)
            else:
                m = len(cov) - k                                       # parts m .. end are covered
                left, l_open = -float(g[m]), (float(g[m - 1]), float(g[m]), i)
    return min(right, left), points


def segment_covers(hulls: Callable[[np.ndarray], object], anchor_frames: np.ndarray, R: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """``covers(g)`` for :func:`frontier_reach`: per segment of the grid ``g``, whether some anchor ``k`` has
    ``D_i(x_k)^2 < R_k^2`` on the bounds ``hulls(g)`` (an object with ``dist_sq(y)`` per segment, e.g.
    :class:`.surfel_bounds.HullValues`)."""
    R2 = np.asarray(R, dtype=np.float64) ** 2

    def covers(g: np.ndarray) -> np.ndarray:
        h = hulls(np.asarray(g, dtype=np.float64))
        out = np.zeros(len(g) - 1, dtype=bool)
        for y, r2 in zip(anchor_frames, R2):
            if r2 > 0:
                out |= h.dist_sq(y) < r2
        return out

    return covers


class _EveryFrame:
    """A rule with a p_A bound at every frame of the plan (``K = N``), read with the pair bounds."""

    uses_anchor_distances = False
    adaptive = False

    def estimation_indices(self, num_partitions: int) -> np.ndarray:
        return np.arange(num_partitions)


@dataclass(frozen=True)
class PaperRule(_EveryFrame):
    """The paper's rule (module doc). ``covered_count`` = 2 j segments."""

    name = "paper"

    def reach(self, R: np.ndarray, centre: int, *, pair_bound_sq: np.ndarray, anchor_dist_sq=None) -> tuple[int, int]:
        """(``j``: segments ``centre-j .. centre+j-1`` covered, segments covered)."""
        j = paper_reach(pair_bound_sq, R, centre)
        return j, 2 * j


@dataclass(frozen=True)
class PairwiseRule(_EveryFrame):
    """Segment ``i`` covered when ``B_i < R_i^2 + R_{i+1}^2`` (module doc)."""

    name = "pairwise"

    def covered(self, R: np.ndarray, *, pair_bound_sq: np.ndarray, anchor_dist_sq=None) -> np.ndarray:
        return np.asarray(pair_bound_sq) < R[:-1] ** 2 + R[1:] ** 2

    def reach(self, R: np.ndarray, centre: int, *, pair_bound_sq: np.ndarray, anchor_dist_sq=None) -> tuple[int, int]:
        covered = self.covered(R, pair_bound_sq=pair_bound_sq)
        return symmetric_reach(covered, centre), int(covered.sum())


@dataclass(frozen=True)
class AnchorsRule:
    """Segment ``i`` covered by an anchor ``a`` with ``D_i(x_a) < R_a`` (``anchor_dist_sq``: (K, S)); the
    ``num_anchors`` evenly spread anchors of :func:`anchor_indices`, or any fixed set (:mod:`.anchors`)."""

    num_anchors: int = 9
    name = "anchors"
    uses_anchor_distances = True
    adaptive = False

    def estimation_indices(self, num_partitions: int) -> np.ndarray:
        return anchor_indices(num_partitions, self.num_anchors)

    def covered(self, R: np.ndarray, *, anchor_dist_sq: np.ndarray, pair_bound_sq=None) -> np.ndarray:
        return np.any(np.asarray(anchor_dist_sq) < (np.asarray(R)[:, None] ** 2), axis=0)

    def reach(self, R: np.ndarray, centre: int, *, anchor_dist_sq: np.ndarray, pair_bound_sq=None) -> tuple[int, int]:
        covered = self.covered(R, anchor_dist_sq=anchor_dist_sq)
        return symmetric_reach(covered, centre), int(covered.sum())


@dataclass(frozen=True)
class AdaptiveAnchorsRule(AnchorsRule):
    """The anchors of surfel imaging: at most ``num_anchors`` grid frames placed from the distance bounds
    and the selection samples (:func:`.anchors.place_anchors`, before the estimation samples are drawn),
    then covered as :class:`AnchorsRule` with ``K`` = the anchors placed; the radius is
    :func:`covered_radius` (the grid is refined where frames differ, so it need not be symmetric)."""

    adaptive = True

    def place(self, dist_sq_row, alphas: np.ndarray, centre: int, target: float,
              rows_out: dict | None = None, budget: int | None = None) -> np.ndarray:
        """Grid indices of at most ``budget`` (default ``num_anchors``) anchors (the centre first) for the
        target Cohen radius ``target`` (``rows_out`` receives each anchor's distance row,
        :func:`.anchors.place_anchors`)."""
        from .anchors import place_anchors

        return np.array(place_anchors(dist_sq_row, alphas, centre, target ** 2, int(budget or self.num_anchors), partial=True,
                                      rows_out=rows_out), dtype=np.int64)

    def predicted_reach(self, anchor_rows: dict, est_idx: np.ndarray, alphas: np.ndarray, centre: int, radius: float) -> float:
        """The radius the anchors ``est_idx`` (their rows in ``anchor_rows``) would cover if each got the
        Cohen radius ``radius`` (a planning value)."""
        if radius <= 0 or len(est_idx) == 0:
            return 0.0
        D2 = np.stack([anchor_rows[int(a)] for a in est_idx])
        return self.radius(np.full(len(est_idx), float(radius)), D2, alphas, centre)[0]

    def radius(self, R: np.ndarray, anchor_dist_sq: np.ndarray, alphas: np.ndarray, centre: int) -> tuple[float, np.ndarray]:
        """(covered radius, covered segments)."""
        covered = self.covered(R, anchor_dist_sq=anchor_dist_sq)
        return covered_radius(covered, alphas, centre), covered


def coverage_rule(name: str, num_anchors: int = 9, imaging: str = "paper"):
    """The rule object of a ``coverage`` setting (paper, pairwise, anchors) under an imaging kind: with
    surfel imaging the anchors are placed adaptively (:class:`AdaptiveAnchorsRule`)."""
    anchors = AdaptiveAnchorsRule(int(num_anchors)) if imaging == "surfel" else AnchorsRule(int(num_anchors))
    rules = {"paper": PaperRule(), "pairwise": PairwiseRule(), "anchors": anchors}
    if name not in rules:
        from .errors import PwsError

        raise PwsError(f"unknown coverage rule {name!r}: expected one of {', '.join(rules)}")
    return rules[name]


__all__ = ["COVERAGES", "FRONTIER_PARTS", "FRONTIER_ROUNDS", "AdaptiveAnchorsRule", "AnchorsRule", "PairwiseRule", "PaperRule", "anchor_indices", "cohen_radii",
           "covered_radius", "covered_run", "coverage_rule", "frontier_reach", "segment_covers",
           "packing_bound", "paper_reach", "symmetric_reach"]

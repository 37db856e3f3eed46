"""Anchors from the distance profile: where to estimate ``p_A`` so that every segment is covered.

Given sound distance bounds ``D_i(x_j)^2`` (every frame of segment ``i`` lies within ``D_i(x_j)`` of the
grid frame ``x_j``, :class:`.imaging.HullValues`) and a *target* Cohen radius ``r`` predicted from the
selection samples, :func:`place_anchors` picks grid frames greedily, outward from ``alpha = 0`` and
balancing both sides (the certified radius is symmetric), so that every segment it reaches has an anchor
within ``r``; it stops at ``max_anchors`` (the budget: ``n0 + max_anchors * n`` classifier calls) or when a
segment cannot be covered by any nearby grid frame.

Why Bonferroni stays valid: the anchor set is a function of the plan, the bounds and the ``n0``
selection samples only. The ``n`` estimation samples of each anchor are drawn afterwards, independent
of those, so conditionally on the anchor set the ``K`` Clopper-Pearson bounds at level ``alpha / K``
fail together with probability at most ``alpha`` (the same argument as Cohen et al.'s separate
selection and estimation samples); the joint first look's split of ``alpha`` over its looks
(:mod:`.sequential`) rests on the same conditioning.
"""
from __future__ import annotations

import functools
from typing import Callable

import numpy as np
from scipy.special import gammaln

from .partition import Plan
from .smoothing import clopper_pearson_lower, cohen_radius

REFINE_FRACTION = 2.0  # grid segments whose end frames differ by more than target / this are subdivided
REFINE_ROUNDS = 2      # rounds of that subdivision where the anchors of the first fall short (core.anchored)
FIRST_ROUND_SHARE = 0.5  # of the room the grid cap leaves, the first round may take (the rest: the rounds after it)
TARGET_MARGIN = 0.95   # the target radius is this fraction of the radius the selection samples predict
SEARCH_WINDOW = 16     # grid frames beyond the first uncovered segment tried as the next anchor
PLAN_QUANTILE = 0.75   # a unanimous selection: the votes planned for are this quantile of their predictive


def planned_votes(rate: float, m: int, n0: int) -> int:
    """The votes of ``m`` samples a plan counts on at the vote rate ``rate`` the ``n0`` selection samples
    gave: ``floor(m * rate)``, and where the selection was unanimous (``rate`` 1) the PLAN_QUANTILE
    quantile of the ``m`` votes' posterior predictive (a uniform prior: ``p ~ Beta(n0 + 1, 1)``, the votes
    beta-binomial; all ``m`` while ``P(all m) = (n0 + 1) / (n0 + m + 1) > 1 - PLAN_QUANTILE``). A
    selection cannot tell ``p_A = 0.98`` from 1 (0.98^64 = 0.27): read as ``p_A = 1``, it predicted for
    1,024 samples a unanimous look where 1,005 votes came; the anchors, placed for that, left gaps, and more
    samples per anchor certified less (issue 34). A planning value only: soundness never rests on it."""
    if rate < 1.0:
        return int(np.floor(int(m) * max(0.0, float(rate))))
    return _unanimous_votes(int(m), int(n0), PLAN_QUANTILE)


@functools.lru_cache(maxsize=4096)
def _unanimous_votes(m: int, n0: int, quantile: float) -> int:
    """:func:`planned_votes` after a unanimous selection (remembered: the plans ask for it every frame)."""
    # the votes X ~ BetaBinomial(m, n0 + 1, 1): P(X = k) = a m! Gamma(k + a) / (k! Gamma(m + a + 1)), a = n0 + 1; the
    # least k with P(X <= k) at least the quantile (the cumulative sums never decrease), as scipy.stats.betabinom.ppf
    # (the same k on every (m, n0) compared; that module's import costs about a second of a command's start)
    a = n0 + 1.0
    k = np.arange(m + 1, dtype=np.float64)
    cdf = np.cumsum(np.exp(np.log(a) + gammaln(m + 1.0) - gammaln(m + a + 1.0) + gammaln(k + a) - gammaln(k + 1.0)))
    return min(m, int(np.searchsorted(cdf, quantile - 1e-9)))   # a float tie (m = 3 n0 + 3) goes below


def target_radius(k0: int, n0: int, n: int, sigma: float, alpha: float, max_anchors: int) -> float:
    """The Cohen radius an anchor will likely get: the selection frequency ``k0 / n0`` carried over to
    ``n`` estimation samples (:func:`planned_votes`) at the worst Bonferroni level ``alpha / max_anchors``,
    times TARGET_MARGIN (0 when the prediction is not above 1/2). A planning value only: soundness never
    rests on it."""
    k_hat = planned_votes(int(k0) / max(1, int(n0)), n, n0)
    p = float(clopper_pearson_lower(k_hat, n, alpha / max(1, max_anchors)))
    if p <= 0.5:
        return 0.0
    return TARGET_MARGIN * float(cohen_radius(p, sigma))


def predicted_target(k_hat: int, n: int, sigma: float, level: float, margin: float = 1.0) -> float:
    """``margin`` times the Cohen radius of ``k_hat`` votes of ``n`` at the level ``level`` (0 when the bound
    is not above 1/2): the target of a joint first look (:mod:`.sequential`; a planning value). No margin by
    default: a unanimous look gives exactly this radius, and an anchor a miss leaves short gets its next look."""
    p = float(clopper_pearson_lower(int(k_hat), int(n), float(level)))
    return float(margin) * float(cohen_radius(p, sigma)) if p > 0.5 else 0.0


ROW_BLOCK = 8          # segments per lazily computed piece of a candidate's distance row


def place_anchors(dist_sq_row: Callable[..., np.ndarray], alphas: np.ndarray, centre: int, target_sq: float,
                  max_anchors: int, *, partial: bool = False, rows_out: dict[int, np.ndarray] | None = None) -> list[int]:
    """Grid indices of the anchors (the centre first). ``dist_sq_row(j)`` returns ``D_i(x_j)^2`` for every
    segment ``i`` (segment ``i`` joins grid points ``i`` and ``i + 1`` of ``alphas``; ``alphas[centre]`` = 0);
    with ``partial``, ``dist_sq_row(j, i0, i1)`` returns them for segments ``i0 .. i1 - 1`` only, and a
    candidate's row is computed only as far as the search needs it (the chosen anchors' rows in full).
    ``rows_out`` (a dict) receives the full row of every anchor placed (computed once)."""
    S = len(alphas) - 1
    rows: dict[int, np.ndarray] = {}
    known: dict[int, np.ndarray] = {}

    def part(j: int, i0: int, i1: int) -> np.ndarray:
        """``D_i(x_j)^2`` for ``i0 <= i < i1``."""
        i0, i1 = max(0, i0), min(S, i1)
        if j in rows:
            return rows[j][i0:i1]
        if not partial:
            rows[j] = np.asarray(dist_sq_row(j), dtype=np.float64)
            return rows[j][i0:i1]
        vals, done = known.setdefault(j, np.full(S, np.nan)), known.get(-1 - j)
        if done is None:
            done = known[-1 - j] = np.zeros(S, bool)
        for b0 in range(i0 - i0 % ROW_BLOCK, i1, ROW_BLOCK):
            b1 = min(S, b0 + ROW_BLOCK)
            if not done[b0:b1].all():
                vals[b0:b1] = np.asarray(dist_sq_row(j, b0, b1), dtype=np.float64)
                done[b0:b1] = True
        return vals[i0:i1]

    def row(j: int) -> np.ndarray:
        return part(j, 0, S)

    def reach_with(j: int, side: str) -> float:
        """How far the covered run reaches on ``side`` with ``j`` added (its row read only as needed)."""
        if side == "r":
            f = frontier_right(covered)
            while f < S:
                blk = slice(f, min(S, f + ROW_BLOCK))
                ok = covered[blk] | (part(j, blk.start, blk.stop) < target_sq)
                if ok.all():
                    f = blk.stop
                    continue
                f += int(np.argmin(ok))
                break
            return float(alphas[f])
        f = frontier_left(covered)
        while f >= 0:
            blk = slice(max(0, f - ROW_BLOCK + 1), f + 1)
            ok = (covered[blk] | (part(j, blk.start, blk.stop) < target_sq))[::-1]
            if ok.all():
                f = blk.start - 1
                continue
            f -= int(np.argmin(ok))
            break
        return -float(alphas[f + 1])

    anchors = [centre]
    covered = row(centre) < target_sq
    if target_sq <= 0:
        return _with_rows(anchors, row, rows_out)

    def frontier_right(cov):
        f = centre
        while f < S and cov[f]:
            f += 1
        return f  # first uncovered segment on the right (S if none)

    def frontier_left(cov):
        f = centre - 1
        while f >= 0 and cov[f]:
            f -= 1
        return f  # first uncovered segment on the left (-1 if none)

    blocked = {"r": False, "l": False}
    while len(anchors) < max_anchors:
        fr, fl = frontier_right(covered), frontier_left(covered)
        reach_r, reach_l = float(alphas[fr]), -float(alphas[fl + 1])
        open_r = fr < S and not blocked["r"]
        open_l = fl >= 0 and not blocked["l"]
        if not open_r and not open_l:
            break
        # the symmetric radius is the smaller reach: extend that side; stop once the other side is
        # blocked below this one's reach (more anchors there would not widen the certificate)
        side = "r" if open_r and (not open_l or reach_r <= reach_l) else "l"
        if (side == "r" and (fl >= 0 and blocked["l"]) and reach_r >= reach_l) or \
           (side == "l" and (fr < S and blocked["r"]) and reach_l >= reach_r):
            break
        seg = fr if side == "r" else fl
        if side == "r":
            cands = range(seg, min(S, seg + SEARCH_WINDOW) + 1)
        else:
            cands = range(seg + 1, max(0, seg + 1 - SEARCH_WINDOW) - 1, -1)
        best, best_reach = None, -1.0
        for j in cands:
            if j in anchors or not part(j, seg, seg + 1)[0] < target_sq:
                continue
            reach = reach_with(j, side)
            if reach > best_reach:
                best, best_reach = j, reach
        if best is None:
            blocked[side] = True
            continue
        anchors.append(best)
        covered |= row(best) < target_sq
    return _with_rows(anchors, row, rows_out)


def budget_ladder(max_anchors: int) -> list[int]:
    """The budgets below ``max_anchors`` a placement is also tried with (:func:`best_placement`): 1, 2, 3,
    4, 6, 8, 12, 16, 24, 32, 48, ... (powers of two and three times them), largest first."""
    out, k = set(), 1
    while k < max_anchors:
        out.update(b for b in (k, 3 * k) if b < max_anchors)
        k *= 2
    return sorted(out, reverse=True)


def best_placement(rule, dist_sq_row: Callable[..., np.ndarray], alphas: np.ndarray, centre: int, max_anchors: int,
                   target_of: Callable[[int], float], limit: float, first: tuple | None = None) -> tuple:
    """The anchors, among placements for at most ``max_anchors``, predicted to reach farthest: the budget
    is an upper bound (issue 34: a larger one must not certify less).

    A placement is predicted to reach the radius its anchors cover if each gets ``target_of(K)``, the
    Cohen radius the selection samples predict at the level ``alpha / K`` of the ``K`` anchors used; of a
    placement, the first ``j`` anchors (:func:`best_prefix`) are kept where they reach farther at their
    own level (an anchor that widens neither side costs every other one some radius). The budget's own
    placement (``first``, if already made) is tried first, then the smaller budgets of
    :func:`budget_ladder`, largest first, while the placement before was stopped by the grid (a segment no
    grid frame nearby covers at its target): a smaller budget places at a larger target, so it may pass
    that segment (RealSense frame, 224x224, ry: ...). A placement that fit its whole budget ends the
    search (it was limited by its count; fewer anchors would cover less), as does a reach of ``limit``
    (the requested radius). Of equal reaches the earlier placement and the longer prefix are kept (the
    budget's own anchors unless fewer are predicted to reach farther).

    Only the bounds and the selection samples are used: the anchors, hence the Bonferroni ``K``, are fixed
    before any estimation sample is drawn. ``dist_sq_row(j, i0, i1)`` as in :func:`place_anchors`
    (partial); its blocks are computed once for all the placements. Returns ``(predicted, anchors, their
    rows, the budget placed for)``."""
    cache: dict[tuple, np.ndarray] = {}

    def row(j: int, i0: int = 0, i1: int | None = None) -> np.ndarray:
        key = (j, i0, i1)
        if key not in cache:
            cache[key] = dist_sq_row(j, i0, i1)
        return cache[key]

    best = None
    for k in [int(max_anchors)] + budget_ladder(int(max_anchors)):
        if best is not None and best[0] >= limit:
            break
        if k == max_anchors and first is not None:
            idx, rows = first
        else:
            rows = {}
            idx = rule.place(row, alphas, centre, target_of(k), rows_out=rows, budget=k)
        predicted, j = best_prefix(rule, rows, idx, alphas, centre, target_of)
        if best is None or predicted > best[0]:
            best = (predicted, idx[:j], {int(a): rows[int(a)] for a in idx[:j]}, k)
        if len(idx) >= k:
            break   # every anchor of this budget fit: it was limited by its count, so fewer would not do better
    return best


def best_prefix(rule, rows: dict, idx, alphas: np.ndarray, centre: int, target_of: Callable[[int], float]) -> tuple[float, int]:
    """``(reach, j)``: the first ``j`` anchors of the placement ``idx`` (in the order placed) with the largest
    covered radius at ``target_of(j)`` (``rule.radius``, the coverage rule's; the most of equal reach)."""
    D2 = np.stack([rows[int(a)] for a in idx])
    best = (0.0, 1)
    for j in range(1, len(idx) + 1):
        t = float(target_of(j))
        if t <= 0:
            continue
        r = float(rule.radius(np.full(j, t), D2[:j], alphas, centre)[0])
        if r >= best[0]:
            best = (r, j)
    return best


def _with_rows(anchors: list[int], row: Callable[[int], np.ndarray], rows_out: dict[int, np.ndarray] | None) -> list[int]:
    if rows_out is not None:
        for a in anchors:
            rows_out[a] = row(a)
    return anchors


def refine_plan(plan: Plan, frames: np.ndarray, max_step: float, max_partitions: int,
                reach: float | None = None, keep: tuple[float, float] | None = None) -> Plan:
    """Subdivide every segment whose end frames differ (l2) by more than ``max_step`` into equal parts so
    that consecutive frames differ by about ``max_step`` at most (fine enough to place anchors within a
    target radius), keeping at most ``max_partitions`` grid points. Where that is more than the cap
    allows, the segments nearest ``alpha = 0`` (rendered path from 0 to their near end, both sides) get
    their parts first and the farthest get none: the covered run grows outward from 0, so a point far
    out is worth less than one near 0 (scaling every segment's parts down instead left a grid that a
    larger anchor budget, reaching farther, refined too little near 0 to place a second anchor: RealSense
    frame, 224x224, ry, 48 anchors, 2% of the radius where 24 certified 15%).
    With ``reach`` (a path length), only segments within that rendered path length of ``alpha = 0`` on
    their side are refined: the anchor budget cannot cover farther, so finer frames there buy nothing.
    With ``keep = (lo, hi)``, segments inside ``[lo, hi]`` are left as they are (a run the anchors
    already cover). The grid stays a grid of the same interval that contains 0; only tightness depends on it."""
    f = np.asarray(frames, dtype=np.float64)
    d = np.sqrt(((f[1:] - f[:-1]) ** 2).reshape(len(f) - 1, -1).sum(axis=1))
    parts = np.maximum(1, np.ceil(d / max(max_step, 1e-12))).astype(np.int64)
    centre = int(np.searchsorted(plan.alphas, 0.0))
    right = np.cumsum(d[centre:])                     # path from alpha = 0 to each segment's far end
    left = np.cumsum(d[:centre][::-1])[::-1]
    far = np.concatenate([left, right]) - d            # path to each segment's near end
    if reach is not None:
        parts = np.where(far <= reach, parts, 1)
    if keep is not None:
        a = plan.alphas
        parts = np.where((a[:-1] >= keep[0]) & (a[1:] <= keep[1]), 1, parts)
    room = max(0, int(max_partitions) - 1 - len(d))    # points the cap lets the refinement add
    if int((parts - 1).sum()) > room:
        order = np.argsort(far, kind="stable")         # nearest to alpha = 0 first
        want = (parts - 1)[order]
        before = np.cumsum(want) - want
        parts[order] = 1 + np.clip(room - before, 0, want)
    if int(parts.max()) == 1:
        return plan
    a = plan.alphas
    pieces = [a[i] + (a[i + 1] - a[i]) * np.arange(parts[i]) / parts[i] for i in range(len(d))]
    alphas = np.concatenate(pieces + [a[-1:]])
    alphas[np.argmin(np.abs(alphas))] = 0.0
    details = dict(plan.details, refined_from=int(len(a)), refine_max_step=float(max_step))
    return Plan(plan.method, plan.axis, plan.radius, float(np.diff(alphas).max()), len(alphas), alphas, plan.unit, details)

"""The anchors' distance rows ``D_i(x_j)^2`` (:meth:`.surfel_bounds.HullValues.dist_sq`), computed exactly
only where a comparison can need them (issue 34, item 3: on a real frame most of the placement's time).

The anchors read a row only through comparisons ``D_i(x_j)^2 < t^2`` with ``t`` at most a known threshold
(the placement's targets; the estimated Cohen radii, :meth:`DistanceRows.complete`), and through one
value, the largest distance of a segment to its nearest anchor (:meth:`DistanceRows.max_min`). A cheap
**lower bound** decides most comparisons: with the box centre ``c = (lo + hi) / 2`` and half-width
``r = (hi - lo) / 2`` of every output value, ``max(y - lo, hi - y) = |y - c| + r``, so

    D_i(y)^2 / SAFETY = sum (|y - c| + r)^2 >= |y - c|^2 + |r|^2,

and ``|y - c|^2`` of every grid frame ``y`` and segment is one matrix product (centred on one frame, so
the terms are small), taken in float64 with its rounding bound subtracted (Higham, Accuracy and Stability
of Numerical Algorithms, 3.1: a sum of ``n`` products in any order errs by at most ``gamma_n`` times the
sum of their magnitudes). Where the bound of a segment is below the threshold,
its value is computed exactly (bit for bit the value of any call that asks for it); elsewhere the bound is
returned: every comparison with a ``t^2`` up to the threshold comes out as the exact value's would
(``exact >= bound >= threshold >= t^2``). So the anchors, the radius and every value a certificate
reports are those of the exact rows; only the time differs.
"""
from __future__ import annotations

import numpy as np

U64 = float(np.finfo(np.float64).eps) / 2   # unit roundoff of float64
GRAM_CHUNK = 512                           # values per column chunk of the product (its temporaries stay in the cache)


class DistanceRows:
    """``row(j, i0, i1)``: ``D_i(x_j)^2`` for segments ``i0 .. i1 - 1`` of ``hulls`` (a HullValues) and
    grid frame ``frames[j]``, exact for each segment whose bound may be below ``threshold_sq`` (module doc),
    else that lower bound, which is at least ``threshold_sq``. Each exact value is computed once, and is bit for
    bit the value of a call of ``i0 .. i1 - 1`` (:meth:`.surfel_bounds.HullValues.dist_sq` gives a segment the
    same value in every call of two or more segments, and sums it in another order in a call of it alone: a piece
    of one segment is computed alone, any other in a call of two or more)."""

    def __init__(self, hulls, frames: np.ndarray, threshold_sq: float):
        self.hulls, self.frames = hulls, frames
        self.threshold_sq = float(threshold_sq)
        self.lower = _lower_bounds(hulls, frames)
        # (j, i, alone): answered by the bound, in a piece of segment i alone or not
        self.approx: set[tuple[int, int, bool]] = set()
        self.exact_calls = 0                              # exact values computed
        self.bound_calls = 0                              # values answered by the bound
        # exact values by (j, i, alone): the placements of several budgets (.anchors.best_placement) read the same pieces
        self._exact: dict[tuple[int, int, bool], float] = {}
        self._scratch: list = []                          # HullValues.dist_sq's work buffers, kept between its calls

    def _values(self, j: int, segments: list[int], alone: bool) -> np.ndarray:
        """The exact ``D_i(x_j)^2`` of ``segments``, those not known yet computed: each in a call of its own where
        ``alone``, else together in one call of two or more (another segment joins one that would be alone)."""
        j = int(j)
        todo = [i for i in segments if (j, i, alone) not in self._exact]
        if todo:
            y = self.frames[j]
            if alone:
                got = [float(self.hulls.dist_sq(y, slice(i, i + 1), self._scratch)[0]) for i in todo]
            else:
                ask = todo if len(todo) > 1 else todo + [todo[0] + 1 if todo[0] + 1 < self.hulls.num_segments else todo[0] - 1]
                got = self.hulls.dist_sq(y, np.asarray(ask, dtype=np.int64), self._scratch).tolist()
                todo = ask
            self.exact_calls += len(todo)
            self._exact.update(zip(((j, i, alone) for i in todo), got))
        return np.array([self._exact[(j, i, alone)] for i in segments], dtype=np.float64)

    def row(self, j: int, i0: int = 0, i1: int | None = None) -> np.ndarray:
        S = self.hulls.num_segments
        i1 = S if i1 is None else min(int(i1), S)
        i0 = max(0, int(i0))
        j, alone = int(j), i1 - i0 == 1
        out = self.lower[j, i0:i1].copy()
        need = out < self.threshold_sq
        if need.any():
            at = np.flatnonzero(need)
            out[at] = self._values(j, (at + i0).tolist(), alone)
        bounded = np.flatnonzero(~need)
        if len(bounded):
            self.approx.update((j, int(i), alone) for i in bounded + i0)
            self.bound_calls += len(bounded)
        return out

    def _make_exact(self, rows: np.ndarray, where: dict[int, int], entries) -> None:
        """``rows[where[j], i]`` made exact for the ``(j, i, alone)`` of ``entries`` (one call per grid frame)."""
        by: dict[tuple[int, bool], list[int]] = {}
        for j, i, alone in entries:
            by.setdefault((j, alone), []).append(i)
        for (j, alone), segs in by.items():
            segs = sorted(segs)
            rows[where[j], segs] = self._values(j, segs, alone)
            self.approx.difference_update((j, i, alone) for i in segs)

    def complete(self, rows: np.ndarray, idx, threshold_sq: float) -> None:
        """Make ``rows`` (the rows of grid frames ``idx``, as this object's calls gave them) exact wherever a
        value was answered by the bound and that bound lies below ``threshold_sq`` (a comparison with a larger
        radius than the placement's threshold: the estimated Cohen radii)."""
        if threshold_sq <= self.threshold_sq:
            return
        where = {int(j): k for k, j in enumerate(idx)}
        self._make_exact(rows, where, [e for e in self.approx if e[0] in where and self.lower[e[0], e[1]] < threshold_sq])

    def max_min(self, rows: np.ndarray, idx) -> float:
        """``max_i min_k rows[k, i]`` of the exact rows, where ``rows`` may hold bounds (:meth:`complete`):
        while a column's least entry is a bound, it is computed exactly (a bound below every exact entry of its
        column could hide a smaller exact value; at the end each column's least entry is exact and no bound is
        below it, so it is the exact minimum)."""
        if rows.size == 0:
            return 0.0
        where = {int(j): k for k, j in enumerate(idx)}
        bounded: dict[tuple[int, int], bool] = {(j, i): alone for j, i, alone in self.approx if j in where}
        while True:
            arg = rows.argmin(axis=0)
            todo = [(j, i, bounded.pop((j, i))) for i, j in enumerate(int(idx[k]) for k in arg.tolist()) if (j, i) in bounded]
            if not todo:
                return float(rows.min(axis=0).max())
            self._make_exact(rows, where, todo)


def _lower_bounds(hulls, frames: np.ndarray) -> np.ndarray:
    """``L[j, i] <= D_i(frames[j])^2 / SAFETY`` for every grid frame and segment (module doc), float64."""
    S, F = hulls.num_segments, len(frames)
    Y = np.asarray(frames).reshape(F, -1)
    lo, hi = hulls.lo.reshape(S, -1), hulls.hi.reshape(S, -1)
    n = Y.shape[1]
    ref = Y[min(F - 1, F // 2)].astype(np.float64)
    G = np.zeros((F, S))
    yy, cc, rr = np.zeros(F), np.zeros(S), np.zeros(S)
    for s in range(0, n, GRAM_CHUNK):
        e = min(n, s + GRAM_CHUNK)
        # float32 values in float64: their differences and sums are exact unless their exponents differ by about
        # 30 (then the rounding is relative to the centred values, or 2u r, within the slack below)
        y = Y[:, s:e].astype(np.float64)
        y -= ref[s:e]
        c, h64 = lo[:, s:e].astype(np.float64), hi[:, s:e].astype(np.float64)
        r2 = h64 - c                  # 2 r (its squares' sum times 1/4: the same as r's, scaling by 2 is exact)
        c += h64                      # c = (lo + hi) / 2 - ref, in place
        c *= 0.5
        c -= ref[s:e]
        G += y @ c.T
        yy += np.einsum("ij,ij->i", y, y)
        cc += np.einsum("ij,ij->i", c, c)
        rr += 0.25 * np.einsum("ij,ij->i", r2, r2)
    # |y - c|^2 = |y|^2 + |c|^2 - 2 y.c; each of the three sums of n products errs by at most gamma times its
    # magnitudes' sum (|y|^2, |c|^2, |y||c|), the chunks' partial sums included; the two additions by 2u more
    gamma = 2.0 * (n + n // GRAM_CHUNK + 8) * U64
    ny, nc = np.sqrt(yy * (1 + gamma)), np.sqrt(cc * (1 + gamma))
    err = (gamma + 4 * U64) * (ny[:, None] + nc[None, :]) ** 2 * (1 + gamma)
    d = np.maximum(yy[:, None] + cc[None, :] - 2.0 * G - err, 0.0)
    return (d + rr[None, :] * (1 - gamma)) * (1 - 4 * U64)

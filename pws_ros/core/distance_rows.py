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
sum of their magnitudes). Where the bound of some segment of a requested block is below the threshold,
the block is computed exactly as before (the same call, so bit for bit the same values); elsewhere the
bound is returned: every comparison with a ``t^2`` up to the threshold comes out as the exact value's
would (``exact >= bound >= threshold >= t^2``). So the anchors, the radius and every value a certificate
reports are those of the exact rows; only the time differs.
"""
from __future__ import annotations

import numpy as np

U64 = float(np.finfo(np.float64).eps) / 2   # unit roundoff of float64
GRAM_CHUNK = 2048                          # values per column chunk of the product (memory stays bounded)


class DistanceRows:
    """``row(j, i0, i1)``: ``D_i(x_j)^2`` for segments ``i0 .. i1 - 1`` of ``hulls`` (a HullValues) and
    grid frame ``frames[j]``, exact wherever some segment of the call may be below ``threshold_sq``
    (module doc), else a lower bound that is at least ``threshold_sq`` everywhere in the call."""

    def __init__(self, hulls, frames: np.ndarray, threshold_sq: float):
        self.hulls, self.frames = hulls, frames
        self.threshold_sq = float(threshold_sq)
        self.lower = _lower_bounds(hulls, frames)
        self.approx: set[tuple[int, int, int]] = set()   # (j, i0, i1) calls answered by the bound
        self.exact_calls = 0                            # exact rows computed
        self.bound_calls = 0                            # calls answered by the bound
        # exact rows by call: the placements of several budgets (.anchors.best_placement) read the same pieces
        self._exact: dict[tuple[int, int, int], np.ndarray] = {}

    def exact(self, j: int, i0: int, i1: int) -> np.ndarray:
        key = (int(j), int(i0), int(i1))
        got = self._exact.get(key)
        if got is None:
            self.exact_calls += 1
            got = self._exact[key] = self.hulls.dist_sq(self.frames[j], slice(i0, i1))
        return got.copy()

    def row(self, j: int, i0: int = 0, i1: int | None = None) -> np.ndarray:
        S = self.hulls.num_segments
        i1 = S if i1 is None else min(int(i1), S)
        i0 = max(0, int(i0))
        lb = self.lower[j, i0:i1]
        if not len(lb) or bool((lb < self.threshold_sq).any()):
            return self.exact(j, i0, i1)
        self.approx.add((int(j), i0, i1))
        self.bound_calls += 1
        return lb.copy()

    def complete(self, rows: np.ndarray, idx, threshold_sq: float) -> None:
        """Make ``rows`` (the rows of grid frames ``idx``, as this object's calls gave them) exact wherever a
        call was answered by the bound and some segment of it lies below ``threshold_sq`` (a comparison with
        a larger radius than the placement's threshold: the estimated Cohen radii)."""
        if threshold_sq <= self.threshold_sq:
            return
        where = {int(j): k for k, j in enumerate(idx)}
        for (j, i0, i1) in sorted(self.approx):
            k = where.get(j)
            if k is not None and bool((self.lower[j, i0:i1] < threshold_sq).any()):
                rows[k, i0:i1] = self.exact(j, i0, i1)
                self.approx.discard((j, i0, i1))

    def max_min(self, rows: np.ndarray, idx) -> float:
        """``max_i min_k rows[k, i]`` of the exact rows, where ``rows`` may hold bounds (:meth:`complete`):
        while a column's least entry is a bound, that block is computed exactly (a bound below every exact
        entry of its column could hide a smaller exact value; at the end each column's least entry is exact
        and no bound is below it, so it is the exact minimum)."""
        if rows.size == 0:
            return 0.0
        where = {int(j): k for k, j in enumerate(idx)}
        blocks = {}
        for (j, i0, i1) in self.approx:
            k = where.get(j)
            if k is not None:
                for i in range(i0, i1):
                    blocks[(k, i)] = (j, i0, i1)
        while True:
            arg = rows.argmin(axis=0)
            todo = {blocks[(int(k), i)] for i, k in enumerate(arg) if (int(k), i) in blocks}
            if not todo:
                return float(rows.min(axis=0).max())
            for (j, i0, i1) in todo:
                rows[where[j], i0:i1] = self.exact(j, i0, i1)
                self.approx.discard((j, i0, i1))
                for i in range(i0, i1):
                    blocks.pop((where[j], i), None)


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
        y = Y[:, s:e].astype(np.float64) - ref[s:e]
        l64, h64 = lo[:, s:e].astype(np.float64), hi[:, s:e].astype(np.float64)
        c = (l64 + h64) * 0.5 - ref[s:e]
        r = (h64 - l64) * 0.5
        G += y @ c.T
        yy += np.einsum("ij,ij->i", y, y)
        cc += np.einsum("ij,ij->i", c, c)
        rr += np.einsum("ij,ij->i", r, r)
    # |y - c|^2 = |y|^2 + |c|^2 - 2 y.c; each of the three sums of n products errs by at most gamma times its
    # magnitudes' sum (|y|^2, |c|^2, |y||c|), the chunks' partial sums included; the two additions by 2u more
    gamma = 2.0 * (n + n // GRAM_CHUNK + 8) * U64
    ny, nc = np.sqrt(yy * (1 + gamma)), np.sqrt(cc * (1 + gamma))
    err = (gamma + 4 * U64) * (ny[:, None] + nc[None, :]) ** 2 * (1 + gamma)
    d = np.maximum(yy[:, None] + cc[None, :] - 2.0 * G - err, 0.0)
    return (d + rr[None, :] * (1 - gamma)) * (1 - 4 * U64)

"""Exact pixel states along a one-axis motion: where each point is, and which point a pixel shows.

For a cloud and a motion range ``[lo, hi]`` this module computes, analytically up to float64
bisection, every *visit* (point ``P`` inside pixel ``(r, s)`` during ``[t0, t1]``) and then, per
pixel, the *elementary intervals* between consecutive visit boundaries together with the set of
values the pixel can show there: the colours of the points that can win the z-buffer (a point is
kept unless some other point covering the whole interval is surely nearer) or the background when
no point covers it (holes are states too).

Everything downstream that must be sound (the per-segment bounds of :mod:`.bounds`) or faithful to
the paper (the consistent intervals of :mod:`.partition`) is read off these intervals.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import CameraIntrinsics
from .motion import project, split_points

BISECT_ITERS = 64


@dataclass
class Visits:
    """Point ``point[i]`` lies in pixel ``(row[i], col[i])`` with positive depth for ``t0[i] <= alpha <= t1[i]``."""

    point: np.ndarray
    row: np.ndarray
    col: np.ndarray
    t0: np.ndarray
    t1: np.ndarray

    def __len__(self) -> int:
        return len(self.point)


def _uvd(points, intr, axis, alpha):
    u, v, d = project(points, intr, axis, alpha)
    big = 1e12
    u = np.nan_to_num(u, nan=big, posinf=big, neginf=-big)
    v = np.nan_to_num(v, nan=big, posinf=big, neginf=-big)
    return u, v, d


def compute_visits(points: np.ndarray, intr: CameraIntrinsics, axis: str, lo: float, hi: float) -> Visits:
    """All visits of all points over ``[lo, hi]`` (see :class:`Visits`)."""
    points = np.asarray(points, dtype=np.float64)
    W, H = intr.width, intr.height
    splits = split_points(points, axis, lo, hi)  # (N, M) NaN padded
    # piece boundaries per point: lo, splits..., hi
    N = len(points)
    bounds = np.concatenate([np.full((N, 1), lo), splits, np.full((N, 1), hi)], axis=1)
    bounds = np.where(np.isnan(bounds), np.inf, bounds)
    bounds.sort(axis=1)
    a = bounds[:, :-1]
    b = bounds[:, 1:]
    ok = np.isfinite(b) & (b > a)
    pidx, _ = np.nonzero(ok)
    a, b = a[ok], b[ok]
    P = points[pidx]
    eps = (b - a) * 1e-12
    ua, va, da = _uvd(P, intr, axis, a + eps)
    ub, vb, db = _uvd(P, intr, axis, b - eps)
    _, _, dm = _uvd(P, intr, axis, 0.5 * (a + b))
    # prune pieces that are behind the camera or never touch the image
    umin, umax = np.minimum(ua, ub), np.maximum(ua, ub)
    vmin, vmax = np.minimum(va, vb), np.maximum(va, vb)
    keep = (dm > 0) & (umax >= 0) & (umin < W) & (vmax >= 0) & (vmin < H)
    pidx, a, b, P = pidx[keep], a[keep], b[keep], P[keep]
    ua, ub, va, vb = ua[keep], ub[keep], va[keep], vb[keep]
    umin, umax, vmin, vmax = umin[keep], umax[keep], vmin[keep], vmax[keep]
    n_pieces = len(pidx)

    # integer crossings k in (min, max], restricted to the image edges [0, W] / [0, H]
    def crossings(fmin, fmax, limit):
        k0 = np.clip(np.floor(fmin) + 1, 0, limit)
        k1 = np.clip(np.floor(fmax), -1, limit)
        k1 = np.where(fmax < 0, -1, k1)
        count = np.maximum(0, (k1 - k0 + 1)).astype(np.int64)
        count = np.where(fmin > limit, 0, count)
        return k0.astype(np.int64), count

    ku0, cu = crossings(umin, umax, W)
    kv0, cv = crossings(vmin, vmax, H)
    times = [a, b]
    owners = [np.arange(n_pieces), np.arange(n_pieces)]
    for k0, cnt, comp in ((ku0, cu, 0), (kv0, cv, 1)):
        total = int(cnt.sum())
        if total == 0:
            continue
        own = np.repeat(np.arange(n_pieces), cnt)
        first = np.repeat(np.cumsum(cnt) - cnt, cnt)
        k = k0[own] + (np.arange(total) - first)
        fa = (ua if comp == 0 else va)[own]
        lo_t, hi_t = a[own].copy(), b[own].copy()
        increasing = ((ub if comp == 0 else vb)[own]) > fa
        Pk = P[own]
        for _ in range(BISECT_ITERS):
            mid = 0.5 * (lo_t + hi_t)
            uu, vv, _ = _uvd(Pk, intr, axis, mid)
            f = uu if comp == 0 else vv
            below = f < k  # not yet reached k when increasing
            go_right = np.where(increasing, below, ~below)
            lo_t = np.where(go_right, mid, lo_t)
            hi_t = np.where(go_right, hi_t, mid)
        times.append(0.5 * (lo_t + hi_t))
        owners.append(own)
    t_all = np.concatenate(times)
    o_all = np.concatenate(owners)
    order = np.lexsort((t_all, o_all))
    t_all, o_all = t_all[order], o_all[order]
    same = o_all[1:] == o_all[:-1]
    s0, s1, own = t_all[:-1][same], t_all[1:][same], o_all[:-1][same]
    nonzero = s1 > s0
    s0, s1, own = s0[nonzero], s1[nonzero], own[nonzero]
    uu, vv, dd = _uvd(P[own], intr, axis, 0.5 * (s0 + s1))
    inside = (dd > 0) & (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
    s0, s1, own = s0[inside], s1[inside], own[inside]
    col = np.floor(uu[inside]).astype(np.int64)
    row = np.floor(vv[inside]).astype(np.int64)
    point = pidx[own]
    # merge consecutive visits of one point to one pixel (split across pieces)
    if len(point):
        order = np.lexsort((s0, point))
        point, row, col, s0, s1 = point[order], row[order], col[order], s0[order], s1[order]
        cont = (point[1:] == point[:-1]) & (row[1:] == row[:-1]) & (col[1:] == col[:-1]) & (s0[1:] <= s1[:-1])
        start = np.concatenate([[True], ~cont])
        grp = np.cumsum(start) - 1
        t1 = np.full(grp[-1] + 1, -np.inf)
        np.maximum.at(t1, grp, s1)
        point, row, col, s0 = point[start], row[start], col[start], s0[start]
        s1 = t1
    return Visits(point, row, col, s0, s1)


@dataclass
class PixelStates:
    """Per pixel, elementary intervals ``[start, end]`` of the motion range and the values a pixel can
    show there.

    ``pix[j]``, ``start[j]``, ``end[j]``: interval ``j`` (sorted by pixel then time, tiling
    ``[lo, hi]`` for every pixel of the image). Candidates of interval ``j`` are
    ``cand_point[cand_ptr[j]:cand_ptr[j+1]]`` (point indices; ``-1`` = background/hole).
    ``winner[j]`` is the value the renderer shows inside the interval (nearest, lowest index) or -1.
    """

    lo: float
    hi: float
    pix: np.ndarray
    start: np.ndarray
    end: np.ndarray
    winner: np.ndarray
    cand_ptr: np.ndarray
    cand_point: np.ndarray

    @property
    def num_candidates(self) -> np.ndarray:
        return np.diff(self.cand_ptr)


def pixel_states(points: np.ndarray, intr: CameraIntrinsics, axis: str, lo: float, hi: float,
                 visits: Visits | None = None, tol: float | None = None) -> PixelStates:
    """Elementary intervals and candidate values of every pixel over ``[lo, hi]``.

    Visit boundaries of one pixel closer than ``tol`` (default ``1e-12 * max(|lo|, |hi|, 1e-9)``, the
    float64 resolution of the motion value itself) are merged: a point leaving and its neighbour
    entering at the same instant leaves no hole.
    """
    points = np.asarray(points, dtype=np.float64)
    if visits is None:
        visits = compute_visits(points, intr, axis, lo, hi)
    if tol is None:
        tol = 1e-12 * max(abs(lo), abs(hi), 1e-9)
    H, W = intr.height, intr.width
    npix = H * W
    vp = visits.row * W + visits.col
    # breakpoints per pixel: visit boundaries plus lo/hi for every pixel
    bp_pix = np.concatenate([vp, vp, np.arange(npix), np.arange(npix)])
    bp_t = np.concatenate([visits.t0, visits.t1, np.full(npix, lo), np.full(npix, hi)])
    bp_t = np.clip(bp_t, lo, hi)
    order = np.lexsort((bp_t, bp_pix))
    bp_pix, bp_t = bp_pix[order], bp_t[order]
    # snap: drop a breakpoint within tol of the previous kept one of the same pixel
    newpix = np.concatenate([[True], bp_pix[1:] != bp_pix[:-1]])
    gap = np.concatenate([[np.inf], np.diff(bp_t)])
    keep = newpix | (gap > tol)
    bp_pix, bp_t = bp_pix[keep], bp_t[keep]
    same = bp_pix[1:] == bp_pix[:-1]
    pix, start, end = bp_pix[:-1][same], bp_t[:-1][same], bp_t[1:][same]
    # pixel block offsets for interval lookup
    n_int = len(pix)
    block_start = np.searchsorted(pix, np.arange(npix), side="left")
    block_end = np.searchsorted(pix, np.arange(npix), side="right")
    # covering pairs (visit, interval): intervals of the visit's pixel within [t0 - tol, t1 + tol]
    # intervals of one pixel are sorted; use per-visit searchsorted through a global key on (pix, start)
    first = np.empty(len(visits), dtype=np.int64)
    last = np.empty(len(visits), dtype=np.int64)
    if len(visits):
        # np.searchsorted per block via offset trick: start is monotone within a block
        key_pix = pix.astype(np.float64)
        # rank of times inside each block
        bs = block_start[vp]
        be = block_end[vp]
        # vectorised binary search within [bs, be)
        lo_i, hi_i = bs.copy(), be.copy()
        target = visits.t0 - tol
        for _ in range(int(np.ceil(np.log2(max(2, int((be - bs).max(initial=1)) + 1)))) + 1):
            mid = (lo_i + hi_i) // 2
            midc = np.minimum(mid, n_int - 1)
            go = (mid < hi_i) & (start[midc] < target)
            lo_i = np.where(go, mid + 1, lo_i)
            hi_i = np.where(go, hi_i, mid)
        first = lo_i
        lo_i, hi_i = bs.copy(), be.copy()
        target = visits.t1 + tol
        for _ in range(int(np.ceil(np.log2(max(2, int((be - bs).max(initial=1)) + 1)))) + 1):
            mid = (lo_i + hi_i) // 2
            midc = np.minimum(mid, n_int - 1)
            go = (mid < hi_i) & (end[midc] <= target)
            lo_i = np.where(go, mid + 1, lo_i)
            hi_i = np.where(go, hi_i, mid)
        last = lo_i  # exclusive
        del key_pix
    cnt = np.maximum(0, last - first)
    total = int(cnt.sum())
    own = np.repeat(np.arange(len(visits)), cnt)
    off = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    jint = np.repeat(first, cnt) + off
    vpt = visits.point[own]
    # Candidates: Q is dropped only if some covering point R is strictly nearer than Q at both ends
    # of the interval. Depth differences of two points are linear in alpha (translations), constant
    # (rz) or harmonic (rx, ry: a sign change needs a zero, and two zeros are pi apart), so on an
    # interval shorter than pi "nearer at both ends" means nearer throughout: the test is exact for a
    # single dominating occluder and never drops a point that can win.
    s_j, e_j = start[jint], end[jint]
    _, _, ds = project(points[vpt], intr, axis, s_j)
    _, _, de = project(points[vpt], intr, axis, e_j)
    _, _, dmid = project(points[vpt], intr, axis, 0.5 * (s_j + e_j))
    is_cand = np.ones(total, dtype=bool)
    for primary, secondary in ((ds, de), (de, ds)):
        order = np.lexsort((secondary, primary, jint))
        head = np.concatenate([[True], jint[order][1:] != jint[order][:-1]]) if total else np.zeros(0, bool)
        wit = np.empty(n_int, dtype=np.int64)
        wit[jint[order][head]] = order[head]
        w = wit[jint]
        dominated = (ds[w] < ds) & (de[w] < de)
        is_cand &= ~dominated
    # winner (renderer's choice at the midpoint): min depth, then min index
    order = np.lexsort((vpt, dmid, jint))
    first_of = np.concatenate([[True], jint[order][1:] != jint[order][:-1]]) if total else np.zeros(0, bool)
    winner = np.full(n_int, -1, dtype=np.int64)
    winner[jint[order][first_of]] = vpt[order][first_of]
    # candidate lists (CSR); empty intervals get the background (-1)
    cj, cp = jint[is_cand], vpt[is_cand]
    empty = np.ones(n_int, bool)
    empty[cj] = False
    cj = np.concatenate([cj, np.nonzero(empty)[0]])
    cp = np.concatenate([cp, np.full(int(empty.sum()), -1, dtype=np.int64)])
    order = np.lexsort((cp, cj))
    cj, cp = cj[order], cp[order]
    ptr = np.zeros(n_int + 1, dtype=np.int64)
    np.add.at(ptr, cj + 1, 1)
    ptr = np.cumsum(ptr)
    return PixelStates(lo, hi, pix, start, end, winner, ptr, cp)

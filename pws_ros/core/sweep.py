"""Exact pixel states along a one-axis motion: where each point is, and which point a pixel shows.

For a cloud and a motion range ``[lo, hi]`` this module computes, analytically up to float64
bisection, every *visit* (point ``P`` inside pixel ``(r, s)`` during ``[t0, t1]``) and then, per
pixel, the *elementary intervals* between consecutive visit boundaries together with the set of
values the pixel can show there: the colours of the points that can win the z-buffer (a point is
kept unless some other point covering the whole interval is surely nearer, beyond the depth tie
margin of :func:`.motion.depth_tie_margin`) or the background when
no point covers it (holes are states too).

Everything downstream that must be sound (the per-segment bounds of :mod:`.bounds`) or faithful to
the paper (the consistent intervals of :mod:`.partition`) is read off these intervals.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .camera import CameraIntrinsics
from .motion import PIXEL_OVERLAP, depth, depth_tie_margin, project, split_points

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


def _range_end(f_end: np.ndarray, f_near: np.ndarray, f_mid: np.ndarray) -> np.ndarray:
    """A piece's coordinate at its end: the value there, or where it is not finite (the pole of tz: depth 0 at
    the end), where the piece runs to (+-big beyond the image, the way it moves from the middle to ``f_near``, the
    value just inside the end; a coordinate that does not move stays)."""
    big = 1e12
    toward = np.sign(f_near - f_mid)
    return np.where(np.isfinite(f_end), f_end, np.where(toward == 0, f_near, toward * big))


def compute_visits(points: np.ndarray, intr: CameraIntrinsics, axis: str, lo: float, hi: float,
                   overlap: float = PIXEL_OVERLAP) -> Visits:
    """All visits of all points over ``[lo, hi]`` (see :class:`Visits`); ``overlap``: the footprints' overlap
    (:func:`.motion.pixel_span`'s ``PIXEL_OVERLAP``; :func:`pixel_states` also asks for a little more and a
    little less, for the renderer's rounding)."""
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
    um, vm, dm = _uvd(P, intr, axis, 0.5 * (a + b))
    # the ends themselves too: u and v are monotonic on a piece, so its range is that of its ends; where an end is
    # a pole (tz: depth 0), u and v run off to +-inf in the last eps before it, across every row or column they
    # head for (a point 1e-14 m off the axis, 1e-12 m before its pole, crosses half the image)
    with np.errstate(divide="ignore", invalid="ignore"):
        u_a, v_a, _ = project(P, intr, axis, a)
        u_b, v_b, _ = project(P, intr, axis, b)
    u_a, v_a = _range_end(u_a, ua, um), _range_end(v_a, va, vm)
    u_b, v_b = _range_end(u_b, ub, um), _range_end(v_b, vb, vm)
    # prune pieces that are behind the camera or never touch the image
    umin, umax = np.minimum.reduce([ua, ub, u_a, u_b]), np.maximum.reduce([ua, ub, u_a, u_b])
    vmin, vmax = np.minimum.reduce([va, vb, v_a, v_b]), np.maximum.reduce([va, vb, v_a, v_b])
    e = float(overlap)
    keep = (dm > 0) & (umax + e >= 0) & (umin - e < W) & (vmax + e >= 0) & (vmin - e < H)
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

    times = [a, b]
    owners = [np.arange(n_pieces), np.arange(n_pieces)]
    # the footprint edges: where c + e or c - e crosses an integer (c = u or v), found by bisection on
    # exactly the float expressions the renderer floors (motion.pixel_span)
    for comp, off in ((0, e), (0, -e), (1, e), (1, -e)):
        fmin = (umin if comp == 0 else vmin) + off
        fmax = (umax if comp == 0 else vmax) + off
        k0, cnt = crossings(fmin, fmax, W if comp == 0 else H)
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
            f = (uu if comp == 0 else vv) + off
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
    c_lo, c_hi = np.floor(uu - e), np.floor(uu + e)   # motion.pixel_span with this overlap
    r_lo, r_hi = np.floor(vv - e), np.floor(vv + e)
    # each sub-piece lies in one to four pixels (footprints overlap near the edges)
    parts = []
    for r, c, extra in ((r_lo, c_lo, None), (r_lo, c_hi, c_hi != c_lo), (r_hi, c_lo, r_hi != r_lo),
                        (r_hi, c_hi, (c_hi != c_lo) & (r_hi != r_lo))):
        ok = (dd > 0) & (c >= 0) & (c < W) & (r >= 0) & (r < H)
        if extra is not None:
            ok &= extra
        parts.append((own[ok], r[ok], c[ok], s0[ok], s1[ok]))
    own = np.concatenate([p[0] for p in parts])
    row = np.concatenate([p[1] for p in parts]).astype(np.int64)
    col = np.concatenate([p[2] for p in parts]).astype(np.int64)
    s0 = np.concatenate([p[3] for p in parts])
    s1 = np.concatenate([p[4] for p in parts])
    point = pidx[own]
    # merge consecutive visits of one point to one pixel (split across sub-pieces)
    if len(point):
        order = np.lexsort((s0, col, row, point))
        point, row, col, s0, s1 = point[order], row[order], col[order], s0[order], s1[order]
        cont = (point[1:] == point[:-1]) & (row[1:] == row[:-1]) & (col[1:] == col[:-1]) & (s0[1:] <= s1[:-1])
        start = np.concatenate([[True], ~cont])
        grp = np.cumsum(start) - 1
        t1 = np.full(grp[-1] + 1, -np.inf)
        np.maximum.at(t1, grp, s1)
        point, row, col, s0 = point[start], row[start], col[start], s0[start]
        s1 = t1
    return Visits(point, row, col, s0, s1)


TIME_TOL_REL = 1e-10
TIME_TOL_ABS = 1e-12
# pixels by which the torch renderer's u, v may differ from this sweep's numpy ones (a few ulps of coordinates up to
# ~1e4 px: 1e-12; the rest is room): the bounds' footprints are widened (possible) and narrowed (sure) by it
RENDER_SLACK_PX = 1e-9


def default_tol(lo: float, hi: float) -> float:
    """Time tolerance of a sweep over ``[lo, hi]``: how far a computed visit boundary may be from the
    instant at which the float renderer actually switches (bisection, sin/cos rounding)."""
    return max(TIME_TOL_REL * max(abs(lo), abs(hi)), TIME_TOL_ABS)


@dataclass
class PixelStates:
    """Per pixel, elementary intervals ``[start, end]`` of the motion range and the values a pixel can
    show there.

    ``pix[j]``, ``start[j]``, ``end[j]``: interval ``j`` (sorted by pixel then time, tiling
    ``[lo, hi]`` for every pixel of the image). Candidates of interval ``j`` are
    ``cand_point[cand_ptr[j]:cand_ptr[j+1]]`` (point indices; ``-1`` = background/hole).
    ``winner[j]`` is the value the renderer shows inside the interval (nearest, lowest index) or -1.
    ``tol`` is the time tolerance the candidates allow for (:func:`default_tol`).
    """

    lo: float
    hi: float
    pix: np.ndarray
    start: np.ndarray
    end: np.ndarray
    winner: np.ndarray
    cand_ptr: np.ndarray
    cand_point: np.ndarray
    tol: float = 0.0

    @property
    def num_candidates(self) -> np.ndarray:
        return np.diff(self.cand_ptr)


def pixel_states(points: np.ndarray, intr: CameraIntrinsics, axis: str, lo: float, hi: float,
                 visits: Visits | None = None, tol: float | None = None, slack_px: float = 0.0) -> PixelStates:
    """Elementary intervals and candidate values of every pixel over ``[lo, hi]``.

    A visit ``[t0, t1]`` is taken as *possibly* present on ``[t0 - tol, t1 + tol]`` and *surely* present
    on ``[t0 + tol, t1 - tol]`` (range ends excepted), and those four instants are the breakpoints, so a
    boundary's float uncertainty sits in an interval of its own. Candidates of an interval: every
    possibly present point that no surely present point beats (nearer by more than
    :func:`.motion.depth_tie_margin` at both ends of the interval: near-ties count both points),
    plus the background unless some point is surely present. Under ``rx``/``ry`` the depth order of
    two candidates can swap inside an interval: those instants are added as breakpoints too, so
    ``winner`` (the renderer's choice) is constant on every interval.

    ``slack_px`` (the bounds: :data:`RENDER_SLACK_PX`): the renderer computes ``u`` and ``v`` in torch, in
    another order of float operations than this sweep (``1/Z'`` then a fused multiply-add), so where a point's
    ``u`` only touches a footprint edge the two may disagree by an ulp on whether it enters the pixel. A point is
    then *possibly* present wherever its footprint widened by ``slack_px`` covers the pixel, and *surely*
    present only where its footprint narrowed by ``slack_px`` does. (``winner``, which the planner reads, is
    then only approximate near edges; the planner asks for no slack.)
    """
    points = np.asarray(points, dtype=np.float64)
    sure_ok = None
    if visits is None and slack_px > 0:
        wide = compute_visits(points, intr, axis, lo, hi, overlap=PIXEL_OVERLAP + slack_px)
        narrow = compute_visits(points, intr, axis, lo, hi, overlap=PIXEL_OVERLAP - slack_px)
        visits = Visits(*(np.concatenate([getattr(wide, f.name), getattr(narrow, f.name)]) for f in fields(Visits)))
        sure_ok = np.r_[np.zeros(len(wide), bool), np.ones(len(narrow), bool)]
    elif visits is None:
        visits = compute_visits(points, intr, axis, lo, hi)
    if tol is None:
        tol = default_tol(lo, hi)
    st = _states(points, intr, axis, lo, hi, visits, tol, np.zeros(0, np.int64), np.zeros(0), sure_ok)
    if axis in ("rx", "ry"):
        cpix, ct = _depth_order_crossings(points, axis, st)
        if len(cpix):
            st = _states(points, intr, axis, lo, hi, visits, tol, cpix, ct, sure_ok)
    return st


def _block_search(keys: np.ndarray, bs: np.ndarray, be: np.ndarray, target: np.ndarray, strict: bool) -> np.ndarray:
    """Per query, the first index ``j`` in ``[bs, be)`` with ``keys[j] >= target`` (``> target`` if strict),
    ``be`` if none; ``keys`` is sorted inside every block."""
    lo_i, hi_i = bs.copy(), be.copy()
    n = len(keys)
    if n == 0 or len(bs) == 0:
        return lo_i
    steps = int(np.ceil(np.log2(max(2, int((be - bs).max(initial=1)) + 1)))) + 1
    for _ in range(steps):
        mid = (lo_i + hi_i) // 2
        k = keys[np.minimum(mid, n - 1)]
        go = (mid < hi_i) & ((k <= target) if strict else (k < target))
        lo_i = np.where(go, mid + 1, lo_i)
        hi_i = np.where(go, hi_i, mid)
    return lo_i


def _states(points, intr, axis, lo, hi, visits: Visits, tol: float, extra_pix, extra_t, sure_ok=None) -> PixelStates:
    H, W = intr.height, intr.width
    npix = H * W
    vp = visits.row * W + visits.col
    at_lo, at_hi = visits.t0 <= lo, visits.t1 >= hi
    p0 = np.where(at_lo, lo, np.clip(visits.t0 - tol, lo, hi))
    d0 = np.where(at_lo, lo, np.clip(visits.t0 + tol, lo, hi))
    p1 = np.where(at_hi, hi, np.clip(visits.t1 + tol, lo, hi))
    d1 = np.where(at_hi, hi, np.clip(visits.t1 - tol, lo, hi))
    bp_pix = np.concatenate([vp, vp, vp, vp, np.arange(npix), np.arange(npix), extra_pix])
    bp_t = np.concatenate([p0, d0, d1, p1, np.full(npix, lo), np.full(npix, hi), extra_t])
    order = np.lexsort((bp_t, bp_pix))
    bp_pix, bp_t = bp_pix[order], bp_t[order]
    keep = np.concatenate([[True], (bp_pix[1:] != bp_pix[:-1]) | (bp_t[1:] != bp_t[:-1])])
    bp_pix, bp_t = bp_pix[keep], bp_t[keep]
    same = bp_pix[1:] == bp_pix[:-1]
    pix, start, end = bp_pix[:-1][same], bp_t[:-1][same], bp_t[1:][same]
    n_int = len(pix)
    block_start = np.searchsorted(pix, np.arange(npix), side="left")
    block_end = np.searchsorted(pix, np.arange(npix), side="right")
    # (visit, interval) pairs where the visit is possibly present: intervals from p0 to p1
    bs, be = block_start[vp], block_end[vp]
    first = _block_search(start, bs, be, p0, strict=False)
    last = _block_search(end, bs, be, p1, strict=True)  # exclusive
    cnt = np.maximum(0, last - first)
    total = int(cnt.sum())
    own = np.repeat(np.arange(len(visits)), cnt)
    off = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    jint = np.repeat(first, cnt) + off
    # group the pairs by interval (every interval has at least one pair or none at all)
    order = np.argsort(jint, kind="stable")
    jint, own = jint[order], own[order]
    vpt = visits.point[own]
    s_j, e_j = start[jint], end[jint]
    sure = (d0[own] <= s_j) & (e_j <= d1[own])
    if sure_ok is not None and total:
        # pixel_states' slack: a visit of the widened footprints is never sure, and a point is one candidate of an
        # interval however many of its visits cover it (sure if one of them is)
        sure &= sure_ok[own]
        key = jint.astype(np.int64) * (len(points) + 1) + vpt
        order = np.lexsort((~sure, key))
        first_of = order[np.concatenate([[True], key[order][1:] != key[order][:-1]])]
        first_of.sort()
        jint, own, vpt, s_j, e_j, sure = (x[first_of] for x in (jint, own, vpt, s_j, e_j, sure))
        total = len(jint)
    if total:
        g_first = np.concatenate([[True], jint[1:] != jint[:-1]])
        g_start = np.nonzero(g_first)[0]
        g_int = jint[g_start]
        gid = np.cumsum(g_first) - 1
    else:
        g_start = g_int = gid = np.zeros(0, np.int64)

    def group_min(x):
        return np.minimum.reduceat(x, g_start) if total else x[:0]

    # Candidates (the tie rule of motion.depth_tie_margin): Q is dropped only if some surely present point
    # R is nearer than Q by more than depth_tie_margin at both ends of the interval; depths closer than
    # that may compare either way in float arithmetic (ulp-close copies of a point, equal quantised
    # depths), and the renderer resolves an exact float tie to the lower index, which may be Q, so both
    # count. Depth differences of two points are linear in alpha (translations), constant (rz) or
    # harmonic (rx, ry: concave where positive, and two zeros are pi apart), so on an interval shorter
    # than pi a difference above the margin at both ends stays above the smaller margin throughout: the
    # test never drops a point that can win, float rounding included. Witnesses: the surely present
    # point nearest at the start (ties: nearest at the end) and the one nearest at the end (ties:
    # nearest at the start).
    P = points[vpt]
    ds = depth(P, axis, s_j)
    de = depth(P, axis, e_j)
    ms, me = depth_tie_margin(ds), depth_tie_margin(de)
    is_cand = np.ones(total, dtype=bool)
    for primary, secondary, m_p, m_s in ((ds, de, ms, me), (de, ds, me, ms)):
        p_sure = np.where(sure, primary, np.inf)
        p_min = group_min(p_sure)[gid]
        s_w = group_min(np.where(sure & (p_sure == p_min), secondary, np.inf))[gid]
        is_cand &= ~((p_min < primary - m_p) & (s_w < secondary - m_s))
    # winner (the renderer's choice at the midpoint): the nearest candidate present there, exact float
    # ties to the lower index (every point that can win is a candidate, so this is the renderer's rule)
    mid = 0.5 * (s_j + e_j)
    present = is_cand & (visits.t0[own] <= mid) & (mid <= visits.t1[own])
    dm = np.where(present, depth(P, axis, mid), np.inf)
    dm_min = group_min(dm)[gid]
    big = np.iinfo(np.int64).max
    w = group_min(np.where(present & (dm == dm_min), vpt, big))
    winner = np.full(n_int, -1, dtype=np.int64)
    winner[g_int] = np.where(w == big, -1, w)
    # candidate lists (CSR, background first); the background wherever no point is surely present
    has_sure = np.zeros(n_int, bool)
    if total:
        has_sure[g_int] = np.maximum.reduceat(sure, g_start)
    bgj = np.nonzero(~has_sure)[0]
    cj = np.concatenate([bgj, jint[is_cand]])
    cp = np.concatenate([np.full(len(bgj), -1, dtype=np.int64), vpt[is_cand]])
    order = np.argsort(cj, kind="stable")
    cj, cp = cj[order], cp[order]
    ptr = np.zeros(n_int + 1, dtype=np.int64)
    np.add.at(ptr, cj + 1, 1)
    ptr = np.cumsum(ptr)
    return PixelStates(lo, hi, pix, start, end, winner, ptr, cp, tol)


def _depth_order_crossings(points: np.ndarray, axis: str, st: PixelStates) -> tuple[np.ndarray, np.ndarray]:
    """(pixel, alpha) where two candidates of one interval swap depth order strictly inside it (rx/ry:
    the depth difference ``A cos t + B sin t`` vanishes at ``atan2(B, A) + pi/2 + k pi``)."""
    X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
    real = st.cand_point >= 0
    cnt = np.add.reduceat(real.astype(np.int64), st.cand_ptr[:-1]) if len(st.cand_point) else np.zeros(len(st.pix), np.int64)
    cnt = np.where(np.diff(st.cand_ptr) > 0, cnt, 0)
    out_pix, out_t = [], []
    for k in np.unique(cnt[cnt >= 2]):
        js = np.nonzero(cnt == k)[0]
        # candidate lists are sorted with the background (-1) first: real points are the last k
        base = st.cand_ptr[js + 1] - k
        ia, ib = np.triu_indices(int(k), 1)
        pa = st.cand_point[base[:, None] + ia[None, :]].ravel()
        pb = st.cand_point[base[:, None] + ib[None, :]].ravel()
        jj = np.repeat(js, len(ia))
        A = Z[pa] - Z[pb]
        B = (Y[pb] - Y[pa]) if axis == "rx" else (X[pa] - X[pb])
        phi = np.arctan2(B, A) + 0.5 * np.pi
        s, e = st.start[jj] + st.tol, st.end[jj] - st.tol
        for m in range(-2, 3):
            t = phi + m * np.pi
            ok = (t > s) & (t < e) & ((A != 0) | (B != 0))
            out_pix.append(st.pix[jj[ok]])
            out_t.append(t[ok])
    if not out_pix:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(out_pix).astype(np.int64), np.concatenate(out_t)

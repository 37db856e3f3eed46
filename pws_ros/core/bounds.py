"""Sound per-segment bounds for a rendered plan (holes included).

For a plan ``alpha_1 < ... < alpha_N`` and frames ``x_i``, every frame ``x(alpha)`` with ``alpha`` in segment
``[alpha_i, alpha_{i+1}]`` shows, at each pixel, one of the values the exact sweep (:mod:`.sweep`) allows
there: the end frames' values, or an *extra* value (a point that appears only inside the segment, a
second point that swaps in, or the background of a hole). With ``V_{p,i}`` those values:

* ``pair_bound_sq[i] = sum_p max_{v in V_{p,i} ∪ {x_i[p], x_{i+1}[p]}} (|v - x_i[p]|^2 + |v - x_{i+1}[p]|^2)``
  bounds ``|x(alpha) - x_i|^2 + |x(alpha) - x_{i+1}|^2``; it equals ``|x_i - x_{i+1}|^2`` where Lemma 1 holds.
* ``D_i(y)^2 = sum_p max_v |v - y[p]|^2`` bounds ``|x(alpha) - y|^2`` for any anchor frame ``y``.

Distances are computed on the float32 frames exactly as they are handed to the noise, in float64,
with a relative safety margin for rounding.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .partition import Plan, validate_grid
from .render import Renderer
from .sweep import RENDER_SLACK_PX, pixel_states

SAFETY = 1.0 + 1e-9


@dataclass
class SegmentValues:
    """Sparse extra values per (segment, pixel): ``seg``, ``pix`` (row * W + col), ``val`` (E, 3) float32."""

    alphas: np.ndarray
    seg: np.ndarray
    pix: np.ndarray
    val: np.ndarray
    shape: tuple[int, int]

    @property
    def num_segments(self) -> int:
        return len(self.alphas) - 1

    def _slice(self, k0: int, k1: int) -> slice:
        a = int(np.searchsorted(self.seg, k0, side="left"))
        b = int(np.searchsorted(self.seg, k1, side="left"))
        return slice(a, b)

    def pair_bound_sq(self, frames: np.ndarray, k0: int = 0) -> np.ndarray:
        """Bounds for segments ``k0 .. k0 + len(frames) - 2`` given the frames ``x_{k0} .. x_{k0+len-1}``."""
        f = _flat(frames)
        a, b = f[:-1], f[1:]
        d = ((a - b) ** 2).sum(axis=2)  # (S, P)
        base = d.sum(axis=1)
        def excess(seg, pix, v):
            return ((v - a[seg, pix]) ** 2).sum(1) + ((v - b[seg, pix]) ** 2).sum(1) - d[seg, pix]

        return (base + self._extra(k0, len(base), excess)) * SAFETY

    def _extra(self, k0: int, nseg: int, excess_fn) -> np.ndarray:
        """Per segment ``k0 .. k0+nseg-1``: sum over pixels of the largest positive excess of an extra value."""
        sl = self._slice(k0, k0 + nseg)
        if sl.stop <= sl.start:
            return np.zeros(nseg)
        seg = self.seg[sl] - k0
        pix = self.pix[sl]
        return _sum_of_group_max(seg, pix, excess_fn(seg, pix, self.val[sl].astype(np.float64)), nseg)

    def anchor_dist_sq(self, frames: np.ndarray, anchor: np.ndarray, k0: int = 0) -> np.ndarray:
        """``D_i(anchor)^2`` for segments ``k0 ..`` given consecutive frames (see module doc)."""
        f = _flat(frames)
        y = _flat(anchor[None])[0]
        a, b = f[:-1], f[1:]
        da = ((a - y) ** 2).sum(axis=2)
        db = ((b - y) ** 2).sum(axis=2)
        m = np.maximum(da, db)
        base = m.sum(axis=1)

        def excess(seg, pix, v):
            return ((v - y[pix]) ** 2).sum(1) - m[seg, pix]

        return (base + self._extra(k0, len(base), excess)) * SAFETY


def _flat(frames) -> np.ndarray:
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().numpy()
    f = np.asarray(frames, dtype=np.float64)
    return f.reshape(f.shape[0], -1, f.shape[-1])


def _sum_of_group_max(seg: np.ndarray, pix: np.ndarray, excess: np.ndarray, nseg: int) -> np.ndarray:
    """Per segment, the sum over pixels of max(0, max excess of that (segment, pixel))."""
    out = np.zeros(nseg)
    pos = excess > 0
    if not pos.any():
        return out
    seg, pix, excess = seg[pos], pix[pos], excess[pos]
    key = seg.astype(np.int64) * (int(pix.max()) + 1) + pix
    uniq, inv = np.unique(key, return_inverse=True)
    best = np.zeros(len(uniq))
    np.maximum.at(best, inv, excess)
    useg = (uniq // (int(pix.max()) + 1)).astype(np.int64)
    np.add.at(out, useg, best)
    return out


def segment_values(cloud: Cloud, intr: CameraIntrinsics, axis: str, alphas: np.ndarray, background: float = 0.0) -> SegmentValues:
    """The extra values each pixel can take strictly inside each segment (see module doc)."""
    alphas = np.asarray(alphas, dtype=np.float64)
    pts = cloud.points
    lo, hi = float(alphas[0]), float(alphas[-1])
    st = pixel_states(pts, intr, axis, lo, hi, slack_px=RENDER_SLACK_PX)   # (the renderer's rounding: .sweep)
    nseg = len(alphas) - 1
    # An interval counts for every segment it comes within tol of (a boundary near a grid point may
    # fall on either side of it in the renderer); intervals starting at lo / ending at hi are exact there.
    tol = st.tol
    s = np.where(st.start <= lo, -np.inf, st.start)
    e = np.where(st.end >= hi, np.inf, st.end)
    k_first = np.clip(np.searchsorted(alphas, s - tol, side="left") - 1, 0, nseg - 1)
    k_last = np.clip(np.searchsorted(alphas, e + tol, side="right") - 1, 0, nseg - 1)
    ncand = st.num_candidates
    multi = ncand > 1

    # singleton intervals: only the (at most two) segments they do not cover with margin tol
    def partial(k):
        return ~((s <= alphas[k] - tol) & (e >= alphas[k + 1] + tol))

    segs, ints = [], []
    for k in (k_first, k_last):
        sel = (~multi) & partial(k)
        segs.append(k[sel])
        ints.append(np.nonzero(sel)[0])
    # multi-candidate intervals: every segment they overlap
    mi = np.nonzero(multi)[0]
    if len(mi):
        cnt = k_last[mi] - k_first[mi] + 1
        own = np.repeat(mi, cnt)
        off = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        segs.append(k_first[own] + off)
        ints.append(own)
    seg_i = np.concatenate(segs)
    int_i = np.concatenate(ints)
    # dedupe (k_first == k_last)
    key = np.unique(seg_i.astype(np.int64) * (len(st.pix) + 1) + int_i)
    seg_i, int_i = key // (len(st.pix) + 1), key % (len(st.pix) + 1)
    # expand candidates
    c0, c1 = st.cand_ptr[int_i], st.cand_ptr[int_i + 1]
    cnt = c1 - c0
    own = np.repeat(np.arange(len(int_i)), cnt)
    off = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    cand = st.cand_point[c0[own] + off]
    colors = np.concatenate([cloud.colors, np.full((1, 3), background, dtype=np.float32)])
    val = colors[np.where(cand < 0, len(cloud.colors), cand)]
    seg_e = seg_i[own]
    pix_e = st.pix[int_i[own]]
    val = val.astype(np.float32)
    order = np.lexsort((val[:, 2], val[:, 1], val[:, 0], pix_e, seg_e))
    seg_e, pix_e, val = seg_e[order], pix_e[order], val[order]
    # each (segment, pixel, value) once: a value several intervals (or visits) list bounds nothing more
    new = np.ones(len(seg_e), bool)
    new[1:] = (seg_e[1:] != seg_e[:-1]) | (pix_e[1:] != pix_e[:-1]) | (val[1:] != val[:-1]).any(axis=1)
    return SegmentValues(alphas, seg_e[new], pix_e[new], val[new], intr.shape)


@dataclass
class RenderedPlan:
    """Frames of a plan with their per-segment bounds (everything the certifier needs)."""

    plan: Plan
    frames: torch.Tensor          # (N, H, W, 3) float32
    pair_bound_sq: np.ndarray     # (N-1,)
    values: SegmentValues
    seconds: float = 0.0

    @property
    def alphas(self) -> np.ndarray:
        return self.plan.alphas


def render_plan(cloud: Cloud, intr: CameraIntrinsics, plan: Plan, background: float = 0.0, device: str = "cpu",
                chunk: int = 256) -> RenderedPlan:
    """Render every pose of ``plan`` and compute the per-segment bounds (all frames kept in memory)."""
    t0 = time.perf_counter()
    validate_grid(plan.alphas, plan.radius)
    cloud.require_nonempty()
    r = Renderer(cloud, intr, plan.axis, background=background, device=device)
    values = segment_values(cloud, intr, plan.axis, plan.alphas, background)
    frames = []
    bounds = []
    prev = None
    for s, fr in r.iter_frames(plan.alphas, chunk=chunk):
        frames.append(fr)
        block = fr.cpu().numpy() if prev is None else np.concatenate([prev, fr.cpu().numpy()])
        k0 = s if prev is None else s - 1
        if len(block) >= 2:
            bounds.append(values.pair_bound_sq(block, k0))
        prev = fr[-1:].cpu().numpy()
    return RenderedPlan(plan, torch.cat(frames), np.concatenate(bounds) if bounds else np.zeros(0), values,
                        time.perf_counter() - t0)

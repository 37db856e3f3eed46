"""Sound per-segment bounds of the surfel imaging model (docs/imaging.md and :mod:`.imaging` for the
model; docs/certificate.md for how a certificate uses them).

For a segment ``[a, b]`` of the plan, every native pixel gets the per-channel interval ``[lo, hi]`` of
every value it can show for some ``alpha`` in the segment (:func:`segment_hulls`, :func:`hulls_within`):
the colours of every surfel whose footprint can cover its sample point there and that no surely covering
surfel always hides, plus its uncovered value unless some surfel surely covers it throughout. Footprint
corners are monotone between the split points of :func:`.motion.split_events`, so their ranges over the
segment are read at its ends and at those split points (:class:`.surfel.FootprintSweep`), widened by
``EDGE_EPS`` pixels for float rounding. The renderer ranks its surfels in occlusion order (key, then
index: one constant order for the whole motion), so a surfel that surely covers a pixel throughout the
segment hides every later surfel, equal keys included, by one comparison of ranks: no depth tolerance is
needed. The block mean is linear with positive weights, so the output pixel of every frame of the
segment lies in the block means of ``lo`` and ``hi`` (widened by ``VALUE_EPS`` for float32 rounding).
Distances to any frame ``y`` are then bounded by ``sum max((lo - y)^2, (hi - y)^2)`` (:class:`HullValues`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from .cloud import Cloud
from .errors import require
from .framing import EDGE_EPS, SAFETY, VALUE_EPS, Imaging, block_mean64
from .partition import validate_grid
from .motion import TRANSLATIONS
from .surfel import FootprintSweep, SurfelRenderer, covered_pairs, pixel_range
from .surfel_cover import UnionPolicy, first_covers


@dataclass
class HullValues:
    """Per segment ``i`` of ``alphas`` and output pixel/channel, ``lo[i] <= x(alpha) <= hi[i]`` for every
    ``alpha`` in ``[alphas[i], alphas[i+1]]`` (float32, already widened for rounding)."""

    alphas: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    constant: np.ndarray   # (S, H, W): the pixel shows one value throughout the segment (bitwise)
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def num_segments(self) -> int:
        return len(self.alphas) - 1

    def dist_sq(self, y: np.ndarray, segments: slice | np.ndarray | None = None) -> np.ndarray:
        """``D_i(y)^2 = sum max((lo - y)^2, (hi - y)^2)``: ``|x(alpha) - y|^2 <= D_i(y)^2`` on segment ``i``."""
        sel = slice(None) if segments is None else segments
        y = _as_numpy(y)
        # max((lo - y)^2, (hi - y)^2) = max(y - lo, hi - y)^2 (one of the two is the larger magnitude):
        # float64 throughout, two temporaries, the squares summed as a dot product
        m = np.subtract(y, self.lo[sel], dtype=np.float64)
        e = np.subtract(self.hi[sel], y, dtype=np.float64)
        np.maximum(m, e, out=m)
        m = m.reshape(m.shape[0], -1)
        return np.einsum("ij,ij->i", m, m) * SAFETY

    def pair_bound_sq(self, frames, k0: int = 0) -> np.ndarray:
        """``|x(alpha) - x_i|^2 + |x(alpha) - x_{i+1}|^2`` bounds for segments ``k0 .. k0 + len(frames) - 2``."""
        f = _as_numpy(frames)
        a, b = f[:-1], f[1:]
        sl = slice(k0, k0 + len(a))
        lo, hi = self.lo[sl].astype(np.float64), self.hi[sl].astype(np.float64)
        m = np.maximum((lo - a) ** 2 + (lo - b) ** 2, (hi - a) ** 2 + (hi - b) ** 2)
        return m.reshape(m.shape[0], -1).sum(axis=1) * SAFETY

    def anchor_dist_sq(self, frames, anchor, k0: int = 0) -> np.ndarray:
        """``D_i(anchor)^2`` for segments ``k0 .. k0 + len(frames) - 2`` (same interface as
        :class:`.bounds.SegmentValues`; only the number of frames is used)."""
        return self.dist_sq(anchor, slice(k0, k0 + len(frames) - 1))


    def to_segment_values(self, frames: np.ndarray):
        """The same bounds as sparse extra values (:class:`.bounds.SegmentValues`, the format that crosses
        the topics of the four-process mode): the 8 corners of the box ``[lo, hi]`` of every output
        pixel that is not constant over the segment (a convex distance is largest at a corner, so the
        maximum over the corners is the maximum over the box); a constant pixel shows the end frames'
        value throughout and needs none."""
        from .bounds import SegmentValues

        S = self.num_segments
        lo, hi = self.lo.reshape(S, -1, 3), self.hi.reshape(S, -1, 3)
        seg, pix = np.nonzero(~self.constant.reshape(S, -1))
        segs, pixs, vals = [], [], []
        for corner in range(8):
            pick = [(corner >> ch) & 1 for ch in range(3)]
            v = np.stack([(hi if pick[ch] else lo)[seg, pix, ch] for ch in range(3)], axis=1)
            segs.append(seg)
            pixs.append(pix)
            vals.append(v)
        seg_e, pix_e, val_e = np.concatenate(segs), np.concatenate(pixs), np.concatenate(vals)
        order = np.lexsort((pix_e, seg_e))
        h, w = self.lo.shape[1:3]
        return SegmentValues(np.asarray(self.alphas), seg_e[order], pix_e[order], val_e[order].astype(np.float32), (h, w))

    @classmethod
    def from_segment_values(cls, values, frames) -> "HullValues":
        """The boxes of sparse values received with their frames (the four-process certifier): per segment,
        pixel and channel the least and greatest of the values :class:`.bounds.SegmentValues` allows there
        (both end frames' values and the extra ones). Every value of the set lies in its box, so the box's
        distance bounds are at least the set's; for the sparse form of :meth:`to_segment_values` they are
        the original boxes where a pixel changes and the (bitwise equal) end values where it does not."""
        f = _as_numpy(frames, np.float32)
        require(f.ndim == 4 and f.shape[3] == 3, f"frames must be (N, H, W, 3), got {f.shape}")
        S = len(f) - 1
        require(S >= 1 and values.num_segments == S and tuple(values.shape) == tuple(f.shape[1:3]),
                f"bounds of {values.num_segments} segments at {values.shape} do not fit {len(f)} frames of {f.shape[1:3]}")
        seg, pix, val = np.asarray(values.seg), np.asarray(values.pix), np.asarray(values.val)
        require(seg.ndim == 1 and pix.shape == seg.shape and val.shape == seg.shape + (3,),
                f"sparse bounds need seg (E,), pix (E,) and val (E, 3), got {seg.shape}, {pix.shape}, {val.shape}")
        require(np.issubdtype(seg.dtype, np.integer) and np.issubdtype(pix.dtype, np.integer),
                "sparse bounds name segments and pixels by integers")
        require(bool(np.isfinite(f).all()) and bool(np.isfinite(val).all()), "frames or bounds contain NaN or inf")
        seg, pix = seg.astype(np.int64), pix.astype(np.int64)
        # values are float32 (the renderer's); any other float is rounded outwards, so the box still holds it
        v64 = val.astype(np.float64)
        v32 = v64.astype(np.float32)
        v_lo = np.where(v32.astype(np.float64) > v64, np.nextafter(v32, np.float32(-np.inf)), v32)
        v_hi = np.where(v32.astype(np.float64) < v64, np.nextafter(v32, np.float32(np.inf)), v32)
        lo = np.minimum(f[:-1], f[1:]).reshape(S, -1, 3)
        hi = np.maximum(f[:-1], f[1:]).reshape(S, -1, 3)
        constant = (f[:-1] == f[1:]).all(axis=3).reshape(S, -1)
        if len(seg):
            require(int(seg.min()) >= 0 and int(seg.max()) < S and int(pix.min()) >= 0 and int(pix.max()) < lo.shape[1],
                    "bounds name a segment or pixel outside the plan")
            key = seg * lo.shape[1] + pix
            order = np.argsort(key, kind="stable")
            key = key[order]
            start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
            g = key[start]
            gs, gp = g // lo.shape[1], g % lo.shape[1]
            lo[gs, gp] = np.minimum(lo[gs, gp], np.minimum.reduceat(v_lo[order], start, axis=0))
            hi[gs, gp] = np.maximum(hi[gs, gp], np.maximum.reduceat(v_hi[order], start, axis=0))
            constant[gs, gp] = False
        h, w = f.shape[1:3]
        return cls(np.asarray(values.alphas, dtype=np.float64), lo.reshape(S, h, w, 3), hi.reshape(S, h, w, 3),
                   constant.reshape(S, h, w), {"segments": S, "from": "segment values"})


def render_plan_surfel(cloud: Cloud, imaging: Imaging, plan, device: str = "cpu"):
    """Frames and bounds of a plan with the surfel model as a :class:`.bounds.RenderedPlan` (what the
    projector node publishes; the bounds as :meth:`HullValues.to_segment_values`)."""
    import time

    from .bounds import RenderedPlan

    t0 = time.perf_counter()
    validate_grid(plan.alphas, plan.radius)
    cloud.require_nonempty()
    r = SurfelRenderer(cloud, imaging, plan.axis, device=device, alpha_range=(float(plan.alphas[0]), float(plan.alphas[-1])))
    frames = r.render_batch(plan.alphas)
    hulls = segment_hulls(r, plan.alphas)
    f = frames.cpu().numpy()
    return RenderedPlan(plan, frames, hulls.pair_bound_sq(f), hulls.to_segment_values(f), time.perf_counter() - t0)


def _as_numpy(x, dtype=np.float64) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def segment_hulls(renderer: SurfelRenderer, alphas, *, max_bytes: int = 1 << 30) -> HullValues:
    """The per-segment value intervals of the surfel model for the grid ``alphas`` (see the module doc)."""
    alphas = np.asarray(alphas, dtype=np.float64)
    require(len(alphas) >= 2, "a plan needs at least two motion values")
    return hulls_within(renderer, float(alphas[0]), float(alphas[-1]), max_bytes=max_bytes)(alphas)


def hulls_within(renderer: SurfelRenderer, lo: float, hi: float, *, max_bytes: int = 1 << 30):
    """``hulls(g)``: the :class:`HullValues` of the segments of an increasing grid ``g`` inside ``[lo, hi]``,
    bounded in batches of segments by one sweep set up once over ``[lo, hi]``; for grids chosen one after
    another (:func:`.coverage.frontier_reach`) as for one whole plan (:func:`segment_hulls`). A grid
    whose bounds need more than ``max_bytes`` is refused. ``hulls(g, covers)`` also keeps what decided the
    bounds in ``covers`` (a :class:`SegmentCovers` of ``g``: frames inside the grid from it; ``at``: as its segments
    ``at ..``, a piece of its grid, closed by the caller); ``hulls(g, parent=covers)`` bounds segments inside those
    of a grid bounded before from its covers (:meth:`SegmentCovers.decide`)."""
    sweep = _HullSweep(renderer, float(lo), float(hi))
    h, w = renderer.imaging.out_shape

    def hulls(g, covers: "SegmentCovers | None" = None, parent: "SegmentCovers | None" = None, at: int | None = None) -> HullValues:
        g = np.asarray(g, dtype=np.float64)
        require(len(g) >= 2 and lo <= g[0] and g[-1] <= hi and bool(np.all(np.diff(g) > 0)),
                f"grid {g!r} is not increasing inside [{lo!r}, {hi!r}]")
        S = len(g) - 1
        require(covers is None or np.array_equal(covers.grid if at is None else covers.grid[at:at + S + 1], g),
                "internal: covers of another grid")
        need = 2 * S * h * w * 3 * 4
        require(need <= max_bytes, f"bounds of {S} segments at {w}x{h} need {need / 2**20:.0f} MiB, more than "
                                   f"{max_bytes / 2**20:.0f} MiB: use fewer partitions")
        l_ = np.empty((S, h, w, 3), np.float32)
        h_ = np.empty((S, h, w, 3), np.float32)
        constant = np.empty((S, h, w), bool)
        for s in range(0, S, sweep.batch):
            e = min(S, s + sweep.batch)
            l_[s:e], h_[s:e], constant[s:e] = sweep.segments(g[s:e + 1], None if covers is None else (covers, (at or 0) + s), parent)
        if covers is not None and at is None:
            covers.close()
        return HullValues(g, l_, h_, constant, {"surfels": renderer.num_points, "segments": S})

    return hulls


HULL_BATCH_ELEMENTS = 300_000   # surfel-segments bounded per batch of segments (about 0.5 KB each at the peak: ~160 MB)


class _HullSweep(FootprintSweep):
    """Bounds the surfel footprints over batches of consecutive segments: every tensor operation serves
    a whole batch, so its cost (and the wake-up of torch's threads) is shared by the segments."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.policy = UnionPolicy()   # whether a batch tries the union first (.surfel_cover), per sweep

    @property
    def batch(self) -> int:
        """Segments per batch."""
        return max(1, HULL_BATCH_ELEMENTS // max(1, self.P))

    def segments(self, g, keep=None, parent: "SegmentCovers | None" = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``lo, hi`` (B, h, w, 3) float32 and ``constant`` (B, h, w) of the segments of the grid ``g``;
        ``keep = (covers, s)``: their first surely covering surfels and candidates go to that
        :class:`SegmentCovers` as its segments ``s ..``; ``parent``: the covers of a coarser grid whose segments
        hold these (:meth:`SegmentCovers.decide`, where it applies), the same values."""
        g = np.asarray(g, dtype=np.float64)
        B = len(g) - 1
        if parent is not None and parent.decides(g):
            sure_first, q, cp = parent.decide(self, g)
        else:
            sure_first, q, cp = self._decide(g)
        if keep is not None:
            keep[0].add(keep[1], sure_first, q, cp)
        return self._values(B, sure_first, q, cp)

    def _decide(self, g) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The first surely covering ranks (B H W,) and candidates of the segments of ``g`` from every surfel."""
        r = self.r
        B = len(g) - 1
        H, W = r.intr.height, r.intr.width
        # candidates: possibly covering at some alpha of the segment, and among them the surely covering ones
        # (the sure box lies inside the sweep box, sure_drawn implies maybe): the first surely covering surfel in
        # occlusion order (its rank; P: none) per segment and native pixel hides every later surfel throughout
        # the segment (the order is constant in alpha, equal keys included: the renderer's own ranks), so the
        # candidates are the possibly covering surfels up to it (.surfel_cover.first_covers: that one alone
        # where nothing else can be, decided once for the batch from where the footprints can be over it)
        sure_first, q, cp = first_covers(lambda: self.union(float(g[0]), float(g[-1])), lambda sub: _segment_boxes(*self.ranges(g, sub), H, W),
                                         B, EDGE_EPS, -EDGE_EPS, r.rank, r.samples, covered_pairs, candidates=True, policy=self.policy)
        return sure_first.view(-1), q, cp

    def _values(self, B: int, sure_first: torch.Tensor, q: torch.Tensor, cp: torch.Tensor):
        """:meth:`segments`' values of ``B`` segments from their first surely covering ranks (B H W,) and
        candidates (``q = segment * H * W + pixel``, surfel ``cp``; any outer pairs of rank at most the first,
        at least those of rank below it)."""
        r = self.r
        H, W = r.intr.height, r.intr.width
        # the values of the native pixels: the renderer's own float32 colours (and its uncovered value of
        # each pixel where no surfel surely covers it: the renderer's table), their least and greatest per channel
        # exactly
        HW = H * W
        lo = r.shades.index_select(0, r.shade_rows(sure_first))                                # (B HW, 3)
        hi = lo.clone()
        im = r.imaging
        k = im.factor
        h, w = im.out_shape
        # output pixels whose every native pixel has one value throughout (lo == hi: no candidate's colour differs
        # from the pixel's first value): bitwise constant over the segment
        one = torch.ones(B * h * w, dtype=torch.bool, device=r.device)
        if len(cp):
            idx = q[:, None].expand(-1, 3)
            vals = r.colors.index_select(0, cp)
            moved = q[(vals != lo.index_select(0, q)).any(1)]
            b, p = torch.div(moved, HW, rounding_mode="floor"), moved % HW
            one[(b * h + torch.div(p, W * k, rounding_mode="floor")) * w + torch.div(p % W, k, rounding_mode="floor")] = False
            lo.scatter_reduce_(0, idx, vals, reduce="amin", include_self=True)
            hi.scatter_reduce_(0, idx, vals, reduce="amax", include_self=True)
        lo_o = block_mean64(lo.view(B, H, W, 3), im, -VALUE_EPS).to(torch.float32)
        hi_o = block_mean64(hi.view(B, H, W, 3), im, VALUE_EPS).to(torch.float32)
        one = one.view(B, h, w)
        bx, by = im.border
        if bx:
            one[:, :, :bx] = one[:, :, w - bx:] = True
        if by:
            one[:, :by] = one[:, h - by:] = True
        return lo_o.cpu().numpy(), hi_o.cpu().numpy(), one.cpu().numpy()


class SegmentCovers:
    """What decided the bounds of every segment of a grid, per native pixel: the first surfel (its rank;
    ``P``: none) surely covering it throughout the segment and the candidates, every surfel that may
    cover it somewhere in the segment, up to that one (:func:`.surfel_cover.first_covers`). Kept to decide
    the renderer's frames at poses inside the grid (the grid's refinement) from them instead of from every
    surfel (:meth:`render_batch`), and along a translation the bounds of the refinement's segments
    (:meth:`decide`).

    Why they are the renderer's frames bit for bit: at a pose inside a segment, a surfel the renderer finds
    covering a pixel (its footprint at that pose, the pixel range and box tests of
    :func:`.surfel.covered_pairs`, drawn there) has its footprint inside its sweep box over the segment and
    may be drawn there, so it is an outer pair of the segment; the first surely covering surfel covers the
    pixel at every pose of the segment and hides every later one. The pixel's winner is thus the least rank
    of the first surely covering surfel and of the candidates before it that the renderer's own tests find
    covering at the pose (the same tensors: the footprints of a subset are those of the whole, bit for bit;
    ``P``: nothing covers). Both are the soundness of the bounds themselves (the module doc: footprint ranges
    read at the segment's ends and split points, widened by ``EDGE_EPS``); and the footprints of a subset of
    surfels at one pose are those the renderer computes for all of them at a batch of poses, bit for bit (its
    own union path needs this too; test_surfel_cover.py). Only the candidates before the first surely
    covering surfel are kept, within ``max_bytes`` (else nothing: ``dropped``, and the renderer renders).
    Frames from them are compared with the renderer's in test_segment_covers.py, the certificates before and
    after in docs/timings.md (session 18)."""

    def __init__(self, renderer: SurfelRenderer, grid, max_bytes: int):
        self.r = renderer
        self.grid = np.asarray(grid, dtype=np.float64)
        self.max_bytes = int(max_bytes)
        S, HW = len(self.grid) - 1, renderer.intr.height * renderer.intr.width
        self.used = 4 * S * HW     # bytes held: 4 per segment and native pixel, 16 per candidate
        self.dropped = self.used > self.max_bytes   # nothing kept (the renderer renders then)
        self.first = None if self.dropped else torch.empty((S, HW), dtype=torch.int32, device=renderer.device)
        self._parts: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.where = self.point = self.starts = None

    def add(self, s: int, sure_first: torch.Tensor, q: torch.Tensor, cp: torch.Tensor) -> None:
        """Segments ``s ..``: ``sure_first`` (B H W,) ranks, candidates ``(q, cp)`` with ``q`` counted from segment ``s``."""
        if self.dropped:
            return
        HW = self.first.shape[1]
        B = len(sure_first) // HW
        self.first[s:s + B] = sure_first.view(B, HW)
        before = self.r.rank[cp] < sure_first[q]   # the first surely covering surfel itself needs no test
        self._parts.append((q[before] + s * HW, cp[before]))
        self._count(int(before.sum()))

    def adopt(self, k: int, other: "SegmentCovers", j: int) -> None:
        """Segment ``k`` is segment ``j`` of ``other`` (the same ends): its covers, copied."""
        if self.dropped:
            return
        HW = self.first.shape[1]
        a, b = other.starts[j], other.starts[j + 1]
        self.first[k] = other.first[j]
        self._parts.append((other.where[a:b] + (k - j) * HW, other.point[a:b]))
        self._count(b - a)

    def _count(self, candidates: int) -> None:
        self.used += 16 * int(candidates)
        # close() sorts the candidates: at its peak their pieces, one concatenation, the order and the sorted copy,
        # under four times their size (the first ranks are not copied)
        if self.used + 3 * (self.used - 4 * self.first.numel()) > self.max_bytes:
            self.dropped, self.first, self._parts = True, None, []

    def close(self) -> None:
        """The candidates of every segment in order (where = segment * H * W + pixel)."""
        if self.dropped:
            return
        S, HW = self.first.shape
        dev = self.first.device
        where = torch.cat([w for w, _ in self._parts]) if self._parts else torch.zeros(0, dtype=torch.long, device=dev)
        point = torch.cat([p for _, p in self._parts]) if self._parts else torch.zeros(0, dtype=torch.long, device=dev)
        order = torch.argsort(where)
        self.where, self.point, self._parts = where[order], point[order], []
        self.starts = torch.searchsorted(self.where, torch.arange(S + 1, device=dev) * HW).tolist()

    def first_ranks(self, alphas: torch.Tensor) -> torch.Tensor:
        """The rank of the surfel each native pixel shows at ``alphas`` (inside the grid), (B H W,): the renderer's
        :meth:`.surfel.SurfelRenderer.first_ranks`.
        Per segment, its first surely covering ranks lowered to those of its candidates' surfels covering
        the pixel at the pose (any other pixel such a surfel covers has its first before it)."""
        r, g = self.r, self.grid
        a = alphas.cpu().numpy()
        require(bool(np.all((g[0] <= a) & (a <= g[-1]))), f"alphas {a!r} outside the grid [{g[0]!r}, {g[-1]!r}]")
        B, HW = len(a), self.first.shape[1]
        k = np.clip(np.searchsorted(g, a, side="right") - 1, 0, len(g) - 2)
        ranks = self.first[torch.as_tensor(k, device=self.first.device)].to(torch.long)   # (B, HW), a copy
        for kk in np.unique(k).tolist():
            at = np.flatnonzero(k == kk)
            subset = torch.unique(self.point[self.starts[kk]:self.starts[kk + 1]], sorted=True)
            if len(subset):
                sel = torch.as_tensor(at, device=ranks.device)
                ranks[sel] = r.least_covering(alphas[sel], ranks[sel].reshape(-1), subset).view(len(at), HW)
        return ranks.view(-1)

    def render_batch(self, alphas) -> torch.Tensor:
        """The renderer's ``render_batch(alphas)`` for poses inside the grid, decided from the covers."""
        return self.r.render_batch(alphas, ranks=self.first_ranks)

    def decides(self, g) -> bool:
        """Whether :meth:`decide` applies to the segments of the grid ``g``: kept covers, a translation, each segment
        inside one of the covers' grid."""
        if self.dropped or self.where is None or self.r.axis not in TRANSLATIONS:
            return False
        g, G = np.asarray(g, dtype=np.float64), self.grid
        k = np.searchsorted(G, g[:-1], side="right") - 1
        return bool(np.all((k >= 0) & (k < len(G) - 1)) and np.all(g[1:] <= G[np.minimum(k + 1, len(G) - 1)]))

    def decide(self, sweep: "_HullSweep", g) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What :func:`.surfel_cover.first_covers` gives the bounds of the segments of ``g`` (each inside a segment of
        the covers' grid, a translation: :meth:`decides`), the first surely covering ranks (B H W,) and the
        candidates ``(where, surfel)`` of rank below them, from the covers of the parent segments instead of
        from every surfel.

        Why it is the same. Along a translation the computed projections are monotone in ``alpha`` between split
        events, bit for bit: ``u = cx + fx X / (Z - alpha)`` (tz) is a chain of float operations each monotone in
        the one argument that moves (a subtraction, the reciprocal on one side of the pole, a fused or unfused
        multiply-add), so a value at a new grid point lies between the values at the events or ends around it,
        which are the parent's; the same for ``v``, the corner depths and the centre depth (and tx, ty). So a
        child segment's sweep box lies inside its parent's and its sure box holds the parent's, bit for bit
        (:func:`_segment_boxes`; a wild child is a wild parent), and so do the pixel ranges
        :func:`.surfel.covered_pairs` enumerates (``ceil`` of an edge, monotone too). Hence a pair that may cover
        in the child may in the parent (an outer pair of the parent); the parent's first surely covering surfel surely covers in
        the child, so the child's first is at most the parent's; and every outer pair of the child of rank below
        the parent's first is a kept candidate of the parent. The child's first and candidates are then those
        among the parent's candidates that the bounds' own tests (boxes of the child from
        :meth:`.surfel.FootprintSweep.ranges`, ``EDGE_EPS`` as :func:`.surfel_cover.first_covers` widens them)
        find surely covering and maybe covering (its pixel range, box and mask, then the sure box and mask). Rotations mix two moving terms (``c X - s Z``): no such
        argument, and they are bounded from every surfel."""
        r, G = self.r, self.grid
        g = np.asarray(g, dtype=np.float64)
        B, HW = len(g) - 1, self.first.shape[1]
        H, W = r.intr.height, r.intr.width
        k = (np.searchsorted(G, g[:-1], side="right") - 1).tolist()
        dev = self.first.device
        first = self.first[torch.as_tensor(k, device=dev)].to(torch.long).view(-1)   # the parents' firsts, a copy
        where = torch.cat([self.where[self.starts[kk]:self.starts[kk + 1]] + (b - kk) * HW for b, kk in enumerate(k)])
        point = torch.cat([self.point[self.starts[kk]:self.starts[kk + 1]] for kk in k])
        if not len(point):
            return first, where, point
        subset, loc = torch.unique(point, sorted=True, return_inverse=True)
        outer, omask, inner, imask = _segment_boxes(*sweep.ranges(g, subset), H, W)        # (B, U) each
        seg = torch.div(where, HW, rounding_mode="floor")
        pix = where - seg * HW
        su, sv = r.samples.su[pix], r.samples.sv[pix]
        eps, ieps = EDGE_EPS, -EDGE_EPS
        # the tests of .surfel.covered_pairs (as .surfel_cover.first_covers widens its boxes), pair by pair: the pixel
        # range it enumerates (where the samples do not imply it, .surfel_cover.range_implied), the box and mask
        u0, u1, v0, v1 = (x[seg, loc] for x in outer)
        col, row = pix % W, torch.div(pix, W, rounding_mode="floor")
        c0, c1, r0, r1 = pixel_range(u0, u1, v0, v1, eps, W, H)
        possible = omask[seg, loc] & (c0 <= col) & (col < c1) & (r0 <= row) & (row < r1) \
            & (u0 - eps <= su) & (su < u1 + eps) & (v0 - eps <= sv) & (sv < v1 + eps)
        sure = possible & imask[seg, loc] & (inner[0][seg, loc] - ieps <= su) & (su < inner[1][seg, loc] + ieps) \
            & (inner[2][seg, loc] - ieps <= sv) & (sv < inner[3][seg, loc] + ieps)
        rk = r.rank[point]
        first.scatter_reduce_(0, where[sure], rk[sure], reduce="amin", include_self=True)
        keep = possible & (rk < first[where])
        return first, where[keep], point[keep]


def _segment_boxes(u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi, H: int, W: int):
    """Per segment and surfel (:meth:`.surfel.FootprintSweep.ranges`) the sweep box (where the footprint can be),
    whether it may be drawn, the sure box (where it surely is) and whether it is surely drawn, each (B, P)."""
    # a surfel is drawn at alpha iff every corner and its centre are in front of the camera
    sure_drawn = (d_lo > 0).all(1) & (z_lo > 0)                                           # (B, P)
    maybe = z_hi > 0
    # where a corner may cross depth 0 its projection is unbounded: the whole image
    wild = maybe & ~sure_drawn
    big = float(max(H, W)) + 10.0
    sweep = (u_lo.amin(1).masked_fill_(wild, -big), u_hi.amax(1).masked_fill_(wild, big),
             v_lo.amin(1).masked_fill_(wild, -big), v_hi.amax(1).masked_fill_(wild, big))
    # surely covered: left edge at its rightmost, right edge at its leftmost (module doc)
    sure = (u_hi.amin(1), u_lo.amax(1), v_hi.amin(1), v_lo.amax(1))
    return sweep, maybe, sure, sure_drawn


__all__ = ["HullValues", "SegmentCovers", "hulls_within", "render_plan_surfel", "segment_hulls"]

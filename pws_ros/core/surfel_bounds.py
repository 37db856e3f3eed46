"""Sound per-segment bounds of the surfel imaging model (docs/imaging.md and :mod:`.imaging` for the
model; docs/certificate.md for how a certificate uses them).

For a segment ``[a, b]`` of the plan, every native pixel gets the per-channel interval ``[lo, hi]`` of
every value it can show for some ``alpha`` in the segment (:func:`segment_hulls`, :func:`hulls_within`):
the colours of every surfel whose footprint can cover its sample point there and that no surely covering
surfel always hides, plus its uncovered value unless some surfel surely covers it throughout. Footprint
corners are monotone between the split points of :func:`.motion.split_events`, so their ranges over the
segment are read at its ends and at those split points (:class:`.footprint.FootprintSweep`), widened by
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
from .framing import EDGE_EPS, SAFETY, VALUE_EPS, Imaging, block_mean64, block_origins
from .partition import validate_grid
from .footprint import FootprintSweep, covered_pairs
from .surfel import SurfelRenderer
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

    def dist_sq(self, y: np.ndarray, segments: slice | np.ndarray | None = None, scratch: list | None = None) -> np.ndarray:
        """``D_i(y)^2 = sum max((lo - y)^2, (hi - y)^2)``: ``|x(alpha) - y|^2 <= D_i(y)^2`` on segment ``i``.
        ``scratch``: a list the caller keeps for its many calls, where the two work buffers stay between them."""
        at = np.arange(self.num_segments)[slice(None) if segments is None else segments]
        y = _as_numpy(y).reshape(-1)
        V = int(np.prod(self.lo.shape[1:]))
        lo, hi = self.lo.reshape(len(self.lo), V), self.hi.reshape(len(self.hi), V)
        S = len(at)
        out = np.empty(S)
        # max((lo - y)^2, (hi - y)^2) = max(y - lo, hi - y)^2 (one of the two is the larger magnitude): float64
        # throughout (the bounds cast as they are copied, then subtracted in place: cheaper than a casting ufunc, the
        # same values), the squares of each segment summed as one dot product. Taken a few segments at a time in two
        # buffers (kept in ``scratch`` for the next call: they stay in the cache, no page is mapped anew). Never one segment alone
        # when the call has more: numpy's einsum sums a lone row in another order than each row of a block of two or
        # more, and every block of two or more alike, so a segment's value is the same bit for bit in every call of
        # two or more segments, whichever they are (a call of one segment sums it alone)
        step = max(2, DIST_CHUNK_VALUES // max(1, V)) if S > 1 else 1
        starts = list(range(0, S, step))
        if len(starts) > 1 and S - starts[-1] == 1:
            starts.pop()   # the last block takes the segment that would be alone
        m, d = _work_buffers(scratch, min(S, step + 1), V)
        for s, e in zip(starts, starts[1:] + [S]):
            for k, i in enumerate(at[s:e].tolist()):
                m[k], d[k] = lo[i], hi[i]
            mm, dd = m[:e - s], d[:e - s]
            np.subtract(y, mm, out=mm)
            np.subtract(dd, y, out=dd)
            np.maximum(mm, dd, out=mm)
            out[s:e] = np.einsum("ij,ij->i", mm, mm)
        return out * SAFETY

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


def _work_buffers(scratch: list | None, rows: int, V: int) -> list[np.ndarray]:
    """Two float64 buffers of at least ``rows`` rows of ``V`` values: those kept in ``scratch`` if they fit, else new
    ones (kept there)."""
    if scratch and scratch[0].shape[0] >= rows and scratch[0].shape[1] == V:
        return scratch
    got = [np.empty((rows, V)), np.empty((rows, V))]
    if scratch is not None:
        scratch[:] = got
    return got


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
    bounds in ``covers`` (a :class:`.segment_covers.SegmentCovers` of ``g``: frames inside the grid from it; ``at``: as its segments
    ``at ..``, a piece of its grid, closed by the caller); ``hulls(g, parent=covers)`` bounds segments inside those
    of a grid bounded before from its covers (:meth:`.segment_covers.SegmentCovers.decide`)."""
    sweep = _HullSweep(renderer, float(lo), float(hi))
    h, w = renderer.imaging.out_shape

    def hulls(g, covers=None, parent=None, at: int | None = None) -> HullValues:
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
        values = HullValues(g, l_, h_, constant, {"surfels": renderer.num_points, "segments": S})
        if covers is not None and at is None:
            covers.close(values)
        return values

    return hulls


DIST_CHUNK_VALUES = 2**17       # float64 values per temporary of HullValues.dist_sq (1 MiB: in the cache)
# the largest share of output pixels not constant in the parent segments for which a refinement computes only those
# (gathered by index; more, and every output pixel is computed: measured on camera frames, about where both cost the same)
KEPT_SHARE = 0.25
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

    def segments(self, g, keep=None, parent=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``lo, hi`` (B, h, w, 3) float32 and ``constant`` (B, h, w) of the segments of the grid ``g``;
        ``keep = (covers, s)``: their first surely covering surfels and candidates go to that
        :class:`.segment_covers.SegmentCovers` as its segments ``s ..``; ``parent``: the covers of a coarser grid whose segments
        hold these (:meth:`.segment_covers.SegmentCovers.decide`, where it applies), the same values."""
        g = np.asarray(g, dtype=np.float64)
        B = len(g) - 1
        kept = None
        if parent is not None and parent.decides(g):
            sure_first, q, cp = parent.decide(self, g)
            kept = parent.kept_values(g)
        else:
            sure_first, q, cp = self._decide(g)
        if keep is not None:
            keep[0].add(keep[1], sure_first, q, cp)
        return self._values(B, sure_first, q, cp, kept)

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

    def _values(self, B: int, sure_first: torch.Tensor, q: torch.Tensor, cp: torch.Tensor, kept=None):
        """:meth:`segments`' values of ``B`` segments from their first surely covering ranks (B H W,) and
        candidates (``q = segment * H * W + pixel``, surfel ``cp``; any outer pairs of rank at most the first,
        at least those of rank below it). ``kept``: the parents' ``lo``, ``hi`` and constant pixels
        (:meth:`.segment_covers.SegmentCovers.kept_values`), the values there, so that only the other output pixels
        are computed (the same values, bit for bit)."""
        r = self.r
        H, W = r.intr.height, r.intr.width
        # the values of the native pixels: the renderer's own float32 colours (and its uncovered value of
        # each pixel where no surfel surely covers it: the renderer's table), their least and greatest per channel
        # exactly
        HW = H * W
        im = r.imaging
        k = im.factor
        h, w = im.out_shape
        # output pixels whose every native pixel has one value throughout (lo == hi: no candidate's colour differs
        # from the pixel's first value): bitwise constant over the segment
        one = torch.ones(B * h * w, dtype=torch.bool, device=r.device)
        moved = vals = None
        if len(cp):
            vals = r.colors.index_select(0, cp)
            # the candidates whose colour differs from the pixel's first value: only they move lo and hi (a colour
            # equal to it in every channel leaves both as they are, up to the sign of a zero, which no block mean
            # widened by VALUE_EPS below keeps)
            first_q = r.shades.index_select(0, r.shade_rows_at(sure_first, q))
            differ = torch.nonzero((vals != first_q).any(1), as_tuple=True)[0]
            moved, vals = q.index_select(0, differ), vals.index_select(0, differ)
            b, p = torch.div(moved, HW, rounding_mode="floor"), moved % HW
            one[(b * h + torch.div(p, W * k, rounding_mode="floor")) * w + torch.div(p % W, k, rounding_mode="floor")] = False
        one = one.view(B, h, w)
        bx, by = im.border
        if bx:
            one[:, :, :bx] = one[:, :, w - bx:] = True
        if by:
            one[:, :by] = one[:, h - by:] = True
        changing = ~one
        if kept is not None and float(kept[2].mean()) < 1.0 - KEPT_SHARE:
            kept = None   # most output pixels change in the parents: computing them all costs less than gathering them
        if kept is None:
            # every output pixel: lo of every native pixel, its block means; those of hi differ only at the output
            # pixels some native pixel of which changes (elsewhere lo == hi there, or the border: the same sums),
            # taken there alone in the same order
            lo = r.shades.index_select(0, r.shade_rows(sure_first))                                # (B HW, 3)
            hi = lo.clone()
            _spread(lo, hi, moved, vals)
            mean = block_mean64(lo.view(B, H, W, 3), im)
            lo_o = (mean - VALUE_EPS).to(torch.float32)
            mean[changing] = block_mean64(hi.view(B, H, W, 3), im, at=changing)
            hi_o = mean.add_(VALUE_EPS).to(torch.float32)
            return lo_o.cpu().numpy(), hi_o.cpu().numpy(), one.cpu().numpy()
        # the parents' values where a parent is constant (so is the child, with the same values); the other output
        # pixels (outside the border) computed as above from their native pixels alone
        p_lo, p_hi, p_const = kept
        todo = torch.nonzero((~torch.as_tensor(p_const, device=r.device) | changing).view(-1), as_tuple=True)[0]
        ch = torch.nonzero(changing.view(-1), as_tuple=True)[0]                  # (inside todo)
        nat = _natives(todo, im)
        lo = torch.empty((B * HW, 3), dtype=torch.float32, device=r.device)
        lo.index_copy_(0, nat, r.shades.index_select(0, r.shade_rows_at(sure_first, nat)))
        hi = torch.empty_like(lo)
        nat = _natives(ch, im)
        hi.index_copy_(0, nat, lo.index_select(0, nat))
        _spread(lo, hi, moved, vals)
        mean = block_mean64(lo.view(B, H, W, 3), im, at=todo)                 # (N, 3), in the order of todo
        lo_o = torch.from_numpy(p_lo).view(-1, 3)   # (copies: kept_values gathers the parents' rows)
        lo_o.index_copy_(0, todo.cpu(), (mean - VALUE_EPS).to(torch.float32).cpu())
        mean.index_copy_(0, torch.searchsorted(todo, ch), block_mean64(hi.view(B, H, W, 3), im, at=ch))
        hi_o = torch.from_numpy(p_hi).view(-1, 3)
        hi_o.index_copy_(0, todo.cpu(), mean.add_(VALUE_EPS).to(torch.float32).cpu())
        return p_lo, p_hi, one.cpu().numpy()


def _spread(lo: torch.Tensor, hi: torch.Tensor, moved, vals) -> None:
    """``lo``, ``hi`` (B H W, 3) lowered and raised, in place, to the colours ``vals`` of the candidates at native pixels
    ``moved``."""
    if moved is not None and len(moved):
        idx = moved[:, None].expand(-1, 3)
        lo.scatter_reduce_(0, idx, vals, reduce="amin", include_self=True)
        hi.scatter_reduce_(0, idx, vals, reduce="amax", include_self=True)


def _natives(at: torch.Tensor, im: Imaging) -> torch.Tensor:
    """The native pixels (``(b H + row) W + column``) of the output pixels ``at`` (flat indices, :func:`.framing.block_origins`)."""
    k, W = im.factor, im.out_shape[1] * im.factor
    off = (torch.arange(k, device=at.device)[:, None] * W + torch.arange(k, device=at.device)[None, :]).view(-1)
    return (block_origins(at, im)[:, None] + off[None, :]).view(-1)


def _segment_boxes(u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi, H: int, W: int):
    """Per segment and surfel (:meth:`.footprint.FootprintSweep.ranges`) the sweep box (where the footprint can be),
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


__all__ = ["HullValues", "hulls_within", "render_plan_surfel", "segment_hulls"]

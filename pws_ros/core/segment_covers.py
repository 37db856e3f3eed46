"""What decided the bounds of a grid's segments, kept per native pixel (:class:`SegmentCovers`): the frames
of poses inside the grid and the bounds of the segments of its refinement follow from it instead of from every
surfel (the frames bit for bit; the bounds bit for bit along a translation, soundly along a rotation:
:meth:`SegmentCovers.decide`; :mod:`.surfel_bounds` bounds the segments; test_segment_covers.py)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from .errors import require
from .framing import EDGE_EPS
from .footprint import pixel_range
from .surfel import SurfelRenderer
from .surfel_bounds import _segment_boxes
from .surfel_cover import lower_first, unique_indices

if TYPE_CHECKING:
    from .surfel_bounds import _HullSweep


class SegmentCovers:
    """What decided the bounds of every segment of a grid, per native pixel: the first surfel (its rank;
    ``P``: none) surely covering it throughout the segment and the candidates, every surfel that may
    cover it somewhere in the segment, up to that one (:func:`.surfel_cover.first_covers`). Kept to decide
    the renderer's frames at poses inside the grid (the grid's refinement) from them instead of from every
    surfel (:meth:`render_batch`), and the bounds of the refinement's segments (:meth:`decide`).

    Why they are the renderer's frames bit for bit: at a pose inside a segment, a surfel the renderer finds
    covering a pixel (its footprint at that pose, the pixel range and box tests of
    :func:`.footprint.covered_pairs`, drawn there) has its footprint inside its sweep box over the segment and
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
        self.used = self.first_bytes(renderer, S)     # bytes held: 4 per segment and native pixel, 16 per candidate
        self.dropped = self.used > self.max_bytes   # nothing kept (the renderer renders then)
        self.first = None if self.dropped else torch.empty((S, HW), dtype=torch.int32, device=renderer.device)
        self._parts: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.where = self.point = self.starts = None
        self.values = None   # the bounds these covers decided (a HullValues of the grid, given to close)

    @staticmethod
    def first_bytes(renderer: SurfelRenderer, segments: int) -> int:
        """What the first surely covering ranks of ``segments`` segments take (int32 per segment and native pixel): the
        least the covers of a grid of that many segments hold."""
        return 4 * int(segments) * renderer.intr.height * renderer.intr.width

    def add(self, s: int, sure_first: torch.Tensor, q: torch.Tensor, cp: torch.Tensor) -> None:
        """Segments ``s ..``: ``sure_first`` (B H W,) ranks, candidates ``(q, cp)`` with ``q`` counted from segment ``s``."""
        if self.dropped:
            return
        HW = self.first.shape[1]
        B = len(sure_first) // HW
        self.first[s:s + B] = sure_first.view(B, HW)
        # the first surely covering surfel itself needs no test
        before = torch.nonzero(self.r.rank.index_select(0, cp) < sure_first.index_select(0, q), as_tuple=True)[0]
        self._parts.append((q.index_select(0, before) + s * HW, cp.index_select(0, before)))
        self._count(len(before))

    def adopt(self, k: int, other: "SegmentCovers", j: int) -> None:
        """Segment ``k`` is segment ``j`` of ``other`` (the same ends): its covers, copied."""
        if self.dropped:
            return
        HW = self.first.shape[1]
        where, point = other._candidates(j)
        self.first[k] = other.first[j]
        self._parts.append((where + (k - j) * HW, point))
        self._count(len(point))

    def _count(self, candidates: int) -> None:
        self.used += 16 * int(candidates)
        # close() sorts the candidates: at its peak their pieces, one concatenation, the order and the sorted copy,
        # under four times their size (the first ranks are not copied)
        if self.used + 3 * (self.used - 4 * self.first.numel()) > self.max_bytes:
            self.dropped, self.first, self._parts = True, None, []

    def close(self, values=None) -> None:
        """The candidates of every segment in order (where = segment * H * W + pixel); ``values``: the bounds they
        decided (a :class:`.surfel_bounds.HullValues` of the grid), whose constant pixels a refinement keeps
        (:meth:`kept_values`)."""
        if self.dropped:
            return
        self.values = values
        S, HW = self.first.shape
        dev = self.first.device
        where = torch.cat([w for w, _ in self._parts]) if self._parts else torch.zeros(0, dtype=torch.long, device=dev)
        point = torch.cat([p for _, p in self._parts]) if self._parts else torch.zeros(0, dtype=torch.long, device=dev)
        order = torch.argsort(where)
        self.where, self.point, self._parts = where[order], point[order], []
        self.starts = torch.searchsorted(self.where, torch.arange(S + 1, device=dev) * HW).tolist()

    def _candidates(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Segment ``k``'s candidates (after :meth:`close`): ``where`` (= k H W + pixel) and surfel index."""
        a, b = self.starts[k], self.starts[k + 1]
        return self.where[a:b], self.point[a:b]

    def holds(self, alphas) -> bool:
        """Whether every pose of ``alphas`` lies inside the grid."""
        a, g = np.asarray(alphas, dtype=np.float64), self.grid
        return bool(np.all((g[0] <= a) & (a <= g[-1])))

    def _parents(self, g: np.ndarray) -> np.ndarray | None:
        """The segment of the grid holding each segment of the grid ``g`` (None: some segment lies in none)."""
        G = self.grid
        k = np.searchsorted(G, g[:-1], side="right") - 1
        if np.all((k >= 0) & (k < len(G) - 1)) and np.all(g[1:] <= G[np.minimum(k + 1, len(G) - 1)]):
            return k
        return None

    def first_ranks(self, alphas: torch.Tensor) -> torch.Tensor:
        """The rank of the surfel each native pixel shows at ``alphas`` (inside the grid), (B H W,): the renderer's
        :meth:`.surfel.SurfelRenderer.first_ranks`.
        Per segment, its first surely covering ranks lowered to those of its candidates' surfels covering
        the pixel at the pose (any other pixel such a surfel covers has its first before it)."""
        r, g = self.r, self.grid
        a = alphas.cpu().numpy()
        require(self.holds(a), f"alphas {a!r} outside the grid [{g[0]!r}, {g[-1]!r}]")
        k = np.clip(np.searchsorted(g, a, side="right") - 1, 0, len(g) - 2)
        dev = self.first.device
        ranks = self.first.index_select(0, torch.as_tensor(k, device=dev)).to(torch.long).view(-1)   # (B HW,), a copy
        # every pose with the surfels of its segment's candidates, as one flat batch of pose-surfel footprints
        poses, surfels = [], []
        for kk in np.unique(k).tolist():
            subset = unique_indices(self._candidates(kk)[1], r.num_points, inverse=False)
            if len(subset):
                for i in np.flatnonzero(k == kk).tolist():
                    poses.append(torch.full((len(subset),), i, dtype=torch.long, device=dev))
                    surfels.append(subset)
        if poses:
            pose = torch.cat(poses)
            r.least_covering_at(alphas.index_select(0, pose), torch.cat(surfels), pose, ranks)
        return ranks

    def render_batch(self, alphas) -> torch.Tensor:
        """The renderer's ``render_batch(alphas)`` for poses inside the grid, decided from the covers."""
        return self.r.render_batch(alphas, ranks=self.first_ranks)

    def kept_values(self, g):
        """For the segments of the grid ``g`` (:meth:`decides`): their parents' bounds ``lo``, ``hi`` (B, h, w, 3) and
        where a parent is constant (B, h, w), numpy; None where :meth:`close` was given no bounds.

        Where a parent segment is constant, the bounds :meth:`decide` leads to for a child (:mod:`.surfel_bounds`'
        values) are the parent's, bit for bit, so they need not be computed. Constant means every native pixel of the
        output pixel has no candidate whose colour differs from that of its first surely covering surfel (or its
        uncovered value), by ``!=``, or that it is in the border (whose values are the background's in every
        segment). The child's first surely covering surfel is the parent's or one of its candidates, and the child's
        candidates are some of the parent's (:meth:`decide`), so each native pixel's first value in the child equals
        the parent's (up to the sign of a zero) and no child candidate differs from it: the child is constant there,
        with the same block means (the same sums in the same order; a sum of zeros only may differ in its sign, which
        the bounds' ``VALUE_EPS`` removes) and so the same ``lo``, ``hi``."""
        if self.values is None:
            return None
        k = self._parents(np.asarray(g, dtype=np.float64))
        v = self.values
        return v.lo[k], v.hi[k], v.constant[k]

    def decides(self, g) -> bool:
        """Whether :meth:`decide` applies to the segments of the grid ``g``: kept covers, each segment inside one of
        the covers' grid."""
        if self.dropped or self.where is None:
            return False
        return self._parents(np.asarray(g, dtype=np.float64)) is not None

    def decide(self, sweep: "_HullSweep", g) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The first surely covering ranks (B H W,) and the candidates ``(where, surfel)`` of rank below them of the
        segments of ``g``, each inside a segment of the covers' grid (:meth:`decides`), as
        :func:`.surfel_cover.first_covers` gives them for the bounds, from the covers of the parent segments instead of
        from every surfel: the parent's candidates that the bounds' own tests (boxes of the child from
        :meth:`.footprint.FootprintSweep.ranges`, ``EDGE_EPS`` as :func:`.surfel_cover.first_covers` widens them: the
        pixel range, box and mask, then the sure box and mask) find maybe and surely covering in the child.

        Why it is sound, along any axis. A segment's covers hold two facts: at every pose of the segment, the surfel
        the renderer shows at a pixel is its first surely covering surfel or one of its candidates, and that first
        surfel covers the pixel at every pose. Covers found from every surfel hold them by the bounds' own soundness
        (the module doc of :mod:`.surfel_bounds`: footprint ranges read at the ends and split points, widened by
        ``EDGE_EPS``). A child lies inside its parent, so at each of its poses the renderer's winner is the parent's
        first or a parent candidate of lower rank. The child's own boxes (the same soundness over the child) keep the
        winner among the candidates that pass the child's test or make it the child's first, and a candidate passing
        the child's sure test covers the pixel throughout the child, so lowering the first to it hides only what it
        hides. So the child's covers found here hold both facts too (a further refinement may decide from them), and
        the values a pixel can show over the child lie among their colours, as the bounds need.

        Why it is the same as from every surfel. Along a translation, bit for bit: the computed projections are
        monotone in ``alpha`` between split events, ``u = cx + fx X / (Z - alpha)`` (tz) being a chain of float
        operations each monotone in the one argument that moves (a subtraction, the reciprocal on one side of the
        pole, a fused or unfused multiply-add), so a value at a new grid point lies between the values at the events
        or ends around it, which are the parent's; the same for ``v``, the corner depths and the centre depth (and tx,
        ty). So a child segment's sweep box lies inside its parent's and its sure box holds the parent's, bit for bit
        (:func:`.surfel_bounds._segment_boxes`; a wild child is a wild parent), and so do the pixel ranges
        :func:`.footprint.covered_pairs` enumerates (``ceil`` of an edge, monotone too). Hence a pair that may cover in
        the child may in the parent; the parent's first surely covering surfel surely covers in the child, so the
        child's first is at most the parent's; and every outer pair of the child of rank below the parent's first is
        a kept candidate of the parent. A rotation mixes two moving terms (``c X - s Z``): no such argument. There a
        child's box can come out a few ulps outside its parent's, and only where a sample point lies in that sliver
        can the two differ (both sound, by the argument above). Measured equal: every refinement of the RealSense,
        Kinect, TUM and demo frames (rx, ry, rz; issue 34) and 540 random clouds with near-plane points and one-ulp
        segments (test_segment_covers.py)."""
        r = self.r
        g = np.asarray(g, dtype=np.float64)
        HW = self.first.shape[1]
        H, W = r.intr.height, r.intr.width
        k = self._parents(g).tolist()
        dev = self.first.device
        first = self.first.index_select(0, torch.as_tensor(k, device=dev)).to(torch.long).view(-1)   # the parents' firsts, a copy
        parts = [self._candidates(kk) for kk in k]
        where = torch.cat([w + (b - kk) * HW for b, (kk, (w, _)) in enumerate(zip(k, parts))])
        point = torch.cat([p for _, p in parts])
        if not len(point):
            return first, where, point
        subset, loc = unique_indices(point, r.num_points)
        outer, omask, inner, imask = _segment_boxes(*sweep.ranges(g, subset), H, W)        # (B, U) each
        seg = torch.div(where, HW, rounding_mode="floor")
        pix = where - seg * HW
        su, sv = r.samples.su.index_select(0, pix), r.samples.sv.index_select(0, pix)
        eps, ieps = EDGE_EPS, -EDGE_EPS
        at = seg * len(subset) + loc   # the pair's (segment, surfel) in the (B, U) tensors

        def pick(x):
            return x.reshape(-1).index_select(0, at)

        # the tests of .footprint.covered_pairs (as .surfel_cover.first_covers widens its boxes), pair by pair: the pixel
        # range it enumerates (where the samples do not imply it, .surfel_cover.range_implied), the box and mask
        u0, u1, v0, v1 = (pick(x) for x in outer)
        col, row = pix % W, torch.div(pix, W, rounding_mode="floor")
        c0, c1, r0, r1 = pixel_range(u0, u1, v0, v1, eps, W, H)
        possible = pick(omask) & (c0 <= col) & (col < c1) & (r0 <= row) & (row < r1) \
            & (u0 - eps <= su) & (su < u1 + eps) & (v0 - eps <= sv) & (sv < v1 + eps)
        sure = possible & pick(imask) & (pick(inner[0]) - ieps <= su) & (su < pick(inner[1]) + ieps) \
            & (pick(inner[2]) - ieps <= sv) & (sv < pick(inner[3]) + ieps)
        rk = r.rank.index_select(0, point)
        lower_first(first, where, rk, sure)
        keep = torch.nonzero(possible & (rk < first.index_select(0, where)), as_tuple=True)[0]
        return first, where.index_select(0, keep), point.index_select(0, keep)


__all__ = ["SegmentCovers"]

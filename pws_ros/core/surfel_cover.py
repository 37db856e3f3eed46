"""Which surfel a native pixel shows over a batch of poses or segments, without testing every surfel at
every element of the batch (the renderer's winners, :class:`.surfel.SurfelRenderer`, and the bounds'
candidates, :mod:`.surfel_bounds`).

Both ask, per element ``b`` of a batch (a pose, or a segment of motion) and native pixel ``q``, about the
pairs (surfel ``p``, pixel ``q``) whose sample point lies in an *outer* box of ``p`` (:func:`.footprint.covered_pairs`:
a footprint, or where a footprint can be over a segment) and those whose sample lies in an *inner* box
(the same footprint, or where it surely is throughout the segment): ``first[b, q]``, the least occlusion
rank of the inner pairs (the renderer's winner, the bounds' first surely covering surfel), and the outer
pairs of rank at most ``first`` (the bounds' candidates). :func:`first_covers` gives exactly what
enumerating every element's pairs gives (:func:`reference_first_covers`), in two passes:

1. **Union.** One :func:`.footprint.covered_pairs` call on the boxes of the whole batch: per surfel the hull
   of its outer boxes (float ``min`` / ``max`` over the elements, so every element's box lies inside it
   bit for bit) and the intersection of its inner boxes and pixel ranges (inside every element's inner
   box). A pixel whose first pair in occlusion order among the union's is inside the intersection shows
   that surfel at every element (every other pair of that element has a larger rank): *static*, decided
   once for the batch.
2. **The rest.** The other pixels (*dynamic*: a nearer surfel's edge may cross the sample) are decided per
   element from their union pairs of rank at most the first static-inner one, with the very tests of
   :func:`.footprint.covered_pairs` (pixel range, then box; ``eps`` as given).

On a real camera frame most pixels are static over a batch of neighbouring poses (neighbouring surfels of
one surface overlap; only edges crossing a sample change a pixel), so the per-element work is a small share.
Everything is torch on the renderer's device, float64 boxes; no Python loop over elements or pixels.
"""
from __future__ import annotations

import torch

from .framing import SAMPLE_JITTER, SURFEL_OVERLAP

# relative and absolute room for float rounding between a box over a range of motion and the boxes at the
# poses or segments inside it (rounding is ~1e-16 relative; the union only has to be a superset)
UNION_SLACK = 1e-9
# dynamic pairs per surfel above which a batch is enumerated element by element instead (measured on camera
# frames: about where the two cost the same)
DYNAMIC_SHARE = 1.0
# px the median footprint may move over a batch for the union to be tried (rs / TUM tz batches move 0.2-0.5 px
# and gain, coarse ry grids about 1 px and do not)
MOTION_LIMIT = 0.6
# the least distance of a sample point from the edges of its jitter square for which the pixel ranges of
# covered_pairs never exclude a sample its box test takes (see range_implied)
MIN_MARGIN = 1e-9


def range_implied(samples) -> bool:
    """Whether a sample point inside a box (the box test of :func:`.footprint.covered_pairs`, any ``eps`` >= 0
    or its negative) always lies in the pixel range it enumerates for that box, so that the box test alone
    decides a pair. The range is the pixels whose jitter square ``c + 1/2 +- SAMPLE_JITTER`` reaches the box;
    a sample at least ``MIN_MARGIN`` inside its square is in range with that margin (float rounding of
    the range's expressions is below 1e-11 px for images under 10^5 px). Checked once per sample pattern
    (the R2 offsets keep about 1e-6 px from the square's edges on camera images)."""
    if getattr(samples, "_range_implied", None) is None:
        ok = max(samples.W, samples.H) < 10**5
        for s_, n in ((samples.su, samples.W), (samples.sv, samples.H)):
            centre = torch.arange(samples.H * samples.W, device=s_.device)
            centre = (centre % samples.W if n == samples.W else torch.div(centre, samples.W, rounding_mode="floor")).to(s_.dtype) + 0.5
            if len(s_):
                ok = ok and float((SAMPLE_JITTER - (s_ - centre).abs()).min()) > MIN_MARGIN
        samples._range_implied = bool(ok)
    return samples._range_implied


def unique_indices(x: torch.Tensor, n: int, inverse: bool = True):
    """``torch.unique(x, sorted=True, return_inverse=inverse)`` of indices ``x`` in ``[0, n)`` (long), by marking them
    in a table of ``n`` instead of sorting ``x`` (the same tensors; linear in ``n + len(x)``)."""
    mark = torch.zeros(n, dtype=torch.bool, device=x.device).index_fill_(0, x, True)
    subset = torch.nonzero(mark, as_tuple=True)[0]
    if not inverse:
        return subset
    return subset, torch.cumsum(mark, 0).sub_(1).index_select(0, x)


def lower_first(first: torch.Tensor, where: torch.Tensor, ranks: torch.Tensor, sure: torch.Tensor) -> torch.Tensor:
    """``first`` lowered in place, at ``where``, to the ``ranks`` of the pairs flagged ``sure`` (the first surely
    covering surfel of each element and pixel)."""
    i = torch.nonzero(sure, as_tuple=True)[0]
    return first.scatter_reduce_(0, where.index_select(0, i), ranks.index_select(0, i), "amin", include_self=True)


def widen(x: torch.Tensor, sign: float) -> torch.Tensor:
    """``x`` moved by ``UNION_SLACK`` outwards (``sign`` -1: down, +1: up; NaN: to that infinity)."""
    y = torch.add(x, x.abs().mul_(UNION_SLACK).add_(UNION_SLACK), alpha=sign)   # x + sign (SLACK + SLACK |x|)
    return y.nan_to_num_(nan=sign * float("inf"), posinf=float("inf"), neginf=-float("inf"))


class UnionPolicy:
    """Whether a batch tries the union first: after a batch whose pixels were mostly dynamic, or whose footprints
    moved more than ``MOTION_LIMIT`` (a motion of a good part of a pixel per batch, e.g. a coarse rotation grid), the
    next ``RETRY_AFTER`` batches of the same renderer or sweep enumerate their pairs directly. Only the speed depends
    on it."""

    RETRY_AFTER = 4

    def __init__(self):
        self.skip = 0


def union_of(u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi):
    """From the footprint ranges of each surfel over a range of motion ``[a, b]`` (one segment of
    :meth:`.footprint.FootprintSweep.ranges`: (C, P) and (P,)), the ``union`` of :func:`first_covers`: a box
    holding its footprint at every pose of ``[a, b]`` (``[-inf, inf]`` where a corner may cross depth 0),
    whether it may be drawn there, a box inside its footprint at every pose, and whether it is surely drawn
    throughout; with room for float rounding (:func:`widen`), so that the footprints and sweep boxes
    computed at poses and segments inside ``[a, b]`` lie inside the first box and hold the second bit for bit."""
    maybe = widen(z_hi, 1.0) > 0
    sure = (widen(d_lo, -1.0) > 0).all(0) & (widen(z_lo, -1.0) > 0)
    wild = maybe & ~sure
    inf = float("inf")
    outer = tuple(widen(x, sg).masked_fill_(wild, sg * inf)
                  for x, sg in ((u_lo.amin(0), -1.0), (u_hi.amax(0), 1.0), (v_lo.amin(0), -1.0), (v_hi.amax(0), 1.0)))
    inner = (widen(u_hi.amin(0), 1.0), widen(u_lo.amax(0), -1.0), widen(v_hi.amin(0), 1.0), widen(v_lo.amax(0), -1.0))
    return outer, maybe, inner, sure


def first_covers(union, element_boxes, B: int, eps: float, ieps: float, rank: torch.Tensor, samples, pairs,
                 candidates: bool = False, policy: UnionPolicy | None = None):
    """``first`` (B, H*W) long: per element ``b`` and native pixel the least ``rank`` of the surfels whose
    inner box holds the pixel's sample point among those whose outer box does, ``P`` where none, exactly as
    :func:`.footprint.covered_pairs` with ``inner`` tests them (:func:`reference_first_covers`); ``pairs``: that
    function (passed in by its module, which imports this one).

    ``element_boxes(subset)`` gives the boxes of the surfels ``subset`` (a sorted index tensor, None: all)
    at every element: ``(outer, omask, inner, imask)``, ``outer = (u0, u1, v0, v1)`` each (B, U), the inner box
    inside the outer one and ``imask`` implying ``omask``; the outer box is widened by ``eps``, the inner by
    ``ieps <= eps``, as covered_pairs widens them. ``union = (outer, omask, inner, imask)``, each (P,): per surfel a box holding
    its outer box at every element (with a mask true wherever ``omask`` is) and one inside its inner box at
    every element (``imask``: true only where ``imask`` is true at every element), with room for float
    rounding (:func:`widen`); or a function returning them, called only where the union pass is taken (a batch
    enumerated directly never needs it). ``policy``: see :class:`UnionPolicy`. With ``candidates``, also ``(where, point)`` of every outer pair of rank at
    most ``first`` at the pixels and elements where that may be more than the ``first`` surfel itself
    (``where = b * H * W + pixel``); everywhere else the ``first`` surfel (if any) is the only one."""
    def enumerated():   # every element's pairs (reference_first_covers)
        first, where, point = reference_first_covers(*element_boxes(None), eps, ieps, rank, samples, pairs)
        return (first, where, point) if candidates else first

    direct = policy is not None and policy.skip > 0
    if direct:
        policy.skip -= 1
    if direct or not range_implied(samples):
        return enumerated()
    if callable(union):   # given as a function: computed only now that the union pass is taken
        union = union()
    HW = samples.H * samples.W
    (U, umask, I, imask_u), P = union, len(rank)
    dev = rank.device
    if B > 1 and len(rank):
        # how far the footprints move over the batch (the union's width beyond the footprint's 1 + 2
        # SURFEL_OVERLAP px; the median surfel): past MOTION_LIMIT most pixels change, so enumerate directly
        move = torch.maximum(U[1] - U[0], U[3] - U[2])[umask & imask_u]
        if len(move) and float(move.median()) - (1.0 + 2 * SURFEL_OVERLAP) > MOTION_LIMIT:
            if policy is not None:   # the next batches of a grid move about as much: no union for them either
                policy.skip = policy.RETRY_AFTER
            return enumerated()
    # 1. the union: per pixel the first pair in occlusion order, and the first surely covering throughout
    pt, pix, ins = pairs(*(x[None] for x in U), umask[None], samples, eps, inner=(*(x[None] for x in I), imask_u[None], ieps))
    rk = rank.index_select(0, pt)
    r_first = torch.full((HW,), P, dtype=torch.long, device=dev).scatter_reduce_(0, pix, rk, "amin", include_self=True)
    s_first = lower_first(torch.full((HW,), P, dtype=torch.long, device=dev), pix, rk, ins)
    first = s_first.expand(B, HW).clone()
    # 2. the dynamic pixels: their union pairs up to the static first one, tested element by element
    dyn = torch.nonzero((r_first < s_first).index_select(0, pix) & (rk <= s_first.index_select(0, pix)), as_tuple=True)[0]
    pt, pix, rk = pt.index_select(0, dyn), pix.index_select(0, dyn), rk.index_select(0, dyn)
    if B > 1 and len(pt) > DYNAMIC_SHARE * P:
        # most pixels may change within the batch (a motion of a good part of a pixel): testing their pairs
        # element by element costs more than enumerating every element's pairs
        if policy is not None:
            policy.skip = policy.RETRY_AFTER
        return enumerated()
    where_out, point_out = [], []
    if len(pt):
        subset, loc = unique_indices(pt, P)
        outer, omask, inner, imask = element_boxes(subset)
        nan = torch.tensor(float("nan"), dtype=outer[0].dtype, device=dev)
        # one row per surfel and element (a mask folded in as NaN: no sample is inside a NaN box), gathered per pair
        # widened as covered_pairs widens them
        cols = [torch.where(omask, outer[0] - eps, nan), outer[1] + eps, outer[2] - eps, outer[3] + eps,
                torch.where(imask, inner[0] - ieps, nan), inner[1] + ieps, inner[2] - ieps, inner[3] + ieps]
        su, sv = samples.su.index_select(0, pix), samples.sv.index_select(0, pix)   # (D,)
        flat = first.view(-1)
        at = pix[None, :] + torch.arange(B, device=dev)[:, None] * HW          # (B, D)
        g = [c.index_select(1, loc) for c in cols]                             # (B, D) each
        possible = (g[0] <= su) & (su < g[1]) & (g[2] <= sv) & (sv < g[3])
        sure = possible & (g[4] <= su) & (su < g[5]) & (g[6] <= sv) & (sv < g[7])
        at, rkb = at.view(-1), rk.repeat(B)                                    # (B D,)
        lower_first(flat, at, rkb, sure.view(-1))
        if candidates:
            keep = torch.nonzero(possible.view(-1) & (rkb <= flat.index_select(0, at)), as_tuple=True)[0]
            where_out.append(at.index_select(0, keep))
            point_out.append(pt.repeat(B).index_select(0, keep))
    if not candidates:
        return first
    empty = torch.zeros(0, dtype=torch.long, device=dev)
    return first, (torch.cat(where_out) if where_out else empty), (torch.cat(point_out) if point_out else empty)


def reference_first_covers(outer, omask, inner, imask, eps: float, ieps: float, rank: torch.Tensor, samples, pairs):
    """:func:`first_covers` by enumerating every element's pairs (:func:`.footprint.covered_pairs`), what the
    renderer and the bounds did before it (boxes (B, P) as ``element_boxes`` gives them): ``first`` and
    every candidate pair ``(where, point)``."""
    B, P = outer[0].shape
    HW = samples.H * samples.W
    cp, q, is_sure = pairs(*outer, omask, samples, eps, inner=(*inner, imask, ieps))
    first = torch.full((B * HW,), P, dtype=torch.long, device=rank.device)
    rk = rank.index_select(0, cp)
    lower_first(first, q, rk, is_sure)
    keep = torch.nonzero(rk <= first.index_select(0, q), as_tuple=True)[0]
    return first.view(B, HW), q.index_select(0, keep), cp.index_select(0, keep)


__all__ = ["UnionPolicy", "first_covers", "lower_first", "range_implied", "reference_first_covers", "union_of", "unique_indices",
           "widen"]

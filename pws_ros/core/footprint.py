"""Where a surfel's footprint is, and which native pixels it covers (docs/imaging.md, sections 4 to 6): the
geometry the renderer (:mod:`.surfel`) and the bounds (:mod:`.surfel_bounds`, :mod:`.segment_covers`) share.

A surfel is the fronto-parallel square of :func:`surfel_corners` around its point; at motion ``alpha`` its
footprint is the axis-aligned bounding box ``[umin, umax) x [vmin, vmax)`` of its corners' projections
(:func:`project_corners`, :func:`footprint_corners`: the corners that decide it along an axis). It covers native
pixel ``(r, c)`` when the pixel's sample point (:class:`SamplePoints`) lies inside (:func:`covered_pairs`, the
pixels it can be: :func:`pixel_range`). :class:`FootprintSweep` is where the footprints can be over the segments
of a range of motion: per segment the range of every corner, read at the segment's ends and at the split points
of :func:`.motion.split_events` inside it.
"""
from __future__ import annotations

import numpy as np
import torch

from .camera import CameraIntrinsics
from .errors import require
from .framing import SAMPLE_JITTER, SURFEL_OVERLAP
from .motion import TRANSLATIONS, depth, project, split_events
from .surfel_cover import union_of

_CORNER_SIGNS = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))
# covered_pairs: the most pixel-surfel pairs one call may hold (a frame of a real camera holds a few
# million per batch; a cloud of points at the camera plane would ask for billions: refused, never allocated)
PAIR_BYTES = 17                      # two int64 indices and a flag per pair kept
MAX_COVERED_PAIRS = 32 * 2**20       # about 0.5 GiB of pairs
PAIR_CHUNK = 2**21                   # box pixels beyond the 2x2 corner enumerated at a time (bounded temporaries)


def footprint_corners(corners: np.ndarray, axis: str) -> np.ndarray:
    """The corners ``(C, P, 3)`` of :func:`surfel_corners` whose projections give every footprint along ``axis``:
    along a translation two opposite ones (0 and 3), since ``u`` of a corner depends on its ``X`` and ``Z`` only,
    ``v`` on its ``Y`` and ``Z``, and its depth on ``Z`` (corner 1 has the ``X`` of 3 and the ``Y`` of 0, corner 2
    the reverse, all four the same ``Z``): the other two project onto the same values bit for bit (the same
    float operations on the same numbers), at every pose and split event (a translation's only event, the pole
    of tz, is at ``Z``), so every least and greatest over the four corners is that over the two. Along a
    rotation all four."""
    return np.ascontiguousarray(corners[[0, 3]]) if axis in TRANSLATIONS else corners


def project_corners(corners: torch.Tensor, intr: CameraIntrinsics, axis: str, alpha: torch.Tensor):
    """``u, v, depth`` of the footprint corners ``corners`` (..., C, P, 3) at ``alpha`` (broadcast as
    :func:`.motion.project`), each (..., C', P): :func:`.motion.project` of every corner, except along ry with four
    corners, where a corner's ``u`` and depth depend on its ``X`` and ``Z`` only (the rotation leaves ``Y`` alone):
    those of the two columns (corners 0 and 1: ``X -+ hx``) are computed once, ``u`` and depth (..., 2, P) (corners 2
    and 3 share them bit for bit; corner ``k = 2 row + column``: :meth:`FootprintSweep.ranges` folds the split events
    of corner ``k`` into column ``k % 2``), and ``v`` (..., 4, P) from the rows' ``Y`` and the columns' ``1 / Z'``: the
    very operations of :func:`.motion.project` on the same numbers."""
    if axis != "ry" or corners.shape[-3] != 4:
        return project(corners, intr, axis, alpha, xp=torch)
    cols = corners[..., 0:2, :, :]                          # corners 0 and 1: X - hx, X + hx (Z shared)
    X, Z = cols[..., 0], cols[..., 2]
    c, s = torch.cos(alpha), torch.sin(alpha)
    Xp, Zp = torch.mul(X, c).addcmul_(Z, s, value=-1.0), torch.mul(X, s).addcmul_(Z, c)   # as motion._project_torch
    inv = torch.reciprocal(Zp).clamp_(-1e300, 1e300)
    u = torch.addcmul(torch.tensor(intr.cx + 0.5, dtype=inv.dtype, device=inv.device), Xp, inv, value=intr.fx)
    Y = corners[..., 0::2, :, 1]                            # corners 0 and 2: the rows' Y - hy, Y + hy
    v = torch.addcmul(torch.tensor(intr.cy + 0.5, dtype=inv.dtype, device=inv.device), Y.unsqueeze(-2), inv.unsqueeze(-3),
                      value=intr.fy)                        # (..., row, column, P): corner 2 row + column
    return u, v.flatten(-3, -2), Zp


def surfel_corners(points: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """The four corners ``(4, P, 3)`` of every surfel (see the module doc); a point at depth <= 0 has a
    surfel of size 0."""
    z = np.maximum(points[:, 2], 0.0)
    hx = (0.5 + SURFEL_OVERLAP) * z / intr.fx
    hy = (0.5 + SURFEL_OVERLAP) * z / intr.fy
    out = np.repeat(points[None], 4, axis=0).copy()
    for k, (sx, sy) in enumerate(_CORNER_SIGNS):
        out[k, :, 0] += sx * hx
        out[k, :, 1] += sy * hy
    return out


class SamplePoints:
    """Where each native pixel samples the footprints: its centre ``(c + 1/2, r + 1/2)`` moved by a fixed
    offset of at most SAMPLE_JITTER pixels per coordinate (a deterministic low-discrepancy pattern).

    At ``alpha = 0`` the offset changes nothing (a sample stays inside its own surfel and outside its
    neighbours'), but under motion the pixels of a uniformly shifted surface hand over at different
    instants instead of all at once, so the image changes gradually and no single pose change is a jump
    of the whole picture by a pixel."""

    def __init__(self, H: int, W: int, device):
        r, c = np.mgrid[0:H, 0:W]
        g = 1.32471795724474602596  # the plastic number: R2 sequence
        jx = SAMPLE_JITTER * (2.0 * np.mod(0.5 + (r * W + c) / g, 1.0) - 1.0)
        jy = SAMPLE_JITTER * (2.0 * np.mod(0.5 + (r * W + c) / (g * g), 1.0) - 1.0)
        self.W, self.H = W, H
        self.su = torch.as_tensor((c + 0.5 + jx).reshape(-1), device=device)
        self.sv = torch.as_tensor((r + 0.5 + jy).reshape(-1), device=device)


def pixel_range(umin, umax, vmin, vmax, eps: float, W: int, H: int):
    """The pixels whose sample point can lie in the box ``[umin - eps, umax + eps) x [vmin - eps, vmax + eps)``
    (their jitter squares ``c + 1/2 +- SAMPLE_JITTER`` reach it): columns ``c0 <= c < c1``, rows ``r0 <= r < r1``,
    float tensors holding integers in ``[0, W]``, ``[0, H]`` (NaN where an edge is NaN)."""
    return (torch.ceil(umin - (eps + 0.5 + SAMPLE_JITTER)).clamp_(0, W), torch.ceil(umax + (eps - 0.5 + SAMPLE_JITTER)).clamp_(0, W),
            torch.ceil(vmin - (eps + 0.5 + SAMPLE_JITTER)).clamp_(0, H), torch.ceil(vmax + (eps - 0.5 + SAMPLE_JITTER)).clamp_(0, H))


def covered_pairs(umin, umax, vmin, vmax, mask, samples: SamplePoints, eps: float, inner=None):
    """``(point, where, inside)`` of every native pixel whose sample point lies in the box
    ``[umin - eps, umax + eps) x [vmin - eps, vmax + eps)`` of a point where ``mask`` (arrays (B, P);
    ``eps`` < 0 shrinks the boxes), ``where = b * H * W + pixel`` for batch element ``b``. With
    ``inner = (umin, umax, vmin, vmax, mask, eps)`` of boxes inside these, ``inside`` flags the pairs whose
    sample also lies in the inner box (else None)."""
    W, H = samples.W, samples.H
    B, P = umin.shape
    dev = umin.device
    # the pixels whose sample can lie in the box: columns c0 <= c < c1, rows r0 <= r < r1
    c0, c1, r0, r1 = (x.long().view(-1) for x in pixel_range(umin, umax, vmin, vmax, eps, W, H))
    nc, nr = c1.sub_(c0).clamp_(min=0), r1.sub_(r0).clamp_(min=0)   # (a NaN edge: no pixel, not an overflow)
    live = mask.reshape(-1) & (nc > 0) & (nr > 0)
    base = r0.mul_(W).add_(c0)
    lo_u, hi_u = (umin - eps).view(-1), (umax + eps).view(-1)
    lo_v, hi_v = (vmin - eps).view(-1), (vmax + eps).view(-1)
    if inner is not None:
        iu0, iu1, iv0, iv1, imask, ieps = inner
        inner = ((iu0 - ieps).view(-1), (iu1 + ieps).view(-1), (iv0 - ieps).view(-1), (iv1 + ieps).view(-1), imask.reshape(-1))

    def inside(su, sv, boxes, at=None):   # samples su, sv in the boxes (at: of these boxes only)
        u0, u1, v0, v1 = (x if at is None else x.index_select(0, at) for x in boxes[:4])
        ok = (u0 <= su) & (su < u1) & (v0 <= sv) & (sv < v1)
        return ok.logical_and_(boxes[4] if at is None else boxes[4].index_select(0, at)) if len(boxes) > 4 else ok

    def modulo(f):   # f % P (one batch element: f itself)
        return f if B == 1 else f % P

    points, wheres, insides = [], [], []
    # the 2x2 corner of every box, offset by offset over all boxes at once (no per-pair gathers)
    batch_base = base + torch.arange(B, device=dev).mul_(H * W).repeat_interleave(P)   # b * H * W + r0 * W + c0
    wide, tall = nc > 1, nr > 1
    for sel, off in ((live, 0), (live & wide, 1), (live & tall, W), (live & wide & tall, W + 1)):
        pix = (base + off).clamp_(0, H * W - 1)
        su, sv = samples.su.index_select(0, pix), samples.sv.index_select(0, pix)
        f = torch.nonzero(inside(su, sv, (lo_u, hi_u, lo_v, hi_v, sel)), as_tuple=True)[0]
        points.append(modulo(f))
        wheres.append(batch_base.index_select(0, f).add_(off))
        if inner is not None:
            insides.append(inside(su.index_select(0, f), sv.index_select(0, f), inner, f))
    more = torch.nonzero(live & ((nc > 2) | (nr > 2)), as_tuple=True)[0]
    if len(more):  # boxes over 2 pixels a side (a point near the camera plane, long sweeps): the rest of each
        counts = nc.index_select(0, more) * nr.index_select(0, more)
        total = int(counts.sum()) + sum(len(w) for w in wheres)
        require(total <= MAX_COVERED_PAIRS,
                f"the surfels of this frame can cover {total} pixel-surfel pairs in one batch, more than the "
                f"{MAX_COVERED_PAIRS} (about {MAX_COVERED_PAIRS * PAIR_BYTES / 2**20:.0f} MiB) one frame may hold: "
                "points very near the camera plane or implausible coordinates (check the input cloud)")
        # enumerated in pieces of about PAIR_CHUNK pixels (memory stays bounded whatever the boxes): piece k
        # ends at the first box whose running pixel count reaches (k + 1) PAIR_CHUNK
        ends = torch.cumsum(counts, 0)
        marks = torch.arange(PAIR_CHUNK, int(ends[-1]) + PAIR_CHUNK, PAIR_CHUNK, device=dev)
        stops = torch.unique(torch.searchsorted(ends, marks).clamp_(max=len(more) - 1)).tolist()
        for start, stop in zip([0] + [s + 1 for s in stops[:-1]], stops):
            piece = more[start:stop + 1]
            nc_p = nc.index_select(0, piece)
            cnt = nc_p * nr.index_select(0, piece)
            rep = torch.repeat_interleave(torch.arange(len(piece), device=dev), cnt)
            t = torch.arange(int(cnt.sum()), device=dev) - (torch.cumsum(cnt, 0) - cnt).index_select(0, rep)
            f, ncr = piece.index_select(0, rep), nc_p.index_select(0, rep)
            dr, dc = torch.div(t, ncr, rounding_mode="floor"), t % ncr
            rest = torch.nonzero((dr > 1) | (dc > 1), as_tuple=True)[0]
            f, off = f.index_select(0, rest), dr.index_select(0, rest) * W + dc.index_select(0, rest)
            pix = base.index_select(0, f) + off
            su, sv = samples.su.index_select(0, pix), samples.sv.index_select(0, pix)
            ok = torch.nonzero(inside(su, sv, (lo_u, hi_u, lo_v, hi_v), f), as_tuple=True)[0]
            f, off, su, sv = (x.index_select(0, ok) for x in (f, off, su, sv))
            points.append(modulo(f))
            wheres.append(batch_base.index_select(0, f) + off)
            if inner is not None:
                insides.append(inside(su, sv, inner, f))
    return torch.cat(points), torch.cat(wheres), (torch.cat(insides) if inner is not None else None)


class FootprintSweep:
    """Where the surfel footprints can be over the segments of a grid: per segment and surfel the range of
    every corner's ``u``, ``v`` and the least corner depth and the centre depth range (:meth:`ranges`),
    read at the segment's ends and at the split points of :func:`.motion.split_events` inside it (between
    them every corner moves monotonically). Every tensor operation serves a whole batch of consecutive
    segments. The bounds (:mod:`.surfel_bounds`) build on it; the renderer uses it to leave out the
    surfels no motion of a range can show (:meth:`maybe_visible`)."""

    def __init__(self, r, lo: float, hi: float):   # r: the .surfel.SurfelRenderer (not imported: it imports this module)
        self.r = r
        self.P = r.num_points
        corners = r.corners_np.reshape(-1, 3)
        self.corner_ev = split_events(corners, r.axis, lo, hi)      # corner u, v, depth extrema
        self.centre_ev = split_events(r.points_np, r.axis, lo, hi)  # centre depth extrema

    @staticmethod
    def _inside(ev, g: np.ndarray, device):
        """The events strictly inside the segments of the grid ``g``: (index, alpha, segment) tensors (an
        event on a grid point is that point, evaluated as an end)."""
        i, t = ev
        s, e = np.searchsorted(t, g[0], side="right"), np.searchsorted(t, g[-1], side="left")
        i, t = i[s:e], t[s:e]
        seg = np.searchsorted(g, t, side="left") - 1          # g[seg] < t <= g[seg + 1]
        ok = t < g[np.minimum(seg + 1, len(g) - 1)]
        return (torch.as_tensor(i[ok], device=device), torch.as_tensor(t[ok], device=device),
                torch.as_tensor(seg[ok], device=device))

    def ranges(self, g, subset: torch.Tensor | None = None):
        """Per segment ``[g[k], g[k+1]]`` and surfel: the range of every footprint corner's ``u`` and ``v`` (B, C, P;
        :func:`footprint_corners`), the least corner depth (B, C, P), the centre depth range (B, P) each (along ry ``u``
        and depth per column, (B, 2, P): :func:`project_corners`). ``subset`` (sorted surfel indices): those surfels
        only (U in place of P), bit for bit the same values."""
        r, P = self.r, self.P
        g = np.asarray(g, dtype=np.float64)
        B = len(g) - 1
        t = torch.as_tensor(g, dtype=torch.float64, device=r.device)
        corners, points = (r.corners, r.points) if subset is None else (r.corners.index_select(1, subset), r.points.index_select(0, subset))
        C, U = corners.shape[:2]
        u, v, d = project_corners(corners[None], r.intr, r.axis, t[:, None, None])        # (B+1, C', U)
        Cu = u.shape[1]   # C, or the columns along ry (project_corners)
        zc = depth(points[None], r.axis, t[:, None], xp=torch)                           # (B+1, U)
        u_lo, u_hi = torch.minimum(u[:-1], u[1:]).reshape(-1), torch.maximum(u[:-1], u[1:]).reshape(-1)   # (B C U)
        v_lo, v_hi = torch.minimum(v[:-1], v[1:]).reshape(-1), torch.maximum(v[:-1], v[1:]).reshape(-1)
        d_lo = torch.minimum(d[:-1], d[1:]).reshape(-1)
        z_lo, z_hi = torch.minimum(zc[:-1], zc[1:]).reshape(-1), torch.maximum(zc[:-1], zc[1:]).reshape(-1)
        local = None
        if subset is not None:   # surfel index -> its place in the subset (-1: not in it)
            local = torch.full((P,), -1, dtype=torch.long, device=r.device)
            local[subset] = torch.arange(U, device=r.device)
        flat, te, seg = self._inside(self.corner_ev, g, r.device)
        if local is not None and len(flat):
            k, p = torch.div(flat, P, rounding_mode="floor"), flat % P
            ok = local[p] >= 0
            flat, te, seg = k[ok] * U + local[p[ok]], te[ok], seg[ok]
        if len(flat):
            uu, vv, dd = project(corners.reshape(-1, 3).index_select(0, flat), r.intr, r.axis, te, xp=torch)
            at = seg * (C * U) + flat
            # u and depth of corner k = 2 row + column go to slot k % Cu: its column along ry (project_corners),
            # the corner itself elsewhere (Cu = C)
            k = torch.div(flat, U, rounding_mode="floor")
            au = seg * (Cu * U) + (k % Cu) * U + (flat - k * U)
            # in place: each range is a new tensor of its own (no copy of the whole range per event scatter)
            u_lo.scatter_reduce_(0, au, uu, "amin")
            u_hi.scatter_reduce_(0, au, uu, "amax")
            v_lo.scatter_reduce_(0, at, vv, "amin")
            v_hi.scatter_reduce_(0, at, vv, "amax")
            d_lo.scatter_reduce_(0, au, dd, "amin")
        p, te, seg = self._inside(self.centre_ev, g, r.device)
        if local is not None and len(p):
            ok = local[p] >= 0
            p, te, seg = local[p[ok]], te[ok], seg[ok]
        if len(p):
            zz = depth(points[p], r.axis, te, xp=torch)
            at = seg * U + p
            z_lo.scatter_reduce_(0, at, zz, "amin")
            z_hi.scatter_reduce_(0, at, zz, "amax")
        shape, sh_u = (B, C, U), (B, Cu, U)
        return (u_lo.view(sh_u), u_hi.view(sh_u), v_lo.view(shape), v_hi.view(shape), d_lo.view(sh_u),
                z_lo.view(B, U), z_hi.view(B, U))

    def union(self, a: float, b: float):
        """Per surfel where its footprint can be over ``[a, b]``, with room for rounding (:func:`.surfel_cover.union_of`)."""
        return union_of(*(x[0] for x in self.ranges([a, b])))

    def maybe_visible(self, a: float, b: float) -> np.ndarray:
        """Surfels that can cover a native pixel for some alpha in ``[a, b]`` (a superset)."""
        u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi = (x[0] for x in self.ranges([a, b]))
        H, W = self.r.intr.height, self.r.intr.width
        wild = (z_hi > 0) & ~((d_lo > 0).all(0) & (z_lo > 0))
        inside = (u_hi.amax(0) >= -1) & (u_lo.amin(0) <= W + 1) & (v_hi.amax(0) >= -1) & (v_lo.amin(0) <= H + 1)
        return ((z_hi > 0) & (inside | wild)).cpu().numpy()


__all__ = ["FootprintSweep", "MAX_COVERED_PAIRS", "SamplePoints", "covered_pairs", "footprint_corners", "pixel_range",
           "project_corners", "surfel_corners"]

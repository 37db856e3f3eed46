"""The surfel renderer: the frames of the surfel imaging model for any motion (docs/imaging.md,
sections 4 to 7; the whole model: docs/imaging.md and :mod:`.imaging`).

Every point of the one-frame cloud stands for the surface patch its depth pixel saw: a fronto-parallel
square *surfel* centred on the point, of half side ``(1/2 + SURFEL_OVERLAP) Z / fx`` by
``(1/2 + SURFEL_OVERLAP) Z / fy`` (``Z`` its depth in the recorded frame, ``fx, fy`` the rendered camera,
:func:`surfel_corners`). At motion ``alpha`` its *footprint* is the axis-aligned bounding box
``[umin, umax) x [vmin, vmax)`` of the projections of its four corners (pixel-edge coordinates,
:func:`.motion.project`); it covers native pixel ``(r, c)`` when the pixel's sample point (its centre
``(c + 1/2, r + 1/2)`` moved by a fixed offset of at most ``SAMPLE_JITTER``, :class:`SamplePoints`) lies
inside (:func:`covered_pairs`). A surfel with a corner or its centre at depth ``<= 0`` is not drawn. The
pixel shows the covering surfel nearest to the *recorded* camera centre (the least :func:`occlusion_key`
``X^2 + Y^2 + Z^2``, float64; equal keys: the lower point index), or its uncovered value where none covers
it (invalid depth, disocclusions, what the recording never saw: ``Imaging.uncovered``). The order is fixed
for the whole motion: for rotations it is exactly the occlusion order along every ray (a rotation about
the optical centre has no parallax); for the translations of a certificate (millimetres) it can differ
from the moved camera's only between surfaces closer together along a ray than the translation. It also
keeps neighbours of one surface, whose patches overlap, from trading places as the camera turns
(ordering by the moved depth made every overlap of a slanted plane flip at one pose, a jump of the whole
image). At ``alpha = 0`` a cloud back-projected from the camera's own depth image re-renders that image
exactly (every surfel covers its own pixel); neighbours at equal depth overlap by ``SURFEL_OVERLAP``
pixels, so moving the camera opens no sampling holes, only true disocclusions.

Below the camera's resolution the cloud is first binned (:func:`bin_cloud`); frames are reduced to the
classifier's input by :func:`.framing.reduce_frames`. :class:`FootprintSweep` is where the footprints can
be over a range of motion, shared with the bounds (:mod:`.surfel_bounds`).
"""
from __future__ import annotations

import threading
import zlib
from typing import Iterator

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import require
from .framing import SAMPLE_JITTER, SURFEL_OVERLAP, Imaging, reduce_frames
from .motion import TRANSLATIONS, depth, parse_axis, project, split_events
from .render import DEFAULT_MAX_ELEMENTS, resolve_device
from .surfel_cover import UnionPolicy, first_covers, range_implied, union_of

_CORNER_SIGNS = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))
# covered_pairs: the most pixel-surfel pairs one call may hold (a frame of a real camera holds a few
# million per batch; a cloud of points at the camera plane would ask for billions: refused, never allocated)
PAIR_BYTES = 17                      # two int64 indices and a flag per pair kept
MAX_COVERED_PAIRS = 32 * 2**20       # about 0.5 GiB of pairs
# poses rendered from one union of footprints (surfel_cover.first_covers): neighbouring poses share most
# winners, poses far apart few
UNION_POSES = 5
PAIR_CHUNK = 2**21                   # box pixels beyond the 2x2 corner enumerated at a time (bounded temporaries)


class SurfelRenderer:
    """Renders frames of the surfel model for batches of motion values (torch, float64 geometry).

    Same interface as :class:`.render.Renderer`: ``render_batch(alphas)`` and ``iter_frames``; frames are
    ``(B, H, W, 3)`` float32 at the classifier's input size (the reduced, border-masked image). With
    ``alpha_range``, surfels that no motion in that range can bring into the image are left out at once
    (only motions inside the range may then be rendered)."""

    def __init__(self, cloud: Cloud, imaging: Imaging, axis: str, *, device: str | torch.device | None = "cpu",
                 max_elements: int = DEFAULT_MAX_ELEMENTS, alpha_range: tuple[float, float] | None = None):
        require(imaging.kind == "surfel", "SurfelRenderer needs surfel imaging")
        self.axis = parse_axis(axis)
        self.imaging = imaging
        self.alpha_range, self._sweep, self._policy, self._shades = None, None, UnionPolicy(), None
        self.intr = imaging.camera
        self.background = float(imaging.background)
        self.device = resolve_device(device)
        self.max_elements = int(max_elements)
        self.samples = SamplePoints(self.intr.height, self.intr.width, self.device)
        self._set_points(*bin_cloud(np.asarray(cloud.points, dtype=np.float64), np.asarray(cloud.colors, np.float32), imaging,
                                    cloud.filled_mask))
        # what each native pixel shows where no surfel covers it (imaging.uncovered), from every surfel drawn,
        # fixed for the whole motion: the renderer and the bounds read this one table
        HW = self.intr.height * self.intr.width
        if imaging.uncovered == "frame":
            self.uncovered = self.colors[self.by_rank[self.first_ranks(_alphas([0.0], self.device))]].reshape(HW, 3).clone()
        else:
            self.uncovered = self.colors[self.num_points].expand(HW, 3).clone()
        if alpha_range is not None:
            # drop the surfels no pose of the range can show (in order: the tie rule is unchanged)
            self._sweep = FootprintSweep(self, *alpha_range)
            keep = self._sweep.maybe_visible(*alpha_range)
            if not keep.all():
                self._set_points(self.points_np[keep], self.colors_np[keep])
                self._sweep = None          # made again, for the points kept, when several poses are rendered
            self.alpha_range = (float(alpha_range[0]), float(alpha_range[1]))

    def _set_points(self, pts: np.ndarray, colors: np.ndarray) -> None:
        self.num_points = len(pts)
        # the occlusion order as ranks (occlusion_key, then the index: a stable sort): surfel i hides surfel j
        # wherever both cover a pixel iff rank[i] < rank[j]; the renderer and the bounds compare ranks only
        order = np.argsort(occlusion_key(pts), kind="stable")
        rank = np.empty(len(pts), np.int64)
        rank[order] = np.arange(len(pts))
        self.rank = torch.as_tensor(rank, device=self.device)
        self.by_rank = torch.as_tensor(np.append(order, len(pts)), device=self.device)  # rank -> index, P -> P
        self.points_np, self.colors_np = pts, colors
        self.corners_np = footprint_corners(surfel_corners(pts, self.intr), self.axis)   # (C, P, 3)
        self.points = torch.as_tensor(pts, device=self.device)
        self.corners = torch.as_tensor(self.corners_np, device=self.device)
        bg = np.full((1, 3), self.background, dtype=np.float32)
        self.colors = torch.as_tensor(np.concatenate([colors, bg]), device=self.device)
        self._shades = None

    @property
    def shades(self) -> torch.Tensor:
        """What a native pixel shows, by rank (:meth:`first_ranks`): row ``k < P`` the colour of the surfel of
        rank ``k``, row ``P + pixel`` that pixel's uncovered value, float32 (P + H W, 3); the renderer's frames
        and the bounds' values (:mod:`.surfel_bounds`) read this one table (:meth:`shade_rows`)."""
        if self._shades is None:
            self._shades = torch.cat([self.colors.index_select(0, self.by_rank[:self.num_points]), self.uncovered])
            require(bool(torch.isfinite(self._shades).all()), "internal: a surfel colour or uncovered value that is not finite")
        return self._shades

    def shade_rows(self, ranks: torch.Tensor) -> torch.Tensor:
        """The rows of :attr:`shades` of ranks (B H W,) of native pixels (``P``: that pixel's uncovered value)."""
        HW = self.intr.height * self.intr.width
        P = self.num_points
        rows = ranks.view(-1, HW)
        return torch.where(rows == P, torch.arange(P, P + HW, device=ranks.device), rows).view(-1)

    def shade_rows_at(self, ranks: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        """:meth:`shade_rows` of ``ranks`` (B H W,) at the native pixels ``where`` (b H W + pixel) only."""
        HW = self.intr.height * self.intr.width
        P = self.num_points
        rows = ranks.index_select(0, where)
        return torch.where(rows == P, where % HW + P, rows)

    @property
    def chunk_size(self) -> int:
        return max(1, self.max_elements // max(1, 4 * self.num_points))

    def footprints(self, alphas: torch.Tensor, subset: torch.Tensor | None = None):
        """Footprint boxes ``umin, umax, vmin, vmax``, centre depth and drawn mask, each (B, P) (``subset``:
        of those surfels only, (B, U), bit for bit the same values)."""
        corners, points = (self.corners, self.points) if subset is None else (self.corners.index_select(1, subset),
                                                                              self.points.index_select(0, subset))
        return self._boxes(corners[None], points[None], alphas[:, None], 1)   # (B, C', P) corners, (B, P) each

    def _boxes(self, corners: torch.Tensor, points: torch.Tensor, alphas: torch.Tensor, dim: int):
        """Footprint boxes, centre depth and drawn mask of ``corners`` (corner axis ``dim``) and their ``points`` at
        ``alphas`` (broadcast against ``points``' leading axes), element by element."""
        u, v, d = project_corners(corners, self.intr, self.axis, alphas.unsqueeze(dim))
        zc = depth(points, self.axis, alphas, xp=torch)
        drawn = (d > 0).all(dim=dim) & (zc > 0)
        return u.amin(dim), u.amax(dim), v.amin(dim), v.amax(dim), zc, drawn

    def first_ranks(self, alphas: torch.Tensor) -> torch.Tensor:
        """The rank (:meth:`_set_points`) of the surfel each native pixel shows, (B Hn Wn,) (``num_points``: none
        covers it): the covering surfel first in occlusion order."""
        H, W = self.intr.height, self.intr.width
        B, n = alphas.shape[0], self.num_points
        idx = torch.full((B * H * W,), n, dtype=torch.long, device=self.device)
        if n == 0:
            return idx
        sweep = self._sweep_for(alphas)
        if sweep is None:
            return self.least_covering(alphas, idx)

        def boxes_at(alphas, subset):   # the footprints at every pose, inner box = outer box
            umin, umax, vmin, vmax, zc, drawn = self.footprints(alphas, subset)
            return (umin, umax, vmin, vmax), drawn, (umin, umax, vmin, vmax), drawn

        out = []
        for s in range(0, B, UNION_POSES):
            a = alphas[s:s + UNION_POSES]
            union = lambda a=a: sweep.union(float(a.min()), float(a.max()))   # noqa: E731 (only if the union pass runs)
            out.append(first_covers(union, lambda sub: boxes_at(a, sub), len(a), 0.0, 0.0, self.rank, self.samples,
                                    covered_pairs, policy=self._policy))
        return torch.cat(out).view(-1)

    def least_covering(self, alphas: torch.Tensor, ranks: torch.Tensor, subset: torch.Tensor | None = None) -> torch.Tensor:
        """``ranks`` (B H W,) lowered in place, per pose and native pixel, to the rank of every surfel (of the sorted
        index tensor ``subset``, None: all) covering it there (:func:`covered_pairs`, the footprints at the poses)."""
        umin, umax, vmin, vmax, zc, drawn = self.footprints(alphas, subset)
        p_i, where, _ = covered_pairs(umin, umax, vmin, vmax, drawn, self.samples, 0.0)
        return ranks.scatter_reduce_(0, where, self.rank.index_select(0, p_i if subset is None else subset.index_select(0, p_i)),
                                     reduce="amin", include_self=True)

    def least_covering_at(self, alphas: torch.Tensor, surfels: torch.Tensor, poses: torch.Tensor, ranks: torch.Tensor) -> torch.Tensor:
        """``ranks`` (B H W,) lowered in place: at pose ``poses[i]`` (motion ``alphas[i]``) to the rank of surfel
        ``surfels[i]`` wherever it covers a native pixel (:meth:`least_covering` for any pose-surfel pairs, in one
        flat batch: the footprints of :meth:`footprints` computed element by element, the same operations on the
        same numbers)."""
        HW = self.intr.height * self.intr.width
        umin, umax, vmin, vmax, _, drawn = self._boxes(self.corners.index_select(1, surfels), self.points.index_select(0, surfels),
                                                       alphas, 0)                           # (N,) each
        p_i, where, _ = covered_pairs(umin[None], umax[None], vmin[None], vmax[None], drawn[None], self.samples, 0.0)
        where = where + poses.index_select(0, p_i) * HW
        return ranks.scatter_reduce_(0, where, self.rank.index_select(0, surfels.index_select(0, p_i)), reduce="amin",
                                     include_self=True)

    def _sweep_for(self, alphas: torch.Tensor):
        """The footprint sweep over the renderer's motion range when it holds ``alphas`` and several poses are
        rendered at once (:func:`.surfel_cover.first_covers`), else None (each pose on its own)."""
        if len(alphas) < 2 or self.alpha_range is None or not range_implied(self.samples):
            return None
        if not (self.alpha_range[0] <= float(alphas.min()) and float(alphas.max()) <= self.alpha_range[1]):
            return None
        if self._sweep is None:
            self._sweep = FootprintSweep(self, *self.alpha_range)
        return self._sweep

    def _shade(self, ranks: torch.Tensor) -> torch.Tensor:
        """The colours (B, Hn, Wn, 3) of the ranks (B Hn Wn,) of :meth:`first_ranks`."""
        return self.shades.index_select(0, self.shade_rows(ranks)).view(-1, self.intr.height, self.intr.width, 3)

    def render_native(self, alphas) -> torch.Tensor:
        """Native-resolution frames (B, Hn, Wn, 3) float32, before reduction and border."""
        a = _alphas(alphas, self.device)
        return torch.cat([self._shade(self.first_ranks(a[s:s + self.chunk_size]))
                          for s in range(0, len(a), self.chunk_size)]) if len(a) else \
            torch.empty((0, self.intr.height, self.intr.width, 3), dtype=torch.float32, device=self.device)

    def render_batch(self, alphas, ranks=None) -> torch.Tensor:
        """Frames ``(B, H, W, 3)`` float32 as handed to the noise (reduced, border masked); ``ranks(alphas)``:
        the rank of the surfel each native pixel shows, (B Hn Wn,) (default the renderer's own,
        :meth:`first_ranks`; the same from :class:`.segment_covers.SegmentCovers`)."""
        a = _alphas(alphas, self.device)
        ranks = ranks or self.first_ranks
        out = [reduce_frames(self._shade(ranks(a[s:s + self.chunk_size])), self.imaging)
               for s in range(0, len(a), self.chunk_size)]
        if not out:
            h, w = self.imaging.out_shape
            return torch.empty((0, h, w, 3), dtype=torch.float32, device=self.device)
        return torch.cat(out)

    def iter_frames(self, alphas, chunk: int | None = None) -> Iterator[tuple[int, torch.Tensor]]:
        alphas = np.asarray(alphas, dtype=np.float64).reshape(-1)
        step = int(chunk or max(1, min(64, self.chunk_size)))
        for s in range(0, len(alphas), step):
            yield s, self.render_batch(alphas[s:s + step])


def occlusion_key(points: np.ndarray) -> np.ndarray:
    """What orders overlapping surfels (the smaller wins; equal: the lower index): the squared distance
    ``X^2 + Y^2 + Z^2`` of the point from the recorded camera centre, float64, fixed for the whole motion."""
    p = np.asarray(points, dtype=np.float64)
    return p[:, 0] * p[:, 0] + p[:, 1] * p[:, 1] + p[:, 2] * p[:, 2]


def bin_cloud(points: np.ndarray, colors: np.ndarray, imaging: Imaging,
              filled_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The cloud the surfels are made of when frames are rendered below the camera's resolution
    (``imaging.decimate`` = s > 1): the points in front of the camera are binned by the rendered pixel
    their ``alpha = 0`` projection falls in (``floor`` of the pixel-edge coordinates, bins beyond the image
    included, since motion can bring them in); each bin becomes one point on the ray through its pixel
    centre at the depth of its nearest point (equal depths: the lower index), with the mean colour of the
    bin (float64, then float32). A camera's own ``s x s`` pixel block thus becomes one surfel, and the
    ``alpha = 0`` frame is the block mean of the valid pixels' colours. Order: bins row by row.
    ``s = 1`` returns the cloud unchanged.

    First of all, with a working volume (``imaging.volume``, :mod:`.volume`) only the measured points inside
    it (chosen at ``alpha = 0`` on the recorded coordinates; ``filled_mask``: the points with a filled depth,
    never inside) are kept, in their order: every surfel the renderer and the bounds draw comes from here."""
    s = int(imaging.decimate)
    if s == 1 and imaging.volume is None:
        return points, colors
    cam = imaging.camera
    # the plan and the renderer of every axis of a frame bin the same cloud: the latest result is kept
    # (one entry, for the same array objects with the same contents (CRC-32 of their bytes: an edit in
    # place is a new cloud), the same camera and volume; the result is shared, never modified)
    points, colors = np.ascontiguousarray(points), np.ascontiguousarray(colors)
    filled = None if imaging.volume is None or filled_mask is None else np.ascontiguousarray(filled_mask, dtype=bool)
    key = (cam, s, imaging.volume, points.shape, points.dtype.str, colors.dtype.str, zlib.crc32(memoryview(points).cast("B")),
           zlib.crc32(memoryview(colors).cast("B")), None if filled is None else zlib.crc32(memoryview(filled).cast("B")))
    with _BINS_LOCK:   # (a frame's axes at the same time, axis_threads: the second waits for the first's bins)
        for p_, c_, k_, out_ in _LAST_BINS:
            if p_ is points and c_ is colors and k_ == key:
                return out_
        inside = imaging.select(points, filled)
        sel_p, sel_c = (points, colors) if inside.all() else (points[inside], colors[inside])
        out_ = _bin(sel_p, sel_c, cam) if s > 1 else (sel_p, sel_c)
        _LAST_BINS[:] = [(points, colors, key, out_)]
        return out_


_LAST_BINS: list = []
_BINS_LOCK = threading.Lock()


def _bin(points: np.ndarray, colors: np.ndarray, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    front = points[:, 2] > 0
    pts, cols = points[front], colors[front]
    if not len(pts):
        return pts, cols
    u, v, _ = project(pts, cam, "tx", 0.0)
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    order = np.lexsort((pts[:, 2], col, row))            # by row, column, then nearest first (stable)
    r_s, c_s = row[order], col[order]
    start = np.flatnonzero(np.r_[True, (r_s[1:] != r_s[:-1]) | (c_s[1:] != c_s[:-1])])
    count = np.diff(np.r_[start, len(order)])
    z = pts[order[start], 2]
    rr, cc = r_s[start].astype(np.float64), c_s[start].astype(np.float64)
    out = np.stack([(cc - cam.cx) * z / cam.fx, (rr - cam.cy) * z / cam.fy, z], axis=1)  # u = cc + 1/2 at alpha 0
    mean = np.add.reduceat(cols[order].astype(np.float64), start, axis=0) / count[:, None]
    return out, mean.astype(np.float32)


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


def _alphas(alphas, device) -> torch.Tensor:
    a = torch.as_tensor(np.asarray(alphas, dtype=np.float64), device=device).reshape(-1)
    require(bool(torch.all(torch.isfinite(a))), "motion values must be finite")
    return a


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

    def __init__(self, r: SurfelRenderer, lo: float, hi: float):
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


__all__ = ["FootprintSweep", "SamplePoints", "SurfelRenderer", "bin_cloud", "covered_pairs", "footprint_corners",
           "occlusion_key", "pixel_range", "project_corners", "surfel_corners"]

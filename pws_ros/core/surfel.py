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
classifier's input by :func:`.framing.reduce_frames`. Where a footprint is and which pixels it covers, at a
pose or over a range of motion (:class:`.footprint.FootprintSweep`, shared with the bounds), is
:mod:`.footprint`.
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
from .footprint import FootprintSweep, SamplePoints, covered_pairs, footprint_corners, project_corners, surfel_corners
from .framing import Imaging, reduce_frames
from .motion import depth, parse_axis, project
from .render import DEFAULT_MAX_ELEMENTS, resolve_device
from .surfel_cover import UnionPolicy, first_covers, range_implied

# poses rendered from one union of footprints (surfel_cover.first_covers): neighbouring poses share most
# winners, poses far apart few
UNION_POSES = 5


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


def _alphas(alphas, device) -> torch.Tensor:
    a = torch.as_tensor(np.asarray(alphas, dtype=np.float64), device=device).reshape(-1)
    require(bool(torch.all(torch.isfinite(a))), "motion values must be finite")
    return a


__all__ = ["SurfelRenderer", "bin_cloud", "occlusion_key"]

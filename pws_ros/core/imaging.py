"""The imaging model: the image a camera moved by ``alpha`` delivers to the classifier, and its bounds.

One home for what a certificate is about. Two models:

* ``surfel`` (the default). Every point of the one-frame cloud stands for the surface patch its depth
  pixel saw: a fronto-parallel square *surfel* centred on the point, of half side
  ``(1/2 + SURFEL_OVERLAP) Z / fx`` by ``(1/2 + SURFEL_OVERLAP) Z / fy`` (``Z`` its depth in the recorded
  frame, ``fx, fy`` the native camera). At motion ``alpha`` its *footprint* is the axis-aligned bounding
  box ``[umin, umax) x [vmin, vmax)`` of the projections of its four corners (pixel-edge coordinates,
  :func:`.motion.project`); it covers native pixel ``(r, c)`` when the pixel centre ``(c + 1/2, r + 1/2)``
  lies inside. A surfel with a corner at depth ``<= 0`` is not drawn. The pixel shows the covering
  surfel nearest to the *recorded* camera centre (the least :func:`occlusion_key` ``X^2 + Y^2 + Z^2``,
  float64; equal keys: the lower point index), or ``background`` where none covers it (invalid depth,
  disocclusions, what the recording never saw). The order is fixed for the whole motion: for rotations
  it is exactly the occlusion order along every ray (a rotation about the optical centre has no
  parallax); for the translations of a certificate (millimetres) it can differ from the moved camera's
  only between surfaces closer together along a ray than the translation. It also keeps neighbours of
  one surface, whose patches overlap, from trading places as the camera turns (ordering by the moved
  depth made every overlap of a slanted plane flip at one pose, a jump of the whole image).
  At ``alpha = 0`` a cloud back-projected from the camera's own depth image re-renders that image
  exactly (every surfel covers its own pixel centre); neighbours at equal depth overlap by
  ``SURFEL_OVERLAP`` pixels, so moving the camera opens no sampling holes, only true disocclusions.

  The camera image is cropped, centred, to ``s k`` times the classifier's input size and rendered at
  ``k`` times it (``render_factor``; 0 = the camera's resolution, ``s = 1``): with ``s > 1`` the cloud is
  first binned (:func:`bin_cloud`, one surfel per ``s x s`` block of camera pixels, its mean colour), so
  a 640x480 camera and a 160x90 model render at 320x180 (``k = 2``, ``s = 2``, the default) or at
  640x360 (``render_factor: 0``, ``k = 4``). Frames are reduced by an exact ``k x k`` block mean (float64, then float32: what
  ``cv2.resize(..., INTER_AREA)`` does at an integer factor), and a border of ``border`` output pixels
  (columns left and right, rows top and bottom) is set to ``background`` in every frame and in the
  classifier's input. The border is computed from the requested radii (how far any point of the frame
  moves, less the native pixels beyond the crop), so that what enters the image from outside the
  recording is masked; where it is too small, the bounds count the background instead (sound either way).
* ``paper``: the paper's model (one point paints one pixel, holes show ``background``) at the
  classifier's input size, rendered by :mod:`.render` and bounded by the exact sweep of :mod:`.sweep`.

Bounds of the surfel model (:func:`segment_hulls`): for a segment ``[a, b]`` of the plan, every native
pixel gets the per-channel interval ``[lo, hi]`` of every value it can show for some ``alpha`` in the
segment: the colours of every surfel whose footprint can cover its centre there and that no surely
covering surfel always hides, plus the background unless some surfel surely covers it throughout.
Footprint corners are monotone between the split points of :func:`.motion.split_events`, so their
ranges over the segment are read at its ends and at those split points, widened by ``EDGE_EPS`` pixels
for float rounding. The renderer ranks its surfels in occlusion order (key, then index: one constant
order for the whole motion), so a surfel that surely covers a pixel throughout the segment hides every
later surfel, equal keys included, by one comparison of ranks: no depth tolerance is needed.
The block mean is linear with positive weights, so the output pixel of every frame of the segment lies
in the block means of ``lo`` and ``hi`` (widened by ``VALUE_EPS`` for float32 rounding). Distances to
any frame ``y`` are then bounded by ``sum max((lo - y)^2, (hi - y)^2)`` (:class:`HullValues`).

(One module on purpose, over the usual ~400 lines: the renderer and the bounds implement one model
with one set of constants and helpers, and must not drift apart.)
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace
from typing import Any, Iterator

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import PwsError, require
from .motion import AXES, depth, parse_axis, project, split_events
from .partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX, Plan, plan_partitions, plan_step, validate_grid
from .render import DEFAULT_MAX_ELEMENTS, resolve_device

IMAGING_KINDS = ("surfel", "paper")
UNCOVERED = ("frame", "background")   # what a native pixel no surfel covers shows (surfel imaging; see Imaging)
SURFEL_OVERLAP = 0.15   # px each side: see the module doc (neighbours overlap by more than a segment moves)
SAMPLE_JITTER = 0.33    # px: largest offset of a pixel's sample point from its centre (< 1/2 - SURFEL_OVERLAP)
EDGE_EPS = 1e-6         # px: float tolerance of a footprint edge in the bounds
VALUE_EPS = 1e-6        # float32 rounding of a block mean (values in [0, 1])
SAFETY = 1.0 + 1e-9     # relative margin on float64 sums of squares
DEFAULT_RENDER_FACTOR = 2  # surfel frames at 2x the classifier's input (640x480 camera, 160x90 model: 2x2 bins)
_CORNER_SIGNS = ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))


@dataclass(frozen=True)
class Imaging:
    """How frames are made for one input camera: ``kind``, the native ``camera`` frames are rendered
    with (the centred crop for ``surfel``, the rescaled camera for ``paper``), the block-mean
    ``factor``, the masked ``border`` (output pixels: columns left/right, rows top/bottom) and the
    ``background`` value; ``source`` is the input camera and ``crop`` the crop's (x0, y0) in it."""

    kind: str
    camera: CameraIntrinsics
    factor: int = 1
    border: tuple[int, int] = (0, 0)
    background: float = 0.0
    source: CameraIntrinsics | None = field(default=None, compare=False)  # not sent between nodes
    crop: tuple[int, int] = (0, 0)
    decimate: int = 1   # surfel: input pixels per rendered pixel (a side); the cloud is binned to match
    # surfel: what a native pixel that no surfel covers shows: "frame" = its colour in the alpha = 0 frame
    # (``background`` where no surfel covers it there either), fixed for the whole motion; "background"
    uncovered: str = "background"

    @property
    def out_shape(self) -> tuple[int, int]:
        """(H, W) of the frames handed to the classifier."""
        return (self.camera.height // self.factor, self.camera.width // self.factor)

    def describe(self) -> str:
        h, w = self.out_shape
        if self.kind == "paper":
            return f"paper imaging (one point per pixel) at {w}x{h}, holes = {self.background:g}"
        src = self.source or self.camera
        s = self.decimate
        binned = "" if s == 1 else (f", cloud binned {s}x{s} and rendered at {self.camera.width}x{self.camera.height}")
        uncovered = (f"uncovered = the alpha = 0 frame (else {self.background:g})" if self.uncovered == "frame"
                     else f"uncovered = {self.background:g}")
        return (f"surfel imaging: {src.width}x{src.height} camera, centred crop {s * self.camera.width}x{s * self.camera.height} "
                f"at ({self.crop[0]}, {self.crop[1]}){binned}, {self.factor}x{self.factor} block mean to {w}x{h}, border "
                f"{self.border[0]} col / {self.border[1]} row masked (= {self.background:g}), {uncovered}")

    @classmethod
    def from_dict(cls, d: dict[str, Any], camera: CameraIntrinsics) -> "Imaging":
        """The inverse of :meth:`to_dict` given the native ``camera`` (e.g. what crossed a topic)."""
        try:
            im = cls(str(d["kind"]), camera, int(d["factor"]), (int(d["border_cols"]), int(d["border_rows"])),
                     float(d["background"]), None, (int(d["crop_x0"]), int(d["crop_y0"])), int(d.get("decimate", 1)),
                     str(d.get("uncovered", "background")))
        except (KeyError, TypeError, ValueError) as exc:
            raise PwsError(f"malformed imaging description: {exc}") from None
        require(im.kind in IMAGING_KINDS and im.factor >= 1 and im.decimate >= 1 and im.uncovered in UNCOVERED,
                f"malformed imaging description: {d}")
        require(camera.width % im.factor == 0 and camera.height % im.factor == 0,
                f"imaging factor {im.factor} does not divide the camera {camera.width}x{camera.height}")
        return im

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "factor": self.factor, "border_cols": self.border[0], "border_rows": self.border[1],
                "crop_x0": self.crop[0], "crop_y0": self.crop[1], "native_width": self.camera.width,
                "native_height": self.camera.height, "width": self.out_shape[1], "height": self.out_shape[0],
                "background": self.background, "decimate": self.decimate, "uncovered": self.uncovered}


def make_imaging(kind: str, intr: CameraIntrinsics, model_size: tuple[int, int] | None, *, background: float = 0.0,
                 border: int = -1, cloud: Cloud | None = None, radii: dict[str, float] | None = None,
                 render_factor: int = 0, uncovered: str = "background") -> Imaging:
    """The imaging of camera ``intr`` for a classifier of input ``model_size`` = (H, W) (None: any size).

    ``border`` < 0 computes it from ``cloud`` and the motion ``radii`` ({axis: b}) of the frame
    (:func:`auto_border`); 0 masks nothing. ``render_factor`` (surfel): frames are rendered at that many
    times the classifier's input (0: the camera's own resolution, the largest factor that fits); a
    smaller factor bins the camera's pixels ``decimate x decimate`` (see :func:`bin_cloud`). ``uncovered``
    (surfel): what a native pixel no surfel covers shows (:data:`UNCOVERED`, see :class:`Imaging`)."""
    require(kind in IMAGING_KINDS, f"unknown imaging model {kind!r}: expected one of {', '.join(IMAGING_KINDS)}")
    require(uncovered in UNCOVERED, f"unknown uncovered rule {uncovered!r}: expected one of {', '.join(UNCOVERED)}")
    require(math.isfinite(background), f"background must be finite, got {background}")
    h, w = (intr.height, intr.width) if model_size is None else (int(model_size[0]), int(model_size[1]))
    if kind == "paper":
        cam = intr if (h, w) == (intr.height, intr.width) else intr.scaled(w, h)
        return Imaging("paper", cam, 1, (0, 0), float(background), intr, (0, 0))
    k_max = min(intr.width // w, intr.height // h)
    require(k_max >= 1, f"camera {intr.width}x{intr.height} is smaller than the classifier's input {w}x{h}: "
                        f"no crop of the camera image reduces to it (use imaging: paper to rescale, or a model for this size)")
    require(int(render_factor) >= 0, f"render_factor must be >= 0 (0: the camera's resolution), got {render_factor}")
    k = min(int(render_factor), k_max) if render_factor else k_max
    s = k_max // k                     # camera pixels per rendered pixel (a side)
    x0, y0 = (intr.width - s * k * w) // 2, (intr.height - s * k * h) // 2
    cam = replace(intr, width=s * k * w, height=s * k * h, cx=intr.cx - x0, cy=intr.cy - y0)
    if s > 1:
        cam = cam.scaled(k * w, k * h)
    im = Imaging("surfel", cam, k, (0, 0), float(background), intr, (x0, y0), s, uncovered)
    if border < 0:
        bx, by = auto_border(im, cloud, radii or {}) if cloud is not None else (0, 0)
    else:
        bx = by = int(border)
    require(2 * bx < w and 2 * by < h, f"border {bx}x{by} px masks the whole {w}x{h} image")
    return replace(im, border=(int(bx), int(by)))


def auto_border(im: Imaging, cloud: Cloud, radii: dict[str, float]) -> tuple[int, int]:
    """Output pixels to mask (columns, rows) so that no point of the crop moves in from beyond the
    recorded image: the largest displacement of a point seen in the crop over every ``[-b, b]``, less
    the native pixels available beyond the crop on the narrower side, in output pixels (rounded up)."""
    src = im.source or im.camera
    pts = cloud.points[cloud.points[:, 2] > 0]
    if not len(pts) or not radii:
        return (0, 0)
    u0, v0, _ = project(pts, im.camera, "tx", 0.0)
    seen = (u0 >= 0) & (u0 < im.camera.width) & (v0 >= 0) & (v0 < im.camera.height)
    pts, u0, v0 = pts[seen], u0[seen], v0[seen]
    if not len(pts):
        return (0, 0)
    du = dv = 0.0
    for axis, b in radii.items():
        for a in (-float(b), float(b)):
            u, v, d = project(pts, im.camera, parse_axis(axis), a)
            ok = d > 0
            if ok.any():
                du = max(du, float(np.max(np.abs(u[ok] - u0[ok]))))
                dv = max(dv, float(np.max(np.abs(v[ok] - v0[ok]))))
    d = im.decimate  # the spare camera pixels beyond the crop, in rendered pixels
    spare_x = min(im.crop[0], src.width - im.crop[0] - d * im.camera.width) / d
    spare_y = min(im.crop[1], src.height - im.crop[1] - d * im.camera.height) / d
    k = im.factor
    return (int(math.ceil(max(0.0, du - spare_x) / k)), int(math.ceil(max(0.0, dv - spare_y) / k)))


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
        self.intr = imaging.camera
        self.background = float(imaging.background)
        self.device = resolve_device(device)
        self.max_elements = int(max_elements)
        self.samples = SamplePoints(self.intr.height, self.intr.width, self.device)
        self._set_points(*bin_cloud(np.asarray(cloud.points, dtype=np.float64), np.asarray(cloud.colors, np.float32), imaging))
        # what each native pixel shows where no surfel covers it (imaging.uncovered), from the whole cloud,
        # fixed for the whole motion: the renderer and the bounds read this one table
        HW = self.intr.height * self.intr.width
        if imaging.uncovered == "frame":
            self.uncovered = self.colors[self._winners(_alphas([0.0], self.device))].reshape(HW, 3).clone()
        else:
            self.uncovered = self.colors[self.num_points].expand(HW, 3).clone()
        if alpha_range is not None:
            # drop the surfels no pose of the range can show (in order: the tie rule is unchanged)
            keep = _HullSweep(self, *alpha_range).maybe_visible(*alpha_range)
            if not keep.all():
                self._set_points(self.points_np[keep], self.colors_np[keep])

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
        self.corners_np = surfel_corners(pts, self.intr)                     # (4, P, 3)
        self.points = torch.as_tensor(pts, device=self.device)
        self.corners = torch.as_tensor(self.corners_np, device=self.device)
        bg = np.full((1, 3), self.background, dtype=np.float32)
        self.colors = torch.as_tensor(np.concatenate([colors, bg]), device=self.device)

    @property
    def chunk_size(self) -> int:
        return max(1, self.max_elements // max(1, 4 * self.num_points))

    def footprints(self, alphas: torch.Tensor):
        """Footprint boxes ``umin, umax, vmin, vmax``, centre depth and drawn mask, each (B, P)."""
        u, v, d = project(self.corners[None], self.intr, self.axis, alphas[:, None, None], xp=torch)  # (B, 4, P)
        zc = depth(self.points[None], self.axis, alphas[:, None], xp=torch)                          # (B, P)
        drawn = (d > 0).all(dim=1) & (zc > 0)
        return u.amin(1), u.amax(1), v.amin(1), v.amax(1), zc, drawn

    def _winners(self, alphas: torch.Tensor) -> torch.Tensor:
        """Index of the surfel each native pixel shows (``num_points`` = background), (B, Hn, Wn)."""
        H, W = self.intr.height, self.intr.width
        B, n = alphas.shape[0], self.num_points
        idx = torch.full((B * H * W,), n, dtype=torch.long, device=self.device)
        if n == 0:
            return idx.view(B, H, W)
        umin, umax, vmin, vmax, zc, drawn = self.footprints(alphas)
        p_i, where, _ = covered_pairs(umin, umax, vmin, vmax, drawn, self.samples, 0.0)
        # the covering surfel first in occlusion order (the least rank, see _set_points)
        idx.scatter_reduce_(0, where, self.rank[p_i], reduce="amin", include_self=True)
        return self.by_rank[idx].view(B, H, W)

    def _shade(self, winners: torch.Tensor) -> torch.Tensor:
        """The colours (B, Hn, Wn, 3) of winner indices (``num_points``: the pixel's uncovered value)."""
        H, W = self.intr.height, self.intr.width
        return torch.where((winners == self.num_points)[..., None], self.uncovered.view(H, W, 3), self.colors[winners])

    def render_native(self, alphas) -> torch.Tensor:
        """Native-resolution frames (B, Hn, Wn, 3) float32, before reduction and border."""
        a = _alphas(alphas, self.device)
        return torch.cat([self._shade(self._winners(a[s:s + self.chunk_size]))
                          for s in range(0, len(a), self.chunk_size)]) if len(a) else \
            torch.empty((0, self.intr.height, self.intr.width, 3), dtype=torch.float32, device=self.device)

    def render_batch(self, alphas) -> torch.Tensor:
        """Frames ``(B, H, W, 3)`` float32 as handed to the noise (reduced, border masked)."""
        a = _alphas(alphas, self.device)
        out = [reduce_frames(self._shade(self._winners(a[s:s + self.chunk_size])), self.imaging)
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


def bin_cloud(points: np.ndarray, colors: np.ndarray, imaging: Imaging) -> tuple[np.ndarray, np.ndarray]:
    """The cloud the surfels are made of when frames are rendered below the camera's resolution
    (``imaging.decimate`` = s > 1): the points in front of the camera are binned by the rendered pixel
    their ``alpha = 0`` projection falls in (``floor`` of the pixel-edge coordinates, bins beyond the image
    included, since motion can bring them in); each bin becomes one point on the ray through its pixel
    centre at the depth of its nearest point (equal depths: the lower index), with the mean colour of the
    bin (float64, then float32). A camera's own ``s x s`` pixel block thus becomes one surfel, and the
    ``alpha = 0`` frame is the block mean of the valid pixels' colours. Order: bins row by row.
    ``s = 1`` returns the cloud unchanged."""
    s = int(imaging.decimate)
    if s == 1:
        return points, colors
    cam = imaging.camera
    # the plan and the renderer of every axis of a frame bin the same cloud: the latest result is kept
    # (one entry, for the same array objects with the same contents (CRC-32 of their bytes: an edit in
    # place is a new cloud) and the same camera; the result is shared, never modified)
    points, colors = np.ascontiguousarray(points), np.ascontiguousarray(colors)
    key = (cam, s, points.shape, points.dtype.str, colors.dtype.str, zlib.crc32(memoryview(points).cast("B")),
           zlib.crc32(memoryview(colors).cast("B")))
    for p_, c_, k_, out_ in _LAST_BINS:
        if p_ is points and c_ is colors and k_ == key:
            return out_
    out_ = _bin(points, colors, cam)
    _LAST_BINS[:] = [(points, colors, key, out_)]
    return out_


_LAST_BINS: list = []


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


def surfel_corners(points: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """The four corners ``(4, P, 3)`` of every surfel (see module doc); a point at depth <= 0 has a
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
    c0 = torch.ceil(umin - (eps + 0.5 + SAMPLE_JITTER)).clamp_(0, W).long().view(-1)
    c1 = torch.ceil(umax + (eps - 0.5 + SAMPLE_JITTER)).clamp_(0, W).long().view(-1)
    r0 = torch.ceil(vmin - (eps + 0.5 + SAMPLE_JITTER)).clamp_(0, H).long().view(-1)
    r1 = torch.ceil(vmax + (eps - 0.5 + SAMPLE_JITTER)).clamp_(0, H).long().view(-1)
    nc, nr = c1.sub_(c0).clamp_(min=0), r1.sub_(r0).clamp_(min=0)   # (a NaN edge: no pixel, not an overflow)
    live = mask.reshape(-1) & (nc > 0) & (nr > 0)
    base = r0.mul_(W).add_(c0)
    lo_u, hi_u = (umin - eps).view(-1), (umax + eps).view(-1)
    lo_v, hi_v = (vmin - eps).view(-1), (vmax + eps).view(-1)
    if inner is not None:
        iu0, iu1, iv0, iv1, imask, ieps = inner
        inner = ((iu0 - ieps).view(-1), (iu1 + ieps).view(-1), (iv0 - ieps).view(-1), (iv1 + ieps).view(-1), imask.reshape(-1))

    def inside(su, sv, boxes, at=None):   # samples su, sv in the boxes (at: of these boxes only)
        u0, u1, v0, v1 = (x if at is None else x[at] for x in boxes[:4])
        ok = (u0 <= su) & (su < u1) & (v0 <= sv) & (sv < v1)
        return ok.logical_and_(boxes[4] if at is None else boxes[4][at]) if len(boxes) > 4 else ok

    points, wheres, insides = [], [], []
    # the 2x2 corner of every box, offset by offset over all boxes at once (no per-pair gathers)
    batch_base = base + torch.arange(B, device=dev).mul_(H * W).repeat_interleave(P)   # b * H * W + r0 * W + c0
    wide, tall = nc > 1, nr > 1
    for sel, off in ((live, 0), (live & wide, 1), (live & tall, W), (live & wide & tall, W + 1)):
        pix = (base + off).clamp_(0, H * W - 1)
        su, sv = samples.su[pix], samples.sv[pix]
        f = torch.nonzero(inside(su, sv, (lo_u, hi_u, lo_v, hi_v, sel)), as_tuple=True)[0]
        points.append(f % P)
        wheres.append(batch_base[f] + off)
        if inner is not None:
            insides.append(inside(su, sv, inner)[f])
    more = torch.nonzero(live & ((nc > 2) | (nr > 2)), as_tuple=True)[0]
    if len(more):  # boxes over 2 pixels a side (a point near the camera plane, long sweeps): the rest of each
        cnt = nc[more] * nr[more]
        rep = torch.repeat_interleave(torch.arange(len(more), device=dev), cnt)
        t = torch.arange(int(cnt.sum()), device=dev) - (torch.cumsum(cnt, 0) - cnt)[rep]
        f, ncr = more[rep], nc[more][rep]
        dr, dc = torch.div(t, ncr, rounding_mode="floor"), t % ncr
        rest = (dr > 1) | (dc > 1)
        f, off = f[rest], dr[rest] * W + dc[rest]
        pix = base[f] + off
        su, sv = samples.su[pix], samples.sv[pix]
        ok = inside(su, sv, (lo_u, hi_u, lo_v, hi_v), f)
        f, off, su, sv = f[ok], off[ok], su[ok], sv[ok]
        points.append(f % P)
        wheres.append(batch_base[f] + off)
        if inner is not None:
            insides.append(inside(su, sv, inner, f))
    return torch.cat(points), torch.cat(wheres), (torch.cat(insides) if inner is not None else None)


def reduce_frames(native: torch.Tensor, imaging: Imaging) -> torch.Tensor:
    """Exact ``k x k`` block mean (float64, then float32) of native frames (B, Hn, Wn, 3) and the border."""
    return _block_mean64(native.to(torch.float64), imaging).to(torch.float32)


def make_renderer(cloud: Cloud, imaging: Imaging, axis: str, *, device: str | torch.device | None = "cpu",
                  alpha_range: tuple[float, float] | None = None):
    """The renderer of ``imaging``: :class:`SurfelRenderer` (``alpha_range``: leave out the surfels no
    motion in it can show) or the paper model's :class:`.render.Renderer`."""
    if imaging.kind == "surfel":
        return SurfelRenderer(cloud, imaging, axis, device=device, alpha_range=alpha_range)
    from .render import Renderer

    return Renderer(cloud, imaging.camera, axis, background=imaging.background, device=device)


def plan_for(cloud: Cloud, imaging: Imaging, axis: str, radius: float, method: str = "pws_of", *,
             step_px: float = DEFAULT_STEP_PX, delta: float | None = None, max_partitions: int = DEFAULT_FRAME_BUDGET,
             min_partitions: int = 0) -> Plan:
    """The plan of ``imaging``: the step rule of :func:`.partition.plan_step` for surfel imaging (on the
    surfels that are drawn: the cloud binned by :func:`bin_cloud`, in the rendered camera), the
    paper's methods (:func:`.partition.plan_partitions`, ``delta`` for PwS-OF) for paper imaging."""
    if imaging.kind == "surfel":  # the speeds of the surfels that are rendered (the binned cloud)
        pts, cols = bin_cloud(np.asarray(cloud.points, dtype=np.float64), np.asarray(cloud.colors, np.float32), imaging)
        return plan_step(Cloud(pts, cols) if len(pts) and pts is not cloud.points else cloud, imaging.camera, axis, radius, method,
                         step_px=step_px, max_partitions=max_partitions, min_partitions=min_partitions)
    return plan_partitions(cloud, imaging.camera, axis, radius, method, delta=delta,
                           max_partitions=max_partitions, min_partitions=min_partitions)


def segment_bounds(renderer, cloud: Cloud, imaging: Imaging, alphas, *, max_bytes: int = 1 << 30):
    """The per-segment bounds of ``imaging`` on the grid ``alphas`` (both have ``pair_bound_sq`` and
    ``anchor_dist_sq``): :func:`segment_hulls` of the surfel ``renderer``, or the exact sweep's
    :class:`.bounds.SegmentValues` for paper imaging."""
    if imaging.kind == "surfel":
        return segment_hulls(renderer, alphas, max_bytes=max_bytes)
    from .bounds import segment_values

    return segment_values(cloud, imaging.camera, renderer.axis, alphas, imaging.background)


# ---------------------------------------------------------------------------------------------------
# Bounds


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
    """The per-segment value intervals of the surfel model for the grid ``alphas`` (see module doc)."""
    alphas = np.asarray(alphas, dtype=np.float64)
    require(len(alphas) >= 2, "a plan needs at least two motion values")
    return hulls_within(renderer, float(alphas[0]), float(alphas[-1]), max_bytes=max_bytes)(alphas)


def hulls_within(renderer: SurfelRenderer, lo: float, hi: float, *, max_bytes: int = 1 << 30):
    """``hulls(g)``: the :class:`HullValues` of the segments of an increasing grid ``g`` inside ``[lo, hi]``,
    bounded in batches of segments by one sweep set up once over ``[lo, hi]``; for grids chosen one after
    another (:func:`.coverage.frontier_reach`) as for one whole plan (:func:`segment_hulls`). A grid
    whose bounds need more than ``max_bytes`` is refused."""
    sweep = _HullSweep(renderer, float(lo), float(hi))
    h, w = renderer.imaging.out_shape

    def hulls(g) -> HullValues:
        g = np.asarray(g, dtype=np.float64)
        require(len(g) >= 2 and lo <= g[0] and g[-1] <= hi and bool(np.all(np.diff(g) > 0)),
                f"grid {g!r} is not increasing inside [{lo!r}, {hi!r}]")
        S = len(g) - 1
        need = 2 * S * h * w * 3 * 4
        require(need <= max_bytes, f"bounds of {S} segments at {w}x{h} need {need / 2**20:.0f} MiB, more than "
                                   f"{max_bytes / 2**20:.0f} MiB: use fewer partitions")
        l_ = np.empty((S, h, w, 3), np.float32)
        h_ = np.empty((S, h, w, 3), np.float32)
        constant = np.empty((S, h, w), bool)
        for s in range(0, S, sweep.batch):
            e = min(S, s + sweep.batch)
            l_[s:e], h_[s:e], constant[s:e] = sweep.segments(g[s:e + 1])
        return HullValues(g, l_, h_, constant, {"surfels": renderer.num_points, "segments": S})

    return hulls


HULL_BATCH_ELEMENTS = 300_000   # surfel-segments bounded per batch of segments (about 0.5 KB each at the peak: ~160 MB)


class _HullSweep:
    """Evaluates the surfel footprints over batches of consecutive segments: every tensor operation serves
    a whole batch, so its cost (and the wake-up of torch's threads) is shared by the segments."""

    def __init__(self, r: SurfelRenderer, lo: float, hi: float):
        self.r = r
        self.P = r.num_points
        corners = r.corners_np.reshape(-1, 3)
        self.corner_ev = split_events(corners, r.axis, lo, hi)      # corner u, v, depth extrema
        self.centre_ev = split_events(r.points_np, r.axis, lo, hi)  # centre depth extrema

    @property
    def batch(self) -> int:
        """Segments per batch."""
        return max(1, HULL_BATCH_ELEMENTS // max(1, self.P))

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

    def ranges(self, g):
        """Per segment ``[g[k], g[k+1]]`` and surfel: the range of every corner's ``u`` and ``v`` (B, 4, P), the
        least corner depth (B, 4, P), the centre depth range (B, P) each."""
        r, P = self.r, self.P
        g = np.asarray(g, dtype=np.float64)
        B = len(g) - 1
        t = torch.as_tensor(g, dtype=torch.float64, device=r.device)
        u, v, d = project(r.corners[None], r.intr, r.axis, t[:, None, None], xp=torch)   # (B+1, 4, P)
        zc = depth(r.points[None], r.axis, t[:, None], xp=torch)                          # (B+1, P)
        u_lo, u_hi = torch.minimum(u[:-1], u[1:]).reshape(-1), torch.maximum(u[:-1], u[1:]).reshape(-1)   # (B 4 P)
        v_lo, v_hi = torch.minimum(v[:-1], v[1:]).reshape(-1), torch.maximum(v[:-1], v[1:]).reshape(-1)
        d_lo = torch.minimum(d[:-1], d[1:]).reshape(-1)
        z_lo, z_hi = torch.minimum(zc[:-1], zc[1:]).reshape(-1), torch.maximum(zc[:-1], zc[1:]).reshape(-1)
        flat, te, seg = self._inside(self.corner_ev, g, r.device)
        if len(flat):
            uu, vv, dd = project(r.corners.reshape(-1, 3)[flat], r.intr, r.axis, te, xp=torch)
            at = seg * (4 * P) + flat
            u_lo = u_lo.scatter_reduce(0, at, uu, "amin")
            u_hi = u_hi.scatter_reduce(0, at, uu, "amax")
            v_lo = v_lo.scatter_reduce(0, at, vv, "amin")
            v_hi = v_hi.scatter_reduce(0, at, vv, "amax")
            d_lo = d_lo.scatter_reduce(0, at, dd, "amin")
        p, te, seg = self._inside(self.centre_ev, g, r.device)
        if len(p):
            zz = depth(r.points[p], r.axis, te, xp=torch)
            at = seg * P + p
            z_lo = z_lo.scatter_reduce(0, at, zz, "amin")
            z_hi = z_hi.scatter_reduce(0, at, zz, "amax")
        shape = (B, 4, P)
        return (u_lo.view(shape), u_hi.view(shape), v_lo.view(shape), v_hi.view(shape), d_lo.view(shape),
                z_lo.view(B, P), z_hi.view(B, P))

    def segments(self, g) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``lo, hi`` (B, h, w, 3) float32 and ``constant`` (B, h, w) of the segments of the grid ``g``."""
        return self._bound(*self.ranges(g))

    def maybe_visible(self, a: float, b: float) -> np.ndarray:
        """Surfels that can cover a native pixel for some alpha in ``[a, b]`` (a superset)."""
        u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi = (x[0] for x in self.ranges([a, b]))
        H, W = self.r.intr.height, self.r.intr.width
        wild = (z_hi > 0) & ~((d_lo > 0).all(0) & (z_lo > 0))
        inside = (u_hi.amax(0) >= -1) & (u_lo.amin(0) <= W + 1) & (v_hi.amax(0) >= -1) & (v_lo.amin(0) <= H + 1)
        return ((z_hi > 0) & (inside | wild)).cpu().numpy()

    def _bound(self, u_lo, u_hi, v_lo, v_hi, d_lo, z_lo, z_hi):
        r = self.r
        H, W = r.intr.height, r.intr.width
        HW = H * W
        B, _, P = u_lo.shape
        dev = r.device
        # a surfel is drawn at alpha iff every corner and its centre are in front of the camera
        sure_drawn = (d_lo > 0).all(1) & (z_lo > 0)                                           # (B, P)
        maybe = z_hi > 0
        # where a corner may cross depth 0 its projection is unbounded: the whole image
        wild = maybe & ~sure_drawn
        big = float(max(H, W)) + 10.0
        sw_u0 = u_lo.amin(1).masked_fill_(wild, -big)
        sw_u1 = u_hi.amax(1).masked_fill_(wild, big)
        sw_v0 = v_lo.amin(1).masked_fill_(wild, -big)
        sw_v1 = v_hi.amax(1).masked_fill_(wild, big)
        # surely covered: left edge at its rightmost, right edge at its leftmost (module doc)
        su0, su1 = u_hi.amin(1), u_lo.amax(1)
        sv0, sv1 = v_hi.amin(1), v_lo.amax(1)
        # candidates: possibly covering at some alpha of the segment (q: segment and native pixel), and
        # among them the surely covering pairs (the sure box lies inside the sweep box, sure_drawn implies maybe)
        cp, q, is_sure = covered_pairs(sw_u0, sw_u1, sw_v0, sw_v1, maybe, r.samples, EDGE_EPS,
                                       inner=(su0, su1, sv0, sv1, sure_drawn, -EDGE_EPS))
        # the first surely covering surfel in occlusion order (its rank; P: none), per segment and native
        # pixel: it hides every later surfel throughout the segment (the order is constant in alpha, equal
        # keys included: the renderer's own ranks)
        sure_first = torch.full((B * HW,), P, dtype=torch.long, device=dev)
        sure_first.scatter_reduce_(0, q[is_sure], r.rank[cp[is_sure]], reduce="amin", include_self=True)
        rc = r.rank[cp]
        keep = rc <= sure_first[q]
        cp, q = cp[keep], q[keep]
        # the values of the native pixels: the renderer's own float32 colours (and its uncovered value of
        # each pixel where no surfel surely covers it), their least and greatest per channel exactly
        col = r.colors
        open_ = (sure_first == P)[:, None]
        uncovered = r.uncovered.repeat(B, 1)                                               # (B HW, 3)
        lo = torch.where(open_, uncovered, torch.tensor(float("inf"), dtype=col.dtype, device=dev))
        hi = torch.where(open_, uncovered, torch.tensor(float("-inf"), dtype=col.dtype, device=dev))
        if len(cp):
            idx = q[:, None].expand(-1, 3)
            vals = col[cp]
            lo.scatter_reduce_(0, idx, vals, reduce="amin", include_self=True)
            hi.scatter_reduce_(0, idx, vals, reduce="amax", include_self=True)
        # every pixel has a value (the background where open, its sure surfel otherwise: kept, the channels together)
        require(bool(torch.isfinite(lo[:, 0]).all()), "internal: a pixel without any value")
        im = r.imaging
        lo_o = _block_mean64(lo.view(B, H, W, 3).to(torch.float64), im) - VALUE_EPS
        hi_o = _block_mean64(hi.view(B, H, W, 3).to(torch.float64), im) + VALUE_EPS
        # output pixels whose every native pixel has one value throughout: bitwise constant over the segment
        k = im.factor
        h, w = im.out_shape
        one = (lo == hi).all(dim=1).view(B, h, k, w, k).all(dim=4).all(dim=2)
        bx, by = im.border
        if bx:
            one[:, :, :bx] = one[:, :, w - bx:] = True
        if by:
            one[:, :by] = one[:, h - by:] = True
        return (lo_o.cpu().numpy().astype(np.float32), hi_o.cpu().numpy().astype(np.float32), one.cpu().numpy())


def _block_mean64(x: torch.Tensor, im: Imaging) -> torch.Tensor:
    """Block mean of float64 native images (B, Hn, Wn, 3) to the output size, border set to background."""
    k = im.factor
    h, w = im.out_shape
    if k > 1:  # the k*k strided slices summed in a fixed order (faster than a two-axis mean), then / k^2
        blocks = x.view(x.shape[0], h, k, w, k, 3)
        out = blocks[:, :, 0, :, 0].clone()
        for i in range(k):
            for j in range(k):
                if i or j:
                    out += blocks[:, :, i, :, j]
        out /= float(k * k)
    else:
        out = x.clone()
    bx, by = im.border
    if bx:
        out[:, :, :bx] = im.background
        out[:, :, w - bx:] = im.background
    if by:
        out[:, :by] = im.background
        out[:, h - by:] = im.background
    return out


__all__ = ["AXES", "DEFAULT_RENDER_FACTOR", "EDGE_EPS", "HullValues", "IMAGING_KINDS", "Imaging", "SURFEL_OVERLAP", "UNCOVERED",
           "SurfelRenderer", "auto_border", "bin_cloud", "make_imaging", "make_renderer", "occlusion_key", "plan_for", "reduce_frames",
           "render_plan_surfel", "hulls_within", "segment_bounds", "segment_hulls", "surfel_corners"]

"""The imaging of one camera: which part of its image is rendered, at what resolution, and how a
rendered frame becomes the classifier's input (docs/imaging.md, sections 3, 7 and 8; the whole model:
docs/imaging.md and :mod:`.imaging`).

* :class:`Imaging` records it for one input camera: the model (``surfel`` or ``paper``), the native
  camera the frames are rendered with, the block-mean ``factor``, the binning ``decimate``, the masked
  ``border``, the ``background`` and what an uncovered pixel shows; :func:`make_imaging` makes it for a
  classifier's input size and :func:`auto_border` sizes the border.
* Crop and factor (surfel): the camera image is cropped, centred, to ``s k`` times the classifier's input
  size and rendered at ``k`` times it (``render_factor``; 0 = the camera's resolution, ``s = 1``): with
  ``s > 1`` the cloud is first binned (:func:`.surfel.bin_cloud`, one surfel per ``s x s`` block of camera
  pixels, its mean colour), so a 640x480 camera and a 160x90 model render at 320x180 (``k = 2``,
  ``s = 2``, the default) or at 640x360 (``render_factor: 0``, ``k = 4``).
* Block mean and border (:func:`reduce_frames`): frames are reduced by an exact ``k x k`` block mean
  (float64, then float32: what ``cv2.resize(..., INTER_AREA)`` does at an integer factor), and a border
  of ``border`` output pixels (columns left and right, rows top and bottom) is set to ``background`` in
  every frame and in the classifier's input. The border is computed from the requested radii (how far
  any point of the frame moves, less the native pixels beyond the crop), so that what enters the image
  from outside the recording is masked; where it is too small, the bounds count the background instead
  (sound either way).

Also the one home of the surfel model's constants (the footprint overlap, the sample jitter) and of its
bounds' float tolerances: the renderer (:mod:`.surfel`) and the bounds (:mod:`.surfel_bounds`) read
them here, and :mod:`.imaging` re-exports them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import PwsError, require
from .motion import parse_axis, project
from .volume import WorkingVolume, count_inside

IMAGING_KINDS = ("surfel", "paper")
UNCOVERED = ("frame", "background")   # what a native pixel no surfel covers shows (surfel imaging; see Imaging)
SURFEL_OVERLAP = 0.15   # px each side: see surfel_corners (neighbours overlap by more than a segment moves)
SAMPLE_JITTER = 0.33    # px: largest offset of a pixel's sample point from its centre (< 1/2 - SURFEL_OVERLAP)
EDGE_EPS = 1e-6         # px: float tolerance of a footprint edge in the bounds
VALUE_EPS = 1e-6        # float32 rounding of a block mean (values in [0, 1])
SAFETY = 1.0 + 1e-9     # relative margin on float64 sums of squares
DEFAULT_RENDER_FACTOR = 2  # surfel frames at 2x the classifier's input (640x480 camera, 160x90 model: 2x2 bins)


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
    # surfel: the part of the cloud that is drawn (docs/imaging.md section 4a; None: every point)
    volume: WorkingVolume | None = None

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
        volume = "" if self.volume is None else f"working volume {self.volume.describe()} (outside: {self.background:g}), "
        centred = self.crop == ((src.width - s * self.camera.width) // 2, (src.height - s * self.camera.height) // 2)
        crop = "centred crop" if centred else "camera window"
        return (f"surfel imaging: {src.width}x{src.height} camera, {volume}{crop} {s * self.camera.width}x{s * self.camera.height} "
                f"at ({self.crop[0]}, {self.crop[1]}){binned}, {self.factor}x{self.factor} block mean to {w}x{h}, border "
                f"{self.border[0]} col / {self.border[1]} row masked (= {self.background:g}), {uncovered}")

    @classmethod
    def from_dict(cls, d: dict[str, Any], camera: CameraIntrinsics) -> "Imaging":
        """The inverse of :meth:`to_dict` given the native ``camera`` (e.g. what crossed a topic)."""
        try:
            im = cls(str(d["kind"]), camera, int(d["factor"]), (int(d["border_cols"]), int(d["border_rows"])),
                     float(d["background"]), None, (int(d["crop_x0"]), int(d["crop_y0"])), int(d.get("decimate", 1)),
                     str(d.get("uncovered", "background")), WorkingVolume.from_dict(d.get("working_volume")))
        except (KeyError, TypeError, ValueError) as exc:
            raise PwsError(f"malformed imaging description: {exc}") from None
        require(im.kind in IMAGING_KINDS and im.factor >= 1 and im.decimate >= 1 and im.uncovered in UNCOVERED
                and (im.volume is None or im.kind == "surfel"), f"malformed imaging description: {d}")
        require(camera.width % im.factor == 0 and camera.height % im.factor == 0,
                f"imaging factor {im.factor} does not divide the camera {camera.width}x{camera.height}")
        return im

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "factor": self.factor, "border_cols": self.border[0], "border_rows": self.border[1],
                "crop_x0": self.crop[0], "crop_y0": self.crop[1], "native_width": self.camera.width,
                "native_height": self.camera.height, "width": self.out_shape[1], "height": self.out_shape[0],
                "background": self.background, "decimate": self.decimate, "uncovered": self.uncovered,
                "working_volume": None if self.volume is None else self.volume.to_dict()}

    def select(self, points: np.ndarray, filled_mask: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: the points the imaging draws: all without a working volume; with one, the measured points
        inside it (``filled_mask``: which points have a filled depth; they are never inside)."""
        if self.volume is None:
            return np.ones(len(points), bool)
        inside = self.volume.contains(points)
        return inside if filled_mask is None else inside & ~np.asarray(filled_mask, bool)


def make_imaging(kind: str, intr: CameraIntrinsics, model_size: tuple[int, int] | None, *, background: float = 0.0,
                 border: int = -1, cloud: Cloud | None = None, radii: dict[str, float] | None = None,
                 render_factor: int = 0, uncovered: str = "background", volume: WorkingVolume | None = None) -> Imaging:
    """The imaging of camera ``intr`` for a classifier of input ``model_size`` = (H, W) (None: any size).

    ``border`` < 0 computes it from ``cloud`` and the motion ``radii`` ({axis: b}) of the frame
    (:func:`auto_border`); 0 masks nothing. ``render_factor`` (surfel): frames are rendered at that many
    times the classifier's input (0: the camera's own resolution, the largest factor that fits); a
    smaller factor bins the camera's pixels ``decimate x decimate`` (see :func:`bin_cloud`). ``uncovered``
    (surfel): what a native pixel no surfel covers shows (:data:`UNCOVERED`, see :class:`Imaging`). ``volume``
    (surfel): only the points of the cloud inside it are drawn (:mod:`.volume`); with a ``cloud``, PwsError
    when no measured point lies in it (nothing to certify about)."""
    require(kind in IMAGING_KINDS, f"unknown imaging model {kind!r}: expected one of {', '.join(IMAGING_KINDS)}")
    require(uncovered in UNCOVERED, f"unknown uncovered rule {uncovered!r}: expected one of {', '.join(UNCOVERED)}")
    require(math.isfinite(background), f"background must be finite, got {background}")
    h, w = (intr.height, intr.width) if model_size is None else (int(model_size[0]), int(model_size[1]))
    require(volume is None or kind == "surfel", "a working volume needs surfel imaging (imaging: paper draws every point)")
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
    if volume is not None and volume.window > 0 and cloud is not None:
        volume, s, x0, y0 = _window(volume, cloud, intr, k, s, w, h)
    cam = replace(intr, width=s * k * w, height=s * k * h, cx=intr.cx - x0, cy=intr.cy - y0)
    if s > 1:
        cam = cam.scaled(k * w, k * h)
    im = Imaging("surfel", cam, k, (0, 0), float(background), intr, (x0, y0), s, uncovered, volume)
    if volume is not None and cloud is not None:
        measured, filled = count_inside(volume, cloud.points, cloud.filled_mask)
        require(measured > 0, f"nothing in the working volume ({volume.describe()}): none of the frame's "
                              f"{len(cloud.points) - cloud.filled} measured points lies in it"
                              + (f" ({filled} filled ones do)" if filled else ""))
    if border < 0:
        bx, by = auto_border(im, cloud, radii or {}) if cloud is not None else (0, 0)
    else:
        bx = by = int(border)
    require(2 * bx < w and 2 * by < h, f"border {bx}x{by} px masks the whole {w}x{h} image")
    return replace(im, border=(int(bx), int(by)))


WINDOW_MARGIN = 0.15   # the camera window: the box of the subject's points, widened by this share on each side
SUBJECT_STEP = 0.02    # m: neighbouring pixels whose depths differ by at most this belong to one cluster (the window's subject)


def window_subject(points: np.ndarray, candidates: np.ndarray, intr: CameraIntrinsics,
                   step: float = SUBJECT_STEP) -> np.ndarray:
    """(N,) bool: the camera window's **subject** among the ``candidates`` ((N,) bool: the measured points
    inside the working volume), decided from the depth alone (docs/imaging.md section 4b):

    1. each candidate with ``Z > 0`` falls in the camera pixel ``(floor(v + 1/2), floor(u + 1/2))``,
       ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` (the pixel it was measured in); the pixel's depth is the
       smallest ``Z`` there (candidates outside the image take no part);
    2. 4-neighbouring pixels whose depths differ by at most ``step`` are connected: clusters;
    3. a cluster **spans the view** when its pixels reach both the left and the right column or both the
       top and the bottom row of the image (a wall, a floor, a table top); the subject is the **largest
       cluster that does not** (most pixels; ties: the nearer smallest depth, then the first pixel in
       row-major order): e.g. a hand and arm before a wall;
    4. its points: the candidates in its pixels within ``step`` of the pixel's depth.

    Where every cluster spans the view (or no candidate falls in the image), the subject is every
    candidate (the nearest of the whole volume decides the window, as without clusters)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    p = np.asarray(points, dtype=np.float64)
    cand = np.asarray(candidates, dtype=bool) & (p[:, 2] > 0)
    W, H = intr.width, intr.height
    idx = np.flatnonzero(cand)
    if not len(idx):
        return cand
    q = p[idx]
    col = np.floor(intr.fx * q[:, 0] / q[:, 2] + intr.cx + 0.5)
    row = np.floor(intr.fy * q[:, 1] / q[:, 2] + intr.cy + 0.5)
    seen = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    if not seen.any():
        return cand
    idx, z = idx[seen], q[seen, 2]
    pix = row[seen].astype(np.int64) * W + col[seen].astype(np.int64)
    depth = np.full(H * W, np.inf)
    np.minimum.at(depth, pix, z)
    has = np.isfinite(depth)
    grid = np.arange(H * W).reshape(H, W)
    src, dst = [], []
    for a, b in ((grid[:, :-1], grid[:, 1:]), (grid[:-1, :], grid[1:, :])):
        a, b = a.reshape(-1), b.reshape(-1)
        link = has[a] & has[b]
        a, b = a[link], b[link]
        near = np.abs(depth[a] - depth[b]) <= step
        src.append(a[near])
        dst.append(b[near])
    node = np.full(H * W, -1, np.int64)
    nodes = np.flatnonzero(has)
    node[nodes] = np.arange(len(nodes))
    r, c = node[np.concatenate(src)], node[np.concatenate(dst)]
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(len(nodes), len(nodes)))
    count, label = connected_components(graph, directed=False)
    rows, cols = nodes // W, nodes % W
    size = np.bincount(label, minlength=count)
    spans = np.zeros(count, bool)
    for lo_hit, hi_hit in ((cols == 0, cols == W - 1), (rows == 0, rows == H - 1)):
        lo_any = np.bincount(label, weights=lo_hit, minlength=count) > 0
        hi_any = np.bincount(label, weights=hi_hit, minlength=count) > 0
        spans |= lo_any & hi_any
    if spans.all():
        return cand
    zmin = np.full(count, np.inf)
    np.minimum.at(zmin, label, depth[nodes])
    first = np.full(count, len(nodes))
    np.minimum.at(first, label, np.arange(len(nodes)))
    ok = np.flatnonzero(~spans)
    best = ok[np.lexsort((first[ok], zmin[ok], -size[ok]))[0]]
    mine = np.zeros(H * W, bool)
    mine[nodes[label == best]] = True
    keep = mine[pix] & (np.abs(z - depth[pix]) <= step)
    out = np.zeros(len(p), bool)
    out[idx[keep]] = True
    return out


def _window(volume: WorkingVolume, cloud: Cloud, intr: CameraIntrinsics, k: int, s_max: int, w: int, h: int):
    """The frame's volume (:meth:`WorkingVolume.for_frame` of the :func:`window_subject`) and the camera window
    around the subject (``volume.window`` > 0): the box of its pixels (1st to 99th percentile, widened by
    WINDOW_MARGIN), the smallest crop of the input's aspect, ``s k`` camera pixels per input pixel (s <= the
    whole frame's), that holds it, centred on it and kept inside the camera image. Returns (volume, s, x0, y0)."""
    filled = cloud.filled_mask
    p = np.asarray(cloud.points, dtype=np.float64)
    cand = volume.contains(p)
    if filled is not None:
        cand &= ~np.asarray(filled, dtype=bool)
    subject = window_subject(p, cand, intr)
    vol = volume.for_frame(p, filled, subject)
    inside = vol.contains(p) & subject
    if not inside.any():
        return vol, s_max, (intr.width - s_max * k * w) // 2, (intr.height - s_max * k * h) // 2
    q = p[inside]
    u = intr.fx * q[:, 0] / q[:, 2] + intr.cx
    v = intr.fy * q[:, 1] / q[:, 2] + intr.cy
    (u0, u1), (v0, v1) = np.percentile(u, [1, 99]), np.percentile(v, [1, 99])
    bw, bh = (u1 - u0) * (1 + 2 * WINDOW_MARGIN), (v1 - v0) * (1 + 2 * WINDOW_MARGIN)
    s = int(min(s_max, max(1, math.ceil(max(bw / (k * w), bh / (k * h))))))
    cw, ch = s * k * w, s * k * h
    x0 = int(min(max(0, round((u0 + u1) / 2 - cw / 2)), intr.width - cw))
    y0 = int(min(max(0, round((v0 + v1) / 2 - ch / 2)), intr.height - ch))
    return vol, s, x0, y0


def auto_border(im: Imaging, cloud: Cloud, radii: dict[str, float]) -> tuple[int, int]:
    """Output pixels to mask (columns, rows) so that no point of the crop moves in from beyond the
    recorded image: of the points drawn (the working volume's), the largest displacement of a point seen in the crop over every ``[-b, b]``, less
    the native pixels available beyond the crop on the narrower side, in output pixels (rounded up)."""
    src = im.source or im.camera
    pts = cloud.points[(cloud.points[:, 2] > 0) & im.select(cloud.points, cloud.filled_mask)]   # the points that are drawn
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


def reduce_frames(native: torch.Tensor, imaging: Imaging) -> torch.Tensor:
    """Exact ``k x k`` block mean (float64, then float32) of native frames (B, Hn, Wn, 3) and the border."""
    return block_mean64(native, imaging).to(torch.float32)


def block_mean64(x: torch.Tensor, im: Imaging, offset: float = 0.0, at: torch.Tensor | None = None) -> torch.Tensor:
    """Block mean in float64 of native images (B, Hn, Wn, 3) to the output size, border set to background,
    plus ``offset`` everywhere. ``x`` float32 or float64: every sum is taken in float64 (a float32 value
    converts exactly), so both give the same result bit for bit. ``at``: output pixels outside the border only,
    (B, h, w) bool or their flat indices ``(b h + row) w + column`` ascending (:func:`block_origins`): those alone,
    (N, 3) in the order of ``at.nonzero()``, bit for bit those values (the same sums in the same order)."""
    k = im.factor
    h, w = im.out_shape
    if at is not None:   # each block's k x k native pixels gathered by index
        base, Wn = block_origins(at, im), w * k
        flat = x.reshape(-1, 3)
        out = _block_sums(lambda i, j: flat.index_select(0, base + (i * Wn + j)), k)
        return out.add_(offset) if offset else out
    blocks = x.view(x.shape[0], h, k, w, k, 3)
    out = _block_sums(lambda i, j: blocks[:, :, i, :, j], k)
    bx, by = im.border
    if bx:
        out[:, :, :bx] = im.background
        out[:, :, w - bx:] = im.background
    if by:
        out[:, :by] = im.background
        out[:, h - by:] = im.background
    if offset:
        out += offset
    return out


def block_origins(at: torch.Tensor, im: Imaging) -> torch.Tensor:
    """The native pixel (``(b H + row) W + column``) at the top left of the block of each output pixel of ``at``:
    (B, h, w) bool, or the flat indices ``(b h + row) w + column`` of output pixels; in the order of ``at.nonzero()``."""
    k = im.factor
    h, w = im.out_shape
    o = at.view(-1).nonzero(as_tuple=True)[0] if at.dtype == torch.bool else at
    b, rc = torch.div(o, h * w, rounding_mode="floor"), o % (h * w)
    return (b * (h * k) + torch.div(rc, w, rounding_mode="floor") * k) * (w * k) + (rc % w) * k


def _block_sums(pixel, k: int) -> torch.Tensor:
    """The means over k x k blocks in float64, ``pixel(i, j)`` the values of every block's pixel ``(i, j)``: summed
    in one fixed order, row by row (faster than a two-axis mean, and the same sums bit for bit whichever way the
    pixels are read), then / k^2."""
    out = pixel(0, 0).to(torch.float64, copy=True)
    for i in range(k):
        for j in range(k):
            if i or j:
                out += pixel(i, j)
    if k > 1:
        out /= float(k * k)
    return out


__all__ = ["DEFAULT_RENDER_FACTOR", "EDGE_EPS", "IMAGING_KINDS", "Imaging", "SAFETY", "SAMPLE_JITTER", "SUBJECT_STEP", "SURFEL_OVERLAP",
           "UNCOVERED", "VALUE_EPS", "WINDOW_MARGIN", "auto_border", "block_mean64", "block_origins", "make_imaging", "reduce_frames", "window_subject"]

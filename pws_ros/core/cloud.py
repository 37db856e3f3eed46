"""Coloured point clouds in the camera optical frame, and the one-frame cloud of an RGB-D image."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import CameraIntrinsics
from .errors import PwsError, require


def colors_to_float(colors: np.ndarray, what: str = "colors") -> np.ndarray:
    """uint8 (0..255) or float (0..1) colours as float32 in [0, 1]."""
    colors = np.asarray(colors)
    if colors.dtype == np.uint8:
        return colors.astype(np.float32) / np.float32(255.0)
    require(np.issubdtype(colors.dtype, np.floating) or np.issubdtype(colors.dtype, np.integer), f"{what} must be numeric, got {colors.dtype}")
    out = colors.astype(np.float32)
    require(bool(np.all(np.isfinite(out))), f"{what} contain NaN or inf")
    if out.size and not (out.min() >= 0.0 and out.max() <= 1.0):
        raise PwsError(f"{what} must be uint8 or float in [0, 1], got range [{out.min():.3g}, {out.max():.3g}]")
    return out


@dataclass(eq=False)
class Cloud:
    """``points`` (N, 3) float64 metres in the camera optical frame; ``colors`` (N, 3) float32 in [0, 1];
    ``filled``: how many of the points have a filled, not a measured, depth (:func:`fill_depth`);
    ``filled_mask`` (N,) bool, where known: which ones (``filled`` is then its count)."""

    points: np.ndarray
    colors: np.ndarray
    filled: int = 0   # points whose depth was filled (:func:`fill_depth`), not measured
    filled_mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.asarray(self.points)
        require(pts.ndim == 2 and pts.shape[1] == 3, f"points must have shape (N, 3), got {pts.shape}")
        require(np.issubdtype(pts.dtype, np.number), f"points must be numeric, got {pts.dtype}")
        pts = pts.astype(np.float64)
        require(bool(np.all(np.isfinite(pts))), "points contain NaN or inf")
        cols = np.asarray(self.colors)
        require(cols.ndim == 2 and cols.shape[1] == 3, f"colors must have shape (N, 3), got {cols.shape}")
        require(len(cols) == len(pts), f"points and colors differ in length ({len(pts)} vs {len(cols)})")
        self.points = np.ascontiguousarray(pts)
        self.colors = np.ascontiguousarray(colors_to_float(cols))
        if self.filled_mask is not None:
            mask = np.asarray(self.filled_mask, dtype=bool).reshape(-1)
            require(len(mask) == len(pts), f"filled_mask has {len(mask)} entries for {len(pts)} points")
            self.filled_mask = mask
            self.filled = int(mask.sum())

    def __len__(self) -> int:
        return len(self.points)

    def require_nonempty(self) -> "Cloud":
        require(len(self) > 0, "the point cloud is empty")
        require(bool(np.any(self.points[:, 2] > 0)), "no point of the cloud is in front of the camera (z > 0)")
        return self

    @classmethod
    def load(cls, path: str | Path) -> "Cloud":
        """Read an ``.npz`` with ``points`` (N,3) and ``colors`` (N,3)."""
        path = Path(path)
        require(path.is_file(), f"cloud file not found: {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [k for k in ("points", "colors") if k not in data.files]
                require(not missing, f"cloud file {path} lacks array(s) {', '.join(missing)} (has: {', '.join(data.files) or 'none'})")
                points, colors = data["points"], data["colors"]
        except PwsError:
            raise
        except Exception as exc:  # zipfile/npy errors
            raise PwsError(f"cannot read cloud file {path}: {exc}") from None
        try:
            return cls(points, colors)
        except PwsError as exc:
            raise PwsError(f"cloud file {path}: {exc}") from None

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, points=self.points, colors=self.colors)


DEPTH_FILLS = ("row", "off")
DEFAULT_MIN_VALID_DEPTH = 0.1   # the least share of an image's pixels with valid depth that describes a scene


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """Pixels with a valid depth: finite and > 0 (0, NaN, inf and negatives are a driver's "no return")."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0)


def require_valid_share(valid: np.ndarray, min_valid: float, what: str = "the depth image's pixels have") -> None:
    """PwsError when less than ``min_valid`` (a share in [0, 1]) of ``valid`` is True: too little is measured
    to describe a scene (``min_valid_depth``)."""
    share = float(valid.mean()) if valid.size else 0.0
    require(share >= min_valid, f"only {share:.1%} of {what} a valid depth, below min_valid_depth "
                                f"{min_valid:.1%}: too little is measured to describe a scene")


def _fill_rows(depth: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every invalid pixel of a row with a valid pixel gets the larger (farther) depth of the nearest
    valid pixels to its left and right in the row (the one that exists, near the row's ends)."""
    H, W = depth.shape
    cols = np.arange(W)
    left = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)            # nearest valid at or left, -1: none
    flipped = np.maximum.accumulate(np.where(valid[:, ::-1], cols, -1), axis=1)
    right = np.where(flipped >= 0, W - 1 - flipped, W)[:, ::-1]                  # nearest valid at or right, W: none
    rows = np.arange(H)[:, None]
    d_left = np.where(left >= 0, depth[rows, np.clip(left, 0, W - 1)], -np.inf)
    d_right = np.where(right < W, depth[rows, np.clip(right, 0, W - 1)], -np.inf)
    filled = np.maximum(d_left, d_right)
    ok = np.isfinite(filled)
    return np.where(valid, depth, np.where(ok, filled, np.nan)), valid | ok


def fill_depth(depth: np.ndarray, *, min_valid: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The depth image with its invalid pixels filled: ``(filled depth, was_filled mask)``.

    The rule (``depth_fill: row``), deterministic and part of the imaging model: an invalid pixel takes
    the depth of the **farther** of the nearest valid pixels to its left and to its right in its row
    (only one side exists near a row's end), so that a filled point never occludes a measured surface:
    it continues the surface behind. A row with no valid pixel is filled the same way along its
    column from the row-filled image. PwsError when fewer than ``min_valid`` of the pixels (a share
    in [0, 1]) have a valid depth (no pixel at all is always an error): too little is measured to
    describe a scene.
    """
    depth = np.asarray(depth, dtype=np.float64)
    require(depth.ndim == 2 and depth.size > 0, f"depth must be a non-empty 2-D image, got shape {depth.shape}")
    valid = valid_depth(depth)
    require(bool(valid.any()), "the depth image has no valid pixel (every depth is 0, NaN, inf or negative)")
    require_valid_share(valid, min_valid)
    out, ok = _fill_rows(depth, valid)
    if not ok.all():
        cols_out, cols_ok = _fill_rows(out.T, ok.T)
        out, ok = cols_out.T, cols_ok.T
    return out, ok & ~valid


def cloud_from_rgbd(depth_m: np.ndarray, rgb: np.ndarray, intr: CameraIntrinsics, *, fill: str = "off",
                    min_valid: float = 0.0) -> Cloud:
    """The one-frame cloud: one point per valid depth pixel, at the pixel centre, with its colour.

    ``depth_m`` (H, W) metres (NaN, inf or <= 0 are invalid); ``rgb`` (H, W, 3) uint8 or float in
    [0, 1]; ``intr`` must have the same size. Point order is row-major over the pixels kept.
    ``fill="row"``: invalid pixels are given a depth first (:func:`fill_depth`, refusing an image with
    less than ``min_valid`` valid pixels), so every pixel with a colour becomes a point; the cloud's
    ``filled`` counts them. ``fill="off"`` keeps only the measured pixels.
    """
    require(fill in DEPTH_FILLS, f"unknown depth_fill {fill!r}: expected one of {', '.join(DEPTH_FILLS)}")
    depth = np.asarray(depth_m, dtype=np.float64)
    require(depth.ndim == 2, f"depth must be a 2-D image, got shape {depth.shape}")
    rgb = np.asarray(rgb)
    require(rgb.ndim == 3 and rgb.shape[2] == 3, f"colour image must have shape (H, W, 3), got {rgb.shape}")
    require(depth.shape == rgb.shape[:2], f"depth {depth.shape[1]}x{depth.shape[0]} and colour {rgb.shape[1]}x{rgb.shape[0]} differ in size")
    require(depth.shape == intr.shape, f"image {depth.shape[1]}x{depth.shape[0]} does not match camera {intr.width}x{intr.height}")
    was_filled = None
    if fill == "row":
        depth, was_filled = fill_depth(depth, min_valid=min_valid)
    else:
        require_valid_share(valid_depth(depth), min_valid)
    valid = valid_depth(depth)
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols]
    x = (cols - intr.cx) * z / intr.fx
    y = (rows - intr.cy) * z / intr.fy
    return Cloud(np.stack([x, y, z], axis=1), colors_to_float(rgb, "colour image")[rows, cols],
                 filled_mask=was_filled[rows, cols] if was_filled is not None else None)

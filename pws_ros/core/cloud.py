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


@dataclass
class Cloud:
    """``points`` (N, 3) float64 metres in the camera optical frame; ``colors`` (N, 3) float32 in [0, 1]."""

    points: np.ndarray
    colors: np.ndarray

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


def cloud_from_rgbd(depth_m: np.ndarray, rgb: np.ndarray, intr: CameraIntrinsics) -> Cloud:
    """The one-frame cloud: one point per valid depth pixel, at the pixel centre, with its colour.

    ``depth_m`` (H, W) metres (NaN, inf or <= 0 are invalid); ``rgb`` (H, W, 3) uint8 or float in
    [0, 1]; ``intr`` must have the same size. Point order is row-major over valid pixels.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    require(depth.ndim == 2, f"depth must be a 2-D image, got shape {depth.shape}")
    rgb = np.asarray(rgb)
    require(rgb.ndim == 3 and rgb.shape[2] == 3, f"colour image must have shape (H, W, 3), got {rgb.shape}")
    require(depth.shape == rgb.shape[:2], f"depth {depth.shape[1]}x{depth.shape[0]} and colour {rgb.shape[1]}x{rgb.shape[0]} differ in size")
    require(depth.shape == intr.shape, f"image {depth.shape[1]}x{depth.shape[0]} does not match camera {intr.width}x{intr.height}")
    valid = np.isfinite(depth) & (depth > 0)
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols]
    x = (cols - intr.cx) * z / intr.fx
    y = (rows - intr.cy) * z / intr.fy
    return Cloud(np.stack([x, y, z], axis=1), colors_to_float(rgb, "colour image")[rows, cols])

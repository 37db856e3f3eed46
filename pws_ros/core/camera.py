"""Pinhole camera intrinsics (ROS ``CameraInfo`` / OpenCV convention).

Intrinsics follow ROS: pixel column ``c`` is centred at ``u = c`` (OpenCV convention). The paper
assigns a point to pixel ``floor(rho)``; we therefore work in *pixel-edge* coordinates
``rho = (fx X/Z + cx + 1/2, fy Y/Z + cy + 1/2)`` so that pixel ``(r, c)`` covers
``rho in [c, c+1) x [r, r+1)`` and a point back-projected through the centre of pixel ``(r, c)``
lands exactly in the middle of it. See :func:`pws_ros.core.motion.project`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import PwsError, read_yaml_file, require


@dataclass(frozen=True)
class CameraIntrinsics:
    """Image size and pinhole parameters (no distortion: frames are rectified/rendered)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    frame_id: str = ""

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            require(isinstance(value, (int, float)) and math.isfinite(value), f"camera {name} must be finite, got {value!r}")
        require(int(self.width) > 0 and int(self.height) > 0, f"camera size must be positive, got {self.width}x{self.height}")
        require(self.fx > 0 and self.fy > 0, f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (int(self.height), int(self.width))

    def scaled(self, width: int, height: int) -> "CameraIntrinsics":
        """Intrinsics of the same camera resampled to ``width x height`` pixels.

        Pixel edges scale linearly: ``(c + 1/2) * s - 1/2`` maps centres to centres.
        """
        require(int(width) > 0 and int(height) > 0, f"target size must be positive, got {width}x{height}")
        sx = int(width) / self.width
        sy = int(height) / self.height
        return replace(
            self,
            width=int(width),
            height=int(height),
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    # ---- I/O -----------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "camera info") -> "CameraIntrinsics":
        """From a camera_calibration YAML dict (``image_width``, ``camera_matrix.data``) or a
        flat dict (``width, height, fx, fy, cx, cy``)."""
        require(isinstance(data, dict), f"{source}: expected a mapping")
        require("image_width" not in data or "camera_matrix" in data, f"{source}: missing field 'camera_matrix' (a "
                "camera_calibration YAML has image_width, image_height and camera_matrix.data)")
        try:
            if "camera_matrix" in data:
                k = np.asarray(data["camera_matrix"]["data"], dtype=float).reshape(-1)
                require(k.size == 9, f"{source}: camera_matrix.data must have 9 numbers, got {k.size}")
                width, height = int(data["image_width"]), int(data["image_height"])
                fx, fy, cx, cy = k[0], k[4], k[2], k[5]
            elif "k" in data or "K" in data:
                k = np.asarray(data.get("k", data.get("K")), dtype=float).reshape(-1)
                require(k.size == 9, f"{source}: k must have 9 numbers, got {k.size}")
                width, height = int(data["width"]), int(data["height"])
                fx, fy, cx, cy = k[0], k[4], k[2], k[5]
            else:
                width, height = int(data["width"]), int(data["height"])
                fx, fy, cx, cy = (float(data[n]) for n in ("fx", "fy", "cx", "cy"))
        except KeyError as exc:
            raise PwsError(f"{source}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise PwsError(f"{source}: malformed value ({exc})") from None
        return cls(width, height, float(fx), float(fy), float(cx), float(cy), str(data.get("camera_name", data.get("frame_id", ""))))

    @classmethod
    def from_yaml(cls, path: str | Path) -> "CameraIntrinsics":
        """Read a ROS camera_info YAML file as written by camera_calibration."""
        path = Path(path)
        data = read_yaml_file(path, "camera file")
        return cls.from_dict(data, source=f"camera file {path}")

    @classmethod
    def from_camera_info(cls, msg: Any) -> "CameraIntrinsics":
        """From a ``sensor_msgs/CameraInfo`` (rclpy or rosbags message: same field names)."""
        k = np.asarray(msg.k, dtype=float).reshape(-1)
        require(k.size == 9, f"CameraInfo.k must have 9 numbers, got {k.size}")
        require(k[0] > 0 and k[4] > 0, f"CameraInfo has no intrinsics (fx={k[0]}, fy={k[4]}): is the camera calibrated?")
        frame = getattr(getattr(msg, "header", None), "frame_id", "") or ""
        return cls(int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]), frame)

    def to_dict(self) -> dict[str, Any]:
        """camera_calibration YAML layout."""
        return {
            "image_width": int(self.width),
            "image_height": int(self.height),
            "camera_name": self.frame_id or "camera",
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in self.K.reshape(-1)]},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
            "projection_matrix": {
                "rows": 3,
                "cols": 4,
                "data": [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            },
        }

    def to_yaml(self, path: str | Path) -> None:
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))

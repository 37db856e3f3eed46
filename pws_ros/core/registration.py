"""Depth registration: a depth image resampled into the colour camera (what depth_image_proc's
``register`` node does), and the rigid transforms it needs.

Every valid depth pixel ``(r, c)`` is a small square patch of the surface it measured: the square
``[c - 1/2, c + 1/2] x [r - 1/2, r + 1/2]`` of the depth image (ROS pixel-centre coordinates) at its
depth ``Z``, back-projected with the depth camera's intrinsics (``X = (c - cx) Z / fx``), moved into
the colour camera's optical frame with the depth -> colour :class:`Extrinsic`
(``P_colour = R P_depth + t``) and projected with the colour intrinsics. The patch's *footprint* is
the bounding box of its four projected corners in pixel-edge coordinates (``u = fx X/Z + cx + 1/2``,
the convention of :mod:`pws_ros.core.camera`); it gives its depth (the patch centre's ``Z`` in the
colour frame) to every colour pixel whose centre ``(col + 1/2, row + 1/2)`` lies in
``[umin, umax) x [vmin, vmax)``, and at least to the pixel its centre projects into
(``col = floor(fx X/Z + cx + 1/2)``). Where several patches reach one colour pixel the nearest depth
wins. A colour camera of higher resolution than the depth camera (a RealSense: fx 613 vs 390) so
receives a depth at every colour pixel the depth camera saw, not one pixel per depth pixel (a footprint
is cut to ``ceil(fx_colour / fx_depth) + 2`` pixels a side, so a degenerate one cannot flood the image); colour
pixels that no patch reaches (what the depth camera did not see: parallax, invalid depth) stay holes
(0 for uint16 millimetres, NaN for float metres). Patches with a corner behind the colour camera,
and pixels outside its image, are dropped. Lens distortion is not modelled: both images are taken
as rectified (pinhole), as everywhere else in this package.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from .camera import CameraIntrinsics
from .errors import require


def _rotation(value: object, what: str) -> np.ndarray:
    r = np.asarray(value, dtype=np.float64)
    require(r.shape == (3, 3), f"{what} must be a 3x3 matrix, got shape {r.shape}")
    require(bool(np.all(np.isfinite(r))), f"{what} contains NaN or inf")
    err = float(np.max(np.abs(r @ r.T - np.eye(3))))
    require(err < 1e-5 and np.linalg.det(r) > 0, f"{what} is not a rotation matrix (|R R^T - I| = {err:.2g}, det {np.linalg.det(r):.3g})")
    return r


@dataclass(frozen=True)
class Extrinsic:
    """A rigid transform from a source optical frame to a target one: ``P_target = R P_source + t``
    (``rotation`` 3x3, ``translation`` metres). ``source`` says where it came from (for the log)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "rotation", _rotation(self.rotation, "extrinsic rotation"))
        t = np.asarray(self.translation, dtype=np.float64).reshape(-1)
        require(t.shape == (3,) and bool(np.all(np.isfinite(t))), f"extrinsic translation must be 3 finite numbers, got {self.translation!r}")
        object.__setattr__(self, "translation", t)

    @classmethod
    def from_quaternion(cls, quaternion_xyzw: Iterable[float], translation: Iterable[float], source: str = "") -> "Extrinsic":
        """From a unit quaternion ``(x, y, z, w)`` (``geometry_msgs/Quaternion`` order) and a translation."""
        q = np.asarray(list(quaternion_xyzw), dtype=np.float64)
        require(q.shape == (4,) and bool(np.all(np.isfinite(q))), f"quaternion must be 4 finite numbers (x, y, z, w), got {q.tolist()}")
        norm = float(np.linalg.norm(q))
        require(abs(norm - 1.0) < 1e-3, f"quaternion {q.tolist()} is not a unit quaternion (norm {norm:.6g})")
        x, y, z, w = q / norm
        rot = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        return cls(rot, np.asarray(list(translation), dtype=np.float64), source)

    def inverse(self) -> "Extrinsic":
        """The transform back: ``P_source = R^T (P_target - t)``."""
        return Extrinsic(self.rotation.T, -self.rotation.T @ self.translation, self.source)

    def then(self, other: "Extrinsic") -> "Extrinsic":
        """``other`` applied after ``self``: ``P = R_o (R_s P + t_s) + t_o``."""
        return Extrinsic(other.rotation @ self.rotation, other.rotation @ self.translation + other.translation,
                         " + ".join(s for s in (self.source, other.source) if s))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` points moved into the target frame."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def describe(self) -> str:
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(self.rotation)) - 1.0) / 2.0))))
        t = ", ".join(f"{v:+.4f}" for v in self.translation)
        return f"t = ({t}) m, rotation {angle:.2f} deg" + (f" ({self.source})" if self.source else "")


def chain_transform(edges: Iterable[tuple[str, str, Extrinsic]], source: str, target: str) -> Extrinsic | None:
    """The transform from frame ``source`` to frame ``target`` through a tree of transforms, or None.

    ``edges`` are ``(parent, child, T)`` with ``T`` mapping child coordinates to parent coordinates
    (``P_parent = R P_child + t``, as a ``geometry_msgs/TransformStamped`` from ``header.frame_id``
    to ``child_frame_id`` in TF). The path may go up and down the tree (e.g. depth optical frame ->
    camera_link -> colour optical frame). Later duplicates of an edge replace earlier ones.
    """
    require(bool(source) and bool(target), "frame names must be non-empty to look up a transform")
    graph: dict[str, dict[str, Extrinsic]] = {}
    for parent, child, T in edges:
        graph.setdefault(child, {})[parent] = T              # child -> parent
        graph.setdefault(parent, {})[child] = T.inverse()    # parent -> child
    if source == target:
        return Extrinsic(source="same frame")
    if source not in graph or target not in graph:
        return None
    prev: dict[str, tuple[str, Extrinsic]] = {}
    seen = {source}
    todo = deque([source])
    while todo:
        node = todo.popleft()
        if node == target:
            break
        for nxt, T in graph[node].items():
            if nxt not in seen:
                seen.add(nxt)
                prev[nxt] = (node, T)
                todo.append(nxt)
    if target not in prev:
        return None
    steps = []
    node = target
    while node != source:
        node, T = prev[node][0], prev[node][1]
        steps.append(T)
    out = Extrinsic()
    for T in reversed(steps):
        out = Extrinsic(T.rotation @ out.rotation, T.rotation @ out.translation + T.translation)
    return out


def _to_colour(rows: np.ndarray, cols: np.ndarray, z: np.ndarray, depth_camera: CameraIntrinsics,
               extrinsic: Extrinsic) -> np.ndarray:
    """Depth-image points ``(row, col)`` (pixel-centre coordinates) at depth ``z``, in the colour frame."""
    pts = np.empty((len(z), 3))
    pts[:, 0] = (cols - depth_camera.cx) * z / depth_camera.fx
    pts[:, 1] = (rows - depth_camera.cy) * z / depth_camera.fy
    pts[:, 2] = z
    return extrinsic.apply(pts)


def register_depth(depth: np.ndarray, depth_camera: CameraIntrinsics, color_camera: CameraIntrinsics,
                   extrinsic: Extrinsic) -> np.ndarray:
    """``depth`` (depth camera's image) as seen by the colour camera, in the colour camera's size.

    ``depth``: ``(H, W)`` uint16 millimetres (0 = invalid) or float metres (NaN, inf, <= 0 invalid),
    of ``depth_camera``'s size. ``extrinsic`` maps depth-camera points into the colour camera.
    Returns the same kind: uint16 millimetres with 0 in holes (rounded to the nearest millimetre),
    or float metres (the input's float type) with NaN in holes. Nearest depth wins (see the module doc). (A uint16 pixel
    whose registered depth exceeds 65.535 m becomes 0, the driver's "no return".)
    """
    depth = np.asarray(depth)
    require(depth.ndim == 2, f"depth must be a 2-D image, got shape {depth.shape}")
    require(depth.shape == depth_camera.shape,
            f"depth image {depth.shape[1]}x{depth.shape[0]} does not match its camera {depth_camera.width}x{depth_camera.height}")
    millimetres = depth.dtype == np.uint16
    require(millimetres or np.issubdtype(depth.dtype, np.floating),
            f"depth must be uint16 millimetres or float metres, got {depth.dtype}")
    if millimetres:
        valid = depth > 0
        rows, cols = np.nonzero(valid)
        z = depth[rows, cols].astype(np.float64) / 1000.0
    else:
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth > 0)
        rows, cols = np.nonzero(valid)
        z = depth[rows, cols].astype(np.float64)
    H, W = color_camera.shape
    best = np.full(H * W, np.inf)
    centre = _to_colour(rows, cols, z, depth_camera, extrinsic)
    corners = [_to_colour(rows + dr, cols + dc, z, depth_camera, extrinsic) for dr in (-0.5, 0.5) for dc in (-0.5, 0.5)]
    front = (centre[:, 2] > 0) & np.all([c[:, 2] > 0 for c in corners], axis=0)
    zc = centre[front, 2]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        uv = [(color_camera.fx * c[front, 0] / c[front, 2] + color_camera.cx + 0.5,
               color_camera.fy * c[front, 1] / c[front, 2] + color_camera.cy + 0.5) for c in corners]
        u_c = np.floor(color_camera.fx * centre[front, 0] / zc + color_camera.cx + 0.5)
        v_c = np.floor(color_camera.fy * centre[front, 1] / zc + color_camera.cy + 0.5)
    us, vs = np.stack([q[0] for q in uv]), np.stack([q[1] for q in uv])
    # colour pixels whose centre lies in the footprint box: col in [ceil(umin - 1/2), ceil(umax - 1/2))
    c0, c1 = np.ceil(us.min(0) - 0.5), np.ceil(us.max(0) - 0.5)
    r0, r1 = np.ceil(vs.min(0) - 0.5), np.ceil(vs.max(0) - 0.5)
    # the centre's own pixel always (a footprint narrower than a pixel may hold no pixel centre)
    c0, c1 = np.minimum(c0, u_c), np.maximum(c1, u_c + 1)
    r0, r1 = np.minimum(r0, v_c), np.maximum(r1, v_c + 1)
    ok = np.isfinite(c0) & np.isfinite(c1) & np.isfinite(r0) & np.isfinite(r1) & (c1 > 0) & (c0 < W) & (r1 > 0) & (r0 < H)
    c0, c1, r0, r1, zc = np.clip(c0[ok], 0, W), np.clip(c1[ok], 0, W), np.clip(r0[ok], 0, H), np.clip(r1[ok], 0, H), zc[ok]
    nw, nh = (c1 - c0).astype(np.int64), (r1 - r0).astype(np.int64)
    c0, r0 = c0.astype(np.int64), r0.astype(np.int64)
    # a footprint is about fx_colour / fx_depth pixels wide; a degenerate one (a corner near the
    # colour camera's plane) is cut to that size plus 2, so one stray pixel cannot flood the image
    cap = int(math.ceil(max(color_camera.fx / depth_camera.fx, color_camera.fy / depth_camera.fy))) + 2
    nw, nh = np.minimum(nw, cap), np.minimum(nh, cap)
    wide, high = int(nw.max(initial=0)), int(nh.max(initial=0))
    for dr in range(high):
        for dc in range(wide):
            m = (dc < nw) & (dr < nh)
            np.minimum.at(best, (r0[m] + dr) * W + (c0[m] + dc), zc[m])
    hole = ~np.isfinite(best)
    if millimetres:
        mm = np.floor(best * 1000.0 + 0.5)
        mm[hole | (mm > 65535)] = 0   # beyond the uint16 range: no return, as the driver writes it
        return mm.astype(np.uint16).reshape(H, W)
    best[hole] = np.nan
    return best.astype(depth.dtype).reshape(H, W)


__all__ = ["Extrinsic", "chain_transform", "register_depth"]

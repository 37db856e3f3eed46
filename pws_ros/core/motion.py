"""One-axis camera motion in the camera optical frame (x right, y down, z forward).

A camera moved by ``alpha`` along one axis sees a point ``P`` at ``P' = R^T (P - t)``:
translations ``tx, ty, tz`` (metres) set ``t = alpha * e_axis``; rotations ``rx, ry, rz`` (radians)
set ``R`` to the rotation about that axis::

    rx = [[1,0,0],[0,c,-s],[0,s,c]]   ry = [[c,0,s],[0,1,0],[-s,0,c]]   rz = [[c,-s,0],[s,c,0],[0,0,1]]

The projection in pixel-edge coordinates is ``rho = (fx X'/Z' + cx + 1/2, fy Y'/Z' + cy + 1/2)``,
depth ``D = Z'``; the point lands in pixel ``(row, col) = (floor rho_2, floor rho_1)``.

Pixel footprints overlap by :data:`PIXEL_OVERLAP` (1e-6 px): a point within that distance of a pixel
edge is drawn in both pixels (see :func:`pixel_span`). Without it, two equal-depth points one pixel
apart (every flat patch of a depth image) hand a pixel over at one instant, and float rounding can
leave the pixel empty at exactly that instant; with it the hand-over always overlaps, so the exact
sweep of :mod:`.sweep` and the renderer agree up to float tolerance. Images differ from plain
``floor`` only for motions within ~1e-6 px of a crossing.
"""
from __future__ import annotations

import math

import numpy as np

from .camera import CameraIntrinsics
from .errors import PwsError

AXES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
TRANSLATIONS = ("tx", "ty", "tz")
ROTATIONS = ("rx", "ry", "rz")
UNITS = {"tx": "m", "ty": "m", "tz": "m", "rx": "rad", "ry": "rad", "rz": "rad"}
# CMS baseline motion-space smoothing sigma per axis (REFERENCE.md).
CMS_SIGMA = {"tz": 0.1, "tx": 0.05, "ty": 0.05, "rx": 0.0436, "ry": 0.0436, "rz": 0.122}
# The paper's headline radii per axis.
PAPER_RADIUS = {
    "tz": 0.010,
    "tx": 0.005,
    "ty": 0.005,
    "rz": math.radians(0.7),
    "rx": math.radians(0.25),
    "ry": math.radians(0.25),
}


PIXEL_OVERLAP = 1e-6


def pixel_span(c, xp=np):
    """First and last pixel index whose footprint ``[k - PIXEL_OVERLAP, k + 1 + PIXEL_OVERLAP)`` holds
    pixel-edge coordinate ``c`` (equal except within PIXEL_OVERLAP of an edge); float arrays."""
    return xp.floor(c - PIXEL_OVERLAP), xp.floor(c + PIXEL_OVERLAP)


# Depth tie rule of every imaging model: the renderer keeps the nearest depth and resolves exact float
# ties to the lower point index; bounds treat two depths closer than depth_tie_margin as tied (both count).
DEPTH_TIE_REL = 1e-9


def depth_tie_margin(d, xp=np):
    """Depths closer than this (metres) may compare either way in float arithmetic: bounds count both."""
    return DEPTH_TIE_REL * (xp.abs(d) + 1.0)


def parse_axis(name: str) -> str:
    """Normalise an axis name (``Tz``, ``tz``, ``RY`` ...); raise PwsError if unknown."""
    axis = str(name).strip().lower()
    if axis not in AXES:
        raise PwsError(f"unknown motion axis {name!r}: expected one of {', '.join(AXES)}")
    return axis


def rotation_matrix(axis: str, angle: float) -> np.ndarray:
    """The rotation R of the camera for ``axis`` in ``rx, ry, rz`` (identity for translations)."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == "rx":
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    if axis == "ry":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if axis == "rz":
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.eye(3)


def camera_pose(axis: str, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the moved camera in the original optical frame."""
    axis = parse_axis(axis)
    t = np.zeros(3)
    if axis in TRANSLATIONS:
        t[TRANSLATIONS.index(axis)] = alpha
        return np.eye(3), t
    return rotation_matrix(axis, alpha), t


def transform(points, axis: str, alpha, xp=np):
    """Coordinates ``P' = R^T (P - t)`` of ``points[..., 3]`` for motion ``alpha`` (broadcasts).

    Works with numpy (``xp=np``) and torch (``xp=torch``) arrays. ``alpha`` must broadcast against
    ``points[..., 0]``.
    """
    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    if axis == "tx":
        return X - alpha, Y + 0 * alpha, Z + 0 * alpha
    if axis == "ty":
        return X + 0 * alpha, Y - alpha, Z + 0 * alpha
    if axis == "tz":
        return X + 0 * alpha, Y + 0 * alpha, Z - alpha
    c, s = xp.cos(alpha), xp.sin(alpha)
    if axis == "rx":  # R^T = [[1,0,0],[0,c,s],[0,-s,c]]
        return X + 0 * alpha, c * Y + s * Z, -s * Y + c * Z
    if axis == "ry":  # R^T = [[c,0,-s],[0,1,0],[s,0,c]]
        return c * X - s * Z, Y + 0 * alpha, s * X + c * Z
    if axis == "rz":  # R^T = [[c,s,0],[-s,c,0],[0,0,1]]
        return c * X + s * Y, -s * X + c * Y, Z + 0 * alpha
    raise PwsError(f"unknown motion axis {axis!r}")


def depth(points, axis: str, alpha, xp=np):
    """Depth ``Z'`` of ``points[..., 3]`` under motion ``alpha`` (the third coordinate of :func:`transform`,
    computed alone)."""
    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    if axis == "tz":
        return Z - alpha
    if axis == "rx":
        return -xp.sin(alpha) * Y + xp.cos(alpha) * Z
    if axis == "ry":
        return xp.sin(alpha) * X + xp.cos(alpha) * Z
    if axis in AXES:
        return Z + 0 * alpha
    raise PwsError(f"unknown motion axis {axis!r}")


def project(points, intr: CameraIntrinsics, axis: str, alpha, xp=np):
    """Pixel-edge coordinates ``(u, v)`` and depth ``D`` of points under motion ``alpha``.

    ``u`` and ``v`` are meaningful only where ``D > 0``.
    """
    if xp is not np:
        return _project_torch(points, intr, axis, alpha)
    Xp, Yp, Zp = transform(points, axis, alpha, xp=xp)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * Xp / Zp + (intr.cx + 0.5)
        v = intr.fy * Yp / Zp + (intr.cy + 0.5)
    return u, v, Zp


def _project_torch(points, intr: CameraIntrinsics, axis: str, alpha):
    """:func:`project` for torch tensors with few full-size temporaries (the renderers' hot loop): the
    same formulas, ``1/Z'`` computed once (a last-bit difference from ``X'/Z'``, far below the pixel
    tolerances of the bounds)."""
    import torch

    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    if axis in TRANSLATIONS:   # the moved coordinate only; the others broadcast as they are
        k = TRANSLATIONS.index(axis)
        Xp, Yp, Zp = (X - alpha if k == 0 else X), (Y - alpha if k == 1 else Y), (Z - alpha if k == 2 else Z)
    else:                      # the rotations of transform(), each new coordinate in two passes
        c, s = torch.cos(alpha), torch.sin(alpha)
        if axis == "rx":   # Y' = c Y + s Z, Z' = -s Y + c Z
            Xp, Yp, Zp = X, torch.mul(Y, c).addcmul_(Z, s), torch.mul(Y, s).neg_().addcmul_(Z, c)
        elif axis == "ry":   # X' = c X - s Z, Z' = s X + c Z
            Xp, Yp, Zp = torch.mul(X, c).addcmul_(Z, s, value=-1.0), Y, torch.mul(X, s).addcmul_(Z, c)
        elif axis == "rz":   # X' = c X + s Y, Y' = -s X + c Y
            Xp, Yp, Zp = torch.mul(X, c).addcmul_(Y, s), torch.mul(X, s).neg_().addcmul_(Y, c), Z
        else:
            raise PwsError(f"unknown motion axis {axis!r}")
    # (numpy's rule on the two shapes: torch.broadcast_shapes imports its symbolic-shape machinery and sympy on first
    # use, half a second of a command's start)
    shape = np.broadcast_shapes(tuple(points.shape[:-1]), tuple(torch.as_tensor(alpha).shape))
    Zp = Zp.expand(shape) if Zp.shape != shape else Zp
    # 1/Z' kept finite: a depth within 1e-300 of 0 then gives a point far off the image (as X'/Z' does),
    # never 0 * inf = NaN
    inv = torch.reciprocal(Zp).clamp_(-1e300, 1e300)
    u = torch.addcmul(torch.tensor(intr.cx + 0.5, dtype=inv.dtype, device=inv.device), Xp, inv, value=intr.fx)
    v = torch.addcmul(torch.tensor(intr.cy + 0.5, dtype=inv.dtype, device=inv.device), Yp, inv, value=intr.fy)
    return u, v, Zp


def split_events(points: np.ndarray, axis: str, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Motion values in ``(lo, hi)`` splitting ``[lo, hi]`` into pieces on which ``u``, ``v`` and the depth
    of each point are monotonic and the depth has constant sign, as sparse (point index, alpha) pairs
    sorted by alpha: the pole of tz (``Z - alpha = 0``) and, for rotations, the angles where a harmonic
    ``A cos t + B sin t`` of the point is stationary (``atan2(B, A) + k pi``) or zero (``+ pi/2``)."""
    X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
    bases: list[np.ndarray] = []
    if axis == "rz":  # u ~ X c + Y s ; v ~ Y c - X s
        bases = [np.arctan2(Y, X), np.arctan2(-X, Y)]
    elif axis == "rx":  # depth = Z c - Y s ; Y' = Y c + Z s
        bases = [np.arctan2(-Y, Z)]
    elif axis == "ry":  # depth = Z c + X s ; X' = X c - Z s
        bases = [np.arctan2(X, Z)]
    cands = [Z] if axis == "tz" else [b + offset + k * math.pi for b in bases for offset in (0.0, 0.5 * math.pi)
                                       for k in range(-3, 4)]
    idx, ts = [], []
    for t in cands:
        m = np.nonzero((t > lo) & (t < hi))[0]
        idx.append(m)
        ts.append(t[m])
    if not idx:
        return np.zeros(0, np.int64), np.zeros(0)
    i, t = np.concatenate(idx), np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    return i[order].astype(np.int64), t[order]


def split_points(points: np.ndarray, axis: str, lo: float, hi: float) -> np.ndarray:
    """The :func:`split_events` of every point as an array ``(N, M)``, each row sorted, NaN for unused slots."""
    n = len(points)
    idx, t = split_events(points, axis, lo, hi)
    if not len(idx):
        return np.full((n, 0), np.nan)
    order = np.lexsort((t, idx))
    idx, t = idx[order], t[order]
    counts = np.bincount(idx, minlength=n)
    out = np.full((n, int(counts.max())), np.nan)
    out[idx, np.arange(len(idx)) - (np.cumsum(counts) - counts)[idx]] = t
    return out


def lipschitz_constant(points: np.ndarray, intr: CameraIntrinsics, axis: str, lo: float, hi: float, samples: int = 33) -> np.ndarray:
    """``L_P = max_alpha |d rho / d alpha|_inf`` over ``[lo, hi]`` for each point.

    Evaluated with the analytic derivative on a grid of ``samples`` values including the split
    points (where it peaks for these functions); used for planning only (PwS-L / PwS-OF).
    """
    grid = np.linspace(lo, hi, samples)
    extra = split_points(points, axis, lo, hi)
    best = np.zeros(len(points))
    h = max(abs(hi - lo), 1e-9) * 1e-6

    def deriv(alpha):
        u1, v1, _ = project(points, intr, axis, alpha + h)
        u0, v0, _ = project(points, intr, axis, alpha - h)
        return np.maximum(np.abs(u1 - u0), np.abs(v1 - v0)) / (2 * h)

    for a in grid:
        best = np.fmax(best, deriv(a))
    for j in range(extra.shape[1]):
        col = extra[:, j]
        ok = ~np.isnan(col)
        if ok.any():
            d = deriv(np.where(ok, col, lo))
            best = np.where(ok, np.fmax(best, d), best)
    return best

"""Batched z-buffer rasterisation of a coloured cloud under one-axis camera motion (torch).

Pixel ``(row, col) = (floor v, floor u)`` in pixel-edge coordinates (see :mod:`.motion`; a point within
``PIXEL_OVERLAP`` = 1e-6 px of a pixel edge is drawn on both sides of it); the nearest
depth wins, exact float ties go to the lower point index: the depth tie rule of
:func:`.motion.depth_tie_margin`, whose bounds (:mod:`.sweep`) count every point within that margin of the
nearest, since ulp-close depths may compare either way here; points with ``z <= 0`` or outside the
image are dropped; empty pixels get ``background``. Poses are processed in chunks so memory stays bounded
(``max_elements`` point-projections at a time) whatever the number of poses.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import PwsError, require
from .motion import PIXEL_OVERLAP, parse_axis, pixel_span, project

DEFAULT_MAX_ELEMENTS = 1 << 22


def resolve_device(device: str | torch.device | None) -> torch.device:
    """A torch device; PwsError if CUDA is asked for and not available."""
    if device is None or device == "":
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise PwsError(f"invalid device {device!r}: {exc}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise PwsError(f"device {device!r} requested but CUDA is not available")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise PwsError(f"device {device!r} requested but only {torch.cuda.device_count()} CUDA device(s) exist")
    return dev


class Renderer:
    """Holds a cloud on a device and renders frames for batches of motion values."""

    def __init__(self, cloud: Cloud, intr: CameraIntrinsics, axis: str, *, background: float = 0.0,
                 device: str | torch.device | None = "cpu", max_elements: int = DEFAULT_MAX_ELEMENTS):
        require(np.isfinite(background), f"background must be finite, got {background}")
        self.axis = parse_axis(axis)
        self.intr = intr
        self.background = float(background)
        self.device = resolve_device(device)
        self.max_elements = int(max_elements)
        pts = np.asarray(cloud.points, dtype=np.float64)
        self.points = torch.as_tensor(pts, device=self.device)
        cols = np.asarray(cloud.colors, dtype=np.float32)
        # row N is the background "colour"
        bg = np.full((1, 3), self.background, dtype=np.float32)
        self.colors = torch.as_tensor(np.concatenate([cols, bg], axis=0), device=self.device)
        self.num_points = len(pts)

    @property
    def chunk_size(self) -> int:
        return max(1, self.max_elements // max(1, self.num_points))

    def _winners(self, alphas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Index of the winning point per pixel (N = empty) and its depth (0 where empty)."""
        H, W = self.intr.height, self.intr.width
        B = alphas.shape[0]
        n = self.num_points
        idx = torch.full((B * H * W,), n, dtype=torch.long, device=self.device)
        depth = torch.zeros((B * H * W,), dtype=torch.float64, device=self.device)
        if n == 0:
            return idx.view(B, H, W), depth.view(B, H, W)
        u, v, z = project(self.points[None, :, :], self.intr, self.axis, alphas[:, None], xp=torch)
        e = PIXEL_OVERLAP  # (c + e >= 0) == (floor(c + e) >= 0) and (c - e < W) == (floor(c - e) < W)
        ok = (z > 0) & (u + e >= 0) & (u - e < W) & (v + e >= 0) & (v - e < H)
        b_i, p_i = torch.nonzero(ok, as_tuple=True)
        if b_i.numel() == 0:
            return idx.view(B, H, W), depth.view(B, H, W)
        cl, ch = (t.long() for t in pixel_span(u[b_i, p_i], xp=torch))
        rl, rh = (t.long() for t in pixel_span(v[b_i, p_i], xp=torch))
        # up to four pixels per point (overlapping footprints, see motion.PIXEL_OVERLAP); the extra
        # ones concern only the few points within 1e-6 px of an edge
        near = torch.nonzero((ch != cl) | (rh != rl), as_tuple=True)[0]
        if near.numel():
            e_b, e_p = b_i[near], p_i[near]
            e_cl, e_ch, e_rl, e_rh = cl[near], ch[near], rl[near], rh[near]
            dc, dr = e_ch != e_cl, e_rh != e_rl
            parts = [(e_rl[dc], e_ch[dc], e_b[dc], e_p[dc]), (e_rh[dr], e_cl[dr], e_b[dr], e_p[dr])]
            both = dc & dr
            parts.append((e_rh[both], e_ch[both], e_b[both], e_p[both]))
            rl = torch.cat([rl] + [q[0] for q in parts])
            cl = torch.cat([cl] + [q[1] for q in parts])
            b_i = torch.cat([b_i] + [q[2] for q in parts])
            p_i = torch.cat([p_i] + [q[3] for q in parts])
        valid = (cl >= 0) & (cl < W) & (rl >= 0) & (rl < H)
        if not bool(valid.all()):
            b_i, p_i, rl, cl = b_i[valid], p_i[valid], rl[valid], cl[valid]
        key = (b_i * H + rl) * W + cl
        zz = z[b_i, p_i]
        zmin = torch.full((B * H * W,), float("inf"), dtype=torch.float64, device=self.device)
        zmin.scatter_reduce_(0, key, zz, reduce="amin", include_self=True)
        at_min = zz == zmin[key]
        idx.scatter_reduce_(0, key[at_min], p_i[at_min], reduce="amin", include_self=True)
        filled = idx < n
        depth[filled] = zmin[filled]
        return idx.view(B, H, W), depth.view(B, H, W)

    def render_batch(self, alphas, return_depth: bool = False):
        """Frames ``(B, H, W, 3)`` float32 on the device for motion values ``alphas`` (B,)."""
        a = torch.as_tensor(np.asarray(alphas, dtype=np.float64), device=self.device).reshape(-1)
        require(bool(torch.all(torch.isfinite(a))), "motion values must be finite")
        frames, depths = [], []
        for s in range(0, a.shape[0], self.chunk_size):
            idx, depth = self._winners(a[s : s + self.chunk_size])
            frames.append(self.colors[idx])
            depths.append(depth)
        if not frames:
            H, W = self.intr.shape
            out = torch.empty((0, H, W, 3), dtype=torch.float32, device=self.device)
            return (out, torch.empty((0, H, W), dtype=torch.float64, device=self.device)) if return_depth else out
        out = torch.cat(frames)
        return (out, torch.cat(depths)) if return_depth else out

    def iter_frames(self, alphas, chunk: int | None = None) -> Iterator[tuple[int, torch.Tensor]]:
        """Yield ``(start, frames)`` for consecutive chunks of ``alphas`` (bounded memory)."""
        alphas = np.asarray(alphas, dtype=np.float64).reshape(-1)
        step = int(chunk or max(1, min(256, self.chunk_size)))
        for s in range(0, len(alphas), step):
            yield s, self.render_batch(alphas[s : s + step])


def render(cloud: Cloud, intr: CameraIntrinsics, axis: str, alphas, *, background: float = 0.0,
           device: str | None = "cpu", return_depth: bool = False, max_elements: int = DEFAULT_MAX_ELEMENTS):
    """Render frames for every motion value in ``alphas``: numpy ``(B, H, W, 3)`` float32 in [0, 1]
    (and depth ``(B, H, W)`` float64 metres, 0 where empty, with ``return_depth``)."""
    r = Renderer(cloud, intr, axis, background=background, device=device, max_elements=max_elements)
    out = r.render_batch(alphas, return_depth=return_depth)
    if return_depth:
        return out[0].cpu().numpy(), out[1].cpu().numpy()
    return out.cpu().numpy()

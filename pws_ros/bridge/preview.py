"""Preview frames for humans (``rendered/preview``): every k-th frame of a plan and its alpha = 0
frame, as uint8 RGB ``(axis, index, image)`` triples."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..core.cloud import Cloud
from .scheme import preview_image


def preview_indices(alphas: Any, every: int) -> list[int]:
    """Indices ``0, k, 2k, ...`` of a grid plus the index of ``alpha = 0``."""
    alphas = np.asarray(alphas)
    keep = set(range(0, len(alphas), max(1, int(every))))
    zero = np.nonzero(alphas == 0.0)[0]
    if len(zero):
        keep.add(int(zero[0]))
    return sorted(keep)


def preview_frames(axis: str, rendered: Any, every: int) -> list[tuple[str, int, np.ndarray]]:
    """Every ``every``-th frame of a rendered plan and its alpha = 0 frame, as uint8 RGB."""
    return [(axis, i, preview_image(rendered.frames[i])) for i in preview_indices(rendered.alphas, every)]


def render_previews(cloud: Cloud, imaging: Any, plan: Any, every: int, *, device: str = "cpu") -> list[tuple[str, int, np.ndarray]]:
    """Every ``every``-th frame of a plan (and its alpha = 0 frame) rendered as uint8 RGB (the pipeline,
    which keeps no rendered plan)."""
    from ..core.imaging import make_renderer

    idx = preview_indices(plan.alphas, every)
    renderer = make_renderer(cloud, imaging, plan.axis, device=device)
    frames = renderer.render_batch(np.asarray(plan.alphas)[idx]).cpu().numpy()
    return [(plan.axis, int(i), preview_image(f)) for i, f in zip(idx, frames)]


__all__ = ["preview_frames", "preview_indices", "render_previews"]

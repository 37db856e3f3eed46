"""Preview frames for humans (``rendered/preview``): every k-th frame of a plan and its alpha = 0
frame, as uint8 RGB ``(axis, index, image)`` triples; and the alpha = 0 frame alone (what the classifier
saw at the recorded pose), the view of the overlay image (:mod:`pws_ros.bridge.overlay`)."""
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


def alpha0_preview(result: Any) -> np.ndarray | None:
    """The alpha = 0 frame among a :class:`~pws_ros.bridge.engine.FrameResult`'s previews (uint8 RGB), or None."""
    for axis, index, img in result.previews:
        plan = result.plans.get(axis)
        if plan is not None and 0 <= index < len(plan.alphas) and float(plan.alphas[index]) == 0.0:
            return img
    return None


def alpha0_view(result: Any, cloud: Cloud | None, *, device: str = "cpu") -> np.ndarray | None:
    """The alpha = 0 frame of a certified frame (uint8 RGB): from its previews when they hold it (free),
    else rendered from ``cloud`` (the cloud the frame was rendered from) with the frame's imaging; None
    when the frame has no imaging (its input could not be converted) or no axis."""
    img = alpha0_preview(result)
    imaging = getattr(result, "imaging", None)
    if img is not None or imaging is None or cloud is None or not result.certificates:
        return img
    from ..core.imaging import make_renderer

    renderer = make_renderer(cloud, imaging, result.certificates[0].axis, device=device)
    return preview_image(renderer.render_batch(np.zeros(1))[0])


def assembled_alpha0(frame: Any) -> np.ndarray | None:
    """The alpha = 0 frame (uint8 RGB) of an :class:`~pws_ros.bridge.assembly.AssembledFrame` (the four-process
    certifier: every rendered frame of a plan arrived), from its first complete axis; None if none has it."""
    bundle = frame.info
    for ax in frame.axes:
        plan = bundle.plans.get(ax.axis) if bundle is not None else None
        if ax.ok and ax.frames and plan is not None:
            zero = np.nonzero(np.asarray(plan.alphas) == 0.0)[0]
            if len(zero) and int(zero[0]) < len(ax.frames):
                return preview_image(ax.frames[int(zero[0])])
    return None


__all__ = ["alpha0_preview", "alpha0_view", "assembled_alpha0", "preview_frames", "preview_indices", "render_previews"]

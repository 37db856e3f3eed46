"""The imaging model: the image a camera moved by ``alpha`` delivers to the classifier, and its bounds.

One home for what a certificate is about, defined precisely in docs/imaging.md; one import for all of
it (every name below is importable from here). Two models:

* ``surfel`` (the default): every point of the one-frame cloud is a small fronto-parallel square (a
  surfel) drawn in a fixed occlusion order, in a centred crop of the camera rendered at a multiple of
  the classifier's input and block-averaged down to it.
* ``paper``: the paper's model (one point paints one pixel, holes show ``background``) at the
  classifier's input size, rendered by :mod:`.render` and bounded by the exact sweep of :mod:`.sweep`
  (:mod:`.bounds`).

The pieces, each module beside the section of docs/imaging.md it implements:

* :mod:`.framing` — :class:`Imaging` (what one camera's imaging is: crop, factor, binning, border,
  background, uncovered value), :func:`make_imaging`, :func:`auto_border`, :func:`reduce_frames` (the
  block mean and the border), and the model's constants (``SURFEL_OVERLAP``, ``SAMPLE_JITTER``) and
  float tolerances (``EDGE_EPS``, ``VALUE_EPS``, ``SAFETY``) in one home;
* :mod:`.surfel` — the surfel renderer (:class:`SurfelRenderer`, :func:`bin_cloud`,
  :func:`surfel_corners`, :func:`occlusion_key`, :class:`SamplePoints`);
* :mod:`.surfel_bounds` — its sound per-segment bounds (:class:`HullValues`, :func:`segment_hulls`,
  :func:`hulls_within`, :func:`render_plan_surfel`);
* here — what differs by model: :func:`make_renderer`, :func:`plan_for`, :func:`segment_bounds`.
"""
from __future__ import annotations

import numpy as np
import torch

from .cloud import Cloud
from .framing import (DEFAULT_RENDER_FACTOR, EDGE_EPS, IMAGING_KINDS, SAFETY, SAMPLE_JITTER, SURFEL_OVERLAP, UNCOVERED,
                      VALUE_EPS, Imaging, auto_border, make_imaging, reduce_frames)
from .motion import AXES
from .partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX, Plan, plan_partitions, plan_step
from .footprint import SamplePoints, covered_pairs, surfel_corners
from .surfel import SurfelRenderer, bin_cloud, occlusion_key
from .surfel_bounds import HullValues, hulls_within, render_plan_surfel, segment_hulls


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
        pts, cols = bin_cloud(np.asarray(cloud.points, dtype=np.float64), np.asarray(cloud.colors, np.float32), imaging,
                              cloud.filled_mask)
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


__all__ = ["AXES", "DEFAULT_RENDER_FACTOR", "EDGE_EPS", "HullValues", "IMAGING_KINDS", "Imaging", "SAFETY", "SAMPLE_JITTER",
           "SURFEL_OVERLAP", "SamplePoints", "SurfelRenderer", "UNCOVERED", "VALUE_EPS", "auto_border", "bin_cloud",
           "covered_pairs", "hulls_within", "make_imaging", "make_renderer", "occlusion_key", "plan_for", "reduce_frames",
           "render_plan_surfel", "segment_bounds", "segment_hulls", "surfel_corners"]

"""Certification of a smoothed classifier against one-axis camera motion (PwS, PwS-L, PwS-OF, CMS).

The method on one screen (Theorems 1-3 of the paper with the per-segment bounds of :mod:`.bounds`):

1. Plan the grid ``alpha_1 = -b < ... < alpha_N = +b`` (contains 0) with :func:`.partition.plan_partitions`.
2. Render every partition frame ``x_i`` and the sound per-segment bound ``B_i`` with
   ``|x(alpha) - x_i|^2 + |x(alpha) - x_{i+1}|^2 <= B_i`` for all ``alpha`` in segment ``i`` (holes included).
3. Selection: ``n0`` noisy samples of the original frame (``alpha = 0``) pick the label ``c_A``.
4. Estimation: ``n`` fresh noisy samples per partition frame (or per anchor) count ``c_A``;
   ``p_A^(i)`` is the one-sided Clopper-Pearson lower bound at level ``alpha / m`` (Bonferroni over the
   ``m`` bounds used) and ``R_i = sigma Phi^-1(p_A^(i))`` (0 if ``p_A^(i) <= 1/2``).
5. Coverage of segment ``i`` (any frame of it is within the Cohen radius of some estimated frame; the
   rules are objects of :mod:`.coverage`):
   * ``paper``: ``max_i sqrt(B_i / 2) < min_i R_i`` (Theorem 1 with ``B_i`` in place of ``|x_i - x_{i+1}|^2``);
   * ``pairwise``: ``B_i < R_i^2 + R_{i+1}^2``;
   * ``anchors``: some anchor ``a`` has ``D_i(x_a) < R_a`` (``p_A`` estimated at ``K`` anchors only; with
     surfel imaging the anchors are placed from the distance bounds, :class:`.coverage.AdaptiveAnchorsRule`).
6. The certified radius is the largest ``r`` such that every segment inside ``[-r, r]`` is covered; the
   certificate holds for ``[-b, b]`` iff it reaches ``b``. With the adaptive anchors and a renderer
   (:func:`certify`), a covered run that stops inside a grid segment is extended by refining that segment
   once the radii are known (:func:`.coverage.frontier_reach`; coverage is a fact of the bounds on any
   grid); from received frames and bounds (:func:`certify_rendered`) it stops at the grid point.

The adaptive anchors' path (the grid refined for a target radius, the placement of the anchors, their
estimation in looks: :func:`.anchored._certify_anchored`) is :mod:`.anchored`; the configuration and the
certificate of a covered interval, which both paths share, are :mod:`.certify_common`. Their names stay
importable from here.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Iterator

import numpy as np
import torch

# the anchors' path and the shared pieces; their names are importable from here as before
from .anchor_geometry import _FixedGeometry, _RendererGeometry, grid_cap, refine_for_target, refined_hulls  # noqa: F401
from .anchored import _certify_anchored, anchor_grid, largest_target, placement  # noqa: F401
from .bounds import SegmentValues
from .camera import CameraIntrinsics
from .certify_common import CertifyConfig, _conclude, bounds_bytes, segment_bytes  # noqa: F401
from .cloud import Cloud
from .coverage import COVERAGES, cohen_radii, coverage_rule  # noqa: F401
from .errors import require
from .imaging import HullValues, Imaging, make_imaging, make_renderer, plan_for, segment_bounds
from .model import LoadedModel
from .motion import parse_axis
from .partition import Plan, check_radius, validate_grid
from .result import Certificate
from .smoothing import SmoothedClassifier, bonferroni, clopper_pearson_lower
from .volume import volume_text

METHODS = ("pws", "pws_l", "pws_of", "cms")


def imaging_for(cloud: Cloud, intr: CameraIntrinsics, model: LoadedModel, config: CertifyConfig,
                radii: dict[str, float]) -> Imaging:
    """The imaging of ``config`` for camera ``intr`` and ``model``'s input size (border from ``radii``)."""
    return make_imaging(config.imaging, intr, getattr(model, "input_size", None), background=config.background,
                        border=int(config.border), cloud=cloud, radii=radii, render_factor=int(config.render_factor),
                        uncovered=config.uncovered, volume=config.working_volume)


def certify(cloud: Cloud, intr: CameraIntrinsics, model: LoadedModel, axis: str, radius: float, method: str = "pws_of",
            config: CertifyConfig | None = None, denoiser=None, plan: Plan | None = None,
            progress: Callable[[int, int], None] | None = None, imaging: Imaging | None = None) -> Certificate:
    """Certify the smoothed prediction on ``cloud`` seen by camera ``intr`` for motions ``[-radius, radius]``.

    The guarantee of a ``certified`` result (``cert.radius``; ``not_certified`` certifies the smaller
    ``cert.radius`` in the same sense): with probability at least ``1 - config.alpha`` over the noise,
    the smoothed classifier ``g(x) = argmax_c P(f(x + N(0, sigma^2 I)) = c)`` returns ``cert.label`` for
    the image ``x(a)`` of every motion ``a`` in ``[-cert.radius, cert.radius]`` along ``axis``, where ``x(a)``
    is the image the imaging model (docs/imaging.md) makes from ``cloud`` moved by ``a``. It rests on sound
    per-segment bounds of the plan's grid (every image of a segment lies within ``D_i`` of an anchor frame)
    and one-sided Clopper-Pearson bounds whose levels sum to at most ``alpha``: ``alpha / K`` over the ``K``
    anchors (Bonferroni), or the anchors' joint first look and its individual looks (:mod:`.sequential`), all
    placed and planned before any estimation sample is drawn (``abstain``: the top class is not certified
    even at 0).

    ``intr`` is the input camera; frames are made by the imaging model of ``config.imaging`` (or the given
    ``imaging``). ``cloud`` is the cloud that is rendered: the entire cloud for ``pws`` (paper imaging only),
    the one-frame cloud for ``pws_of`` (``pws_l`` uses what it is given). ``method='cms'`` runs the CMS
    baseline with the same imaging model. ``cert.plan`` is the plan the certificate rests on (the given or
    planned one, refined by the adaptive anchors).
    """
    config = (config or CertifyConfig()).validate()
    axis = parse_axis(axis)
    radius = check_radius(radius)
    require(method in METHODS, f"unknown method {method!r}: expected one of {', '.join(METHODS)}")
    cloud.require_nonempty()
    if imaging is None:
        require(not (config.imaging == "surfel" and method == "pws"),
                "method pws plans on the entire scene cloud, which has no depth pixels to make surfels of: "
                "use imaging paper, or method pws_of / pws_l with the one-frame cloud")
        imaging = imaging_for(cloud, intr, model, config, {axis: radius})
    cam = imaging.camera
    model.check_input_size(*imaging.out_shape, what="camera")
    if method == "cms":
        from .cms import certify_cms

        cert = certify_cms(cloud, cam, model, axis, radius, motion_sigma=config.cms_sigma, n0=config.n0, n=config.n,
                           alpha=config.alpha, seed=config.seed, device=config.device, batch_size=config.batch_size,
                           background=config.background, progress=progress, imaging=imaging)
        cert.imaging, cert.working_volume = imaging.kind, volume_text(imaging.volume)
        return cert
    t_start = time.perf_counter()
    if plan is None:
        plan = plan_for(cloud, imaging, axis, radius, method, step_px=config.step_px, delta=config.delta,
                        max_partitions=config.max_partitions, min_partitions=int(config.min_partitions))
    else:
        require(plan.axis == axis, f"plan is for axis {plan.axis}, not {axis}")
        require(abs(plan.radius - radius) <= 1e-12 * radius, f"plan is for radius {plan.radius:g}, not {radius:g}")
        validate_grid(plan.alphas, plan.radius)
    t_plan = time.perf_counter() - t_start
    t0 = time.perf_counter()
    timings = {"plan": t_plan, "render": 0.0}
    renderer = make_renderer(cloud, imaging, axis, device=config.device,
                             alpha_range=(float(plan.alphas[0]), float(plan.alphas[-1])))
    rule = coverage_rule(config.coverage, config.num_anchors, imaging.kind)
    if rule.adaptive:
        cert = _certify_anchored(_RendererGeometry(renderer, config), plan, rule, model, config, denoiser, progress,
                                 method, timings, t_start)
    else:
        values = segment_bounds(renderer, cloud, imaging, plan.alphas, max_bytes=bounds_bytes(config))
        timings["bounds"] = time.perf_counter() - t0
        cert = _certify_stream(renderer.render_batch, renderer.iter_frames(plan.alphas, chunk=config.chunk), plan, values,
                               rule, model, config, denoiser, progress, method, timings, t_start)
    cert.bounds["imaging"] = imaging.to_dict()
    cert.imaging, cert.working_volume = imaging.kind, volume_text(imaging.volume)
    return cert


def certify_rendered(rendered, model: LoadedModel, config: CertifyConfig | None = None, denoiser=None,
                     progress: Callable[[int, int], None] | None = None) -> Certificate:
    """Certify from an already rendered plan (:class:`.bounds.RenderedPlan`), e.g. frames that crossed
    topics between the projector and certifier nodes. A surfel plan with ``coverage: anchors`` gets the
    adaptive anchors as in :func:`certify`, on the grid as received (the planner node refined it,
    :func:`.anchored.anchor_grid`; no refinement and no frontier here: the certifier has no renderer)."""
    config = (config or CertifyConfig()).validate()
    t_start = time.perf_counter()
    frames = rendered.frames
    require(frames.shape[0] == rendered.plan.num_partitions,
            f"{frames.shape[0]} frames for a plan of {rendered.plan.num_partitions} partitions: refusing to certify an incomplete partition set")
    model.check_input_size(int(frames.shape[1]), int(frames.shape[2]), what="frame")
    imaging = str(rendered.plan.details.get("imaging", "paper"))
    rule = coverage_rule(config.coverage, config.num_anchors, imaging)
    if rule.adaptive:
        f = frames.detach().cpu().numpy() if isinstance(frames, torch.Tensor) else np.asarray(frames, np.float32)
        t0 = time.perf_counter()
        hulls = HullValues.from_segment_values(rendered.values, f)
        timings = {"plan": 0.0, "render": 0.0, "bounds": time.perf_counter() - t0}
        cert = _certify_anchored(_FixedGeometry(f, hulls), rendered.plan, rule, model, config, denoiser, progress,
                                 rendered.plan.method, timings, t_start)
        cert.imaging = imaging
        return cert

    step = int(config.chunk or 128)

    def frames_at(alphas):
        return frames[torch.as_tensor(np.searchsorted(rendered.plan.alphas, np.asarray(alphas)))]

    chunks = ((s, frames[s : s + step]) for s in range(0, len(frames), step))
    cert = _certify_stream(frames_at, chunks, rendered.plan, rendered.values, rule,
                           model, config, denoiser, progress, rendered.plan.method, {"plan": 0.0, "render": 0.0}, t_start)
    cert.imaging = imaging
    return cert


def _certify_stream(frames_at: Callable, chunks: Iterator, plan: Plan, values: SegmentValues, rule, model: LoadedModel,
                    config: CertifyConfig, denoiser, progress, method: str, timings: dict[str, float],
                    t_start: float) -> Certificate:
    """Certify with a rule of fixed estimation frames (:mod:`.coverage`): ``frames_at(alphas)`` renders
    frames, ``chunks`` yields ``(start, frames)`` over the whole grid in order."""
    N = plan.num_partitions
    centre = int(np.searchsorted(plan.alphas, 0.0))
    require(plan.alphas[centre] == 0.0, "plan grid lacks alpha = 0")
    sc = SmoothedClassifier(model, config.sigma, batch_size=config.batch_size, seed=config.seed, denoiser=denoiser)
    anchors = rule.uses_anchor_distances
    est_idx = rule.estimation_indices(N)
    m_bounds = len(est_idx)
    a_level = bonferroni(config.alpha, m_bounds)
    total_work = config.n0 + m_bounds * config.n
    done = [0]

    def tick(k):
        done[0] += k
        if progress is not None:
            progress(min(done[0], total_work), total_work)

    t_render = timings.get("render", 0.0)
    t_stats = 0.0
    # 1. selection at alpha = 0
    t0 = time.perf_counter()
    x0 = frames_at(np.array([0.0]))
    t_render += time.perf_counter() - t0
    counts0 = sc.sample_counts(x0, int(config.n0))
    label = int(torch.argmax(counts0[0]).item())
    tick(config.n0)
    # 2. stream the frames: bounds per segment, counts at estimation frames
    B = np.zeros(N - 1)
    k_est = np.zeros(m_bounds, dtype=np.int64)
    est_pos = {int(i): j for j, i in enumerate(est_idx)}
    anchor_frames = None
    D2 = None
    if anchors:
        t0 = time.perf_counter()
        anchor_frames = frames_at(plan.alphas[est_idx]).cpu().numpy()
        t_render += time.perf_counter() - t0
        D2 = np.zeros((m_bounds, N - 1))
        # fixed anchors share their noise draws, as the adaptive ones do (each bound a Binomial count;
        # Bonferroni needs no independence between them)
        c = sc.sample_counts(torch.as_tensor(anchor_frames), int(config.n), common_noise=True)
        k_est[:] = c[:, label].numpy()
        tick(m_bounds * config.n)
    prev = None
    it = iter(chunks)
    while True:
        t0 = time.perf_counter()
        try:
            s, fr = next(it)
        except StopIteration:
            t_render += time.perf_counter() - t0
            break
        fr_np = fr.cpu().numpy()
        t_render += time.perf_counter() - t0
        t1 = time.perf_counter()
        block = fr_np if prev is None else np.concatenate([prev, fr_np])
        k0 = s if prev is None else s - 1
        if len(block) >= 2:
            B[k0 : k0 + len(block) - 1] = values.pair_bound_sq(block, k0)
            if anchors:
                for j in range(m_bounds):
                    D2[j, k0 : k0 + len(block) - 1] = values.anchor_dist_sq(block, anchor_frames[j], k0)
        prev = fr_np[-1:]
        t_stats += time.perf_counter() - t1
        if not anchors:
            c = sc.sample_counts(fr, int(config.n))
            k_est[s : s + len(fr_np)] = c[:, label].numpy()
            tick(len(fr_np) * config.n)
    # 3. statistics and coverage
    t1 = time.perf_counter()
    n = int(config.n)
    p_lower = np.asarray(clopper_pearson_lower(k_est, n, a_level), dtype=np.float64).reshape(-1)
    R = cohen_radii(p_lower, config.sigma)
    bounds: dict[str, Any] = {"max_pair_bound_sq": float(B.max()) if len(B) else 0.0,
                              "M": float(np.sqrt(B.max() / 2)) if len(B) else 0.0,
                              "R_min": float(R.min()), "R_centre": float(R[est_pos[centre]]) if centre in est_pos else float("nan"),
                              "lemma1_holds": plan.details.get("lemma1_holds")}
    j, covered_count = rule.reach(R, centre, pair_bound_sq=B, anchor_dist_sq=D2)
    bounds["segments_covered"] = covered_count
    t_stats += time.perf_counter() - t1
    timings = dict(timings)
    timings.update(render=t_render, inference=sc.inference_seconds, statistics=t_stats)
    # segments centre-j .. centre+j-1 are covered: the interval [alphas[centre-j], alphas[centre+j]], whose
    # symmetric part is what is certified (a grid need not be symmetric about 0: a received or given plan)
    reach = min(float(plan.alphas[centre + j]), -float(plan.alphas[centre - j])) if j else 0.0
    return _conclude(plan, centre, reach, est_pos, p_lower, R, label, model, config, method, sc,
                     bounds, timings, t_start, frames_rendered=N + 1 + (m_bounds if anchors else 0))

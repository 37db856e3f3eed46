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

(One module over the usual ~450 lines on purpose: :func:`certify`, the two certification paths it
dispatches to — every frame estimated, :func:`_certify_stream`, and the adaptive anchors,
:func:`_certify_anchored` — and the grid refinement they share make one statistical argument whose parts
must agree on the order of selection, placement and estimation.)
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Iterator

import numpy as np
import torch

from .anchors import FIRST_ROUND_SHARE, REFINE_FRACTION, REFINE_ROUNDS, best_placement, predicted_target, refine_plan, target_radius
from .bounds import SegmentValues
from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import require
from .imaging import DEFAULT_RENDER_FACTOR, IMAGING_KINDS, UNCOVERED, HullValues, Imaging, SurfelRenderer, make_imaging, make_renderer, plan_for, hulls_within, segment_bounds
from .model import LoadedModel
from .coverage import (COVERAGES, FRONTIER_PARTS, FRONTIER_ROUNDS, AdaptiveAnchorsRule, cohen_radii, coverage_rule, covered_run, frontier_reach,
                       packing_bound, segment_covers)
from .motion import UNITS, parse_axis
from .partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX, Plan, check_radius, validate_grid
from .sequential import FIRST_LOOK, Looks, estimate, joint_looks, joint_rate, single
from .result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate
from .smoothing import SmoothedClassifier, bonferroni, clopper_pearson_lower
from .volume import WorkingVolume, volume_text

METHODS = ("pws", "pws_l", "pws_of", "cms")


@dataclass
class CertifyConfig:
    sigma: float = 0.5
    n0: int = 100
    n: int = 1000
    alpha: float = 0.01
    seed: int = 0
    device: str = "cpu"
    batch_size: int = 500
    coverage: str = "anchors"
    num_anchors: int = 24
    background: float = 0.0
    uncovered: str = "frame"   # surfel: what a pixel no surfel covers shows (core.imaging.UNCOVERED)
    max_partitions: int = DEFAULT_FRAME_BUDGET
    max_memory_mb: float = 2048.0
    min_partitions: int = 0
    delta: float | None = None
    cms_sigma: float | None = None
    chunk: int = 128
    imaging: str = "surfel"
    border: int = -1
    step_px: float = DEFAULT_STEP_PX
    render_factor: int = DEFAULT_RENDER_FACTOR
    # anchors coverage: where the anchors placed are predicted to fall short of the radius, the estimation
    # samples the axis was sized for (num_anchors * n) are spread over the K anchors placed (n_est =
    # num_anchors * n // K), fixed before any estimation sample is drawn; off: n per anchor. A time budget
    # that shrinks the sizes turns it on (they pay for num_anchors * n samples; bridge.budget)
    spread_estimation: bool = False
    # surfel: only the points inside are drawn (core.volume; docs/imaging.md section 4a); None: every point
    working_volume: WorkingVolume | None = None
    # surfel: rounds a side of the frontier refinement once the radii are known (.coverage.frontier_reach);
    # fewer rounds cost fewer bounds and may leave a smaller radius (a time budget lowers it, bridge.budget)
    frontier_rounds: int = FRONTIER_ROUNDS
    # anchors coverage: samples of an anchor's first look (core.sequential): the anchors are placed for what
    # n_first samples certify where that covers more per sample than n, up to num_anchors * n // n_first of
    # them; an anchor whose first look falls short gets the rest of its n. 0 (or >= n): n samples each
    n_first: int = FIRST_LOOK

    def validate(self) -> "CertifyConfig":
        require(math.isfinite(self.sigma) and self.sigma > 0, f"sigma must be positive, got {self.sigma}")
        require(int(self.n0) >= 1 and int(self.n) >= 1, f"n0 and n must be >= 1, got n0={self.n0}, n={self.n}")
        require(0 < self.alpha < 1, f"alpha must lie in (0, 1), got {self.alpha}")
        require(self.coverage in COVERAGES, f"unknown coverage rule {self.coverage!r}: expected one of {', '.join(COVERAGES)}")
        require(int(self.num_anchors) >= 1, f"num_anchors must be >= 1, got {self.num_anchors}")
        require(int(self.batch_size) >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        require(int(self.min_partitions) >= 0, f"min_partitions must be >= 0, got {self.min_partitions}")
        require(math.isfinite(self.background), f"background must be finite, got {self.background}")
        require(self.uncovered in UNCOVERED, f"unknown uncovered rule {self.uncovered!r}: expected one of {', '.join(UNCOVERED)}")
        require(self.imaging in IMAGING_KINDS, f"unknown imaging model {self.imaging!r}: expected one of {', '.join(IMAGING_KINDS)}")
        require(self.working_volume is None or self.imaging == "surfel",
                "a working volume needs surfel imaging (imaging: paper draws every point)")
        require(math.isfinite(self.step_px) and self.step_px > 0, f"step_px must be positive, got {self.step_px}")
        require(int(self.render_factor) >= 0, f"render_factor must be >= 0 (0: the camera's resolution), got {self.render_factor}")
        require(int(self.n_first) >= 0, f"n_first must be >= 0 (0: one look of n samples), got {self.n_first}")
        require(int(self.frontier_rounds) >= 0, f"frontier_rounds must be >= 0, got {self.frontier_rounds}")
        require(math.isfinite(self.max_memory_mb) and self.max_memory_mb >= 64,
                f"max_memory_mb must be at least 64, got {self.max_memory_mb}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def segment_bytes(imaging: Imaging) -> int:
    """Memory one segment of the surfel bounds and one frame take at the classifier's input size."""
    h, w = imaging.out_shape
    return h * w * (3 * 4 * 2 + 1) + h * w * 3 * 4


def bounds_bytes(config: CertifyConfig) -> int:
    """The share of ``max_memory_mb`` the per-segment bounds and frames of one axis may take (half; the
    renderer streams its chunks within the rest): a refined grid stays within it, a larger plan is an
    ERROR naming the ceiling, never an out-of-memory kill."""
    return int(config.max_memory_mb * 2**20 / 2)


def _label_name(model: LoadedModel, label: int) -> str:
    try:
        return model.class_names[label]
    except (IndexError, AttributeError, TypeError):
        return f"class_{label}"


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
    and one-sided Clopper-Pearson bounds at Bonferroni level ``alpha / K`` over the ``K`` anchors, placed
    before any estimation sample is drawn (``abstain``: the top class is not certified even at 0).

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
    :func:`anchor_grid`; no refinement and no frontier here: the certifier has no renderer)."""
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
    return _conclude(plan, centre, float(plan.alphas[centre + j]), est_pos, p_lower, R, label, model, config, method, sc,
                     bounds, timings, t_start, frames_rendered=N + 1 + (m_bounds if anchors else 0))


def _conclude(plan: Plan, centre: int, reach: float, est_pos: dict[int, int], p_lower: np.ndarray, R: np.ndarray, label: int,
              model: LoadedModel, config: CertifyConfig, method: str, sc: SmoothedClassifier, bounds: dict[str, Any],
              timings: dict[str, float], t_start: float, frames_rendered: int, n_est: int | None = None) -> Certificate:
    """The certificate of a covered interval ``[-reach, reach]`` (``reach`` = ``plan.radius``: certified)."""
    axis = plan.axis
    centre_ok = (R[est_pos[centre]] > 0) if centre in est_pos else False
    radius = float(reach) if centre_ok else 0.0
    certified = bool(centre_ok and radius >= plan.radius)
    if not centre_ok:
        status, reason = STATUS_ABSTAIN, f"p_A lower bound at the original pose is {p_lower[est_pos[centre]]:.4f} <= 0.5"
    elif certified:
        status, reason = STATUS_CERTIFIED, ""
    else:
        status = STATUS_NOT_CERTIFIED
        reason = f"covered up to ±{radius:g} {UNITS[axis]} of ±{plan.radius:g} ({config.coverage} rule)"
    timings["total"] = time.perf_counter() - t_start
    if "coarsened_from" in plan.details:
        bounds["coarsened_from"] = plan.details["coarsened_from"]
    return Certificate(axis=axis, unit=UNITS[axis], method=method, coverage=config.coverage,
                       requested_radius=float(plan.radius), status=status, certified=certified, radius=radius,
                       label=label, class_name=_label_name(model, label), p_a_lower=[float(p) for p in p_lower],
                       sigma=float(config.sigma), n0=int(config.n0), n=int(config.n if n_est is None else n_est), alpha=float(config.alpha),
                       num_bounds=len(p_lower), num_partitions=plan.num_partitions, delta_alpha=float(plan.delta_alpha),
                       frames_rendered=frames_rendered, classifier_calls=int(sc.calls), bounds=bounds, timings=timings,
                       reason=reason, seed=int(config.seed), plan=plan)


class _RendererGeometry:
    """What the adaptive anchors need of the imaging model, from the renderer (pipeline, replay,
    ``pws certify``): frames of the plan, the plan refined for the target, bounds of any grid inside
    the plan's range, hence the frontier refinement."""

    def __init__(self, renderer: SurfelRenderer, config: CertifyConfig):
        self.renderer, self.config = renderer, config
        self._bounds_of = None
        self._last = None   # the last grid bounded and its HullValues (a refinement bounds only its new segments)

    def start(self, plan: Plan) -> Plan:
        """The grid to begin with. A plan already at the grid cap leaves the refinement no room, so every
        other point is dropped (0 and both ends kept): the refinement puts points back where neighbouring
        frames differ by more than the target allows. Only the grid's tightness depends on it."""
        n = len(plan.alphas)
        if n < max(5, grid_cap(self.renderer.imaging, self.config)):
            return plan
        centre = int(np.searchsorted(plan.alphas, 0.0))
        alphas = plan.alphas[np.union1d(np.arange(centre % 2, n, 2), [0, n - 1])]
        return Plan(plan.method, plan.axis, plan.radius, float(np.diff(alphas).max()), len(alphas), alphas, plan.unit,
                    dict(plan.details, thinned_from=n))

    def frames(self, plan: Plan) -> np.ndarray:
        return self.renderer.render_batch(plan.alphas).cpu().numpy()

    def refine(self, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
               keep: tuple[float, float] | None = None, share: float = 1.0) -> tuple[Plan, np.ndarray]:
        return refine_for_target(self.renderer, plan, frames, target, max_anchors, self.config, keep=keep, share=share)

    def bounds(self, plan: Plan):
        # one sweep over the plan's range bounds its grid here, the new segments of a refinement of it (the
        # bounds of a segment depend on its ends only) and, later, the frontier's finer segments
        g = plan.alphas
        if self._last is None or (self._last[0][0], self._last[0][-1]) != (g[0], g[-1]):
            self._bounds_of = hulls_within(self.renderer, float(g[0]), float(g[-1]), max_bytes=bounds_bytes(self.config))
            self._last = (g, self._bounds_of(g))
        elif not np.array_equal(self._last[0], g):
            self._last = (g, refined_hulls(self._bounds_of, *self._last, g))
        return self._last[1]

    def frontier(self, anchor_frames: np.ndarray, R: np.ndarray, alphas: np.ndarray, covered: np.ndarray,
                 centre: int) -> tuple[float, list[float]]:
        return frontier_reach(segment_covers(self._bounds_of, anchor_frames, R), alphas, covered, centre,
                              rounds=int(self.config.frontier_rounds))


class _FixedGeometry:
    """The same from frames and bounds received for a fixed grid (the four-process certifier; the planner
    refined the grid for the largest possible target, :func:`anchor_grid`): nothing is refined further,
    and a covered run that stops inside a segment stops at its grid point (no frontier refinement)."""

    def __init__(self, frames: np.ndarray, hulls):
        self._frames, self._hulls = frames, hulls

    def frames(self, plan: Plan) -> np.ndarray:
        return self._frames

    def start(self, plan: Plan) -> Plan:
        return plan

    def refine(self, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
               keep: tuple[float, float] | None = None, share: float = 1.0) -> tuple[Plan, np.ndarray]:
        return plan, frames

    def bounds(self, plan: Plan):
        return self._hulls

    frontier = None


def grid_cap(imaging: Imaging, config: CertifyConfig) -> int:
    """The most grid points a refined plan may have: ``max_partitions``, and as many frames and segment
    bounds as the memory ceiling holds (:func:`bounds_bytes`)."""
    return min(int(config.max_partitions), int(bounds_bytes(config) // max(1, segment_bytes(imaging))))


def refine_for_target(renderer: SurfelRenderer, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
                      config: CertifyConfig, reserve: int = 0, keep: tuple[float, float] | None = None,
                      share: float = 1.0) -> tuple[Plan, np.ndarray]:
    """The plan refined where consecutive frames differ by more than ``target / REFINE_FRACTION``
    (:func:`.anchors.refine_plan`), and its frames (only the new poses rendered). Anchors cover about 2
    target radii of rendered path each: no refinement farther than the budget reaches; the refined grid
    stays within :func:`grid_cap` less ``reserve`` points (never below the plan's own size) and adds at
    most ``share`` of the room that leaves. One round; :func:`_certify_anchored` asks for more where the
    anchors fall short."""
    coarse = plan
    room = max(0, grid_cap(renderer.imaging, config) - int(reserve) - len(frames))
    plan = refine_plan(plan, frames, target / REFINE_FRACTION, len(frames) + int(share * room),
                       reach=(max_anchors + 1) * target, keep=keep)
    if len(plan.alphas) != len(frames):  # render only the new poses
        old = np.searchsorted(plan.alphas, coarse.alphas)
        new = np.setdiff1d(np.arange(len(plan.alphas)), old)
        full = np.empty((len(plan.alphas),) + frames.shape[1:], dtype=frames.dtype)
        full[old] = frames
        full[new] = renderer.render_batch(plan.alphas[new]).cpu().numpy()
        frames = full
    return plan, frames


def refined_hulls(bounds_of, old_grid: np.ndarray, old, grid: np.ndarray):
    """The HullValues of ``grid`` from those of ``old_grid`` (``old``): a segment of ``grid`` that is a segment
    of ``old_grid`` keeps its bounds (they depend on its two ends only); the runs of new segments are bounded
    by ``bounds_of`` (:func:`.imaging.hulls_within` over the same range)."""
    S = len(grid) - 1
    i = np.searchsorted(old_grid, grid[:-1])
    ok = i < len(old_grid) - 1
    kept = np.zeros(S, bool)
    kept[ok] = (old_grid[i[ok]] == grid[:-1][ok]) & (old_grid[i[ok] + 1] == grid[1:][ok])
    lo = np.empty((S,) + old.lo.shape[1:], old.lo.dtype)
    hi = np.empty_like(lo)
    constant = np.empty((S,) + old.constant.shape[1:], bool)
    lo[kept], hi[kept], constant[kept] = old.lo[i[kept]], old.hi[i[kept]], old.constant[i[kept]]
    new = np.flatnonzero(~kept)
    if len(new):
        starts = new[np.r_[True, np.diff(new) > 1]]
        ends = new[np.r_[np.diff(new) > 1, True]] + 1
        for s, e in zip(starts, ends):
            part = bounds_of(grid[s:e + 1])
            lo[s:e], hi[s:e], constant[s:e] = part.lo, part.hi, part.constant
    return HullValues(grid, lo, hi, constant, dict(old.details, segments=S))


def _planned(k0: int, config: CertifyConfig) -> tuple[Callable[[int], Looks], int, Callable[[int], float]]:
    """The plans of :func:`placement` before its weak-frame fallback."""
    n0, n, sigma, alpha = int(config.n0), int(config.n), float(config.sigma), float(config.alpha)
    budget = int(config.num_anchors) * n

    def individual(k: int) -> float:
        return target_radius(int(k0), n0, n, sigma, alpha, int(k))

    def fixed(k: int) -> Looks:
        return single(n)

    if int(config.n_first) <= 0:
        return fixed, int(config.num_anchors), individual
    most = max(1, budget // min(int(config.n_first), n))

    def looks_of(k: int) -> Looks:
        return joint_looks(max(1, budget // max(1, int(k))), n)

    def joint(k: int) -> float:
        looks = looks_of(k)
        m = int(looks.sizes[0])
        return predicted_target(int(np.floor(m * joint_rate(int(k0), n0, int(k)))), m, sigma, looks.level(0, alpha, int(k)))

    m_most = int(looks_of(most).sizes[0])
    if joint(most) / m_most >= individual(int(config.num_anchors)) / n:
        return looks_of, most, joint
    return fixed, int(config.num_anchors), individual


def placement(k0: int, config: CertifyConfig) -> tuple[Callable[[int], Looks], int, Callable[[int], float]]:
    """``(looks_of, most anchors, target_of)`` of the adaptive anchors after ``k0`` of the ``n0`` selection
    votes went to the top class (:mod:`.sequential`), fixed before any estimation sample is drawn:

    * where the selection predicts that the anchors will keep the label together (:func:`.sequential.joint_rate`),
      the joint plan: ``K`` anchors share the estimation budget ``num_anchors * n`` in a joint first look of
      ``m = num_anchors * n // K`` samples each (at least ``n_first``: up to ``num_anchors * n // n_first``
      anchors), then, where ``m < n``, an individual look of ``n`` for the anchors it leaves short;
    * else one individual look of ``n`` samples for at most ``num_anchors`` anchors (``n_first`` 0: always).

    The one with the larger target per sample at the most anchors is chosen. ``looks_of(K)``: the looks of
    ``K`` anchors; ``target_of(K)``: the Cohen radius the selection predicts for one of them at the first
    look (:func:`.anchors.target_radius`; a planning value). Fewer anchors get more samples each, hence a
    larger target: a placement stopped by a segment no grid frame covers at the target of many anchors
    tries fewer (:func:`.anchors.best_placement`).

    Where even that predicts no radius at the most anchors' level (a weak frame), the centre alone (level
    alpha) gets the whole estimation budget in one look: it may still certify a small radius. Its samples
    come n at a time and the axis stops as soon as they make a bound above 1/2 all but impossible
    (:func:`.sequential.futile`)."""
    looks_of, most, target_of = _planned(k0, config)
    if target_of(most) > 0 or most <= 1:
        return looks_of, most, target_of
    budget = int(config.num_anchors) * int(config.n)

    def centre_alone(k: int) -> float:
        return target_radius(int(k0), int(config.n0), budget, config.sigma, config.alpha, int(k))

    return (lambda k: single(budget)), 1, centre_alone


def largest_target(config: CertifyConfig) -> tuple[float, int]:
    """The target radius of the adaptive anchors when every selection sample votes for one class (the
    largest any selection can give; it needs no classifier), and the most anchors then (:func:`placement`)."""
    _, most, target_of = _planned(int(config.n0), config)
    return target_of(most), most


def anchor_grid(cloud: Cloud, imaging: Imaging, plan: Plan, config: CertifyConfig) -> Plan:
    """The grid the four-process mode renders for the certifier's adaptive anchors: ``plan`` refined
    (:func:`refine_for_target`) for :func:`largest_target`. The planner node has no classifier, so it
    cannot refine for the target the selection samples will give, as the pipeline does: with a smaller
    target its segments are coarser than the pipeline's (looser bounds: a smaller radius, never a wrong
    one). The certifier cannot refine the frontier either (no renderer), so the first segment on each side
    of 0 gets the points the frontier refinement would reach there, at ``FRONTIER_PARTS^-k`` of its length
    (``k = 1 .. FRONTIER_ROUNDS``; the refinement leaves room for them within :func:`grid_cap`, and where
    the plan itself fills the cap as many as fit are added, the coarsest first): a weak frame's covered
    run, which stops near 0, then ends at one of them instead of at 0. The grid is fixed before any noise
    is drawn, from the cloud and the configuration only (a planner configured differently from the
    certifier only changes how tight the bounds are). Other imaging or coverage: ``plan`` itself.
    ``config``: the axis' (its per-axis ``alpha``, as the certifier will use)."""
    config = config.validate()
    if imaging.kind != "surfel" or config.coverage != "anchors":
        return plan
    target, most = largest_target(config)
    if target <= 0:
        return plan
    renderer = make_renderer(cloud, imaging, plan.axis, device=config.device,
                             alpha_range=(float(plan.alphas[0]), float(plan.alphas[-1])))
    frames = renderer.render_batch(plan.alphas).cpu().numpy()
    near_points = 2 * FRONTIER_ROUNDS
    plan = refine_for_target(renderer, plan, frames, target, most, config, reserve=near_points)[0]
    # the points near 0, coarsest first, as many as the cap leaves room for
    a = plan.alphas
    c = int(np.searchsorted(a, 0.0))
    room = grid_cap(imaging, config) - len(a)
    near = [float(a[j]) * FRONTIER_PARTS ** -k for k in range(1, FRONTIER_ROUNDS + 1) for j in (c - 1, c + 1) if 0 <= j < len(a)]
    near = near[:max(0, room)]
    if not near:
        return plan
    alphas = np.union1d(a, np.asarray(near, dtype=np.float64))
    return Plan(plan.method, plan.axis, plan.radius, float(np.diff(alphas).max()), len(alphas), alphas, plan.unit,
                dict(plan.details, near_centre_points=int(len(alphas) - len(a))))


def _certify_anchored(geometry, plan: Plan, rule: AdaptiveAnchorsRule, model: LoadedModel,
                      config: CertifyConfig, denoiser,
                      progress, method: str, timings: dict[str, float], t_start: float) -> Certificate:
    """Anchors from the distance profile (:mod:`.anchors`): the selection samples at alpha = 0 predict a target
    radius; the grid is refined where consecutive frames differ by more than a fraction of it; anchors are
    placed so that every segment lies within the target of one (sound bounds of :func:`.imaging.segment_hulls`);
    then p_A is estimated at those anchors only (Bonferroni over them) and segment ``i`` is covered by any
    anchor ``a`` with ``D_i(x_a) < R_a``. ``geometry``: :class:`_RendererGeometry` (refines the grid and the
    frontier) or :class:`_FixedGeometry` (frames and bounds received, nothing refined)."""
    sc = SmoothedClassifier(model, config.sigma, batch_size=config.batch_size, seed=config.seed, denoiser=denoiser)
    budget_samples = int(config.num_anchors) * int(config.n)    # the estimation budget of the axis
    total_work = config.n0 + budget_samples
    t0 = time.perf_counter()
    plan = geometry.start(plan)
    frames = geometry.frames(plan)
    t_render = timings.get("render", 0.0) + time.perf_counter() - t0
    zero = int(np.searchsorted(plan.alphas, 0.0))  # the selection frame: alpha = 0 is on every grid
    require(zero < len(plan.alphas) and plan.alphas[zero] == 0.0, "plan grid lacks alpha = 0")
    counts0 = sc.sample_counts(torch.as_tensor(frames[zero:zero + 1]), int(config.n0))
    label = int(torch.argmax(counts0[0]).item())
    if progress is not None:
        progress(config.n0, total_work)
    looks_of, max_anchors, target_of = placement(int(counts0[0, label]), config)
    target = target_of(max_anchors)
    t0 = time.perf_counter()
    if target > 0:
        plan, frames = geometry.refine(plan, frames, target, max_anchors, share=FIRST_ROUND_SHARE)
    t_render += time.perf_counter() - t0
    t_stats = 0.0

    def row(jj: int, i0: int = 0, i1: int | None = None) -> np.ndarray:
        return hulls.dist_sq(frames[jj], slice(i0, i1))

    # Anchors on the refined grid; where they cannot cover the requested radius at the target, the grid is
    # refined REFINE_ROUNDS - 1 rounds more (each on the frames the last one rendered; only the new segments
    # are bounded) and the anchors placed again: on a real camera frame many small pixel changes add up, so
    # the end frames of a split segment stay far apart (distance grows like the square root of the motion;
    # RealSense frame, a constant classifier at 160x90, ry: one round 5% of the requested radius, two 54%, three 66%;
    # two rounds keep every axis within 5 s there: tz 3.8 s instead of 5.2 s, demo frame 6 5.9 s instead of 8.1 s).
    # A frame covered after one round pays for no more. Only the bounds and the selection samples are used:
    # the anchors are fixed before any estimation sample is drawn.
    # Of the two placements the one whose anchors would cover more (each at the Cohen radius the selection
    # predicts at its own Bonferroni level alpha / K: more anchors, each a little weaker) is kept.
    best = None
    for attempt in (1, 2):
        t0 = time.perf_counter()
        hulls = geometry.bounds(plan)
        timings = dict(timings, bounds=timings.get("bounds", 0.0) + time.perf_counter() - t0)
        t1 = time.perf_counter()
        centre = int(np.searchsorted(plan.alphas, 0.0))
        anchor_rows: dict[int, np.ndarray] = {}
        est_idx = rule.place(row, plan.alphas, centre, target, rows_out=anchor_rows)
        predicted = rule.predicted_reach(anchor_rows, est_idx, plan.alphas, centre, target_of(len(est_idx)))
        chosen = (predicted, est_idx, anchor_rows, max_anchors)
        if 0 < target and predicted < plan.radius:
            # the budget is an upper bound: a smaller one (a larger target, a level of fewer anchors) may reach
            # farther on this grid (:func:`.anchors.best_placement`; bounds and selection samples only)
            chosen = best_placement(rule, row, plan.alphas, centre, max_anchors, target_of, plan.radius,
                                    first=(est_idx, anchor_rows))
        if best is None or chosen[0] >= best[0]:   # a tie: the refined grid (finer segments, tighter bounds)
            best = (chosen[0], plan, frames, hulls, centre, chosen[1], chosen[2], chosen[3])
        t_stats += time.perf_counter() - t1
        if target <= 0 or attempt == 2 or predicted >= plan.radius:
            break
        t0 = time.perf_counter()
        finer, finer_frames = plan, frames
        keep = None
        if len(est_idx) < max_anchors:
            # the placement stopped at a segment no grid frame nearby covers, with anchors to spare: the run it
            # covers stays as it is and only the grid beyond it is refined (its anchors keep covering it)
            D2 = np.stack([anchor_rows[int(a)] for a in est_idx])
            keep = covered_run(rule.radius(np.full(len(est_idx), target), D2, plan.alphas, centre)[1], plan.alphas, centre)
        for _ in range(REFINE_ROUNDS - 1):
            finer, finer_frames = geometry.refine(finer, finer_frames, target, max_anchors, keep=keep)
        t_render += time.perf_counter() - t0
        if len(finer.alphas) == len(plan.alphas):
            break
        plan, frames = finer, finer_frames
    predicted, plan, frames, hulls, centre, est_idx, anchor_rows, budget = best
    N = plan.num_partitions
    K = len(est_idx)
    # the looks, from the bounds and the selection samples only, before any estimation draw: the budget the
    # anchors were placed for where they cover the request at its target; else (short of it) the K anchors
    # placed share the whole estimation budget (a larger look each: joint plan, .sequential)
    covers_request = rule.predicted_reach(anchor_rows, est_idx, plan.alphas, centre, target_of(budget)) >= plan.radius
    looks = looks_of(budget if covers_request else K)
    spread = bool(config.spread_estimation) and 0 < K and predicted < plan.radius
    if spread and budget_samples // K > looks.last:
        # the samples the axis was sized for go to the anchors there are (one look of num_anchors * n // K
        # samples each, joint where the plan's first look was, the same K): CertifyConfig.spread_estimation
        looks = Looks((budget_samples // K,), (1.0,), looks.joint)
    D2 = np.stack([anchor_rows[int(a)] for a in est_idx])
    planned = target_of(budget if covers_request else K)   # the radius each anchor is planned to get

    def votes_of(idx: np.ndarray, m: int) -> np.ndarray:
        # the anchors of a call share their noise draws (common random numbers: each bound holds, Bonferroni
        # needs no independence between them, and the joint look needs them: SmoothedClassifier.common_votes)
        return sc.common_votes(torch.as_tensor(frames[est_idx[idx]]), int(m), label).numpy()

    def go_on(p: np.ndarray) -> np.ndarray:
        # an anchor whose bound falls short of the radius it was placed for, while the anchors do not yet cover
        # what the placement predicted (or the request): a decision from the samples seen so far (.sequential)
        R_now = cohen_radii(p, config.sigma)
        if rule.radius(R_now, D2, plan.alphas, centre)[0] >= min(float(predicted), float(plan.radius)):
            return np.zeros(K, bool)
        return R_now < planned

    # the estimation (.sequential.estimate): a joint first look or the centre first, then looks for the anchors
    # left short, the risk split over every look
    est = estimate(votes_of, K, looks, config.alpha, go_on, budget=max(budget_samples, K * looks.sizes[0]), chunk=int(config.n))
    p_lower, used = est.p_lower, est.samples
    if progress is not None:
        progress(total_work, total_work)
    t1 = time.perf_counter()
    R = cohen_radii(p_lower, config.sigma)
    reach, covered = rule.radius(R, D2, plan.alphas, centre)   # the placed anchors: a fixed set (module doc of .anchors)
    t_stats += time.perf_counter() - t1
    splits: list[float] = []
    if reach < plan.radius and R[0] > 0 and geometry.frontier is not None:
        # the covered run stops inside a grid segment: refine it with the radii now known (frontier_reach)
        t0 = time.perf_counter()
        reach, splits = geometry.frontier(frames[est_idx], R, plan.alphas, covered, centre)
        timings = dict(timings, bounds=timings.get("bounds", 0.0) + time.perf_counter() - t0)
    t1 = time.perf_counter()
    steps = np.sqrt(np.sum((frames[1:].astype(np.float64) - frames[:-1]) ** 2, axis=(1, 2, 3)))
    half = (plan.alphas[:-1] >= -reach) & (plan.alphas[1:] <= reach)
    bounds: dict[str, Any] = {
        "anchors": [float(plan.alphas[a]) for a in est_idx], "target_radius": float(target),
        "R_min": float(R.min()), "R_centre": float(R[0]), "segments_covered": int(covered.sum()),
        "max_anchor_dist": float(np.sqrt(D2.min(axis=0).max())) if D2.size else 0.0,
        # the rendered path over the covered range / (2 R): an estimate of the anchors needed, not a bound (a
        # flickering path can be long inside one ball); packing_anchor_bound is one (packing_bound)
        "path_length": float(steps.sum()), "path_anchor_bound": float(steps[half].sum() / (2 * max(float(R.max()), 1e-12))),
        "packing_anchor_bound": packing_bound(frames[(plan.alphas >= -reach) & (plan.alphas <= reach)], float(R.max())),
        "frontier_splits": len(splits), "spread_estimation": spread, "placement_budget": int(budget),
        # what each bound rests on: its votes for the label of its samples, at the level of the look it stopped
        # at (alpha * share / K; the largest of its looks' bounds): core.sequential
        "looks": looks.to_dict(), **est.to_dict(),
    }
    if splits:
        # the grid the certificate rests on holds the refinement points (self-audits check their segments)
        alphas = np.union1d(plan.alphas, np.asarray(splits, dtype=np.float64))
        plan = Plan(plan.method, plan.axis, plan.radius, float(np.diff(alphas).max()), len(alphas), alphas, plan.unit,
                    dict(plan.details, frontier_splits=len(splits)))
        centre = int(np.searchsorted(plan.alphas, 0.0))
    t_stats += time.perf_counter() - t1
    timings = dict(timings)
    timings.update(render=t_render, inference=sc.inference_seconds, statistics=t_stats)
    cert = _conclude(plan, centre, reach, {centre: 0}, p_lower, R, label, model, config,
                     method, sc, bounds, timings, t_start, frames_rendered=N, n_est=int(used.max()) if K else 0)
    if est.futile:
        cert.reason = (f"stopped early at the original pose: {int(est.votes[0])} of {int(used[0])} noise samples for the "
                       f"label, too few for a p_A bound above 0.5 even at all {looks.last} (futility stop; no bound claimed)")
    return cert

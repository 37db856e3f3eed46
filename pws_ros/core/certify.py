"""Certification of a smoothed classifier against one-axis camera motion (PwS, PwS-L, PwS-OF, CMS).

The method on one screen (Theorems 1-3 of the paper with the per-segment bounds of :mod:`.bounds`):

1. Plan the grid ``alpha_1 = -b < ... < alpha_N = +b`` (contains 0) with :func:`.partition.plan_partitions`.
2. Render every partition frame ``x_i`` and the sound per-segment bound ``B_i`` with
   ``|x(alpha) - x_i|^2 + |x(alpha) - x_{i+1}|^2 <= B_i`` for all ``alpha`` in segment ``i`` (holes included).
3. Selection: ``n0`` noisy samples of the original frame (``alpha = 0``) pick the label ``c_A``.
4. Estimation: ``n`` fresh noisy samples per partition frame (or per anchor) count ``c_A``;
   ``p_A^(i)`` is the one-sided Clopper-Pearson lower bound at level ``alpha / m`` (Bonferroni over the
   ``m`` bounds used) and ``R_i = sigma Phi^-1(p_A^(i))`` (0 if ``p_A^(i) <= 1/2``).
5. Coverage of segment ``i`` (any frame of it is within the Cohen radius of some estimated frame):
   * ``paper``: ``max_i sqrt(B_i / 2) < min_i R_i`` (Theorem 1 with ``B_i`` in place of ``|x_i - x_{i+1}|^2``);
   * ``pairwise``: ``B_i < R_i^2 + R_{i+1}^2``;
   * ``anchors``: some anchor ``a`` has ``D_i(x_a) < R_a`` (``p_A`` estimated at ``K`` anchors only).
6. The certified radius is the largest symmetric sub-interval ``[-alpha_j, alpha_j]`` of the grid whose
   segments are all covered; the certificate holds for ``[-b, b]`` iff it reaches ``b``.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import numpy as np
import torch

from .bounds import SegmentValues, segment_values
from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import require
from .model import LoadedModel
from .motion import UNITS, parse_axis
from .partition import DEFAULT_MAX_PARTITIONS, Plan, check_radius, plan_partitions, validate_grid
from .render import Renderer
from .result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate
from .smoothing import SmoothedClassifier, bonferroni, clopper_pearson_lower, cohen_radius

METHODS = ("pws", "pws_l", "pws_of", "cms")
COVERAGES = ("paper", "pairwise", "anchors")


@dataclass
class CertifyConfig:
    sigma: float = 0.5
    n0: int = 100
    n: int = 1000
    alpha: float = 0.01
    seed: int = 0
    device: str = "cpu"
    batch_size: int = 500
    coverage: str = "pairwise"
    num_anchors: int = 9
    background: float = 0.0
    max_partitions: int = DEFAULT_MAX_PARTITIONS
    min_partitions: int = 0
    delta: float | None = None
    cms_sigma: float | None = None
    chunk: int = 128

    def validate(self) -> "CertifyConfig":
        require(math.isfinite(self.sigma) and self.sigma > 0, f"sigma must be positive, got {self.sigma}")
        require(int(self.n0) >= 1 and int(self.n) >= 1, f"n0 and n must be >= 1, got n0={self.n0}, n={self.n}")
        require(0 < self.alpha < 1, f"alpha must lie in (0, 1), got {self.alpha}")
        require(self.coverage in COVERAGES, f"unknown coverage rule {self.coverage!r}: expected one of {', '.join(COVERAGES)}")
        require(int(self.num_anchors) >= 1, f"num_anchors must be >= 1, got {self.num_anchors}")
        require(int(self.batch_size) >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        require(int(self.min_partitions) >= 0, f"min_partitions must be >= 0, got {self.min_partitions}")
        require(math.isfinite(self.background), f"background must be finite, got {self.background}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def anchor_indices(num_partitions: int, num_anchors: int) -> np.ndarray:
    """``K`` anchors evenly spread over the grid, always including the centre (``alpha = 0``)."""
    m = num_partitions // 2
    k = max(1, min(int(num_anchors), num_partitions))
    idx = np.unique(np.round(np.linspace(0, num_partitions - 1, k)).astype(np.int64))
    return np.unique(np.concatenate([idx, [m]]))


def symmetric_reach(covered: np.ndarray, centre: int) -> int:
    """Largest ``j`` such that segments ``centre-j .. centre+j-1`` are all covered."""
    nseg = len(covered)
    j = 0
    while j < centre and centre + j < nseg and covered[centre - j - 1] and covered[centre + j]:
        j += 1
    return j


def cohen_radii(p_a_lower, sigma: float) -> np.ndarray:
    """Cohen radii ``R_i`` of the p_A lower bounds (0 where p_A <= 1/2; finite where p_A = 1)."""
    R = np.asarray(cohen_radius(np.asarray(p_a_lower, dtype=np.float64), sigma), dtype=np.float64).reshape(-1)
    return np.where(np.isfinite(R), R, np.finfo(np.float64).max)


def paper_reach(pair_bound_sq: np.ndarray, R: np.ndarray, centre: int) -> int:
    """Largest ``j`` with ``max sqrt(B / 2) < min R`` over segments ``centre-j .. centre+j-1`` and partitions
    ``centre-j .. centre+j`` (the paper's rule on each symmetric sub-interval)."""
    Mseg = np.sqrt(np.asarray(pair_bound_sq, dtype=np.float64) / 2)
    j = 0
    while j < centre and Mseg[centre - j - 1 : centre + j + 1].max() < R[centre - j - 1 : centre + j + 2].min():
        j += 1
    return j


def _label_name(model: LoadedModel, label: int) -> str:
    try:
        return model.class_names[label]
    except (IndexError, AttributeError, TypeError):
        return f"class_{label}"


def certify(cloud: Cloud, intr: CameraIntrinsics, model: LoadedModel, axis: str, radius: float, method: str = "pws_of",
            config: CertifyConfig | None = None, denoiser=None, plan: Plan | None = None,
            progress: Callable[[int, int], None] | None = None) -> Certificate:
    """Certify the smoothed prediction on ``cloud`` seen by ``intr`` for motions ``[-radius, radius]``.

    ``cloud`` is the cloud that is rendered: the entire cloud for ``pws``, the one-frame cloud for
    ``pws_of`` (``pws_l`` uses what it is given). ``method='cms'`` runs the CMS baseline.
    """
    config = (config or CertifyConfig()).validate()
    axis = parse_axis(axis)
    radius = check_radius(radius)
    require(method in METHODS, f"unknown method {method!r}: expected one of {', '.join(METHODS)}")
    cloud.require_nonempty()
    model.check_input_size(intr.height, intr.width, what="camera")
    if method == "cms":
        from .cms import certify_cms

        return certify_cms(cloud, intr, model, axis, radius, motion_sigma=config.cms_sigma, n0=config.n0, n=config.n,
                           alpha=config.alpha, seed=config.seed, device=config.device, batch_size=config.batch_size,
                           background=config.background, progress=progress)
    t_start = time.perf_counter()
    if plan is None:
        plan = plan_partitions(cloud, intr, axis, radius, method, delta=config.delta, max_partitions=config.max_partitions,
                               min_partitions=int(config.min_partitions))
    else:
        require(plan.axis == axis, f"plan is for axis {plan.axis}, not {axis}")
        require(abs(plan.radius - radius) <= 1e-12 * radius, f"plan is for radius {plan.radius:g}, not {radius:g}")
        validate_grid(plan.alphas, plan.radius)
    t_plan = time.perf_counter() - t_start
    t0 = time.perf_counter()
    values = segment_values(cloud, intr, axis, plan.alphas, config.background)
    renderer = Renderer(cloud, intr, axis, background=config.background, device=config.device)
    t_render = time.perf_counter() - t0
    return _certify_stream(renderer, plan, values, model, config, denoiser, progress, method,
                           {"plan": t_plan, "render": t_render}, t_start)


def certify_rendered(rendered, model: LoadedModel, config: CertifyConfig | None = None, denoiser=None,
                     progress: Callable[[int, int], None] | None = None) -> Certificate:
    """Certify from an already rendered plan (:class:`.bounds.RenderedPlan`), e.g. frames that crossed
    topics between the projector and certifier nodes."""
    config = (config or CertifyConfig()).validate()
    t_start = time.perf_counter()
    frames = rendered.frames
    require(frames.shape[0] == rendered.plan.num_partitions,
            f"{frames.shape[0]} frames for a plan of {rendered.plan.num_partitions} partitions: refusing to certify an incomplete partition set")
    model.check_input_size(int(frames.shape[1]), int(frames.shape[2]), what="frame")

    class _Given:
        def iter_frames(self, alphas, chunk=None):
            step = int(chunk or 128)
            for s in range(0, len(alphas), step):
                yield s, frames[s : s + step]

        def render_batch(self, alphas):
            idx = np.searchsorted(rendered.plan.alphas, np.asarray(alphas))
            return frames[torch.as_tensor(idx)]

    return _certify_stream(_Given(), rendered.plan, rendered.values, model, config, denoiser, progress,
                           rendered.plan.method, {"plan": 0.0, "render": 0.0}, t_start)


def _certify_stream(renderer, plan: Plan, values: SegmentValues, model: LoadedModel, config: CertifyConfig, denoiser,
                    progress, method: str, timings: dict[str, float], t_start: float) -> Certificate:
    axis, N = plan.axis, plan.num_partitions
    centre = int(np.searchsorted(plan.alphas, 0.0))
    require(plan.alphas[centre] == 0.0, "plan grid lacks alpha = 0")
    sc = SmoothedClassifier(model, config.sigma, batch_size=config.batch_size, seed=config.seed, denoiser=denoiser)
    anchors = config.coverage == "anchors"
    est_idx = anchor_indices(N, config.num_anchors) if anchors else np.arange(N)
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
    x0 = renderer.render_batch(np.array([0.0]))
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
        anchor_frames = renderer.render_batch(plan.alphas[est_idx]).cpu().numpy()
        t_render += time.perf_counter() - t0
        D2 = np.zeros((m_bounds, N - 1))
        c = sc.sample_counts(torch.as_tensor(anchor_frames), int(config.n))
        k_est[:] = c[:, label].numpy()
        tick(m_bounds * config.n)
    prev = None
    it = renderer.iter_frames(plan.alphas, chunk=config.chunk)
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
    if config.coverage == "paper":
        j = paper_reach(B, R, centre)
        covered_count = 2 * j
    elif config.coverage == "pairwise":
        covered = B < R[:-1] ** 2 + R[1:] ** 2
        j = symmetric_reach(covered, centre)
        covered_count = int(covered.sum())
    else:
        covered = np.any(D2 < (R[:, None] ** 2), axis=0)
        j = symmetric_reach(covered, centre)
        covered_count = int(covered.sum())
    bounds["segments_covered"] = covered_count
    centre_ok = (R[est_pos[centre]] > 0) if centre in est_pos else False
    radius = float(plan.alphas[centre + j]) if centre_ok else 0.0
    certified = bool(centre_ok and j == centre)
    if not centre_ok:
        status, reason = STATUS_ABSTAIN, f"p_A lower bound at the original pose is {p_lower[est_pos[centre]]:.4f} <= 0.5"
    elif certified:
        status, reason = STATUS_CERTIFIED, ""
    else:
        status = STATUS_NOT_CERTIFIED
        reason = f"covered up to ±{radius:g} {UNITS[axis]} of ±{plan.radius:g} ({config.coverage} rule)"
    t_stats += time.perf_counter() - t1
    timings = dict(timings)
    timings.update(render=t_render, inference=sc.inference_seconds, statistics=t_stats,
                   total=time.perf_counter() - t_start)
    return Certificate(axis=axis, unit=UNITS[axis], method=method, coverage=config.coverage,
                       requested_radius=float(plan.radius), status=status, certified=certified, radius=radius,
                       label=label, class_name=_label_name(model, label), p_a_lower=[float(p) for p in p_lower],
                       sigma=float(config.sigma), n0=int(config.n0), n=n, alpha=float(config.alpha), num_bounds=m_bounds,
                       num_partitions=N, delta_alpha=float(plan.delta_alpha), frames_rendered=N + 1 + (m_bounds if anchors else 0),
                       classifier_calls=int(sc.calls), bounds=bounds, timings=timings, reason=reason, seed=int(config.seed))

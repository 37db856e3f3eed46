"""The anchors' path of a certificate (``coverage: anchors``; docs/certificate.md, step 5): the grid
refined for the target radius the selection samples predict (:mod:`.anchor_geometry`: :func:`refine_for_target`,
within :func:`grid_cap`; only new segments bounded, :func:`refined_hulls`), the placement of the anchors and its
plan of looks (:func:`placement`; :func:`largest_target` and :func:`anchor_grid` for the four-process
planner), and their estimation in looks (:func:`_certify_anchored`). The placement itself is
:mod:`.anchors`, the looks :mod:`.sequential`; :mod:`.certify` dispatches here and re-exports these names."""
from __future__ import annotations

import functools
import time
from typing import Any, Callable

import numpy as np
import torch

from .anchor_geometry import grid_cap, refine_for_target
from .anchors import FIRST_ROUND_SHARE, REFINE_ROUNDS, best_placement, planned_votes, predicted_target, target_radius
from .certify_common import CertifyConfig, _conclude
from .cloud import Cloud
from .coverage import FRONTIER_PARTS, FRONTIER_ROUNDS, AdaptiveAnchorsRule, cohen_radii, covered_run, packing_bound
from .distance_rows import DistanceRows
from .errors import require
from .imaging import Imaging, make_renderer
from .model import LoadedModel
from .partition import Plan
from .result import Certificate
from .sequential import Looks, estimate, joint_looks, joint_rate, single
from .smoothing import SmoothedClassifier


@functools.lru_cache(maxsize=65536)
def _joint_target(k0: int, n0: int, m: int, k: int, n: int, sigma: float, alpha: float) -> float:
    """The target of a joint first look of ``m`` samples for ``k`` anchors (:func:`_planned`; remembered across
    frames: a planning value of integers and the configuration only)."""
    return predicted_target(planned_votes(joint_rate(k0, n0, k), m, n0), m, sigma, joint_looks(m, n).level(0, alpha, k))


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

    def target_at(m: int, k: int) -> float:
        return _joint_target(int(k0), n0, int(m), int(k), n, sigma, alpha)

    @functools.lru_cache(maxsize=None)
    def first_of(k: int) -> int:
        # the first look's size: of those the budgets of 1 .. num_anchors anchors give k anchors, the one predicting the
        # largest target (of equal ones the largest). A larger budget can always plan as a smaller one, so the target
        # of k anchors never decreases as num_anchors grows (issue 34, item 2: a full look of n samples can predict
        # less than a smaller joint look, its planned votes the 3/4 quantile of their posterior predictive)
        k = max(1, int(k))
        sizes = {min(n, max(1, j * n // k)) for j in range(1, int(config.num_anchors) + 1)}
        sizes = {m for m in sizes if m >= min(int(config.n_first), n)} | {min(n, max(1, budget // k))}
        return max(sizes, key=lambda m: (target_at(m, k), m))

    def looks_of(k: int) -> Looks:
        return joint_looks(first_of(int(k)), n)

    def joint(k: int) -> float:
        return target_at(first_of(int(k)), int(k))

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
    anchor ``a`` with ``D_i(x_a) < R_a``. ``geometry``: :class:`.anchor_geometry._RendererGeometry` (refines the grid and the
    frontier) or :class:`.anchor_geometry._FixedGeometry` (frames and bounds received, nothing refined)."""
    sc = SmoothedClassifier(model, config.sigma, batch_size=config.batch_size, seed=config.seed, denoiser=denoiser)
    budget_samples = int(config.num_anchors) * int(config.n)    # the estimation budget of the axis
    total_work = config.n0 + budget_samples
    t0 = time.perf_counter()
    plan = geometry.start(plan)
    geometry.prepare(plan)
    timings = dict(timings, bounds=timings.get("bounds", 0.0) + time.perf_counter() - t0)
    t0 = time.perf_counter()
    frames = geometry.frames(plan)
    t_render = timings.get("render", 0.0) + time.perf_counter() - t0
    zero = int(np.searchsorted(plan.alphas, 0.0))  # the selection frame: alpha = 0 is on every grid
    require(zero < len(plan.alphas) and plan.alphas[zero] == 0.0, "plan grid lacks alpha = 0")
    counts0 = sc.sample_counts(torch.as_tensor(frames[zero:zero + 1]), int(config.n0))
    label = int(torch.argmax(counts0[0]).item())
    if progress is not None:
        progress(config.n0, total_work)
    looks_of, max_anchors, target_of = placement(int(counts0[0, label]), config)
    target_of = functools.lru_cache(maxsize=None)(target_of)
    target = target_of(max_anchors)
    t1 = time.perf_counter()
    # every radius the placement compares distances with (.distance_rows: larger distances need no exact value):
    # the targets of every budget up to the most anchors, and up to the rule's own budget (the weak frame's first
    # placement), squared as Python's pow and numpy's t * t may round them, with room
    plan_sq = _plan_sq([float(target_of(k)) for k in range(1, max(int(max_anchors), int(rule.num_anchors)) + 1)])
    t_stats = time.perf_counter() - t1
    t0 = time.perf_counter()
    if target > 0:
        plan, frames = geometry.refine(plan, frames, target, max_anchors, share=FIRST_ROUND_SHARE)
    moved = geometry.pop_bounds_seconds()   # the refined grid bounded inside refine (anchor_geometry)
    t_render += time.perf_counter() - t0 - moved
    timings = dict(timings, bounds=timings.get("bounds", 0.0) + moved)

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
        dist = DistanceRows(hulls, frames, plan_sq)
        row = dist.row
        anchor_rows: dict[int, np.ndarray] = {}
        # at most the plan's anchors (a weak frame's plan: the centre alone, with the whole estimation budget)
        est_idx = rule.place(row, plan.alphas, centre, target, rows_out=anchor_rows,
                             budget=min(int(max_anchors), int(rule.num_anchors)))
        predicted = rule.predicted_reach(anchor_rows, est_idx, plan.alphas, centre, target_of(len(est_idx)))
        chosen = (predicted, est_idx, anchor_rows, max_anchors)
        if 0 < target and predicted < plan.radius:
            # the budget is an upper bound: a smaller one (a larger target, a level of fewer anchors) may reach
            # farther on this grid (:func:`.anchors.best_placement`; bounds and selection samples only)
            chosen = best_placement(rule, row, plan.alphas, centre, max_anchors, target_of, plan.radius,
                                    first=(est_idx, anchor_rows))
        if best is None or chosen[0] >= best[0]:   # a tie: the refined grid (finer segments, tighter bounds)
            best = (chosen[0], plan, frames, hulls, centre, chosen[1], chosen[2], chosen[3], dist)
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
        moved = geometry.pop_bounds_seconds()
        t_render += time.perf_counter() - t0 - moved
        timings = dict(timings, bounds=timings.get("bounds", 0.0) + moved)
        if len(finer.alphas) == len(plan.alphas):
            break
        plan, frames = finer, finer_frames
    predicted, plan, frames, hulls, centre, est_idx, anchor_rows, budget, dist = best
    N = plan.num_partitions
    K = len(est_idx)
    # the looks, from the bounds and the selection samples only, before any estimation draw: the budget the
    # anchors were placed for where they cover the request at its target; else (short of it) the K anchors
    # placed share the whole estimation budget (a larger look each: joint plan, .sequential)
    covers_request = rule.predicted_reach(anchor_rows, est_idx, plan.alphas, centre, target_of(budget)) >= plan.radius
    placed_for = budget if covers_request else K
    looks = looks_of(placed_for)
    spread = bool(config.spread_estimation) and 0 < K and predicted < plan.radius
    if spread and budget_samples // K > looks.last:
        # the samples the axis was sized for go to the anchors there are (one look of num_anchors * n // K
        # samples each, joint where the plan's first look was, the same K): CertifyConfig.spread_estimation
        looks = Looks((budget_samples // K,), (1.0,), looks.joint)
    D2 = np.stack([anchor_rows[int(a)] for a in est_idx])
    planned = target_of(placed_for)   # the radius each anchor is planned to get

    def votes_of(idx: np.ndarray, m: int) -> np.ndarray:
        # the anchors of a call share their noise draws (common random numbers: each bound holds, Bonferroni
        # needs no independence between them, and the joint look needs them: SmoothedClassifier.common_votes)
        return sc.common_votes(torch.as_tensor(frames[est_idx[idx]]), int(m), label).numpy()

    def go_on(p: np.ndarray) -> np.ndarray:
        # an anchor whose bound falls short of the radius it was placed for, while the anchors do not yet cover
        # what the placement predicted (or the request): a decision from the samples seen so far (.sequential)
        R_now = cohen_radii(p, config.sigma)
        dist.complete(D2, est_idx, _square(R_now))
        if rule.radius(R_now, D2, plan.alphas, centre)[0] >= min(float(predicted), float(plan.radius)):
            return np.zeros(K, bool)
        return R_now < planned

    # the estimation (.sequential.estimate): a joint first look or the centre first, then looks for the anchors
    # left short, the risk split over every look
    est = estimate(votes_of, K, looks, config.alpha, go_on, budget=max(budget_samples, K * looks.sizes[0]), chunk=int(config.n))
    p_lower, used = est.p_lower, est.samples
    if progress is not None:   # the images the classifier saw: the most the plan allowed, or fewer (looks not made)
        progress(int(sc.calls), int(sc.calls))
    t1 = time.perf_counter()
    R = cohen_radii(p_lower, config.sigma)
    dist.complete(D2, est_idx, _square(R))
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
        "max_anchor_dist": float(np.sqrt(dist.max_min(D2, est_idx))) if D2.size else 0.0,
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


def _plan_sq(targets: list[float]) -> float:
    """A threshold at or above every ``t^2`` of ``targets`` however it is rounded (``t ** 2`` calls C's pow,
    numpy squares an array as ``t * t``: they may differ by one unit in the last place)."""
    return max([0.0] + [max(t * t, t ** 2) for t in targets]) * (1.0 + 1e-12)


def _square(R: np.ndarray) -> float:
    """The largest ``R^2`` (inf where a radius is unbounded)."""
    r = float(np.max(R)) if len(R) else 0.0
    return r * r if r < 1e150 else float("inf")

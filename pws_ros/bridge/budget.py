"""A time budget per frame (``time_budget_s``): the work of each axis sized from measured costs.

The certifier keeps a :class:`CostModel` of this machine: what a classifier batch and an image cost
(noise, denoiser and classifier, as :class:`~pws_ros.core.smoothing.SmoothedClassifier` spends them),
what the geometry costs per grid point (rendering, the per-segment bounds, the anchor placement) and
what an axis costs whatever its size (planning, set-up). It is measured by a warm-up (the classifier at
start, the geometry on the first frame) and updated after every axis from the certificate's own
timings (the first axis of each imaging replaces the warm-up's figures, later ones are an exponential
moving average, :data:`EMA_WEIGHT`).

Before an axis runs, :func:`size_axis` turns the axis' share of the frame's budget into the sizes
that bound its work: ``n0``, ``num_anchors`` and ``n`` (at most ``n0 + num_anchors * n`` classifier
calls, whichever way the core spends them: anchors sharing their noise, or the weak-frame branch's
``num_anchors * n`` samples at the centre) and ``max_partitions`` (the grid the geometry renders and
bounds). The configured sizes are kept when they fit; otherwise all shrink together (the anchors with
the square root of the factor, n with the rest, n0 and the grid in proportion, n0 not below
:data:`MIN_N0`, n not below :func:`answer_n`, the fewest samples with which a p_A bound can exceed 1/2),
the largest that fits, found by bisection on the cost model. A frame that needs more work than fits
gets a smaller radius, never more time.

When even the least work (n0 = MIN_N0, one anchor, n = answer_n, 3 grid points) does not fit, the
geometry is coarsened (:func:`size_work`, the :class:`Level` s in order): surfel frames rendered at
render factor 1 (the classifier's input size, from binned camera pixels: far fewer rendered pixels
than the configured factor), then fewer rounds of the frontier refinement (``frontier_rounds``). When
the coarsest least work does not fit either, it runs anyway: the axis answers (a smaller radius)
flagged as over budget with the time it took; lack of time alone is never an ERROR. The start-up work
(the warm-ups that measure this machine, the batch size check) is never charged to a frame.

Under reduced sizes the engine also sets ``spread_estimation``: where fewer anchors are placed
than sized and they fall short of the radius, the ``num_anchors * n`` estimation samples go to the
anchors there are (:class:`~pws_ros.core.certify_common.CertifyConfig`), so the sized time is spent. ``n0``
only selects the label and plans the anchors: fewer selection samples never make a certificate wrong,
only its anchors less well placed.

Why the statistics stay valid: the sizes (and the imaging and frontier rounds of a coarser level) are a
function of the budget and the machine's measured timings only, fixed before the axis draws any sample,
so they are independent of the axis' noise. The bounds hold on any grid and for any imaging, and the
certificate records the imaging it used.
Clopper-Pearson and the Bonferroni split hold conditionally on them, exactly as for sizes written in
the configuration. Sampling never stops early because time runs out (a stopping rule that would look
at the counts).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any

from ..core.coverage import FRONTIER_PARTS, FRONTIER_ROUNDS

SAFETY = 0.85          # the work of an axis is sized for this fraction of its share (the cost model is an estimate)
EMA_WEIGHT = 0.3       # weight of the newest observation in the cost model's moving averages
MIN_POINTS = 3         # the smallest grid: -b, 0, +b
MIN_N0 = 8             # the fewest selection samples a budget leaves (n0 only picks the label and plans the anchors)
WARMUP_POINTS = 9      # grid points of the geometry warm-up on the first frame


def frontier_points(rounds: int = FRONTIER_ROUNDS) -> int:
    """Points the frontier refinement may add to a grid in ``rounds`` rounds a side."""
    return 2 * int(rounds) * (FRONTIER_PARTS - 1)


def answer_n(alpha: float) -> int:
    """The fewest estimation samples with which a one-sided Clopper-Pearson bound at level ``alpha`` can
    exceed 1/2 (all of them the top class: ``alpha ** (1 / n) > 1/2``); fewer can certify nothing."""
    return int(math.floor(math.log2(1.0 / min(max(float(alpha), 1e-300), 0.5)))) + 1


@dataclass
class CostModel:
    """Seconds per unit of work on this machine (NaN until measured). The geometry is kept for the
    configured imaging and, once measured (only when a budget needs it), for the coarse one (render
    factor 1, :class:`Level`)."""

    batch_s: float = math.nan    # one classifier call, whatever its size (noise buffer, launch, synchronisation)
    image_s: float = math.nan    # one image of a call (noise, denoiser, classifier)
    point_s: float = math.nan    # one grid point: its frame rendered, its segment bounded, distance rows to anchors
    fixed_s: float = math.nan    # one axis whatever its sizes (planning, renderer set-up, previews)
    updates: int = 0             # observations folded in after the warm-up
    fine_updates: int = 0        # of them, axes at the configured imaging / at the coarse one (their geometry)
    coarse_updates: int = 0
    coarse_point_s: float = math.nan   # point_s and fixed_s at the coarse imaging (render factor 1)
    coarse_fixed_s: float = math.nan

    @property
    def ready(self) -> bool:
        return all(math.isfinite(v) for v in (self.batch_s, self.image_s, self.point_s, self.fixed_s))

    def has(self, coarse: bool) -> bool:
        """The geometry of that imaging is measured."""
        return math.isfinite(self.coarse_point_s if coarse else self.point_s)

    # ---- predictions ----
    def batches(self, n0: int, anchors: int, n: int, batch_size: int) -> int:
        """The most classifier calls of an axis: the selection (``n0`` samples of one frame), then either
        ``anchors`` frames sharing ``n`` noise draws a batch at a time, or the weak-frame branch's
        ``anchors * n`` samples of the centre (fewer calls)."""
        bs = max(1, int(batch_size))
        return math.ceil(n0 / bs) + int(anchors) * math.ceil(n / bs)

    def inference_s(self, n0: int, anchors: int, n: int, batch_size: int) -> float:
        return self.batch_s * self.batches(n0, anchors, n, batch_size) + self.image_s * (n0 + anchors * n)

    def geometry_s(self, points: int, rounds: int = FRONTIER_ROUNDS, coarse: bool = False) -> float:
        return (self.coarse_point_s if coarse else self.point_s) * (int(points) + frontier_points(rounds))

    def axis_s(self, n0: int, anchors: int, n: int, points: int, batch_size: int, rounds: int = FRONTIER_ROUNDS,
               coarse: bool = False) -> float:
        fixed = self.coarse_fixed_s if coarse else self.fixed_s
        return fixed + self.inference_s(n0, anchors, n, batch_size) + self.geometry_s(points, rounds, coarse)

    # ---- measurements ----
    def set_inference(self, t_one: float, t_full: float, batch_size: int) -> None:
        """From the time of a call with 1 image and one with ``batch_size`` images."""
        bs = max(1, int(batch_size))
        image = max(0.0, (t_full - t_one) / (bs - 1)) if bs > 1 else 0.0
        if bs == 1 or image == 0.0:
            image = t_full / bs
        self.image_s = image
        self.batch_s = max(0.0, t_one - image)

    def set_geometry(self, fixed_s: float, point_s: float, coarse: bool = False) -> None:
        if coarse:
            self.coarse_fixed_s, self.coarse_point_s = max(0.0, fixed_s), max(0.0, point_s)
        else:
            self.fixed_s, self.point_s = max(0.0, fixed_s), max(0.0, point_s)

    def observe(self, cert: Any, wall_s: float, batch_size: int, coarse: bool = False) -> None:
        """Fold in one axis' certificate (its timings, calls and grid) and its wall time in the engine
        (``coarse``: made with the coarse imaging, whose geometry it updates)."""
        t = getattr(cert, "timings", None) or {}
        calls = int(getattr(cert, "classifier_calls", 0) or 0)
        if not self.ready or not self.has(coarse) or calls <= 0 or "inference" not in t:
            return
        # the first axis replaces the warm-up's figures (a few grid points and calls of a grey frame, with the
        # first-use costs in them: EfficientNet-Lite0 on the RealSense frame, axes predicted 4.2 and 6.2 s
        # took 2.7 and 2.8 s), later axes are averaged in
        w = EMA_WEIGHT if self.updates else 1.0
        n0 = int(cert.n0)
        est = calls - n0
        anchors = max(1, int(getattr(cert, "num_bounds", 0) or 0))   # the p_A bounds estimated: anchors (or frames)
        per = max(1, est // anchors) if anchors > 1 else max(1, est)
        predicted = self.inference_s(n0, anchors, per, batch_size) if est > 0 else self.inference_s(n0, 0, 1, batch_size)
        if predicted > 0 and math.isfinite(float(t["inference"])):
            r = (1 - w) + w * float(t["inference"]) / predicted
            self.batch_s *= r
            self.image_s *= r
        geometry = sum(float(t.get(k, 0.0)) for k in ("render", "bounds", "statistics"))
        points = int(getattr(cert, "frames_rendered", 0) or 0) + int((cert.bounds or {}).get("frontier_splits", 0) or 0)
        fixed = max(0.0, float(wall_s) - float(t["inference"]) - geometry)
        p_name, f_name, u_name = (("coarse_point_s", "coarse_fixed_s", "coarse_updates") if coarse
                                  else ("point_s", "fixed_s", "fine_updates"))
        w = EMA_WEIGHT if getattr(self, u_name) else 1.0
        if points > 0:
            setattr(self, p_name, (1 - w) * getattr(self, p_name) + w * geometry / points)
        setattr(self, f_name, (1 - w) * getattr(self, f_name) + w * fixed)
        setattr(self, u_name, getattr(self, u_name) + 1)
        self.updates += 1


@dataclass(frozen=True)
class Level:
    """How coarse an axis' geometry is: ``coarse``, surfel frames at render factor 1 (the classifier's
    input size, binned camera pixels) instead of the configured factor; ``rounds`` of the frontier
    refinement a side."""

    coarse: bool = False
    rounds: int = FRONTIER_ROUNDS


def levels(can_coarsen: bool) -> list[Level]:
    """The levels in the order a budget tries them: the configured geometry, render factor 1 (where it
    is coarser), then fewer frontier rounds (2, 1, none)."""
    out = [Level(False, FRONTIER_ROUNDS)] + ([Level(True, FRONTIER_ROUNDS)] if can_coarsen else [])
    return out + [Level(out[-1].coarse, r) for r in (2, 1, 0) if r < FRONTIER_ROUNDS]


@dataclass(frozen=True)
class Sizes:
    """The work of one axis under a budget."""

    n0: int
    num_anchors: int
    n: int
    max_partitions: int
    share_s: float          # the axis' share of the frame's budget
    predicted_s: float      # what the cost model predicts for these sizes (at most SAFETY * share_s when fits)
    reduced: bool           # smaller than configured
    fits: bool              # False: even the least work of the coarsest level is predicted above the share (it runs
                            # anyway, flagged as over budget)
    coarse: bool = False    # the geometry of a coarser Level: the imaging at render factor 1 ...
    frontier_rounds: int = FRONTIER_ROUNDS   # ... and these frontier rounds

    @property
    def coarsened(self) -> bool:
        return self.coarse or self.frontier_rounds < FRONTIER_ROUNDS

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def size_axis(share_s: float, costs: CostModel, *, n0: int, n: int, num_anchors: int, max_partitions: int,
              batch_size: int, per_point: bool = False, safety: float = SAFETY, min_n: int = 1,
              level: Level = Level()) -> Sizes:
    """The largest sizes (configured ones at most) whose predicted time at ``level`` is within
    ``safety * share_s``; ``fits`` False (and the least work) when none is.

    ``per_point``: p_A is estimated at every grid frame (coverage pairwise or paper), so the estimated
    frames are the grid points, not ``num_anchors``. ``min_n``: the least n (:func:`answer_n`). A
    function of the budget, the configuration and ``costs`` only (nothing about the frame's samples)."""
    target = safety * float(share_s)
    P0 = max(MIN_POINTS, int(max_partitions))
    A0, N0, S0 = max(1, int(num_anchors)), max(1, int(n)), max(1, int(n0))
    n_least = min(N0, max(1, int(min_n)))

    def at(s: float) -> tuple[int, int, int, int]:
        if s >= 1.0:
            return S0, A0, N0, P0
        p = min(P0, max(MIN_POINTS, int(math.floor(s * P0))))
        sel = min(S0, max(MIN_N0, int(math.floor(s * S0))))
        if per_point:
            return sel, A0, min(N0, max(n_least, int(math.floor(s * N0)))), p
        a = min(A0, max(1, int(math.floor(A0 * math.sqrt(s)))))
        nn = min(N0, max(n_least, int(math.floor(s * A0 * N0 / a))))
        return sel, a, nn, p

    def cost(sz: tuple[int, int, int, int]) -> float:
        return costs.axis_s(sz[0], sz[3] if per_point else sz[1], sz[2], sz[3], batch_size, level.rounds, level.coarse)

    def sizes(sz: tuple[int, int, int, int], reduced: bool, fits: bool) -> Sizes:
        return Sizes(*sz, float(share_s), cost(sz), reduced, fits, level.coarse, level.rounds)

    full = at(1.0)
    if cost(full) <= target:
        return sizes(full, False, True)
    least = at(0.0)
    if not cost(least) <= target:
        return sizes(least, True, False)
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if cost(at(mid)) <= target:
            lo = mid
        else:
            hi = mid
    sel, a, nn, p = at(lo)
    # what the shrunk geometry leaves goes to the estimation samples (n up to the configured one): where the
    # grid points cost far more than a classifier call, scaling everything together left most of the share
    # unused and too few samples for any bound above 1/2 (EfficientNet-Lite0 on the RealSense frame: 22
    # calls in 2.2 s of a 5 s share)
    top = N0
    while nn < top:
        mid = (nn + top + 1) // 2
        if cost((sel, a, mid, p)) <= target:
            nn = mid
        else:
            top = mid - 1
    return sizes((sel, a, nn, p), True, True)


def size_work(share_s: float, costs: CostModel, *, can_coarsen: bool, **conf: Any) -> Sizes:
    """The sizes at the first :func:`levels` whose least work fits ``share_s`` (a level whose imaging is not
    measured keeps the configured imaging, with its frontier rounds); where none fits, the least work of
    the coarsest level (``fits`` False: it runs anyway, over budget). ``conf``: what :func:`size_axis`
    takes besides the share and the costs."""
    out = None
    for level in levels(can_coarsen):
        out = size_axis(share_s, costs, level=level if costs.has(level.coarse) else Level(False, level.rounds), **conf)
        if out.fits:
            break
    assert out is not None
    return out


def _noisy_calls(model: Any, shape: tuple[int, int], batch_size: int, sigma: float, denoiser: Any, warm: int):
    """A :class:`~pws_ros.core.smoothing.SmoothedClassifier` of ``model`` at ``batch_size``, a grey frame of
    ``shape`` (H, W) and ``timed(k, repeats)``: the mean seconds of ``sample_counts(frame, k)``. A first
    call of ``warm`` images is made here: lazy initialisation (JIT, kernels) is not a cost per call."""
    import torch

    from ..core.smoothing import SmoothedClassifier

    sc = SmoothedClassifier(model, sigma, batch_size=int(batch_size), seed=0, denoiser=denoiser)
    frame = torch.full((1, int(shape[0]), int(shape[1]), 3), 0.5)
    sc.sample_counts(frame, int(warm))

    def timed(k: int, repeats: int) -> float:
        total = 0.0
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            sc.sample_counts(frame, k)
            total += time.perf_counter() - t0
        return total / max(1, repeats)

    return timed


def measure_inference(model: Any, shape: tuple[int, int], batch_size: int, sigma: float,
                      denoiser: Any = None, repeats: int = 2) -> tuple[float, float]:
    """(seconds of a call with 1 image, seconds of a call with ``batch_size`` images), through
    :class:`~pws_ros.core.smoothing.SmoothedClassifier` (noise + denoiser + classifier); the first call
    (lazy initialisation, JIT) is not counted, the mean of ``repeats`` is."""
    timed = _noisy_calls(model, shape, int(batch_size), sigma, denoiser, warm=1)
    return timed(1, repeats), timed(int(batch_size), repeats)


def measure_per_image(model: Any, shape: tuple[int, int], batch_sizes: tuple[int, ...], sigma: float,
                      denoiser: Any = None, images: int = 32) -> dict[int, float]:
    """Seconds per image of noisy classifier calls (as :func:`measure_inference` makes them) at each batch
    size, over the same ``images`` images (at least one full call of each size; a first full call of each
    size, which builds its kernels, is not counted)."""
    out = {}
    for bs in sorted({max(1, int(b)) for b in batch_sizes}):
        k = max(bs, int(images))
        out[bs] = _noisy_calls(model, shape, bs, sigma, denoiser, warm=bs)(k, 1) / k
    return out


__all__ = ["CostModel", "EMA_WEIGHT", "Level", "MIN_N0", "MIN_POINTS", "SAFETY", "Sizes", "WARMUP_POINTS",
           "answer_n", "frontier_points", "levels", "measure_inference", "measure_per_image", "size_axis", "size_work"]

"""How much work a frame gets: the engine's decisions on the batch size of its classifier calls and, under
a time budget (``time_budget_s``), on each axis' sizes and geometry (:class:`FrameBudget`).

The arithmetic (the cost model, the sizes that fit a share, the coarser levels) is :mod:`.budget`'s;
this module measures this machine (the warm-ups), splits a frame's budget over its axes, picks each
axis' work before it draws any sample and records what the certificate rests on. Start-up work (the
warm-ups, the batch size check) is never charged to a frame: :meth:`FrameBudget.ready` returns its
seconds and the engine leaves them out of the frame's budget and time (``FrameResult.timings["startup"]``).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict
from typing import Any, Callable

from ..core.errors import PwsError
from .budget import (FRONTIER_ROUNDS, MIN_POINTS, SAFETY, WARMUP_POINTS, CostModel, Level, Sizes, answer_n, measure_inference,
                     measure_per_image, size_axis, size_work)

LogFn = Callable[[str, str], None]   # (level: "info" | "warn" | "error", message)

BATCH_CHECK_SMALL = 4       # choose_batch_size: the small batch timed against the configured one
BATCH_CHECK_LARGEST = 32    # ... the configured one timed at most at this size (a larger call costs seconds and GB)
BATCH_CHECK_GAIN = 1.25     # ... used when the small batch is at least this much faster per image
DEMO_RENDER_PIXELS = 320 * 180   # what the shipped defaults render (640x480 camera, 160x90 model, render_factor 2)
DEMO_INPUT_PIXELS = 160 * 90
COARSE_FACTOR = 1           # the render factor of the coarse level (budget.Level.coarse)


class FrameBudget:
    """The time budget of one :class:`~pws_ros.bridge.engine.FrameCertifier` (``engine``): its cost model,
    the warm-ups that measure it, each axis' :class:`~.budget.Sizes` and the record of them."""

    def __init__(self, engine: Any):
        self.engine = engine
        self.costs = CostModel()          # what work costs on this machine
        self._batch_checked = False       # the batch size was timed against a small one (check_batch_size)

    @property
    def on(self) -> bool:
        c = self.engine.config
        return float(c.time_budget_s) > 0 and c.method != "cms"

    def check_batch_size(self, shape: tuple[int, int]) -> float:
        """Once (at start when the input size is known then, else before the first certificate): the batch
        size of the engine's classifier calls on ``shape`` inputs, from :func:`choose_batch_size`. Returns
        the seconds it took (0 when nothing was timed; start-up work)."""
        if self._batch_checked:
            return 0.0
        self._batch_checked = True
        e = self.engine
        e.batch_size, spent = choose_batch_size(e.model, shape, e.batch_size, float(e.config.sigma), device=e.device,
                                                denoiser=e.denoiser, log=e.log)
        return spent

    # ---- warm-ups (start-up work: never charged to a frame) ----
    def warm_up_inference(self, shape: tuple[int, int]) -> None:
        """Measure a classifier call of 1 image and of ``batch_size`` images at input ``shape`` (H, W)."""
        e = self.engine
        t_one, t_full = measure_inference(e.model, shape, e.batch_size, float(e.config.sigma), denoiser=e.denoiser)
        self.costs.set_inference(t_one, t_full, e.batch_size)
        e.log("info", f"time budget {e.config.time_budget_s:g} s per frame: a classifier call of {e.batch_size} images takes "
                      f"{1000 * t_full:.1f} ms here ({1000 * t_one:.1f} ms for 1)")

    def warm_up_geometry(self, cloud: Any, imaging: Any, axis: str, dense_cloud: Any = None, coarse: bool = False,
                         timed: bool = True) -> None:
        """Measure planning and the geometry of a small grid (WARMUP_POINTS points) of this frame with
        ``imaging`` (``coarse``: the coarse level's, :data:`COARSE_FACTOR`); ``timed`` False: only the first,
        uncounted pass (what is paid once, lazy initialisation, for another axis)."""
        from ..core.certify import bounds_bytes
        from ..core.imaging import make_renderer, segment_bounds

        e = self.engine
        src = e.source_cloud(cloud, dense_cloud)
        for points in (MIN_POINTS, WARMUP_POINTS)[:2 if timed else 1]:   # the first pass pays what is paid once: not counted
            t0 = time.perf_counter()
            plan = e.plan_axis(src, imaging, axis, max_partitions=points)
            renderer = make_renderer(src, imaging, axis, device=e.device, alpha_range=(float(plan.alphas[0]), float(plan.alphas[-1])))
            t1 = time.perf_counter()
            renderer.render_batch(plan.alphas)
            segment_bounds(renderer, src, imaging, plan.alphas, max_bytes=bounds_bytes(e.certify_config()))
            t2 = time.perf_counter()
        if not timed:
            return
        per_point = (t2 - t1) / max(1, plan.num_partitions)
        self.costs.set_geometry(t1 - t0, per_point, coarse=coarse)
        what = f"render factor {imaging.factor}" + (" (coarse)" if coarse else "")
        e.log("info", f"time budget: planning and set-up take {1000 * (t1 - t0):.1f} ms, the geometry {1000 * per_point:.1f} "
                      f"ms per grid point at {what} (warm-up, {plan.num_partitions} points)")

    def ready(self, cloud: Any, imaging: Any, dense_cloud: Any, coarse_imaging: Callable[[], Any]) -> float:
        """The warm-ups not yet made (the classifier when its input size was unknown at start; the geometry
        on the first frame, on the first axis that plans; the coarse geometry when the least work of the
        configured one cannot fit an axis' share of the whole budget); returns their seconds (start-up)."""
        t0 = time.perf_counter()
        if not math.isfinite(self.costs.batch_s):
            self.warm_up_inference(tuple(imaging.out_shape))
        self._warm_geometry(cloud, imaging, dense_cloud, False)
        if self.can_coarsen(imaging) and not self.costs.has(True) and self.costs.ready:
            c = self.engine.config
            whole = float(c.time_budget_s) / max(1, len(c.axes))
            if not self.size(whole, imaging, coarse_ok=False).fits:
                try:
                    self._warm_geometry(cloud, coarse_imaging(), dense_cloud, True)
                except PwsError:
                    pass   # no coarse imaging for this frame: the configured one, with fewer frontier rounds
        return time.perf_counter() - t0

    def _warm_geometry(self, cloud: Any, imaging: Any, dense_cloud: Any, coarse: bool) -> None:
        """Measured on the first axis that plans; every other axis pays its own lazy initialisation here."""
        if self.costs.has(coarse):
            return
        for axis in self.engine.config.axes:
            try:
                self.warm_up_geometry(cloud, imaging, axis, dense_cloud, coarse=coarse, timed=not self.costs.has(coarse))
            except PwsError:
                continue   # an axis that cannot plan is reported by its certificate

    # ---- decisions ----
    def share(self, frame_s: float, axes_left: int) -> float:
        """The next axis' share: an even split, over the ``axes_left`` axes still to run, of
        what is left of the frame's budget after ``frame_s`` seconds of the frame's own work (its imaging and
        the axes before; start-up work is not in it). An axis that took less than its share leaves the rest
        to the axes after it; one that took more takes it from them."""
        return max(0.0, float(self.engine.config.time_budget_s) - float(frame_s)) / max(1, int(axes_left))

    @staticmethod
    def can_coarsen(imaging: Any) -> bool:
        """Surfel imaging rendering at more than :data:`COARSE_FACTOR` times the classifier's input."""
        return getattr(imaging, "kind", "") == "surfel" and int(imaging.factor) > COARSE_FACTOR

    def size(self, share_s: float, imaging: Any = None, coarse_ok: bool = True) -> Sizes:
        """The sizes and level of one axis for ``share_s`` seconds (:func:`.budget.size_work`; only the
        configured geometry without ``coarse_ok`` or an ``imaging`` that can be coarsened)."""
        c, e = self.engine.config, self.engine
        conf = dict(n0=int(c.n0), n=int(c.n), num_anchors=int(c.num_anchors), max_partitions=int(c.max_partitions),
                    batch_size=e.batch_size, per_point=c.coverage != "anchors", min_n=answer_n(c.alpha / max(1, len(c.axes))))
        if not coarse_ok:
            return size_axis(share_s, self.costs, level=Level(), **conf)
        return size_work(share_s, self.costs, can_coarsen=imaging is not None and self.can_coarsen(imaging), **conf)

    def record(self, cert: Any, sizes: Sizes, spent: float, imaging: Any) -> None:
        """What the certificate rests on under a time budget: ``bounds["time_budget"]`` (the frame's budget,
        the axis' share, the time spent, the sizes and geometry used and configured, the cost model they came
        from, whether it ran over), ``timings["budget"]`` (the share, seconds); the cost model learns from it.
        An axis over its share says so in its reason, with the time it took."""
        c = self.engine.config
        over = float(spent) > float(sizes.share_s)
        if cert.status != "error":
            self.costs.observe(cert, spent, self.engine.batch_size, coarse=sizes.coarse)
        cert.timings["budget"] = float(sizes.share_s)
        cert.bounds["time_budget"] = {
            "frame_budget_s": float(c.time_budget_s), "share_s": float(sizes.share_s), "spent_s": float(spent),
            "predicted_s": float(sizes.predicted_s), "target_s": SAFETY * float(sizes.share_s), "reduced": bool(sizes.reduced),
            "fits": bool(sizes.fits), "over_budget": over, "coarsened": bool(sizes.coarsened),
            "render_factor": int(getattr(imaging, "factor", 1)), "frontier_rounds": int(sizes.frontier_rounds),
            "n0": int(sizes.n0), "num_anchors": int(sizes.num_anchors), "n": int(sizes.n), "max_partitions": int(sizes.max_partitions),
            "configured": {"n0": int(c.n0), "num_anchors": int(c.num_anchors), "n": int(c.n), "max_partitions": int(c.max_partitions),
                           "render_factor": int(c.render_factor), "frontier_rounds": FRONTIER_ROUNDS},
            "costs": {k: float(v) for k, v in asdict(self.costs).items()},
        }
        if over and cert.status != "error":
            note = f"over budget: took {spent:.3g} s of this axis' {sizes.share_s:.3g} s share"
            if not sizes.fits:
                note += (f" (the least work, {least_text(sizes, imaging)}, was predicted at {sizes.predicted_s:.3g} s, more than the "
                         f"{SAFETY * sizes.share_s:.3g} s ({100 * SAFETY:.0f}% of the share) it is sized for)")
            cert.reason = f"{cert.reason}; {note}" if cert.reason else note


def least_text(sizes: Sizes, imaging: Any) -> str:
    """The work of ``sizes`` in words (n0, anchors, n, grid, render factor, frontier rounds)."""
    return (f"n0 = {sizes.n0}, {sizes.num_anchors} anchor{'s' if sizes.num_anchors != 1 else ''}, n = {sizes.n}, "
            f"{sizes.max_partitions} grid points, render factor {getattr(imaging, 'factor', 1)}, "
            f"{sizes.frontier_rounds} frontier rounds")


# ---- the batch size of classifier calls ----
def size_advice(imaging: Any, batch_size: int) -> list[str]:
    """Warnings for a classifier input much larger than the demo model's (bring-your-own models): the
    bounds' cost grows with the rendered pixels, a classifier call's memory with batch_size x input."""
    out = []
    h, w = imaging.out_shape
    rendered = imaging.camera.width * imaging.camera.height
    if imaging.kind == "surfel" and imaging.factor > 1 and rendered > 2 * DEMO_RENDER_PIXELS:
        out.append(f"render_factor {imaging.factor} renders {imaging.camera.width}x{imaging.camera.height} for a {w}x{h} model "
                   f"({rendered / DEMO_RENDER_PIXELS:.1f}x the pixels of the shipped defaults): the bounds take about that much "
                   f"longer; render_factor: 1 renders {w}x{h} from camera bins (measured on a 640x480 Kinect frame with a "
                   "224x224 EfficientNet-Lite0: 13-19 s per axis instead of 26-29 s)")
    if batch_size * h * w > 2 * 256 * DEMO_INPUT_PIXELS:
        out.append(f"batch_size {batch_size} of {w}x{h} inputs: one classifier call holds {batch_size * h * w * 12 / 2**20:.0f} MiB "
                   "of input and several times that in activations; on a CPU lower it (batch_size 32 with a 224x224 "
                   "EfficientNet-Lite0: peak memory 1.4 GB instead of 3.9 GB, inference 1.6x as fast)")
    return out


def choose_batch_size(model: Any, shape: tuple[int, int], batch_size: int, sigma: float, *, device: str,
                      denoiser: Any = None, log: LogFn | None = None) -> tuple[int, float]:
    """(batch size, seconds spent): on a CPU and for an input over twice the demo model's, noisy classifier
    calls of ``batch_size`` images (at most BATCH_CHECK_LARGEST) are timed against calls of BATCH_CHECK_SMALL,
    and the small ones are chosen when they are at least BATCH_CHECK_GAIN as fast per image
    (:func:`faster_batch`): a large model on a CPU often is, its activations leaving the cache. Else
    ``batch_size`` as it is, untimed. The certificates do not depend on the batch size (the noise is drawn
    one image at a time, :class:`~pws_ros.core.smoothing.SmoothedClassifier`); a smaller call only needs
    less memory. ``log(level, message)`` hears what was measured and chosen."""
    h, w = int(shape[0]), int(shape[1])
    if str(device) != "cpu" or int(batch_size) <= BATCH_CHECK_SMALL or h * w <= 2 * DEMO_INPUT_PIXELS:
        return int(batch_size), 0.0
    say = log or (lambda level, message: None)
    large = min(int(batch_size), BATCH_CHECK_LARGEST)
    t0 = time.perf_counter()
    try:
        per_image = measure_per_image(model, (h, w), (BATCH_CHECK_SMALL, large), float(sigma), denoiser=denoiser)
    except Exception as e:  # noqa: BLE001 - a check must not stop certification; the certificate reports real failures
        say("info", f"batch size check skipped: {e}")
        return int(batch_size), time.perf_counter() - t0
    spent = time.perf_counter() - t0
    timed = ", ".join(f"{1000 * t:.1f} ms per image in calls of {b}" for b, t in per_image.items())
    small = faster_batch(per_image)
    if small is None:
        say("info", f"batch size check: {timed}; batch_size {batch_size} kept ({spent:.1f} s)")
        return int(batch_size), spent
    say("info", f"batch size check: {timed}: classifier calls of {small} images from now on, "
                f"{per_image[large] / per_image[small]:.1f}x as fast per image as {large} (configured batch_size {batch_size}; "
                f"the certificates do not depend on it; batch_size: {small} skips this check; {spent:.1f} s)")
    return small, spent


def faster_batch(per_image: dict[int, float]) -> int | None:
    """The smallest batch size timed when it is at least BATCH_CHECK_GAIN as fast per image as the largest
    (``per_image``: seconds per image in calls of each size), else None."""
    small, large = min(per_image), max(per_image)
    if small >= large or per_image[small] <= 0 or per_image[large] < BATCH_CHECK_GAIN * per_image[small]:
        return None
    return small


__all__ = ["BATCH_CHECK_GAIN", "BATCH_CHECK_LARGEST", "BATCH_CHECK_SMALL", "COARSE_FACTOR", "FrameBudget", "choose_batch_size",
           "faster_batch", "least_text", "size_advice"]

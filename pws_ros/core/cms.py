"""CMS baseline: Gaussian smoothing in motion space (Hu et al. 2022, "Robustness certification of
visual perception models via camera motion smoothing").

The smoothed classifier is ``g(delta) = argmax_c P(f(render(delta + eps)) = c)`` with
``eps ~ N(0, s^2)`` a one-axis camera motion (``s = motion_sigma``, default
:data:`pws_ros.core.motion.CMS_SIGMA`), and ``f`` the base classifier applied to the *clean*
rendered frame (no pixel noise). Cohen's theorem in the one-dimensional motion space gives: if
``P(f(render(eps)) = c) >= p_A > 1/2`` then ``g(delta) = c`` for every ``|delta| < R = s Phi^-1(p_A)``.

Procedure (fixed sample sizes, one bound so Bonferroni ``m = 1``): ``n0`` motions pick the
candidate class ``c`` (most frequent clean prediction), ``n`` fresh motions count
``k = #{f = c}``, ``p_A = clopper_pearson_lower(k, n, alpha)``. ``p_A <= 1/2`` abstains (radius 0);
otherwise the certified radius is ``R`` and the requested radius is certified iff it is ``< R``.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import torch

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import require
from .model import LoadedModel
from .motion import CMS_SIGMA, UNITS, parse_axis
from .render import Renderer, resolve_device
from .result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate
from .smoothing import clopper_pearson_lower, cohen_radius


def _positive_int(value, name: str) -> int:
    require(isinstance(value, (int, np.integer)) and not isinstance(value, bool) and int(value) >= 1,
            f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _positive_float(value, name: str) -> float:
    require(isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            and math.isfinite(float(value)) and float(value) > 0, f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def certify_cms(cloud: Cloud, intr: CameraIntrinsics, model: LoadedModel, axis: str, radius: float, *,
                motion_sigma: float | None = None, n0: int = 100, n: int = 1000, alpha: float = 0.01, seed: int = 0,
                device: str | torch.device | None = "cpu", batch_size: int = 500, background: float = 0.0,
                progress: Callable[[int, int], None] | None = None, imaging=None) -> Certificate:
    """Certify ``model`` on ``cloud`` seen by ``intr`` against motion ``|alpha| <= radius`` along
    ``axis`` with the CMS baseline; see the module docstring. Raises PwsError on bad input.

    ``radius`` of the returned certificate is the certified radius ``R`` (0 on abstain), in the
    axis unit; ``certified`` is ``requested radius < R``. Motion samples come from a numpy
    generator seeded with ``seed``; frames are rendered and classified ``batch_size`` at a time.
    """
    t_start = time.perf_counter()
    axis = parse_axis(axis)
    unit = UNITS[axis]
    radius = _positive_float(radius, "radius")
    s = _positive_float(CMS_SIGMA[axis] if motion_sigma is None else motion_sigma, "motion_sigma")
    n0 = _positive_int(n0, "n0")
    n = _positive_int(n, "n")
    batch_size = _positive_int(batch_size, "batch_size")
    require(isinstance(alpha, (int, float, np.floating)) and math.isfinite(float(alpha)) and 0.0 < float(alpha) < 1.0,
            f"alpha must lie in (0, 1), got {alpha!r}")
    alpha = float(alpha)
    require(isinstance(seed, (int, np.integer)) and not isinstance(seed, bool), f"seed must be an integer, got {seed!r}")
    require(isinstance(cloud, Cloud), f"cloud must be a Cloud, got {type(cloud).__name__}")
    cloud.require_nonempty()
    require(isinstance(intr, CameraIntrinsics), f"intr must be CameraIntrinsics, got {type(intr).__name__}")
    require(callable(model), "model must be a LoadedModel")
    check = getattr(model, "check_input_size", None)
    if check is not None:
        check(*(imaging.out_shape if imaging is not None else intr.shape), what="camera image")
    require(progress is None or callable(progress), "progress must be callable(done, total)")

    dev = resolve_device(device)
    model_dev = torch.device(getattr(model, "device", "cpu"))
    if imaging is not None and imaging.kind == "surfel":  # the imaging model of core.imaging
        from .imaging import SurfelRenderer

        renderer = SurfelRenderer(cloud, imaging, axis, device=dev)
    else:
        renderer = Renderer(cloud, intr, axis, background=background, device=dev)
    rng = np.random.Generator(np.random.PCG64(int(seed)))
    select_alphas = rng.normal(0.0, s, size=n0)
    estimate_alphas = rng.normal(0.0, s, size=n)
    total = n0 + n
    timings = {"render": 0.0, "inference": 0.0, "statistics": 0.0}
    done = 0
    calls = 0

    def count_predictions(alphas: np.ndarray) -> np.ndarray:
        nonlocal done, calls
        counts = np.zeros(0, dtype=np.int64)
        for start in range(0, len(alphas), batch_size):
            t0 = time.perf_counter()
            frames = renderer.render_batch(alphas[start : start + batch_size])
            _sync(dev)
            t1 = time.perf_counter()
            x = frames.permute(0, 3, 1, 2).contiguous().to(model_dev)
            with torch.no_grad():
                pred = model(x).argmax(dim=1)
            c = max(int(model.num_classes), 1)
            batch_counts = torch.bincount(pred, minlength=c).cpu().numpy().astype(np.int64)
            t2 = time.perf_counter()
            timings["render"] += t1 - t0
            timings["inference"] += t2 - t1
            if counts.size < batch_counts.size:
                counts = np.pad(counts, (0, batch_counts.size - counts.size))
            counts[: batch_counts.size] += batch_counts
            calls += int(x.shape[0])
            done += int(x.shape[0])
            if progress is not None:
                progress(done, total)
        return counts

    select_counts = count_predictions(select_alphas)
    label = int(np.argmax(select_counts))  # lowest index on ties
    est_counts = count_predictions(estimate_alphas)
    count = int(est_counts[label]) if label < est_counts.size else 0

    t0 = time.perf_counter()
    p_a = float(clopper_pearson_lower(count, n, alpha))
    R = float(cohen_radius(p_a, s))
    timings["statistics"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start

    bounds = {"R": R, "count": count, "selection_count": int(select_counts[label]), "candidate": label,
              "motion_sigma": s}
    if p_a <= 0.5:
        status, certified, out_radius = STATUS_ABSTAIN, False, 0.0
        reason = f"p_A lower bound {p_a:.4f} <= 0.5 for candidate class {label}: abstain"
        out_label, name = -1, ""
    else:
        certified = radius < R
        status = STATUS_CERTIFIED if certified else STATUS_NOT_CERTIFIED
        out_radius = R
        reason = "" if certified else f"requested radius {radius:g} {unit} is not below the certified radius {R:.6g} {unit}"
        out_label = label
        name = model.class_name(label) if hasattr(model, "class_name") else str(label)
    return Certificate(
        axis=axis, unit=unit, method="cms", coverage="cms", requested_radius=radius, status=status,
        certified=bool(certified), radius=out_radius, label=out_label, class_name=name, p_a_lower=[p_a], sigma=s,
        n0=n0, n=n, alpha=alpha, num_bounds=1, num_partitions=0, delta_alpha=float("nan"),
        frames_rendered=total, classifier_calls=calls, bounds=bounds, timings=timings, reason=reason, seed=int(seed),
    )


__all__ = ["certify_cms"]

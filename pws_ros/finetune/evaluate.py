"""The report's measure: on held-out frames, the smoothed prediction (``n`` noisy samples at sigma,
majority vote, ties to the lower class) against the teacher's clean prediction, and p_A (the top
class's share of the samples) and p_teacher (the teacher's class's share).

Beside it, the teacher's own stability (:func:`teacher_stability`), the ceiling of that agreement: a
frame whose clean answer the teacher itself gives up under noise far below sigma (``STABILITY_SIGMA``,
about 2.5 grey levels) or under the requested motion (the cached motion views) has no answer a
smoothed classifier can be expected to reproduce; the agreement is also stated on the stable frames."""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from ..core.smoothing import clopper_pearson_lower, cohen_radius
from .cache import RecordingCache, derive

_EVAL, _STABLE = 21, 22
STABILITY_SIGMA = 0.01      # the teacher's answer under noise of ~2.5 grey levels (images in [0, 1])
STABILITY_SAMPLES = 20
STABILITY_SHARE = 0.9       # stable: that answer on >= 90% of those copies and on every motion view
QUANTILES = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)


def heldout_items(caches: list[RecordingCache], splits: list[range]) -> list[tuple[int, int]]:
    return [(ci, k) for ci, s in enumerate(splits) for k in s]


@torch.no_grad()
def smoothed_counts(model: Callable[[torch.Tensor], torch.Tensor], caches: list[RecordingCache], items: list[tuple[int, int]],
                    *, sigma: float, n: int, seed: int, batch_size: int, device: torch.device, num_classes: int,
                    progress: Callable[[int], None] | None = None) -> np.ndarray:
    """(K, C) class counts of ``n`` noisy copies of each held-out alpha = 0 frame. The noise of frame
    (recording, index) depends only on the seed and that frame: before and after see the same draws."""
    out = np.zeros((len(items), num_classes), dtype=np.int64)
    for row, (ci, k) in enumerate(items):
        c = caches[ci]
        x = torch.from_numpy(np.asarray(c.views[k, 0]).transpose(2, 0, 1).astype(np.float32) / 255.0).to(device)
        g = torch.Generator(device=device).manual_seed(derive(seed, _EVAL, ci, c.frames[k]["index"]))
        done = 0
        while done < n:
            b = min(batch_size, n - done)
            noise = torch.randn((b,) + tuple(x.shape), generator=g, device=device) * float(sigma)
            pred = model(x[None] + noise).argmax(dim=1).cpu().numpy()
            out[row] += np.bincount(pred, minlength=num_classes)[:num_classes]
            done += b
        if progress is not None:
            progress(1)
    return out


@torch.no_grad()
def teacher_stability(teacher: Callable[[torch.Tensor], torch.Tensor], caches: list[RecordingCache],
                      items: list[tuple[int, int]], teacher_top: np.ndarray, *, seed: int, device: torch.device,
                      sigma: float = STABILITY_SIGMA, samples: int = STABILITY_SAMPLES) -> dict[str, np.ndarray]:
    """Per held-out frame: the share of ``samples`` copies of the alpha = 0 frame with Gaussian noise of
    ``sigma`` on which the teacher keeps its clean answer (``noise``), the share of the cached motion
    views on which it does (``motion``; 1 when there are none), how many motion views a frame has
    (``motion_views``; 0 for a recording evaluated without them, where only the noise is tested) and
    ``stable`` (noise share >= STABILITY_SHARE and every motion view)."""
    noise_keep = np.zeros(len(items))
    motion_keep = np.ones(len(items))
    motion_views = np.zeros(len(items), dtype=np.int64)
    for row, (ci, k) in enumerate(items):
        c = caches[ci]
        x = torch.from_numpy(np.asarray(c.views[k]).transpose(0, 3, 1, 2).astype(np.float32) / 255.0).to(device)
        g = torch.Generator(device=device).manual_seed(derive(seed, _STABLE, ci, c.frames[k]["index"]))
        noisy = x[:1] + torch.randn((samples,) + tuple(x.shape[1:]), generator=g, device=device) * float(sigma)
        noise_keep[row] = float((teacher(noisy).argmax(dim=1).cpu().numpy() == teacher_top[row]).mean())
        motion_views[row] = len(x) - 1
        if len(x) > 1:
            motion_keep[row] = float((teacher(x[1:]).argmax(dim=1).cpu().numpy() == teacher_top[row]).mean())
    return {"noise": noise_keep, "motion": motion_keep, "motion_views": motion_views,
            "stable": (noise_keep >= STABILITY_SHARE) & (motion_keep >= 1.0)}


def stability_summary(stab: dict[str, np.ndarray], *, sigma: float = STABILITY_SIGMA,
                      samples: int = STABILITY_SAMPLES) -> dict[str, Any]:
    stable = stab["stable"]
    return {"sigma": float(sigma), "samples": int(samples), "stable_share_needed": STABILITY_SHARE,
            "frames": int(len(stable)), "stable_frames": int(stable.sum()),
            "stable_share": float(stable.mean()) if len(stable) else None,
            "noise_keep_mean": float(stab["noise"].mean()) if len(stable) else None,
            "motion_keep_mean": float(stab["motion"].mean()) if len(stable) else None,
            "frames_with_motion_views": int((np.asarray(stab.get("motion_views", ())) > 0).sum()),
            "meaning": (f"the teacher's clean answer kept on >= {STABILITY_SHARE:.0%} of {samples} copies with noise "
                        f"sigma {sigma:g} and on every motion view; on the other frames that little noise or the requested "
                        "motion changes the teacher's answer, so no smoothed classifier can be expected to reproduce it")}


def _quantiles(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {}
    return {f"q{int(round(q * 100)):02d}": float(np.quantile(values, q)) for q in QUANTILES}


@torch.no_grad()
def clean_predictions(model: Callable[[torch.Tensor], torch.Tensor], caches: list[RecordingCache], items: list[tuple[int, int]],
                      device: torch.device) -> np.ndarray:
    """(K,) the base classifier's class on each held-out clean alpha = 0 frame (no noise)."""
    out = np.zeros(len(items), dtype=np.int64)
    for row, (ci, k) in enumerate(items):
        x = torch.from_numpy(np.asarray(caches[ci].views[k, 0]).transpose(2, 0, 1).astype(np.float32) / 255.0).to(device)
        out[row] = int(model(x[None]).argmax(dim=1)[0])
    return out


def summarize(counts: np.ndarray, teacher: np.ndarray, truth: np.ndarray, *, sigma: float, alpha: float = 0.001,
              stable: np.ndarray | None = None, clean: np.ndarray | None = None) -> dict[str, Any]:
    """Aggregates of one model on the held-out frames (see the module doc); ``alpha``: the one-sided
    Clopper-Pearson bound of p_A behind the pixel-space Cohen radius sigma * Phi^-1(p_A lower);
    ``stable``: the frames where the teacher's answer is stable (:func:`teacher_stability`)."""
    n = counts.sum(axis=1)
    top = counts.argmax(axis=1)
    p_a = counts[np.arange(len(top)), top] / np.maximum(n, 1)
    p_teacher = counts[np.arange(len(top)), teacher] / np.maximum(n, 1)
    agree = top == teacher
    lower = np.asarray(clopper_pearson_lower(counts[np.arange(len(top)), top], n, alpha), dtype=np.float64)
    radius = np.where(lower > 0.5, np.asarray(cohen_radius(np.clip(lower, 0.5, 1.0), sigma), dtype=np.float64), 0.0)
    out: dict[str, Any] = {
        "frames": int(len(top)),
        "agreement": float(agree.mean()) if len(top) else None,
        "p_a_mean": float(p_a.mean()) if len(top) else None,
        "p_a_quantiles": _quantiles(p_a),
        "p_teacher_mean": float(p_teacher.mean()) if len(top) else None,
        "p_teacher_quantiles": _quantiles(p_teacher),
        "l2_radius_median": float(np.median(np.where(agree, radius, 0.0))) if len(top) else None,
    }
    if stable is not None:
        out["agreement_on_stable"] = float(agree[stable].mean()) if stable.any() else None
        out["stable_frames"] = int(stable.sum())
    has = truth >= 0
    if has.any():
        out["accuracy_vs_truth"] = float((top[has] == truth[has]).mean())
        if clean is not None:
            out["clean_accuracy_vs_truth"] = float((np.asarray(clean)[has] == truth[has]).mean())
        out["frames_with_truth"] = int(has.sum())
    return out


def per_frame(counts: np.ndarray, teacher: np.ndarray) -> list[dict[str, Any]]:
    n = counts.sum(axis=1)
    rows = []
    for i in range(len(counts)):
        top = int(counts[i].argmax())
        rows.append({"top": top, "p_a": float(counts[i, top] / max(1, n[i])), "p_teacher": float(counts[i, teacher[i]] / max(1, n[i])),
                     "agrees": bool(top == int(teacher[i]))})
    return rows


__all__ = ["QUANTILES", "STABILITY_SHARE", "STABILITY_SIGMA", "clean_predictions", "heldout_items", "per_frame", "smoothed_counts",
           "stability_summary", "summarize", "teacher_stability"]

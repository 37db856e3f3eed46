"""Randomized-smoothing statistics: Monte-Carlo class counts under Gaussian pixel noise and the
Clopper-Pearson / Cohen bounds built on them (after Cohen et al. 2019, locuslab/smoothing).

The method on one screen
------------------------
* Smoothed classifier ``g(x) = argmax_c P(f(x + e) = c)``, ``e ~ N(0, sigma^2 I)``, ``x`` the
  rendered float32 frame exactly as given (values in [0, 1]; no clamping, no resizing).
* Selection: ``n0`` noisy samples pick the candidate top class ``c_A`` (the argmax of the counts).
* Estimation: ``n`` *fresh* samples count ``k = #{f(x + e) = c_A}``;
  ``p_A_lower = clopper_pearson_lower(k, n, alpha')`` is a one-sided lower bound valid with
  probability ``1 - alpha'``. With ``p_B = 1 - p_A`` the certified L2 radius is
  ``sigma / 2 (Phi^-1(p_A) - Phi^-1(p_B)) = sigma Phi^-1(p_A)`` (:func:`cohen_radius`), 0 (abstain)
  when ``p_A_lower <= 1/2``.
* Here a bound's sample size is fixed (no early stopping); the anchors' estimation in several looks,
  each bound at a level fixed in advance, is :mod:`.sequential`.

Bonferroni rule: when a decision rests on ``m`` bounds (one per partition, or per anchor), every
one of them is computed at ``alpha' = bonferroni(alpha, m) = alpha / m``, so the whole decision
holds with probability at least ``1 - alpha``. ``m`` is the number of bounds actually used.
"""
from __future__ import annotations

import functools
import math
import time
from typing import Any, Callable, Iterator

import numpy as np
import torch
from scipy.special import ndtri as _ndtri   # scipy.stats.norm.ppf's own function

from .errors import require
from .model import LoadedModel


# ---- statistics ----------------------------------------------------------------------------

@functools.lru_cache(maxsize=1)
def _beta_quantile() -> Callable[..., Any]:
    """``scipy.stats.beta.ppf``'s own quantile function, ``(q, a, b)``: the ufunc it calls, from ``scipy.special``
    where this scipy keeps it there (1.14 and later do; 1.12 and earlier keep it in ``scipy.stats``), else
    ``scipy.stats.beta.ppf`` itself. The same values either way; importing ``scipy.stats`` costs about a second of
    every command's start (issue 34, item 3)."""
    from scipy.special import _ufuncs

    ufunc = getattr(_ufuncs, "_beta_ppf", None)
    if ufunc is not None:
        return ufunc
    from scipy.stats import beta

    return beta.ppf


def _beta_ppf(q: Any, a: Any, b: Any) -> np.ndarray:
    """The ``q`` quantile of ``Beta(a, b)`` for ``0 < q < 1``, ``a, b > 0`` (what ``scipy.stats.beta.ppf`` gives there)."""
    with np.errstate(over="ignore"):   # (as scipy.stats: an overflow inside the inversion is not an error)
        return np.asarray(_beta_quantile()(q, a, b), dtype=np.float64)


def _to_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _brief(x: Any) -> str:
    """A one-line description of a scalar or array argument for error messages."""
    arr = _to_numpy(x)
    if arr.ndim == 0:
        return repr(arr.item())
    return f"an array of shape {arr.shape}"


def _check_alpha(alpha: Any) -> np.ndarray:
    a = _to_numpy(alpha).astype(np.float64)
    require(bool(np.all(np.isfinite(a)) and np.all(a > 0) and np.all(a < 1)), f"alpha must lie in (0, 1), got {_brief(alpha)}")
    return a


def _check_counts(k: Any, n: Any) -> tuple[np.ndarray, np.ndarray]:
    k_arr, n_arr = _to_numpy(k), _to_numpy(n)
    for name, arr in (("k", k_arr), ("n", n_arr)):
        require(np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating),
                f"{name} must be numeric, got {arr.dtype}")
        f = arr.astype(np.float64)
        require(bool(np.all(np.isfinite(f)) and np.all(f == np.round(f))), f"{name} must be whole numbers, got {_brief(arr)}")
    k_arr, n_arr = k_arr.astype(np.int64), n_arr.astype(np.int64)
    require(bool(np.all(n_arr >= 1)), f"n must be >= 1, got {_brief(n)}")
    require(bool(np.all(k_arr >= 0) and np.all(k_arr <= n_arr)), f"counts must satisfy 0 <= k <= n, got k={_brief(k)}, n={_brief(n)}")
    return k_arr, n_arr


def _out(value: np.ndarray, *inputs: Any) -> Any:
    if all(np.ndim(_to_numpy(x)) == 0 for x in inputs):
        return float(value)
    return value


def clopper_pearson_lower(k: Any, n: Any, alpha: Any) -> Any:
    """One-sided Clopper-Pearson lower bound on a binomial proportion at confidence ``1 - alpha``.

    ``Beta.ppf(alpha, k, n - k + 1)``; 0.0 when ``k == 0``. The largest ``p`` with
    ``P(Bin(n, p) >= k) <= alpha``. Scalars give a float, arrays (broadcast) an ndarray. Integer counts
    and a float level are remembered (the anchors' plans ask for the same bounds every frame).
    """
    if _plain_int(k) and _plain_int(n) and isinstance(alpha, (float, np.floating)):
        return _cp_lower_scalar(int(k), int(n), float(alpha))
    return _cp_lower(k, n, alpha)


def _plain_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


@functools.lru_cache(maxsize=4096)
def _cp_lower_scalar(k: int, n: int, alpha: float) -> float:
    return _cp_lower(k, n, alpha)


def _cp_lower(k: Any, n: Any, alpha: Any) -> Any:
    a = _check_alpha(alpha)
    k_arr, n_arr = _check_counts(k, n)
    k_b, n_b, a_b = np.broadcast_arrays(k_arr, n_arr, a)
    safe_k = np.maximum(k_b, 1)
    lo = np.where(k_b == 0, 0.0, _beta_ppf(a_b, safe_k, n_b - k_b + 1))
    return _out(np.asarray(lo, dtype=np.float64), k, n, alpha)


def clopper_pearson_upper(k: Any, n: Any, alpha: Any) -> Any:
    """One-sided Clopper-Pearson upper bound at confidence ``1 - alpha``: ``Beta.ppf(1 - alpha,
    k + 1, n - k)``; 1.0 when ``k == n``."""
    a = _check_alpha(alpha)
    k_arr, n_arr = _check_counts(k, n)
    k_b, n_b, a_b = np.broadcast_arrays(k_arr, n_arr, a)
    safe_b = np.maximum(n_b - k_b, 1)
    hi = np.where(k_b == n_b, 1.0, _beta_ppf(1.0 - a_b, k_b + 1, safe_b))
    return _out(np.asarray(hi, dtype=np.float64), k, n, alpha)


def bonferroni(alpha: float, m: int) -> float:
    """Per-bound level ``alpha / m`` so that ``m`` bounds hold jointly with probability >= 1 - alpha."""
    require(isinstance(alpha, (int, float, np.floating, np.integer)) and math.isfinite(float(alpha)) and 0.0 < float(alpha) < 1.0,
            f"alpha must lie in (0, 1), got {alpha!r}")
    require(isinstance(m, (int, np.integer)) and not isinstance(m, bool) and int(m) >= 1,
            f"the number of bounds m must be an integer >= 1, got {m!r}")
    return float(alpha) / int(m)


def _check_num(num: Any) -> int:
    require(isinstance(num, (int, np.integer)) and not isinstance(num, bool) and int(num) >= 1,
            f"the number of noise samples must be an integer >= 1, got {num!r}")
    return int(num)


def _check_sigma(sigma: Any) -> float:
    require(isinstance(sigma, (int, float, np.floating, np.integer)) and not isinstance(sigma, bool)
            and math.isfinite(float(sigma)) and float(sigma) > 0, f"sigma must be a positive finite number, got {sigma!r}")
    return float(sigma)


def cohen_radius(p_a_lower: Any, sigma: float) -> Any:
    """Certified L2 radius ``sigma * Phi^-1(p_A)`` (= ``sigma/2 (Phi^-1(p_A) - Phi^-1(p_B))`` with
    ``p_B = 1 - p_A``); 0.0 where ``p_A <= 1/2`` (abstain), ``inf`` where ``p_A == 1``."""
    s = _check_sigma(sigma)
    p = _to_numpy(p_a_lower).astype(np.float64)
    require(bool(np.all(np.isfinite(p)) and np.all(p >= 0) and np.all(p <= 1)), f"p_a_lower must lie in [0, 1], got {_brief(p_a_lower)}")
    with np.errstate(divide="ignore"):
        r = np.where(p > 0.5, s * _ndtri(np.where(p > 0.5, p, 0.75)), 0.0)
    return _out(np.asarray(r, dtype=np.float64), p_a_lower)


def cohen_radius_two_sided(p_a_lower: Any, p_b_upper: Any, sigma: float) -> Any:
    """``sigma/2 (Phi^-1(p_A_lower) - Phi^-1(p_B_upper))``, 0 where ``p_A_lower <= p_B_upper``
    (Cohen's Theorem 1 with a separate bound on the runner-up)."""
    s = _check_sigma(sigma)
    pa = _to_numpy(p_a_lower).astype(np.float64)
    pb = _to_numpy(p_b_upper).astype(np.float64)
    for name, p in (("p_a_lower", pa), ("p_b_upper", pb)):
        require(bool(np.all(np.isfinite(p)) and np.all(p >= 0) and np.all(p <= 1)), f"{name} must lie in [0, 1]")
    with np.errstate(divide="ignore", invalid="ignore"):
        r = 0.5 * s * (_ndtri(pa) - _ndtri(pb))
    r = np.where(pa > pb, r, 0.0)
    return _out(np.asarray(r, dtype=np.float64), p_a_lower, p_b_upper)


# ---- Monte-Carlo sampling ------------------------------------------------------------------

def _frames_tensor(frames: Any, what: str = "frames") -> torch.Tensor:
    if isinstance(frames, np.ndarray):
        require(frames.dtype == np.float32, f"{what} must be float32, got {frames.dtype}")
        frames = torch.from_numpy(np.ascontiguousarray(frames))
    require(isinstance(frames, torch.Tensor), f"{what} must be a torch tensor or numpy array, got {type(frames).__name__}")
    require(frames.dtype == torch.float32, f"{what} must be float32 (values in [0, 1]), got {frames.dtype}")
    require(frames.ndim == 4 and frames.shape[3] == 3, f"{what} must have shape (B, H, W, 3), got {tuple(frames.shape)}")
    require(frames.shape[1] >= 1 and frames.shape[2] >= 1, f"{what} must have a positive size, got {tuple(frames.shape)}")
    require(bool(torch.isfinite(frames).all()), f"{what} contain NaN or inf")
    return frames


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class SmoothedClassifier:
    """Counts the base classifier's votes under Gaussian pixel noise.

    One ``torch.Generator`` on the model's device, seeded with ``seed``: the same sequence of calls gives
    identical counts, whatever the ``batch_size`` (noise images are drawn one at a time, in sample order).
    ``denoiser`` (optional, ``(B,3,H,W) -> (B,3,H,W)``) is applied after the noise and before the
    classifier (denoised smoothing).
    ``calls`` counts images classified; ``inference_seconds`` the time spent in noise, denoiser
    and classifier (device-synchronised).
    """

    def __init__(self, model: LoadedModel, sigma: float, *, batch_size: int = 500, seed: int = 0,
                 denoiser: Callable[[torch.Tensor], torch.Tensor] | None = None):
        require(callable(model), "model must be a LoadedModel (callable)")
        self.model = model
        self.sigma = _check_sigma(sigma)
        require(isinstance(batch_size, (int, np.integer)) and not isinstance(batch_size, bool) and int(batch_size) >= 1,
                f"batch_size must be an integer >= 1, got {batch_size!r}")
        self.batch_size = int(batch_size)
        require(isinstance(seed, (int, np.integer)) and not isinstance(seed, bool), f"seed must be an integer, got {seed!r}")
        self.seed = int(seed)
        self.denoiser = denoiser
        self.device = torch.device(getattr(model, "device", "cpu"))
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(self.seed)
        self.calls = 0
        self.inference_seconds = 0.0

    def reseed(self, seed: int | None = None) -> None:
        """Restart the noise stream (at ``seed``, default the constructor's)."""
        if seed is not None:
            self.seed = int(seed)
        self.generator.manual_seed(self.seed)

    # --
    def _classify(self, x: torch.Tensor, use_denoiser: bool) -> torch.Tensor:
        if use_denoiser and self.denoiser is not None:
            shape = tuple(x.shape)
            x = self.denoiser(x)
            require(isinstance(x, torch.Tensor) and tuple(x.shape) == shape,
                    f"denoiser returned shape {tuple(getattr(x, 'shape', ()))}, expected {shape}")
        logits = self.model(x)
        self.calls += int(x.shape[0])
        return logits.argmax(dim=1)

    def _check_size(self, frames: torch.Tensor) -> None:
        check = getattr(self.model, "check_input_size", None)
        if check is not None:
            check(frames.shape[1], frames.shape[2], what="frame")

    def sample_counts(self, frames: Any, num: int,
                      progress: Callable[[int, int], None] | None = None, *, common_noise: bool = False) -> torch.Tensor:
        """Votes per class: ``(B, C)`` int64 (CPU) for ``num`` noisy samples of each frame.

        ``frames`` ``(B, H, W, 3)`` float32 (torch, any device, or numpy); each sample is
        ``frame.permute(2, 0, 1) + N(0, sigma^2 I)``. Samples of consecutive frames share
        classifier batches of up to ``batch_size`` images, so memory is bounded by ``batch_size``.
        ``progress(done, total)`` is called after each batch (``total = B * num``).

        ``common_noise``: the frames share the same ``num`` noise draws (common random numbers), drawn a
        batch at a time. Each frame's count is still Binomial(``num``, its p_A), so each Clopper-Pearson
        bound holds; a Bonferroni union bound over the frames needs no independence between them. The
        noise, the costliest part after the classifier on a CPU, is then drawn once instead of B times.
        """
        num = _check_num(num)
        frames = _frames_tensor(frames)
        self._check_size(frames)
        B, H, W, _ = frames.shape
        total = B * num
        counts: torch.Tensor | None = None
        if B == 0:
            return torch.zeros((0, max(self.model.num_classes, 0)), dtype=torch.long)
        chw = frames.permute(0, 3, 1, 2)  # a view: values untouched
        if common_noise and B > 1:
            return self._common_counts(chw, num, progress)
        t0 = time.perf_counter()
        try:
            buffer = self._noise_buffer(min(total, self.batch_size), H, W)
            for start in range(0, total, self.batch_size):
                stop = min(total, start + self.batch_size)
                f0, f1 = start // num, (stop - 1) // num
                sub = chw[f0 : f1 + 1].to(self.device).contiguous()   # (channel-first in memory: the add reads it in order)
                local = torch.arange(start, stop, device=self.device) // num - f0
                noise = self._draw(buffer[: stop - start])
                if f0 == f1:
                    batch = noise.mul_(self.sigma).add_(sub[0])
                else:
                    batch = noise.mul_(self.sigma).add_(sub.index_select(0, local))
                pred = self._classify(batch, use_denoiser=True)
                if counts is None:
                    counts = self._zero_counts(B).view(-1)
                C = counts.numel() // B
                counts.index_add_(0, (local + f0) * C + pred, torch.ones_like(pred))
                if progress is not None:
                    progress(stop, total)
            _sync(self.device)
        finally:
            self.inference_seconds += time.perf_counter() - t0
        assert counts is not None
        return counts.view(B, -1).cpu()

    def _noise_buffer(self, n: int, H: int, W: int) -> torch.Tensor:
        """Room for ``n`` noise images, refilled in place batch after batch (no new allocation per batch)."""
        return torch.empty((n, 3, H, W), device=self.device, dtype=torch.float32)

    def _draw(self, noise: torch.Tensor) -> torch.Tensor:
        """Fill ``noise`` (b, 3, H, W) with N(0, 1), one image at a time: the k-th noise image of a call is
        the same whatever ``batch_size`` splits the call into, so the counts do not depend on the batch size.
        (A whole batch drawn at once depends on the batch's size: on a CPU torch draws normals 16 values at a
        time, so it equals the image-by-image draw only where 3·H·W is a multiple of 16; on a GPU not at all.)"""
        for image in noise:
            image.normal_(generator=self.generator)
        return noise

    def _zero_counts(self, B: int) -> torch.Tensor:
        """``(B, C)`` vote counters; after the first classifier call (a model may learn C from its output)."""
        C = self.model.num_classes
        require(C >= 1, f"model {getattr(self.model, 'path', '')} has no known number of classes")
        return torch.zeros((B, C), dtype=torch.long, device=self.device)

    def _common_predictions(self, chw: torch.Tensor, num: int) -> Iterator[tuple[int, int, int, torch.Tensor]]:
        """``(start, b, k, pred)``: the predictions of samples ``start .. start + b - 1`` of frame ``k``, one
        noise batch serving every frame in turn (common random numbers); time counted in ``inference_seconds``."""
        B, _, H, W = chw.shape
        t0 = time.perf_counter()
        try:
            # the frames on the device in channel-first order once (a permuted view makes every add below gather
            # strided values: twice as slow on a CPU)
            chw = chw.to(self.device).contiguous()
            buffer = self._noise_buffer(min(num, self.batch_size), H, W)
            out = torch.empty_like(buffer)
            for start in range(0, num, self.batch_size):
                b = min(self.batch_size, num - start)
                noise = self._draw(buffer[:b]).mul_(self.sigma)
                x = out[:b]
                for k in range(B):
                    torch.add(noise, chw[k], out=x)
                    yield start, b, k, self._classify(x, use_denoiser=True)
            _sync(self.device)
        finally:
            self.inference_seconds += time.perf_counter() - t0

    def _common_counts(self, chw: torch.Tensor, num: int, progress: Callable[[int, int], None] | None) -> torch.Tensor:
        """:meth:`sample_counts` with ``common_noise``: one noise batch serves every frame in turn."""
        B = chw.shape[0]
        counts: torch.Tensor | None = None
        done = 0
        for _, b, k, pred in self._common_predictions(chw, num):
            if counts is None:
                counts = self._zero_counts(B)
            C = counts.shape[1]
            require(int(pred.max()) < C, f"model output has more than the {C} classes it declares")
            counts[k] += torch.bincount(pred, minlength=C)
            done += b
            if progress is not None:
                progress(done, B * num)
        assert counts is not None
        return counts.cpu()

    def common_votes(self, frames: Any, num: int, label: int) -> torch.Tensor:
        """``(B, num)`` bool (CPU): whether each of ``num`` noisy samples of each frame is classified ``label``,
        the frames sharing their noise draws (sample ``j`` of every frame adds the same noise image), drawn as
        :meth:`sample_counts` with ``common_noise`` draws them. Column ``j`` thus tells whether every frame
        kept the label under one noise draw: the joint vote of :mod:`.sequential`."""
        num = _check_num(num)
        frames = _frames_tensor(frames)
        self._check_size(frames)
        votes = torch.zeros((frames.shape[0], num), dtype=torch.bool)
        for start, b, k, pred in self._common_predictions(frames.permute(0, 3, 1, 2), num):
            votes[k, start:start + b] = (pred == int(label)).cpu()
        return votes

    def predict(self, frames: Any, *, use_denoiser: bool = False) -> torch.Tensor:
        """Clean argmax (no noise) of the base classifier per frame: ``(B,)`` int64 (CPU).
        The denoiser is skipped unless ``use_denoiser``."""
        frames = _frames_tensor(frames)
        self._check_size(frames)
        B = frames.shape[0]
        out = []
        t0 = time.perf_counter()
        try:
            for start in range(0, B, self.batch_size):
                x = frames[start : start + self.batch_size].permute(0, 3, 1, 2).to(self.device)
                out.append(self._classify(x.contiguous(), use_denoiser=use_denoiser))
            _sync(self.device)
        finally:
            self.inference_seconds += time.perf_counter() - t0
        if not out:
            return torch.zeros(0, dtype=torch.long)
        return torch.cat(out).cpu()


def derive_seed(seed: int, stamp_ns: int, axis: str) -> int:
    """The seed of one frame and axis: a 63-bit integer drawn from ``numpy.random.SeedSequence`` of
    (seed, stamp, axis), so equal inputs give equal certificates while the noise of different frames and
    axes is independent (not the same draws reused)."""
    from .motion import AXES, parse_axis

    entropy = [int(seed) & 0xFFFFFFFFFFFFFFFF, int(stamp_ns) & 0xFFFFFFFFFFFFFFFF, AXES.index(parse_axis(axis))]
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0] >> np.uint64(1))


def top_class(counts: Any) -> int:
    """Index of the most frequent class (lowest index on ties) of a 1-D count vector."""
    c = _to_numpy(counts)
    require(c.ndim == 1 and c.size >= 1, f"counts must be a non-empty 1-D vector, got shape {c.shape}")
    return int(np.argmax(c))


__all__ = ["SmoothedClassifier", "bonferroni", "clopper_pearson_lower", "clopper_pearson_upper", "cohen_radius",
           "cohen_radius_two_sided", "top_class"]

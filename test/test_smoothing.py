from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from pws_ros.core.errors import PwsError
from pws_ros.core.model import LoadedModel, load_model
from pws_ros.core.smoothing import (SmoothedClassifier, bonferroni, clopper_pearson_lower, clopper_pearson_upper,
                                    cohen_radius, cohen_radius_two_sided, top_class)


# ---- Clopper-Pearson ---------------------------------------------------------------------

def _upper_tail(k: int, n: int, p: float) -> float:
    """P(Bin(n, p) >= k), summed exactly term by term (no scipy)."""
    return math.fsum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(k, n + 1))


def _lower_tail(k: int, n: int, p: float) -> float:
    return math.fsum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(0, k + 1))


def _bisect(f, target: float, increasing: bool) -> float:
    lo, hi = 0.0, 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if (f(mid) < target) == increasing:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def test_clopper_pearson_known_values():
    assert clopper_pearson_lower(10, 10, 0.05) == pytest.approx(0.05 ** (1 / 10), rel=1e-12)
    assert clopper_pearson_lower(0, 10, 0.05) == 0.0
    assert clopper_pearson_upper(10, 10, 0.05) == 1.0
    assert clopper_pearson_upper(0, 10, 0.05) == pytest.approx(1 - 0.05 ** (1 / 10), rel=1e-12)
    assert clopper_pearson_lower(1000, 1000, 0.001) == pytest.approx(0.001 ** (1 / 1000), rel=1e-12)
    assert isinstance(clopper_pearson_lower(3, 10, 0.05), float)


def test_clopper_pearson_and_cohen_are_scipy_stats_values_bit_for_bit():
    """The bounds and radii come from scipy.special (importing scipy.stats costs about a second of every command's
    start): they are scipy.stats' own values, bit for bit, over the sample sizes, votes and levels certificates use
    (every certificate made before the change is made again)."""
    from scipy.stats import beta

    for n in (1, 2, 7, 64, 100, 256, 1000, 1024, 6144, 6208):
        k = np.arange(n + 1)
        for alpha in (0.5, 0.01, 0.01 / 24, 0.01 / 96 / 3, 1e-6):
            safe = np.maximum(k, 1)
            want_lo = np.where(k == 0, 0.0, beta.ppf(alpha, safe, n - k + 1))
            want_hi = np.where(k == n, 1.0, beta.ppf(1 - alpha, k + 1, np.maximum(n - k, 1)))
            assert np.array_equal(clopper_pearson_lower(k, n, alpha), want_lo), (n, alpha)
            assert np.array_equal(clopper_pearson_upper(k, n, alpha), want_hi), (n, alpha)
    p = np.random.default_rng(0).uniform(0.5, 1.0, 10_000)
    assert np.array_equal(cohen_radius(p, 0.25), np.where(p > 0.5, 0.25 * norm.ppf(p), 0.0))
    pa, pb = p[:5000], 1.0 - p[5000:]
    assert np.array_equal(cohen_radius_two_sided(pa, pb, 0.5), np.where(pa > pb, 0.5 * 0.5 * (norm.ppf(pa) - norm.ppf(pb)), 0.0))


def test_a_scipy_without_the_ufunc_in_scipy_special_uses_scipy_stats(monkeypatch):
    """scipy 1.12 and earlier keep beta.ppf's function in scipy.stats only: the bounds then come from there, the same."""
    import types

    import scipy.special
    from scipy.stats import beta   # (imported first: scipy.stats keeps its own reference to the ufuncs)

    import pws_ros.core.smoothing as smoothing

    k, n = np.arange(0, 257), 256
    want = clopper_pearson_lower(k, n, 0.001)
    monkeypatch.setattr(scipy.special, "_ufuncs", types.SimpleNamespace())   # no _beta_ppf there
    smoothing._beta_quantile.cache_clear()
    try:
        assert smoothing._beta_quantile() == beta.ppf
        assert np.array_equal(clopper_pearson_lower(k, n, 0.001), want)
    finally:
        smoothing._beta_quantile.cache_clear()


@pytest.mark.parametrize("k,n,alpha", [(1, 5, 0.05), (7, 10, 0.01), (55, 100, 0.001), (99, 100, 0.2), (37, 80, 0.5 / 7)])
def test_clopper_pearson_matches_exact_binomial_tail(k, n, alpha):
    # lower: the p at which P(Bin(n,p) >= k) = alpha (increasing in p)
    ref_lo = _bisect(lambda p: _upper_tail(k, n, p), alpha, increasing=True)
    assert clopper_pearson_lower(k, n, alpha) == pytest.approx(ref_lo, abs=1e-10)
    # upper: the p at which P(Bin(n,p) <= k) = alpha (decreasing in p)
    ref_hi = _bisect(lambda p: _lower_tail(k, n, p), alpha, increasing=False)
    assert clopper_pearson_upper(k, n, alpha) == pytest.approx(ref_hi, abs=1e-10)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 400), frac=st.floats(0, 1), alpha=st.floats(1e-6, 0.5))
def test_clopper_pearson_properties(n, frac, alpha):
    k = int(round(frac * n))
    lo, hi = clopper_pearson_lower(k, n, alpha), clopper_pearson_upper(k, n, alpha)
    assert 0.0 <= lo <= k / n <= hi <= 1.0
    # soundness at the bound: the tail probability is (at most) alpha
    if k > 0:
        assert _upper_tail(k, n, lo) <= alpha * (1 + 1e-6) + 1e-12
    # monotone in k, in n and in alpha
    if k < n:
        assert clopper_pearson_lower(k + 1, n, alpha) >= lo
    assert clopper_pearson_lower(k, n + 1, alpha) <= lo
    assert clopper_pearson_lower(k, n, alpha / 2) <= lo
    # symmetry between the two bounds
    assert clopper_pearson_upper(n - k, n, alpha) == pytest.approx(1 - lo, abs=1e-12)


def test_clopper_pearson_vectorised_and_coverage():
    k = np.arange(0, 21)
    lo = clopper_pearson_lower(k, 20, 0.05)
    assert isinstance(lo, np.ndarray) and lo.shape == (21,)
    assert np.all(np.diff(lo) > 0)
    for i in (0, 7, 20):
        assert lo[i] == clopper_pearson_lower(int(k[i]), 20, 0.05)
    assert np.array_equal(clopper_pearson_lower(torch.tensor([3, 4]), 10, 0.1), clopper_pearson_lower(np.array([3, 4]), 10, 0.1))
    # empirical coverage: P(lower > p) <= alpha
    rng = np.random.default_rng(0)
    n, p, alpha, reps = 50, 0.7, 0.1, 20000
    draws = rng.binomial(n, p, size=reps)
    miss = np.mean(clopper_pearson_lower(draws, n, alpha) > p)
    assert miss <= alpha + 3 * math.sqrt(alpha * (1 - alpha) / reps)


@pytest.mark.parametrize("args", [(11, 10, 0.05), (-1, 10, 0.05), (3, 0, 0.05), (3, 10, 0.0), (3, 10, 1.0),
                                  (2.5, 10, 0.05), (3, 10, float("nan"))])
def test_clopper_pearson_rejects_bad_input(args):
    with pytest.raises(PwsError):
        clopper_pearson_lower(*args)
    with pytest.raises(PwsError):
        clopper_pearson_upper(*args)


def test_bonferroni():
    assert bonferroni(0.01, 1) == 0.01
    assert bonferroni(0.01, 400) == pytest.approx(2.5e-5)
    for bad in [(0.0, 3), (1.0, 3), (0.01, 0), (0.01, 2.5), (float("nan"), 2), (0.01, True)]:
        with pytest.raises(PwsError):
            bonferroni(*bad)


def test_cohen_radius():
    for p in (0.51, 0.7, 0.99, 0.999999):
        r = cohen_radius(p, 0.5)
        assert r == pytest.approx(0.25 * (norm.ppf(p) - norm.ppf(1 - p)), rel=1e-9)
        assert r == pytest.approx(cohen_radius_two_sided(p, 1 - p, 0.5), rel=1e-9)
    assert cohen_radius(0.5, 0.5) == 0.0 and cohen_radius(0.2, 0.5) == 0.0 and cohen_radius(0.0, 1.0) == 0.0
    assert cohen_radius(1.0, 0.5) == math.inf
    arr = cohen_radius(np.array([0.3, 0.5, 0.8413447460685429]), 2.0)
    assert arr.shape == (3,) and arr[0] == 0.0 and arr[1] == 0.0 and arr[2] == pytest.approx(2.0, rel=1e-9)
    assert cohen_radius_two_sided(0.4, 0.4, 1.0) == 0.0
    for bad in [(1.2, 0.5), (-0.1, 0.5), (0.7, 0.0), (0.7, -1.0), (0.7, float("inf"))]:
        with pytest.raises(PwsError):
            cohen_radius(*bad)


def test_top_class():
    assert top_class([3, 9, 9, 1]) == 1
    assert top_class(torch.tensor([0, 0, 5])) == 2
    with pytest.raises(PwsError):
        top_class([])


# ---- smoothed classifier -----------------------------------------------------------------

H, W = 24, 32


def _frames(values, channel=0, other=0.3) -> torch.Tensor:
    f = torch.full((len(values), H, W, 3), other, dtype=torch.float32)
    for i, v in enumerate(values):
        f[i, :, :, channel] = v
    return f


@pytest.fixture
def threshold_model(make_model_file, tiny_nets):
    return load_model(make_model_file(tiny_nets.MeanThresholdNet(0.5, channel=0), ["low", "high"], input_size=(H, W)))


class Recorder(torch.nn.Module):
    """Python (not scripted) classifier that records its inputs; class 1 iff mean of channel 0 > 0.5."""

    def __init__(self):
        super().__init__()
        self.sizes: list[int] = []
        self.inputs: list[torch.Tensor] = []

    def forward(self, x):
        self.sizes.append(int(x.shape[0]))
        self.inputs.append(x.clone())
        m = x[:, 0].mean(dim=(1, 2))
        return torch.stack([0.5 - m, m - 0.5], dim=1)


def _recording_model(input_size=None):
    rec = Recorder()
    return rec, LoadedModel(module=rec, class_names=["low", "high"], input_size=input_size, path="recorder", meta={},
                            device=torch.device("cpu"))


def test_vote_frequencies_match_gaussian_probability(threshold_model):
    sigma, num = 0.5, 3000
    gaps = [-0.03, 0.0, 0.01, 0.025]
    frames = _frames([0.5 + g for g in gaps])
    sc = SmoothedClassifier(threshold_model, sigma, batch_size=700, seed=3)  # batches straddle frames
    counts = sc.sample_counts(frames, num)
    assert counts.shape == (4, 2) and counts.dtype == torch.long
    assert counts.sum(1).tolist() == [num] * 4
    assert sc.calls == 4 * num
    std = sigma / math.sqrt(H * W)  # the mean of d iid N(0, sigma^2) has std sigma / sqrt(d)
    for i, g in enumerate(gaps):
        p = norm.cdf(g / std)
        freq = counts[i, 1].item() / num
        assert abs(freq - p) <= 4.5 * math.sqrt(max(p * (1 - p), 1e-4) / num), (g, freq, p)


def test_deterministic_with_seed_and_seeds_differ(threshold_model):
    frames = _frames([0.5, 0.505])
    a = SmoothedClassifier(threshold_model, 0.5, batch_size=128, seed=11).sample_counts(frames, 500)
    b = SmoothedClassifier(threshold_model, 0.5, batch_size=128, seed=11).sample_counts(frames, 500)
    c = SmoothedClassifier(threshold_model, 0.5, batch_size=128, seed=12).sample_counts(frames, 500)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    sc = SmoothedClassifier(threshold_model, 0.5, batch_size=128, seed=11)
    first = sc.sample_counts(frames, 500)
    second = sc.sample_counts(frames, 500)  # the stream continues
    assert torch.equal(first, a) and not torch.equal(second, a)
    sc.reseed()
    assert torch.equal(sc.sample_counts(frames, 500), a)


def test_samples_are_exactly_frame_plus_seeded_noise():
    rec, model = _recording_model()
    frames = torch.rand(3, 5, 4, 3, generator=torch.Generator().manual_seed(0))
    sigma, seed, num, bs = 0.7, 5, 4, 5
    SmoothedClassifier(model, sigma, batch_size=bs, seed=seed).sample_counts(frames, num)
    g = torch.Generator().manual_seed(seed)
    chw = frames.permute(0, 3, 1, 2)
    flat_index = torch.arange(3 * num) // num
    start = 0
    for x in rec.inputs:
        b = x.shape[0]
        noise = torch.stack([torch.randn((3, 5, 4), generator=g) for _ in range(b)])   # one image at a time
        expected = noise * sigma + chw[flat_index[start : start + b]]
        assert torch.equal(x, expected)
        start += b
    assert start == 3 * num
    allx = torch.cat(rec.inputs)
    assert allx.dtype == torch.float32 and allx.min() < 0 and allx.max() > 1  # no clamping


def test_common_noise_samples_are_each_frame_plus_the_same_draws():
    rec, model = _recording_model()
    frames = torch.rand(3, 5, 4, 3, generator=torch.Generator().manual_seed(1))
    sigma, seed, num, bs = 0.7, 5, 7, 3
    sc = SmoothedClassifier(model, sigma, batch_size=bs, seed=seed)
    counts = sc.sample_counts(frames, num, common_noise=True)
    assert counts.shape == (3, 2) and counts.sum(1).tolist() == [num] * 3 and sc.calls == 3 * num
    g = torch.Generator().manual_seed(seed)
    chw = frames.permute(0, 3, 1, 2)
    inputs = iter(rec.inputs)
    for b in (3, 3, 1):                      # the noise of a batch is drawn once, then serves every frame
        noise = torch.stack([torch.randn((3, 5, 4), generator=g) for _ in range(b)]) * sigma
        for k in range(3):
            assert torch.equal(next(inputs), noise + chw[k])
    assert next(inputs, None) is None


@pytest.mark.parametrize("common_noise", [False, True])
def test_counts_do_not_depend_on_the_batch_size(common_noise):
    """The k-th noise image of a call is the same whatever batch_size splits the call into: every
    classifier input, and so every count, is equal for batch sizes 1, 3, 7 and 64."""
    frames = torch.rand(3, 5, 4, 3, generator=torch.Generator().manual_seed(2))
    seen = []
    for bs in (1, 3, 7, 64):
        rec, model = _recording_model()
        counts = SmoothedClassifier(model, 0.7, batch_size=bs, seed=9).sample_counts(frames, 10, common_noise=common_noise)
        inputs = torch.cat(rec.inputs)
        if common_noise:   # batches serve every frame in turn: order the inputs by frame
            per = [x for k in range(3) for x in _frames_of(rec.inputs, k, 3)]
            inputs = torch.cat(per)
        seen.append((counts, inputs))
    for counts, inputs in seen[1:]:
        assert torch.equal(counts, seen[0][0]) and torch.equal(inputs, seen[0][1])


def _frames_of(inputs: list, k: int, frames: int) -> list:
    """The inputs for frame ``k`` of a common-noise call (each noise batch serves the frames in turn)."""
    return [x for i, x in enumerate(inputs) if i % frames == k]


def test_common_noise_keeps_each_frames_vote_frequency(threshold_model):
    sigma, num = 0.5, 3000
    gaps = [-0.03, 0.0, 0.01, 0.025, 0.01]
    sc = SmoothedClassifier(threshold_model, sigma, batch_size=700, seed=4)
    counts = sc.sample_counts(_frames([0.5 + g for g in gaps]), num, common_noise=True)
    std = sigma / math.sqrt(H * W)
    for i, g in enumerate(gaps):
        p = norm.cdf(g / std)
        freq = counts[i, 1].item() / num
        assert abs(freq - p) <= 4.5 * math.sqrt(max(p * (1 - p), 1e-4) / num), (g, freq, p)
    assert torch.equal(counts[2], counts[4])   # equal frames, the same draws: the same votes
    # ordered frames, the same draws: votes for "high" are monotone in the frame's mean (common random numbers)
    assert counts[0, 1] <= counts[1, 1] <= counts[2, 1] <= counts[3, 1]


def test_frames_not_modified(threshold_model):
    frames = _frames([0.4, 0.6])
    before = frames.clone()
    sc = SmoothedClassifier(threshold_model, 0.5, batch_size=64, seed=0)
    sc.sample_counts(frames, 100)
    sc.predict(frames)
    assert torch.equal(frames, before)
    arr = before.numpy().copy()
    sc.sample_counts(arr, 10)
    assert np.array_equal(arr, before.numpy())


def test_denoiser_applied_after_noise(threshold_model):
    frames = _frames([0.9, 0.95])
    seen = []

    def zero_denoiser(x):
        seen.append(x.clone())
        return torch.zeros_like(x)

    sc = SmoothedClassifier(threshold_model, 0.5, batch_size=100, seed=0, denoiser=zero_denoiser)
    counts = sc.sample_counts(frames, 150)
    assert counts[:, 0].tolist() == [150, 150]  # every sample became the zero image -> class "low"
    plain = SmoothedClassifier(threshold_model, 0.5, batch_size=100, seed=0).sample_counts(frames, 150)
    assert plain[:, 1].tolist() == [150, 150]
    # the denoiser saw the noisy samples, not the clean frames
    noisy = torch.cat(seen)
    assert noisy.shape == (300, 3, H, W)
    resid = noisy - frames.permute(0, 3, 1, 2).repeat_interleave(150, dim=0)
    assert abs(resid.std().item() - 0.5) < 0.01
    # clean prediction skips the denoiser unless asked
    assert sc.predict(frames).tolist() == [1, 1]
    assert sc.predict(frames, use_denoiser=True).tolist() == [0, 0]
    bad = SmoothedClassifier(threshold_model, 0.5, denoiser=lambda x: x[:, :, :-1])
    with pytest.raises(PwsError, match="denoiser returned shape"):
        bad.sample_counts(frames, 2)


@pytest.mark.parametrize("B,num,bs,expected", [(3, 10, 4, [4] * 7 + [2]), (1, 1000, 300, [300, 300, 300, 100]),
                                               (7, 1, 3, [3, 3, 1]), (2, 5, 500, [10])])
def test_batch_size_respected(B, num, bs, expected):
    rec, model = _recording_model()
    sc = SmoothedClassifier(model, 0.25, batch_size=bs, seed=0)
    counts = sc.sample_counts(torch.rand(B, 4, 4, 3), num)
    assert rec.sizes == expected
    assert counts.sum().item() == B * num and sc.calls == B * num
    rec.sizes.clear()
    sc.predict(torch.rand(B, 4, 4, 3))
    assert max(rec.sizes) <= bs and sum(rec.sizes) == B and sc.calls == B * num + B


def test_predict_and_progress(threshold_model):
    sc = SmoothedClassifier(threshold_model, 0.5, batch_size=2, seed=0)
    pred = sc.predict(_frames([0.1, 0.7, 0.49, 0.51, 0.9]))
    assert pred.tolist() == [0, 1, 0, 1, 1] and sc.calls == 5
    ticks = []
    sc.sample_counts(_frames([0.5]), 5, progress=lambda d, t: ticks.append((d, t)))
    assert ticks == [(2, 5), (4, 5), (5, 5)]


def test_smoothed_classifier_rejects_bad_input(threshold_model):
    sc = SmoothedClassifier(threshold_model, 0.5)
    good = _frames([0.5])
    with pytest.raises(PwsError, match="noise samples"):
        sc.sample_counts(good, 0)
    with pytest.raises(PwsError, match="float32"):
        sc.sample_counts(good.double(), 3)
    with pytest.raises(PwsError, match="float32"):
        sc.sample_counts((good * 255).to(torch.uint8).numpy(), 3)
    with pytest.raises(PwsError, match=r"\(B, H, W, 3\)"):
        sc.sample_counts(good.permute(0, 3, 1, 2), 3)
    bad = good.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(PwsError, match="NaN"):
        sc.sample_counts(bad, 3)
    with pytest.raises(PwsError, match=r"expects 32x24 .* frame is 10x12"):
        sc.sample_counts(torch.zeros(1, 12, 10, 3), 3)
    for kwargs in ({"sigma": 0.0}, {"sigma": -1.0}, {"sigma": float("nan")}, {"sigma": 0.5, "batch_size": 0},
                   {"sigma": 0.5, "seed": 1.5}):
        with pytest.raises(PwsError):
            SmoothedClassifier(threshold_model, **kwargs)

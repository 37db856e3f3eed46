"""More anchors never certify less (issue 34): the anchor budget ``num_anchors`` is an upper bound.

1. The grid refinement at the grid cap gives its points to the segments nearest ``alpha = 0`` first
   (a budget reaching farther no longer thins the grid near 0 until no second anchor fits).
2. :func:`best_placement` on one grid, against brute-force coverage: a budget whose anchors are stopped
   by a segment its target cannot cover tries the smaller budgets of the ladder (larger targets).
3. End to end with a classifier that never changes its answer (the ceiling): the certified radius is
   non-decreasing over the budgets 4, 8, 16, 24, 48 on synthetic frames (two of them collapsed at 48
   before: 36% -> 18% and 48% -> 22% of the requested radius) and on a real RealSense frame.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from conftest import recomputed_p_a_lower, shared_path
from pws_ros.core.anchors import best_placement, budget_ladder, refine_plan, target_radius
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.certify import CertifyConfig, certify
from pws_ros.core.cloud import cloud_from_rgbd
from pws_ros.core.coverage import AdaptiveAnchorsRule, covered_radius
from pws_ros.core.imaging import make_imaging
from pws_ros.core.partition import Plan, make_grid
from pws_ros.replay.ceiling import never_changing_model

BUDGETS = (4, 8, 16, 24, 48)
REAL_BUDGETS = (4, 8, 24)   # the real frame: three budgets (each up to 4 times as many anchors with the joint first look)
FRONTIER_SLACK = 0.02   # of the requested radius: see test_more_anchors_never_certify_less_on_synthetic_frames


def test_refine_plan_at_the_cap_gives_the_points_nearest_zero_first():
    alphas = make_grid(1.0, 0.25)  # 9 points, alpha = 0 at index 4
    plan = Plan("pws_of", "tx", 1.0, 0.25, 9, alphas)
    frames = np.arange(9, dtype=np.float64).reshape(9, 1, 1, 1)  # every segment differs by 1.0: 4 parts wanted
    # room for 12 of the 24 points wanted: the four segments whose near end is nearest 0 (rendered path) get
    # all theirs, the four beyond none
    out = refine_plan(plan, frames, 0.25, 9 + 12)
    want = set(np.round(alphas, 9)) | {round(a + 0.0625 * k, 9) for a in (-0.5, -0.25, 0.0, 0.25) for k in (1, 2, 3)}
    assert set(np.round(out.alphas, 9)) == want and len(out.alphas) == 21
    # room for 2: the points go to the segment next to 0 (scaling every segment's 3 points by 2/24 and
    # rounding down added none, with room left: the collapse at 48 anchors)
    out = refine_plan(plan, frames, 0.25, 9 + 2)
    assert len(out.alphas) == 11 and set(out.alphas) - set(alphas) <= set(np.linspace(-0.25, 0.0, 4)[1:3])


def test_budget_ladder():
    assert budget_ladder(1) == []
    assert budget_ladder(24) == [16, 12, 8, 6, 4, 3, 2, 1]
    assert budget_ladder(48) == [32, 24, 16, 12, 8, 6, 4, 3, 2, 1]
    assert budget_ladder(20) == [16, 12, 8, 6, 4, 3, 2, 1]


def _target_of(k: int) -> float:
    return target_radius(64, 64, 256, 0.5, 0.01, k)


def _profile(rng, S):
    """Random 1-D distance profile: grid frame ``j`` at path position ``p_j``, segment ``i`` a box
    ``[min(p_i, p_i+1) - w_i, max(...) + w_i]`` (``w_i``: how far the frames inside it wander), ``D_i(x_j)``
    the distance from ``p_j`` to the farthest point of that box (as ``HullValues.dist_sq``). A wide box
    stops a small target and not a larger one."""
    alphas = np.unique(np.concatenate([[-1.0, 0.0, 1.0], rng.uniform(-0.999, 0.999, S - 2)]))
    centre = int(np.searchsorted(alphas, 0.0))
    n = len(alphas) - 1
    p = np.cumsum(np.concatenate([[0.0], rng.exponential(rng.uniform(0.05, 0.5), n)]))
    p -= p[centre]
    w = rng.exponential(0.3, n) * (rng.random(n) < 0.5)
    return alphas, centre, p, np.minimum(p[:-1], p[1:]) - w, np.maximum(p[:-1], p[1:]) + w


def _rows(p, lo, hi):
    def row(j, i0=0, i1=None):
        return np.maximum(p[j] - lo[i0:i1], hi[i0:i1] - p[j]) ** 2
    return row


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), S=st.integers(4, 60))
def test_best_placement_against_brute_force(seed, S):
    """The predicted reach is the covered radius of the anchors chosen at the target of their number;
    never less than the budget's own placement (or any first part of it); and never less than a smaller
    budget's choice whose own placement the search tried (it goes down the ladder while a placement is
    stopped by the grid: from such a budget on, both try the same placements)."""
    rng = np.random.default_rng(seed)
    alphas, centre, p, lo, hi = _profile(rng, S)
    row = _rows(p, lo, hi)
    ladder = sorted(set(budget_ladder(64)) | {64})
    own = {k: AdaptiveAnchorsRule(k).place(row, alphas, centre, _target_of(k)) for k in ladder}
    chosen = {k: best_placement(AdaptiveAnchorsRule(k), row, alphas, centre, k, _target_of, 1.0) for k in ladder}

    def covered_by(idx, R):
        covered = np.array([any(row(int(a))[i] < R ** 2 for a in idx) for i in range(len(alphas) - 1)])
        return covered_radius(covered, alphas, centre)

    for K in ladder:
        predicted, idx, rows, k = chosen[K]
        assert 1 <= len(idx) <= k <= K and idx[0] == centre and (k == K or k in budget_ladder(K))
        assert sorted(rows) == sorted(int(a) for a in idx)
        assert predicted == covered_by(idx, _target_of(len(idx)))
        assert all(predicted >= covered_by(own[K][:j], _target_of(j)) for j in range(1, len(own[K]) + 1))
        tried = [K] + budget_ladder(K)
        for j, b in enumerate(tried):
            if predicted >= 1.0 or (j > 0 and len(own[tried[j - 1]]) >= tried[j - 1]):
                break
            assert predicted >= chosen[b][0], (K, b)


def test_a_budget_stopped_by_a_wide_segment_takes_a_smaller_one_that_passes_it():
    """Evenly spaced frames (0.3 apart) and one segment on each side whose frames wander 0.54 beyond its
    ends: its nearest frames are 0.84 from its farthest point, more than the target of 24 or 48 anchors
    (0.836, 0.821) and less than that of 16 (0.846)."""
    S = 200
    alphas, centre = np.linspace(-1.0, 1.0, S + 1), S // 2
    p = (np.arange(S + 1) - centre) * 0.3
    w = np.zeros(S)
    w[[centre - 11, centre + 10]] = 0.54
    row = _rows(p, np.minimum(p[:-1], p[1:]) - w, np.maximum(p[:-1], p[1:]) + w)
    own = AdaptiveAnchorsRule(48).place(row, alphas, centre, _target_of(48))
    assert len(own) < 48 and alphas[own].max() < alphas[centre + 11]          # stopped at the wide segment
    predicted, idx, _rows_, k = best_placement(AdaptiveAnchorsRule(48), row, alphas, centre, 48, _target_of, 1.0)
    assert k == 16 and len(idx) == 16 and predicted > alphas[centre + 11]       # 16 anchors pass it


def _scene(seed: int):
    """A 32x24 camera seeing a far wall and one to three boxes, in 4x4 colour blocks, a few holes; one axis
    and a requested radius about the size the anchor budget decides (about 10% to 100% of it certified)."""
    rng = np.random.default_rng(seed)
    W, H = 32, 24
    cam = CameraIntrinsics(W, H, 30.0, 30.0, (W - 1) / 2, (H - 1) / 2, "cam")
    depth = np.full((H, W), rng.uniform(1.5, 3.0))
    for _ in range(rng.integers(1, 4)):
        x0, y0 = rng.integers(0, W - 4), rng.integers(0, H - 4)
        depth[y0:y0 + rng.integers(3, H // 2), x0:x0 + rng.integers(3, W // 2)] = rng.uniform(0.6, 1.4)
    depth[rng.random((H, W)) < 0.05] = 0.0
    colour = np.kron(rng.random((H // 4 + 1, W // 4 + 1, 3)), np.ones((4, 4, 1)))[:H, :W].astype(np.float32)
    axis = ("tx", "ty", "tz", "rx", "ry", "rz")[seed % 6]
    radius = 8 * {"tx": 0.02, "ty": 0.02, "tz": 0.05, "rx": 0.01, "ry": 0.01, "rz": 0.03}[axis]
    return cam, cloud_from_rgbd(depth, colour, cam), axis, radius


def _ceilings(cloud, cam, imaging, axis, radius, budgets, **config):
    model = never_changing_model(imaging.out_shape)
    certs = []
    for k in budgets:
        cfg = CertifyConfig(sigma=0.5, n0=64, n=256, alpha=0.01, num_anchors=k, **config)
        certs.append(certify(cloud, cam, model, axis, radius, "pws_of", cfg, imaging=imaging))
    return certs


def _check_sound(cert):
    """The level is that of the anchors used: every vote for the label (a classifier that never changes its
    answer), each bound recomputed from the votes the certificate records (conftest.recomputed_p_a_lower)."""
    K = len(cert.bounds["anchors"])
    assert cert.num_bounds == K <= cert.bounds["placement_budget"]
    assert cert.bounds["anchor_votes"] == cert.bounds["anchor_samples"]
    assert np.allclose(cert.p_a_lower, recomputed_p_a_lower(cert), rtol=1e-9, atol=1e-12)


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000))
@example(seed=7)    # ty: 24 -> 48 anchors 36% -> 18% with n samples each before the fix; budgets 4..48 now 19/30/61/60/66%
@example(seed=20)   # tz: 48 anchors 22% where 24 certified 48%, before the fix
@example(seed=64)   # ry: 24 -> 48 anchors 87% -> 83% before the plan's first look was chosen per budget (now 98%)
@example(seed=128)  # tz: 24 -> 48 anchors 88% -> 78%, the same (now 97%)
@example(seed=2774)  # a scene where the budget barely matters (8.4% at 4 anchors, 11.0% from 8 on)
def test_more_anchors_never_certify_less_on_synthetic_frames(seed):
    """Non-decreasing up to FRONTIER_SLACK of the request: what the placements predict (the anchors'
    planned radii) never decreases; the frontier refinement after the estimation then resolves the end of
    the covered run to a quarter of a segment per round on grids that differ between budgets (seed 7,
    budget 16 -> 24: 61.2% -> 60.0%, both placements predicting 59.4%)."""
    cam, cloud, axis, radius = _scene(seed)
    im = make_imaging("surfel", cam, (12, 16), background=0.0, border=0)
    certs = _ceilings(cloud, cam, im, axis, radius, BUDGETS, border=0, seed=seed)
    radii = [c.radius for c in certs]
    assert all(b >= a - FRONTIER_SLACK * radius for a, b in zip(radii, radii[1:])), (axis, [r / radius for r in radii])
    # (whether the budget matters is the scene's: seed 2774 certifies 8.4% at 4 anchors and 11.0% from 8 on; that it
    # does on the examples is test_the_budget_decides_on_the_synthetic_frames)
    assert radii[-1] >= max(radii) - FRONTIER_SLACK * radius
    for c in certs:
        _check_sound(c)


def test_the_budget_decides_on_the_synthetic_frames():
    """Not vacuous: on the examples above the budget matters (short of the request at 4, more at 48)."""
    for seed in (7, 20):
        cam, cloud, axis, radius = _scene(seed)
        im = make_imaging("surfel", cam, (12, 16), background=0.0, border=0)
        small, large = _ceilings(cloud, cam, im, axis, radius, (4, 48), border=0, seed=seed)
        assert 0 < small.radius < 0.3 * radius and large.radius > 2 * small.radius


def test_more_anchors_never_certify_less_on_a_real_frame():
    """The RealSense recording (../shared/data) at 80x45, ry and tz at four times the shipped radii, where
    the budget decides (about 15% of the request at 4 anchors, 100% at 48), through ``pws ceiling``."""
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.replay import ReplayOptions
    from pws_ros.replay.ceiling import ceiling

    bag = shared_path("realsense_single_rgbd")
    radius = {"ry": 4 * math.radians(0.25), "tz": 0.04}
    rows = {}
    for k in REAL_BUDGETS:
        config = PwsConfig(axes=("ry", "tz"), radius_ry=radius["ry"], radius_tz=radius["tz"], num_anchors=k)
        got, top, _ = ceiling(ReplayOptions(bag=bag, config=config, write_output=False, max_frames=1, quiet=True), None,
                              input_size=(45, 80))
        for row in got:
            rows.setdefault(row.axis, []).append(row.ceiling)
        for rec in top.records:
            for cert in rec.certificates:
                _check_sound(cert)
    for axis, radii in rows.items():
        assert all(b >= a for a, b in zip(radii, radii[1:])), (axis, [r / radius[axis] for r in radii])
        assert radii[0] < 0.5 * radius[axis] and radii[-1] == pytest.approx(radius[axis])   # the budget decides


def _predictive_quantile(m: int, n0: int, q: float) -> int:
    """The ``q`` quantile of ``m`` votes after ``n0`` of ``n0`` selection votes, uniform prior: ``p ~ Beta(n0 + 1,
    1)``, ``P(k) = C(m, k) B(k + n0 + 1, m - k + 1) / B(n0 + 1, 1)``, summed in float64 from lgamma."""
    def lbeta(a, b):
        return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    cdf = 0.0
    for k in range(m + 1):
        cdf += math.exp(math.lgamma(m + 1) - math.lgamma(k + 1) - math.lgamma(m - k + 1)
                        + lbeta(k + n0 + 1, m - k + 1) - lbeta(n0 + 1, 1))
        if cdf >= q - 1e-9:
            return k
    return m


def test_a_unanimous_selection_is_not_read_as_p_a_1_for_many_samples():
    """64 of 64 selection votes cannot tell p_A = 0.98 from 1 (0.98^64 = 0.27). Read as p_A = 1, a plan
    predicted for 1,024 samples a unanimous look where 1,005 votes came: the anchors, placed for that
    target, left gaps, and n 1024 certified 15% of a gesture frame's radius where n 256 certified all of
    it (issue 34). The votes planned for are the 3/4 quantile of their posterior predictive (here from
    lgamma sums): all of them up to 194 samples (the looks of the shipped defaults: the demo's calls and
    radii and the ceilings are unchanged), fewer for more samples; and the target follows them."""
    from scipy.stats import beta, norm

    from pws_ros.core.anchors import PLAN_QUANTILE, planned_votes

    assert PLAN_QUANTILE == 0.75
    for m in (1, 64, 96, 136, 194, 195, 196, 256, 1024, 4096):   # 195: P(all) = 1/4 exactly: not all
        ref = _predictive_quantile(m, 64, 0.75)
        assert planned_votes(1.0, m, 64) == ref, m
        assert (ref == m) == (m <= 194), (m, ref)   # P(all m) = 65 / (65 + m) > 1/4 up to m = 194
    assert planned_votes(60 / 64, 1024, 64) == 960   # not unanimous: the frequency
    sigma, alpha, K = 0.35, 0.001, 8
    k_hat = _predictive_quantile(1024, 64, 0.75)
    want = 0.95 * sigma * norm.ppf(beta.ppf(alpha / K, k_hat, 1024 - k_hat + 1))
    unanimous = 0.95 * sigma * norm.ppf((alpha / K) ** (1 / 1024))
    got = target_radius(64, 64, 1024, sigma, alpha, K)
    assert abs(got - want) < 1e-9 and got < 0.9 * unanimous   # 0.68 against 0.79


def test_the_planned_votes_are_scipy_stats_betabinom_quantiles():
    """The unanimous selection's planned votes (the beta-binomial quantile, computed in the module from log-gamma
    sums: importing scipy.stats costs about a second of every command's start) are scipy.stats.betabinom.ppf's,
    for every look size up to 700 at the shipped n0 and on sizes up to 25,000 and other n0, ties m = 3 n0 + 3 included."""
    from scipy.stats import betabinom

    from pws_ros.core.anchors import PLAN_QUANTILE, planned_votes

    rng = np.random.default_rng(3)
    cases = [(m, 64) for m in range(1, 700)] + [(3 * n0 + 3, n0) for n0 in range(1, 200, 7)]
    cases += [(int(rng.integers(1, 25_000)), int(rng.choice([8, 16, 32, 100, 128, 256]))) for _ in range(60)]
    for m, n0 in cases:
        assert planned_votes(1.0, m, n0) == int(betabinom.ppf(PLAN_QUANTILE - 1e-9, m, n0 + 1, 1)), (m, n0)


@settings(max_examples=40, deadline=None)
@given(k0=st.integers(40, 64), a=st.integers(1, 40), more=st.integers(1, 40), n=st.sampled_from([64, 100, 256]),
       n_first=st.sampled_from([16, 32, 64]))
@example(k0=64, a=24, more=24, n=256, n_first=64)   # 32 anchors: 192 samples each planned 0.987, a full look of 256 0.975
def test_a_larger_budget_never_plans_a_smaller_target(k0, a, more, n, n_first):
    """The planned radius of K anchors (the joint plan's first look, :func:`anchored._planned`) never decreases
    as num_anchors grows: a larger budget may always plan as a smaller one. Reference: the target of every first
    look a budget of 1 .. num_anchors anchors' samples gives K anchors, computed here from the Clopper-Pearson
    bound of the planned votes, the largest taken."""
    from pws_ros.core.anchored import _planned
    from pws_ros.core.anchors import planned_votes, predicted_target
    from pws_ros.core.sequential import joint_looks, joint_rate

    n0, sigma, alpha = 64, 0.5, 0.01
    plans = [_planned(k0, CertifyConfig(sigma=sigma, n0=n0, n=n, alpha=alpha, num_anchors=b, n_first=n_first)) for b in (a, a + more)]
    compared = 0
    for K in range(1, min(plans[0][1], 48) + 1):
        small, large = (p[2](K) for p in plans)
        if plans[0][0](K).joint and plans[1][0](K).joint:
            assert large >= small, (K, small, large)
            best = 0.0
            for j in range(1, a + more + 1):
                m = min(n, max(1, j * n // K))
                if m >= min(n_first, n) or j == a + more:
                    level = alpha * (1.0 if m >= n else 0.9)
                    best = max(best, predicted_target(planned_votes(joint_rate(k0, n0, K), m, n0), m, sigma, level))
            assert math.isclose(large, best, rel_tol=1e-12, abs_tol=1e-15), (K, large, best)
            compared += 1
    if (k0, a, more, n, n_first) == (64, 24, 24, 256, 64):
        assert compared >= 32


def _path_of_frames(F: int, step: float):
    """A fixed geometry of ``F`` 4x4 frames on ``[-1, 1]`` (0 on the grid) whose one pixel walks ``step`` a frame, its
    segments' exact boxes, and its plan (tx): a path each Cohen radius covers several segments of."""
    from pws_ros.core.anchor_geometry import _FixedGeometry
    from pws_ros.core.surfel_bounds import HullValues

    alphas = np.linspace(-1.0, 1.0, F)
    alphas[F // 2] = 0.0
    f = np.full((F, 4, 4, 3), 0.5, np.float32)
    f[:, 1, 1, 0] = (0.5 + step * np.arange(F)).astype(np.float32)
    hulls = HullValues(alphas, np.minimum(f[:-1], f[1:]), np.maximum(f[:-1], f[1:]), np.zeros((F - 1, 4, 4), bool))
    plan = Plan("pws_of", "tx", 1.0, float(np.diff(alphas).max()), F, alphas, "m", {"imaging": "surfel"})
    return _FixedGeometry(f, hulls), plan


def test_a_weak_frame_estimates_the_centre_alone_with_the_whole_budget():
    """Where the selection predicts no radius at the most anchors' level (a weak frame: p_A about 0.62), the
    plan is the centre alone with all ``num_anchors * n`` samples at level alpha (docs/certificate.md): never
    more anchors each with that whole budget (3 anchors of 800 samples each, 2,464 calls, before), which a
    time budget sizing the work for ``n0 + num_anchors * n`` calls would overrun. Frames on a path whose
    segments the Cohen radius covers several of, a classifier whose p_A is known in closed form."""
    import torch
    from scipy.stats import norm

    from pws_ros.core.anchored import _certify_anchored
    from pws_ros.core.model import LoadedModel

    p, sigma, v0 = 0.62, 0.5, 0.5
    thr = v0 - sigma * float(norm.ppf(p))   # class 0 iff pixel (0, 0, 0) plus its noise exceeds thr: P = p on every frame

    class Net(torch.nn.Module):
        def forward(self, x):
            a = x[:, 0, 0, 0] - thr
            return torch.stack([a, torch.zeros_like(a)], 1)

    model = LoadedModel(Net().eval(), ["a", "b"], None, "closed form")
    geometry, plan = _path_of_frames(81, 0.0083)
    cfg = CertifyConfig(sigma=sigma, n0=64, n=100, alpha=0.01, num_anchors=8, seed=3, batch_size=2000).validate()
    cert = _certify_anchored(geometry, plan, AdaptiveAnchorsRule(cfg.num_anchors), model, cfg, None, None, "pws_of", {}, 0.0)
    b = cert.bounds
    assert b["looks"]["sizes"] == [cfg.num_anchors * cfg.n] and not b["looks"]["joint"]   # the weak-frame plan
    assert b["anchors"] == [0.0] and b["anchor_samples"] == [cfg.num_anchors * cfg.n]
    assert cert.classifier_calls == cfg.n0 + cfg.num_anchors * cfg.n
    # its one bound at level alpha, recomputed from the votes it records
    assert np.allclose(cert.p_a_lower, recomputed_p_a_lower(cert), rtol=1e-9, atol=1e-12)


def test_progress_ends_at_the_images_the_classifier_saw():
    """The anchors' progress ends at the classifier calls made (a joint first look that certifies needs far fewer
    than the n0 + num_anchors * n the plan allowed: a bar at "6208/6208" after 448 calls, before)."""
    from pws_ros.core.anchored import _certify_anchored

    geometry, plan = _path_of_frames(41, 0.01)
    cfg = CertifyConfig(sigma=0.5, n0=64, n=256, alpha=0.01, num_anchors=8, seed=1).validate()
    ticks = []
    cert = _certify_anchored(geometry, plan, AdaptiveAnchorsRule(cfg.num_anchors), never_changing_model((4, 4)),
                             cfg, None, lambda done, total: ticks.append((done, total)), "pws_of", {}, 0.0)
    assert cert.certified and cert.classifier_calls < cfg.n0 + cfg.num_anchors * cfg.n   # the case this is about
    assert ticks[0] == (cfg.n0, cfg.n0 + cfg.num_anchors * cfg.n)
    assert ticks[-1] == (cert.classifier_calls, cert.classifier_calls)

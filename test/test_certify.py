"""Certificates are never wrong on a classifier whose smoothed behaviour is known in closed form.

Scene: a bright square (channel 0 = C, at 0.8 m) on a dark plane (1 m), dark background. Classifier:
``MeanThresholdNet(T)`` says "bright" iff the mean of channel 0 exceeds ``T``. Under Gaussian pixel noise
the mean of ``d = H W`` noise values is ``N(0, sigma^2 / d)``, so the smoothed classifier's probability of
"bright" on a frame ``x`` is exactly ``p(x) = Phi((mean_0(x) - T) sqrt(d) / sigma)``.

For every certificate we check, on a dense sweep of ``[-r, r]`` (``r`` the certified radius):
(a) the true ``p`` of the certified class is > 1/2 at every motion (the claim itself);
(b) each estimated frame's true ``p`` is >= its reported ``p_a_lower`` (the statistics);
(c) each swept frame is within the Cohen radius ``sigma Phi^-1(p_a_lower)`` of some estimated frame (the
    coverage argument the certificate rests on).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binom, norm

from conftest import LinearNet, MeanThresholdNet
from pws_ros.core.bounds import render_plan
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.certify import COVERAGES, CertifyConfig, certify, certify_rendered
from pws_ros.core.coverage import anchor_indices
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.model import load_model, save_model
from pws_ros.core.partition import Plan, make_grid, plan_partitions
from pws_ros.core.render import render
from pws_ros.core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate

W, H = 40, 30
D = W * H
CAM = CameraIntrinsics(width=W, height=H, fx=40.0, fy=40.0, cx=19.5, cy=14.5)
C = 0.1       # square brightness (channel 0 only)
T = 0.008     # decision threshold on the mean of channel 0 (the square is 480 px: mean 0.04 at rest)
SIGMA = 0.4
ROWS, COLS = slice(5, 25), slice(8, 32)


def one_frame_scene() -> Cloud:
    depth = np.full((H, W), 1.0)
    depth[ROWS, COLS] = 0.8
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[ROWS, COLS, 0] = C
    return cloud_from_rgbd(depth, rgb, CAM)


def entire_scene() -> Cloud:
    """The same scene sampled more densely than the pixels and beyond the view (no holes for the motions
    used below: tz up to 0.3 m, ry up to 0.3 rad)."""
    step = 1.0 / 64
    px, py = np.meshgrid(np.arange(-0.95, 0.95, step), np.arange(-0.45, 0.45, step))
    plane = np.stack([px.ravel(), py.ravel(), np.ones(px.size)], 1)
    plane = plane[~((np.abs(plane[:, 0]) < 0.24) & (np.abs(plane[:, 1]) < 0.2))]  # hidden behind the square
    z = 0.8
    sx, sy = np.meshgrid((np.arange(8, 32, 0.5) + 0.25 - CAM.cx - 0.5) * z / CAM.fx,
                         (np.arange(5, 25, 0.5) + 0.25 - CAM.cy - 0.5) * z / CAM.fy)
    square = np.stack([sx.ravel(), sy.ravel(), np.full(sx.size, z)], 1)
    cols = np.zeros((len(plane) + len(square), 3), np.float32)
    cols[len(plane):, 0] = C
    return Cloud(np.concatenate([plane, square]), cols)


def sweep(r: float, k: int = 601) -> np.ndarray:
    """Dense motions over [-r, r]: the ends and interior points nudged off round values (exact pixel-edge
    instants are covered by test_sweep_bounds.test_bound_at_merged_crossing_instant)."""
    g = np.linspace(-r, r, k)
    g[1:-1] += r * 1.2345e-7
    return g


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    path = save_model(MeanThresholdNet(T), tmp_path_factory.mktemp("certify") / "mean.pt", ["dark", "bright"], input_size=(H, W))
    return load_model(path)


def true_p(frames: np.ndarray, label: int) -> np.ndarray:
    m = frames[..., 0].astype(np.float64).reshape(len(frames), -1).mean(axis=1)
    p1 = norm.cdf((m - T) * math.sqrt(D) / SIGMA)
    return p1 if label == 1 else 1.0 - p1


def check_certificate(cert: Certificate, cloud: Cloud, plan: Plan, config: CertifyConfig, background: float = 0.0,
                      alphas=None):
    assert cert.num_partitions == plan.num_partitions
    if config.coverage == "anchors":
        est = anchor_indices(plan.num_partitions, config.num_anchors)
    else:
        est = np.arange(plan.num_partitions)
    # Bonferroni over exactly the bounds used, at level alpha / m: every p_a_lower is a one-sided
    # Clopper-Pearson lower bound at that level for some count k, i.e. (its defining equation)
    # P(Bin(n, p) >= k) = alpha / m, or p = 0 for k = 0
    assert cert.num_bounds == len(est) == len(cert.p_a_lower)
    level = config.alpha / cert.num_bounds
    k = np.arange(1, config.n + 1)
    for p in cert.p_a_lower:
        assert p == 0.0 or np.min(np.abs(binom.sf(k - 1, config.n, p) / level - 1)) <= 1e-6, p
    if cert.status == STATUS_ABSTAIN:
        assert cert.radius == 0.0 and not cert.certified
        return
    assert 0.0 <= cert.radius <= plan.radius
    assert cert.certified == (cert.status == STATUS_CERTIFIED) == (cert.radius == plan.radius)
    assert cert.radius in plan.alphas
    if cert.radius == 0.0:
        return
    est_frames = render(cloud, CAM, plan.axis, plan.alphas[est], background=background)
    pl = np.asarray(cert.p_a_lower)
    # (b) the statistics hold (true p at every estimated frame)
    assert np.all(true_p(est_frames, cert.label) >= pl - 1e-12)
    R = np.where(pl > 0.5, SIGMA * norm.ppf(np.clip(pl, 0.5, 1 - 1e-16)), 0.0)
    g = sweep(cert.radius, 601 if len(cloud) < 5000 else 301) if alphas is None else np.asarray(alphas)
    x = render(cloud, CAM, plan.axis, g, background=background)
    # (a) the claim: the smoothed classifier keeps the label on the whole certified range
    p = true_p(x, cert.label)
    assert np.all(p > 0.5), f"certified radius {cert.radius} but p = {p.min():.4f} at alpha = {g[np.argmin(p)]:.4f}"
    # (c) the coverage argument: every frame is inside some estimated frame's Cohen ball
    xf = x.reshape(len(g), -1).astype(np.float64)
    inside = np.zeros(len(g), bool)
    for e, r in zip(est_frames.reshape(len(est), -1).astype(np.float64), R):
        if r > 0:
            inside |= ((xf - e) ** 2).sum(axis=1) < r * r
    assert inside.all(), f"alpha = {g[~inside][:5]} outside every Cohen ball"


CASES = [
    ("one_frame", "tx", 0.6, 0.02, "pairwise"),
    ("one_frame", "tx", 0.6, 0.02, "paper"),
    ("one_frame", "ty", 0.5, 0.02, "pairwise"),
    ("one_frame", "rz", 0.8, 0.05, "anchors"),
    ("entire", "tz", 0.3, 0.02, "pairwise"),
    ("entire", "ry", 0.3, 0.0125, "pairwise"),
]


@pytest.fixture(scope="module")
def scenes():
    return {"one_frame": one_frame_scene(), "entire": entire_scene()}


@pytest.mark.parametrize("kind,axis,radius,step,coverage", CASES)
def test_certificates_are_never_wrong(kind, axis, radius, step, coverage, model, scenes):
    cloud = scenes[kind]
    alphas = make_grid(radius, step)
    plan = Plan("pws", axis, radius, step, len(alphas), alphas)
    config = CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=200, alpha=0.001, seed=len(alphas), coverage=coverage, batch_size=1000,
                           num_anchors=2 * len(alphas) // 3 + 1 if coverage == "anchors" else 9)
    cert = certify(cloud, CAM, model, axis, radius, "pws", config, plan=plan)
    assert cert.label == 1 and cert.class_name == "bright" and cert.coverage == coverage
    check_certificate(cert, cloud, plan, config)
    # non-vacuous: a real range is certified here (the coarse tz grid on the entire cloud is left out:
    # its segments hold too many switches for sigma to cover, which is a correct refusal)
    if (kind, axis) != ("entire", "tz"):
        assert cert.radius > 0


def test_certified_range_stops_before_the_true_boundary(model, scenes):
    """tx: the square leaves the view and the mean falls below T at |alpha| ~ 0.55 m; asking for 0.7 m
    must not be certified, and the certified radius must lie below the first wrong motion."""
    cloud = scenes["one_frame"]
    radius = 0.7
    alphas = make_grid(radius, 0.025)
    plan = Plan("pws", "tx", radius, 0.025, len(alphas), alphas)
    g = np.linspace(-radius, radius, 2801)
    p = true_p(render(cloud, CAM, "tx", g), 1)
    boundary = np.abs(g[p <= 0.5]).min()
    assert 0.4 < boundary < 0.7
    config = CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=200, alpha=0.001, seed=5, batch_size=1000)
    cert = certify(cloud, CAM, model, "tx", radius, "pws", config, plan=plan)
    assert cert.status == STATUS_NOT_CERTIFIED and not cert.certified
    assert 0 < cert.radius < boundary
    check_certificate(cert, cloud, plan, config)


@pytest.mark.parametrize("method", ["pws", "pws_l", "pws_of"])
def test_planned_methods_are_never_wrong(method, model, scenes):
    cloud = scenes["one_frame"]
    radius = 0.08
    config = CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=150, alpha=0.001, seed=11, batch_size=1000, max_partitions=400,
                           coverage="pairwise")
    plan = plan_partitions(cloud, CAM, "tx", radius, method, max_partitions=400)
    cert = certify(cloud, CAM, model, "tx", radius, method, config)
    assert cert.method == method and cert.num_partitions == plan.num_partitions
    assert cert.delta_alpha == pytest.approx(plan.delta_alpha)
    assert cert.status == STATUS_CERTIFIED and cert.radius == radius
    check_certificate(cert, cloud, plan, config)


def test_determinism_and_bonferroni(model, scenes):
    cloud = scenes["one_frame"]
    alphas = make_grid(0.1, 0.02)
    plan = Plan("pws", "tx", 0.1, 0.02, len(alphas), alphas)
    outs = []
    for cov in COVERAGES:
        cfg = CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=60, alpha=0.01, seed=7, coverage=cov, num_anchors=3, batch_size=77)
        a = certify(cloud, CAM, model, "tx", 0.1, "pws", cfg, plan=plan)
        b = certify(cloud, CAM, model, "tx", 0.1, "pws", cfg, plan=plan)
        da, db = a.to_dict(), b.to_dict()
        da.pop("timings"), db.pop("timings")
        assert da == db
        expected_m = len(anchor_indices(len(alphas), 3)) if cov == "anchors" else len(alphas)
        assert a.num_bounds == expected_m == len(a.p_a_lower)
        if cov == "anchors":
            assert len(anchor_indices(len(alphas), 3)) < len(alphas)
        assert a.classifier_calls == 32 + expected_m * 60
        outs.append(a)
    c = certify(cloud, CAM, model, "tx", 0.1, "pws",
                CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=60, alpha=0.01, seed=8, batch_size=77), plan=plan)
    assert c.p_a_lower != outs[1].p_a_lower  # another seed, other noise
    # with all n votes for the label the lower bound is (alpha/m)^(1/n): Bonferroni at m partitions
    assert max(outs[1].p_a_lower) == pytest.approx((0.01 / len(alphas)) ** (1 / 60), rel=1e-9)


def test_anchor_indices():
    for n in (3, 5, 41, 101):
        for k in (1, 2, 5, 9, 200):
            idx = anchor_indices(n, k)
            assert n // 2 in idx and np.all(np.diff(idx) > 0) and idx[0] >= 0 and idx[-1] < n
            if k >= 2:
                assert idx[0] == 0 and idx[-1] == n - 1
            assert len(idx) <= min(n, max(k, 1) + 1)


def test_abstains_on_a_coin_flip(tmp_path):
    """A uniform grey scene at exactly the threshold: the noisy mean is above or below with probability 1/2."""
    cloud = Cloud(np.array([[0.0, 0.0, 1.0]]), np.full((1, 3), 0.5, np.float32))
    model = load_model(save_model(MeanThresholdNet(0.5), tmp_path / "coin.pt", ["a", "b"], input_size=(H, W)))
    alphas = make_grid(0.05, 0.025)
    plan = Plan("pws", "tx", 0.05, 0.025, len(alphas), alphas)
    for cov in COVERAGES:
        cfg = CertifyConfig(imaging="paper", sigma=0.5, n0=50, n=200, seed=3, background=0.5, coverage=cov)
        cert = certify(cloud, CAM, model, "tx", 0.05, "pws", cfg, plan=plan)
        assert cert.status == STATUS_ABSTAIN and cert.radius == 0.0 and not cert.certified
        assert cert.reason
        assert max(cert.p_a_lower) < 0.5


def test_certify_rendered_equals_certify(model, scenes):
    cloud = scenes["one_frame"]
    plan = plan_partitions(cloud, CAM, "tx", 0.05, "pws_of")
    for cov in COVERAGES:
        cfg = CertifyConfig(imaging="paper", sigma=SIGMA, n0=20, n=50, alpha=0.01, seed=4, coverage=cov, chunk=4, batch_size=100, num_anchors=4)
        direct = certify(cloud, CAM, model, "tx", 0.05, "pws_of", cfg, plan=plan)
        rendered = render_plan(cloud, CAM, plan, background=cfg.background)
        via = certify_rendered(rendered, model, cfg)
        a, b = direct.to_dict(), via.to_dict()
        for k in ("timings",):
            a.pop(k), b.pop(k)
        a["bounds"].pop("lemma1_holds", None), b["bounds"].pop("lemma1_holds", None)
        a["bounds"].pop("imaging")  # the direct path records its Imaging; a rendered plan carries none
        assert a == b
        assert direct.bounds["max_pair_bound_sq"] == pytest.approx(float(rendered.pair_bound_sq.max()))
    # an incomplete set of frames is refused
    rendered.frames = rendered.frames[:-1]
    with pytest.raises(PwsError, match="incomplete"):
        certify_rendered(rendered, model, cfg)


def test_cms_through_certify(model, scenes):
    """method='cms' runs the CMS baseline with the config's sample sizes, alpha, seed and motion sigma.
    Under tx motion with sigma 0.05 m the bright square (0.8 m, 24 px wide) shifts by at most ~12 px at
    5 sigma and keeps a channel-0 mean far above T (checked below), so every one of the n motions votes
    "bright": k = n, whose one-sided Clopper-Pearson bound is alpha^(1/n), and R = s Phi^-1(alpha^(1/n))."""
    cloud = scenes["one_frame"]
    s, n, alpha = 0.05, 60, 0.01
    extreme = render(cloud, CAM, "tx", [-5 * s, 5 * s])
    assert np.all(extreme[..., 0].reshape(2, -1).mean(axis=1) > 2 * T)
    cert = certify(cloud, CAM, model, "tx", 0.01, "cms", CertifyConfig(imaging="paper", n0=20, n=n, alpha=alpha, seed=0, cms_sigma=s))
    assert isinstance(cert, Certificate)
    assert cert.method == "cms" and cert.num_bounds == 1 and cert.n0 == 20 and cert.n == n and cert.alpha == alpha
    assert cert.label == 1 and cert.class_name == "bright" and cert.bounds["count"] == n
    assert cert.bounds["motion_sigma"] == s and cert.frames_rendered == 20 + n
    assert cert.p_a_lower[0] == pytest.approx(alpha ** (1 / n), rel=1e-9)
    assert cert.radius == pytest.approx(s * norm.ppf(alpha ** (1 / n)), rel=1e-9)
    assert cert.status == STATUS_CERTIFIED and cert.certified  # 0.01 < R = 0.072


def test_certify_bad_input(model, scenes, tmp_path):
    cloud = scenes["one_frame"]
    cfg = CertifyConfig(imaging="paper", n0=10, n=10)
    with pytest.raises(PwsError):
        certify(Cloud(np.zeros((0, 3)), np.zeros((0, 3))), CAM, model, "tx", 0.05, "pws_of", cfg)
    with pytest.raises(PwsError):
        certify(Cloud(np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3))), CAM, model, "tx", 0.05, "pws_of", cfg)
    # paper imaging rescales the camera to the model's input; surfel imaging needs a camera at least that big
    big = load_model(save_model(LinearNet(2), tmp_path / "lin.pt", ["a", "b"], input_size=(2 * CAM.height, 2 * CAM.width)))
    assert certify(cloud, CAM, big, "tx", 0.05, "pws_of", cfg).bounds["imaging"]["width"] == 2 * CAM.width
    with pytest.raises(PwsError, match="smaller than the classifier's input"):
        certify(cloud, CAM, big, "tx", 0.05, "pws_of", CertifyConfig(n0=10, n=10))
    for r in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(PwsError):
            certify(cloud, CAM, model, "tx", r, "pws_of", cfg)
    with pytest.raises(PwsError):
        certify(cloud, CAM, model, "tw", 0.05, "pws_of", cfg)
    with pytest.raises(PwsError):
        certify(cloud, CAM, model, "tx", 0.05, "pws_x", cfg)
    for bad in (dict(coverage="all"), dict(sigma=0.0), dict(n=0), dict(alpha=1.0), dict(num_anchors=0), dict(batch_size=0)):
        with pytest.raises(PwsError):
            certify(cloud, CAM, model, "tx", 0.05, "pws_of", CertifyConfig(imaging="paper", **{**dict(n0=10, n=10), **bad}))
    plan = plan_partitions(cloud, CAM, "tx", 0.05, "pws_of")
    with pytest.raises(PwsError):
        certify(cloud, CAM, model, "ty", 0.05, "pws_of", cfg, plan=plan)  # plan for another axis
    with pytest.raises(PwsError):
        certify(cloud, CAM, model, "tx", 0.06, "pws_of", cfg, plan=plan)  # plan for another radius


def test_coverage_at_an_exact_crossing_instant(model, scenes):
    cloud = scenes["one_frame"]
    radius = 0.08
    config = CertifyConfig(imaging="paper", sigma=SIGMA, n0=32, n=150, alpha=0.001, seed=11, batch_size=1000, max_partitions=400,
                           coverage="pairwise")
    plan = plan_partitions(cloud, CAM, "tx", radius, "pws", max_partitions=400)
    cert = certify(cloud, CAM, model, "tx", radius, "pws", config, plan=plan)
    assert cert.status == STATUS_CERTIFIED
    check_certificate(cert, cloud, plan, config, alphas=[-0.07, 0.01, 0.03])


def test_certify_returns_the_plan_it_rests_on_and_never_serialises_it():
    """certify returns what it produces: cert.plan is the grid the certificate rests on (refined by the
    adaptive anchors: its partitions are the certificate's), and the JSON of a certificate leaves it out."""
    import json

    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.certify import CertifyConfig, certify
    from pws_ros.core.cloud import cloud_from_rgbd
    from pws_ros.core.model import load_model, save_model

    cam = CameraIntrinsics(16, 12, 14.0, 15.0, 7.5, 5.5, "cam")
    rng = np.random.default_rng(3)
    cloud = cloud_from_rgbd(rng.uniform(1.0, 1.5, cam.shape), rng.random(cam.shape + (3,)).astype(np.float32), cam)
    import tempfile
    from pathlib import Path

    from conftest import MeanThresholdNet

    with tempfile.TemporaryDirectory() as d:
        model = load_model(save_model(MeanThresholdNet(0.3), Path(d) / "m.pt", ["a", "b"], input_size=(3, 4)))
        cert = certify(cloud, cam, model, "tz", 0.01, "pws_of", CertifyConfig(n0=16, n=32, num_anchors=3))
    assert cert.plan is not None and cert.plan.num_partitions == cert.num_partitions and 0.0 in cert.plan.alphas
    d = cert.to_dict()
    assert "plan" not in d and json.loads(cert.to_json())["num_partitions"] == cert.num_partitions


@pytest.mark.parametrize("axis", ["tz", "ry"])
def test_refined_hulls_reuse_kept_segments_and_equal_a_fresh_bound(axis):
    """The adaptive anchors refine a grid and bound only its new segments (core.anchor_geometry.refined_hulls): the
    result equals, bitwise, the bounds of the refined grid computed from scratch (a segment's bounds depend
    on its two ends only), also where new segments come in several runs."""
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.certify import refined_hulls
    from pws_ros.core.cloud import cloud_from_rgbd
    from pws_ros.core.imaging import hulls_within, make_imaging, make_renderer

    cam = CameraIntrinsics(16, 12, 14.0, 15.0, 7.5, 5.5, "cam")
    rng = np.random.default_rng(11)
    depth = rng.uniform(0.8, 1.6, cam.shape)
    depth[rng.random(cam.shape) < 0.2] = 0.0
    cloud = cloud_from_rgbd(depth, rng.random(cam.shape + (3,)).astype(np.float32), cam)
    im = make_imaging("surfel", cam, (3, 4), border=0, uncovered="frame")
    b = 0.03
    r = make_renderer(cloud, im, axis, alpha_range=(-b, b))
    bounds_of = hulls_within(r, -b, b)
    coarse = np.linspace(-b, b, 7)
    coarse[3] = 0.0
    fine = np.union1d(coarse, [-0.025, -0.021, 0.004, 0.006, 0.029])   # three runs of new segments
    got = refined_hulls(bounds_of, coarse, bounds_of(coarse), fine)
    want = hulls_within(r, -b, b)(fine)
    for name in ("lo", "hi", "constant"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    np.testing.assert_array_equal(got.alphas, fine)


@pytest.mark.parametrize("coverage", COVERAGES)
@pytest.mark.parametrize("alphas, bad", [([-1.0, -0.1, 0.0, 0.5, 1.0], 0), ([-1.0, -0.5, 0.0, 0.1, 1.0], 3)])
def test_a_grid_not_symmetric_about_0_certifies_only_what_both_sides_cover(coverage, alphas, bad):
    """Every-frame rules read the radius from the segments covered on both sides of 0: on a grid that is not
    symmetric (a received or given plan may be any increasing grid holding 0), segment ``bad`` may show a value
    far from every frame (a disocclusion), so no motion inside it is covered; the radius is the smaller of the two
    covered ends, here 0.1 on either side (segments [-0.1, 0] and [0, 0.1] hold motions the claim covers)."""
    from pws_ros.core.bounds import RenderedPlan, SegmentValues
    from pws_ros.replay.ceiling import never_changing_model

    import torch

    alphas = np.asarray(alphas)
    h, w = 4, 4
    frames = np.full((len(alphas), h, w, 3), 0.5, np.float32)
    values = SegmentValues(alphas, np.array([bad]), np.array([0]), np.array([[60.0, 60.0, 60.0]], np.float32), (h, w))
    plan = Plan("pws_of", "tx", 1.0, float(np.diff(alphas).max()), len(alphas), alphas, "m", {"imaging": "paper"})
    rendered = RenderedPlan(plan, torch.from_numpy(frames), values.pair_bound_sq(frames), values)
    cfg = CertifyConfig(coverage=coverage, n0=16, n=200, alpha=0.01, num_anchors=len(alphas))
    cert = certify_rendered(rendered, never_changing_model((h, w)), cfg)
    # the independent reading: the largest Cohen radius of the bounds, and the bad segment's
    # squared distance from any frame (one pixel, three channels at 60 against 0.5) far beyond it
    R = _largest_cohen_radius(cert)
    assert 3 * (60.0 - 0.5) ** 2 > 4 * R * R
    assert cert.status == STATUS_NOT_CERTIFIED and cert.radius == pytest.approx(0.1)


def _largest_cohen_radius(cert) -> float:
    """The largest Cohen radius of a certificate's bounds, computed here (float64, scipy)."""
    return cert.sigma * float(norm.ppf(max(cert.p_a_lower)))

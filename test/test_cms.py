"""CMS on a toy scene whose decision boundary in motion space is known.

Scene: a bright square (Z = 0.95 m, half-size 2 cm, centred at X = X0) in front of a dark plane
(Z = 1 m). Classifier: class 1 iff the bright pixels' column centroid is left of the image centre.
Moving the camera by ``a`` along tx shifts the square's image by ``-fx a / Z``, so ``f`` says 1 iff
``a`` lies in ``(a_star, a_exit]``: ``a_star`` ~ X0 (centroid crosses the centre, within one pixel,
``Z / fx`` metres) and ``a_exit`` where the square leaves the image on the left. Both ends are
found by bisection through the real renderer + classifier; the motion-smoothed classifier's
probability is then ``p(d) = Phi((a_exit - d)/s) - Phi((a_star - d)/s)``, which gives its exact
robust radius.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from pws_ros.core.cms import certify_cms
from pws_ros.core.errors import PwsError
from pws_ros.core.model import load_model
from pws_ros.core.render import render

W, H = 96, 48
FX = 200.0
Z_SQUARE = 0.95
HALF = 0.02
SIGMA = 0.05  # CMS_SIGMA["tx"]


class CentroidLeftNet(torch.nn.Module):
    """Logits (-1, 1) -> class 1 iff the column centroid of the bright pixels (channel 0 > 1/2) is
    left of the image centre (class 0 when there is none)."""

    def __init__(self, width: int):
        super().__init__()
        self.width = int(width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = (x[:, 0] > 0.5).to(x.dtype)
        cols = torch.arange(self.width, dtype=x.dtype, device=x.device) + 0.5
        mass = w.sum(dim=(1, 2))
        centroid = (w.sum(dim=1) * cols).sum(dim=1) / mass.clamp_min(1e-6)
        left = (mass > 0.5) & (centroid < 0.5 * self.width)
        score = torch.where(left, torch.ones_like(mass), -torch.ones_like(mass))
        return torch.stack([-score, score], dim=1)


@pytest.fixture(scope="module")
def camera() -> CameraIntrinsics:
    return CameraIntrinsics(width=W, height=H, fx=FX, fy=FX, cx=(W - 1) / 2, cy=(H - 1) / 2)


def toy_cloud(x0: float) -> Cloud:
    g = np.arange(-HALF, HALF + 1e-9, 0.002)
    sx, sy = np.meshgrid(g + x0, g)
    square = np.stack([sx.ravel(), sy.ravel(), np.full(sx.size, Z_SQUARE)], axis=1)
    px, py = np.meshgrid(np.arange(-0.5, 0.5 + 1e-9, 0.01), np.arange(-0.2, 0.2 + 1e-9, 0.01))
    plane = np.stack([px.ravel(), py.ravel(), np.ones(px.size)], axis=1)
    points = np.concatenate([square, plane])
    colors = np.concatenate([np.ones((len(square), 3)), np.full((len(plane), 3), 0.05)]).astype(np.float32)
    return Cloud(points, colors)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    from pws_ros.core.model import save_model

    path = save_model(CentroidLeftNet(W), tmp_path_factory.mktemp("cms") / "centroid.pt", ["right", "left"], input_size=(H, W))
    return load_model(path)


def f_of_motion(cloud, camera, model, a: float, axis: str = "tx") -> int:
    frame = torch.from_numpy(render(cloud, camera, axis, [a]))
    return int(model(frame.permute(0, 3, 1, 2).contiguous()).argmax(1)[0])


def boundary(cloud, camera, model, lo: float, hi: float, axis: str = "tx") -> float:
    """The motion where f changes between lo and hi (f(lo) != f(hi)), to 1e-7."""
    flo = f_of_motion(cloud, camera, model, lo, axis)
    assert f_of_motion(cloud, camera, model, hi, axis) != flo
    while hi - lo > 1e-7:
        mid = 0.5 * (lo + hi)
        if f_of_motion(cloud, camera, model, mid, axis) == flo:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def smoothed_p(d, a_star, a_exit, s=SIGMA):
    return norm.cdf((a_exit - d) / s) - norm.cdf((a_star - d) / s)


def true_robust_radius(a_star, a_exit, s=SIGMA) -> float:
    """Distance from 0 to the nearest d with p(d) = 1/2 (p is unimodal, p(0) > 1/2)."""
    mid = 0.5 * (a_star + a_exit)
    assert smoothed_p(0.0, a_star, a_exit, s) > 0.5

    def solve(lo, hi, increasing):
        for _ in range(200):
            m = 0.5 * (lo + hi)
            if (smoothed_p(m, a_star, a_exit, s) < 0.5) == increasing:
                lo = m
            else:
                hi = m
        return 0.5 * (lo + hi)

    d_lo = solve(a_star - 10 * s, min(0.0, mid), True)
    d_hi = solve(max(0.0, mid), a_exit + 10 * s, False)
    return min(-d_lo, d_hi)


@pytest.fixture(scope="module")
def left_scene(camera, model):
    x0 = -0.03
    cloud = toy_cloud(x0)
    a_star = boundary(cloud, camera, model, -0.1, 0.0)
    a_exit = boundary(cloud, camera, model, 0.1, 0.5)
    return cloud, x0, a_star, a_exit


def test_toy_boundary_matches_analysis(left_scene, camera, model):
    cloud, x0, a_star, a_exit = left_scene
    pixel = Z_SQUARE / FX
    assert abs(a_star - x0) <= pixel  # the centroid crosses the centre within one pixel of X0
    # the square's right edge leaves the image (u < 0) around X0 + HALF + (W/2) Z / fx
    assert abs(a_exit - (x0 + HALF + 0.5 * W * Z_SQUARE / FX)) <= pixel
    assert f_of_motion(cloud, camera, model, 0.0) == 1
    assert f_of_motion(cloud, camera, model, a_star - 0.01) == 0


def test_cms_radius_sound_and_certifies_small_radius(left_scene, camera, model):
    cloud, _, a_star, a_exit = left_scene
    r_true = true_robust_radius(a_star, a_exit)
    p_true = smoothed_p(0.0, a_star, a_exit)
    assert 0.02 < r_true < 0.04 and 0.65 < p_true < 0.8
    ticks = []
    cert = certify_cms(cloud, camera, model, "tx", 0.01, n0=50, n=600, alpha=0.01, seed=1, batch_size=256,
                       progress=lambda d, t: ticks.append((d, t)))
    assert cert.status == "certified" and cert.certified
    assert cert.label == 1 and cert.class_name == "left"
    R = cert.bounds["R"]
    assert cert.radius == R and 0.01 < R <= r_true  # certifies the small radius, never beyond the truth
    assert R == pytest.approx(SIGMA * norm.ppf(cert.p_a_lower[0]), rel=1e-12)
    # the estimate samples motion with the right sigma: the vote frequency matches p(0)
    freq = cert.bounds["count"] / 600
    assert abs(freq - p_true) <= 4.5 * math.sqrt(p_true * (1 - p_true) / 600)
    assert cert.p_a_lower[0] <= p_true
    # bookkeeping
    assert (cert.method, cert.coverage, cert.unit, cert.axis) == ("cms", "cms", "m", "tx")
    assert cert.sigma == SIGMA and cert.n0 == 50 and cert.n == 600 and cert.num_bounds == 1 and cert.num_partitions == 0
    assert cert.frames_rendered == 650 and cert.classifier_calls == 650 and cert.seed == 1
    assert set(cert.timings) >= {"render", "inference", "statistics", "total"}
    assert ticks[-1] == (650, 650) and len(ticks) >= 3
    cert.to_json()  # serialisable

    # a radius at or beyond R is not certified, with the same certified radius
    far = certify_cms(cloud, camera, model, "tx", 0.035, n0=50, n=600, alpha=0.01, seed=1, batch_size=256)
    assert far.status == "not_certified" and not far.certified and far.radius == R and far.reason


def test_cms_never_exceeds_true_radius_over_seeds(left_scene, camera, model):
    cloud, _, a_star, a_exit = left_scene
    r_true = true_robust_radius(a_star, a_exit)
    radii = [certify_cms(cloud, camera, model, "tx", 0.005, n0=20, n=200, seed=s, batch_size=220).radius for s in range(4)]
    assert all(0 < r <= r_true for r in radii)
    assert len(set(radii)) > 1  # seeds matter


def test_cms_deterministic(left_scene, camera, model):
    cloud = left_scene[0]
    a = certify_cms(cloud, camera, model, "tx", 0.01, n0=10, n=100, seed=7, batch_size=64)
    b = certify_cms(cloud, camera, model, "tx", 0.01, n0=10, n=100, seed=7, batch_size=33)
    assert a.bounds["count"] == b.bounds["count"] and a.radius == b.radius and a.p_a_lower == b.p_a_lower


def test_cms_mirror_and_abstain(camera, model):
    right = certify_cms(toy_cloud(+0.03), camera, model, "tx", 0.01, n0=20, n=300, seed=0)
    assert right.certified and right.label == 0 and right.class_name == "right"
    centred = certify_cms(toy_cloud(0.0), camera, model, "tx", 0.01, n0=20, n=300, seed=0)
    assert centred.status == "abstain" and not centred.certified and centred.radius == 0.0 and centred.label == -1
    assert centred.p_a_lower[0] <= 0.5


def test_cms_rotation_axis_is_sound(camera, model):
    """Under ry the square's image moves the same way: f = 1 ("left") for theta in (theta_star, theta_exit],
    theta_star ~ atan(X0 / Z) where the camera turns to face the square. Found by bisection through the
    renderer, the smoothed probability and the true robust radius follow as for tx; CMS in radians
    certifies a small rotation and never claims a radius beyond the true one."""
    cloud = toy_cloud(-0.03)
    s = 0.02
    t_star = boundary(cloud, camera, model, -0.1, 0.0, "ry")
    t_exit = boundary(cloud, camera, model, 0.1, 0.5, "ry")
    assert abs(t_star - math.atan(-0.03 / Z_SQUARE)) <= 1.5 / FX  # within a pixel and a half of the geometry
    r_true = true_robust_radius(t_star, t_exit, s)
    cert = certify_cms(cloud, camera, model, "RY", 0.01, n0=20, n=400, seed=0, motion_sigma=s)
    assert cert.axis == "ry" and cert.unit == "rad" and cert.sigma == s and cert.frames_rendered == 420
    assert cert.status == "certified" and cert.label == 1 and cert.class_name == "left"
    assert 0.01 < cert.radius <= r_true
    assert cert.p_a_lower[0] <= smoothed_p(0.0, t_star, t_exit, s)


def test_cms_rejects_bad_input(camera, model):
    cloud = toy_cloud(-0.03)
    for kwargs in ({"radius": 0.0}, {"radius": -0.01}, {"radius": float("nan")}, {"radius": math.inf},
                   {"radius": 0.01, "n0": 0}, {"radius": 0.01, "n": 0}, {"radius": 0.01, "alpha": 1.0},
                   {"radius": 0.01, "alpha": 0.0}, {"radius": 0.01, "motion_sigma": 0.0}, {"radius": 0.01, "batch_size": 0}):
        radius = kwargs.pop("radius")
        with pytest.raises(PwsError):
            certify_cms(cloud, camera, model, "tx", radius, **kwargs)
    with pytest.raises(PwsError, match="unknown motion axis"):
        certify_cms(cloud, camera, model, "tw", 0.01)
    with pytest.raises(PwsError, match="empty"):
        certify_cms(Cloud(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)), camera, model, "tx", 0.01)
    with pytest.raises(PwsError, match="in front of the camera"):
        certify_cms(Cloud(-np.ones((4, 3)), np.ones((4, 3))), camera, model, "tx", 0.01)
    small = CameraIntrinsics(width=48, height=24, fx=100.0, fy=100.0, cx=23.5, cy=11.5)
    with pytest.raises(PwsError, match=r"expects 96x48 .* camera image is 48x24"):
        certify_cms(cloud, small, model, "tx", 0.01)

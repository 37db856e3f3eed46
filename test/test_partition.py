"""Partition planning: the grid, the PwS / PwS-L / PwS-OF steps against dense sweeps, C_delta (errata
pinned), the Plan JSON round trip and bad input."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import project
from pws_ros.core.partition import Plan, c_delta, inner_visits, make_grid, plan_partitions, validate_grid
from pws_ros.core.render import render

W, H = 12, 9
CAM = CameraIntrinsics(width=W, height=H, fx=13.0, fy=12.0, cx=5.5, cy=4.0)
RADIUS = {"tx": 0.1, "ty": 0.1, "tz": 0.2, "rx": 0.1, "ry": 0.1, "rz": 0.25}


# ---- the grid --------------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(radius=st.floats(1e-5, 10.0), ratio=st.floats(1e-3, 3.0))
def test_grid_properties(radius, ratio):
    delta = radius * ratio
    a = make_grid(radius, delta, max_partitions=10**6)
    m = len(a) // 2
    assert len(a) % 2 == 1 and len(a) >= 3
    assert a[m] == 0.0 and np.all(np.diff(a) > 0)
    # starts at -b, ends at +b (to the last bits; exactness is pinned in test_grid_ends_exactly_at_radius)
    assert abs(a[0] + radius) <= 4 * np.spacing(radius) and abs(a[-1] - radius) <= 4 * np.spacing(radius)
    steps = np.diff(a)
    assert steps.max() <= delta * (1 + 1e-11)
    # uniform
    np.testing.assert_allclose(steps, radius / m, rtol=1e-9)
    # never coarser than asked, never more than needed: 2 ceil(b / delta) + 1 (up to rounding of b / delta)
    q = radius / delta
    if abs(q - round(q)) > 1e-9 * max(1.0, q):
        assert len(a) == 2 * math.ceil(q) + 1
    else:
        assert len(a) in (2 * round(q) + 1, 2 * round(q) + 3, 3)
    validate_grid(a, radius)


def test_grid_known_values():
    np.testing.assert_allclose(make_grid(1.0, 0.5), [-1, -0.5, 0, 0.5, 1])
    np.testing.assert_allclose(make_grid(1.0, 0.4), [-1, -2 / 3, -1 / 3, 0, 1 / 3, 2 / 3, 1])
    np.testing.assert_allclose(make_grid(1.0, 5.0), [-1, 0, 1])  # delta > b: one segment each side
    assert len(make_grid(0.01, 1e-4)) == 201


@pytest.mark.parametrize("radius", [0.7, 0.1, 0.2])
def test_grid_ends_exactly_at_radius(radius):
    a = make_grid(radius, radius / 3)
    assert a[0] == -radius and a[-1] == radius


def test_grid_cap_makes_a_coarser_grid_never_a_truncated_one():
    assert len(make_grid(1.0, 0.01, max_partitions=201)) == 201
    coarse = make_grid(1.0, 0.01, max_partitions=200)  # 199 frames over the whole [-1, 1], step 1/99
    assert len(coarse) == 199 and coarse[0] == -1.0 and coarse[-1] == 1.0 and 0.0 in coarse
    np.testing.assert_allclose(np.diff(coarse), 1 / 99, rtol=1e-12)
    with pytest.raises(PwsError):
        make_grid(1.0, 0.0)
    with pytest.raises(PwsError):
        make_grid(1.0, float("nan"))
    with pytest.raises(PwsError):
        make_grid(-1.0, 0.1)


def test_validate_grid_rejects_bad_grids():
    good = make_grid(1.0, 0.25)
    validate_grid(good, 1.0)
    for bad in (good[1:], good[:-1], good + 0.01, good[::-1], np.array([-1.0, -0.5, 0.5, 1.0]), np.array([0.0])):
        with pytest.raises(PwsError):
            validate_grid(bad, 1.0)
    with pytest.raises(PwsError):
        validate_grid(np.array([-1.0, 0.0, np.nan, 1.0]), 1.0)


# ---- scenes ----------------------------------------------------------------------------------

def one_frame_cloud(seed: int, noise: bool = True) -> Cloud:
    rng = np.random.default_rng(seed)
    depth = np.full((H, W), rng.uniform(1.5, 2.5))
    if noise:
        depth += rng.normal(0, 0.02, (H, W))
    depth[2:6, 3:8] = rng.uniform(0.9, 1.2)  # a near box: occlusion and holes when moving
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    return cloud_from_rgbd(depth, rgb, CAM)


def dense_cloud(seed: int) -> Cloud:
    rng = np.random.default_rng(seed)
    n = 60
    z = np.concatenate([rng.uniform(0.9, 1.3, n // 2), rng.uniform(1.6, 3.0, n - n // 2)])
    x = rng.uniform(-0.6, 0.6, n) * z
    y = rng.uniform(-0.5, 0.5, n) * z
    return Cloud(np.stack([x, y, z], 1), rng.random((n, 3)).astype(np.float32))


def unique_colours(cloud: Cloud) -> Cloud:
    """The same points, each with its own colour (channel 0 = (i + 1) / (N + 1)), to read winners off frames."""
    n = len(cloud)
    c = np.zeros((n, 3), np.float32)
    c[:, 0] = (np.arange(n) + 1) / np.float32(n + 1)
    return Cloud(cloud.points, c)


def dense_runs(cloud: Cloud, axis: str, radius: float, window: float, K: int = 12001):
    """(lower, upper) bounds on the shortest consistent interval (run of one winning point at one pixel)
    that intersects (-b, b) inside the window, read off a dense sweep; and the sample step."""
    cc = unique_colours(cloud)
    n = len(cc)
    lo, hi = -window * radius, window * radius
    g = np.linspace(lo, hi, K)
    h = g[1] - g[0]
    f = render(cc, CAM, axis, g, background=0.0)[..., 0].reshape(K, -1)
    ident = np.rint(f * (n + 1)).astype(np.int64) - 1  # -1: hole
    lower, upper = math.inf, math.inf
    for p in range(ident.shape[1]):
        s = ident[:, p]
        cut = np.nonzero(np.diff(s))[0]
        starts = np.concatenate([[0], cut + 1])
        ends = np.concatenate([cut, [K - 1]])
        for k0, k1 in zip(starts, ends):
            if s[k0] < 0 or k0 == 0 or k1 == K - 1:
                continue
            if g[k1] > -radius and g[k0] < radius:  # surely intersects (-b, b)
                upper = min(upper, (k1 - k0 + 2) * h)
            if g[k1 + 1] > -radius and g[k0 - 1] < radius:  # possibly intersects
                lower = min(lower, (k1 - k0) * h)
    return lower, upper, h


# rx/ry only on scenes where no two points' depth order can cross inside a pixel (flat depth levels):
# see test_pws_delta_with_depth_order_crossing for the others
CASES = [("one_frame", s, a) for s in (0, 1) for a in ("tx", "ty", "tz", "rz")] + \
        [("flat", s, a) for s in (0, 1) for a in ("rx", "ry")] + \
        [("dense", s, a) for s in (0, 1) for a in ("tx", "ty", "tz", "rz")]


def scene(kind: str, seed: int) -> Cloud:
    if kind == "dense":
        return dense_cloud(seed)
    return one_frame_cloud(seed, noise=(kind == "one_frame"))


@pytest.mark.parametrize("kind,seed,axis", CASES)
def test_pws_delta_is_the_shortest_consistent_interval(kind, seed, axis):
    cloud = scene(kind, seed)
    radius = RADIUS[axis]
    plan = plan_partitions(cloud, CAM, axis, radius, "pws")
    lower, upper, h = dense_runs(cloud, axis, radius, plan.details["window"])
    d = plan.delta_alpha
    assert d <= min(upper, radius) + 1e-12
    if d >= h:  # no run shorter than the dense step can hide between samples
        assert d >= min(lower, radius) - 1e-12
    assert plan.details["min_run"] <= upper + 1e-12
    # the grid realises the step
    assert plan.num_partitions == len(plan.alphas) and np.diff(plan.alphas).max() <= d * (1 + 1e-11)
    assert plan.alphas[0] == pytest.approx(-radius, abs=1e-15) and plan.alphas[-1] == pytest.approx(radius, abs=1e-15)


@pytest.mark.parametrize("kind,seed,axis", [("one_frame", 1, "rx"), ("one_frame", 2, "ry")])
def test_pws_delta_noisy_one_frame_rotation(kind, seed, axis):
    cloud = scene(kind, seed)
    radius = RADIUS[axis]
    plan = plan_partitions(cloud, CAM, axis, radius, "pws")
    lower, upper, h = dense_runs(cloud, axis, radius, plan.details["window"])
    assert plan.delta_alpha <= min(upper, radius) + 1e-12


def test_pws_delta_with_depth_order_crossing():
    cam = CameraIntrinsics(width=14, height=10, fx=15.0, fy=14.0, cx=6.5, cy=4.5)
    pts = np.array([[-0.069, -0.669, 2.735], [-0.148, -0.508, 2.752]])
    cloud = unique_colours(Cloud(pts, np.zeros((2, 3), np.float32)))
    plan = plan_partitions(cloud, cam, "rx", 0.15, "pws")
    K = 24001
    g = np.linspace(-0.6, 0.6, K)
    f = render(cloud, cam, "rx", g, background=0.0)[..., 0].reshape(K, -1)
    p = 3 * 14 + 6
    s = np.rint(f[:, p] * 3).astype(int) - 1
    cut = np.nonzero(np.diff(s))[0]
    shortest = min((b - a) * (g[1] - g[0]) for a, b in zip(cut[:-1], cut[1:]) if s[a + 1] >= 0)
    assert shortest < 0.01  # point 1 wins pixel (3, 6) only for ~0.006 rad
    assert plan.delta_alpha <= shortest + 2 * (g[1] - g[0])


def dense_visit_upper(cloud: Cloud, axis: str, radius: float, window: float, K: int = 12001, min_extent: float = 0.0) -> float:
    """Upper bound on the shortest in-pixel visit (occlusion ignored) intersecting (-b, b), from a dense sweep;
    only visits whose sampled extent ``|rho(last) - rho(first)|_inf`` (a lower bound on the true one) is at
    least ``min_extent`` px count."""
    lo, hi = -window * radius, window * radius
    g = np.linspace(lo, hi, K)
    h = g[1] - g[0]
    u, v, z = project(cloud.points[:, None, :], CAM, axis, g[None, :])
    inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    key = np.where(inside, np.floor(np.where(inside, v, 0)) * W + np.floor(np.where(inside, u, 0)), -1).astype(np.int64)
    best = math.inf
    for p, s in enumerate(key):
        cut = np.nonzero(np.diff(s))[0]
        for k0, k1 in zip(np.concatenate([[0], cut + 1]), np.concatenate([cut, [K - 1]])):
            if s[k0] >= 0 and k0 > 0 and k1 < K - 1 and g[k1] > -radius and g[k0] < radius:
                if max(abs(u[p, k1] - u[p, k0]), abs(v[p, k1] - v[p, k0])) >= min_extent:
                    best = min(best, (k1 - k0 + 2) * h)
    return best


@pytest.mark.parametrize("kind,seed,axis", [c for c in CASES if c[1] == 0])
def test_pws_l_delta_is_below_every_visit(kind, seed, axis):
    """Thm 2: |rho(sup U) - rho(inf U)| / L_P <= |U| for every visit U, so delta_alpha (PwS-L) is no longer
    than the shortest visit of any point to any pixel."""
    cloud = scene(kind, seed)
    radius = RADIUS[axis]
    plan = plan_partitions(cloud, CAM, axis, radius, "pws_l")
    window = plan.details["window"]
    vis = inner_visits(cloud.points, CAM, axis, radius, window)
    assert plan.delta_alpha <= min(float((vis.t1 - vis.t0).max(initial=radius)), radius)
    ok = (vis.t1 - vis.t0) > 1e-9 * radius
    if ok.any():
        assert plan.delta_alpha <= float((vis.t1 - vis.t0)[ok].min()) * (1 + 1e-6)
    assert plan.delta_alpha <= dense_visit_upper(cloud, axis, radius, window) * (1 + 1e-6)


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
def test_pws_of_plan(axis):
    """Thm 3: delta_alpha = min over pixels of [min_P 1/(L_P + C_delta)] [min_P (extent - 2 delta)] over the
    visits spanning more than 2 delta px. For each such visit U that product is at most extent / L_P <= |U|,
    so the step never exceeds the shortest of them (dense sweep). Translations, in closed form: C_delta = 0,
    L_P = f / Z and a pixel crossing spans 1 px plus the two footprint overlaps (2e-6 px), so
    delta_alpha = Z_min (1 + 2e-6 - 2 delta) / f (Z_min: the near box)."""
    cloud = one_frame_cloud(0, noise=False)
    radius = RADIUS[axis]
    for d in (0.05, 0.2):
        plan = plan_partitions(cloud, CAM, axis, radius, "pws_of", delta=d)
        assert plan.method == "pws_of" and plan.axis == axis and plan.unit == ("m" if axis[0] == "t" else "rad")
        assert plan.details["delta_px"] == d
        assert 0 < plan.delta_alpha <= radius
        upper = dense_visit_upper(cloud, axis, radius, plan.details["window"], min_extent=2 * d + 1e-9)
        assert plan.delta_alpha <= upper * (1 + 1e-6)
        if axis in ("tx", "ty"):
            f = CAM.fx if axis == "tx" else CAM.fy
            assert plan.delta_alpha == pytest.approx(cloud.points[:, 2].min() * (1 + 2e-6 - 2 * d) / f, rel=1e-6)
        assert plan.num_partitions == len(plan.alphas) >= 3
        assert np.diff(plan.alphas).max() <= plan.delta_alpha * (1 + 1e-11)


def test_pws_l_point_through_a_pixel_corner():
    cam = CameraIntrinsics(width=16, height=12, fx=16.0, fy=15.0, cx=7.5, cy=5.5)
    # the centre of pixel (2, 12) at 1 m: under tz its ray passes exactly through pixel corners
    cloud = Cloud(np.array([[0.21875, -0.23333333333333334, 1.0]]), np.ones((1, 3), np.float32))
    plan = plan_partitions(cloud, cam, "tz", 0.3, "pws_l")
    assert plan.delta_alpha > 1e-6


@pytest.mark.parametrize("method", ["pws_l", "pws_of"])
def test_large_rotation_plans(method):
    cloud = Cloud(np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3), np.float32))
    assert plan_partitions(cloud, CAM, "ry", 0.5, "pws").num_partitions < 100
    plan = plan_partitions(cloud, CAM, "ry", 0.5, method)
    assert plan.delta_alpha > 1e-4


# ---- C_delta (Lemma D.2), errata pinned ------------------------------------------------------

def random_points(seed: int, n: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.8, 4.0, n)
    return np.stack([rng.uniform(-0.7, 0.7, n) * z, rng.uniform(-0.6, 0.6, n) * z, z], axis=1)


def paper_c_rx(P, fx, fy, b, delta):
    """Lemma D.2 for R_x, written out term by term from the paper (the positive form)."""
    best = 0.0
    for X, Y, Z in P:
        for th in (-b, b):
            c, s = math.cos(th), math.sin(th)
            den = -Y * s + Z * c
            t1 = delta / fy * (fx * abs(X) + fy * abs(Y * c + Z * s)) / den
            t2 = 2 * delta * abs(Y * c + Z * s) / den
            best = max(best, t1, t2)
    return delta**2 / fy + best


def paper_c_ry_fixed(P, fx, fy, b, delta):
    """Lemma D.2 for R_y with the erratum fixed: delta^2 / f_x (the paper prints delta^2 / f_y)."""
    best = 0.0
    for X, Y, Z in P:
        for th in (-b, b):
            c, s = math.cos(th), math.sin(th)
            den = X * s + Z * c
            t1 = 2 * delta * abs(X * c - Z * s) / den
            t2 = delta / fx * (fy * abs(Y) + fx * abs(X * c - Z * s)) / den
            best = max(best, t1, t2)
    return delta**2 / fx + best


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), b=st.floats(1e-3, 0.3), delta=st.floats(1e-3, 2.0),
       fx=st.floats(5.0, 2000.0), fy=st.floats(5.0, 2000.0))
def test_c_delta_closed_forms(seed, b, delta, fx, fy):
    P = random_points(seed)
    cam = CameraIntrinsics(width=64, height=48, fx=fx, fy=fy, cx=31.5, cy=23.5)
    assert c_delta(P, cam, "tx", b, delta) == 0.0
    assert c_delta(P, cam, "ty", b, delta) == 0.0
    assert c_delta(P, cam, "rz", b, delta) == pytest.approx(max(fx / fy, fy / fx) * delta, rel=1e-12)
    assert c_delta(P, cam, "tz", b, delta) == pytest.approx(max(delta / (Z - b) for Z in P[:, 2]), rel=1e-12)
    crx = c_delta(P, cam, "rx", b, delta)
    assert crx > 0  # the reference code's rx branch came out negative
    assert crx == pytest.approx(paper_c_rx(P, fx, fy, b, delta), rel=1e-10)
    cry = c_delta(P, cam, "ry", b, delta)
    assert cry > 0
    assert cry == pytest.approx(paper_c_ry_fixed(P, fx, fy, b, delta), rel=1e-10)
    # symmetry: R_y on a cloud is R_x on the cloud with x <-> y and fx <-> fy swapped
    swapped = P[:, [1, 0, 2]]
    cam_sw = CameraIntrinsics(width=48, height=64, fx=fy, fy=fx, cx=23.5, cy=31.5)
    assert cry == pytest.approx(c_delta(swapped, cam_sw, "rx", b, delta), rel=1e-12)
    # and C_delta grows with delta
    assert c_delta(P, cam, "rx", b, 2 * delta) > crx and c_delta(P, cam, "ry", b, 2 * delta) > cry


def test_c_delta_ry_uses_fx_not_fy():
    P = random_points(3)
    cam = CameraIntrinsics(width=64, height=48, fx=100.0, fy=400.0, cx=31.5, cy=23.5)
    d = 0.5
    printed = paper_c_ry_fixed(P, cam.fx, cam.fy, 0.1, d) - d**2 / cam.fx + d**2 / cam.fy  # the paper's delta^2/f_y
    assert c_delta(P, cam, "ry", 0.1, d) == pytest.approx(paper_c_ry_fixed(P, cam.fx, cam.fy, 0.1, d), rel=1e-12)
    assert c_delta(P, cam, "ry", 0.1, d) != pytest.approx(printed, rel=1e-9)


def test_c_delta_rejects_points_behind():
    P = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 2.0]])
    with pytest.raises(PwsError):
        c_delta(P, CAM, "tz", 0.2, 0.05)  # Z - b < 0
    with pytest.raises(PwsError):
        c_delta(np.array([[0.0, 5.0, 0.1]]), CAM, "rx", 0.1, 0.05)  # -Y s + Z c < 0 at theta = b
    with pytest.raises(PwsError):
        c_delta(np.array([[5.0, 0.0, 0.1]]), CAM, "ry", 0.1, 0.05)


# ---- Plan JSON round trip and bad input ------------------------------------------------------

@pytest.mark.parametrize("method", ["pws", "pws_l", "pws_of"])
def test_plan_json_round_trip(method, tmp_path):
    cloud = one_frame_cloud(1)
    plan = plan_partitions(cloud, CAM, "ry", 0.05, method)
    text = plan.to_json()
    back = Plan.from_dict(json.loads(text))
    assert (back.method, back.axis, back.radius, back.delta_alpha, back.num_partitions, back.unit) == \
           (plan.method, plan.axis, plan.radius, plan.delta_alpha, plan.num_partitions, plan.unit)
    np.testing.assert_array_equal(back.alphas, plan.alphas)
    assert back.details.keys() == plan.details.keys()
    path = tmp_path / "plan.json"
    plan.to_json(path)
    loaded = Plan.load(path)
    np.testing.assert_array_equal(loaded.alphas, plan.alphas)
    assert loaded.to_dict() == back.to_dict()


def test_plan_load_bad_input(tmp_path):
    plan = plan_partitions(one_frame_cloud(0), CAM, "tx", 0.05, "pws_of")
    d = plan.to_dict()
    for mutate in (lambda x: x.pop("alphas"), lambda x: x.pop("axis"), lambda x: x.update(axis="tw"),
                   lambda x: x.update(num_partitions=x["num_partitions"] + 2), lambda x: x.update(radius=1.0),
                   lambda x: x.update(alphas=x["alphas"][:-1]), lambda x: x.update(alphas=[a + 1e-3 for a in x["alphas"]]),
                   lambda x: x.update(delta_alpha="abc")):
        bad = json.loads(json.dumps(d))
        mutate(bad)
        with pytest.raises(PwsError):
            Plan.from_dict(bad)
    with pytest.raises(PwsError):
        Plan.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(PwsError):
        Plan.load(tmp_path / "bad.json")


@pytest.mark.parametrize("kwargs", [
    dict(radius=0.0), dict(radius=-0.1), dict(radius=float("nan")), dict(radius=float("inf")), dict(radius="abc"),
    dict(method="pws_x"), dict(method="cms"), dict(axis="tw"), dict(axis=""),
    dict(max_partitions=2), dict(max_partitions=10.5), dict(method="pws_of", delta=0.0), dict(method="pws_of", delta=float("nan")),
    dict(method="pws_of", delta=-1.0), dict(axis="tz", radius=5.0),
])
def test_plan_bad_input(kwargs):
    args = dict(axis="tx", radius=0.05, method="pws")
    args.update(kwargs)
    with pytest.raises(PwsError):
        plan_partitions(one_frame_cloud(0), CAM, args.pop("axis"), args.pop("radius"), args.pop("method"), **args)


def test_plan_bad_cloud():
    with pytest.raises(PwsError):
        plan_partitions(Cloud(np.zeros((0, 3)), np.zeros((0, 3))), CAM, "tx", 0.1, "pws")
    with pytest.raises(PwsError):
        plan_partitions(Cloud(np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3))), CAM, "tx", 0.1, "pws")


def test_plan_cap_coarsens_the_plan_instead_of_refusing():
    cloud = one_frame_cloud(0)
    full = plan_partitions(cloud, CAM, "tx", 0.1, "pws")
    assert full.num_partitions > 5
    capped = plan_partitions(cloud, CAM, "tx", 0.1, "pws", max_partitions=full.num_partitions - 2)
    assert capped.num_partitions == full.num_partitions - 2 and capped.details["coarsened_from"] == full.num_partitions
    assert capped.alphas[0] == -0.1 and capped.alphas[-1] == 0.1 and 0.0 in capped.alphas
    same = plan_partitions(cloud, CAM, "tx", 0.1, "pws", max_partitions=full.num_partitions)
    np.testing.assert_array_equal(same.alphas, full.alphas)


def test_axis_names_are_normalised():
    cloud = one_frame_cloud(0)
    assert plan_partitions(cloud, CAM, "Tx", 0.05, "pws").axis == "tx"
    assert plan_partitions(cloud, CAM, " RZ ", 0.05, "pws").axis == "rz"


def test_min_partitions_refines_a_coarse_plan():
    cloud = one_frame_cloud(0, noise=False)
    radius = RADIUS["ry"] / 20  # a sub-pixel motion: PwS-OF plans the minimum, 3 partitions
    plan = plan_partitions(cloud, CAM, "ry", radius, "pws_of")
    assert plan.num_partitions == 3 and "refined_for_min_partitions" not in plan.details
    fine = plan_partitions(cloud, CAM, "ry", radius, "pws_of", min_partitions=33)
    assert fine.num_partitions == 33 and fine.details["refined_for_min_partitions"] == 33
    assert fine.delta_alpha == plan.delta_alpha  # the method's delta_alpha is still reported
    validate_grid(fine.alphas, radius)
    np.testing.assert_allclose(np.diff(fine.alphas), radius / 16, rtol=1e-9)
    assert plan_partitions(cloud, CAM, "ry", radius, "pws_of", min_partitions=34).num_partitions == 35
    # a plan already finer than asked is left alone
    dense = plan_partitions(cloud, CAM, "tz", RADIUS["tz"], "pws_of")
    again = plan_partitions(cloud, CAM, "tz", RADIUS["tz"], "pws_of", min_partitions=5)
    assert dense.num_partitions > 5 and np.array_equal(dense.alphas, again.alphas)
    # max_partitions wins (a cost cap must not need a second setting lowered)
    assert plan_partitions(cloud, CAM, "ry", radius, "pws_of", min_partitions=10**6, max_partitions=1000).num_partitions == 999
    for bad in (-1, 2.5):
        with pytest.raises(PwsError):
            plan_partitions(cloud, CAM, "ry", radius, "pws_of", min_partitions=bad)


def test_plan_step_tz_with_no_point_near_the_view_is_a_plan_not_a_crash():
    """A cloud whose points all lie far outside the view (seen live: a big-endian PointCloud2 read
    little-endian) left nothing to take the nearest depth of; the check's message was built anyway and
    raised ValueError (zero-size minimum). Now the plan is made (nothing moves in the view)."""
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.cloud import Cloud
    from pws_ros.core.partition import plan_step

    cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    cloud = Cloud(np.array([[100.0, 0.0, 1.0], [-80.0, 50.0, 2.0]]), np.full((2, 3), 0.5))
    plan = plan_step(cloud, cam, "tz", 0.01)
    assert plan.alphas[0] == -0.01 and plan.alphas[-1] == 0.01 and 0.0 in plan.alphas

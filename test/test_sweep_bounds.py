"""Soundness of the per-segment bounds and faithfulness of the exact sweep, against the renderer.

Key property: for any frame ``x = x(alpha)`` with ``alpha`` in segment ``[alpha_i, alpha_{i+1}]`` of a plan,
``|x - x_i|^2 + |x - x_{i+1}|^2 <= pair_bound_sq[i]`` and ``|x - y|^2 <= D_i(y)^2`` for any anchor ``y``,
whatever the plan (PwS, PwS-L, PwS-OF, or a deliberately coarse grid with several pixel switches and
holes per segment).
"""
from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from pws_ros.core.bounds import SAFETY, render_plan, segment_values
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import AXES, pixel_span, project
from pws_ros.core.partition import Plan, make_grid, plan_partitions
from pws_ros.core.render import render
from pws_ros.core.sweep import compute_visits, pixel_states

W, H = 14, 10
CAM = CameraIntrinsics(width=W, height=H, fx=15.0, fy=14.0, cx=6.5, cy=4.5)
# radii that move the scene by one to a few pixels
RADIUS = {"tx": 0.15, "ty": 0.15, "tz": 0.3, "rx": 0.15, "ry": 0.15, "rz": 0.3}
MAX_PARTITIONS = 700
SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])


def one_frame_cloud(rng: np.random.Generator) -> Cloud:
    """Depth image with a near box (depth discontinuity), noise, and invalid pixels (holes)."""
    far = rng.uniform(1.5, 3.0)
    depth = np.full((H, W), far) + (rng.normal(0, 0.03, (H, W)) if rng.random() < 0.5 else 0.0)
    for _ in range(rng.integers(1, 3)):
        r0, c0 = rng.integers(0, H - 2), rng.integers(0, W - 2)
        depth[r0 : r0 + rng.integers(2, 6), c0 : c0 + rng.integers(2, 7)] = rng.uniform(0.8, far - 0.2)
    depth[rng.random((H, W)) < rng.uniform(0, 0.15)] = 0.0
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    return cloud_from_rgbd(depth, rgb, CAM)


def dense_cloud(rng: np.random.Generator) -> Cloud:
    """Random points in (and around) the frustum: a front layer and occluded points behind it."""
    n_front, n_back = int(rng.integers(20, 80)), int(rng.integers(20, 120))
    z = np.concatenate([rng.uniform(0.9, 1.3, n_front), rng.uniform(1.6, 3.0, n_back)])
    x = rng.uniform(-0.7, 0.7, len(z)) * z
    y = rng.uniform(-0.6, 0.6, len(z)) * z
    cols = rng.random((len(z), 3)).astype(np.float32)
    return Cloud(np.stack([x, y, z], axis=1), cols)


def make_plan(cloud: Cloud, axis: str, method: str, radius: float) -> Plan:
    if method == "coarse":
        alphas = make_grid(radius, radius / 3)
        return Plan("coarse", axis, radius, radius / 3, len(alphas), alphas)
    try:
        return plan_partitions(cloud, CAM, axis, radius, method, max_partitions=MAX_PARTITIONS)
    except PwsError as exc:  # the partition cap (or a radius reaching the cloud): skip this example
        assert "partitions" in str(exc) or "reaches" in str(exc) or "behind" in str(exc), str(exc)
        assume(False)
        raise


def sample_alphas(rng, alphas, k=24):
    """Random motion values: uniform over [-b, b] and one inside each of a few random segments."""
    seg = rng.integers(0, len(alphas) - 1, k)
    t = rng.random(k)
    a = alphas[seg] + t * (alphas[seg + 1] - alphas[seg])
    return np.concatenate([a, rng.uniform(alphas[0], alphas[-1], k)])


def boundary_alphas(rng, cloud, axis, alphas, k=16):
    """The adversarial instants: computed visit boundaries and their float neighbours (where a hand-over
    of two equal-depth points, or a rounding difference between the sweep and the renderer, bites)."""
    vis = compute_visits(cloud.points, CAM, axis, float(alphas[0]), float(alphas[-1]))
    t = np.concatenate([vis.t0, vis.t1])
    t = t[(t > alphas[0]) & (t < alphas[-1])]
    if len(t) == 0:
        return np.zeros(0)
    t = rng.choice(t, min(k, len(t)), replace=False)
    out = [t]
    for steps in (1, 2):
        up, down = t.copy(), t.copy()
        for _ in range(steps):
            up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
        out += [up, down]
    a = np.concatenate(out)
    return a[(a >= alphas[0]) & (a <= alphas[-1])]


def sqdist(a, b):
    return ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).reshape(len(a), -1).sum(axis=1)


@SETTINGS
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["one_frame", "dense"]), axis=st.sampled_from(AXES),
       method=st.sampled_from(["pws", "pws_l", "pws_of", "coarse"]), background=st.sampled_from([0.0, 1.0]))
def test_segment_bounds_are_sound(seed, kind, axis, method, background):
    rng = np.random.default_rng(seed)
    cloud = one_frame_cloud(rng) if kind == "one_frame" else dense_cloud(rng)
    radius = RADIUS[axis] * rng.uniform(0.5, 1.5)
    plan = make_plan(cloud, axis, method, radius)
    rp = render_plan(cloud, CAM, plan, background=background)
    frames = rp.frames.numpy()
    alphas = plan.alphas
    assert frames.shape == (len(alphas), H, W, 3)
    assert rp.pair_bound_sq.shape == (len(alphas) - 1,)
    # the plan frames are the renderer's frames
    np.testing.assert_array_equal(frames, render(cloud, CAM, axis, alphas, background=background))

    a = np.concatenate([sample_alphas(rng, alphas), boundary_alphas(rng, cloud, axis, alphas)])
    x = render(cloud, CAM, axis, a, background=background)
    seg = np.clip(np.searchsorted(alphas, a, side="right") - 1, 0, len(alphas) - 2)
    lhs = sqdist(x, frames[seg]) + sqdist(x, frames[seg + 1])
    bad = lhs > rp.pair_bound_sq[seg]
    assert not bad.any(), (f"pair bound violated at alpha={a[bad]}, segment {seg[bad]}: "
                           f"{lhs[bad]} > {rp.pair_bound_sq[seg][bad]}")
    # anchors: a plan frame and an arbitrary image
    for y in (frames[rng.integers(0, len(alphas))], rng.random((H, W, 3)).astype(np.float32)):
        D2 = rp.values.anchor_dist_sq(frames, y)
        assert D2.shape == (len(alphas) - 1,)
        d = sqdist(x, np.broadcast_to(y, x.shape))
        assert np.all(d <= D2[seg]), f"anchor bound violated: {d[d > D2[seg]]} > {D2[seg][d > D2[seg]]}"
        # the bound is never below what the end frames themselves give
        assert np.all(D2 >= np.maximum(sqdist(frames[:-1], np.broadcast_to(y, frames[:-1].shape)),
                                       sqdist(frames[1:], np.broadcast_to(y, frames[1:].shape))))

    # Lemma 1 per segment: when no extra value (or only the end frames' own values) can show up in
    # segment i, the bound is exactly |x_i - x_{i+1}|^2 (times the safety factor)
    base = sqdist(frames[:-1], frames[1:])
    assert np.all(rp.pair_bound_sq >= base)
    v = rp.values
    flat = frames.reshape(len(alphas), -1, 3)
    only_ends = np.ones(len(alphas) - 1, bool)
    if len(v.seg):
        at_a = np.all(v.val == flat[v.seg, v.pix], axis=1)
        at_b = np.all(v.val == flat[v.seg + 1, v.pix], axis=1)
        np.logical_and.at(only_ends, v.seg, at_a | at_b)
    np.testing.assert_allclose(rp.pair_bound_sq[only_ends], base[only_ends] * SAFETY, rtol=1e-12, atol=1e-300)


def test_coarse_grid_bound_is_strict_where_a_hole_opens():
    """A near square over a far plane (one-frame cloud): moving uncovers pixels with no point (holes).
    With a single segment, the bound must cover the hole value that neither end frame shows."""
    depth = np.full((H, W), 2.0)
    depth[3:7, 4:9] = 1.0
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[3:7, 4:9] = 255
    rgb[depth == 2.0] = 100
    cloud = cloud_from_rgbd(depth, rgb, CAM)
    alphas = np.array([-0.2, 0.0, 0.2])
    plan = Plan("coarse", "tx", 0.2, 0.2, 3, alphas)
    rp = render_plan(cloud, CAM, plan, background=0.0)
    frames = rp.frames.numpy()
    dense = np.linspace(-0.2, 0.2, 201)
    x = render(cloud, CAM, "tx", dense, background=0.0)
    # a hole really opens in between: some pixel is empty where both end frames of its segment show a point
    seg_ = np.clip(np.searchsorted(alphas, dense, side="right") - 1, 0, 1)
    holes = [(xi.sum(axis=2) == 0) & (frames[k].sum(axis=2) > 0) & (frames[k + 1].sum(axis=2) > 0) for xi, k in zip(x, seg_)]
    assert any(h.any() for h in holes)
    seg = np.clip(np.searchsorted(alphas, dense, side="right") - 1, 0, 1)
    lhs = sqdist(x, frames[seg]) + sqdist(x, frames[seg + 1])
    assert np.all(lhs <= rp.pair_bound_sq[seg])
    assert np.all(rp.pair_bound_sq > sqdist(frames[:-1], frames[1:]))


# ---- the exact sweep against dense sampling --------------------------------------------------

def _interval_at(st, alpha):
    """Per pixel, the index of the elementary interval containing alpha and its distance to the ends."""
    npix = H * W
    out = np.empty(npix, dtype=np.int64)
    margin = np.empty(npix)
    for p in range(npix):
        lo, hi = np.searchsorted(st.pix, p, "left"), np.searchsorted(st.pix, p, "right")
        assert hi > lo, f"pixel {p} has no interval"
        s, e = st.start[lo:hi], st.end[lo:hi]
        # tiling: starts at lo, ends at hi, contiguous
        assert s[0] == st.lo and e[-1] == st.hi and np.all(s[1:] == e[:-1]) and np.all(e > s)
        j = lo + min(int(np.searchsorted(e, alpha, "left")), hi - lo - 1)
        out[p] = j
        margin[p] = min(alpha - st.start[j], st.end[j] - alpha)
    return out, margin


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["one_frame", "dense"]), axis=st.sampled_from(AXES))
def test_pixel_states_winner_is_the_rendered_value(seed, kind, axis):
    rng = np.random.default_rng(seed)
    cloud = one_frame_cloud(rng) if kind == "one_frame" else dense_cloud(rng)
    b = RADIUS[axis]
    st_ = pixel_states(cloud.points, CAM, axis, -b, b)
    assert len(st_.cand_ptr) == len(st_.pix) + 1 and st_.cand_ptr[-1] == len(st_.cand_point)
    assert np.all(st_.num_candidates >= 1)
    bg = 0.5
    colors = np.concatenate([cloud.colors, np.full((1, 3), bg, np.float32)])
    alphas = rng.uniform(-b, b, 6)
    frames = render(cloud, CAM, axis, alphas, background=bg).reshape(len(alphas), -1, 3)
    for a, fr in zip(alphas, frames):
        j, margin = _interval_at(st_, a)
        ok = margin > 1e-9 * b
        winner = st_.winner[j]
        expect = colors[np.where(winner < 0, len(cloud.colors), winner)]
        # the winner is what the renderer shows (depth-order crossings under rx/ry are breakpoints)
        np.testing.assert_array_equal(fr[ok], expect[ok])
        # the shown value is always one of the interval's candidates (what the bounds rely on)
        for p in np.nonzero(ok)[0]:
            cands = st_.cand_point[st_.cand_ptr[j[p]] : st_.cand_ptr[j[p] + 1]]
            cand_cols = colors[np.where(cands < 0, len(cloud.colors), cands)]
            assert np.any(np.all(cand_cols == fr[p], axis=1)), f"pixel {p}: shown value not a candidate"


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["one_frame", "dense"]), axis=st.sampled_from(AXES))
def test_compute_visits_matches_dense_sampling(seed, kind, axis):
    rng = np.random.default_rng(seed)
    cloud = one_frame_cloud(rng) if kind == "one_frame" else dense_cloud(rng)
    pts = cloud.points
    b = RADIUS[axis] * 2
    vis = compute_visits(pts, CAM, axis, -b, b)
    assert np.all(vis.t0 <= vis.t1) and np.all(vis.t0 >= -b) and np.all(vis.t1 <= b)
    assert np.all((vis.row >= 0) & (vis.row < H) & (vis.col >= 0) & (vis.col < W))
    K = 301
    grid = np.linspace(-b, b, K)
    u, v, z = project(pts[:, None, :], CAM, axis, grid[None, :])  # (N, K)
    # the footprint rule of the renderer (motion.pixel_span): up to 2 x 2 pixels per sample
    c_lo, c_hi = pixel_span(np.where(z > 0, u, -10.0))
    r_lo, r_hi = pixel_span(np.where(z > 0, v, -10.0))
    tol = 1e-9 * b
    foot = [(r, c) for r in (r_lo, r_hi) for c in (c_lo, c_hi)]
    covered = [np.zeros(u.shape, bool) for _ in foot]
    for p, r, c, t0, t1 in zip(vis.point, vis.row, vis.col, vis.t0, vis.t1):
        within = (grid >= t0 - tol) & (grid <= t1 + tol)
        strict = (grid > t0 + tol) & (grid < t1 - tol)
        # every sample strictly inside a visit has that pixel in its footprint, in front of the camera
        inside_fp = (z[p] > 0) & (r_lo[p] <= r) & (r <= r_hi[p]) & (c_lo[p] <= c) & (c <= c_hi[p])
        assert np.all(inside_fp[strict]), f"point {p} not in ({r},{c}) during [{t0},{t1}]"
        for (rr, cc), cov in zip(foot, covered):
            cov[p] |= within & (rr[p] == r) & (cc[p] == c)
    # every in-image footprint pixel of every sample lies in some visit of its point to that pixel
    for (rr, cc), cov in zip(foot, covered):
        inside = (z > 0) & (cc >= 0) & (cc < W) & (rr >= 0) & (rr < H)
        missing = inside & ~cov
        assert not missing.any(), f"{missing.sum()} in-image samples not in any visit, e.g. {np.argwhere(missing)[0]}"


def test_segment_values_reports_switching_pixels():
    """A single point sliding across three pixels in one segment: the middle pixel's value shows up
    only strictly inside the segment, so segment_values must list it (and the holes it leaves)."""
    # u(0) = 7.3, v = 5.21 (off a row edge, so the point is drawn in one row)
    pt = Cloud(np.array([[0.02, 0.05, 1.0]]), np.array([[1.0, 0.5, 0.25]], np.float32))
    # tx by a moves u by -fx a / Z = -15 a pixels: a = -0.1 .. 0.1 crosses three pixels
    alphas = np.array([-0.1, 0.0, 0.1])
    vals = segment_values(pt, CAM, "tx", alphas, background=0.0)
    u0 = project(pt.points, CAM, "tx", 0.0)[0][0]
    row = int(np.floor(project(pt.points, CAM, "tx", 0.0)[1][0]))
    for k, (a0, a1) in enumerate(zip(alphas[:-1], alphas[1:])):
        ua, ub = u0 - CAM.fx * a0, u0 - CAM.fx * a1
        cols = set(range(int(np.floor(min(ua, ub))), int(np.floor(max(ua, ub))) + 1))
        listed = {int(p) % W for p, s in zip(vals.pix, vals.seg) if s == k and int(p) // W == row}
        assert cols <= listed
    # and the bound of each segment covers the point sitting in the middle pixel
    x = render(pt, CAM, "tx", np.linspace(-0.1, 0.1, 101))
    plan = Plan("coarse", "tx", 0.1, 0.1, 3, alphas)
    rp = render_plan(pt, CAM, plan)
    f = rp.frames.numpy()
    seg = np.clip(np.searchsorted(alphas, np.linspace(-0.1, 0.1, 101), side="right") - 1, 0, 1)
    lhs = sqdist(x, f[seg]) + sqdist(x, f[seg + 1])
    assert np.all(lhs <= rp.pair_bound_sq[seg])
    # segment 0 (u: 8.8 -> 7.3) only swaps two pixels: Lemma 1, bound = |x_0 - x_1|^2 = 2 c^2; segment 1
    # (u: 7.3 -> 5.8) passes through pixel 6, shown by neither end: bound 4 c^2, reached there (tight)
    c2 = float((pt.colors.astype(np.float64) ** 2).sum())
    np.testing.assert_allclose(rp.pair_bound_sq, [2 * c2, 4 * c2], rtol=1e-8)
    np.testing.assert_allclose([lhs[seg == 0].max(), lhs[seg == 1].max()], [2 * c2, 4 * c2], rtol=1e-6)


# two points whose depth order flips under rx while both sit in pixel (3, 6); found by the property
# test above (dense scene, seed 200586) and reduced to two points
CROSSING_POINTS = np.array([[-0.069, -0.669, 2.735], [-0.148, -0.508, 2.752]])


def test_winner_follows_depth_order_crossing():
    from scipy.optimize import brentq

    pts = CROSSING_POINTS
    b = 0.15
    cloud = Cloud(pts, np.array([[1, 0, 0], [0, 1, 0]], np.float32))
    tc = brentq(lambda t: project(pts[:1], CAM, "rx", t)[2][0] - project(pts[1:], CAM, "rx", t)[2][0], 0.05, 0.15)
    st_ = pixel_states(pts, CAM, "rx", -b, b)
    p = 3 * W + 6
    for a in (tc - 0.002, tc + 0.002):
        j, margin = _interval_at(st_, a)
        assert margin[p] > 1e-4
        shown = render(cloud, CAM, "rx", [a], background=0.5).reshape(-1, 3)[p]
        # the shown point is a candidate (the bounds stay sound) ...
        cands = st_.cand_point[st_.cand_ptr[j[p]] : st_.cand_ptr[j[p] + 1]]
        assert any(np.array_equal(cloud.colors[c], shown) for c in cands)
        # ... but `winner` should be the shown point on both sides of the crossing
        np.testing.assert_array_equal(cloud.colors[st_.winner[j[p]]], shown)


def test_bound_at_merged_crossing_instant():
    cam = CameraIntrinsics(width=40, height=30, fx=40.0, fy=40.0, cx=19.5, cy=14.5)
    # the centres of pixels (15, 8) and (15, 9) at 0.8 m, as cloud_from_rgbd makes them
    pts = np.array([[(c - cam.cx) * 0.8 / cam.fx, 0.0, 0.8] for c in (8, 9)])
    cloud = Cloud(pts, np.ones((2, 3), np.float32))
    a = -0.07
    u = project(pts, cam, "tx", a)[0]
    assert math.floor(u[0]) == 11 and math.floor(u[1]) == 13  # pixel 12 is empty at this alpha
    alphas = make_grid(0.08, 0.08 / 11)
    plan = Plan("coarse", "tx", 0.08, 0.08 / 11, len(alphas), alphas)
    rp = render_plan(cloud, cam, plan)
    f = rp.frames.numpy()
    i = int(np.searchsorted(alphas, a, side="right") - 1)
    assert alphas[i] < a < alphas[i + 1]
    x = render(cloud, cam, "tx", [a])
    lhs = sqdist(x, f[i : i + 1]) + sqdist(x, f[i + 1 : i + 2])
    assert lhs[0] <= rp.pair_bound_sq[i]


def _pair_and_anchor_excess(cloud, cam, axis, alphas, poses, seg):
    """The largest ``|x - x_i|^2 + |x - x_{i+1}|^2 - pair_bound_sq[seg]`` and ``|x - y|^2 - D_seg(y)^2`` (every grid
    frame ``y`` an anchor) over the rendered frames ``x`` of ``poses`` (float64): > 0 is a violation."""
    values = segment_values(cloud, cam, axis, alphas, background=0.0)
    frames = render(cloud, cam, axis, alphas).astype(np.float64)
    x = render(cloud, cam, axis, poses).astype(np.float64)
    pair = ((x - frames[seg]) ** 2).sum((1, 2, 3)) + ((x - frames[seg + 1]) ** 2).sum((1, 2, 3))
    worst = float((pair - values.pair_bound_sq(frames)[seg]).max())
    for y in frames:
        d = ((x - y) ** 2).sum((1, 2, 3))
        worst = max(worst, float((d - values.anchor_dist_sq(frames, y)[seg]).max()))
    return worst


def test_a_point_crossing_the_image_just_before_its_pole_is_bounded():
    """tz: a point 1e-14 m off the optical axis at depth 1 m, in a segment running into its pole (alpha = 1): in
    the last ~1e-12 m before it the renderer draws it across rows 7..11. The sweep read a piece's range just inside
    its ends (1e-12 of the piece), so it listed none of those rows, and both bounds fell short (24 > 12, a fuzzer's
    find); a piece's range now reaches its ends, running to the image edge at a pole."""
    cam = CameraIntrinsics(width=16, height=12, fx=16.0, fy=16.0, cx=7.5, cy=5.5)
    cloud = Cloud(np.array([[0.0, 1e-14, 1.0]]), np.ones((1, 3), np.float32))
    poses = 1.0 - np.array([1e-13, 6.5e-14, 5e-14, 3.6e-14, 3e-14, 1e-12, 2e-16])   # v = 6 + 1.6e-13 / depth: rows 7 .. 11
    lit = render(cloud, cam, "tz", poses)[..., 0] > 0
    assert {r for r in range(12) if lit[:, r].any()} >= {7, 8, 9, 10, 11}   # the case this is about
    assert _pair_and_anchor_excess(cloud, cam, "tz", np.array([-1.2, 0.0, 1.2]), poses, 1) <= 0


def test_a_rotation_touching_a_footprint_edge_is_bounded():
    """rx: a point whose u extremum lies on a footprint edge (9 + PIXEL_OVERLAP): the torch renderer (1/Z' then a
    fused multiply-add) computed u one ulp below the sweep's numpy value there and drew it in column 8 for ~2e-8 rad,
    a pixel the sweep never listed (18 > 6, a fuzzer's find; it depends on how this CPU rounds). The bounds' sweep
    now counts a point possibly present within RENDER_SLACK_PX of its footprint and surely present only inside it
    by as much."""
    cam = CameraIntrinsics(width=16, height=12, fx=16.0, fy=16.0, cx=7.5, cy=5.5)
    cloud = Cloud(np.array([[0.10546741612418233, -0.08821160231884806, 1.6851697953671547]]), np.ones((1, 3), np.float32))
    r = 0.10974989110815422
    poses = 0.05229808424925814 + np.linspace(-3e-7, 3e-7, 121)
    assert _pair_and_anchor_excess(cloud, cam, "rx", np.array([-r, 0.0, r]), poses, 1) <= 0


def test_segment_values_list_each_value_of_a_pixel_once():
    """A value a pixel can show in a segment is listed once however many elementary intervals (or visits of the
    bounds' widened and narrowed footprints) hold it: the bounds take a max over the values, and the four-process
    mode sends them all (ry on this scene: 389,880 rows before, 73,800 after at 160x90)."""
    rng = np.random.default_rng(3)
    depth_m = np.full((H, W), 2.0)
    depth_m[2:8, 3:10] = 1.2
    cloud = cloud_from_rgbd(depth_m, rng.integers(0, 256, (H, W, 3), dtype=np.uint8), CAM)
    for axis in ("ry", "tx"):
        values = segment_values(cloud, CAM, axis, make_grid(RADIUS[axis], RADIUS[axis] / 4))
        rows = np.column_stack([values.seg, values.pix, values.val.view(np.int32)])
        assert len(rows) > 0 and len(np.unique(rows, axis=0)) == len(rows), axis

"""The z-buffer renderer against a plain per-point reference, and the motion conventions.

The reference renderer below loops over the points one by one (numpy): project, drop ``z <= 0`` and
points outside the image, ``floor`` to a pixel, keep the nearest depth and, on equal depth, the
lower point index; empty pixels show the background.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import AXES, PIXEL_OVERLAP, project, transform
from pws_ros.core.render import Renderer, render

W, H = 40, 30
CAM = CameraIntrinsics(width=W, height=H, fx=36.0, fy=33.0, cx=19.5, cy=14.5)
# motion ranges that move the scene by several pixels (and push points behind the camera for tz)
ALPHA_SCALE = {"tx": 0.4, "ty": 0.4, "tz": 1.5, "rx": 0.5, "ry": 0.5, "rz": 1.2}


def reference_render(points, colors, intr, axis, alpha, background):
    """Per-point z-buffer: nearest depth wins, ties to the lower index, z <= 0 and off-image dropped."""
    Hh, Ww = intr.height, intr.width
    frame = np.full((Hh, Ww, 3), np.float32(background), dtype=np.float32)
    depth = np.full((Hh, Ww), np.inf)
    owner = np.full((Hh, Ww), -1)
    u, v, z = project(points, intr, axis, alpha)
    for i in range(len(points)):
        if not (z[i] > 0):
            continue
        if not (0 <= u[i] < Ww and 0 <= v[i] < Hh):
            continue
        c, r = int(math.floor(u[i])), int(math.floor(v[i]))
        if z[i] < depth[r, c]:  # strict: an equal depth keeps the earlier (lower) index
            depth[r, c] = z[i]
            owner[r, c] = i
            frame[r, c] = colors[i]
    depth[owner < 0] = 0.0
    return frame, depth, owner


def random_scene(rng: np.random.Generator, n: int, ties: bool = True) -> Cloud:
    """Points in front of, beside and behind the camera; duplicated points and shared depths make ties."""
    z = rng.uniform(-0.5, 3.0, n)
    z[rng.random(n) < 0.5] = rng.uniform(0.5, 2.0)  # many points share one depth (ties under tx/ty/tz/rz)
    x = rng.uniform(-0.9, 0.9, n) * np.abs(z) + rng.normal(0, 0.05, n)
    y = rng.uniform(-0.9, 0.9, n) * np.abs(z) + rng.normal(0, 0.05, n)
    pts = np.stack([x, y, z], axis=1)
    cols = rng.random((n, 3)).astype(np.float32)
    if ties:
        k = max(1, n // 5)
        dup = rng.integers(0, n, k)
        pts = np.concatenate([pts, pts[dup]])  # same position and depth, later index
        cols = np.concatenate([cols, rng.random((k, 3)).astype(np.float32)])
        perm = rng.permutation(len(pts))
        pts, cols = pts[perm], cols[perm]
    return Cloud(pts, cols)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), n=st.integers(1, 120),
       background=st.sampled_from([0.0, 1.0, 0.25]), nalpha=st.integers(1, 4))
def test_render_equals_reference(seed, axis, n, background, nalpha):
    rng = np.random.default_rng(seed)
    cloud = random_scene(rng, n)
    alphas = rng.uniform(-1, 1, nalpha) * ALPHA_SCALE[axis]
    alphas[0] = 0.0 if rng.random() < 0.3 else alphas[0]
    frames, depths = render(cloud, CAM, axis, alphas, background=background, return_depth=True)
    assert frames.shape == (nalpha, H, W, 3) and frames.dtype == np.float32
    assert depths.shape == (nalpha, H, W)
    for b, a in enumerate(alphas):
        ref, ref_depth, _ = reference_render(cloud.points, cloud.colors, CAM, axis, a, background)
        np.testing.assert_array_equal(frames[b], ref)
        np.testing.assert_allclose(depths[b], ref_depth, rtol=1e-13, atol=0)  # torch and numpy sin/cos may differ by an ulp


def test_ties_go_to_lower_index():
    pts = np.array([[0.0, 0.0, 1.0], [0.001, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.9]])
    cols = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float32)
    # without the nearer point 3, points 0, 1, 2 share the centre pixel at equal depth: 0 wins
    f = render(Cloud(pts[:3], cols[:3]), CAM, "tx", [0.0])[0]
    np.testing.assert_array_equal(f[15, 20], [1, 0, 0])
    # reversed order: the (now) lowest index, the blue point, wins
    f = render(Cloud(pts[:3][::-1], cols[:3][::-1]), CAM, "tx", [0.0])[0]
    np.testing.assert_array_equal(f[15, 20], [0, 0, 1])
    # a nearer point beats any index
    f = render(Cloud(pts, cols), CAM, "tx", [0.0])[0]
    np.testing.assert_array_equal(f[15, 20], [1, 1, 1])


def test_behind_and_outside_points_are_dropped():
    pts = np.array([
        [0.0, 0.0, -1.0],     # behind: would project to the centre with a flipped sign
        [0.0, 0.0, 0.0],      # on the camera plane
        [5.0, 0.0, 1.0],      # far right, outside
        [-5.0, 0.0, 1.0],     # far left
        [0.0, 5.0, 1.0],      # below
        [0.0, -5.0, 1.0],     # above
    ])
    cols = np.ones((len(pts), 3), dtype=np.float32)
    frames = render(Cloud(pts, cols), CAM, "tx", [0.0, 0.01], background=0.5)
    assert np.all(frames == np.float32(0.5))
    # tz moving past the point puts it behind the camera (a point on the optical axis sits on the corner
    # of four pixels here, u = 20, v = 15, and is drawn in all four: motion.PIXEL_OVERLAP)
    one = Cloud(np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3), np.float32))
    f = render(one, CAM, "tz", [0.0, 0.999, 1.0, 1.5], background=0.0)
    assert f[0].sum() == 12 and f[1].sum() == 12 and f[2].sum() == 0 and f[3].sum() == 0
    assert f[0, 14:16, 19:21].sum() == 12


def test_pixel_footprints_overlap_by_pixel_overlap():
    """Pixel (r, c) covers u in [c - e, c + 1 + e) with e = PIXEL_OVERLAP: a point exactly on an edge is
    drawn on both sides of it (on the image border: inside only), one 2e beyond the border is dropped."""
    e = PIXEL_OVERLAP
    Z = 1.0
    v_row = 10.5  # mid-row: one row only

    def at(u):  # the point whose pixel-edge coordinates are (u, v_row) at alpha = 0
        return [(u - CAM.cx - 0.5) * Z / CAM.fx, (v_row - CAM.cy - 0.5) * Z / CAM.fy, Z]

    for u, cols in ((0.0, {0}), (float(W), {W - 1}), (-2 * e, set()), (W + 2 * e, set()), (5.0, {4, 5}),
                    (5.0 + 2 * e, {5}), (5.0 - 2 * e, {4}), (12.5, {12})):
        pts = np.array([at(u)])
        uu = project(pts, CAM, "tx", 0.0)[0][0]
        assert abs(uu - u) < 1e-12
        f = render(Cloud(pts, np.ones((1, 3), np.float32)), CAM, "tx", [0.0])[0]
        shown = set(np.nonzero(f[..., 0].sum(axis=0))[0].tolist())
        assert shown == cols, (u, shown)
        assert set(np.nonzero(f[..., 0].sum(axis=1))[0].tolist()) <= {10}


@pytest.mark.parametrize("background", [0.0, 1.0, 0.3])
def test_identity_at_zero_for_one_frame_cloud(background):
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.4, 4.0, (H, W))
    depth[rng.random((H, W)) < 0.1] = 0.0  # holes show the background
    depth[3, 4] = np.nan
    depth[5, 6] = np.inf
    cloud = cloud_from_rgbd(depth, rgb, CAM)
    frame, d = render(cloud, CAM, "rz", [0.0], background=background, return_depth=True)
    valid = np.isfinite(depth) & (depth > 0)
    expected = np.where(valid[..., None], rgb.astype(np.float32) / np.float32(255.0), np.float32(background))
    np.testing.assert_array_equal(frame[0], expected)
    np.testing.assert_allclose(d[0], np.where(valid, depth, 0.0), rtol=1e-12)
    # every axis is the identity at alpha = 0
    for axis in AXES:
        np.testing.assert_array_equal(render(cloud, CAM, axis, [0.0], background=background)[0], expected)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), max_elements=st.integers(1, 300))
def test_chunking_gives_identical_frames(seed, axis, max_elements):
    rng = np.random.default_rng(seed)
    cloud = random_scene(rng, 60)
    alphas = rng.uniform(-1, 1, 7) * ALPHA_SCALE[axis]
    full, dfull = render(cloud, CAM, axis, alphas, return_depth=True)
    small, dsmall = render(cloud, CAM, axis, alphas, return_depth=True, max_elements=max_elements)
    np.testing.assert_array_equal(full, small)
    np.testing.assert_array_equal(dfull, dsmall)
    r = Renderer(cloud, CAM, axis, max_elements=max_elements)
    chunks = list(r.iter_frames(alphas, chunk=3))
    assert [s for s, _ in chunks] == [0, 3, 6]
    np.testing.assert_array_equal(np.concatenate([f.numpy() for _, f in chunks]), full)


def test_empty_cloud_and_empty_alphas():
    empty = Cloud(np.zeros((0, 3)), np.zeros((0, 3), np.float32))
    f = render(empty, CAM, "tx", [0.0, 0.1], background=0.7)
    assert f.shape == (2, H, W, 3) and np.all(f == np.float32(0.7))
    one = Cloud(np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3), np.float32))
    assert render(one, CAM, "tx", []).shape == (0, H, W, 3)


def test_render_bad_input():
    one = Cloud(np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3), np.float32))
    with pytest.raises(PwsError):
        render(one, CAM, "tw", [0.0])
    with pytest.raises(PwsError):
        render(one, CAM, "tx", [float("nan")])
    with pytest.raises(PwsError):
        render(one, CAM, "tx", [0.0], background=float("inf"))
    with pytest.raises(PwsError):
        render(one, CAM, "tx", [0.0], device="cuda:99")


# ---- the motion conventions, checked independently ------------------------------------------

def ref_R(axis: str, a: float) -> np.ndarray:
    """REFERENCE.md: rz = [[c,-s,0],[s,c,0],[0,0,1]], ry = [[c,0,s],[0,1,0],[-s,0,c]], rx = [[1,0,0],[0,c,-s],[0,s,c]]."""
    c, s = math.cos(a), math.sin(a)
    return {
        "rx": np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float),
        "ry": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], float),
        "rz": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float),
    }.get(axis, np.eye(3))


def ref_t(axis: str, a: float) -> np.ndarray:
    t = np.zeros(3)
    if axis in ("tx", "ty", "tz"):
        t["xyz".index(axis[1])] = a
    return t


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES))
def test_projection_matches_matrix_convention(seed, axis):
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(0.5, 3, 50)], axis=1)
    a = float(rng.uniform(-1, 1) * ALPHA_SCALE[axis] * 0.3)
    R, t = ref_R(axis, a), ref_t(axis, a)
    Pp = (R.T @ (pts - t).T).T  # P' = R^T (P - t)
    u_ref = CAM.fx * Pp[:, 0] / Pp[:, 2] + CAM.cx + 0.5
    v_ref = CAM.fy * Pp[:, 1] / Pp[:, 2] + CAM.cy + 0.5
    u, v, z = project(pts, CAM, axis, a)
    np.testing.assert_allclose(z, Pp[:, 2], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(u, u_ref, rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(v, v_ref, rtol=1e-11, atol=1e-9)
    X, Y, Z = transform(pts, axis, a)
    np.testing.assert_allclose(np.stack([X, Y, Z], 1), Pp, atol=1e-12)
    # the torch projection of the renderers (its own copy of the formulas) against the same reference,
    # for one motion value and for a batch broadcast against the points
    import torch

    for alpha in (torch.tensor(a, dtype=torch.float64), torch.tensor([a, 0.0], dtype=torch.float64)[:, None]):
        ut, vt, zt = (x.numpy() for x in project(torch.as_tensor(pts), CAM, axis, alpha, xp=torch))
        assert ut.shape == vt.shape == zt.shape == tuple(alpha.shape[:-1]) + (len(pts),)
        np.testing.assert_allclose(zt.reshape(-1, len(pts))[0], Pp[:, 2], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ut.reshape(-1, len(pts))[0], u_ref, rtol=1e-11, atol=1e-9)
        np.testing.assert_allclose(vt.reshape(-1, len(pts))[0], v_ref, rtol=1e-11, atol=1e-9)


def test_motion_directions():
    """Camera moving right (tx > 0) sees the scene move left; rz > 0 turns image content
    the way R^T says: a point right of the centre moves up (v decreases) in the image."""
    p = np.array([[0.2, 0.0, 1.0]])
    u0, v0, _ = project(p, CAM, "tx", 0.0)
    u1, _, _ = project(p, CAM, "tx", 0.05)
    assert u1[0] < u0[0]
    _, v2, _ = project(p, CAM, "rz", 0.1)  # Y' = -s X + c Y < 0
    assert v2[0] < v0[0]
    u3, _, _ = project(np.array([[0.0, 0.0, 1.0]]), CAM, "ry", 0.1)  # X' = -s Z: scene moves left
    assert u3[0] < CAM.cx + 0.5
    _, v4, _ = project(np.array([[0.0, 0.0, 1.0]]), CAM, "rx", 0.1)  # Y' = s Z: scene moves down
    assert v4[0] > CAM.cy + 0.5
    _, _, z5 = project(np.array([[0.0, 0.0, 1.0]]), CAM, "tz", 0.25)
    assert z5[0] == pytest.approx(0.75)

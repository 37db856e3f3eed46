"""Depth registration (core/registration.py) against a brute force written here: plain loops, float64."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.errors import PwsError
from pws_ros.core.registration import Extrinsic, chain_transform, register_depth


def brute_register(depth, dcam, ccam, R, t, millimetres):
    """Reference: every valid depth pixel, one at a time, as the square patch [c -+ 1/2] x [r -+ 1/2]
    at its depth; its projected corners' bounding box gives the patch centre's colour-frame depth to
    every colour pixel whose centre lies in it (and always to the pixel the centre projects into),
    cut to ceil(fx ratio) + 2 pixels a side after clipping to the image; the smallest depth wins."""
    H, W = ccam.height, ccam.width
    cap = math.ceil(max(ccam.fx / dcam.fx, ccam.fy / dcam.fy)) + 2
    best = [[math.inf] * W for _ in range(H)]

    def to_colour(r, c, z):
        p = [(c - dcam.cx) * z / dcam.fx, (r - dcam.cy) * z / dcam.fy, z]
        return [sum(R[i][k] * p[k] for k in range(3)) + t[i] for i in range(3)]

    for r in range(depth.shape[0]):
        for c in range(depth.shape[1]):
            d = float(depth[r, c])
            if millimetres:
                if d <= 0:
                    continue
                z = d / 1000.0
            else:
                if not (math.isfinite(d) and d > 0):
                    continue
                z = d
            q = to_colour(r, c, z)
            corners = [to_colour(r + dr, c + dc, z) for dr in (-0.5, 0.5) for dc in (-0.5, 0.5)]
            if q[2] <= 0 or any(k[2] <= 0 for k in corners):
                continue
            us = [ccam.fx * k[0] / k[2] + ccam.cx + 0.5 for k in corners]
            vs = [ccam.fy * k[1] / k[2] + ccam.cy + 0.5 for k in corners]
            uc = math.floor(ccam.fx * q[0] / q[2] + ccam.cx + 0.5)
            vc = math.floor(ccam.fy * q[1] / q[2] + ccam.cy + 0.5)
            c0, c1 = min(math.ceil(min(us) - 0.5), uc), max(math.ceil(max(us) - 0.5), uc + 1)
            r0, r1 = min(math.ceil(min(vs) - 0.5), vc), max(math.ceil(max(vs) - 0.5), vc + 1)
            c0, c1, r0, r1 = max(c0, 0), min(c1, W), max(r0, 0), min(r1, H)
            for row in range(r0, min(r1, r0 + cap)):
                for col in range(c0, min(c1, c0 + cap)):
                    if q[2] < best[row][col]:
                        best[row][col] = q[2]
    out = np.zeros((H, W)) if millimetres else np.full((H, W), np.nan)
    for r in range(H):
        for c in range(W):
            if math.isfinite(best[r][c]):
                out[r, c] = math.floor(best[r][c] * 1000.0 + 0.5) if millimetres else best[r][c]
    return out


def random_case(rng, millimetres):
    dh, dw = rng.integers(4, 13, 2)
    ch, cw = rng.integers(4, 13, 2)
    dcam = CameraIntrinsics(int(dw), int(dh), *rng.uniform(5, 15, 2), *(rng.uniform(0.3, 0.7, 2) * [dw, dh]))
    ccam = CameraIntrinsics(int(cw), int(ch), *rng.uniform(5, 15, 2), *(rng.uniform(0.3, 0.7, 2) * [cw, ch]))
    R = Rotation.from_rotvec(rng.normal(scale=0.1, size=3)).as_matrix()
    t = rng.normal(scale=0.05, size=3)
    z = rng.uniform(0.4, 3.0, (dh, dw))
    if millimetres:
        depth = np.round(z * 1000).astype(np.uint16)
        depth[rng.random((dh, dw)) < 0.2] = 0
    else:
        depth = z.copy()
        depth[rng.random((dh, dw)) < 0.1] = np.nan
        depth[rng.random((dh, dw)) < 0.05] = 0.0
        depth[rng.random((dh, dw)) < 0.05] = -1.0
    return depth, dcam, ccam, R, t


@pytest.mark.parametrize("millimetres", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_register_matches_brute_force(seed, millimetres):
    rng = np.random.default_rng(seed)
    depth, dcam, ccam, R, t = random_case(rng, millimetres)
    got = register_depth(depth, dcam, ccam, Extrinsic(R, t))
    want = brute_register(depth, dcam, ccam, R, t, millimetres)
    assert got.shape == (ccam.height, ccam.width)
    if millimetres:
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, want)
    else:
        assert got.dtype == depth.dtype
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=0, atol=1e-12)
    assert np.count_nonzero(got if millimetres else ~np.isnan(got)) > 0


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_register_matches_brute_force_hypothesis(seed, millimetres):
    rng = np.random.default_rng(seed)
    depth, dcam, ccam, R, t = random_case(rng, millimetres)
    got = register_depth(depth, dcam, ccam, Extrinsic(R, t)).astype(np.float64)
    want = brute_register(depth, dcam, ccam, R, t, millimetres)
    np.testing.assert_allclose(np.nan_to_num(got, nan=-1), np.nan_to_num(want, nan=-1), rtol=0, atol=1e-12)


def test_equal_depth_collisions_and_nearest_wins():
    """A 4x4 depth camera seen by a 2x2 colour camera of half the focal length: each colour pixel
    receives four depth pixels. Equal depths give that depth; otherwise the nearest one wins."""
    dcam = CameraIntrinsics(4, 4, 4.0, 4.0, 1.5, 1.5)
    ccam = CameraIntrinsics(2, 2, 2.0, 2.0, 0.5, 0.5)
    plane = np.full((4, 4), 2.0)
    np.testing.assert_array_equal(register_depth(plane, dcam, ccam, Extrinsic()), np.full((2, 2), 2.0))
    depth = plane.copy()
    depth[0, 0], depth[0, 1], depth[1, 0], depth[1, 1] = 3.0, 1.25, np.nan, 3.0   # top-left colour pixel
    depth[2:, 2:] = np.nan                                                         # bottom-right: nothing arrives
    got = register_depth(depth, dcam, ccam, Extrinsic())
    want = brute_register(depth, dcam, ccam, np.eye(3), np.zeros(3), False)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert got[0, 0] == want[0, 0] == 1.25
    assert np.isnan(got[1, 1])            # a hole stays a hole
    mm = register_depth(np.where(np.isnan(depth), 0, depth * 1000).astype(np.uint16), dcam, ccam, Extrinsic())
    np.testing.assert_array_equal(mm, [[1250, 2000], [2000, 0]])


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_identity_extrinsic_and_equal_intrinsics_give_the_input(dtype):
    rng = np.random.default_rng(5)
    cam = CameraIntrinsics(40, 30, 35.0, 36.0, 19.3, 14.8)
    if dtype == np.uint16:
        depth = rng.integers(0, 6000, (30, 40)).astype(np.uint16)
        depth[rng.random((30, 40)) < 0.2] = 0
    else:
        depth = rng.uniform(0.2, 8.0, (30, 40)).astype(dtype)
        depth[rng.random((30, 40)) < 0.2] = np.nan
    got = register_depth(depth, cam, cam, Extrinsic())
    assert got.dtype == depth.dtype
    np.testing.assert_array_equal(got, depth)


def test_points_behind_or_outside_the_colour_camera_are_dropped():
    cam = CameraIntrinsics(8, 6, 8.0, 8.0, 3.5, 2.5)
    depth = np.full((6, 8), 1.0)
    behind = Extrinsic(translation=[0.0, 0.0, -2.0])     # every point ends up at z = -1
    assert np.isnan(register_depth(depth, cam, cam, behind)).all()
    aside = Extrinsic(translation=[100.0, 0.0, 0.0])
    assert np.isnan(register_depth(depth, cam, cam, aside)).all()


def test_bad_input_is_refused():
    cam = CameraIntrinsics(8, 6, 8.0, 8.0, 3.5, 2.5)
    with pytest.raises(PwsError, match="does not match its camera"):
        register_depth(np.ones((5, 8)), cam, cam, Extrinsic())
    with pytest.raises(PwsError, match="uint16 millimetres or float metres"):
        register_depth(np.ones((6, 8), dtype=np.int32), cam, cam, Extrinsic())
    with pytest.raises(PwsError, match="not a rotation"):
        Extrinsic(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(PwsError, match="unit quaternion"):
        Extrinsic.from_quaternion([0, 0, 0, 2], [0, 0, 0])


def test_quaternion_matches_scipy():
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = Rotation.random(random_state=int(rng.integers(1 << 30)))
        xyzw = q.as_quat()   # scipy's order is (x, y, z, w) too
        T = Extrinsic.from_quaternion(xyzw, [1, 2, 3])
        np.testing.assert_allclose(T.rotation, q.as_matrix(), atol=1e-12)
        p = rng.normal(size=(5, 3))
        np.testing.assert_allclose(T.inverse().apply(T.apply(p)), p, atol=1e-12)


def test_chain_transform_through_a_common_parent():
    """camera_link -> depth optical and camera_link -> colour optical (TF: parent <- child)."""
    rng = np.random.default_rng(4)
    A = Extrinsic(Rotation.random(random_state=1).as_matrix(), rng.normal(size=3))   # depth -> link
    B = Extrinsic(Rotation.random(random_state=2).as_matrix(), rng.normal(size=3))   # colour -> link
    edges = [("link", "depth_optical", A), ("link", "color_optical", B), ("world", "link", Extrinsic(translation=[5, 0, 0]))]
    T = chain_transform(edges, "depth_optical", "color_optical")
    p = rng.normal(size=(6, 3))
    # independent: into the link frame with A, back out with B^T (p_c = B^T (p_link - t_B))
    p_link = p @ A.rotation.T + A.translation
    want = (p_link - B.translation) @ B.rotation
    np.testing.assert_allclose(T.apply(p), want, atol=1e-12)
    assert chain_transform(edges, "depth_optical", "nowhere") is None
    assert chain_transform(edges + [("other", "x", Extrinsic())], "depth_optical", "x") is None


def test_vga_frame_is_fast():
    cam_d = CameraIntrinsics(640, 480, 390.4, 390.4, 331.4, 242.2)
    cam_c = CameraIntrinsics(640, 480, 613.2, 613.4, 319.9, 239.2)
    depth = np.random.default_rng(0).integers(300, 4000, (480, 640)).astype(np.uint16)
    T = Extrinsic.from_quaternion([-5.3e-05, 0.00646, 0.00515, 0.99997], [0.0143, 0.0006, 0.0006])
    register_depth(depth, cam_d, cam_c, T)
    t0 = time.perf_counter()
    register_depth(depth, cam_d, cam_c, T)
    assert time.perf_counter() - t0 < 1.0

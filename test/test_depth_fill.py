"""The invalid-depth fill (core/cloud.py fill_depth, ``depth_fill: row``) against a brute force
written here (plain loops, float64), and what it means for the input paths."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import cloud_from_rgbd, fill_depth
from pws_ros.core.errors import PwsError


def _valid(d: float) -> bool:
    return math.isfinite(d) and d > 0


def _fill_line(line: list[float]) -> list[float]:
    """Each invalid entry: the larger of the nearest valid entries left and right (the one that exists)."""
    out = []
    for j, d in enumerate(line):
        if _valid(d):
            out.append(d)
            continue
        left = next((line[i] for i in range(j - 1, -1, -1) if _valid(line[i])), None)
        right = next((line[i] for i in range(j + 1, len(line)) if _valid(line[i])), None)
        got = [v for v in (left, right) if v is not None]
        out.append(max(got) if got else math.nan)
    return out


def brute_fill(depth: np.ndarray) -> np.ndarray:
    """Rows first; a row with no valid pixel is then filled along its column from the row-filled image."""
    H, W = depth.shape
    rows = [_fill_line([float(depth[r, c]) for c in range(W)]) for r in range(H)]
    if all(_valid(v) for row in rows for v in row):
        return np.array(rows)
    cols = [_fill_line([rows[r][c] for r in range(H)]) for c in range(W)]
    return np.array([[cols[c][r] for c in range(W)] for r in range(H)])


def _random_depth(rng, H, W, holes):
    d = rng.uniform(0.5, 4.0, (H, W))
    # near-duplicate and equal depths: the farther of two equal neighbours is either
    d[rng.random((H, W)) < 0.3] = 1.25
    d = np.where(rng.random((H, W)) < holes, rng.choice([0.0, np.nan, np.inf, -1.0], (H, W)), d)
    return d


@pytest.mark.parametrize("seed", range(8))
def test_fill_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    H, W = rng.integers(1, 12, 2)
    d = _random_depth(rng, H, W, rng.uniform(0.1, 0.9))
    if not np.any(np.isfinite(d) & (d > 0)):
        d[0, 0] = 2.0
    if seed % 3 == 0 and H > 2:
        d[1] = 0.0          # a whole row without depth: filled along the columns
    got, was_filled = fill_depth(d)
    want = brute_fill(d)
    np.testing.assert_array_equal(got, want)
    measured = np.isfinite(d) & (d > 0)
    np.testing.assert_array_equal(was_filled, ~measured & np.isfinite(want))
    assert np.all(got[measured] == d[measured])


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 9), st.integers(1, 9), st.floats(0.0, 0.95))
def test_fill_hypothesis(seed, H, W, holes):
    rng = np.random.default_rng(seed)
    d = _random_depth(rng, H, W, holes)
    d[rng.integers(H), rng.integers(W)] = rng.uniform(0.5, 4.0)
    got, _ = fill_depth(d)
    np.testing.assert_array_equal(got, brute_fill(d))
    assert np.all(np.isfinite(got))                     # one valid pixel fills every pixel (rows, then columns)
    # a filled pixel never lies in front of both of its row's nearest measured neighbours
    assert got.min() >= np.nanmin(np.where(np.isfinite(d) & (d > 0), d, np.nan))


def test_fill_prefers_the_farther_surface():
    # a hole between a near object (1 m) and the wall behind (3 m) continues the wall, not the object
    d = np.array([[1.0, 1.0, 0.0, 0.0, 3.0, 3.0]])
    got, was = fill_depth(d)
    np.testing.assert_array_equal(got, [[1.0, 1.0, 3.0, 3.0, 3.0, 3.0]])
    np.testing.assert_array_equal(was, [[False, False, True, True, False, False]])


def test_no_or_too_little_valid_depth_is_refused():
    with pytest.raises(PwsError, match="no valid pixel"):
        fill_depth(np.zeros((4, 5)))
    one = np.zeros((10, 10))
    one[3, 3] = 1.0
    with pytest.raises(PwsError, match="1.0% of the depth image.*min_valid_depth 10.0%"):
        fill_depth(one, min_valid=0.1)
    cam = CameraIntrinsics(10, 10, 10.0, 10.0, 4.5, 4.5)
    rgb = np.zeros((10, 10, 3), np.uint8)
    for fill in ("row", "off"):
        with pytest.raises(PwsError, match="min_valid_depth"):
            cloud_from_rgbd(one, rgb, cam, fill=fill, min_valid=0.1)
    assert len(cloud_from_rgbd(one, rgb, cam, fill="off")) == 1      # no minimum asked: as before


def test_filled_cloud_has_every_pixel_back_projected_through_its_centre():
    cam = CameraIntrinsics(6, 4, 5.0, 6.0, 2.5, 1.5)
    d = np.array([[1.0, 0, 2.0, 2.0, 0, 0], [0] * 6, [1.5, 1.5, np.nan, 1.0, 1.0, 1.0], [1.0] * 6])
    rgb = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    cloud = cloud_from_rgbd(d, rgb, cam, fill="row")
    want = brute_fill(d)
    assert len(cloud) == 24 and cloud.filled == int(np.sum(~(np.isfinite(d) & (d > 0))))
    for i, (r, c) in enumerate((r, c) for r in range(4) for c in range(6)):       # row-major, every pixel
        z = want[r, c]
        np.testing.assert_allclose(cloud.points[i], [(c - cam.cx) * z / cam.fx, (r - cam.cy) * z / cam.fy, z], rtol=1e-12)
        np.testing.assert_allclose(cloud.colors[i], rgb[r, c] / 255.0, rtol=1e-6)
    with pytest.raises(PwsError, match="unknown depth_fill"):
        cloud_from_rgbd(d, rgb, cam, fill="inpaint")

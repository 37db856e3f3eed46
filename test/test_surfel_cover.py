"""The union kernel of :mod:`pws_ros.core.surfel_cover` gives bit for bit what enumerating every pose's or
segment's pairs gives (the renderer and the bounds before it; :func:`reference_first_covers`), on random
clouds with holes, ulp-close duplicates, points near the camera plane and behind it, every axis, fine and
coarse grids (the union path forced on, whatever the motion); and the restricted footprint ranges equal the
full ones. The brute-force tests of test_imaging.py check both against the documented model."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
import torch

import pws_ros.core.footprint as footprint_mod
import pws_ros.core.surfel as surfel_mod
import pws_ros.core.surfel_cover as cover
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.imaging import SurfelRenderer, hulls_within, make_imaging
from pws_ros.core.footprint import FootprintSweep

CAM = CameraIntrinsics(32, 24, 30.0, 31.0, 15.5, 11.5, "cam")   # native 32x24, model 16x12
RADIUS = {"tx": 0.03, "ty": 0.03, "tz": 0.06, "rx": 0.03, "ry": 0.03, "rz": 0.08}


def random_cloud(rng) -> Cloud:
    depth = rng.uniform(0.8, 1.6, CAM.shape)
    depth[rng.random(CAM.shape) < 0.1] = 0.0
    depth[:, : CAM.width // 3] = 1.0                       # a flat patch: equal depths
    r0, c0 = rng.integers(0, CAM.height - 6), rng.integers(0, CAM.width - 8)
    depth[r0:r0 + 6, c0:c0 + 8] = 0.5                      # a near box: depth edges
    cloud = cloud_from_rgbd(depth, rng.random(CAM.shape + (3,)).astype(np.float32), CAM)
    pts, cols = cloud.points, cloud.colors
    extra = np.array([[0.01, 0.0, 1e-3], [0.02, -0.01, 0.02], [0.1, 0.1, -0.5], [0.0, 0.0, 0.0]])  # near / behind
    k = 5
    idx = rng.choice(len(pts), k)
    dup = pts[idx] * (1.0 + rng.integers(-3, 4, k)[:, None] * np.finfo(np.float64).eps)
    pts = np.concatenate([pts, extra, dup])
    cols = np.concatenate([cols, rng.random((len(extra) + k, 3)).astype(np.float32)])
    perm = rng.permutation(len(pts))
    return Cloud(pts[perm], cols[perm])


def _both(monkeypatch, fn):
    """fn() with the union path forced on wherever it applies, and with the reference enumeration only."""
    monkeypatch.setattr(cover, "MOTION_LIMIT", float("inf"))
    monkeypatch.setattr(cover, "DYNAMIC_SHARE", float("inf"))
    fast = fn()
    monkeypatch.setattr(cover, "range_implied", lambda samples: False)
    monkeypatch.setattr(surfel_mod, "range_implied", lambda samples: False)
    return fast, fn()


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("coarse", [False, True])
def test_union_kernel_equals_the_enumeration(monkeypatch, axis, seed, coarse):
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng)
    b = RADIUS[axis] * (4.0 if coarse else 1.0)
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
    grid = np.union1d(np.sort(rng.uniform(-b, b, 40 if coarse else 90)), [-b, 0.0, b])
    fine = np.linspace(grid[10], grid[11], 7)

    def run():
        r = SurfelRenderer(cloud, im, axis, alpha_range=(-b, b))
        frames = r.render_batch(grid).numpy()
        hulls = hulls_within(r, -b, b)
        return frames, hulls(grid), hulls(fine)

    (f1, h1, g1), (f0, h0, g0) = _both(monkeypatch, run)
    assert np.array_equal(f1, f0)
    for x, y in ((h1, h0), (g1, g0)):
        assert np.array_equal(x.lo, y.lo) and np.array_equal(x.hi, y.hi) and np.array_equal(x.constant, y.constant)


@pytest.mark.parametrize("axis", ["tz", "ry", "rz"])
def test_ranges_of_a_subset_are_those_of_the_whole(axis):
    rng = np.random.default_rng(3)
    cloud = random_cloud(rng)
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2)
    r = SurfelRenderer(cloud, im, axis)
    b = RADIUS[axis] * 3
    sweep = FootprintSweep(r, -b, b)
    g = np.linspace(-b, b, 9)
    sub = torch.as_tensor(np.sort(rng.choice(r.num_points, r.num_points // 3, replace=False)))
    full, part = sweep.ranges(g), sweep.ranges(g, sub)
    for x, y in zip(full, part):
        assert torch.equal(x[..., sub], y)
    fp, fs = r.footprints(torch.as_tensor(g)), r.footprints(torch.as_tensor(g), sub)
    for x, y in zip(fp, fs):
        assert torch.equal(x[..., sub], y)
    for i in range(len(g)):   # one pose of a subset (segment_covers.SegmentCovers) against a batch of every surfel
        for x, y in zip(fp, r.footprints(torch.as_tensor(g[i:i + 1]), sub)):
            assert torch.equal(x[i:i + 1, sub], y)


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "ry"])
def test_shared_corners_give_every_footprint(monkeypatch, axis):
    """Along a translation the renderer and the sweep project two opposite corners of each surfel
    (footprint.footprint_corners), along ry the u and depth of two columns (footprint.project_corners): the footprints,
    the segments' sweep and sure boxes and the unions are bit for bit those of all four corners projected each on
    its own (motion.project), over ranges that hold split events (the pole of tz: points at depth 1 mm and 2 cm;
    ry's stationary depths near the centre column) and points behind the camera."""
    from pws_ros.core.motion import project
    from pws_ros.core.surfel_bounds import _segment_boxes
    from pws_ros.core.surfel_cover import union_of

    rng = np.random.default_rng(11)
    cloud = random_cloud(rng)
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2)
    b = RADIUS[axis] * 3
    g = np.linspace(-b, b, 13)

    def run():
        r = SurfelRenderer(cloud, im, axis)
        sweep = FootprintSweep(r, -b, b)
        H, W = r.intr.height, r.intr.width
        boxes = _segment_boxes(*sweep.ranges(g), H, W)
        flat = [*boxes[0], boxes[1], *boxes[2], boxes[3]]
        union = union_of(*(x[0] for x in sweep.ranges([-b, b])))
        return r.corners.shape[0], flat + [*union[0], union[1], *union[2], union[3]] + list(r.footprints(torch.as_tensor(g)))

    two, got = run()
    for mod in (surfel_mod, footprint_mod):   # the renderer's names and the sweep's
        monkeypatch.setattr(mod, "footprint_corners", lambda corners, axis: corners)
        monkeypatch.setattr(mod, "project_corners", lambda c, intr, axis, a: project(c, intr, axis, a, xp=torch))
    four, want = run()
    assert (two, four) == (4 if axis == "ry" else 2, 4)
    assert len(FootprintSweep(SurfelRenderer(cloud, im, axis), -b, b).corner_ev[0]) > 0 or axis in ("tx", "ty")
    for x, y in zip(got, want):
        assert x.dtype == y.dtype and torch.equal(x, y)


def test_union_holds_every_footprint_and_sweep_box():
    rng = np.random.default_rng(5)
    cloud = random_cloud(rng)
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2)
    for axis in ("tz", "ry", "rz"):
        r = SurfelRenderer(cloud, im, axis)
        b = RADIUS[axis] * 2
        sweep = FootprintSweep(r, -b, b)
        g = np.linspace(-b, b, 11)
        (U, umask, I, imask) = sweep.union(-b, b)
        umin, umax, vmin, vmax, zc, drawn = r.footprints(torch.as_tensor(g))
        assert bool((~drawn | umask).all())
        ok = ~drawn | ((U[0] <= umin) & (umax <= U[1]) & (U[2] <= vmin) & (vmax <= U[3]))
        assert bool(ok.all())
        inside = ~imask | (drawn & (umin <= I[0]) & (I[1] <= umax) & (vmin <= I[2]) & (I[3] <= vmax))
        assert bool(inside.all())



@settings(max_examples=60, deadline=None)
@given(st.integers(1, 400), st.lists(st.integers(0, 10**6), max_size=300))
def test_unique_indices_are_numpy_unique(n, raw):
    """surfel_cover.unique_indices marks instead of sorting: the sorted distinct indices and the inverse that
    numpy.unique gives (empty input, repeats, the ends 0 and n - 1 included)."""
    x = np.array([v % n for v in raw] + ([0, n - 1] if raw else []), dtype=np.int64)
    want, inv = np.unique(x, return_inverse=True)
    got, got_inv = cover.unique_indices(torch.as_tensor(x), n)
    np.testing.assert_array_equal(got.numpy(), want)
    np.testing.assert_array_equal(got_inv.numpy(), inv.reshape(-1))
    np.testing.assert_array_equal(cover.unique_indices(torch.as_tensor(x), n, inverse=False).numpy(), want)


def test_batches_after_one_that_moves_too_far_skip_the_union(monkeypatch):
    """A grid whose footprints move more than ``MOTION_LIMIT`` over a batch: the union is computed for its first batch,
    then skipped for ``UnionPolicy.RETRY_AFTER`` batches (enumerated directly) and tried again; the bounds are those of
    computing the union for every batch (only the speed depends on the policy)."""
    import pws_ros.core.surfel_bounds as sb

    rng = np.random.default_rng(2)
    cloud = random_cloud(rng)
    b = RADIUS["ry"] * 4.0
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
    grid = np.linspace(-b, b, 61)
    monkeypatch.setattr(cover, "MOTION_LIMIT", 0.0)
    monkeypatch.setattr(sb, "HULL_BATCH_ELEMENTS", 3 * len(cloud.points))   # 3 segments a batch: 20 batches
    unions = []
    union = FootprintSweep.union
    monkeypatch.setattr(FootprintSweep, "union", lambda self, a, b_: unions.append(a) or union(self, a, b_))

    def run():
        r = SurfelRenderer(cloud, im, "ry", alpha_range=(-b, b))
        return hulls_within(r, -b, b)(grid)

    got = run()
    assert len(unions) == 20 // (cover.UnionPolicy.RETRY_AFTER + 1)
    unions.clear()
    monkeypatch.setattr(cover.UnionPolicy, "RETRY_AFTER", 0)
    ref = run()
    assert len(unions) == 20
    for name in ("lo", "hi", "constant"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))

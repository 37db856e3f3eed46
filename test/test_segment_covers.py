"""Frames at poses inside a bounded grid, decided from what bounded it (:class:`SegmentCovers`), are the
renderer's bit for bit: on random clouds (holes, ulp duplicates, points near the camera plane and behind it),
every axis, with the bounds' union path (several batches) and their enumeration, at poses inside segments,
on grid points, one ulp either side of them and at both ends; the bounds of a refinement's segments from
them are those from every surfel bit for bit (on random clouds and on a real frame, every axis) and hold every
frame the renderer draws inside them; a lost candidate shows in both; a budget too small keeps nothing; and the
certificates of the anchors' path are those of rendering and bounding every refinement pose and segment from
every surfel."""
from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import pws_ros.core.anchor_geometry as anchor_geometry
import pws_ros.core.surfel as surfel_mod
import pws_ros.core.surfel_bounds as sb
import pws_ros.core.surfel_cover as cover
from pws_ros.core.certify import CertifyConfig, certify
from pws_ros.core.cloud import Cloud
from pws_ros.core.errors import PwsError
from pws_ros.core.framing import SAMPLE_JITTER
from pws_ros.core.imaging import SurfelRenderer, hulls_within, make_imaging
from pws_ros.core.segment_covers import SegmentCovers
from pws_ros.replay.ceiling import never_changing_model
from test_anchor_budgets import _scene
from test_surfel_cover import CAM, RADIUS, random_cloud

BIG = 1 << 30


def _grid_and_covers(axis, seed, scale=2.0, points=30, extra=None, edge_samples=False):
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng)
    if extra is not None:   # more points (their colours random)
        cloud = Cloud(np.concatenate([cloud.points, extra]), np.concatenate([cloud.colors, rng.random((len(extra), 3)).astype(np.float32)]))
    b = RADIUS[axis] * scale
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
    r = SurfelRenderer(cloud, im, axis, alpha_range=(-b, b))
    if edge_samples:   # a third of the sample points on an edge of their jitter square: the pixel ranges are not implied
        S = r.samples
        n = len(S.su)
        at = torch.as_tensor(rng.choice(n, n // 3, replace=False))
        centre = (at % S.W).double() + 0.5
        S.su[at] = centre + torch.as_tensor(rng.choice([-1.0, 1.0], len(at))) * SAMPLE_JITTER
        S._range_implied = None
        assert not cover.range_implied(S)
    grid = np.union1d(np.sort(rng.uniform(-b, b, points)), [-b, 0.0, b])
    covers = SegmentCovers(r, grid, BIG)
    hulls_within(r, -b, b)(grid, covers)
    return rng, r, grid, covers


def _poses(rng, grid):
    b = grid[-1]
    return np.concatenate([rng.uniform(-b, b, 40), grid, np.nextafter(grid[1:-1], np.inf), np.nextafter(grid[1:-1], -np.inf)])


def _count_enumerations(monkeypatch):
    calls = []
    ref = cover.reference_first_covers
    monkeypatch.setattr(cover, "reference_first_covers", lambda *a, **k: calls.append(1) or ref(*a, **k))
    return calls


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
def test_frames_from_covers_of_enumerated_bounds(monkeypatch, axis):
    monkeypatch.setattr(cover, "range_implied", lambda samples: False)
    monkeypatch.setattr(surfel_mod, "range_implied", lambda samples: False)
    rng, r, grid, covers = _grid_and_covers(axis, 11)
    assert covers.where.numel() > 0 and not covers.dropped
    HW = CAM.height * CAM.width
    seg, pix = covers.where // HW, covers.where % HW
    assert bool((r.rank[covers.point] < covers.first[seg, pix].long()).all())   # only those before the first
    poses = _poses(rng, grid)
    np.testing.assert_array_equal(covers.render_batch(poses).numpy(), r.render_batch(poses).numpy())


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
def test_frames_from_covers_of_union_bounds_in_several_batches(monkeypatch, axis):
    """The union path forced on and batches of a few segments (candidates of segment s > 0 offset right)."""
    monkeypatch.setattr(cover, "MOTION_LIMIT", float("inf"))
    monkeypatch.setattr(cover, "DYNAMIC_SHARE", float("inf"))
    monkeypatch.setattr(sb, "HULL_BATCH_ELEMENTS", 3000)
    calls = _count_enumerations(monkeypatch)
    rng, r, grid, covers = _grid_and_covers(axis, 7)
    assert calls == [] and len(grid) - 1 > 3 * max(1, 3000 // r.num_points)   # the union path, several batches
    calls.clear()
    poses = _poses(rng, grid)
    np.testing.assert_array_equal(covers.render_batch(poses).numpy(), r.render_batch(poses).numpy())
    for x in (np.nextafter(grid[0], -np.inf), np.nextafter(grid[-1], np.inf), 2 * grid[-1]):
        with pytest.raises(PwsError, match="outside the grid"):
            covers.render_batch([x])


def test_a_lost_candidate_shows():
    """The comparisons above can fail: one segment's candidates dropped, its poses differ from the renderer's."""
    rng, r, grid, covers = _grid_and_covers("tz", 11)
    counts = np.diff(covers.starts)
    k = int(np.argmax(counts))
    assert counts[k] > 0
    poses = grid[k] + (grid[k + 1] - grid[k]) * np.linspace(0.0, 1.0, 11)
    np.testing.assert_array_equal(covers.render_batch(poses).numpy(), r.render_batch(poses).numpy())
    a, b = covers.starts[k], covers.starts[k + 1]
    keep = np.r_[np.arange(a), np.arange(b, len(covers.where))]
    covers.where, covers.point = covers.where[keep], covers.point[keep]
    covers.starts = [s if i <= k else s - (b - a) for i, s in enumerate(covers.starts)]
    assert not np.array_equal(covers.render_batch(poses).numpy(), r.render_batch(poses).numpy())


def test_a_budget_too_small_keeps_nothing():
    rng = np.random.default_rng(3)
    cloud = random_cloud(rng)
    b = RADIUS["tz"] * 2
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2)
    r = SurfelRenderer(cloud, im, "tz", alpha_range=(-b, b))
    grid = np.linspace(-b, b, 9)
    first_only = 4 * 8 * CAM.height * CAM.width
    assert SegmentCovers(r, grid, first_only - 1).dropped
    covers = SegmentCovers(r, grid, first_only + 16)   # room for the first ranks, not for the candidates
    h = hulls_within(r, -b, b)(grid, covers)
    assert covers.dropped and covers.first is None
    ref = hulls_within(r, -b, b)(grid)
    assert np.array_equal(h.lo, ref.lo) and np.array_equal(h.hi, ref.hi)
    with pytest.raises(PwsError, match="another grid"):
        hulls_within(r, -b, b)(grid[:-1], SegmentCovers(r, grid, BIG))


def _fields(cert):
    d = cert.to_dict()
    d.pop("timings")
    return d


def test_the_anchors_path_certifies_as_when_every_pose_is_rendered(monkeypatch):
    """Where the first placement falls short, the refinement's frames and bounds come from the covers; the
    certificates are those of rendering and bounding from every surfel (COVERS_BYTES = 0:
    nothing kept)."""
    decided = _decisions(monkeypatch)
    used = []
    render_batch = SegmentCovers.render_batch
    monkeypatch.setattr(SegmentCovers, "render_batch", lambda self, a: used.append(len(a)) or render_batch(self, a))
    cases = [(seed, axis, radius) for seed in (0, 1) for axis, radius in (("tz", 0.4), ("ry", 0.08))]
    for seed, axis, radius in cases:
        cam, cloud, _, _ = _scene(seed)   # its own axis and radius aside
        im = make_imaging("surfel", cam, (12, 16), background=0.0, border=0)
        model = never_changing_model(im.out_shape)
        cfg = CertifyConfig(sigma=0.5, n0=64, n=256, alpha=0.01, num_anchors=8, border=0, seed=seed)
        with_covers = certify(cloud, cam, model, axis, radius, "pws_of", cfg, imaging=im)
        monkeypatch.setattr(anchor_geometry, "COVERS_BYTES", 0)
        rendered = certify(cloud, cam, model, axis, radius, "pws_of", replace(cfg), imaging=im)
        monkeypatch.setattr(anchor_geometry, "COVERS_BYTES", 256 * 2**20)
        assert with_covers.status != "error" and _fields(with_covers) == _fields(rendered), (seed, axis)
    assert len(used) >= 2 and sum(used) > 0   # the covers did render (a second refinement happened)
    assert sum(decided) > 0                   # and bound the refinement


@pytest.mark.parametrize("axis", ["tz", "ry", "rz"])
def test_union_and_enumeration_keep_the_same_covers(monkeypatch, axis):
    """The candidates before the first surely covering surfel, per segment and pixel, are one set whichever
    path bounded the grid (the bounds' tests compare only their values)."""
    monkeypatch.setattr(cover, "MOTION_LIMIT", float("inf"))
    monkeypatch.setattr(cover, "DYNAMIC_SHARE", float("inf"))
    monkeypatch.setattr(sb, "HULL_BATCH_ELEMENTS", 3000)
    calls = _count_enumerations(monkeypatch)
    _, _, _, union = _grid_and_covers(axis, 5)
    assert calls == []
    monkeypatch.setattr(cover, "range_implied", lambda samples: False)
    monkeypatch.setattr(surfel_mod, "range_implied", lambda samples: False)
    _, _, _, enumerated = _grid_and_covers(axis, 5)
    assert calls and union.where.numel() > 0
    assert np.array_equal(union.first.numpy(), enumerated.first.numpy())
    pairs = [sorted(zip(c.where.tolist(), c.point.tolist())) for c in (union, enumerated)]
    assert pairs[0] == pairs[1]


def _refined(rng, grid):
    """A refinement of ``grid``: random points inside its segments, midpoints, and points one ulp off the grid
    points (segments of one ulp)."""
    inner = grid[:-1] + (grid[1:] - grid[:-1]) * rng.uniform(0.0, 1.0, len(grid) - 1)
    mids = 0.5 * (grid[:-1] + grid[1:])
    ulps = np.concatenate([np.nextafter(grid[1:-1], np.inf), np.nextafter(grid[1:-1], -np.inf)])
    return np.union1d(grid, np.concatenate([inner, mids[::2], rng.choice(ulps, 6, replace=False)]))


def _decisions(monkeypatch):
    """Counts the segments SegmentCovers.decide decides; each such refinement takes its parents' values at their
    constant pixels (SegmentCovers.kept_values, whatever share of the pixels is constant there) and computes the rest."""
    calls = []
    decide = SegmentCovers.decide

    def counted(self, sweep, g):
        assert self.values is not None and self.kept_values(g) is not None
        calls.append(len(g) - 1)
        return decide(self, sweep, g)

    monkeypatch.setattr(SegmentCovers, "decide", counted)
    monkeypatch.setattr(sb, "KEPT_SHARE", 1.0)
    return calls


@pytest.mark.parametrize("union", [True, False, "edges"])
@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
def test_refined_bounds_from_the_covers_are_those_from_every_surfel(monkeypatch, axis, union):
    """Segments inside a bounded grid's (a refinement) bounded from its covers (SegmentCovers.decide) equal, bit for
    bit, those bounded from every surfel (proven along a translation; along a rotation equal unless rounding puts a
    sample point in a sliver between a child's box and its parent's, which these clouds do not). Parents bounded by the union path in several batches, or by enumeration (also with sample points on
    the edges of their jitter squares: pixel ranges not implied by the box tests); near-plane and behind-camera
    points whose pole lies inside the range (tz), ulp duplicates, segments of one ulp."""
    if union is True:
        monkeypatch.setattr(cover, "MOTION_LIMIT", float("inf"))
        monkeypatch.setattr(cover, "DYNAMIC_SHARE", float("inf"))
        monkeypatch.setattr(sb, "HULL_BATCH_ELEMENTS", 3000)
    elif union is False:   # every batch of more than one segment enumerated
        monkeypatch.setattr(cover, "MOTION_LIMIT", -float("inf"))
    enumerations = _count_enumerations(monkeypatch)
    calls = _decisions(monkeypatch)
    for seed in (3, 8):
        # points whose pole is inside the motion's range, seen mirrored near the image centre once behind the
        # camera (there they are no candidate: not drawn)
        rng, r, grid, covers = _grid_and_covers(axis, seed, extra=np.array([[0.0, 0.0, 0.01], [0.001, -0.002, 0.03]]),
                                                edge_samples=union == "edges")
        assert covers.where.numel() > 0 and not covers.dropped
        fine = _refined(rng, grid)
        b = grid[-1]
        got = hulls_within(r, -b, b)(fine, parent=covers)
        ref = hulls_within(r, -b, b)(fine)
        for name in ("lo", "hi", "constant"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{axis} seed {seed} {name}")
        assert not ref.constant.all()
    assert sum(calls) > 0
    assert (enumerations == []) == (union is True)


@pytest.mark.parametrize("axis", ["tx", "ty", "tz", "rx", "ry", "rz"])
def test_refined_bounds_from_the_covers_hold_every_frame_inside(monkeypatch, axis):
    """Soundness, against the renderer: at 12 poses inside each segment of a refinement (its ends, one ulp inside
    them, random ones), every output pixel lies within the bounds decided from the parent's covers, and a pixel
    the bounds call constant shows the segment's first frame's value bit for bit."""
    calls = _decisions(monkeypatch)
    for seed in (4, 9):
        rng, r, grid, covers = _grid_and_covers(axis, seed, extra=np.array([[0.0, 0.0, 0.01], [0.001, -0.002, 0.03]]))
        fine = _refined(rng, grid)
        b = grid[-1]
        got = hulls_within(r, -b, b)(fine, parent=covers)
        a0, a1 = fine[:-1], fine[1:]
        _assert_holds_frames(r, got, [np.nextafter(a0, np.inf), np.nextafter(a1, -np.inf)], rng, 8, (axis, seed))
    assert sum(calls) > 0


def _assert_holds_frames(r, hulls, poses, rng, random: int, what):
    """Every frame the renderer draws inside each segment of ``hulls`` (at its ends, at ``poses`` (one array of a pose
    per segment each) and at ``random`` random points) lies within its bounds, and a pixel the bounds call constant
    shows the segment's first frame's value bit for bit."""
    a0, a1 = hulls.alphas[:-1], hulls.alphas[1:]
    first = r.render_batch(a0).numpy().astype(np.float64)
    for at in [a0, a1, *poses] + [a0 + (a1 - a0) * t for t in rng.uniform(0, 1, random)]:
        x = r.render_batch(np.clip(at, a0, a1)).numpy().astype(np.float64)
        assert np.all(hulls.lo <= x) and np.all(x <= hulls.hi), what
        assert np.all((x == first).all(axis=3)[hulls.constant]), what


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(["rx", "ry", "rz", "tz"]), scale=st.sampled_from([0.5, 2.0, 20.0]))
def test_refined_bounds_from_the_covers_on_random_clouds(seed, axis, scale):
    """Property: on random clouds (holes, a near box, ulp duplicates, near-plane and behind-camera points) and motion
    ranges from a fraction of the shipped radius to 20 times it, the bounds of a refinement decided from its parent's
    covers hold every frame the renderer draws at 6 poses inside each segment, constant pixels bit for bit (every
    axis: SegmentCovers.decide's soundness), and along tz equal those from every surfel bit for bit (proven there; along a rotation the two may
    differ where a sample point falls between a child's box and its parent's, both sound: the fixed clouds above and
    the real frames below check equality there)."""
    rng, r, grid, covers = _grid_and_covers(axis, seed, scale=scale, extra=np.array([[0.0, 0.0, 0.01]]))
    if covers.dropped or covers.where is None:
        return
    fine = _refined(rng, grid)
    b = grid[-1]
    assert covers.decides(fine)
    with pytest.MonkeyPatch.context() as mp:   # the parents' constant pixels kept, whatever their share
        mp.setattr(sb, "KEPT_SHARE", 1.0)
        got = hulls_within(r, -b, b)(fine, parent=covers)
    if axis == "tz":
        ref = hulls_within(r, -b, b)(fine)
        for name in ("lo", "hi", "constant"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{axis} seed {seed} {name}")
    _assert_holds_frames(r, got, [], rng, 4, (axis, seed))


def test_a_lost_candidate_changes_the_refined_bounds(monkeypatch):
    """The comparison above can fail: one parent segment's candidates dropped, its children's bounds differ."""
    calls = _decisions(monkeypatch)
    rng, r, grid, covers = _grid_and_covers("tz", 3)
    fine = _refined(rng, grid)
    b = grid[-1]
    ref = hulls_within(r, -b, b)(fine)
    counts = np.diff(covers.starts)
    k = int(np.argmax(counts))
    a, e = covers.starts[k], covers.starts[k + 1]
    keep = np.r_[np.arange(a), np.arange(e, len(covers.where))]
    covers.where, covers.point = covers.where[keep], covers.point[keep]
    covers.starts = [s if i <= k else s - (e - a) for i, s in enumerate(covers.starts)]
    got = hulls_within(r, -b, b)(fine, parent=covers)
    assert calls and not (np.array_equal(got.lo, ref.lo) and np.array_equal(got.hi, ref.hi))


def test_segments_outside_the_covers_grid_are_bounded_from_every_surfel(monkeypatch):
    calls = _decisions(monkeypatch)
    rng, r, grid, covers = _grid_and_covers("tz", 3)
    b = grid[-1]
    across = np.array([grid[2], grid[4]])            # one segment over two of the covers' grid
    assert not covers.decides(np.array([np.nextafter(-b, -np.inf), -b])) and not covers.decides(np.array([grid[1], b]))
    assert covers.decides(np.array([-b, np.nextafter(-b, np.inf)])) and covers.decides(grid[3:5])
    ref = hulls_within(r, -b, b)(across)
    got = hulls_within(r, -b, b)(across, parent=covers)
    assert calls == [] and np.array_equal(got.lo, ref.lo) and np.array_equal(got.hi, ref.hi)


@pytest.mark.parametrize("axis", ["tx", "tz"])
def test_covers_kept_from_the_parents_covers_are_those_from_every_surfel(axis):
    """A refinement bounded from its parent's covers keeps, per segment and pixel, the same first surely covering
    rank and candidates before it as when bounded from every surfel: its own refinement's frames and bounds come
    from them."""
    rng, r, grid, covers = _grid_and_covers(axis, 3, extra=np.array([[0.0, 0.0, 0.01]]))
    split = np.arange(0, len(grid) - 1, 2)   # every other segment split, the rest kept
    fine = np.union1d(grid, grid[split] + (grid[split + 1] - grid[split]) * rng.uniform(0.0, 1.0, len(split)))
    b = grid[-1]
    bounds_of = hulls_within(r, -b, b)
    kept = [SegmentCovers(r, fine, BIG) for _ in range(3)]
    every = bounds_of(fine, kept[0])
    bounds_of(fine, kept[1], parent=covers)
    # as the anchors' path does it: the segments the refinement keeps copied (bounds and covers), the new ones decided
    old = bounds_of(grid)
    refined = anchor_geometry.refined_hulls(functools.partial(bounds_of, parent=covers), grid, old, fine, (covers, kept[2]))
    for name in ("lo", "hi", "constant"):
        np.testing.assert_array_equal(getattr(refined, name), getattr(every, name))
    pairs = [sorted(zip(c.where.tolist(), c.point.tolist())) for c in kept]
    assert kept[0].where.numel() > 0
    for c, p in zip(kept[1:], pairs[1:]):
        assert np.array_equal(c.first.numpy(), kept[0].first.numpy()) and p == pairs[0]
    poses = _poses(rng, fine)
    np.testing.assert_array_equal(kept[2].render_batch(poses).numpy(), r.render_batch(poses).numpy())


@pytest.mark.parametrize("axis", ["tz", "ry"])
def test_refinements_of_a_real_frame_are_bounded_as_from_every_surfel(monkeypatch, axis):
    """The RealSense frame (../shared/data) at the shipped 160x90, through ``pws ceiling``: every refinement the
    anchors' path bounds from its parent's covers equals, bit for bit, the same segments bounded from every surfel
    (about 200 segments of 59 k surfels on each axis)."""
    from conftest import shared_path
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.replay import ReplayOptions
    from pws_ros.replay.ceiling import ceiling

    bag = shared_path("realsense_single_rgbd")
    refined = anchor_geometry.refined_hulls
    compared = []

    def checked(bounds_of, old_grid, old, grid, covers=None):
        got = refined(bounds_of, old_grid, old, grid, covers)
        if isinstance(bounds_of, functools.partial):   # from the parent's covers
            ref = refined(bounds_of.func, old_grid, old, grid)
            for name in ("lo", "hi", "constant"):
                np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{axis} {name}")
            compared.append(len(grid) - 1)
        return got

    monkeypatch.setattr(anchor_geometry, "refined_hulls", checked)
    kept = []
    kept_values = SegmentCovers.kept_values
    monkeypatch.setattr(SegmentCovers, "kept_values", lambda self, g: kept.append(1) or kept_values(self, g))
    monkeypatch.setattr(sb, "KEPT_SHARE", 1.0)   # every refinement keeps its parents' constant pixels
    config = PwsConfig().with_params({"axes": [axis]})
    ceiling(ReplayOptions(bag=bag, config=config, write_output=False, quiet=True, max_frames=1), None, input_size=(90, 160))
    assert sum(compared) > 100 and kept


def _median_motion(points, intr, axis: str, a: float, b: float) -> float:
    """How far (px) the median point moves between poses ``a`` and ``b``: the larger of its moves in ``u`` and ``v``,
    each point projected through ``R^T (P - t)`` in plain float64 loops (points projected onto depth 0 left out)."""
    import math
    import statistics

    def uv(p, alpha):
        X, Y, Z = (float(x) for x in p)
        c, s = math.cos(alpha), math.sin(alpha)
        X, Y, Z = {"tx": (X - alpha, Y, Z), "ty": (X, Y - alpha, Z), "tz": (X, Y, Z - alpha),
                   "rx": (X, c * Y + s * Z, -s * Y + c * Z), "ry": (c * X - s * Z, Y, s * X + c * Z),
                   "rz": (c * X + s * Y, -s * X + c * Y, Z)}[axis]
        return None if Z == 0.0 else (intr.fx * X / Z + intr.cx + 0.5, intr.fy * Y / Z + intr.cy + 0.5)

    moves = []
    for p in points:
        p0, p1 = uv(p, a), uv(p, b)
        if p0 is not None and p1 is not None:
            moves.append(max(abs(p1[0] - p0[0]), abs(p1[1] - p0[1])))
    return statistics.median(moves)


def test_the_coarse_grid_is_every_kth_point_where_the_median_surfel_barely_moves():
    """:func:`.anchor_geometry.coarse_grid` against a plain computation: the largest ``k`` of ``COARSE_STEPS`` whose
    ``k`` segments the median surfel crosses within ``COARSE_MOTION`` px (the segments taken as even over the grid), on
    grids of at least ``4 k + 1`` points along a translation; every ``k``-th point counted from ``alpha = 0``, with both
    ends; else None (always along a rotation).
    Each outcome (8, 4, none) occurs, and a grid whose ``alpha = 0`` is not a multiple of ``k`` from its start."""
    seen, offset = set(), False
    for seed, axis, scale, n in [(0, "tz", 0.2, 129), (1, "tz", 2.0, 33), (2, "tz", 20.0, 129), (3, "ry", 1.0, 41),
                                 (4, "tx", 0.05, 17), (5, "rz", 0.3, 65), (6, "tz", 1.0, 16), (7, "rx", 0.01, 129),
                                 (8, "ty", 0.1, 65)]:
        rng = np.random.default_rng(seed)
        b = RADIUS[axis] * scale
        im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
        r = SurfelRenderer(random_cloud(rng), im, axis, alpha_range=(-b, b))
        g = np.union1d(np.linspace(-b, 0.7 * b, n), [0.0])   # alpha = 0 off the grid's middle
        got = anchor_geometry.coarse_grid(r, g, anchor_geometry.COVERS_BYTES)
        per_segment = _median_motion(r.points_np, r.intr, axis, float(g[0]), float(g[-1])) / (len(g) - 1)
        steps = [k for k in anchor_geometry.COARSE_STEPS if len(g) >= 4 * k + 1 and k * per_segment <= anchor_geometry.COARSE_MOTION
                 and axis in ("tx", "ty", "tz")]
        if not steps:
            assert got is None, (seed, axis)
            seen.add(None)
            continue
        k, centre = steps[0], list(g).index(0.0)
        want = sorted({i for i in range(len(g)) if (i - centre) % k == 0} | {0, len(g) - 1})
        np.testing.assert_array_equal(got, g[want], err_msg=f"{seed} {axis}")
        seen.add(k)
        offset |= centre % k != 0
    assert seen == {8, 4, None} and offset


def _geometry_bounds(monkeypatch, r, g, coarse: bool):
    """The bounds and frames ``prepare`` gives the grid ``g``, with or without its coarse grid (forced where used),
    the grids bounded, and the covers kept."""
    from pws_ros.core.partition import Plan

    monkeypatch.setattr(anchor_geometry, "COARSE_MOTION", float("inf") if coarse else -1.0)
    monkeypatch.setattr(anchor_geometry, "COARSE_STEPS", (4,))
    geometry = anchor_geometry._RendererGeometry(r, CertifyConfig())
    bounded = []
    bounds_grid = geometry._bounds_grid
    monkeypatch.setattr(geometry, "_bounds_grid", lambda g_: bounded.append(len(g_)) or bounds_grid(g_))
    plan = Plan("pws_of", r.axis, float(g[-1]), float(np.diff(g).max()), len(g), g)
    geometry.prepare(plan)
    return geometry._last[1], geometry.frames(plan), bounded, geometry._covers


@pytest.mark.parametrize("axis", ["tx", "ty", "tz"])
def test_a_grid_bounded_through_its_coarse_grid_is_bounded_as_from_every_surfel(monkeypatch, axis):
    """``prepare`` bounding a coarse grid first and the grid from its covers gives the bounds of every segment as from
    every surfel bit for bit (proven along a translation: SegmentCovers.decide), the renderer's frames, and keeps the
    covers of the grid itself (its refinement decides from them)."""
    decided = _decisions(monkeypatch)
    for seed in (5, 11):
        rng = np.random.default_rng(seed)
        b = RADIUS[axis] * 2.0
        im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
        r = SurfelRenderer(random_cloud(rng), im, axis, alpha_range=(-b, b))
        g = np.union1d(np.sort(rng.uniform(-b, b, 30)), [-b, 0.0, b])
        ref = hulls_within(r, -b, b)(g)
        direct, direct_frames, bounded, _ = _geometry_bounds(monkeypatch, r, g, coarse=False)
        got, frames, bounded_coarse, covers = _geometry_bounds(monkeypatch, r, g, coarse=True)
        assert bounded == [len(g)] and bounded_coarse[1:] == [len(g)] and bounded_coarse[0] < len(g) // 3
        for name in ("lo", "hi", "constant"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{axis} seed {seed} {name}")
            np.testing.assert_array_equal(getattr(direct, name), getattr(ref, name))
        assert not ref.constant.all()
        np.testing.assert_array_equal(frames, r.render_batch(g).numpy())
        np.testing.assert_array_equal(direct_frames, frames)
        assert covers is not None and np.array_equal(covers.grid, g) and covers.decides(_refined(rng, g))
    assert sum(decided) > 0


def test_the_coarse_first_grid_changes_no_certificate(monkeypatch):
    """The certificates of the anchors' path (the grid to begin with bounded through a coarse grid, forced) are those
    of bounding it from every surfel, along tz and tx."""
    used, coarse = [], []
    coarse_grid = anchor_geometry.coarse_grid
    for seed, axis, radius in [(0, "tz", 0.4), (1, "tz", 0.4), (0, "tx", 0.16)]:
        cam, cloud, _, _ = _scene(seed)
        im = make_imaging("surfel", cam, (12, 16), background=0.0, border=0)
        model = never_changing_model(im.out_shape)
        cfg = CertifyConfig(sigma=0.5, n0=64, n=256, alpha=0.01, num_anchors=8, border=0, seed=seed)
        certs = []
        for limit in (-1.0, float("inf")):
            monkeypatch.setattr(anchor_geometry, "COARSE_MOTION", limit)
            monkeypatch.setattr(anchor_geometry, "COARSE_STEPS", (2,))
            monkeypatch.setattr(anchor_geometry, "coarse_grid", lambda *a: used.append(a[1]) or coarse.append(coarse_grid(*a)) or coarse[-1])
            certs.append(certify(cloud, cam, model, axis, radius, "pws_of", replace(cfg), imaging=im))
        assert certs[0].status != "error" and _fields(certs[0]) == _fields(certs[1]), (seed, axis)
    assert len(used) == 6 and all(len(g) >= 9 for g in used)
    assert all(x is None for x in coarse[0::2]) and all(x is not None for x in coarse[1::2])   # off, then forced


@pytest.mark.parametrize("finer_kept", [True, False])
def test_a_refinements_new_frames_come_from_its_own_covers(monkeypatch, finer_kept):
    """``refine`` bounds the refined grid first and renders its new poses from the refined grid's covers (or, where
    those are beyond the memory ceiling, from the coarser grid's): the renderer's frames bit for bit; the bounds asked
    for next are those kept (no second bounding), the same as bounding the refined grid directly; their time is counted
    as bounds (``pop_bounds_seconds``)."""
    from pws_ros.core.partition import Plan

    rng = np.random.default_rng(7)
    b = RADIUS["tz"] * 2.0
    im = make_imaging("surfel", CAM, (12, 16), render_factor=2, uncovered="frame")
    r = SurfelRenderer(random_cloud(rng), im, "tz", alpha_range=(-b, b))
    g = np.linspace(-b, b, 9)
    if not finer_kept:   # room for the 8 segments' covers, not for the refined grid's
        covers = SegmentCovers(r, g, BIG)
        hulls_within(r, -b, b)(g, covers)
        base = 4 * covers.first.numel()
        monkeypatch.setattr(anchor_geometry, "COVERS_BYTES", covers.used + 3 * (covers.used - base))   # (their peak: _count)
    monkeypatch.setattr(anchor_geometry, "COARSE_STEPS", ())
    geometry = anchor_geometry._RendererGeometry(r, CertifyConfig())
    plan = Plan("pws_of", "tz", b, float(g[1] - g[0]), len(g), g)
    geometry.prepare(plan)
    frames = geometry.frames(plan)
    assert geometry._covers is not None and geometry.pop_bounds_seconds() == 0.0
    rendered, bounded = [], []
    render_batch = SegmentCovers.render_batch
    monkeypatch.setattr(SegmentCovers, "render_batch", lambda self, a: rendered.append(len(self.grid)) or render_batch(self, a))
    refined = anchor_geometry.refined_hulls
    monkeypatch.setattr(anchor_geometry, "refined_hulls", lambda *a, **k: bounded.append(1) or refined(*a, **k))
    finer, finer_frames = geometry.refine(plan, frames, 0.02, 50)
    n = len(finer.alphas)
    assert n > len(g) and bounded == [1]
    assert rendered == ([n] if finer_kept else [len(g)])
    assert (geometry._covers is not None) == finer_kept
    np.testing.assert_array_equal(finer_frames, r.render_batch(finer.alphas).numpy())
    assert geometry.pop_bounds_seconds() > 0.0 and geometry.pop_bounds_seconds() == 0.0
    got = geometry.bounds(finer)
    assert bounded == [1]   # kept, not bounded again
    ref = hulls_within(r, -b, b)(finer.alphas)
    for name in ("lo", "hi", "constant"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)

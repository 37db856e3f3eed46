"""The surfel imaging model (pws_ros.core.imaging) against an independent brute force.

The reference below re-implements the model from its written definition (docs/imaging.md, the page
that defines it: sample points in its section 5, footprints and occlusion order in 6, the crop and
factor rule in 3, binning in 4) with plain Python loops in float64: surfel corners, projection P' = R^T (P - t),
axis-aligned footprint of the four projected corners, one sample point per native pixel (centre plus
the documented R2 offset), the least squared distance from the recorded camera centre wins, exact ties
to the lower index, background where
nothing covers, k x k block mean, masked border. It imports nothing from the production renderer or
bounds, only data classes.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import camera_motion_rt
from pws_ros.core.anchors import place_anchors, refine_plan
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.imaging import UNCOVERED, SurfelRenderer, make_imaging, segment_hulls
from pws_ros.core.partition import Plan, make_grid

AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
SCALE = {"tx": 0.03, "ty": 0.03, "tz": 0.05, "rx": 0.03, "ry": 0.03, "rz": 0.06}
CAM = CameraIntrinsics(8, 6, 7.0, 7.5, 3.5, 2.5, "cam")   # native 8x6, model 4x3: factor 2
# from the documented model (docs/imaging.md): surfel overlap (section 6), the sample points' largest
# offset and the plastic number of their R2 pattern (section 5)
OVERLAP, JITTER, PLASTIC = 0.15, 0.33, 1.32471795724474602596


def reference_native(points, colors, cam, axis, a, background):
    """Native image (H, W, 3) of the surfel model, loops only."""
    H, W = cam.height, cam.width
    RT, t = camera_motion_rt(axis, a)
    best = [[(math.inf, -1) for _ in range(W)] for _ in range(H)]
    for i, (X, Y, Z) in enumerate(points):
        zz = max(Z, 0.0)
        hx, hy = (0.5 + OVERLAP) * zz / cam.fx, (0.5 + OVERLAP) * zz / cam.fy
        us, vs, ok = [], [], True
        for sx, sy in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
            q = [X + sx * hx - t[0], Y + sy * hy - t[1], Z - t[2]]
            p = [sum(RT[r][k] * q[k] for k in range(3)) for r in range(3)]
            if p[2] <= 0:
                ok = False
                break
            us.append(cam.fx * p[0] / p[2] + cam.cx + 0.5)
            vs.append(cam.fy * p[1] / p[2] + cam.cy + 0.5)
        q = [X - t[0], Y - t[1], Z - t[2]]
        d = sum(RT[2][k] * q[k] for k in range(3))
        if not ok or d <= 0:
            continue
        key = X * X + Y * Y + Z * Z   # the occlusion order: recorded distance, fixed for the motion
        for r in range(H):
            for c in range(W):
                k = r * W + c
                su = c + 0.5 + JITTER * (2 * ((0.5 + k / PLASTIC) % 1.0) - 1)
                sv = r + 0.5 + JITTER * (2 * ((0.5 + k / PLASTIC ** 2) % 1.0) - 1)
                if min(us) <= su < max(us) and min(vs) <= sv < max(vs) and (key, i) < best[r][c]:
                    best[r][c] = (key, i)
    img = np.full((H, W, 3), background, dtype=np.float64)
    for r in range(H):
        for c in range(W):
            if best[r][c][1] >= 0:
                img[r, c] = colors[best[r][c][1]]
    return img


def reference_frame(points, colors, im, axis, a):
    # uncovered "frame": a pixel no surfel covers shows its alpha = 0 colour (docs/imaging.md), else background
    bg = reference_native(points, colors, im.camera, axis, 0.0, im.background) if im.uncovered == "frame" else im.background
    nat = reference_native(points, colors, im.camera, axis, a, bg)
    k = im.factor
    h, w = im.out_shape
    out = nat.reshape(h, k, w, k, 3).mean(axis=(1, 3))
    bx, by = im.border
    if bx:
        out[:, :bx] = out[:, w - bx:] = im.background
    if by:
        out[:by] = out[h - by:] = im.background
    return out


def random_cloud(rng, ties: bool) -> Cloud:
    """A depth image of CAM back-projected (holes included), plus stray points; with ``ties``, copies of
    points at the same depth or a few ulps away (what quantised real depth is full of)."""
    depth = rng.uniform(0.8, 1.6, CAM.shape)
    depth[rng.random(CAM.shape) < 0.15] = 0.0
    if rng.random() < 0.5:
        depth[:, : CAM.width // 2] = 1.0  # a flat patch: equal depths
    cloud = cloud_from_rgbd(depth, rng.random(CAM.shape + (3,)).astype(np.float32), CAM)
    pts, cols = cloud.points, cloud.colors
    extra = rng.uniform([-0.6, -0.5, 0.7], [0.6, 0.5, 1.8], (4, 3))
    pts, cols = np.concatenate([pts, extra]), np.concatenate([cols, rng.random((4, 3)).astype(np.float32)])
    if ties:
        k = rng.integers(1, 6)
        idx = rng.choice(len(pts), k)
        scale = 1.0 + rng.integers(-3, 4, k)[:, None] * np.finfo(np.float64).eps
        dup = pts[idx] * scale
        dup[:, 2] = np.where(rng.random(k) < 0.5, pts[idx, 2], dup[:, 2])  # equal depth, or a few ulps off
        pts = np.concatenate([pts, dup])
        cols = np.concatenate([cols, rng.random((k, 3)).astype(np.float32)])
        perm = rng.permutation(len(pts))
        pts, cols = pts[perm], cols[perm]
    return Cloud(pts, cols)


def test_alpha_zero_re_renders_the_camera_image_exactly():
    rng = np.random.default_rng(1)
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, "cam")
    depth = rng.uniform(0.8, 2.0, cam.shape)
    depth[rng.random(cam.shape) < 0.1] = 0.0
    rgb = rng.random(cam.shape + (3,)).astype(np.float32)
    cloud = cloud_from_rgbd(depth, rgb, cam)
    im = make_imaging("surfel", cam, (12, 16), background=0.25, border=0)
    assert im.factor == 4 and (im.camera.width, im.camera.height) == (64, 48)
    frame = SurfelRenderer(cloud, im, "ry").render_batch([0.0])[0].numpy().astype(np.float64)
    expect = np.where((depth > 0)[..., None], rgb, 0.25).reshape(12, 4, 16, 4, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(frame, expect, atol=1e-7)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), ties=st.booleans(),
       border=st.sampled_from([0, 1]), background=st.sampled_from([0.0, 0.5]), uncovered=st.sampled_from(UNCOVERED))
def test_renderer_equals_the_brute_force(seed, axis, ties, border, background, uncovered):
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng, ties)
    im = make_imaging("surfel", CAM, (3, 4), background=background, border=border, uncovered=uncovered)
    alphas = np.concatenate([[0.0], rng.uniform(-1, 1, 2) * SCALE[axis]])
    frames = SurfelRenderer(cloud, im, axis).render_batch(alphas).numpy()
    for f, a in zip(frames, alphas):
        np.testing.assert_allclose(f, reference_frame(cloud.points, cloud.colors, im, axis, a), atol=1e-6)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), ties=st.booleans(), nseg=st.integers(1, 4),
       uncovered=st.sampled_from(UNCOVERED))
def test_segment_bounds_hold_for_dense_alphas(seed, axis, ties, nseg, uncovered):
    """Every frame of a segment (brute force at its ends, their float neighbours and 12 interior poses)
    lies inside the per-pixel bounds, so no distance bound can be exceeded (disocclusions included: the
    random clouds have holes and stray points; uncovered pixels show the background or their alpha = 0 colour)."""
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng, ties)
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0, uncovered=uncovered)
    b = SCALE[axis] * rng.uniform(0.2, 1.0)
    alphas = make_grid(b, b / nseg)
    hulls = segment_hulls(SurfelRenderer(cloud, im, axis), alphas)
    y = rng.random((3, 4, 3))
    for i in range(len(alphas) - 1):
        lo, hi = alphas[i], alphas[i + 1]
        poses = [lo, hi, np.nextafter(lo, hi), np.nextafter(hi, lo), *rng.uniform(lo, hi, 12)]
        first = reference_frame(cloud.points, cloud.colors, im, axis, lo)
        for a in poses:
            f = reference_frame(cloud.points, cloud.colors, im, axis, a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (axis, i, a)
            assert ((f - y) ** 2).sum() <= hulls.dist_sq(y)[i]
            # a pixel the bounds call constant shows one value throughout the segment (the sparse form sends none)
            np.testing.assert_array_equal(f[hulls.constant[i]], first[hulls.constant[i]])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), nseg=st.integers(1, 3))
def test_large_footprints_and_long_sweeps_equal_the_brute_force(seed, axis, nseg):
    """Points a few centimetres from the camera (footprints many pixels wide, sweeping across the image,
    crossing the camera plane) and long segments: the renderer equals the brute force at the grid
    poses and every frame of a segment lies inside its bounds."""
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng, False)
    near = rng.uniform([-0.05, -0.05, 0.03], [0.05, 0.05, 0.12], (5, 3))
    cloud = Cloud(np.concatenate([cloud.points, near]), np.concatenate([cloud.colors, rng.random((5, 3)).astype(np.float32)]))
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0)
    b = {"tx": 0.05, "ty": 0.05, "tz": 0.1, "rx": 0.4, "ry": 0.4, "rz": 0.8}[axis] * rng.uniform(0.5, 1.0)
    alphas = make_grid(b, b / nseg)
    r = SurfelRenderer(cloud, im, axis)
    hulls = segment_hulls(r, alphas)
    frames = r.render_batch(alphas).numpy()
    for i, a in enumerate(alphas):
        np.testing.assert_allclose(frames[i], reference_frame(cloud.points, cloud.colors, im, axis, a), atol=1e-6)
    for i in range(len(alphas) - 1):
        for a in rng.uniform(alphas[i], alphas[i + 1], 8):
            f = reference_frame(cloud.points, cloud.colors, im, axis, a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (axis, i, a)


def test_bounds_are_tight_where_nothing_changes():
    """A fronto-parallel wall moving along tz by a fraction of a pixel: the hull of each segment is the
    two end frames (within float margins), not the background, and a pixel is called constant exactly
    where it does not change."""
    cam = CameraIntrinsics(16, 12, 14.0, 14.0, 7.5, 5.5, "cam")
    rgb = np.full((12, 16, 3), 0.5, np.float32)
    rgb[..., 0] = np.linspace(0, 1, 16, dtype=np.float32)   # neighbours differ in one channel only
    cloud = cloud_from_rgbd(np.full(cam.shape, 2.0), rgb, cam)
    im = make_imaging("surfel", cam, (6, 8), background=0.0, border=0)
    r = SurfelRenderer(cloud, im, "tz")
    alphas = make_grid(0.01, 0.0025)
    hulls = segment_hulls(r, alphas)
    frames = r.render_batch(alphas).numpy()
    for i in range(len(alphas) - 1):
        ends_lo = np.minimum(frames[i], frames[i + 1])
        ends_hi = np.maximum(frames[i], frames[i + 1])
        assert np.all(hulls.lo[i] >= ends_lo - 1e-5) and np.all(hulls.hi[i] <= ends_hi + 1e-5)
        # the pixels the bounds call constant are exactly those no brute-force frame of the segment changes (one
        # pixel of the last segment, where a sample is handed over; the rest of the wall keeps its surfels)
        f = np.stack([reference_frame(cloud.points, cloud.colors, im, "tz", a) for a in np.linspace(alphas[i], alphas[i + 1], 7)])
        np.testing.assert_array_equal(hulls.constant[i], (f == f[0]).all(axis=(0, 3)))
    assert not hulls.constant.all()


def hulls_and_frames(seed: int, axis: str, radius: float, step: float):
    """A random cloud's imaging, grid, production bounds and frames (for the sparse-form tests)."""
    cloud = random_cloud(np.random.default_rng(seed), True)
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0)
    r = SurfelRenderer(cloud, im, axis)
    alphas = make_grid(radius, step)
    return cloud, im, alphas, segment_hulls(r, alphas), r.render_batch(alphas).numpy()


def test_segment_values_conversion_is_as_sound_as_the_hull():
    cloud, im, alphas, hulls, frames = hulls_and_frames(4, "ry", 0.02, 0.01)
    values = hulls.to_segment_values(frames)
    # the sparse form drops only the float margins of constant pixels: equal up to them ...
    np.testing.assert_allclose(values.pair_bound_sq(frames), hulls.pair_bound_sq(frames), rtol=1e-4)
    y = frames[2]
    np.testing.assert_allclose(values.anchor_dist_sq(frames, y), hulls.dist_sq(y), rtol=1e-4)
    # ... and still above every brute-force frame of each segment
    for i in range(len(alphas) - 1):
        for a in np.linspace(alphas[i], alphas[i + 1], 9):
            f = reference_frame(cloud.points, cloud.colors, im, "ry", a)
            assert ((f - frames[i]) ** 2).sum() + ((f - frames[i + 1]) ** 2).sum() <= values.pair_bound_sq(frames)[i]
            assert ((f - y) ** 2).sum() <= values.anchor_dist_sq(frames, y)[i]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.integers(1, 4), st.integers(1, 4), st.integers(0, 40))
def test_boxes_from_segment_values_equal_a_brute_force(seed, S, h, w, E):
    """HullValues.from_segment_values (the four-process certifier's bounds): per segment, pixel and
    channel the least and greatest of the end frames' values and the extra values received (in any
    order, repeated pairs included), loops only; a pixel is constant iff it has no extra value and both
    end frames agree on every channel."""
    from pws_ros.core.bounds import SegmentValues
    from pws_ros.core.imaging import HullValues

    rng = np.random.default_rng(seed)
    levels = np.array([0.0, 0.25, 0.5, 1.0], np.float32)   # few levels: equal values and ties are common
    frames = levels[rng.integers(0, 4, (S + 1, h, w, 3))]
    for s in range(S):   # unchanged pixels
        keep = rng.random((h, w)) < 0.4
        frames[s + 1][keep] = frames[s][keep]
    seg, pix = rng.integers(0, S, E), rng.integers(0, h * w, E)
    val = np.where(rng.random((E, 3)) < 0.5, levels[rng.integers(0, 4, (E, 3))], rng.random((E, 3))).astype(np.float32)
    got = HullValues.from_segment_values(SegmentValues(np.linspace(-1, 1, S + 1), seg, pix, val, (h, w)), frames)
    for s in range(S):
        for p in range(h * w):
            r, c = divmod(p, w)
            extras = [val[e] for e in range(E) if seg[e] == s and pix[e] == p]
            for ch in range(3):
                vs = [float(frames[s, r, c, ch]), float(frames[s + 1, r, c, ch])] + [float(v[ch]) for v in extras]
                assert got.lo[s, r, c, ch] == min(vs) and got.hi[s, r, c, ch] == max(vs)
            assert bool(got.constant[s, r, c]) == (not extras and all(frames[s, r, c] == frames[s + 1, r, c]))
    # the box contains every value, so its distance bound is at least the value set's (loops)
    y = rng.random((h, w, 3)).astype(np.float32)
    d = got.dist_sq(y)
    for s in range(S):
        ref = 0.0
        for p in range(h * w):
            r, c = divmod(p, w)
            cand = [frames[s, r, c], frames[s + 1, r, c]] + [val[e] for e in range(E) if seg[e] == s and pix[e] == p]
            ref += max(sum((float(v[ch]) - float(y[r, c, ch])) ** 2 for ch in range(3)) for v in cand)
        assert d[s] >= ref


def test_boxes_from_segment_values_bound_the_rendered_frames():
    """The round trip hulls -> sparse values -> boxes (what the four-process certifier rebuilds) stays
    above every brute-force frame of each segment, and equals the original boxes where a pixel changes."""
    from pws_ros.core.imaging import HullValues

    cloud, im, alphas, hulls, frames = hulls_and_frames(5, "tz", 0.05, 0.02)
    back = HullValues.from_segment_values(hulls.to_segment_values(frames), frames)
    changing = ~hulls.constant
    assert changing.any()
    np.testing.assert_array_equal(back.lo[changing], hulls.lo[changing])
    np.testing.assert_array_equal(back.hi[changing], hulls.hi[changing])
    np.testing.assert_array_equal(back.constant, hulls.constant)
    y = frames[3]
    for i in range(len(alphas) - 1):
        for a in np.linspace(alphas[i], alphas[i + 1], 9):
            # the frame as delivered: the block mean (exact in float64 for these values) rounded to float32
            f = reference_frame(cloud.points, cloud.colors, im, "tz", a).astype(np.float32).astype(np.float64)
            assert ((f - y) ** 2).sum() <= back.dist_sq(y)[i]
    with pytest.raises(PwsError, match="do not fit"):
        HullValues.from_segment_values(hulls.to_segment_values(frames), frames[:-1])


def test_boxes_from_segment_values_refuse_malformed_input():
    from pws_ros.core.bounds import SegmentValues
    from pws_ros.core.imaging import HullValues

    frames = np.zeros((3, 2, 2, 3), np.float32)
    a = np.array([-1.0, 0.0, 1.0])

    def sv(seg, pix, val, shape=(2, 2)):
        return SegmentValues(a, np.asarray(seg), np.asarray(pix), np.asarray(val), shape)

    ok = sv([0, 1], [3, 0], np.full((2, 3), 0.5, np.float32))
    assert HullValues.from_segment_values(ok, frames).hi.max() == 0.5
    for bad, what in ((sv([0, 1], [3], np.zeros((2, 3))), "seg"), (sv([0], [3], np.zeros((1, 2))), "val"),
                      (sv([[0]], [[3]], np.zeros((1, 3))), "seg"), (sv([0.5], [3], np.zeros((1, 3))), "integers"),
                      (sv([2], [0], np.zeros((1, 3))), "outside"), (sv([0], [4], np.zeros((1, 3))), "outside"),
                      (sv([0], [1], [[np.nan, 0, 0]]), "NaN"), (sv([0], [1], np.zeros((1, 3)), (2, 3)), "do not fit")):
        with pytest.raises(PwsError, match=what):
            HullValues.from_segment_values(bad, frames)
    nan = frames.copy()
    nan[1, 0, 0, 0] = np.inf
    with pytest.raises(PwsError, match="NaN or inf"):
        HullValues.from_segment_values(ok, nan)
    with pytest.raises(PwsError, match=r"\(N, H, W, 3\)"):
        HullValues.from_segment_values(ok, frames[..., :2])
    # a value float32 cannot hold is rounded outwards: the box still contains it
    v = 0.1 + 1e-12
    box = HullValues.from_segment_values(sv([0], [0], [[v, -v, 0.0]]), frames)
    assert float(box.hi[0, 0, 0, 0]) >= v and float(box.lo[0, 0, 0, 1]) <= -v


def test_imaging_errors_and_crop():
    """The crop and factor rule of docs/imaging.md, section 3 (k_max = min(W // w, H // h), centred crop)."""
    with pytest.raises(PwsError, match="smaller than the classifier's input 16x12"):
        make_imaging("surfel", CAM, (12, 16))
    with pytest.raises(PwsError, match="masks the whole"):
        make_imaging("surfel", CAM, (3, 4), border=2)
    with pytest.raises(PwsError, match="unknown imaging model"):
        make_imaging("splat", CAM, (3, 4))
    cam = CameraIntrinsics(640, 480, 460.0, 460.0, 319.5, 239.5, "cam")
    im = make_imaging("surfel", cam, (90, 160))
    assert (im.factor, im.crop, im.camera.width, im.camera.height, im.camera.cy) == (4, (0, 60), 640, 360, 179.5)


def reference_bins(points, colors, cam):
    """The binned cloud of a rendered camera ``cam`` (docs/imaging.md, section 4), loops only: one point per
    rendered pixel hit at alpha = 0, on the ray through its centre at the nearest depth of the bin, with
    the mean colour; bins row by row."""
    bins: dict[tuple[int, int], list[int]] = {}
    for i, (X, Y, Z) in enumerate(points):
        if Z <= 0:
            continue
        u = cam.fx * X / Z + (cam.cx + 0.5)
        v = cam.fy * Y / Z + (cam.cy + 0.5)
        bins.setdefault((math.floor(v), math.floor(u)), []).append(i)
    pts, cols = [], []
    for (r, c) in sorted(bins):
        members = bins[(r, c)]
        z = min(points[i][2] for i in members)
        pts.append([(c - cam.cx) * z / cam.fx, (r - cam.cy) * z / cam.fy, z])
        cols.append([sum(float(colors[i][ch]) for i in members) / len(members) for ch in range(3)])
    return np.array(pts), np.array(cols, dtype=np.float32)


def test_render_factor_bins_the_camera_and_keeps_the_crop():
    """docs/imaging.md, section 3: k = min(render_factor, k_max) (k_max when 0), s = k_max // k, crop offset
    (W - s k w) // 2, and the binned camera's intrinsics."""
    cam = CameraIntrinsics(640, 480, 460.0, 460.0, 319.5, 239.5, "cam")
    im = make_imaging("surfel", cam, (90, 160), render_factor=2)
    c = im.camera
    assert (im.factor, im.decimate, im.crop, c.width, c.height) == (2, 2, (0, 60), 320, 180)
    assert (c.fx, c.cx, c.cy) == (230.0, 159.5, 89.5)       # pixel edges halve: (cx + 1/2) / 2 - 1/2
    assert "binned 2x2" in im.describe()
    three = make_imaging("surfel", cam, (90, 160), render_factor=3)   # 3 does not divide 4: native 480x270
    assert (three.factor, three.decimate, three.crop, three.camera.width) == (3, 1, (80, 105), 480)
    assert make_imaging("surfel", cam, (90, 160), render_factor=9).factor == 4   # at most the camera's resolution
    with pytest.raises(PwsError, match="render_factor must be >= 0"):
        make_imaging("surfel", cam, (90, 160), render_factor=-1)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), ties=st.booleans(), uncovered=st.sampled_from(UNCOVERED))
def test_binned_rendering_and_bounds_equal_the_brute_force(seed, axis, ties, uncovered):
    """render_factor 1 on a 16x12 camera and a 3x4 model: 4x4 camera pixels per output pixel, binned 2x2.
    The renderer draws the reference-binned cloud exactly, and dense poses stay inside the bounds."""
    rng = np.random.default_rng(seed)
    cam = CameraIntrinsics(16, 12, 14.0, 15.0, 7.5, 5.5, "cam")
    depth = rng.uniform(0.8, 1.6, cam.shape)
    depth[rng.random(cam.shape) < 0.15] = 0.0
    if ties:
        depth[:, :8] = 1.0
    cloud = cloud_from_rgbd(depth, rng.random(cam.shape + (3,)).astype(np.float32), cam)
    extra = rng.uniform([-0.6, -0.5, 0.7], [0.6, 0.5, 1.8], (4, 3))  # stray points, some beyond the image
    cloud = Cloud(np.concatenate([cloud.points, extra]), np.concatenate([cloud.colors, rng.random((4, 3)).astype(np.float32)]))
    im = make_imaging("surfel", cam, (3, 4), background=0.5, border=0, render_factor=1, uncovered=uncovered)
    assert (im.factor, im.decimate, im.camera.width) == (1, 4, 4)
    pts, cols = reference_bins(cloud.points, cloud.colors, im.camera)
    r = SurfelRenderer(cloud, im, axis)
    np.testing.assert_allclose(r.points_np, pts, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(r.colors_np, cols, atol=1e-6)
    b = SCALE[axis] * rng.uniform(0.2, 1.0)
    alphas = make_grid(b, b / 2)
    frames = r.render_batch(alphas).numpy()
    hulls = segment_hulls(r, alphas)
    for i, a in enumerate(alphas):
        np.testing.assert_allclose(frames[i], reference_frame(r.points_np, r.colors_np, im, axis, a), atol=1e-6)
    for i in range(len(alphas) - 1):
        for a in [alphas[i], alphas[i + 1], *rng.uniform(alphas[i], alphas[i + 1], 6)]:
            f = reference_frame(r.points_np, r.colors_np, im, axis, a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (axis, i, a)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), factor=st.integers(1, 3), spread=st.integers(0, 30), offset=st.sampled_from([0.0, 1e-6, -1e-6]))
def test_block_mean_sums_float32_input_in_float64(seed, factor, spread, offset):
    """The block mean of float32 native images (what the renderer and the bounds hand it) equals, bit for bit,
    a plain float64 loop over each block in row-major order, divided by k^2, plus the offset; values of
    very different magnitudes (exponents up to 2^spread apart), where a float32 sum would round."""
    from pws_ros.core.framing import block_mean64
    rng = np.random.default_rng(seed)
    cam = CameraIntrinsics(16 * factor, 12 * factor, 7.0, 7.0, 3.5, 2.5, "cam")
    im = make_imaging("surfel", cam, (6, 8), background=0.25, border=1, render_factor=factor)
    k, (h, w) = im.factor, im.out_shape
    x = (rng.random((2, h * k, w * k, 3)) * 2.0 ** rng.integers(-spread, 1, (2, h * k, w * k, 3))).astype(np.float32)
    got = block_mean64(torch.as_tensor(x), im, offset).numpy()
    want = np.empty((2, h, w, 3))
    for b in range(2):
        for r in range(h):
            for c in range(w):
                for ch in range(3):
                    acc = 0.0
                    for i in range(k):
                        for j in range(k):
                            acc += float(x[b, r * k + i, c * k + j, ch])
                    want[b, r, c, ch] = acc / float(k * k)
    bx, by = im.border
    assert bx > 0 or by > 0
    if bx:
        want[:, :, :bx] = want[:, :, w - bx:] = 0.25
    if by:
        want[:, :by] = want[:, h - by:] = 0.25
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, want + offset)
    np.testing.assert_array_equal(got, block_mean64(torch.as_tensor(x, dtype=torch.float64), im, offset).numpy())
    # some output pixels alone (outside the border, in the order of the mask's nonzero): the same values
    at = rng.random((2, h, w)) < 0.3
    at[:, :by] = at[:, h - by:] = False
    at[:, :, :bx] = at[:, :, w - bx:] = False
    part = block_mean64(torch.as_tensor(x), im, offset, at=torch.as_tensor(at)).numpy()
    np.testing.assert_array_equal(part, want[at] + offset)


def test_binned_alpha_zero_frame_is_the_block_mean_of_the_camera_image():
    rng = np.random.default_rng(3)
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, "cam")
    depth = rng.uniform(0.8, 2.0, cam.shape)
    rgb = rng.random(cam.shape + (3,)).astype(np.float32)
    im = make_imaging("surfel", cam, (12, 16), background=0.25, border=0, render_factor=2)
    assert (im.factor, im.decimate) == (2, 2)
    frame = SurfelRenderer(cloud_from_rgbd(depth, rgb, cam), im, "tz").render_batch([0.0])[0].numpy()
    np.testing.assert_allclose(frame, rgb.astype(np.float64).reshape(12, 4, 16, 4, 3).mean(axis=(1, 3)), atol=1e-6)


def test_auto_border_masks_what_enters_from_beyond_the_recording():
    cam = CameraIntrinsics(64, 36, 60.0, 60.0, 31.5, 17.5, "cam")
    cloud = cloud_from_rgbd(np.full(cam.shape, 1.0), np.ones(cam.shape + (3,), np.float32), cam)
    # tx 0.05 m at 1 m moves every point 3 native px = 1.5 output px (factor 2): 2 columns, no rows
    im = make_imaging("surfel", cam, (18, 32), cloud=cloud, radii={"tx": 0.05})
    assert im.border == (2, 0)
    assert make_imaging("surfel", cam, (18, 32), cloud=cloud, radii={"ty": 0.05}).border == (0, 2)


def test_place_anchors_covers_every_segment_within_the_target():
    # frames on a line: D_i(x_j) = distance from point j to the farther end of segment i
    x = np.linspace(0.0, 10.0, 41)
    alphas = np.linspace(-1.0, 1.0, 41)

    def row(j):
        return np.maximum((x[:-1] - x[j]) ** 2, (x[1:] - x[j]) ** 2)

    anchors = place_anchors(row, alphas, 20, 1.0 ** 2, max_anchors=50)
    covered = np.any([row(a) < 1.0 for a in anchors], axis=0)
    assert covered.all() and anchors[0] == 20
    assert len(anchors) <= 7  # the centre covers 8 segments of 0.25, each other anchor 7 (strict <): 16 per side
    few = place_anchors(row, alphas, 20, 1.0, max_anchors=3)  # the budget caps them, symmetric growth
    assert len(few) == 3
    assert place_anchors(row, alphas, 20, 0.0, max_anchors=9) == [20]  # no target radius: the centre only


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), S=st.integers(2, 140), target=st.floats(0.05, 3.0), budget=st.integers(1, 30))
def test_place_anchors_reads_rows_lazily_with_the_same_result(seed, S, target, budget):
    """Rows read block by block (partial=True) choose exactly the anchors that full rows choose."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.exponential(0.3, S + 1)) * rng.choice([-1, 1], S + 1).cumsum().clip(-3, 3)  # wandering path
    alphas = np.linspace(-1.0, 1.0, S + 1)
    alphas[np.argmin(np.abs(alphas))] = 0.0
    centre = int(np.argmin(np.abs(alphas)))
    width = rng.uniform(0, 0.5, S)

    def full(j):
        return np.maximum((x[:-1] - x[j]) ** 2, (x[1:] - x[j]) ** 2) + width ** 2

    def piece(j, i0=0, i1=None):
        return full(j)[i0:i1]

    rows: dict = {}
    lazy = place_anchors(piece, alphas, centre, target ** 2, budget, partial=True, rows_out=rows)
    assert lazy == place_anchors(full, alphas, centre, target ** 2, budget)
    assert sorted(rows) == sorted(lazy) and all(np.array_equal(rows[a], full(a)) for a in lazy)


def test_refine_plan_splits_only_where_frames_differ():
    alphas = make_grid(1.0, 0.5)  # -1, -0.5, 0, 0.5, 1
    plan = Plan("pws_of", "tx", 1.0, 0.5, 5, alphas)
    frames = np.zeros((5, 1, 1, 1))
    frames[4] = 1.0  # only the last segment changes, by 1.0
    out = refine_plan(plan, frames, 0.3, 100)
    assert list(out.alphas[:4]) == [-1.0, -0.5, 0.0, 0.5] and len(out.alphas) == 4 + 4 and out.alphas[-1] == 1.0
    assert refine_plan(plan, frames, 0.3, 6).num_partitions <= 6


def test_refine_plan_stops_where_the_anchor_budget_cannot_reach():
    alphas = make_grid(1.0, 0.25)  # 9 frames, centre index 4
    plan = Plan("pws_of", "tx", 1.0, 0.25, 9, alphas)
    frames = np.arange(9, dtype=np.float64).reshape(9, 1, 1, 1)  # every segment differs by 1.0
    out = refine_plan(plan, frames, 0.5, 1000, reach=1.0)  # segments starting within path 1.0 of alpha = 0
    assert len(out.alphas) == 9 + 4
    got = set(np.round(out.alphas, 9))
    assert got >= {-0.375, -0.125, 0.125, 0.375} and -0.625 not in got and 0.625 not in got


def test_refine_plan_keeps_the_covered_run():
    alphas = make_grid(1.0, 0.25)  # 9 frames, centre index 4
    plan = Plan("pws_of", "tx", 1.0, 0.25, 9, alphas)
    frames = np.arange(9, dtype=np.float64).reshape(9, 1, 1, 1)  # every segment differs by 1.0
    out = refine_plan(plan, frames, 0.5, 1000, keep=(-0.5, 0.25))
    # brute force: each segment not inside [-0.5, 0.25] gets its midpoint, the others none
    want = set(alphas)
    for a, b in zip(alphas[:-1], alphas[1:]):
        if not (a >= -0.5 and b <= 0.25):
            want.add((a + b) / 2)
    assert set(np.round(out.alphas, 9)) == set(np.round(sorted(want), 9))


def test_a_plan_at_the_grid_cap_starts_from_every_other_point():
    """The adaptive anchors begin from every other point of a plan already at the grid cap (0 and both
    ends kept), so the refinement has room; a smaller plan, or the four-process certifier's received
    frames, are used as they are."""
    from types import SimpleNamespace

    from pws_ros.core.certify import CertifyConfig, _FixedGeometry, _RendererGeometry

    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0)
    config = CertifyConfig(max_partitions=9)
    geometry = _RendererGeometry(SimpleNamespace(imaging=im), config)
    full = Plan("pws_of", "tz", 1.0, 0.25, 9, make_grid(1.0, 0.25))
    got = geometry.start(full)
    assert list(got.alphas) == [-1.0, -0.5, 0.0, 0.5, 1.0] and got.num_partitions == 5
    assert got.details["thinned_from"] == 9 and got.delta_alpha == 0.5
    small = Plan("pws_of", "tz", 1.0, 0.5, 5, make_grid(1.0, 0.5))
    assert geometry.start(small) is small
    # alpha = 0 at an odd index: the odd points are kept, and both ends
    odd = Plan("pws_of", "tz", 1.0, 0.4, 9, np.array([-1.0, -0.6, -0.2, 0.0, 0.3, 0.6, 0.8, 0.9, 1.0]))
    assert list(geometry.start(odd).alphas) == [-1.0, -0.6, 0.0, 0.6, 0.9, 1.0]
    assert _FixedGeometry(np.zeros((9, 3, 4, 3)), None).start(full) is full


def test_covered_run_is_the_run_around_the_centre():
    """The run a blocked placement covers (kept unrefined by the extra round of _certify_anchored)."""
    from pws_ros.core.coverage import covered_run

    assert covered_run(np.array([False, True, True, True, False, True]), np.arange(7.0) - 2, 2) == (-1.0, 2.0)
    assert covered_run(np.array([True, False, True, True]), np.arange(5.0) - 2, 2) == (0.0, 2.0)
    assert covered_run(np.array([False, False]), np.array([-1.0, 0.0, 1.0]), 1) == (0.0, 0.0)


def test_memory_ceiling_keeps_the_refined_grid_small_instead_of_failing(monkeypatch):
    import pws_ros.core.anchor_geometry as geometry_mod
    import pws_ros.core.certify as certify_mod
    from conftest import MeanThresholdNet
    from pws_ros.core.model import load_model, save_model

    rng = np.random.default_rng(7)
    cloud = random_cloud(rng, False)
    cfg = certify_mod.CertifyConfig(n0=16, n=32, max_memory_mb=64)
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0)
    # pretend a segment takes a tenth of the bounds' share: at most 10 segments fit
    # (the adaptive anchors' grid cap, core.anchor_geometry.grid_cap, reads it there)
    monkeypatch.setattr(geometry_mod, "segment_bytes", lambda imaging: certify_mod.bounds_bytes(cfg) // 10)
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        model = load_model(save_model(MeanThresholdNet(0.3), Path(d) / "m.pt", ["a", "b"], input_size=(3, 4)))
        cert = certify_mod.certify(cloud, CAM, model, "tx", 0.05, "pws_of", cfg, imaging=im)
        plans = [cert.plan]
    # the frontier refinement bounds a few sub-segments at a time (no stored bounds): its points come on top
    splits = cert.bounds.get("frontier_splits", 0)
    assert cert.status != "error" and cert.num_partitions <= 11 + splits and plans[-1].num_partitions == cert.num_partitions


def test_binning_is_redone_after_an_edit_in_place():
    """The binned cloud is reused for the same, unchanged arrays (plan and axes of one frame), never
    for arrays edited in place since: a render then equals one of a fresh copy of the cloud."""
    rng = np.random.default_rng(7)
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, "cam")
    cloud = cloud_from_rgbd(rng.uniform(0.8, 2.0, cam.shape), rng.random(cam.shape + (3,)).astype(np.float32), cam)
    im = make_imaging("surfel", cam, (12, 16), background=0.25, border=0, render_factor=2)
    assert im.decimate == 2
    first = SurfelRenderer(cloud, im, "ry").render_batch([0.0, 0.01]).numpy()
    np.testing.assert_array_equal(SurfelRenderer(cloud, im, "ry").render_batch([0.0, 0.01]).numpy(), first)
    cloud.colors[[0, 100]] = cloud.colors[[100, 0]]          # same sums, other image
    cloud.points[5, 2] += 0.5
    again = SurfelRenderer(cloud, im, "ry").render_batch([0.0, 0.01]).numpy()
    fresh = SurfelRenderer(Cloud(cloud.points.copy(), cloud.colors.copy()), im, "ry").render_batch([0.0, 0.01]).numpy()
    np.testing.assert_array_equal(again, fresh)
    assert not np.array_equal(again, first)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES))
def test_uncovered_frame_value_is_fixed_by_the_whole_cloud(seed, axis):
    """uncovered "frame": the alpha = 0 colours come from the whole cloud, also for a renderer that drops
    the surfels its alpha range cannot show (a range without 0); and a disoccluded pixel shows that
    colour, not the background, where the background would show with uncovered "background"."""
    rng = np.random.default_rng(seed)
    cloud = random_cloud(rng, False)
    im = make_imaging("surfel", CAM, (3, 4), background=0.0, border=0, uncovered="frame")
    b = SCALE[axis]
    alphas = rng.uniform(0.3 * b, b, 4)
    full = SurfelRenderer(cloud, im, axis).render_batch(alphas).numpy()
    part = SurfelRenderer(cloud, im, axis, alpha_range=(0.3 * b, b)).render_batch(alphas).numpy()
    np.testing.assert_array_equal(full, part)
    for f, a in zip(full, alphas):
        np.testing.assert_allclose(f, reference_frame(cloud.points, cloud.colors, im, axis, a), atol=1e-6)


@pytest.mark.parametrize("uncovered", UNCOVERED)
def test_disocclusion_shows_the_uncovered_value_inside_the_bounds(uncovered):
    """A near bar (colour 1) in front of a far wall (colour 0) that has no points behind the bar: moving
    the camera sideways uncovers pixels no surfel covers. They show the bar's alpha = 0 colour ("frame")
    or the background 0.5, and the bounds of segments far from 0 (where the bar's own surfels have moved
    on) hold them."""
    depth = np.full(CAM.shape, 2.0)
    depth[:, 3:5] = 1.0
    rgb = np.zeros(CAM.shape + (3,), np.float32)
    rgb[:, 3:5] = 1.0
    cloud = cloud_from_rgbd(depth, rgb, CAM)
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0, uncovered=uncovered)
    r = SurfelRenderer(cloud, im, "tx")
    alphas = np.linspace(0.2, 0.3, 3)
    native = r.render_native(alphas).numpy()
    assert np.any(np.all(native == (1.0 if uncovered == "frame" else 0.5), axis=-1)[:, :, :5])   # a disoccluded pixel
    hulls = segment_hulls(r, alphas)
    for i in range(len(alphas) - 1):
        for a in np.linspace(alphas[i], alphas[i + 1], 9):
            f = reference_frame(cloud.points, cloud.colors, im, "tx", a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (i, a)


@pytest.mark.parametrize("axis", ["tz", "ry"])
def test_large_boxes_enumerated_in_pieces_give_the_same_frames_and_bounds(monkeypatch, axis):
    """covered_pairs enumerates the pixels of boxes over 2 pixels a side in pieces of PAIR_CHUNK (bounded
    temporaries): tiny pieces give bitwise the same frames and bounds; more pairs than MAX_COVERED_PAIRS
    (a cloud of points at the camera plane) are refused with a PwsError naming the cause, never allocated."""
    import pws_ros.core.footprint as footprint

    rng = np.random.default_rng(7)
    cloud = random_cloud(rng, False)
    near = rng.uniform([-0.05, -0.05, 0.03], [0.05, 0.05, 0.12], (5, 3))
    cloud = Cloud(np.concatenate([cloud.points, near]), np.concatenate([cloud.colors, rng.random((5, 3)).astype(np.float32)]))
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0)
    alphas = make_grid(0.05, 0.025)

    def run():
        r = SurfelRenderer(cloud, im, axis)
        h = segment_hulls(r, alphas)
        return r.render_batch(alphas).numpy(), h.lo, h.hi

    whole = run()
    monkeypatch.setattr(footprint, "PAIR_CHUNK", 3)
    pieces = run()
    for a, b in zip(whole, pieces):
        np.testing.assert_array_equal(a, b)
    monkeypatch.setattr(footprint, "MAX_COVERED_PAIRS", 50)
    with pytest.raises(PwsError, match="pixel-surfel pairs in one batch"):
        run()

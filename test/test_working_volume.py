"""The working volume (docs/imaging.md, section 4a) against an independent brute force.

The selection rule is written out here with plain loops in float64 (``Z > 0``, ``near <= Z <= far``, and
the lateral limits, all closed, on the recorded coordinates at alpha = 0); the frames are then the brute
force of test_imaging (its reference renderer, binning and block mean: loops only, nothing from the
production renderer or bounds) applied to the selected points. The production renderer must equal it,
and every brute-force frame inside a segment must lie within the production bounds.
"""
from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_imaging import AXES, CAM, SCALE, random_cloud, reference_bins, reference_frame
from pws_ros.bridge.config import config_from_params
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.imaging import UNCOVERED, Imaging, SurfelRenderer, make_imaging, segment_hulls
from pws_ros.core.partition import make_grid
from pws_ros.core.volume import WorkingVolume, volume_from_limits


def reference_select(points, colors, near, far, x=None, y=None):
    """The points of the volume, loops only (docs/imaging.md 4a): kept in their order."""
    keep = []
    for i, (X, Y, Z) in enumerate(points):
        inside = Z > 0 and near <= Z <= far
        if x is not None:
            inside = inside and x[0] <= X <= x[1]
        if y is not None:
            inside = inside and y[0] <= Y <= y[1]
        if inside:
            keep.append(i)
    return np.asarray(points)[keep].reshape(-1, 3), np.asarray(colors)[keep].reshape(-1, 3)


def volume_cloud(rng):
    """A random cloud of CAM (holes, strays, ties) whose depths straddle a far face: some points at the face
    itself, at its float neighbours and a few micrometres either side of it."""
    cloud = random_cloud(rng, True)
    pts, cols = cloud.points.copy(), cloud.colors.copy()
    far = float(np.median(pts[pts[:, 2] > 0, 2]))
    idx = rng.choice(len(pts), min(8, len(pts)), replace=False)
    for j, z in zip(idx, [far, np.nextafter(far, 0), np.nextafter(far, 2), far - 1e-6, far + 1e-6, far - 3e-3, far + 3e-3, far]):
        pts[j] *= z / pts[j, 2] if pts[j, 2] > 0 else 1.0   # moved along its ray: the same pixel, depth z
        pts[j, 2] = z
    return Cloud(pts, cols), far


def lateral(rng):
    return tuple(sorted(rng.uniform(-0.4, 0.4, 2))) if rng.random() < 0.5 else None


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), uncovered=st.sampled_from(UNCOVERED),
       nseg=st.integers(1, 3), boxed=st.booleans())
def test_renderer_and_bounds_under_a_volume_equal_the_brute_force(seed, axis, uncovered, nseg, boxed):
    """Unbinned: the renderer draws exactly the brute force's selected points, at the grid poses and inside
    segments (dense poses, the ends' float neighbours), and every such frame lies inside the bounds."""
    rng = np.random.default_rng(seed)
    cloud, far = volume_cloud(rng)
    near = float(rng.uniform(0.0, 0.9))
    x, y = (lateral(rng), lateral(rng)) if boxed else (None, None)
    vol = WorkingVolume(near, far, x, y)
    im = make_imaging("surfel", CAM, (3, 4), background=0.5, border=0, uncovered=uncovered, volume=vol) \
        if len(reference_select(cloud.points, cloud.colors, near, far, x, y)[0]) else None
    if im is None:   # nothing measured inside: refused (test_a_frame_with_nothing_inside_is_refused)
        return
    pts, cols = reference_select(cloud.points, cloud.colors, near, far, x, y)
    r = SurfelRenderer(cloud, im, axis)
    np.testing.assert_array_equal(r.points_np, pts)
    b = SCALE[axis] * rng.uniform(0.3, 1.0)
    alphas = make_grid(b, b / nseg)
    frames = r.render_batch(alphas).numpy()
    hulls = segment_hulls(r, alphas)
    for i, a in enumerate(alphas):
        np.testing.assert_allclose(frames[i], reference_frame(pts, cols, im, axis, a), atol=1e-6)
    for i in range(len(alphas) - 1):
        lo, hi = alphas[i], alphas[i + 1]
        for a in [lo, hi, np.nextafter(lo, hi), np.nextafter(hi, lo), *rng.uniform(lo, hi, 8)]:
            f = reference_frame(pts, cols, im, axis, a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (axis, i, a)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), axis=st.sampled_from(AXES), uncovered=st.sampled_from(UNCOVERED))
def test_binned_volume_selects_before_binning(seed, axis, uncovered):
    """render_factor 1 on a 16x12 camera: the volume selects camera points first, the bins are made of the
    selected ones only (their nearest depth, their mean colour), and the bounds hold."""
    rng = np.random.default_rng(seed)
    cam = CameraIntrinsics(16, 12, 14.0, 15.0, 7.5, 5.5, "cam")
    depth = rng.uniform(0.8, 1.6, cam.shape)
    depth[rng.random(cam.shape) < 0.1] = 0.0
    cloud = cloud_from_rgbd(depth, rng.random(cam.shape + (3,)).astype(np.float32), cam)
    near, far = 0.0, float(rng.uniform(1.0, 1.4))
    im = make_imaging("surfel", cam, (3, 4), background=0.5, border=0, render_factor=1, uncovered=uncovered,
                      volume=WorkingVolume(near, far))
    pts, cols = reference_bins(*reference_select(cloud.points, cloud.colors, near, far), im.camera)
    r = SurfelRenderer(cloud, im, axis)
    np.testing.assert_allclose(r.points_np, pts, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(r.colors_np, cols, atol=1e-6)
    b = SCALE[axis] * rng.uniform(0.3, 1.0)
    alphas = make_grid(b, b / 2)
    hulls = segment_hulls(r, alphas)
    for i in range(len(alphas) - 1):
        for a in [alphas[i], alphas[i + 1], *rng.uniform(alphas[i], alphas[i + 1], 6)]:
            f = reference_frame(pts, cols, im, axis, a)
            assert np.all(f >= hulls.lo[i] - 1e-7) and np.all(f <= hulls.hi[i] + 1e-7), (axis, i, a)


def test_points_at_the_far_face_are_chosen_once_at_alpha_zero():
    """A wall at exactly the far face (inside: the bounds are closed) and one 1 micrometre behind it
    (outside). Moving the camera back by 5 mm (tz < 0) puts the inside wall beyond the far face: it is
    still drawn; moving forward brings the outside one within it: still not drawn."""
    cam = CameraIntrinsics(16, 12, 14.0, 14.0, 7.5, 5.5, "cam")
    far = 1.25
    depth = np.full(cam.shape, far)
    depth[:, 8:] = far + 1e-6
    rgb = np.zeros(cam.shape + (3,), np.float32)
    rgb[:, :8] = 1.0
    cloud = cloud_from_rgbd(depth, rgb, cam)
    im = make_imaging("surfel", cam, (12, 16), background=0.25, border=0, uncovered="background", volume=WorkingVolume(0.0, far))
    frames = SurfelRenderer(cloud, im, "tz").render_batch([-0.005, 0.0, 0.005]).numpy()
    for f in frames:
        assert np.all(f[:, 1:7] == 1.0)          # the inside wall, whatever its moved depth
        assert np.all(f[:, 9:] == np.float32(0.25))   # the outside wall never
    hulls = segment_hulls(SurfelRenderer(cloud, im, "tz"), make_grid(0.005, 0.0025))
    for i, a in enumerate(np.linspace(-0.005, 0.005, 21)):
        seg = min(int((a + 0.005) // 0.0025), 3)
        f = reference_frame(*reference_select(cloud.points, cloud.colors, 0.0, far), im, "tz", a)
        assert np.all(f >= hulls.lo[seg] - 1e-7) and np.all(f <= hulls.hi[seg] + 1e-7), a


def test_uncovered_frame_comes_from_the_volume_and_the_outside_shows_the_background():
    """A near square (0.8 m) before a far wall (2 m) with a volume of 0-1 m: at alpha = 0 the wall's pixels
    show the background, and with uncovered "frame" a pixel the square leaves under motion shows the
    square's alpha = 0 colour, never the wall's."""
    cam = CameraIntrinsics(16, 12, 14.0, 14.0, 7.5, 5.5, "cam")
    depth = np.full(cam.shape, 2.0)
    depth[3:9, 5:11] = 0.8
    rgb = np.zeros(cam.shape + (3,), np.float32)
    rgb[3:9, 5:11] = 1.0
    cloud = cloud_from_rgbd(depth, rgb, cam)
    im = make_imaging("surfel", cam, (12, 16), background=0.5, border=0, uncovered="frame", volume=WorkingVolume(0.0, 1.0))
    r = SurfelRenderer(cloud, im, "tx")
    zero, moved = r.render_native([0.0, 0.04]).numpy()
    expect = np.broadcast_to(np.where((depth < 1.0)[..., None], 1.0, 0.5), cam.shape + (3,))
    np.testing.assert_array_equal(zero, expect.astype(np.float32))
    assert set(np.unique(moved)) <= {np.float32(0.5), np.float32(1.0)}   # no wall colour (0) ever
    assert not np.array_equal(moved, zero)


def test_a_frame_with_nothing_inside_is_refused():
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.5, 2.0, CAM.shape)
    cloud = cloud_from_rgbd(depth, rng.random(CAM.shape + (3,)).astype(np.float32), CAM)
    with pytest.raises(PwsError, match=r"nothing in the working volume \(depth 0-1 m\): none of the frame's 48 measured"):
        make_imaging("surfel", CAM, (3, 4), cloud=cloud, volume=WorkingVolume(0.0, 1.0))
    # filled points do not count: column 0 without depth is filled from column 1 (X = -0.5 Z there, -0.36 Z in
    # column 1); a volume around x = -0.5 Z holds the 6 filled points and no measured one
    holes = depth.copy()
    holes[:, 0] = 0.0
    filled = cloud_from_rgbd(holes, rng.random(CAM.shape + (3,)).astype(np.float32), CAM, fill="row")
    assert filled.filled == 6
    with pytest.raises(PwsError, match=r"none of the frame's 42 measured points lies in it \(6 filled ones do\)"):
        make_imaging("surfel", CAM, (3, 4), cloud=filled, volume=WorkingVolume(0.0, 2.1, (-1.1, -0.74)))
    depth[2, 2] = 0.9
    make_imaging("surfel", CAM, (3, 4), cloud=cloud_from_rgbd(depth, rng.random(CAM.shape + (3,)).astype(np.float32), CAM),
                 volume=WorkingVolume(0.0, 1.0))   # one measured point is enough


@pytest.mark.parametrize("near, far, x, y, what", [
    (1.0, 1.0, None, None, "must be larger than near"), (1.5, 1.0, None, None, "must be larger than near"),
    (-0.1, 1.0, None, None, "near must be >= 0"), (math.nan, 1.0, None, None, "finite"), (0.0, math.inf, None, None, "finite"),
    (0.0, 1.0, (0.2, 0.2), None, "zero size"), (0.0, 1.0, None, (0.3, -0.3), "zero size"),
    (0.0, 1.0, (math.nan, 0.2), None, "finite")])
def test_bad_volumes_are_refused_naming_the_problem(near, far, x, y, what):
    with pytest.raises(PwsError, match=what):
        WorkingVolume(near, far, x, y)


@pytest.mark.parametrize("params, what", [
    ({"working_volume.near": 1.0, "working_volume.far": 0.5}, "must be larger than near"),
    ({"working_volume.near": 1.0, "working_volume.far": 1.0}, "must be larger than near"),
    ({"working_volume.near": -1.0, "working_volume.far": 1.0}, "out of range"),
    ({"working_volume.far": math.nan}, "must be finite"),
    ({"working_volume.far": 1.0, "working_volume.x_min": 0.2, "working_volume.x_max": 0.2}, "zero size"),
    ({"working_volume.far": 0.0, "working_volume.near": 0.3}, "working_volume.far is 0"),
    ({"working_volume.x_min": -0.3, "working_volume.x_max": 0.3}, "working_volume.far is 0"),
    ({"working_volume.far": 1.5, "imaging": "paper"}, "needs imaging: surfel")])
def test_bad_volume_parameters_are_refused_at_start(params, what):
    with pytest.raises(PwsError, match=what):
        config_from_params(params)


def test_volume_parameters_and_description():
    cfg = config_from_params({"working_volume.far": 1.5, "working_volume.y_min": -0.5, "working_volume.y_max": 0.25})
    assert cfg.working_volume == WorkingVolume(0.0, 1.5, None, (-0.5, 0.25))
    assert cfg.certify_config().working_volume == cfg.working_volume
    assert config_from_params({}).working_volume is None and volume_from_limits(0.0, 0.0) is None
    im = make_imaging("surfel", CAM, (3, 4), volume=cfg.working_volume, background=0.5)
    assert "working volume depth 0-1.5 m, y -0.5 to 0.25 m (outside: 0.5)" in im.describe()
    back = Imaging.from_dict(im.to_dict(), im.camera)
    assert back == im and back.volume == cfg.working_volume
    assert Imaging.from_dict(make_imaging("surfel", CAM, (3, 4)).to_dict(), CAM).volume is None
    with pytest.raises(PwsError, match="working volume"):
        Imaging.from_dict({**im.to_dict(), "working_volume": {"near": 2.0, "far": 1.0}}, im.camera)
    with pytest.raises(PwsError, match="needs surfel imaging"):
        make_imaging("paper", CAM, (3, 4), volume=cfg.working_volume)


def test_the_nodes_record_the_volume_on_every_certificate_and_change_it_at_run_time(model_path):
    """The pipeline and the four processes (ROS-free harness of test_nodes_logic: a 32x24 frame, a square at
    1.2 m before a wall at 2 m) with working_volume 0-1.5 m: every certification names the volume, the four
    processes certify as the pipeline does, and the self-audit finds every bound holding. A change at run
    time goes through the nodes' own validation: a bad one is refused naming it."""
    from test_nodes_logic import frame_messages, pipeline_and_four
    from pws_ros.bridge.config import check_consistency

    def publish(bus):
        for topic, msg in frame_messages(1_700_000_000_000_000_000).items():
            bus.publish(topic, msg)

    runs = pipeline_and_four(model_path, publish, **{"working_volume.far": 1.5, "background": 0.5, "audit_every": 1})
    got = {name: parsed for name, (parsed, _ctx) in runs.items()}
    ctx = runs["pipeline"][1]
    for axis in ("tx", "tz"):
        for name in ("pipeline", "four"):
            v = got[name][axis]
            assert v["working_volume"] == "depth 0-1.5 m" and v["level"] in (0, 1), (name, axis, v["message"])
        assert got["pipeline"][axis]["label"] == got["four"][axis]["label"]
        assert got["pipeline"][axis]["p_a_lower"] == got["four"][axis]["p_a_lower"]
    assert any("working volume depth 0-1.5 m" in m for lvl, m in ctx.logs), ctx.logs
    cfg = ctx.config
    with pytest.raises(PwsError, match="must be larger than near"):
        check_consistency(cfg.with_params({"working_volume.near": 2.0}))   # what a node answers to ros2 param set
    assert check_consistency(cfg.with_params({"working_volume.far": 1.0})) is None


def test_without_a_volume_the_key_says_none(model_path):
    from test_nodes_logic import Bus, Context, params, play
    from pws_ros.bridge import msgbuild
    from pws_ros.nodes.pipeline import PipelineNode

    bus = Bus()
    node = PipelineNode(Context(bus, "pipeline", **params(model_path)))
    try:
        play(bus, [1_700_000_000_000_000_000], lambda: bus.published["/certification"])
        parsed = msgbuild.parse_certification(bus.published["/certification"][0])
        assert all(v["working_volume"] == "none" for v in parsed.values())
    finally:
        node.close()
        bus.close()


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))


@pytest.mark.parametrize("render_factor", [0, 1])
def test_a_volume_draws_measured_points_only(render_factor):
    """With the depth fill on, the points whose depth was filled are never inside a volume (a row whose only
    valid depth is a near hand would otherwise be filled at the hand's depth across the room): the renderer
    draws the measured points inside, as the brute force selects them from the depth image itself."""
    rng = np.random.default_rng(7)
    cam = CameraIntrinsics(16, 12, 14.0, 15.0, 7.5, 5.5, "cam")
    depth = np.zeros(cam.shape)                      # no return: the room beyond the sensor's range
    depth[4:9, 3:9] = rng.uniform(0.6, 0.8, (5, 6))  # the hand
    depth[4:9, 5] = 0.0                              # a hole inside it
    depth[10:, :] = 3.0                              # a far floor, outside the volume
    rgb = rng.random(cam.shape + (3,)).astype(np.float32)
    cloud = cloud_from_rgbd(depth, rgb, cam, fill="row")
    assert cloud.filled == int((depth == 0).sum())
    im = make_imaging("surfel", cam, (3, 4), background=0.5, border=0, render_factor=render_factor, volume=WorkingVolume(0.0, 1.5),
                      cloud=cloud)
    measured = [(c - cam.cx) * depth[r, c] / cam.fx for r in range(12) for c in range(16) if 0 < depth[r, c] <= 1.5]
    r = SurfelRenderer(cloud, im, "ry")
    if render_factor == 0:
        assert sorted(r.points_np[:, 0]) == pytest.approx(sorted(measured), abs=1e-12) and len(r.points_np) == 25
    zero = r.render_native([0.0]).numpy()[0]
    if render_factor == 0:   # at alpha = 0 the hand's measured pixels show their colour, everything else 0.5
        want = np.where(((depth > 0) & (depth <= 1.5))[..., None], rgb, np.float32(0.5))
        np.testing.assert_array_equal(zero, want)
    assert config_from_params({"working_volume.far": 1.5}).background_value == 0.5   # automatic: mid-grey with a volume
    assert config_from_params({}).background_value == 0.0 and config_from_params({"working_volume.far": 1.5, "background": 0.0}).background_value == 0.0


def test_finetune_trains_on_the_images_that_are_certified(model_path, tmp_path):
    """pws finetune renders its training views through the certifier's imaging: with a working volume its
    alpha = 0 view is the brute force's frame of the selected points (background 0.5 outside)."""
    from types import SimpleNamespace

    from pws_ros.bridge.engine import FrameCertifier
    from pws_ros.finetune.cache import FramePreparer

    cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
    rng = np.random.default_rng(3)
    depth = np.full(cam.shape, 2.0)
    depth[6:18, 8:20] = rng.uniform(1.0, 1.3, (12, 12))
    cloud = cloud_from_rgbd(depth, rng.random(cam.shape + (3,)).astype(np.float32), cam)
    cfg = config_from_params({"model_path": str(model_path), "working_volume.far": 1.5, "axes": ["tz"]})
    engine = FrameCertifier(cfg, log=lambda *a: None)
    prep = FramePreparer(SimpleNamespace(views=0, seed=0), engine.model, engine, tmp_path, device="cpu", stop=None,
                         warn=print, info=print)
    imaging = engine.imaging_for(cam, cloud)
    view = prep.render(cloud, imaging, [])[0]
    pts, cols = reference_select(cloud.points, cloud.colors, 0.0, 1.5)
    np.testing.assert_allclose(view, reference_frame(pts, cols, imaging, "tz", 0.0), atol=1e-6)
    assert imaging.background == 0.5 and np.isclose(view, 0.5).any()


@pytest.mark.rclpy
@pytest.mark.slow
@pytest.mark.parametrize("launch_file", ["pws.launch.py", "pws_nodes.launch.py"])
def test_live_launches_certify_with_a_working_volume(launch_file, tmp_path, monkeypatch):
    """ROS 2 (skipped without rclpy): each launch file with working_volume 0-3 m in its parameter file,
    the demo frames played: every certification names the volume on every axis, and frames are certified."""
    import json as _json

    from pws_ros.bridge import msgbuild
    from pws_ros.nodes.live import COLOR, DEPTH, DEPTH_INFO, INFO, Launch, Player, demo_frames, ros_env, wait_for
    from test_live_flood import LAUNCHES

    domain = 100 + (os.getpid() + len(launch_file)) % 50
    env = ros_env(tmp_path, domain)
    for k in ("ROS_DOMAIN_ID", "CYCLONEDDS_URI", "RMW_IMPLEMENTATION", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(k, env[k])
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    config = tmp_path / "volume.yaml"
    config.write_text("/**:\n  ros__parameters:\n    input_mode: rgbd\n    input_qos: reliable\n"
                      f"    model_path: {_json.dumps(str(Path(__file__).resolve().parents[1] / 'bags/models/classifier_sigma0.50.pt'))}\n"
                      "    working_volume:\n      near: 0.0\n      far: 3.0\n")
    launch = Launch(launch_file, {"config_file": str(config)}, tmp_path, env)
    player = None
    try:
        assert wait_for(lambda: set(launch.nodes()) >= set(LAUNCHES[launch_file]) or launch.proc.poll() is not None, 60), launch.text()[-3000:]
        player = Player(domain, {DEPTH: "Image", COLOR: "Image", INFO: "CameraInfo", DEPTH_INFO: "CameraInfo"}, "volume_player")
        assert wait_for(lambda: player.subscribed((DEPTH, COLOR, INFO)), 60), launch.text()[-3000:]
        demo = demo_frames(player.T)
        t0 = time.time_ns() // 10**9 * 10**9
        for k, (build, _label) in enumerate(demo[:3]):
            stamp = t0 + (k + 1) * 10**9
            for topic, msg in build(stamp):
                player.publish(topic, msg)
            assert wait_for(lambda: stamp in player.certified_stamps(), 240, 0.1), launch.text()[-3000:]
        parsed = [msgbuild.parse_certification(m) for m in player.messages()]
        assert len(parsed) == 3
        assert all(v["working_volume"] == "depth 0-3 m" for p in parsed for v in p.values()), parsed
        assert sum(v["level"] == 0 for p in parsed for v in p.values()) >= 1, parsed
        assert "working volume depth 0-3 m" in launch.text()
    finally:
        if player is not None:
            player.close()
        launch.stop()


def test_window_draws_the_nearest_band_in_a_camera_window_around_it():
    """--window: the frame's far face is the 2nd percentile of its in-volume depths + the band, and the
    crop is the smallest one of the input's aspect (s k camera pixels per input pixel) around those
    points' pixels (1st-99th percentile, widened 15% a side), kept in the image: checked against
    numbers worked out here for a 640x480 camera, a near patch (a hand) and a wall behind it."""
    cam = CameraIntrinsics(640, 480, 615.0, 615.0, 320.0, 240.0)
    depth = np.full((480, 640), 1.2, np.float32)              # a wall at 1.2 m
    depth[200:320, 400:560] = 0.7                              # a hand at 0.7 m (6% of the pixels)
    cloud = cloud_from_rgbd(depth, np.zeros((480, 640, 3), np.uint8), cam)
    vol = WorkingVolume(0.0, 1.5, window=0.3)
    framed = vol.for_frame(cloud.points)
    assert framed.far == pytest.approx(1.0) and framed.window == 0.0       # 0.7 (the 2nd percentile) + 0.3
    im = make_imaging("surfel", cam, (60, 80), cloud=cloud, volume=vol, render_factor=2, border=0)
    assert im.volume.far == pytest.approx(1.0)
    # the hand's pixels (pinhole projection of its points), 1st..99th percentile
    hand = cloud.points[np.abs(cloud.points[:, 2] - 0.7) < 1e-6].astype(np.float64)
    u, v = 615.0 * hand[:, 0] / hand[:, 2] + 320.0, 615.0 * hand[:, 1] / hand[:, 2] + 240.0
    (u0, u1), (v0, v1) = np.percentile(u, [1, 99]), np.percentile(v, [1, 99])
    s = max(1, math.ceil(max((u1 - u0) * 1.3 / 160, (v1 - v0) * 1.3 / 120)))
    assert s == 2 and im.decimate == 2 and (s * im.camera.width, s * im.camera.height) == (320, 240)
    x0 = min(max(0, round((u0 + u1) / 2 - 160)), 640 - 320)
    y0 = min(max(0, round((v0 + v1) / 2 - 120)), 480 - 240)
    assert im.crop == (x0, y0)
    # binned 2x2: pixel edges scale, so centres map c -> (c + 0.5) / 2 - 0.5
    assert im.camera.cx == pytest.approx((320.0 - x0 + 0.5) / 2 - 0.5) and im.camera.cy == pytest.approx((240.0 - y0 + 0.5) / 2 - 0.5)
    assert "camera window" in im.describe()
    # without the window: the centred crop of the whole frame and the whole volume
    whole = make_imaging("surfel", cam, (60, 80), cloud=cloud, volume=WorkingVolume(0.0, 1.5), render_factor=2, border=0)
    assert whole.crop == (0, 0) and whole.decimate == 4 and whole.volume.far == 1.5
    assert WorkingVolume.from_dict(vol.to_dict()) == vol
    assert volume_from_limits(0.0, 1.5, window=0.3) == vol
    with pytest.raises(PwsError, match="window"):
        volume_from_limits(0.0, 0.0, window=0.3)
    with pytest.raises(PwsError, match="window"):
        WorkingVolume(0.0, 1.5, window=-1.0)


def reference_subject(points, candidates, fx, fy, cx, cy, width, height, step):
    """The window's subject (docs/imaging.md 4b), loops only: pixel depths, flood fill, the largest cluster
    that does not span the view (ties: nearer, then first pixel in row-major order), its points."""
    depth = {}
    where = {}
    for i, (X, Y, Z) in enumerate(points):
        if not candidates[i] or not Z > 0:
            continue
        c, r = math.floor(fx * X / Z + cx + 0.5), math.floor(fy * Y / Z + cy + 0.5)
        if 0 <= c < width and 0 <= r < height:
            where[i] = (r, c)
            depth[(r, c)] = min(depth.get((r, c), math.inf), Z)
    label = {}
    clusters = []
    for r in range(height):
        for c in range(width):
            if (r, c) not in depth or (r, c) in label:
                continue
            label[(r, c)] = len(clusters)
            todo, members = [(r, c)], []
            while todo:
                a = todo.pop()
                members.append(a)
                for b in ((a[0] - 1, a[1]), (a[0] + 1, a[1]), (a[0], a[1] - 1), (a[0], a[1] + 1)):
                    if b in depth and b not in label and abs(depth[a] - depth[b]) <= step:
                        label[b] = len(clusters)
                        todo.append(b)
            clusters.append(members)
    best = None
    for k, members in enumerate(clusters):
        rows = [m[0] for m in members]
        cols = [m[1] for m in members]
        if (min(cols) == 0 and max(cols) == width - 1) or (min(rows) == 0 and max(rows) == height - 1):
            continue
        key = (-len(members), min(depth[m] for m in members), min(rows[j] * width + cols[j] for j in range(len(members))))
        if best is None or key < best[0]:
            best = (key, k)
    out = np.zeros(len(points), bool)
    for i in range(len(points)):
        if not candidates[i] or not points[i][2] > 0:
            continue
        if best is None:
            out[i] = True
        elif i in where and label[where[i]] == best[1] and abs(points[i][2] - depth[where[i]]) <= step:
            out[i] = True
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_window_subject_matches_a_brute_force_flood_fill(seed):
    """window_subject (vectorised: pixel depths, scipy's connected components) equals the loops above on
    small random scenes: blobs at random depths (some spanning the view), holes, stray points, points sharing
    a pixel, points outside the image and behind the camera, a random candidate mask."""
    from pws_ros.core.framing import SUBJECT_STEP, window_subject

    rng = np.random.default_rng(seed)
    W, H = int(rng.integers(4, 14)), int(rng.integers(3, 11))
    cam = CameraIntrinsics(W, H, 10.0, 11.0, W / 2 - 0.3, H / 2 + 0.2)
    depth = np.zeros((H, W))
    for _ in range(int(rng.integers(1, 5))):
        r0, c0 = int(rng.integers(0, H)), int(rng.integers(0, W))
        r1, c1 = r0 + int(rng.integers(1, H + 1)), c0 + int(rng.integers(1, W + 1))
        z = rng.uniform(0.3, 2.0)
        depth[r0:r1, c0:c1] = z + rng.uniform(-1, 1, size=depth[r0:r1, c0:c1].shape) * rng.choice([0.0, 0.005, 0.03])
    depth[rng.random((H, W)) < rng.uniform(0, 0.3)] = 0.0
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols]
    pts = np.stack([(cols - cam.cx) * z / cam.fx, (rows - cam.cy) * z / cam.fy, z], axis=1)
    extra = rng.normal(0, 1, size=(int(rng.integers(0, 6)), 3)) * [0.5, 0.5, 1.0] + [0, 0, 0.5]
    dup = pts[rng.integers(0, len(pts), size=min(3, len(pts)))] * rng.uniform(0.9, 1.1) if len(pts) else np.zeros((0, 3))
    points = np.concatenate([pts, extra, dup]) if len(pts) else np.concatenate([extra, np.zeros((1, 3)) + [0, 0, 1]])
    cand = rng.random(len(points)) < rng.choice([1.0, 0.8])
    got = window_subject(points, cand, cam)
    want = reference_subject(points.tolist(), cand.tolist(), cam.fx, cam.fy, cam.cx, cam.cy, W, H, SUBJECT_STEP)
    assert np.array_equal(got, want), (seed, np.flatnonzero(got ^ want))


def test_window_follows_the_hand_not_a_nearer_wall_or_clutter():
    """A wall nearer than the hand that spans the view (top to bottom) and small clutter blobs on the floor,
    nearer still: the subject is the hand, the far face the hand's depth + the band, the crop around it."""
    from pws_ros.core.framing import window_subject

    cam = CameraIntrinsics(640, 480, 615.0, 615.0, 320.0, 240.0)
    depth = np.full((480, 640), 3.0, np.float32)               # the room, outside the volume
    depth[:, 400:] = np.linspace(0.7, 1.4, 240)[None, :]      # a slanted wall on the right, 0.7-1.4 m, top to bottom
    depth[100:220, 0:200] = 1.0                                 # the hand and arm from the left at 1.0 m
    for c in range(40, 360, 40):
        depth[440:452, c:c + 10] = 0.6                          # floor clutter, 0.6 m
    cloud = cloud_from_rgbd(depth, np.zeros((480, 640, 3), np.uint8), cam)
    vol = WorkingVolume(0.0, 1.5, window=0.3)
    subject = window_subject(cloud.points, vol.contains(cloud.points), cam)
    assert np.allclose(cloud.points[subject, 2], 1.0) and subject.sum() == 120 * 200
    im = make_imaging("surfel", cam, (60, 80), cloud=cloud, volume=vol, render_factor=2, border=0)
    assert im.volume.far == pytest.approx(1.3)
    assert im.crop[0] == 0 and im.crop[1] <= 100 and im.crop[1] + im.decimate * im.camera.height >= 220
    assert im.decimate * im.camera.width <= 320                # the hand fills the window, not the whole frame
    # the nearest 2% of the whole volume (the wall's near side, ~0.71 m) no longer decides the band
    assert vol.for_frame(cloud.points).far < 1.05

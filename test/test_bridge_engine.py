"""FrameCertifier (pws_ros.bridge.engine): the per-frame pipeline of the nodes, checked against the
core's certify() directly, the four-process path (messages + assembler) against the in-memory path,
per-axis error isolation, camera rescaling to the model's input size and the CUDA fallback."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pws_ros.bridge import msgbuild, scheme
from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.engine import FrameCertifier, resolve_device_with_fallback
from pws_ros.bridge.preview import preview_indices
from pws_ros.bridge.assembly import PartitionAssembler
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.certify import certify
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.model import load_model
from pws_ros.core.render import render

T = msgbuild.rosbags_types()
FAST = {"n0": 16, "n": 32, "batch_size": 64, "axes": ["tz", "ry"]}


def box_depth(intr: CameraIntrinsics) -> np.ndarray:
    """A box at 1.2 m in front of a wall at 2 m, seen by ``intr``."""
    h, w = intr.height, intr.width
    depth = np.full((h, w), 2.0)
    depth[h // 4: 3 * h // 4, w // 4: 5 * w // 8] = 1.2
    return depth


def scene(intr: CameraIntrinsics, seed: int = 0) -> Cloud:
    """A reddish box in front of a wall, seen by ``intr``."""
    rgb = np.random.default_rng(seed).integers(0, 256, (intr.height, intr.width, 3), dtype=np.uint8)
    rgb[..., 0] = 230  # red channel high: MeanThresholdNet says class 1
    return cloud_from_rgbd(box_depth(intr), rgb, intr)


@pytest.fixture
def model_path(make_model_file):
    return make_model_file(input_size=(24, 32))  # MeanThresholdNet(0.5) on the red channel, 2 classes


def make_engine(model_path, **params):
    logs = []
    cfg = config_from_params({**FAST, "model_path": str(model_path), **params})
    return FrameCertifier(cfg, log=lambda level, msg: logs.append((level, msg))), logs


def test_process_matches_core_certify(model_path, small_camera):
    eng, _ = make_engine(model_path)
    cloud = scene(small_camera)
    res = eng.process(cloud, small_camera, 123, frame_id="cam")
    assert [c.axis for c in res.certificates] == ["tz", "ry"]
    assert res.stamp_ns == 123 and res.frame_id == "cam" and res.camera == small_camera
    assert set(res.plans) == {"tz", "ry"} and set(res.compute_ms) == {"tz", "ry"}
    model = load_model(model_path)
    imaging = eng.imaging_for(small_camera, cloud)
    for c in res.certificates:
        assert c.status in ("certified", "not_certified") and c.label == 1 and c.class_name == "c1"
        assert c.method == "pws_of" and c.coverage == "anchors" and c.n == 32 and c.n0 == 16 and c.imaging == "surfel"
        assert {"plan", "render", "inference", "statistics", "total"} <= set(c.timings)
        # the frame's risk 0.01 is split over its two axes
        assert c.frame_alpha == 0.01 and c.alpha == pytest.approx(0.005)
        cfg = eng.certify_config(c.axis, 123)
        assert cfg.seed == c.seed
        ref = certify(cloud, small_camera, model, c.axis, eng.config.radius_for(c.axis), "pws_of", cfg, imaging=imaging)
        assert ref.p_a_lower == c.p_a_lower and ref.radius == c.radius and ref.status == c.status
    tz, ry = res.certificates
    assert tz.seed != ry.seed  # independent noise per axis ...
    again = eng.process(cloud, small_camera, 123)
    assert [c.p_a_lower for c in again.certificates] == [c.p_a_lower for c in res.certificates]  # ... seeded
    assert [c.seed for c in eng.process(cloud, small_camera, 124).certificates] != [tz.seed, ry.seed]  # and per frame


def test_paper_imaging_rescales_the_camera_to_the_model_input(model_path):
    big = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, "cam")
    eng, logs = make_engine(model_path, axes=["tz"], imaging="paper")
    res = eng.process(scene(big), big, 1)
    assert res.camera == big.scaled(32, 24)
    assert res.certificates[0].status != "error", res.certificates[0].reason
    assert not any("aspect ratio" in m for _, m in logs)
    wide = CameraIntrinsics(64, 36, 60.0, 60.0, 31.5, 17.5, "cam")
    res = eng.process(scene(wide), wide, 2)
    assert res.camera.shape == (24, 32) and any("aspect ratio changes" in m for _, m in logs)
    eng.process(scene(wide), wide, 3)  # warned once per engine; paper imaging logs no surfel description
    assert sum("aspect ratio changes" in m for _, m in logs) == 1 and not any("memory per axis" in m for _, m in logs)


def test_surfel_imaging_crops_the_camera_to_a_multiple_of_the_model_input(model_path):
    big = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, "cam")
    eng, logs = make_engine(model_path, axes=["tz"])
    res = eng.process(scene(big), big, 1)
    assert res.camera == big  # 64x48 is twice the model's 32x24: rendered at native resolution, no crop
    assert res.certificates[0].status != "error", res.certificates[0].reason
    assert res.certificates[0].bounds["imaging"]["factor"] == 2
    wide = CameraIntrinsics(70, 36, 60.0, 60.0, 34.5, 17.5, "cam")
    res = eng.process(scene(wide), wide, 2)  # a centred 32x24 crop (x0 = 19, y0 = 6), factor 1
    assert (res.camera.width, res.camera.height, res.camera.cx, res.camera.cy) == (32, 24, 34.5 - 19, 17.5 - 6)
    assert not any("aspect ratio changes" in m for _, m in logs)
    assert sum("memory per axis" in m for _, m in logs) == 1  # the imaging description is logged once per engine
    small = CameraIntrinsics(16, 12, 20.0, 20.0, 7.5, 5.5, "cam")
    (c,) = eng.process(scene(small), small, 3).certificates
    assert c.status == "error" and "smaller than the classifier's input 32x24" in c.reason


def test_render_size_override_and_mismatch_is_an_error_certificate(model_path, small_camera):
    eng, _ = make_engine(model_path, axes=["tz"], render_width=16, render_height=12)
    res = eng.process(scene(small_camera), small_camera, 1)
    (c,) = res.certificates
    assert c.status == "error" and "expects 32x24" in c.reason and "16x12" in c.reason


def test_one_bad_axis_does_not_stop_the_others(model_path, small_camera, monkeypatch):
    eng, _ = make_engine(model_path, axes=["tx", "tz"], **{"radius.tx": 0.05, "radius.tz": 0.02})
    plan_axis = eng.plan_axis

    def failing(cloud, imaging, axis):
        if axis == "tz":
            raise PwsError("tz radius 0.02 m reaches the nearest point of the cloud")
        return plan_axis(cloud, imaging, axis)

    monkeypatch.setattr(eng, "plan_axis", failing)
    res = eng.process(scene(small_camera), small_camera, 1)
    tx, tz = res.certificates
    assert tz.status == "error" and "reaches the nearest point" in tz.reason and tz.requested_radius == 0.02
    assert tz.sigma == 0.5 and tz.n == 32 and "tz" not in res.plans
    assert tx.status != "error" and "tx" in res.plans


def test_a_plan_above_max_partitions_is_coarser_not_refused(model_path, small_camera):
    eng, _ = make_engine(model_path, axes=["tx"], max_partitions=3, **{"radius.tx": 0.05}, imaging="paper")
    (c,) = eng.process(scene(small_camera), small_camera, 1).certificates
    assert c.status != "error" and c.num_partitions == 3 and c.bounds["coarsened_from"] > 3


def test_empty_cloud_gives_error_certificates(model_path, small_camera):
    eng, _ = make_engine(model_path)
    res = eng.process(Cloud(np.zeros((0, 3)), np.zeros((0, 3))), small_camera, 1)
    assert [c.status for c in res.certificates] == ["error", "error"]
    assert all("empty" in c.reason for c in res.certificates)


def test_unexpected_exceptions_are_contained(model_path, small_camera, monkeypatch):
    eng, logs = make_engine(model_path, axes=["tz"])
    monkeypatch.setattr(eng, "plan_axis", lambda *a: (_ for _ in ()).throw(RuntimeError("CUDA out of memory")))
    (c,) = eng.process(scene(small_camera), small_camera, 1).certificates
    assert c.status == "error" and c.reason == "internal error (RuntimeError): CUDA out of memory"
    assert logs and logs[-1][0] == "error"


def four_process(eng: FrameCertifier, cloud: Cloud, camera: CameraIntrinsics, S: int, certifier: FrameCertifier | None = None):
    """plan bundle -> render -> frames/bounds as messages (CDR) -> assembler -> certify_assembled (by ``certifier``,
    a node configured apart, else ``eng``)."""
    bundle = eng.plan_bundle(cloud, camera, S, "cam")
    assert not bundle.errors and bundle.camera == camera
    wire = scheme.parse_plan_bundle_message(T.typestore.deserialize_cdr(
        T.typestore.serialize_cdr(scheme.plan_bundle_message(bundle, T), "std_msgs/msg/String"), "std_msgs/msg/String"))
    asm = PartitionAssembler()
    asm.expect(S, wire.expected(), info=wire)
    for axis, plan in wire.plans.items():
        assert wire.imaging == bundle.imaging
        rendered = eng.render_axis(cloud, wire.imaging, plan)
        n = len(plan.alphas)
        for i in range(n):
            tag, frame = scheme.parse_frame_message(scheme.frame_message(S, axis, i, n, rendered.frames[i], T))
            asm.add_frame(tag.stamp_ns, tag.axis, tag.index, tag.count, frame)
        b = scheme.parse_bounds_message(scheme.bounds_message(S, axis, rendered, T))
        asm.add_bounds(S, axis, b.count, b)
    (frame,) = asm.pop_ready()
    return bundle, (certifier or eng).certify_assembled(frame)


@pytest.mark.parametrize("imaging", ["surfel", "paper"])
def test_four_process_path_gives_the_same_certificate(model_path, small_camera, imaging):
    """The four-process path equals the pipeline's in-memory certify() (pairwise coverage)."""
    eng, _ = make_engine(model_path, axes=["tx", "tz"], **{"radius.tx": 0.05}, imaging=imaging, coverage="pairwise")
    cloud = scene(small_camera)
    S = 1_700_000_000_000_000_000
    bundle, four = four_process(eng, cloud, small_camera, S)
    assert bundle.imaging.kind == imaging
    one = eng.process(cloud, small_camera, S)
    assert four.frame_id == "cam" and [c.axis for c in four.certificates] == ["tx", "tz"]
    for a, b in zip(four.certificates, one.certificates):
        assert a.status == b.status and a.radius == b.radius and a.p_a_lower == b.p_a_lower
        assert a.num_partitions == b.num_partitions and a.bounds["max_pair_bound_sq"] == pytest.approx(b.bounds["max_pair_bound_sq"])


def smooth_scene(intr: CameraIntrinsics) -> Cloud:
    """The box and wall of :func:`scene` in smooth colours (no per-pixel noise: a short rendered path)."""
    h, w = intr.height, intr.width
    r, c = np.mgrid[0:h, 0:w]
    rgb = np.stack([np.full((h, w), 230), 40 + 150 * c // w, 40 + 150 * r // h], axis=-1).astype(np.uint8)
    return cloud_from_rgbd(box_depth(intr), rgb, intr)


def test_four_process_frame_alpha_is_split_over_the_axes_the_planner_sent(model_path, small_camera):
    """The frame's statement covers every axis the certifier certifies: those of the planner's bundle. A
    certifier node configured for fewer axes than its planner still splits the frame's alpha over the axes it
    certifies (the per-axis levels sum to frame_alpha), and names the mismatch once."""
    planner, _ = make_engine(model_path, axes=["tz", "ry", "tx"], **{"radius.tx": 0.05})
    certifier, logs = make_engine(model_path, axes=["tz"])
    for S in (1_700_000_000_000_000_010, 1_700_000_000_000_000_011):
        _, four = four_process(planner, scene(small_camera), small_camera, S, certifier=certifier)
        assert [c.axis for c in four.certificates] == ["tz", "ry", "tx"]
        for c in four.certificates:
            assert c.alpha == pytest.approx(0.01 / 3) and c.frame_alpha == 0.01
        assert sum(c.alpha for c in four.certificates) == pytest.approx(four.certificates[0].frame_alpha)
    warned = [m for level, m in logs if level == "warn" and "the planner sent axes" in m]
    assert len(warned) == 1 and "tz, ry, tx" in warned[0] and "3 axes" in warned[0]


def test_four_process_path_places_the_same_adaptive_anchors(model_path, small_camera):
    """With the default coverage (surfel imaging, anchors) the planner refines the grid for the largest
    target any selection can give and the certifier places the anchors from the received bounds: where the
    selection is unanimous (the pipeline's target is that one) and the pipeline needed no frontier
    refinement, both give the same grid (but for the points near 0 the planner adds), anchors, p_A bounds
    and radius."""
    from pws_ros.core.certify import largest_target

    eng, _ = make_engine(model_path, axes=["tz", "ry"], **{"radius.tz": 0.05, "radius.ry": 0.0125}, sigma=0.25)
    cloud = smooth_scene(small_camera)
    S = 1_700_000_000_000_000_001
    bundle, four = four_process(eng, cloud, small_camera, S)
    one = eng.process(cloud, small_camera, S)
    for a, b in zip(four.certificates, one.certificates):
        # preconditions of the equality (the scene and settings are chosen so that they hold)
        assert b.bounds["target_radius"] == largest_target(eng.certify_config(a.axis, S))[0] and b.bounds["frontier_splits"] == 0
        assert len(b.bounds["anchors"]) >= 2 and b.certified
        assert bundle.plans[a.axis].details["refined_from"] < len(bundle.plans[a.axis].alphas)   # the planner refined
        assert a.status == b.status and a.radius == b.radius and a.p_a_lower == b.p_a_lower, (a.axis, a.reason, b.reason)
        assert a.bounds["anchors"] == b.bounds["anchors"]
        # the same grid, plus the points near 0 that stand in for the frontier refinement (4 a side)
        four_grid, one_grid = bundle.plans[a.axis].alphas, one.plans[b.axis].alphas
        assert set(one_grid) <= set(four_grid) and len(four_grid) == len(one_grid) + 8 == a.num_partitions
        c = int(np.searchsorted(one_grid, 0.0))
        assert set(four_grid) - set(one_grid) == {x / 4 ** k for x in (one_grid[c - 1], one_grid[c + 1]) for k in (1, 2, 3, 4)}
        assert a.classifier_calls == b.classifier_calls and a.coverage == "anchors" and a.imaging == "surfel"
        assert a.bounds["imaging"] == b.bounds["imaging"]


def test_four_process_path_without_frontier_refinement_reaches_a_grid_point(model_path, small_camera):
    """Where the pipeline's covered run stops inside a segment it refines that segment (frontier); the
    four-process certifier has no renderer, so its radius stops at a grid point of its grid (the points
    near 0 the planner adds included): never more than the pipeline's, and still above 0 here."""
    # uncovered: background (black disocclusions) keeps this frame short of the radius (with "frame" it is certified)
    eng, _ = make_engine(model_path, axes=["tz"], **{"radius.tz": 0.2}, sigma=0.25, uncovered="background")
    cloud = smooth_scene(small_camera)
    S = 1_700_000_000_000_000_002
    bundle, four = four_process(eng, cloud, small_camera, S)
    (a,), (b,) = four.certificates, eng.process(cloud, small_camera, S).certificates
    assert b.bounds["frontier_splits"] > 0 and not b.certified   # the case this test is about
    assert a.status == "not_certified" and a.bounds["frontier_splits"] == 0
    # the pipeline, short of the radius after one refinement round, refines its grid further and places its
    # anchors again (the planner refines once): their anchors differ, the pipeline's radius is the larger
    assert 0 < a.radius <= b.radius and b.num_partitions > bundle.plans["tz"].num_partitions
    assert min(abs(bundle.plans["tz"].alphas - a.radius)) == 0 or min(abs(bundle.plans["tz"].alphas + a.radius)) == 0


def test_four_process_points_near_zero_give_a_weak_frame_a_radius(model_path, small_camera):
    """A weak frame (p_A near 1/2: a small Cohen radius, far below the largest target the planner refined
    for) is covered only inside the first segment on one side; the pipeline's frontier refinement finds
    a radius there, and the four-process certifier, which cannot refine, still reaches one of the points
    near 0 the planner added (without them its radius would be 0)."""
    eng, _ = make_engine(model_path, axes=["ry"], **{"radius.ry": 0.0125}, sigma=0.25)
    cloud = smooth_scene(small_camera)
    red = np.full((len(cloud.colors), 1), 146 / 255, np.float32)   # just above MeanThresholdNet's threshold
    cloud = Cloud(cloud.points, np.concatenate([red, cloud.colors[:, 1:]], axis=1))
    S = 10
    bundle, four = four_process(eng, cloud, small_camera, S)
    (a,), (b,) = four.certificates, eng.process(cloud, small_camera, S).certificates
    grid = bundle.plans["ry"].alphas
    c = int(np.searchsorted(grid, 0.0))
    first = min(grid[c + 5], -grid[c - 5])   # the first grid points beyond the 4 added a side
    assert bundle.plans["ry"].details["near_centre_points"] == 8
    assert b.bounds["frontier_splits"] > 0 and 0 < b.radius < first       # the case this test is about
    # the pipeline, short of the radius on its first grid, refines further and places its anchors again (24 of
    # them, each at level alpha / 24); the planner refines once: their anchors differ, and for this weak frame
    # (p_A near 1/2, far below what the selection predicted) neither radius bounds the other
    assert 0 < a.radius < first and b.num_partitions > len(grid) and len(b.p_a_lower) > len(a.p_a_lower)
    assert a.radius in set(np.abs(grid))


@pytest.mark.parametrize("params", [{"coverage": "pairwise"}, {"coverage": "paper"}, {"imaging": "paper"}])
def test_the_planner_refines_only_for_the_adaptive_anchors(model_path, small_camera, params):
    eng, _ = make_engine(model_path, axes=["tz"], **{"radius.tz": 0.05}, sigma=0.25, **params)
    cloud = smooth_scene(small_camera)
    bundle = eng.plan_bundle(cloud, small_camera, 3)
    plan = eng.plan_axis(cloud, bundle.imaging, "tz")
    np.testing.assert_array_equal(bundle.plans["tz"].alphas, plan.alphas)


def test_the_planners_grid_stays_within_max_partitions(model_path, small_camera):
    """The refinement leaves room for the 8 points near 0; where the plan itself fills max_partitions, as
    many as fit are added, the coarsest (1/4 of the first segment) first."""
    for cap in (7, 9, 12, 257):
        eng, _ = make_engine(model_path, axes=["tz"], **{"radius.tz": 0.05}, sigma=0.25, max_partitions=cap)
        bundle = eng.plan_bundle(smooth_scene(small_camera), small_camera, 3)
        plan = bundle.plans["tz"]
        a = plan.alphas
        assert len(a) <= cap and 0.0 in set(a) and np.all(np.diff(a) > 0)
        near = plan.details.get("near_centre_points", 0)
        assert near == 8 or len(a) == cap, (cap, near, len(a))
        if near:   # the added points are the grid's nearest to 0; the farthest of them is 1/4 of a first grid point
            inner = np.sort(np.abs(a[a != 0.0]))[:near]
            assert inner[-1] * 4 in set(np.abs(a))
    assert near == 8


def test_incomplete_set_is_an_error_in_certify_assembled(model_path, small_camera):
    eng, _ = make_engine(model_path, axes=["tz"])
    asm = PartitionAssembler()
    bundle = eng.plan_bundle(scene(small_camera), small_camera, 5, "cam")
    asm.expect(5, bundle.expected(), info=bundle)
    asm.add_frame(5, "tz", 1, len(bundle.plans["tz"].alphas), np.zeros((24, 32, 3), np.float32))
    (frame,) = asm.pop_ready()
    (c,) = eng.certify_assembled(frame).certificates
    assert c.status == "error" and "lost frame(s) 0" in c.reason


def test_cms_only_in_the_pipeline(model_path, small_camera):
    eng, _ = make_engine(model_path, axes=["tz"], method="cms", n0=8, n=16)
    bundle = eng.plan_bundle(scene(small_camera), small_camera, 1)
    assert "only available in the pipeline" in bundle.errors["tz"]
    (c,) = eng.process(scene(small_camera), small_camera, 1).certificates
    assert c.method == "cms" and c.status != "error", c.reason


def test_pws_uses_the_dense_cloud(model_path, small_camera, tmp_path):
    dense = scene(small_camera, seed=1)
    path = tmp_path / "dense.npz"
    dense.save(path)
    eng, logs = make_engine(model_path, axes=["tz"], method="pws", dense_cloud_path=str(path), imaging="paper")
    assert any("loaded dense cloud" in m for _, m in logs)
    one_frame = Cloud(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 0.0]]))
    (c,) = eng.process(one_frame, small_camera, 1).certificates
    ref = certify(dense, small_camera, load_model(model_path), "tz", 0.01, "pws", eng.certify_config("tz", 1))
    assert c.method == "pws" and c.p_a_lower == ref.p_a_lower and c.label == ref.label
    with pytest.raises(PwsError, match="dense cloud file not found"):
        make_engine(model_path, method="pws", dense_cloud_path=str(tmp_path / "none.npz"), imaging="paper")


def test_previews(model_path, small_camera):
    eng, _ = make_engine(model_path, axes=["tx"], **{"radius.tx": 0.05}, imaging="paper")
    cloud = scene(small_camera)
    res = eng.process(cloud, small_camera, 1, preview_every=2)
    plan = res.plans["tx"]
    idx = [i for _, i, _ in res.previews]
    assert idx == preview_indices(plan.alphas, 2) and int(np.nonzero(plan.alphas == 0)[0][0]) in idx
    frames = render(cloud, small_camera, "tx", plan.alphas)
    for _, i, img in res.previews:
        assert img.dtype == np.uint8 and img.shape == (24, 32, 3)
        np.testing.assert_array_equal(img, np.clip(np.rint(frames[i].astype(np.float64) * 255), 0, 255).astype(np.uint8))


def test_device_fallback_and_bad_device(model_path, monkeypatch):
    logs = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # the same on a machine with a GPU
    assert resolve_device_with_fallback("cuda:0", lambda level, m: logs.append((level, m))) == "cpu"
    assert logs == [("warn", "device cuda:0 requested but CUDA is not available; falling back to cpu")]
    eng, logs = make_engine(model_path, device="cuda:1")
    assert eng.device == "cpu" and eng.device_warning == "cuda:1 unavailable, using cpu"
    with pytest.raises(PwsError, match="invalid device 'tpu'"):
        resolve_device_with_fallback("tpu")


def test_missing_model_fails_at_start(tmp_path):
    with pytest.raises(PwsError, match="model file not found: .*nope.pt"):
        FrameCertifier(config_from_params({"model_path": str(tmp_path / "nope.pt")}))


def test_sigma_unlike_the_training_sigma_is_warned_once_per_value(make_model_file, small_camera):
    path = make_model_file(input_size=(24, 32), meta={"sigma": 0.5})
    eng, logs = make_engine(path, sigma=0.25)
    cloud = scene(small_camera)
    eng.process(cloud, small_camera, 1)
    eng.process(cloud, small_camera, 2)
    warned = [m for lv, m in logs if lv == "warn" and "trained with" in m]
    assert len(warned) == 1 and "sigma 0.25 differs from the noise sigma 0.5" in warned[0]
    eng.config = eng.config.with_params({"sigma": 0.5})  # as after `ros2 param set`
    eng.process(cloud, small_camera, 3)
    assert len([m for lv, m in logs if lv == "warn" and "trained with" in m]) == 1
    plain, plain_logs = make_engine(make_model_file(input_size=(24, 32), name="plain.pt"), sigma=0.25)  # no metadata
    plain.process(cloud, small_camera, 1)
    assert not [m for lv, m in plain_logs if "trained with" in m]


def test_self_audit_every_frame_and_a_wrong_bound_withdraws_the_certificate(model_path, small_camera, monkeypatch):
    eng, logs = make_engine(model_path, axes=["tx"], **{"radius.tx": 0.02}, audit_every=1, audit_poses=4)
    cloud = scene(small_camera)
    (c,) = eng.process(cloud, small_camera, 1).certificates
    assert c.status != "error" and c.bounds["audit"]["violations"] == 0
    assert c.bounds["audit"]["poses"] >= 4 * (c.num_partitions - 1)
    # a deliberately wrong bound (half the true one) is caught and the axis turns to ERROR
    import pws_ros.core.imaging as imaging

    true_hulls = imaging.segment_hulls

    def halved(renderer, alphas, **kw):
        h = true_hulls(renderer, alphas, **kw)
        mid = (h.lo + h.hi) / 2
        return imaging.HullValues(h.alphas, mid, mid, h.constant)

    monkeypatch.setattr(imaging, "segment_hulls", halved)
    (c,) = eng.process(cloud, small_camera, 2).certificates
    assert c.status == "error" and "self-audit found" in c.reason and c.bounds["audit"]["violations"] > 0
    assert any(level == "error" and "self-audit" in m for level, m in logs)


def test_size_advice_for_models_much_larger_than_the_demo():
    """A 224x224 model on a 640x480 camera: render_factor 2 renders 448x448 and batch_size 256 holds
    154 MB of input per call: both are said; the shipped defaults (160x90) get no advice."""
    from pws_ros.bridge.sizing import size_advice
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.imaging import make_imaging

    cam = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, "cam")
    big = size_advice(make_imaging("surfel", cam, (224, 224), border=0, render_factor=2), 256)
    assert len(big) == 2 and "448x448" in big[0] and "render_factor: 1" in big[0] and "batch_size 256" in big[1]
    assert size_advice(make_imaging("surfel", cam, (224, 224), border=0, render_factor=1), 32) == []
    assert size_advice(make_imaging("surfel", cam, (90, 160), border=0, render_factor=2), 256) == []


def test_faster_batch_rule():
    """The rule of the start-up check on made-up timings: the small batch at >= BATCH_CHECK_GAIN as fast per image."""
    from pws_ros.bridge.sizing import BATCH_CHECK_GAIN, faster_batch

    assert faster_batch({4: 0.010, 32: 0.025}) == 4
    assert faster_batch({4: 0.010, 32: 0.010 * BATCH_CHECK_GAIN * 0.99}) is None
    assert faster_batch({4: 0.020, 32: 0.010}) is None and faster_batch({4: 0.01}) is None


class _SlowAtLargeBatches(torch.nn.Module):
    """Two classes; a call of B images sleeps 0.4 ms x B^2 (per image 1.6 ms at B = 4, 12.8 ms at B = 32):
    the shape of a large CPU model whose activations leave the cache at large batches."""

    def __init__(self):
        super().__init__()
        self.calls: list[int] = []

    def forward(self, x):
        import time

        self.calls.append(int(x.shape[0]))
        time.sleep(0.0004 * x.shape[0] ** 2)
        return torch.zeros(x.shape[0], 2)


def test_batch_size_check_uses_the_faster_small_batch_once_and_certificates_stay_equal(make_model_file):
    """check_batch_size times the configured batch against batch 4 once, on a large input only, and the
    engine's classifier calls use 4 from then on (said in the log); a 160x90 input (the demo's) and a
    configured batch of 4 are not timed. The certificates do not depend on the batch size: the same frame
    certified with batch 64 and with 4 gives the same certificate."""
    from pws_ros.core.model import LoadedModel

    def engine(batch_size, size):
        module = _SlowAtLargeBatches()
        model = LoadedModel(module, ["a", "b"], size, "slow.pt")
        logs: list[tuple[str, str]] = []
        cfg = config_from_params({"batch_size": batch_size, "sigma": 0.25})
        return FrameCertifier(cfg, model=model, load=False, log=lambda lvl, m: logs.append((lvl, m))), module, logs

    eng, module, logs = engine(32, (224, 224))
    spent = eng.check_batch_size((224, 224))
    said = [m for lvl, m in logs if "batch size check" in m]
    assert len(said) == 1 and "classifier calls of 4 images from now on" in said[0] and "configured batch_size 32" in said[0], logs
    assert spent > 0 and set(module.calls) == {4, 32} and eng.batch_size == 4 and eng.certify_config().batch_size == 4
    n_calls = len(module.calls)
    assert eng.check_batch_size((224, 224)) == 0.0 and len(module.calls) == n_calls and len(logs) == 1   # once
    for batch_size, size in ((32, (90, 160)), (4, (224, 224))):
        eng, module, logs = engine(batch_size, size)
        assert eng.check_batch_size(size) == 0.0 and module.calls == [] and logs == [] and eng.batch_size == batch_size

    from conftest import MeanThresholdNet

    # a threshold near the rendered frame's red mean: p_A well below 1, so the counts depend on the draws; a
    # 30x22 camera: 1980 values per image, not a multiple of 16 (torch draws normals 16 at a time on a CPU, so
    # for such sizes a whole batch drawn at once differs from the same images drawn one by one)
    cam = CameraIntrinsics(30, 22, 30.0, 30.0, 14.5, 10.5, "test_cam")
    path = make_model_file(module=MeanThresholdNet(0.75), input_size=(22, 30), name="near.pt")
    cloud = scene(cam)
    certs = []
    for bs in (64, 4, 5):
        eng, _ = make_engine(path, batch_size=bs)
        certs.append(eng.process(cloud, cam, 3).certificates)
    assert any(0.05 < p < 0.99 for c in certs[0] for p in np.atleast_1d(c.p_a_lower))   # not all samples agree
    for other in certs[1:]:
        for a, b in zip(certs[0], other):
            assert a.status != "error" and (a.status, a.label, a.radius, a.p_a_lower, a.n, a.classifier_calls) == \
                   (b.status, b.label, b.radius, b.p_a_lower, b.n, b.classifier_calls)


def _without_timings(certs) -> list[str]:
    """Every field of the certificates but what was timed (``timings``, any ``*seconds`` entry)."""
    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k != "timings" and not k.endswith("seconds")}
        return [strip(v) for v in x] if isinstance(x, list) else x
    return [json.dumps(strip(c.to_dict()), sort_keys=True, default=str) for c in certs]


@pytest.mark.parametrize("extra", [{}, {"imaging": "paper"}, {"method": "cms", "n0": 8, "n": 16}], ids=["surfel", "paper", "cms"])
def test_axes_at_the_same_time_give_the_frame_of_one_after_another(model_path, small_camera, extra):
    """axis_threads: the certificates (every field but the timings, the self-audits included), plans and previews of
    a frame whose axes run at the same time are those of one axis after another, in config order."""
    cloud = scene(small_camera)
    params = dict(axes=["tz", "ry", "tx"], audit_every=1, audit_poses=3, **{"radius.tx": 0.02}, **extra)
    one, _ = make_engine(model_path, axis_threads=1, **params)
    many, _ = make_engine(model_path, axis_threads=3, **params)
    assert one.axis_workers() == 1 and many.axis_workers() == 3
    a = one.process(cloud, small_camera, 7, preview_every=3)
    b = many.process(cloud, small_camera, 7, preview_every=3)
    assert [c.axis for c in b.certificates] == ["tz", "ry", "tx"]
    assert all(c.status != "error" for c in b.certificates), [c.reason for c in b.certificates]
    assert all(b.certificates[k].bounds["audit"]["violations"] == 0 for k, ax in enumerate(["tz", "ry", "tx"]) if ax in b.plans)
    assert _without_timings(a.certificates) == _without_timings(b.certificates)
    assert {k: p.alphas.tolist() for k, p in a.plans.items()} == {k: p.alphas.tolist() for k, p in b.plans.items()}
    assert [(ax, i) for ax, i, _ in a.previews] == [(ax, i) for ax, i, _ in b.previews] and (a.previews or not a.plans)
    for (_, _, x), (_, _, y) in zip(a.previews, b.previews):
        np.testing.assert_array_equal(x, y)
    assert set(b.compute_ms) == {"tz", "ry", "tx"} and b.timings["total"] > 0


def test_axis_threads_run_the_axes_at_the_same_time(model_path, small_camera, monkeypatch):
    import threading

    eng, _ = make_engine(model_path, axes=["tz", "ry"], axis_threads=2)
    meet = threading.Barrier(2, timeout=20)   # one axis after another never meets: BrokenBarrierError
    certify_axis = eng.certify_axis

    def meeting(*args, **kwargs):
        meet.wait()
        return certify_axis(*args, **kwargs)

    monkeypatch.setattr(eng, "certify_axis", meeting)
    import pws_ros.core.surfel as surfel

    binned, bin_ = [], surfel._bin
    monkeypatch.setattr(surfel, "_bin", lambda *a: binned.append(1) or bin_(*a))
    # a camera of 4x the model's input: its pixels binned 2x2 (imaging.decimate 2), once for both axes, the second
    # axis waiting for the first's bins
    big = CameraIntrinsics(width=128, height=96, fx=120.0, fy=120.0, cx=63.5, cy=47.5, frame_id="test_cam")
    res = eng.process(scene(big), big, 1)
    assert res.imaging.decimate == 2 and len(binned) == 1
    assert [c.axis for c in res.certificates] == ["tz", "ry"] and all(c.status != "error" for c in res.certificates)
    # shutting down: every axis not begun is an ERROR that says so
    stopped = eng.process(scene(small_camera), small_camera, 2, should_stop=lambda: True)
    assert [c.status for c in stopped.certificates] == ["error", "error"]
    assert all(c.reason == "shutting down" for c in stopped.certificates)


def test_how_many_axes_run_at_once(model_path, monkeypatch):
    auto, _ = make_engine(model_path, axes=["tz", "ry", "tx"])
    assert auto.config.axis_threads == 0
    for threads, expected in ((1, 1), (2, 2), (8, 3)):   # one per axis, at most torch's intra-op threads
        monkeypatch.setattr(torch, "get_num_threads", lambda t=threads: t)
        assert auto.axis_workers() == expected
    assert auto.axis_workers(budgeted=True) == 1          # a time budget shares the frame's time in turn
    two, _ = make_engine(model_path, axes=["tz", "ry", "tx"], axis_threads=2)
    assert two.axis_workers() == 2
    single, _ = make_engine(model_path, axes=["tz"], axis_threads=4)
    assert single.axis_workers() == 1


def test_a_signal_leaves_a_frame_whose_axes_run_at_once_without_waiting_for_them(model_path, small_camera, monkeypatch):
    """``pws replay`` stops on SIGINT / SIGTERM by an exception raised in the main thread: with the axes in threads of
    their own it is raised at once (an interruptible wait), not when the axes end, and they never hold up an exit."""
    import signal
    import threading
    import time

    class Stop(Exception):
        pass

    eng, _ = make_engine(model_path, axes=["tz", "ry"], axis_threads=2)
    release = threading.Event()

    def long_axis(cloud, imaging, axis, *args, **kwargs):
        release.wait(60)   # an axis of a large model
        return eng.error_for(axis, "released")

    monkeypatch.setattr(eng, "certify_axis", long_axis)

    def stop(signum, frame):
        raise Stop()

    previous = signal.signal(signal.SIGUSR1, stop)
    main = threading.main_thread().ident
    timer = threading.Timer(0.5, lambda: signal.pthread_kill(main, signal.SIGUSR1))
    try:
        t0 = time.perf_counter()
        timer.start()
        with pytest.raises(Stop):
            eng.process(scene(small_camera), small_camera, 1)
        assert time.perf_counter() - t0 < 20   # not the axes' 60 s
        assert all(t.daemon for t in threading.enumerate() if t.name.startswith("pws-axis"))
    finally:
        signal.signal(signal.SIGUSR1, previous)
        release.set()
        timer.cancel()


def test_at_once_keeps_the_order_and_raises_what_an_item_raised():
    """pws_ros.bridge.axis_threads.at_once: results in order whatever thread computed them, the first error raised."""
    import threading

    from pws_ros.bridge.axis_threads import at_once

    seen = []

    def square(k):
        seen.append(threading.current_thread().name)
        return k * k

    assert at_once(square, 5, 2) == [0, 1, 4, 9, 16]
    assert len(set(seen)) <= 2 and all(name.startswith("pws-axis") for name in seen)

    def third_fails(k):
        if k == 2:
            raise ValueError("item 2")
        return k

    with pytest.raises(ValueError, match="item 2"):
        at_once(third_fails, 4, 3)

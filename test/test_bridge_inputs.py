"""The input front end of cloud_listener/pipeline (pws_ros.bridge.inputs), with rosbags messages."""
from __future__ import annotations

import numpy as np
import pytest

from pws_ros.bridge import msgbuild
from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.inputs import InputAssembler, convert
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from pws_ros.core.errors import PwsError

T = msgbuild.rosbags_types()
CAM = CameraIntrinsics(8, 6, 10.0, 10.0, 3.5, 2.5, "cam")
MS = 1_000_000


def depth_msg(stamp, frame="cam", w=8, h=6):
    mm = np.full((h, w), 1500, np.uint16)
    mm[0, 0] = 0
    return msgbuild.image_from_numpy(msgbuild.make_header(T, stamp, frame), mm, T)


def color_msg(stamp, frame="cam", w=8, h=6):
    return msgbuild.image_from_numpy(msgbuild.make_header(T, stamp, frame), np.full((h, w, 3), 200, np.uint8), T, encoding="bgr8")


def info_msg(stamp=0, cam=CAM):
    return msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, stamp, cam.frame_id), cam, T)


def points_msg(stamp, organized=True):
    rows, cols = np.mgrid[0:6, 0:8]
    z = np.full((6, 8), 2.0)
    pts = np.stack([(cols - CAM.cx) * z / CAM.fx, (rows - CAM.cy) * z / CAM.fy, z], -1).reshape(-1, 3)
    cloud = Cloud(pts, np.full((48, 3), 0.25))
    return msgbuild.cloud_to_pointcloud2(msgbuild.make_header(T, stamp, "cam"), cloud, T, organized_shape=(6, 8) if organized else None)


def test_rgbd_frames_are_matched_and_converted():
    cfg = config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.005})
    asm = InputAssembler(cfg)
    assert asm.on_info(info_msg()) is None
    assert asm.on_depth(depth_msg(100 * MS)) is None
    raw = asm.on_color(color_msg(103 * MS))
    assert raw is not None and raw.source == "rgbd" and raw.stamp_ns == 103 * MS and raw.header.frame_id == "cam"
    frame = convert(raw, cfg)
    # depth_fill: row (the default): the one pixel without depth is filled, every pixel is a point
    assert len(frame.cloud) == 48 and frame.cloud.filled == 1 and frame.intrinsics == CAM and frame.has_color
    np.testing.assert_allclose(frame.cloud.colors, 200 / 255, atol=1e-6)
    off = convert(raw, config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.005, "depth_fill": "off"}))
    assert len(off.cloud) == 47 and off.cloud.filled == 0
    # beyond the tolerance: no frame at once (within sync_max_skew_s it waits to be settled)
    asm.on_depth(depth_msg(200 * MS))
    assert asm.on_color(color_msg(210 * MS)) is None


def test_unsynced_pair_is_settled_by_the_end_of_the_input_and_says_its_skew():
    cfg = config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.005, "sync_max_skew_s": 0.2})
    asm = InputAssembler(cfg)
    asm.on_info(info_msg())
    assert asm.on_color(color_msg(100 * MS)) is None
    assert asm.on_depth(depth_msg(160 * MS)) is None          # a later colour frame could be nearer
    raw = asm.flush()                                         # the end of a recording: none can come
    assert raw is not None and raw.stamp_ns == 100 * MS and raw.skew_ns == 60 * MS
    warn = asm.skew_warning(raw)
    assert "60.0 ms apart" in warn and "sync_max_skew_s" in warn
    assert asm.flush() is None
    # within the tolerance: no warning; a new config at run time (ros2 param set) reaches the matcher
    asm.on_depth(depth_msg(300 * MS))
    raw = asm.on_color(color_msg(302 * MS))
    assert raw is not None and raw.skew_ns == 2 * MS and asm.skew_warning(raw) == ""
    asm.reconfigure(config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.005, "sync_max_skew_s": 0.0}))
    assert asm.matcher.max_skew_ns == 0 and asm.matcher.tolerance_ns == 5 * MS
    asm.on_color(color_msg(400 * MS))
    asm.on_depth(depth_msg(460 * MS))
    assert asm.flush() is None                                # 60 ms apart is refused now


def test_rgbd_pair_waits_for_the_first_camera_info():
    """Drivers often start CameraInfo a little after the images: the newest matched pair is held
    (an older held one is replaced and counted as dropped) and completed by the first CameraInfo."""
    asm = InputAssembler(config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.0}))
    asm.on_depth(depth_msg(1))
    assert asm.on_color(color_msg(1)) is None and asm.waiting_for_info and asm.dropped == 0
    asm.on_depth(depth_msg(2))
    assert asm.on_color(color_msg(2)) is None and asm.dropped == 1  # the pair of stamp 1 is replaced
    raw = asm.on_info(info_msg())
    assert raw is not None and raw.stamp_ns == 2 and not asm.waiting_for_info and asm.frames == 1
    assert len(convert(raw, asm.config).cloud) == 48   # the pixel without depth filled (depth_fill: row)
    assert asm.on_info(info_msg()) is None  # nothing held any more
    asm.on_depth(depth_msg(3))
    raw = asm.on_color(color_msg(3))  # from now on the latest CameraInfo completes each pair at once
    assert raw is not None and raw.stamp_ns == 3 and raw.messages["info"] is not None


def test_unregistered_pair_waits_for_the_depth_camera_info():
    """Depth registered with an extrinsic needs the depth camera's CameraInfo too: a pair matched before
    it arrives is held and completed by it (it used to be converted at once and refused for good)."""
    from pws_ros.core.registration import Extrinsic

    asm = InputAssembler(config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.0,
                                             "depth_camera_info_topic": "/camera/depth/camera_info"}))
    asm.set_extrinsic(Extrinsic(np.eye(3), [0.0, 0.0, 0.0]))
    assert asm.on_info(info_msg()) is None
    asm.on_depth(depth_msg(1, frame="depth"))
    assert asm.on_color(color_msg(1)) is None and asm.waiting_for_info
    assert "depth camera's CameraInfo (/camera/depth/camera_info)" in asm.waiting_for()
    raw = asm.on_depth_info(info_msg(cam=CameraIntrinsics(8, 6, 10.0, 10.0, 3.5, 2.5, "depth")))
    assert raw is not None and raw.stamp_ns == 1 and raw.messages["depth_info"] is not None and not asm.waiting_for_info
    # without a configured depth CameraInfo topic nothing waits for one
    plain = InputAssembler(config_from_params({"input_mode": "rgbd", "sync_tolerance_s": 0.0, "depth_camera_info_topic": ""}))
    plain.set_extrinsic(Extrinsic(np.eye(3), [0.0, 0.0, 0.0]))
    plain.on_info(info_msg())
    plain.on_depth(depth_msg(1, frame="depth"))
    assert plain.on_color(color_msg(1)) is not None


def test_stamp_synced_camera_info():
    asm = InputAssembler(config_from_params({"input_mode": "rgbd", "camera_info_sync": "stamp", "sync_tolerance_s": 0.0}))
    asm.on_depth(depth_msg(5))
    assert asm.on_color(color_msg(5)) is None  # waits for the CameraInfo of that stamp
    raw = asm.on_info(info_msg(5))
    assert raw is not None and raw.messages["info"].header.stamp.nanosec == 5


def test_unregistered_input_fails_in_convert_with_the_hint():
    cfg = config_from_params({"input_mode": "rgbd", "depth_camera_info_topic": "depth/camera_info"})
    asm = InputAssembler(cfg)
    asm.on_info(info_msg())
    asm.on_depth_info(info_msg(cam=CameraIntrinsics(8, 6, 7.0, 7.0, 3.5, 2.5, "cam")))
    asm.on_depth(depth_msg(1))
    raw = asm.on_color(color_msg(1))
    with pytest.raises(PwsError, match="not registered.*aligned_depth_to_color"):
        convert(raw, cfg)


def test_pointcloud2_input_with_and_without_info():
    cfg = config_from_params({"input_mode": "pointcloud2"})
    asm = InputAssembler(cfg)
    frame = convert(asm.on_points(points_msg(1)), cfg)  # organized: intrinsics from the grid
    assert frame.intrinsics.fx == pytest.approx(10.0) and frame.intrinsics.cx == pytest.approx(3.5)
    asm.on_info(info_msg(cam=CAM))
    raw = asm.on_points(points_msg(2, organized=False))
    frame = convert(raw, cfg)
    assert frame.intrinsics == CAM and len(frame.cloud) == 48
    asm2 = InputAssembler(cfg)
    with pytest.raises(PwsError, match="unorganized PointCloud2"):
        convert(asm2.on_points(points_msg(3, organized=False)), cfg)


def test_camera_info_file_fallback(tmp_path):
    path = tmp_path / "cam.yaml"
    CAM.to_yaml(path)
    cfg = config_from_params({"input_mode": "pointcloud2", "camera_info_file": str(path)})
    asm = InputAssembler(cfg)
    frame = convert(asm.on_points(points_msg(1, organized=False)), cfg, asm.fallback)
    assert (frame.intrinsics.fx, frame.intrinsics.width) == (10.0, 8)


def test_auto_mode_locks_onto_the_first_source():
    asm = InputAssembler(config_from_params({"input_mode": "auto"}))
    asm.on_info(info_msg())
    assert asm.on_points(points_msg(1)).source == "pointcloud2"
    assert asm.on_depth(depth_msg(2)) is None and asm.on_color(color_msg(2)) is None
    assert asm.ignored == 2 and asm.locked_source == "pointcloud2"


def test_auto_mode_a_frame_that_fails_to_convert_releases_the_source():
    """A malformed PointCloud2 first (it completes a frame, then fails in convert): the source is released
    (the nodes report the failure), so the RGB-D camera's frames that follow are taken; once a frame
    converts, its source is kept for good and the other is ignored again."""
    cfg = config_from_params({"input_mode": "auto"})
    asm = InputAssembler(cfg)
    asm.on_info(info_msg())
    bad = points_msg(1)
    bad.point_step = 0
    raw = asm.on_points(bad)
    assert raw.source == "pointcloud2" and asm.locked_source == "pointcloud2"
    with pytest.raises(PwsError):
        convert(raw, cfg, asm.fallback)
    asm.conversion_done(raw.source, False)
    assert asm.locked_source is None
    assert asm.on_depth(depth_msg(2)) is None
    good = asm.on_color(color_msg(2))
    assert good is not None and good.source == "rgbd" and asm.locked_source == "rgbd"
    convert(good, cfg, asm.fallback)
    asm.conversion_done(good.source, True)
    assert asm.on_points(points_msg(3)) is None and asm.ignored == 1
    asm.conversion_done("rgbd", False)            # a later bad RGB-D frame: the lock holds
    assert asm.locked_source == "rgbd" and asm.on_points(points_msg(4)) is None
    fixed = InputAssembler(config_from_params({"input_mode": "rgbd"}))
    fixed.conversion_done("rgbd", False)           # a fixed mode is never released
    assert fixed.locked_source == "rgbd"


def test_min_period_skips_frames():
    asm = InputAssembler(config_from_params({"input_mode": "pointcloud2", "min_period_s": 0.5}))
    got = [asm.on_points(points_msg(t * 100 * MS)) is not None for t in range(12)]
    assert got == [True, False, False, False, False, True, False, False, False, False, True, False]
    assert asm.skipped == 9 and asm.frames == 3


def test_unmatched_inputs_are_counted_and_bounded():
    asm = InputAssembler(config_from_params({"input_mode": "rgbd", "sync_queue_size": 2, "sync_tolerance_s": 0.0}))
    asm.on_info(info_msg())
    for i in range(5):
        asm.on_depth(depth_msg(i))
    assert asm.dropped == 3
    assert asm.on_color(color_msg(4)) is not None and asm.dropped == 4  # depth 3 can never match now


def test_max_depth_makes_far_depth_a_hole_in_depth_images_and_clouds():
    """max_depth_m: a saturated uint16 depth (65535 mm) or any depth beyond the limit is a hole like 0: filled
    from the farther valid neighbour in its row (depth_fill: row), dropped with depth_fill: off; the same
    for an organized PointCloud2's z. 0 (the default) keeps it as a measured far surface."""
    mm = np.full((6, 8), 1500, np.uint16)
    mm[:, 5] = 2500
    mm[2, 2:4] = 65535                       # saturated: two pixels between 1.5 m neighbours
    mm[4, 6] = 65535                         # between 2.5 m (left, column 5) and 1.5 m (right, column 7)
    depth = msgbuild.image_from_numpy(msgbuild.make_header(T, 5 * MS, "cam"), mm, T)
    raw_msgs = {"depth": depth, "color": color_msg(5 * MS), "info": info_msg()}
    from pws_ros.bridge.inputs import RawFrame

    raw = RawFrame("rgbd", 5 * MS, depth.header, raw_msgs)
    keep = convert(raw, config_from_params({"input_mode": "rgbd"}))
    assert len(keep.cloud) == 48 and keep.cloud.filled == 0 and np.isclose(keep.cloud.points[:, 2].max(), 65.535)
    cut = convert(raw, config_from_params({"input_mode": "rgbd", "max_depth_m": 10.0}))
    z = cut.cloud.points[:, 2].reshape(6, 8)            # every pixel is a point, row-major
    assert cut.cloud.filled == 3
    # brute force: each hole takes the larger of the nearest valid depths left and right in its row
    want = mm.astype(np.float64) / 1000.0
    for r, c in ((2, 2), (2, 3), (4, 6)):
        left = [d for j, d in enumerate(want[r]) if j < c and mm[r, j] != 65535]
        right = [d for j, d in enumerate(want[r]) if j > c and mm[r, j] != 65535]
        assert np.isclose(z[r, c], max(left[-1], right[0]), atol=1e-6)
    off = convert(raw, config_from_params({"input_mode": "rgbd", "max_depth_m": 10.0, "depth_fill": "off"}))
    assert len(off.cloud) == 45 and off.cloud.points[:, 2].max() < 10.0
    # an organized cloud: the z beyond the limit is invalid, then filled through its pixel centre
    rows, cols = np.mgrid[0:6, 0:8]
    zc = mm.astype(np.float64) / 1000.0
    pts = np.stack([(cols - CAM.cx) * zc / CAM.fx, (rows - CAM.cy) * zc / CAM.fy, zc], -1).reshape(-1, 3)
    pc = msgbuild.cloud_to_pointcloud2(msgbuild.make_header(T, 6 * MS, "cam"), Cloud(pts, np.full((48, 3), 0.25)), T,
                                       organized_shape=(6, 8))
    raw_pc = RawFrame("pointcloud2", 6 * MS, pc.header, {"points": pc, "info": info_msg()})
    far = convert(raw_pc, config_from_params({"input_mode": "pointcloud2"}))
    near = convert(raw_pc, config_from_params({"input_mode": "pointcloud2", "max_depth_m": 10.0}))
    assert far.cloud.filled == 0 and np.isclose(far.cloud.points[:, 2].max(), 65.535)
    assert near.cloud.filled == 3 and len(near.cloud) == 48
    np.testing.assert_allclose(np.sort(near.cloud.points[:, 2]), np.sort(z.reshape(-1)), atol=1e-6)
    with pytest.raises(PwsError, match="max_depth_m"):
        config_from_params({"max_depth_m": -1.0})

"""Camera intrinsics (camera_calibration YAML, CameraInfo messages, resampling) and coloured clouds
(npz round trip, validation, the one-frame cloud of an RGB-D image)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud, cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import project
from pws_ros.core.render import render

CALIBRATION_YAML = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [615.5, 0.0, 321.25, 0.0, 616.75, 238.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.01, -0.02, 0.0, 0.0, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [615.5, 0.0, 321.25, 0.0, 0.0, 616.75, 238.5, 0.0, 0.0, 0.0, 1.0, 0.0]
"""


# ---- intrinsics --------------------------------------------------------------------------------

def test_from_calibration_yaml(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(CALIBRATION_YAML)
    cam = CameraIntrinsics.from_yaml(path)
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (615.5, 616.75, 321.25, 238.5)
    assert cam.frame_id == "narrow_stereo"
    assert cam.shape == (480, 640)
    np.testing.assert_array_equal(cam.K, [[615.5, 0, 321.25], [0, 616.75, 238.5], [0, 0, 1]])
    # to_yaml writes the same layout back
    out = tmp_path / "out.yaml"
    cam.to_yaml(out)
    assert CameraIntrinsics.from_yaml(out) == cam
    data = yaml.safe_load(out.read_text())
    assert data["camera_matrix"]["data"] == [615.5, 0.0, 321.25, 0.0, 616.75, 238.5, 0.0, 0.0, 1.0]
    assert data["image_width"] == 640 and data["image_height"] == 480


def test_missing_or_malformed_camera_file_is_one_line_error(tmp_path):
    with pytest.raises(PwsError, match=r"^camera file not found: .*nope\.yaml$"):
        CameraIntrinsics.from_yaml(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("image_width: [640\n")
    with pytest.raises(PwsError, match=r"^camera file .*bad\.yaml is not valid YAML: [^\n]*$"):
        CameraIntrinsics.from_yaml(bad)


def test_from_flat_and_k_dicts():
    flat = CameraIntrinsics.from_dict({"width": 32, "height": 24, "fx": 30, "fy": 31, "cx": 15.5, "cy": 11.5})
    assert (flat.width, flat.height, flat.fx, flat.fy, flat.cx, flat.cy) == (32, 24, 30.0, 31.0, 15.5, 11.5)
    k = CameraIntrinsics.from_dict({"width": 32, "height": 24, "k": [30, 0, 15.5, 0, 31, 11.5, 0, 0, 1], "frame_id": "cam"})
    assert k == CameraIntrinsics(32, 24, 30.0, 31.0, 15.5, 11.5, "cam")


@pytest.mark.parametrize("text", [
    "image_width: 640\n",                                                  # no camera matrix / size
    "image_width: 640\nimage_height: 480\ncamera_matrix:\n  data: [1, 0, 0]\n",   # 3 numbers, not 9
    "image_height: 480\ncamera_matrix:\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n",  # no width
    "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n",   # no data
    "image_width: abc\nimage_height: 480\ncamera_matrix:\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n",
    "image_width: 640\nimage_height: 480\ncamera_matrix:\n  data: [0, 0, 320, 0, 500, 240, 0, 0, 1]\n",  # fx = 0
    "image_width: 0\nimage_height: 480\ncamera_matrix:\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n",   # no pixels
    "image_width: 640\nimage_height: 480\ncamera_matrix:\n  data: [500, 0, .nan, 0, 500, 240, 0, 0, 1]\n",
    "- just\n- a list\n",
    "camera_matrix: [unclosed\n",                                          # not YAML
    "",                                                                    # empty file
])
def test_bad_yaml(tmp_path, text):
    path = tmp_path / "camera.yaml"
    path.write_text(text)
    with pytest.raises(PwsError) as err:
        CameraIntrinsics.from_yaml(path)
    assert "\n" not in str(err.value)


def test_missing_yaml_file(tmp_path):
    with pytest.raises(PwsError, match="not found"):
        CameraIntrinsics.from_yaml(tmp_path / "nope.yaml")


def _camera_info(k, width=64, height=48, frame_id="camera_color_optical_frame"):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id=frame_id)
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T["sensor_msgs/msg/CameraInfo"](
        header=header, height=height, width=width, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.asarray(k, dtype=np.float64), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


def test_from_rosbags_camera_info():
    msg = _camera_info([60.0, 0, 31.5, 0, 61.0, 23.25, 0, 0, 1])
    cam = CameraIntrinsics.from_camera_info(msg)
    assert cam == CameraIntrinsics(64, 48, 60.0, 61.0, 31.5, 23.25, "camera_color_optical_frame")
    # an uncalibrated camera publishes k = 0
    with pytest.raises(PwsError, match="calibrated"):
        CameraIntrinsics.from_camera_info(_camera_info(np.zeros(9)))
    with pytest.raises(PwsError):
        CameraIntrinsics.from_camera_info(_camera_info([60.0, 0, 31.5, 0, 61.0, 23.25, 0, 0]))
    with pytest.raises(PwsError):
        CameraIntrinsics.from_camera_info(_camera_info([60.0, 0, 31.5, 0, 61.0, 23.25, 0, 0, 1], width=0))


@pytest.mark.parametrize("kw", [dict(fx=0.0), dict(fy=-1.0), dict(cx=float("nan")), dict(cy=float("inf")),
                                dict(width=0), dict(height=-3), dict(fx="500")])
def test_bad_intrinsics(kw):
    args = dict(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    args.update(kw)
    with pytest.raises(PwsError):
        CameraIntrinsics(**args)


@settings(max_examples=40, deadline=None)
@given(w=st.integers(4, 1280), h=st.integers(4, 720), nw=st.integers(1, 400), nh=st.integers(1, 300),
       fx=st.floats(50, 2000), fy=st.floats(50, 2000), ox=st.floats(-20, 20), oy=st.floats(-20, 20))
def test_scaled_maps_pixel_centres_to_centres(w, h, nw, nh, fx, fy, ox, oy):
    cam = CameraIntrinsics(w, h, fx, fy, (w - 1) / 2 + ox, (h - 1) / 2 + oy)
    s = cam.scaled(nw, nh)
    assert (s.width, s.height) == (nw, nh)
    sx, sy = nw / w, nh / h
    assert s.fx == pytest.approx(fx * sx) and s.fy == pytest.approx(fy * sy)
    # the same ray hits proportionally the same place: pixel-edge coordinates scale linearly, so the
    # centre of pixel c (edge coordinate c + 1/2) maps to edge coordinate (c + 1/2) * s
    P = np.array([[0.13, -0.07, 1.3], [-0.4, 0.2, 2.0], [0.0, 0.0, 1.0]])
    u, v, _ = project(P, cam, "tx", 0.0)
    us, vs, _ = project(P, s, "tx", 0.0)
    np.testing.assert_allclose(us, u * sx, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(vs, v * sy, rtol=1e-9, atol=1e-9)
    # the image corners stay the image corners: edge coordinates 0 and W map to 0 and nw
    assert (0 + cam.cx + 0.5) * sx - 0.5 == pytest.approx(s.cx)
    # a centred principal point stays centred
    c = CameraIntrinsics(w, h, fx, fy, (w - 1) / 2, (h - 1) / 2).scaled(nw, nh)
    assert c.cx == pytest.approx((nw - 1) / 2) and c.cy == pytest.approx((nh - 1) / 2)


def test_scaled_examples_and_bad_size():
    cam = CameraIntrinsics(1280, 720, 900.0, 900.0, 639.5, 359.5)
    s = cam.scaled(160, 90)  # the paper's /8
    assert (s.fx, s.fy, s.cx, s.cy) == (112.5, 112.5, 79.5, 44.5)
    with pytest.raises(PwsError):
        cam.scaled(0, 90)


# ---- clouds ------------------------------------------------------------------------------------

def test_cloud_npz_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    cols = rng.random((50, 3)).astype(np.float32)
    c = Cloud(pts, cols)
    assert len(c) == 50 and c.points.dtype == np.float64 and c.colors.dtype == np.float32
    c.save(tmp_path / "c.npz")
    back = Cloud.load(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.colors, cols)
    # uint8 colours are scaled to [0, 1] (and survive a round trip through a file)
    u8 = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    np.savez(tmp_path / "u8.npz", points=pts.astype(np.float32), colors=u8)
    c8 = Cloud.load(tmp_path / "u8.npz")
    assert c8.colors.dtype == np.float32 and c8.points.dtype == np.float64
    np.testing.assert_array_equal(c8.colors, u8.astype(np.float32) / np.float32(255))
    assert c8.colors.max() <= 1.0
    np.testing.assert_array_equal(Cloud(pts, np.full((50, 3), 255, np.uint8)).colors, 1.0)


@pytest.mark.parametrize("points,colors", [
    (np.array([[0.0, 0.0, np.nan]]), np.ones((1, 3))),
    (np.array([[0.0, np.inf, 1.0]]), np.ones((1, 3))),
    (np.zeros((4, 2)), np.ones((4, 3))),
    (np.zeros(3), np.ones((1, 3))),
    (np.zeros((4, 3)), np.ones((3, 3))),
    (np.zeros((4, 3)), np.ones((4, 4))),
    (np.zeros((2, 3)), np.array([[0.5, 0.5, 1.5], [0, 0, 0]])),       # float colour out of [0, 1]
    (np.zeros((2, 3)), np.array([[0.5, 0.5, -0.1], [0, 0, 0]])),
    (np.zeros((2, 3)), np.array([[0.5, np.nan, 0.1], [0, 0, 0]])),
    (np.array([["a", "b", "c"]]), np.ones((1, 3))),
])
def test_bad_clouds(points, colors):
    with pytest.raises(PwsError):
        Cloud(points, colors)


def test_bad_cloud_files(tmp_path):
    with pytest.raises(PwsError, match="not found"):
        Cloud.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "nocol.npz", points=np.zeros((3, 3)))
    with pytest.raises(PwsError, match="colors"):
        Cloud.load(tmp_path / "nocol.npz")
    np.savez(tmp_path / "nan.npz", points=np.array([[0, 0, np.nan]]), colors=np.ones((1, 3)))
    with pytest.raises(PwsError):
        Cloud.load(tmp_path / "nan.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(PwsError):
        Cloud.load(tmp_path / "junk.npz")


def test_empty_cloud_and_require_nonempty():
    empty = Cloud(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0
    with pytest.raises(PwsError, match="empty"):
        empty.require_nonempty()
    with pytest.raises(PwsError, match="front"):
        Cloud(np.array([[0.0, 0.0, -1.0]]), np.ones((1, 3))).require_nonempty()


CAM = CameraIntrinsics(width=20, height=15, fx=18.0, fy=17.0, cx=9.25, cy=7.0)


def test_cloud_from_rgbd_drops_invalid_depth_and_uses_pixel_centres():
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.3, 5.0, (15, 20))
    depth[0, 0] = 0.0
    depth[1, 2] = np.nan
    depth[2, 3] = np.inf
    depth[3, 4] = -np.inf
    depth[4, 5] = -1.0
    rgb = rng.integers(0, 256, (15, 20, 3), dtype=np.uint8)
    cloud = cloud_from_rgbd(depth, rgb, CAM)
    valid = np.isfinite(depth) & (depth > 0)
    assert len(cloud) == valid.sum() == 15 * 20 - 5
    rows, cols = np.nonzero(valid)  # row-major order
    np.testing.assert_allclose(cloud.points[:, 2], depth[rows, cols])
    np.testing.assert_array_equal(cloud.colors, rgb[rows, cols].astype(np.float32) / np.float32(255))
    # back-projection through the pixel centre: (col - cx) Z / fx, (row - cy) Z / fy
    np.testing.assert_allclose(cloud.points[:, 0], (cols - CAM.cx) * depth[rows, cols] / CAM.fx, rtol=1e-12)
    np.testing.assert_allclose(cloud.points[:, 1], (rows - CAM.cy) * depth[rows, cols] / CAM.fy, rtol=1e-12)
    # and the projection puts each point in the middle of its pixel
    u, v, z = project(cloud.points, CAM, "tx", 0.0)
    np.testing.assert_allclose(u, cols + 0.5, atol=1e-9)
    np.testing.assert_allclose(v, rows + 0.5, atol=1e-9)
    # rendering at alpha = 0 gives the image back, holes show the background
    frame = render(cloud, CAM, "tx", [0.0], background=0.25)[0]
    expected = np.where(valid[..., None], rgb.astype(np.float32) / np.float32(255), np.float32(0.25))
    np.testing.assert_array_equal(frame, expected)


def test_cloud_from_rgbd_float_colours_and_bad_shapes():
    depth = np.ones((15, 20))
    rgb = np.full((15, 20, 3), 0.5, np.float32)
    c = cloud_from_rgbd(depth, rgb, CAM)
    assert len(c) == 300 and np.all(c.colors == 0.5)
    with pytest.raises(PwsError):
        cloud_from_rgbd(np.ones((15, 21)), np.zeros((15, 21, 3), np.uint8), CAM)  # not the camera's size
    with pytest.raises(PwsError):
        cloud_from_rgbd(np.ones((15, 20)), np.zeros((15, 19, 3), np.uint8), CAM)  # colour and depth differ
    with pytest.raises(PwsError):
        cloud_from_rgbd(np.ones((15, 20)), np.zeros((15, 20), np.uint8), CAM)  # not 3 channels
    with pytest.raises(PwsError):
        cloud_from_rgbd(np.ones((15, 20, 1)), np.zeros((15, 20, 3), np.uint8), CAM)
    with pytest.raises(PwsError):
        cloud_from_rgbd(np.ones((15, 20)), np.full((15, 20, 3), 2.0), CAM)  # float colours above 1
    # all depth invalid: an empty cloud that certification refuses
    empty = cloud_from_rgbd(np.zeros((15, 20)), np.zeros((15, 20, 3), np.uint8), CAM)
    assert len(empty) == 0
    with pytest.raises(PwsError):
        empty.require_nonempty()


def test_scaled_camera_and_cloud_agree():
    """A cloud made at full resolution renders, with the scaled camera, to the box-downsampled image
    when every 2x2 block has one colour and one depth (centres map to centres)."""
    big = CameraIntrinsics(width=40, height=30, fx=36.0, fy=36.0, cx=19.5, cy=14.5)
    small = big.scaled(20, 15)
    rng = np.random.default_rng(1)
    block = rng.integers(0, 256, (15, 20, 3), dtype=np.uint8)
    rgb = np.repeat(np.repeat(block, 2, axis=0), 2, axis=1)
    depth = np.ones((30, 40))
    cloud = cloud_from_rgbd(depth, rgb, big)
    frame = render(cloud, small, "tx", [0.0])[0]
    np.testing.assert_array_equal(frame, block.astype(np.float32) / np.float32(255))
    assert math.isclose(small.cx, 9.5) and math.isclose(small.cy, 7.0)


def test_a_calibration_yaml_without_its_matrix_names_the_matrix(tmp_path):
    """camera_calibration's format without camera_matrix: the message names that field, not the flat format's
    'width' (which a camera_calibration user never wrote)."""
    path = tmp_path / "camera.yaml"
    path.write_text("image_width: 640\nimage_height: 480\n")
    with pytest.raises(PwsError, match="missing field 'camera_matrix'"):
        CameraIntrinsics.from_yaml(path)

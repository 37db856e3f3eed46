"""Real recordings from other people's drivers (../shared/data, read with rosbags.highlevel.AnyReader):
the Kinect organized PointCloud2 converts; the RealSense depth + colour (not registered) is refused."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from pws_ros.bridge import cloudconv, msgbuild, msgconv
from pws_ros.core.errors import PwsError


def read_all(folder: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([folder]) as reader:
        for conn, _t, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


@pytest.fixture
def kinect():
    return read_all(shared_path("kinect_organized_cloud"))["/camera/depth_registered/points"][0]


@pytest.fixture
def realsense():
    return read_all(shared_path("realsense_single_rgbd"))


def test_kinect_organized_cloud(kinect):
    conv = cloudconv.cloud_from_pointcloud2(kinect)
    cloud, shape = conv
    assert shape == (480, 640) and conv.has_color
    n = kinect.width * kinect.height
    assert 0.70 < conv.valid.mean() < 0.82  # ~76 % finite
    assert len(cloud) == int(conv.valid.sum())
    z = cloud.points[:, 2]
    assert 0.69 < z.min() and z.max() < 1.66
    # brute force check of a few points straight from the bytes (x, y, z float32 at 0/4/8, rgb at 16)
    data = np.asarray(kinect.data, dtype=np.uint8)
    idx = np.nonzero(conv.valid)[0][:: max(1, int(conv.valid.sum()) // 50)]
    k = np.cumsum(conv.valid) - 1
    for i in idx:
        rec = data[i * kinect.point_step: (i + 1) * kinect.point_step]
        xyz = rec[:12].view("<f4")
        packed = int(rec[16:20].view("<u4")[0])
        np.testing.assert_allclose(cloud.points[k[i]], xyz, rtol=0, atol=0)
        np.testing.assert_allclose(cloud.colors[k[i]] * 255, [(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], atol=1e-3)
    assert n == 640 * 480
    # the organized grid gives the Kinect's intrinsics
    _, intr, _ = cloudconv.cloud_and_intrinsics_from_pointcloud2(kinect)
    assert intr.fx == pytest.approx(525.0, rel=1e-5) and intr.fy == pytest.approx(525.0, rel=1e-5)
    assert intr.cx == pytest.approx(319.5, abs=1e-3) and intr.cy == pytest.approx(239.5, abs=1e-3)
    assert intr.frame_id == "camera_rgb_optical_frame"
    # rescaled to a model's input size the camera keeps its field of view
    small = intr.scaled(160, 120)
    assert small.fx == pytest.approx(131.25, rel=1e-5)


def test_kinect_cloud_roundtrip_through_our_pointcloud2(kinect):
    T = msgbuild.rosbags_types()
    cloud, _ = cloudconv.cloud_from_pointcloud2(kinect)
    msg = msgbuild.cloud_to_pointcloud2(kinect.header, cloud, T)
    back, shape = cloudconv.cloud_from_pointcloud2(T.typestore.deserialize_cdr(T.typestore.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__))
    assert shape is None and len(back) == len(cloud)
    np.testing.assert_array_equal(back.points, cloud.points)  # float32 in, float32 out
    np.testing.assert_allclose(back.colors, cloud.colors, atol=1e-6)


def test_realsense_unregistered_depth_and_colour_is_refused(realsense):
    depth = realsense["/device_0/sensor_0/Depth_0/image/data"][0]
    color = realsense["/device_0/sensor_1/Color_0/image/data"][0]
    depth_info = realsense["/device_0/sensor_0/Depth_0/info/camera_info"][0]
    color_info = realsense["/device_0/sensor_1/Color_0/info/camera_info"][0]
    # the streams decode
    d = msgconv.depth_to_meters(depth)
    assert d.shape == (480, 640) and 0.85 < np.isfinite(d).mean() < 0.98
    assert msgconv.color_to_numpy(color).shape == (480, 640, 3)
    # same size, same frame id "0", but different cameras: refused with the clear message
    with pytest.raises(PwsError) as exc:
        msgconv.cloud_from_rgbd(depth, color, color_info, depth_info)
    text = str(exc.value)
    assert "depth and colour are not registered" in text and "/camera/aligned_depth_to_color/image_raw" in text
    assert "fx=390.4" in text and "fx=613.2" in text and "\n" not in text

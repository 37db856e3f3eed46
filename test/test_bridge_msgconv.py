"""Message -> numpy conversions (pws_ros.bridge.msgconv) with rosbags message classes: every bad
input of the issue (row padding, endianness, NaN/zero depth, mismatched sizes, unsupported
encodings, truncated data) and round trips through the builders."""
from __future__ import annotations

import array

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.bridge import cloudconv, msgbuild, msgconv
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from pws_ros.core.cloud import cloud_from_rgbd as core_cloud_from_rgbd
from pws_ros.core.errors import PwsError

T = msgbuild.rosbags_types()


def header(stamp_ns=1_000_000_123, frame="cam"):
    return msgbuild.make_header(T, stamp_ns, frame)


def raw_image(pixels: np.ndarray, encoding: str, *, pad: int = 0, big: bool = False, frame="cam", truncate: int = 0, step=None):
    """An Image whose rows are ``pixels`` (H, W, ...) bytes in the given byte order plus ``pad`` bytes."""
    a = np.asarray(pixels)
    H, W = a.shape[:2]
    if a.dtype.itemsize > 1:
        a = a.astype(a.dtype.newbyteorder(">" if big else "<"))
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(H, -1)
    padded = np.concatenate([rows, np.full((H, pad), 0xAB, np.uint8)], axis=1)
    data = padded.reshape(-1)
    if truncate:
        data = data[:-truncate]
    return T.Image(header=header(frame=frame), height=H, width=W, encoding=encoding, is_bigendian=int(big),
                   step=int(padded.shape[1] if step is None else step), data=data)


def camera_info(w, h, fx=50.0, fy=52.0, cx=None, cy=None, frame="cam", binning=0, roi=(0, 0)):
    cx = (w - 1) / 2 if cx is None else cx
    cy = (h - 1) / 2 if cy is None else cy
    msg = msgbuild.camera_info_from_intrinsics(header(frame=frame), CameraIntrinsics(w, h, fx, fy, cx, cy, frame), T)
    msg.binning_x = binning
    msg.roi = T.RegionOfInterest(x_offset=0, y_offset=0, width=roi[0], height=roi[1], do_rectify=False)
    return msg


rng = np.random.default_rng(0)


# ---- images ----------------------------------------------------------------------------------

@pytest.mark.parametrize("pad", [0, 3, 8])
def test_colour_encodings_with_row_padding(pad):
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    alpha = rng.integers(0, 256, (5, 7, 1), dtype=np.uint8)
    cases = {
        "rgb8": rgb,
        "bgr8": rgb[:, :, ::-1],
        "rgba8": np.concatenate([rgb, alpha], axis=2),
        "bgra8": np.concatenate([rgb[:, :, ::-1], alpha], axis=2),
    }
    for enc, pixels in cases.items():
        out = msgconv.image_to_numpy(raw_image(pixels, enc, pad=pad))
        assert out.dtype == np.uint8 and out.shape == (5, 7, 3)
        np.testing.assert_array_equal(out, rgb, err_msg=enc)
    mono = rgb[:, :, 0]
    out = msgconv.image_to_numpy(raw_image(mono, "mono8", pad=pad))
    np.testing.assert_array_equal(out, np.repeat(mono[:, :, None], 3, axis=2))


@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("pad", [0, 2, 6])
def test_depth_encodings_honour_endianness_and_padding(big, pad):
    mm = rng.integers(0, 65535, (4, 6)).astype(np.uint16)
    for enc in ("16UC1", "mono16"):
        out = msgconv.image_to_numpy(raw_image(mm, enc, pad=pad, big=big))
        assert out.dtype == np.uint16
        np.testing.assert_array_equal(out, mm)
    m = rng.uniform(0.1, 5, (4, 6)).astype(np.float32)
    out = msgconv.image_to_numpy(raw_image(m, "32FC1", pad=pad, big=big))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, m)


def test_big_endian_differs_from_little_endian_reading():
    """The flag matters: the same bytes read with the other byte order give other values."""
    mm = np.array([[1, 256, 1000]], dtype=np.uint16)
    msg = raw_image(mm, "16UC1", big=True)
    np.testing.assert_array_equal(msgconv.image_to_numpy(msg), mm)
    msg.is_bigendian = 0
    np.testing.assert_array_equal(msgconv.image_to_numpy(msg), mm.byteswap())


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 6), w=st.integers(1, 6), pad=st.integers(0, 9), enc=st.sampled_from(["rgb8", "bgr8", "mono8", "16UC1", "32FC1"]),
       big=st.booleans(), seed=st.integers(0, 2**16))
def test_image_roundtrip_property(h, w, pad, enc, big, seed):
    r = np.random.default_rng(seed)
    if enc in ("rgb8", "bgr8"):
        arr = r.integers(0, 256, (h, w, 3), dtype=np.uint8)
        expect = arr if enc == "rgb8" else arr[:, :, ::-1]
    elif enc == "mono8":
        arr = r.integers(0, 256, (h, w), dtype=np.uint8)
        expect = np.repeat(arr[:, :, None], 3, axis=2)
    elif enc == "16UC1":
        arr = r.integers(0, 65536, (h, w)).astype(np.uint16)
        expect = arr
    else:
        arr = r.normal(size=(h, w)).astype(np.float32)
        expect = arr
    np.testing.assert_array_equal(msgconv.image_to_numpy(raw_image(arr, enc, pad=pad, big=big)), expect)


def test_last_row_padding_may_be_missing():
    rgb = rng.integers(0, 256, (3, 4, 3), dtype=np.uint8)
    msg = raw_image(rgb, "rgb8", pad=5, truncate=5)  # data = step*(h-1) + w*3
    np.testing.assert_array_equal(msgconv.image_to_numpy(msg), rgb)


def test_truncated_image_is_refused():
    rgb = rng.integers(0, 256, (3, 4, 3), dtype=np.uint8)
    with pytest.raises(PwsError, match="truncated"):
        msgconv.image_to_numpy(raw_image(rgb, "rgb8", truncate=1))
    with pytest.raises(PwsError, match="truncated"):
        msgconv.image_to_numpy(raw_image(np.zeros((3, 4), np.uint16), "16UC1", truncate=2))


def test_step_smaller_than_a_row_is_refused():
    with pytest.raises(PwsError, match="step 5 is smaller than one row"):
        msgconv.image_to_numpy(raw_image(np.zeros((2, 2, 3), np.uint8), "rgb8", step=5))


@pytest.mark.parametrize("enc", ["yuv422", "8UC3", "bayer_rggb8", "16UC3", "64FC1"])
def test_unsupported_encodings_are_refused(enc):
    msg = raw_image(np.zeros((2, 2, 3), np.uint8), "rgb8")
    msg.encoding = enc
    with pytest.raises(PwsError, match=f"unsupported image encoding '{enc}'"):
        msgconv.image_to_numpy(msg)


def test_empty_encoding_and_bad_sizes_are_refused():
    msg = raw_image(np.zeros((2, 2, 3), np.uint8), "rgb8")
    msg.encoding = ""
    with pytest.raises(PwsError, match="empty encoding"):
        msgconv.image_to_numpy(msg)
    msg = raw_image(np.zeros((2, 2, 3), np.uint8), "rgb8")
    msg.width = 0
    with pytest.raises(PwsError, match="width must be positive"):
        msgconv.image_to_numpy(msg)


def test_rclpy_style_data_containers():
    """rclpy gives array.array('B'); some code gives bytes or lists: all decode the same."""
    rgb = rng.integers(0, 256, (2, 3, 3), dtype=np.uint8)
    base = raw_image(rgb, "rgb8", pad=1)
    raw = bytes(base.data)
    for data in (raw, bytearray(raw), array.array("B", raw), list(raw), memoryview(raw)):
        base.data = data
        np.testing.assert_array_equal(msgconv.image_to_numpy(base), rgb)


def test_builder_roundtrip_all_encodings():
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    for enc in ("rgb8", "bgr8"):
        msg = msgbuild.image_from_numpy(header(), rgb, T, encoding=enc)
        assert msg.encoding == enc and msg.step == 15
        np.testing.assert_array_equal(msgconv.image_to_numpy(msg), rgb)
    mono = rgb[:, :, 1]
    np.testing.assert_array_equal(msgconv.image_to_numpy(msgbuild.image_from_numpy(header(), mono, T))[:, :, 0], mono)
    mm = rng.integers(0, 65536, (4, 5)).astype(np.uint16)
    np.testing.assert_array_equal(msgconv.image_to_numpy(msgbuild.image_from_numpy(header(), mm, T)), mm)
    f3 = rng.normal(size=(4, 5, 3)).astype(np.float32)
    msg = msgbuild.image_from_numpy(header(), f3, T)
    assert msg.encoding == "32FC3"
    np.testing.assert_array_equal(msgconv.image_to_numpy(msg), f3)
    f1 = f3[:, :, 0].copy()
    np.testing.assert_array_equal(msgconv.image_to_numpy(msgbuild.image_from_numpy(header(), f1, T)), f1)


# ---- depth -----------------------------------------------------------------------------------

def test_depth_to_meters_16uc1_millimetres_zero_is_invalid():
    mm = np.array([[0, 1, 1000], [65535, 500, 0]], dtype=np.uint16)
    d = msgconv.depth_to_meters(raw_image(mm, "16UC1", pad=2, big=True))
    assert d.dtype == np.float64
    np.testing.assert_array_equal(np.isnan(d), mm == 0)
    np.testing.assert_allclose(d[mm > 0], mm[mm > 0] / 1000.0)


def test_depth_to_meters_32fc1_nan_inf_zero_negative_are_invalid():
    m = np.array([[np.nan, 0.0, -1.0], [np.inf, 1.25, 3.5]], dtype=np.float32)
    d = msgconv.depth_to_meters(raw_image(m, "32FC1"))
    np.testing.assert_array_equal(np.isnan(d), [[True, True, True], [True, False, False]])
    np.testing.assert_allclose(d[1, 1:], [1.25, 3.5])


def test_depth_with_a_colour_encoding_is_refused():
    with pytest.raises(PwsError, match="depth image has encoding 'rgb8'"):
        msgconv.depth_to_meters(raw_image(np.zeros((2, 2, 3), np.uint8), "rgb8"))
    with pytest.raises(PwsError, match="colour image has encoding '16UC1'"):
        msgconv.color_to_numpy(raw_image(np.zeros((2, 2), np.uint16), "16UC1"))


# ---- camera info -----------------------------------------------------------------------------

def test_camera_info_intrinsics_and_refusals():
    intr = msgconv.intrinsics_from_camera_info(camera_info(8, 6, fx=40.0, fy=41.0, cx=3.5, cy=2.5, frame="opt"))
    assert (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, intr.frame_id) == (8, 6, 40.0, 41.0, 3.5, 2.5, "opt")
    with pytest.raises(PwsError, match="binning"):
        msgconv.intrinsics_from_camera_info(camera_info(8, 6, binning=2))
    with pytest.raises(PwsError, match="region of interest"):
        msgconv.intrinsics_from_camera_info(camera_info(8, 6, roi=(4, 3)))
    msg = camera_info(8, 6)
    msg.k = np.zeros(9)
    with pytest.raises(PwsError, match="calibrated"):
        msgconv.intrinsics_from_camera_info(msg)


# ---- RGB-D -----------------------------------------------------------------------------------

def rgbd_msgs(w=6, h=4, frame="cam", seed=1):
    r = np.random.default_rng(seed)
    mm = r.integers(300, 3000, (h, w)).astype(np.uint16)
    mm[0, 0] = 0
    rgb = r.integers(0, 256, (h, w, 3), dtype=np.uint8)
    return raw_image(mm, "16UC1", pad=4, frame=frame), raw_image(rgb[:, :, ::-1], "bgr8", pad=1, frame=frame), camera_info(w, h, frame=frame), mm, rgb


def test_cloud_from_rgbd_matches_per_pixel_backprojection():
    dmsg, cmsg, info, mm, rgb = rgbd_msgs()
    cloud, intr = msgconv.cloud_from_rgbd(dmsg, cmsg, info)
    assert intr.frame_id == "cam"
    expect_pts, expect_cols = [], []
    for r in range(mm.shape[0]):
        for c in range(mm.shape[1]):
            if mm[r, c] == 0:
                continue
            z = mm[r, c] / 1000.0
            expect_pts.append(((c - intr.cx) * z / intr.fx, (r - intr.cy) * z / intr.fy, z))
            expect_cols.append(rgb[r, c] / 255.0)
    np.testing.assert_allclose(cloud.points, np.array(expect_pts), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cloud.colors, np.array(expect_cols), atol=1e-6)
    ref = core_cloud_from_rgbd(msgconv.depth_to_meters(dmsg), rgb, intr)
    np.testing.assert_array_equal(ref.points, cloud.points)


def test_cloud_from_rgbd_32fc1_with_nan():
    dmsg, cmsg, info, mm, rgb = rgbd_msgs()
    m = (mm / 1000.0).astype(np.float32)
    m[mm == 0] = np.nan
    m[1, 1] = 0.0
    d32 = raw_image(m, "32FC1", big=True, frame="cam")
    cloud, _ = msgconv.cloud_from_rgbd(d32, cmsg, info)
    assert len(cloud) == mm.size - 2


def test_unregistered_sizes_are_refused_with_the_hint():
    dmsg, _, info, _, _ = rgbd_msgs(6, 4)
    _, cmsg, _, _, _ = rgbd_msgs(8, 4)
    with pytest.raises(PwsError) as exc:
        msgconv.cloud_from_rgbd(dmsg, cmsg, info)
    text = str(exc.value)
    assert text == ("depth 6x4 and colour 8x4 are not registered (different sizes); "
                    "use an aligned depth topic such as /camera/aligned_depth_to_color/image_raw")
    assert "\n" not in text


def test_camera_info_of_another_size_is_refused():
    dmsg, cmsg, _, _, _ = rgbd_msgs(6, 4)
    with pytest.raises(PwsError, match="CameraInfo 12x8 does not match the images 6x4"):
        msgconv.cloud_from_rgbd(dmsg, cmsg, camera_info(12, 8))


def test_depth_camera_with_other_intrinsics_is_refused():
    dmsg, cmsg, info, _, _ = rgbd_msgs(6, 4)
    with pytest.raises(PwsError, match="not registered.*aligned_depth_to_color"):
        msgconv.cloud_from_rgbd(dmsg, cmsg, info, camera_info(6, 4, fx=30.0))
    cloud, _ = msgconv.cloud_from_rgbd(dmsg, cmsg, info, camera_info(6, 4))  # same intrinsics: fine
    assert len(cloud) > 0


def test_depth_and_colour_frames_must_agree():
    dmsg, _, info, _, _ = rgbd_msgs(frame="camera_depth_optical_frame")
    _, cmsg, _, _, _ = rgbd_msgs(frame="camera_color_optical_frame")
    with pytest.raises(PwsError, match="depth frame 'camera_depth_optical_frame' and colour frame"):
        msgconv.cloud_from_rgbd(dmsg, cmsg, info)
    cloud, intr = msgconv.cloud_from_rgbd(dmsg, cmsg, info, require_same_frame=False)
    assert len(cloud) > 0


def test_depth_and_colour_swapped_are_refused():
    dmsg, cmsg, info, _, _ = rgbd_msgs()
    with pytest.raises(PwsError, match="depth image has encoding 'bgr8'"):
        msgconv.cloud_from_rgbd(cmsg, dmsg, info)


# ---- PointCloud2 -----------------------------------------------------------------------------

F = {"f4": 7, "f8": 8, "u4": 6, "i4": 5, "u1": 2, "i2": 3}


def make_pc2(points, colors=None, *, color_kind="f4", xyz_kind="f4", shape=None, point_pad=0, row_pad=0, big=False,
             lead=0, name="rgb", frame="cam", truncate=0):
    """A PointCloud2 with fields at unusual offsets: ``lead`` bytes before x, padding after each point/row."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    H, W = shape if shape is not None else (1, n)
    e = ">" if big else "<"
    xs = np.dtype(xyz_kind).itemsize
    layout = [("x", lead), ("y", lead + xs), ("z", lead + 2 * xs)]
    off = lead + 3 * xs
    fields = [T.PointField(name=k, offset=o, datatype=F[xyz_kind], count=1) for k, o in layout]
    if colors is not None:
        fields.append(T.PointField(name=name, offset=off + 1, datatype=F[color_kind], count=1))
        end = off + 5
    else:
        end = off
    step = end + point_pad
    buf = np.zeros((H, W * step + row_pad), np.uint8)
    flat = buf[:, : W * step].reshape(H, W, step)
    for i, (k, o) in enumerate(layout):
        v = pts[:, i].astype(e + xyz_kind).view(np.uint8).reshape(H, W, xs)
        flat[:, :, o: o + xs] = v
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint32)
        packed = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
        if color_kind == "f4":
            packed_bytes = packed.astype(e + "u4").view(np.uint8)
        else:
            packed_bytes = packed.astype(e + color_kind).view(np.uint8)
        flat[:, :, off + 1: off + 5] = packed_bytes.reshape(H, W, 4)
    data = buf.reshape(-1)
    if truncate:
        data = data[:-truncate]
    return T.PointCloud2(header=header(frame=frame), height=H, width=W, fields=fields, is_bigendian=big, point_step=step,
                         row_step=W * step + row_pad, data=data, is_dense=False)


@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("xyz_kind", ["f4", "f8"])
@pytest.mark.parametrize("color_kind", ["f4", "u4"])
def test_pointcloud2_layouts(big, xyz_kind, color_kind):
    r = np.random.default_rng(3)
    pts = r.uniform(-1, 1, (12, 3)) + [0, 0, 2]
    cols = r.integers(0, 256, (12, 3))
    msg = make_pc2(pts, cols, color_kind=color_kind, xyz_kind=xyz_kind, shape=(3, 4), point_pad=3, row_pad=5, big=big, lead=4)
    conv = cloudconv.cloud_from_pointcloud2(msg)
    cloud, shape = conv
    assert shape == (3, 4) and conv.has_color
    tol = 1e-6 if xyz_kind == "f4" else 0
    np.testing.assert_allclose(cloud.points, pts, atol=tol * 4)
    np.testing.assert_allclose(cloud.colors, cols / 255.0, atol=1e-7)


def test_pointcloud2_nan_inf_and_zero_points_are_dropped():
    pts = np.array([[0, 0, 1.0], [np.nan, 0, 1], [0, np.inf, 1], [0, 0, 0], [1, 2, 3.0], [0.5, -0.5, -np.inf]])
    cols = np.arange(18).reshape(6, 3)
    conv = cloudconv.cloud_from_pointcloud2(make_pc2(pts, cols, shape=(2, 3)))
    np.testing.assert_array_equal(conv.valid, [True, False, False, False, True, False])
    np.testing.assert_allclose(conv.cloud.points, pts[[0, 4]])
    np.testing.assert_allclose(conv.cloud.colors * 255, cols[[0, 4]], atol=1e-4)


def test_pointcloud2_without_colour_is_grey_and_flagged():
    pts = np.array([[0, 0, 1.0], [0.1, 0, 1.0]])
    conv = cloudconv.cloud_from_pointcloud2(make_pc2(pts))
    cloud, shape = conv
    assert shape is None and not conv.has_color
    np.testing.assert_allclose(cloud.colors, 0.5)


def test_pointcloud2_rgba_and_separate_channels():
    pts = np.array([[0, 0, 1.0]])
    conv = cloudconv.cloud_from_pointcloud2(make_pc2(pts, [[10, 20, 30]], name="rgba", color_kind="u4"))
    np.testing.assert_allclose(conv.cloud.colors * 255, [[10, 20, 30]], atol=1e-4)
    # r, g, b uint8 fields
    fields = [T.PointField(name=k, offset=o, datatype=7, count=1) for k, o in (("x", 0), ("y", 4), ("z", 8))]
    fields += [T.PointField(name=k, offset=12 + i, datatype=2, count=1) for i, k in enumerate("rgb")]
    rec = np.zeros(1, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"), ("_", "u1")])
    rec["z"], rec["r"], rec["g"], rec["b"] = 2.0, 200, 100, 50
    msg = T.PointCloud2(header=header(), height=1, width=1, fields=fields, is_bigendian=False, point_step=16, row_step=16,
                        data=rec.view(np.uint8).copy(), is_dense=True)
    conv = cloudconv.cloud_from_pointcloud2(msg)
    np.testing.assert_allclose(conv.cloud.colors * 255, [[200, 100, 50]], atol=1e-4)


def test_pointcloud2_bad_inputs():
    pts = np.array([[0, 0, 1.0], [0.1, 0, 1.0]])
    msg = make_pc2(pts, [[1, 2, 3], [4, 5, 6]], truncate=1)
    with pytest.raises(PwsError, match="truncated"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts)
    msg.fields = [f for f in msg.fields if f.name != "z"]
    with pytest.raises(PwsError, match="no 'z' field"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts)
    msg.fields[0] = T.PointField(name="x", offset=0, datatype=3, count=1)
    with pytest.raises(PwsError, match="'x' is INT16: expected FLOAT32 or FLOAT64"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts, [[1, 2, 3], [4, 5, 6]], color_kind="i2" if False else "f4")
    msg.fields[3] = T.PointField(name="rgb", offset=13, datatype=2, count=1)
    with pytest.raises(PwsError, match="'rgb' is UINT8: expected packed"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts)
    msg.fields[2] = T.PointField(name="z", offset=10, datatype=7, count=1)
    with pytest.raises(PwsError, match="does not fit in point_step 12"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts)
    msg.row_step = 10
    with pytest.raises(PwsError, match="row_step 10 is smaller"):
        cloudconv.cloud_from_pointcloud2(msg)
    msg = make_pc2(pts)
    msg.fields[1] = T.PointField(name="y", offset=4, datatype=42, count=1)
    with pytest.raises(PwsError, match="unknown datatype 42"):
        cloudconv.cloud_from_pointcloud2(msg)


def test_pointcloud2_roundtrip_through_builder():
    r = np.random.default_rng(5)
    cloud = Cloud(r.uniform(-1, 1, (20, 3)) + [0, 0, 3], r.integers(0, 256, (20, 3)).astype(np.uint8))
    msg = msgbuild.cloud_to_pointcloud2(header(), cloud, T, organized_shape=(4, 5))
    back, shape = cloudconv.cloud_from_pointcloud2(msg)
    assert shape == (4, 5)
    np.testing.assert_allclose(back.points, cloud.points, rtol=1e-6)
    np.testing.assert_array_equal(np.rint(back.colors * 255), np.rint(cloud.colors * 255))
    # and through CDR, as a bag or DDS would carry it
    raw = T.typestore.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
    again, _ = cloudconv.cloud_from_pointcloud2(T.typestore.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2"))
    np.testing.assert_array_equal(again.points, back.points)


def test_pointcloud2_carries_which_points_were_filled():
    """The pws_filled field: the mask survives the builder and CDR point by point; a cloud without filled
    points keeps the plain 16-byte layout (no field); a foreign cloud without the field has none."""
    r = np.random.default_rng(6)
    mask = r.random(30) < 0.3
    cloud = Cloud(r.uniform(-1, 1, (30, 3)) + [0, 0, 3], r.integers(0, 256, (30, 3)).astype(np.uint8), filled_mask=mask)
    assert cloud.filled == int(mask.sum()) > 0
    msg = msgbuild.cloud_to_pointcloud2(header(), cloud, T)
    assert msg.point_step == 20 and [f.name for f in msg.fields] == ["x", "y", "z", "rgb", cloudconv.FILLED_FIELD]
    raw = T.typestore.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
    back = cloudconv.cloud_from_pointcloud2(T.typestore.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")).cloud
    np.testing.assert_array_equal(back.filled_mask, mask)
    assert back.filled == int(mask.sum())
    np.testing.assert_allclose(back.points, cloud.points, rtol=1e-6)
    plain = msgbuild.cloud_to_pointcloud2(header(), Cloud(cloud.points, cloud.colors), T)
    assert plain.point_step == 16 and len(plain.fields) == 4
    assert cloudconv.cloud_from_pointcloud2(plain).cloud.filled == 0 and cloudconv.cloud_from_pointcloud2(plain).cloud.filled_mask is None


def organized_grid(intr: CameraIntrinsics, depth: np.ndarray) -> np.ndarray:
    rows, cols = np.mgrid[0: intr.height, 0: intr.width]
    z = depth
    return np.stack([(cols - intr.cx) * z / intr.fx, (rows - intr.cy) * z / intr.fy, z], axis=-1).reshape(-1, 3)


def test_intrinsics_estimated_from_an_organized_cloud():
    intr = CameraIntrinsics(16, 12, 20.0, 22.0, 7.3, 5.9)
    depth = np.random.default_rng(2).uniform(0.5, 3.0, (12, 16))
    pts = organized_grid(intr, depth)
    pts[::7] = np.nan
    msg = make_pc2(pts, np.zeros((len(pts), 3)), shape=(12, 16), xyz_kind="f8")
    cloud, est, has_color = cloudconv.cloud_and_intrinsics_from_pointcloud2(msg)
    assert has_color and est.shape == (12, 16) and est.frame_id == "cam"
    for k in ("fx", "fy", "cx", "cy"):
        assert getattr(est, k) == pytest.approx(getattr(intr, k), rel=1e-9, abs=1e-9)


def test_not_a_pinhole_grid_is_refused():
    intr = CameraIntrinsics(16, 12, 20.0, 22.0, 7.5, 5.5)
    pts = organized_grid(intr, np.full((12, 16), 2.0))
    pts = pts[np.random.default_rng(0).permutation(len(pts))]  # shuffled: not an image grid
    msg = make_pc2(pts, shape=(12, 16))
    with pytest.raises(PwsError, match="not a pinhole image grid"):
        cloudconv.cloud_and_intrinsics_from_pointcloud2(msg)


def test_pointcloud2_with_camera_info():
    intr = CameraIntrinsics(16, 12, 20.0, 22.0, 7.5, 5.5)
    pts = organized_grid(intr, np.full((12, 16), 2.0))
    msg = make_pc2(pts, shape=(12, 16))
    _, got, _ = cloudconv.cloud_and_intrinsics_from_pointcloud2(msg, camera_info(16, 12, fx=20.0, fy=22.0, cx=7.5, cy=5.5))
    assert (got.fx, got.cx) == (20.0, 7.5)
    with pytest.raises(PwsError, match="organized PointCloud2 16x12 and CameraInfo 8x6 differ in size"):
        cloudconv.cloud_and_intrinsics_from_pointcloud2(msg, camera_info(8, 6))
    flat = make_pc2(pts)  # unorganized
    with pytest.raises(PwsError, match="unorganized PointCloud2"):
        cloudconv.cloud_and_intrinsics_from_pointcloud2(flat)
    _, got, _ = cloudconv.cloud_and_intrinsics_from_pointcloud2(flat, fallback=intr)
    assert got.fx == 20.0 and got.frame_id == "cam"

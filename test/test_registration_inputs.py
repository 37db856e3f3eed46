"""Depth registration in the input path: the RealSense recording (driver extrinsics topic) and a
synthetic recording whose depth and colour cameras are related through /tf_static."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from conftest import MeanThresholdNet, shared_path
from pws_ros.bagio import BagReader
from pws_ros.bridge import cloudconv, msgbuild, msgconv
from pws_ros.bridge.config import PwsConfig
from pws_ros.bridge.inputs import InputAssembler, convert
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import cloud_from_rgbd
from pws_ros.core.errors import PwsError
from pws_ros.core.registration import Extrinsic, register_depth
from pws_ros.replay import ReplayOptions, discover_inputs, replay
from test_depth_fill import brute_fill
from test_registration import brute_register

RS_DEPTH = "/device_0/sensor_0/Depth_0/image/data"
RS_COLOR = "/device_0/sensor_1/Color_0/image/data"
RS_DEPTH_INFO = "/device_0/sensor_0/Depth_0/info/camera_info"
RS_COLOR_INFO = "/device_0/sensor_1/Color_0/info/camera_info"
RS_TF = ("/device_0/sensor_0/Depth_0/tf/0", "/device_0/sensor_1/Color_0/tf/0")
TINY = dict(axes=("tz",), radius_tz=1e-4, n0=8, n=16, min_partitions=0)


def _first_messages(folder) -> dict:
    with BagReader(folder) as bag:
        return {t: bag.deserialize(v[0]) for t, v in bag.first_messages(list(bag.topics)).items() if v}


@pytest.fixture(scope="module")
def realsense():
    folder = shared_path("realsense_single_rgbd")
    return folder, _first_messages(folder)


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    from pws_ros.core.model import save_model

    return save_model(MeanThresholdNet(0.5), tmp_path_factory.mktemp("m") / "m.pt", ["dark", "bright"], input_size=(24, 32))


def test_realsense_registered_depth_coverage_and_alignment(realsense):
    _folder, m = realsense
    dcam, ccam = (msgconv.intrinsics_from_camera_info(m[t]) for t in (RS_DEPTH_INFO, RS_COLOR_INFO))
    ref_to_d, ref_to_c = (msgconv.extrinsic_from_transform(m[t]) for t in RS_TF)
    T = ref_to_d.inverse().then(ref_to_c)
    assert 0.01 < np.linalg.norm(T.translation) < 0.02           # ~14 mm baseline of a D4xx
    depth = msgconv.image_to_numpy(m[RS_DEPTH])
    reg = register_depth(depth, dcam, ccam, T)
    assert reg.shape == (480, 640) and reg.dtype == np.uint16
    # coverage: the colour camera (fx 613) sees a part of the depth camera's field (fx 390), ~93% of which has
    # a depth; each depth pixel covers its ~1.6x1.6 colour pixels (footprint splat), so no upsampling pinholes
    # are left: as many colour pixels get a depth as the depth image has valid pixels (one point per depth
    # pixel reached only 30-45%)
    valid = reg > 0
    assert valid.mean() > 0.9 and valid.mean() >= (depth > 0).mean() - 0.02
    assert ndimage.binary_dilation(valid, np.ones((3, 3), bool)).mean() > 0.95
    # nearest depth wins: no registered depth is farther than the farthest input depth
    assert reg[valid].min() >= 0.9 * depth[depth > 0].min() and reg.max() <= 1.05 * depth.max()
    # the direction of the recorder's extrinsics: depth edges land on colour edges with T, not with its inverse
    gray = msgconv.color_to_numpy(m[RS_COLOR]).astype(float).mean(axis=2)
    grad = np.hypot(ndimage.sobel(gray, 0), ndimage.sobel(gray, 1))

    def edge_score(E):
        r = register_depth(depth, dcam, ccam, E).astype(float)
        idx = ndimage.distance_transform_edt(r == 0, return_distances=False, return_indices=True)
        filled = r[tuple(idx)]
        edges = np.hypot(ndimage.sobel(filled, 0), ndimage.sobel(filled, 1)) > 200
        return grad[edges].mean()

    assert edge_score(T) > 1.5 * edge_score(T.inverse())


def test_realsense_input_path_gives_a_cloud_instead_of_a_refusal(realsense):
    _folder, m = realsense
    cfg = PwsConfig(sync_tolerance_s=0.15)
    T = msgconv.extrinsic_from_transform(m[RS_TF[0]]).inverse().then(msgconv.extrinsic_from_transform(m[RS_TF[1]]))
    for extrinsic in (None, T):
        a = InputAssembler(cfg)
        a.set_extrinsic(extrinsic)
        a.on_info(m[RS_COLOR_INFO])
        a.on_depth_info(m[RS_DEPTH_INFO])
        assert a.on_color(m[RS_COLOR]) is None
        raw = a.on_depth(m[RS_DEPTH])
        assert raw is not None and raw.source == "rgbd"
        if extrinsic is None:
            with pytest.raises(PwsError, match="not registered"):
                convert(raw, cfg)
            continue
        frame = convert(raw, cfg)
        assert frame.intrinsics.fx == pytest.approx(613.2, abs=0.1)     # the colour camera
        # depth_fill: row (the default): every colour pixel becomes a point, ~4% of them filled
        assert len(frame.cloud) == 640 * 480 and 0 < frame.cloud.filled < 0.1 * 640 * 480
        assert frame.cloud.points[:, 2].min() > 0.1
        off = convert(raw, PwsConfig(sync_tolerance_s=0.15, depth_fill="off"))
        assert 0.9 * 640 * 480 < len(off.cloud) == 640 * 480 - frame.cloud.filled and off.cloud.filled == 0


def test_realsense_replay_registers_and_certifies(realsense, model_path, tmp_path):
    folder, _m = realsense
    logs: list[tuple[str, str]] = []
    cfg = PwsConfig(model_path=str(model_path), **TINY)   # the default sync: 20 ms at once, 0.2 s once settled
    res = replay(ReplayOptions(bag=folder, config=cfg, out=tmp_path / "out", log=lambda lv, msg: logs.append((lv, msg))))
    said = [msg for _lv, msg in logs if "depth registered into the colour camera" in msg]
    assert len(said) == 1 and RS_TF[0] in said[0] and RS_TF[1] in said[0]
    assert res.exit_code == 0, res.message
    (rec,) = res.records
    assert rec.input_error is None or rec.input_error == ""
    assert [c.status for c in rec.certificates] != ["error"]
    # every certificate says how many points of its cloud have a filled depth (depth_fill: row), and the
    # certification message carries it
    assert all(0 < c.filled_points < 0.1 * 640 * 480 for c in rec.certificates)
    with BagReader(tmp_path / "out") as bag:
        diag = bag.deserialize(next(iter(bag.messages(["/certification"]))))
    values = {kv.key: kv.value for kv in diag.status[0].values}
    assert values["filled_points"] == str(rec.certificates[0].filled_points)
    # the pair is 101.6 ms apart (the recording's only colour frame, its nearest depth frame): one WARN says so
    skew = [msg for lv, msg in logs if "101.6 ms apart" in msg]
    assert len(skew) == 1 and "sync_max_skew_s" in skew[0]
    # with sync_max_skew_s 0 only the 20 ms tolerance pairs: they never do, said plainly
    res = replay(ReplayOptions(bag=folder, config=PwsConfig(model_path=str(model_path), sync_max_skew_s=0.0, **TINY),
                               write_output=False, quiet=True, log=lambda *a: None))
    assert res.exit_code == 2 and "sync-tolerance" in res.message and "not registered" not in res.message


# ---- a synthetic recording related through /tf_static ------------------------------------------

DCAM = CameraIntrinsics(32, 24, 20.0, 20.0, 15.5, 11.5, "cam_depth_optical")
CCAM = CameraIntrinsics(32, 24, 28.0, 28.5, 15.0, 12.0, "cam_color_optical")
LINK_TO_DEPTH = Extrinsic(np.eye(3), [0.0, 0.0, 0.0])                                   # child depth -> parent link
LINK_TO_COLOR = Extrinsic(Rotation.from_rotvec([0.0, 0.02, 0.01]).as_matrix(), [0.015, 0.0, 0.0])


def _synthetic_bag(path, with_tf=True):
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin

    T = msgbuild.rosbags_types()
    ts = T.typestore
    rng = np.random.default_rng(0)
    depth = np.full((24, 32), 1500, np.uint16)
    depth[8:16, 10:22] = 900
    depth[0, :5] = 0
    items = []
    for k in range(2):
        stamp = 1_000_000_000 + k * 100_000_000
        rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
        items += [("/camera/depth/camera_info", msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, stamp, DCAM.frame_id), DCAM, T)),
                  ("/camera/color/camera_info", msgbuild.camera_info_from_intrinsics(msgbuild.make_header(T, stamp, CCAM.frame_id), CCAM, T)),
                  ("/camera/depth/image_rect_raw", msgbuild.image_from_numpy(msgbuild.make_header(T, stamp, DCAM.frame_id), depth, T)),
                  ("/camera/color/image_raw", msgbuild.image_from_numpy(msgbuild.make_header(T, stamp, CCAM.frame_id), rgb, T))]
    if with_tf:
        TS, TF = ts.types["geometry_msgs/msg/TransformStamped"], ts.types["tf2_msgs/msg/TFMessage"]
        Tr, V, Q = ts.types["geometry_msgs/msg/Transform"], ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]

        def stamped(parent, child, E):
            x, y, z, w = Rotation.from_matrix(E.rotation).as_quat()
            return TS(header=msgbuild.make_header(T, 0, parent), child_frame_id=child,
                      transform=Tr(translation=V(x=float(E.translation[0]), y=float(E.translation[1]), z=float(E.translation[2])),
                                   rotation=Q(x=float(x), y=float(y), z=float(z), w=float(w))))

        items.insert(0, ("/tf_static", TF(transforms=[stamped("camera_link", DCAM.frame_id, LINK_TO_DEPTH),
                                                      stamped("camera_link", CCAM.frame_id, LINK_TO_COLOR)])))
    conns = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for i, (topic, msg) in enumerate(items):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(conns[topic], 1_000_000_000 + i, ts.serialize_cdr(msg, msg.__msgtype__))
    return path, depth


def test_tf_static_extrinsic_is_found_and_registers_like_the_brute_force(tmp_path, model_path):
    path, depth = _synthetic_bag(tmp_path / "tf")
    cfg = PwsConfig(model_path=str(model_path), **TINY)
    with BagReader(path) as bag:
        inputs = discover_inputs(bag, cfg)
    assert inputs.depth_info == "/camera/depth/camera_info" and inputs.info == "/camera/color/camera_info"
    assert inputs.extrinsic is not None and "/tf_static" in inputs.extrinsic_from
    # independent: depth optical -> link is LINK_TO_DEPTH, link -> colour optical is LINK_TO_COLOR inverted
    R = LINK_TO_COLOR.rotation.T @ LINK_TO_DEPTH.rotation
    t = LINK_TO_COLOR.rotation.T @ (LINK_TO_DEPTH.translation - LINK_TO_COLOR.translation)
    np.testing.assert_allclose(inputs.extrinsic.rotation, R, atol=1e-9)
    np.testing.assert_allclose(inputs.extrinsic.translation, t, atol=1e-9)
    # the frame's cloud is the colour camera's cloud of the brute-force registered depth
    logs: list[str] = []
    res = replay(ReplayOptions(bag=path, config=cfg, out=tmp_path / "out", write_cloud=True, log=lambda lv, msg: logs.append(msg)))
    assert res.exit_code == 0, res.message
    assert sum("depth registered into the colour camera" in s for s in logs) == 1
    assert all(c.status != "error" for r in res.records for c in r.certificates) and len(res.records) == 2
    want = brute_register(np.where(depth > 0, depth / 1000.0, np.nan), DCAM, CCAM, R, t, millimetres=False)   # metres, not rounded
    want_cloud = cloud_from_rgbd(brute_fill(want), np.zeros((24, 32, 3), np.uint8), CCAM)   # depth_fill: row (default)
    with BagReader(tmp_path / "out") as bag:
        msg = bag.deserialize(next(iter(bag.messages(["/cloud"]))))
    got, _shape = cloudconv.cloud_from_pointcloud2(msg)
    assert len(got) == len(want_cloud) > 0.5 * 24 * 32
    np.testing.assert_allclose(np.sort(got.points, axis=0), np.sort(want_cloud.points, axis=0), atol=1e-6)


def test_without_extrinsics_unregistered_depth_is_still_refused(tmp_path, model_path):
    path, _depth = _synthetic_bag(tmp_path / "notf", with_tf=False)
    logs: list[tuple[str, str]] = []
    res = replay(ReplayOptions(bag=path, config=PwsConfig(model_path=str(model_path), **TINY), write_output=False,
                               log=lambda lv, msg: logs.append((lv, msg))))
    assert res.exit_code == 2 and "not registered" in res.message
    assert any(lv == "warn" and "no depth -> colour extrinsic was found" in msg for lv, msg in logs)
    assert not any("depth registered into" in msg for _lv, msg in logs)

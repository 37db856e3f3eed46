"""Recording the world as rosbag2 bags: round trip through rosbags (MCAP and sqlite3) and the
independent mcap + mcap_ros2 reader."""
from __future__ import annotations

import argparse
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest

from pws_ros.core.errors import PwsError
from pws_ros.sim import CLASS_NAMES, dense_cloud_for, render_view
from pws_ros.sim.record import (
    TOPICS,
    TOPIC_COLOR,
    TOPIC_DEPTH,
    TOPIC_INFO,
    TOPIC_POINTS,
    TOPIC_TRUTH,
    frame_schedule,
    pack_rgb,
    read_recording,
    record,
    unpack_rgb,
)

W, H = 48, 27


@pytest.fixture(scope="module")
def mcap_bag(tmp_path_factory) -> Path:
    return record(tmp_path_factory.mktemp("rec") / "bag", 5, seed=3, width=W, height=H, views_per_scene=2)


def test_pack_rgb_round_trip():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, size=(7, 5, 3), dtype=np.uint8)
    assert np.array_equal(unpack_rgb(pack_rgb(rgb)), rgb)
    assert pack_rgb(np.array([[1, 2, 3]], dtype=np.uint8)).view(np.uint32)[0] == (1 << 16) | (2 << 8) | 3


def test_schedule():
    s = frame_schedule(7, seed=10, views_per_scene=3)
    assert [a for a, _ in s] == [10, 10, 10, 11, 11, 11, 12]
    assert len(set(s)) == 7
    with pytest.raises(PwsError):
        frame_schedule(0)


def _check_frame(f, scene_seed, view_index):
    v = render_view(scene_seed, view_index, W, H, dense=False)
    assert np.array_equal(f.rgb, v.rgb)
    assert np.abs(f.depth_m - v.depth).max() <= 0.0005 + 1e-9
    assert f.intrinsics.fx == v.intrinsics.fx and f.intrinsics.cx == v.intrinsics.cx
    assert (f.intrinsics.width, f.intrinsics.height) == (W, H)
    assert f.intrinsics.frame_id == "camera_color_optical_frame"
    # organised cloud: z = depth, x/y from the intrinsics, packed colour = image
    assert np.allclose(f.points[..., 2], v.depth, atol=1e-6)
    cols = np.arange(W)[None, :]
    assert np.allclose(f.points[..., 0], (cols - v.intrinsics.cx) * v.depth / v.intrinsics.fx, atol=1e-5)
    assert np.array_equal(f.point_rgb, v.rgb)
    assert f.truth["label"] == str(v.label) and f.truth["class_name"] == v.class_name
    assert f.truth["scene_seed"] == str(scene_seed) and f.truth["view_index"] == str(view_index)


def test_mcap_round_trip_with_rosbags(mcap_bag):
    frames = list(read_recording(mcap_bag))
    sched = frame_schedule(5, seed=3, views_per_scene=2)
    assert len(frames) == 5
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps) and len(set(stamps)) == 5
    for f, (s, v) in zip(frames, sched):
        _check_frame(f, s, v)
    # the dense cloud of a recorded frame is regenerated from its ground truth
    f = frames[0]
    dense = dense_cloud_for(int(f.truth["scene_seed"]), int(f.truth["view_index"]), int(f.truth["width"]), int(f.truth["height"]))
    assert len(dense) > 1000 and np.all(dense.points[:, 2] > 0)


def test_mcap_opens_with_independent_reader(mcap_bag):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    files = list(Path(mcap_bag).glob("*.mcap"))
    assert len(files) == 1
    counts = Counter()
    by_stamp = defaultdict(set)
    with open(files[0], "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert all(c.compression == "zstd" for c in summary.chunk_indexes)
        for schema, channel, message, msg in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            assert schema.name == TOPICS[channel.topic]
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == message.log_time
            assert msg.header.frame_id == "camera_color_optical_frame"
            by_stamp[stamp].add(channel.topic)
            if channel.topic == TOPIC_COLOR:
                assert (msg.encoding, msg.width, msg.height, msg.step) == ("rgb8", W, H, 3 * W)
            elif channel.topic == TOPIC_DEPTH:
                assert (msg.encoding, msg.step) == ("16UC1", 2 * W)
                mm = np.frombuffer(bytes(msg.data), dtype="<u2")
                assert mm.min() > 0
            elif channel.topic == TOPIC_INFO:
                assert msg.distortion_model == "plumb_bob" and list(msg.d) == [0.0] * 5
                assert len(msg.k) == 9 and len(msg.p) == 12 and list(msg.r) == [1, 0, 0, 0, 1, 0, 0, 0, 1]
            elif channel.topic == TOPIC_POINTS:
                assert (msg.height, msg.width, msg.point_step, msg.row_step, msg.is_dense) == (H, W, 16, 16 * W, False)
                assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("rgb", 12, 7)]
            elif channel.topic == TOPIC_TRUTH:
                (st,) = msg.status
                kv = {k.key: k.value for k in st.values}
                assert st.name == "ground_truth" and kv["class_name"] in CLASS_NAMES
                assert {"label", "class_name", "scene_seed", "view_index"} <= set(kv)
    assert counts == {t: 5 for t in TOPICS}
    assert all(v == set(TOPICS) for v in by_stamp.values()) and len(by_stamp) == 5


def test_sqlite3_round_trip(tmp_path):
    bag = record(tmp_path / "db", 2, storage="sqlite3", seed=0, width=W, height=H)
    assert list(bag.glob("*.db3"))
    frames = list(read_recording(bag))
    assert len(frames) == 2
    for f, (s, v) in zip(frames, frame_schedule(2, 0, 3)):
        _check_frame(f, s, v)


def test_record_without_points(tmp_path):
    """points=False: the same frames, byte for byte, minus the PointCloud2 topic."""
    from mcap.reader import make_reader

    bag = record(tmp_path / "np", 3, seed=4, width=W, height=H, views_per_scene=2, points=False)
    with_points = record(tmp_path / "wp", 3, seed=4, width=W, height=H, views_per_scene=2)
    frames = list(read_recording(bag))
    assert len(frames) == 3
    for f, g, (s, v) in zip(frames, read_recording(with_points), frame_schedule(3, seed=4, views_per_scene=2)):
        assert f.points is None and f.point_rgb is None
        assert f.stamp_ns == g.stamp_ns and f.truth == g.truth and f.intrinsics == g.intrinsics
        assert np.array_equal(f.rgb, g.rgb) and np.array_equal(f.depth_m, g.depth_m)
        v_ = render_view(s, v, W, H, dense=False)
        assert np.array_equal(f.rgb, v_.rgb) and np.abs(f.depth_m - v_.depth).max() <= 0.0005 + 1e-9

    def raw_by_topic(path):
        out = defaultdict(list)
        with open(next(Path(path).glob("*.mcap")), "rb") as fh:
            for _s, channel, message in make_reader(fh).iter_messages():
                out[channel.topic].append((message.log_time, bytes(message.data)))
        return dict(out)

    a, b = raw_by_topic(bag), raw_by_topic(with_points)
    assert set(a) == set(TOPICS) - {TOPIC_POINTS} and set(b) == set(TOPICS)
    assert all(a[t] == b[t] for t in a)  # the other messages are unchanged
    assert sum(f.stat().st_size for f in bag.iterdir()) < sum(f.stat().st_size for f in with_points.iterdir())


def test_recording_is_deterministic(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    x = record(tmp_path / "a" / "bag", 2, seed=5, width=W, height=H, points=False)
    y = record(tmp_path / "b" / "bag", 2, seed=5, width=W, height=H, points=False)
    for name in ("bag.mcap", "metadata.yaml"):
        assert (x / name).read_bytes() == (y / name).read_bytes()


def test_reading_a_bag_without_camera_topics_names_them(tmp_path):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / "other", version=9) as w:
        w.add_connection(TOPIC_TRUTH, TOPICS[TOPIC_TRUTH], typestore=ts)
    with pytest.raises(PwsError, match=f"lacks {TOPIC_DEPTH}.*{TOPIC_INFO}"):
        list(read_recording(tmp_path / "other"))


def test_invalid_depth_is_zero_and_nan(tmp_path):
    bag = record(tmp_path / "far", 1, seed=1, width=W, height=H, max_depth=2.5)
    (f,) = list(read_recording(bag))
    invalid = f.depth_m == 0
    assert invalid.any() and (~invalid).any()
    assert np.all(np.isnan(f.points[invalid])) and np.all(np.isfinite(f.points[~invalid]))


def test_bad_requests(tmp_path):
    (tmp_path / "exists").mkdir()
    with pytest.raises(PwsError, match="already exists"):
        record(tmp_path / "exists", 1, width=W, height=H)
    with pytest.raises(PwsError, match="storage"):
        record(tmp_path / "x", 1, storage="rosbag1", width=W, height=H)
    with pytest.raises(PwsError, match="frames"):
        record(tmp_path / "y", 0, width=W, height=H)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def _cli(argv):
    from pws_ros.commands import sim

    parser = argparse.ArgumentParser(prog="pws")
    sim.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_record_and_view(tmp_path, capsys):
    assert _cli(["sim", "record", "--out", str(tmp_path / "b"), "--frames", "2", "--width", str(W), "--height", str(H)]) == 0
    assert len(list(read_recording(tmp_path / "b"))) == 2
    assert _cli(["sim", "record", "--out", str(tmp_path / "c"), "--frames", "2", "--width", str(W), "--height", str(H), "--no-points"]) == 0
    assert "RGB-D, CameraInfo, ground truth;" in capsys.readouterr().out
    c = list(read_recording(tmp_path / "c"))
    assert len(c) == 2 and all(f.points is None for f in c)
    assert _cli(["sim", "view", "--seed", "2", "--view", "4", "--out-dir", str(tmp_path / "v"), "--width", str(W), "--height", str(H)]) == 0
    for name in ("rgb.png", "depth.png", "camera.yaml", "cloud.npz", "dense_cloud.npz", "view.json"):
        assert (tmp_path / "v" / name).is_file()
    import cv2

    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.cloud import Cloud

    v = render_view(2, 4, W, H)
    rgb = cv2.cvtColor(cv2.imread(str(tmp_path / "v" / "rgb.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(rgb, v.rgb)
    depth = cv2.imread(str(tmp_path / "v" / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and np.abs(depth / 1000.0 - v.depth).max() <= 0.0005 + 1e-9
    cam = CameraIntrinsics.from_yaml(tmp_path / "v" / "camera.yaml")
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (W, H, v.intrinsics.fx, v.intrinsics.fy, v.intrinsics.cx, v.intrinsics.cy)
    assert np.array_equal(Cloud.load(tmp_path / "v" / "dense_cloud.npz").points, v.dense.points)
    assert len(Cloud.load(tmp_path / "v" / "cloud.npz")) == W * H
    assert _cli(["sim", "classes"]) == 0
    assert "beach_ball" in capsys.readouterr().out

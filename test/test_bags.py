"""The shipped demo recording and demo models in bags/: they open with both readers, they are
regenerable from the seeded world, and the models obey the model contract and classify the demo."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from pws_ros.sim import CLASS_NAMES, default_intrinsics, render_view
from pws_ros.sim.record import TOPIC_POINTS, TOPICS, read_recording

BAGS = Path(__file__).resolve().parents[1] / "bags"
DEMO = BAGS / "demo"
MODELS = BAGS / "models"
DEMO_FRAMES = 8             # pws sim record --frames 8 --seed 0 --views-per-scene 1 --width 640 --height 480 --no-points
DEMO_SHAPE = (480, 640)     # the camera; its centred 640x360 crop reduced 4x is the models' 160x90 input
DEMO_TOPICS = set(TOPICS) - {TOPIC_POINTS}


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.fail(f"shipped file {path} is missing (rebuild: see bags/README.md)")
    return path


@pytest.fixture(scope="module")
def demo_frames():
    return list(read_recording(_need(DEMO)))


def _model_input(rgb: np.ndarray) -> torch.Tensor:
    """A 640x480 demo frame as the models' 160x90 input, by hand: centred 640x360 crop (rows 60..419),
    mean of each 4x4 block in float64 (plain loops over the 16 offsets), (3, 90, 160) in [0, 1]."""
    assert rgb.shape == DEMO_SHAPE + (3,)
    crop = rgb[60:420].astype(np.float64) / 255.0
    acc = np.zeros((90, 160, 3))
    for dy in range(4):
        for dx in range(4):
            acc += crop[dy::4, dx::4]
    return torch.from_numpy(acc / 16.0).permute(2, 0, 1).float()


def test_shipped_files_are_small():
    total = sum(f.stat().st_size for f in _need(BAGS).rglob("*") if f.is_file())
    assert total < 12e6
    assert sum(f.stat().st_size for f in _need(DEMO).iterdir() if f.is_file()) <= 5e6
    assert (BAGS / "README.md").is_file()
    text = (BAGS / "README.md").read_text()
    for topic in TOPICS:
        assert topic in text
    assert "dense_cloud_for" in text


def test_demo_opens_with_rosbags_and_matches_the_world(demo_frames):
    assert len(demo_frames) == DEMO_FRAMES
    classes = Counter(f.truth["class_name"] for f in demo_frames)
    assert len(classes) == DEMO_FRAMES  # one frame per class
    assert len({f.truth["view_index"] for f in demo_frames}) == DEMO_FRAMES
    assert len({int(f.truth["view_index"]) // 8 for f in demo_frames}) == 3  # all three rings
    stamps = [f.stamp_ns for f in demo_frames]
    assert stamps == sorted(stamps) and len(set(stamps)) == DEMO_FRAMES
    for f in demo_frames:
        assert f.intrinsics.shape == DEMO_SHAPE and f.rgb.shape == DEMO_SHAPE + (3,) and f.depth_m.shape == DEMO_SHAPE
        assert (f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy) == (460.0, 460.0, 319.5, 239.5)
        assert f.points is None and f.point_rgb is None  # recorded with --no-points
        assert (f.truth["width"], f.truth["height"]) == ("640", "480")
        assert (f.depth_m > 0).mean() > 0.99
    # the centred 640x360 crop reduced 4x is the 160x90 camera the models were trained on
    # (a crop shifts the principal point; a k-fold block mean maps pixel edges u -> u / k)
    cam, small = demo_frames[0].intrinsics, default_intrinsics(160, 90)
    assert (cam.fx / 4, cam.fy / 4) == (small.fx, small.fy)
    assert ((cam.cx + 0.5) / 4 - 0.5, (cam.cy - 60 + 0.5) / 4 - 0.5) == (small.cx, small.cy)
    # regenerable: the recorded images are exactly the seeded world's views
    for f in demo_frames[:: max(1, len(demo_frames) // 4)]:
        v = render_view(int(f.truth["scene_seed"]), int(f.truth["view_index"]), 640, 480, dense=False)
        assert np.array_equal(f.rgb, v.rgb)
        assert np.abs(f.depth_m - v.depth).max() <= 0.0005 + 1e-9
        assert f.truth["class_name"] == v.class_name and f.truth["label"] == str(v.label)


def test_demo_opens_with_independent_mcap_reader():
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (path,) = list(_need(DEMO).glob("*.mcap"))
    counts = Counter()
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert all(c.compression == "zstd" for c in reader.get_summary().chunk_indexes)
        for schema, channel, _message, msg in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            assert msg.header.frame_id == "camera_color_optical_frame"
            assert schema.name == TOPICS[channel.topic]
            if schema.name in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"):
                assert (msg.height, msg.width) == DEMO_SHAPE
    assert counts == {t: DEMO_FRAMES for t in DEMO_TOPICS}


@pytest.mark.parametrize("sigma", ["0.25", "0.50"])
def test_shipped_classifier_contract_and_accuracy(sigma, demo_frames):
    from pws_ros.core.model import load_model

    m = load_model(_need(MODELS / f"classifier_sigma{sigma}.pt"))
    assert m.class_names == list(CLASS_NAMES)
    assert m.input_size == (90, 160)
    assert m.meta["sigma"] == pytest.approx(float(sigma))
    assert (MODELS / "classes.txt").read_text().split() == list(CLASS_NAMES)
    x = torch.stack([_model_input(f.rgb) for f in demo_frames])
    y = np.array([int(f.truth["label"]) for f in demo_frames])
    clean = m(x).argmax(1).numpy()
    assert (clean == y).mean() >= 0.85  # demo scenes 0..7 are held out from training (8 frames: at most 1 wrong)
    # smoothed prediction (majority of 32 noisy copies, seeded) on every demo frame
    g = torch.Generator().manual_seed(0)
    s = float(sigma)
    votes = []
    for i in range(len(x)):
        noisy = x[i : i + 1] + s * torch.randn((32,) + tuple(x.shape[1:]), generator=g)
        votes.append(int(torch.bincount(m(noisy).argmax(1), minlength=len(CLASS_NAMES)).argmax()))
    assert (np.array(votes) == y).mean() >= 0.85


def test_shipped_denoiser_reduces_noise(demo_frames):
    from pws_ros.core.model import load_denoiser

    d = load_denoiser(_need(MODELS / "denoiser_sigma0.50.pt"))
    assert d.meta["sigma"] == 0.5
    x = torch.stack([_model_input(f.rgb) for f in demo_frames[:8]])
    g = torch.Generator().manual_seed(1)
    noisy = x + 0.5 * torch.randn(x.shape, generator=g)
    out = d(noisy)
    assert out.shape == x.shape
    assert float(((out - x) ** 2).mean()) < 0.5 * float(((noisy - x) ** 2).mean())


def test_sample_view_matches_the_world():
    import cv2
    import json

    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.cloud import Cloud, cloud_from_rgbd

    d = _need(BAGS / "sample_view")
    info = json.loads((d / "view.json").read_text())
    v = render_view(info["scene_seed"], info["view_index"], info["width"], info["height"], dense=False)
    rgb = cv2.cvtColor(cv2.imread(str(d / "rgb.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(rgb, v.rgb) and info["class_name"] == v.class_name
    cam = CameraIntrinsics.from_yaml(d / "camera.yaml")
    assert (cam.width, cam.height, cam.fx, cam.cx) == (160, 90, v.intrinsics.fx, v.intrinsics.cx)
    cloud = Cloud.load(d / "cloud.npz")
    ref = cloud_from_rgbd(v.depth, v.rgb, v.intrinsics)
    assert np.allclose(cloud.points, ref.points) and np.allclose(cloud.colors, ref.colors)

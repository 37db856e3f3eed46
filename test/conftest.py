"""Shared, generic test fixtures: a small camera, tiny TorchScript-able classifiers, shared data,
and the ``rclpy`` marker (tests needing rclpy skip when it is not installed)."""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest
import torch

from pws_ros.core.camera import CameraIntrinsics

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """``$PWS_SHARED_DATA`` if set, else ``<repo>/../shared/data``."""
    env = os.environ.get("PWS_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def pytest_collection_modifyitems(config, items):
    if importlib.util.find_spec("rclpy") is not None:
        return
    skip = pytest.mark.skip(reason="rclpy (ROS 2 Jazzy) is not installed in this environment")
    for item in items:
        if "rclpy" in item.keywords:
            item.add_marker(skip)


def need_ros() -> None:
    """Skips the calling test unless ROS 2 Jazzy's rclpy, launch and launch_ros are importable (live tests)."""
    for mod in ("rclpy", "launch", "launch_ros"):
        if importlib.util.find_spec(mod) is None:
            pytest.skip(f"{mod} (ROS 2 Jazzy) is not importable: source a ROS 2 Jazzy installation")


def shared_path(*parts: str) -> Path:
    """A path in the shared data folder; skips the calling test when the folder or the path is absent."""
    root = shared_data_dir()
    if not root.is_dir():
        pytest.skip(f"shared data folder {root} is absent (set PWS_SHARED_DATA to use another)")
    p = root.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} is absent from the shared data")
    return p


@pytest.fixture
def small_camera() -> CameraIntrinsics:
    """A 32x24 pinhole camera, ROS convention principal point at the image centre."""
    return CameraIntrinsics(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5, frame_id="test_cam")


# ---- tiny classifiers (TorchScript-able) ---------------------------------------------------

class MeanThresholdNet(torch.nn.Module):
    """Two classes from the mean of one channel: logits ``[t - m, m - t]`` (class 1 iff m > t)."""

    def __init__(self, threshold: float = 0.5, channel: int = 0):
        super().__init__()
        self.threshold = float(threshold)
        self.channel = int(channel)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = x[:, self.channel].mean(dim=(1, 2))
        return torch.stack([self.threshold - m, m - self.threshold], dim=1)


class LinearNet(torch.nn.Module):
    """Global average pooling per channel then a seeded linear layer to ``num_classes`` logits
    (accepts any image size)."""

    def __init__(self, num_classes: int = 3, seed: int = 0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.fc = torch.nn.Linear(3, num_classes)
        with torch.no_grad():
            self.fc.weight.copy_(torch.randn(num_classes, 3, generator=g))
            self.fc.bias.copy_(torch.randn(num_classes, generator=g))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(x.mean(dim=(2, 3)))


class FixedSizeNet(torch.nn.Module):
    """Flattens a fixed ``(3, H, W)`` image into a linear layer (rejects other sizes)."""

    def __init__(self, height: int = 8, width: int = 8, num_classes: int = 2):
        super().__init__()
        self.fc = torch.nn.Linear(3 * height * width, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(x.flatten(1))


@pytest.fixture
def tiny_nets():
    """The module classes above: ``tiny_nets.MeanThresholdNet(...)`` etc."""
    import types

    return types.SimpleNamespace(MeanThresholdNet=MeanThresholdNet, LinearNet=LinearNet, FixedSizeNet=FixedSizeNet)


@pytest.fixture
def make_model_file(tmp_path):
    """Factory: ``make_model_file(module=None, class_names=None, input_size=(24, 32), name='model.pt',
    meta=None) -> Path`` saves a TorchScript model with :func:`pws_ros.core.model.save_model`
    (default: a 2-class MeanThresholdNet) into the test's tmp folder."""
    from pws_ros.core.model import save_model

    def make(module=None, class_names=None, input_size=(24, 32), name="model.pt", meta=None):
        module = module if module is not None else MeanThresholdNet(0.5)
        if class_names is None:
            with torch.no_grad():
                c = module(torch.zeros((1, 3) + tuple(input_size or (32, 32)))).shape[1]
            class_names = [f"c{i}" for i in range(c)]
        return save_model(module, tmp_path / name, class_names, input_size=input_size, meta=meta)

    return make


def camera_motion_rt(axis: str, a: float) -> tuple[list[list[float]], list[float]]:
    """Reference camera motion for brute-force tests, written out from its definition (no production
    import): ``R^T`` (nested lists) and ``t`` such that a point ``P`` is seen at ``P' = R^T (P - t)``."""
    import math

    c, s = math.cos(a), math.sin(a)
    t = [0.0, 0.0, 0.0]
    if axis[0] == "t":
        t["xyz".index(axis[1])] = a
        R = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    elif axis == "rx":
        R = [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    elif axis == "ry":
        R = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    else:
        R = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    return [[R[j][i] for j in range(3)] for i in range(3)], t


def recomputed_p_a_lower(cert) -> list[float]:
    """The p_A bounds of an adaptive-anchors certificate recomputed from what it records (docs/certificate.md,
    "the estimation in looks"), with scipy's Beta quantile: the joint look's bound of ``joint_votes`` of its
    first look at ``alpha * share``, and each anchor's own bound of ``anchor_votes`` of ``anchor_samples`` at
    ``alpha * share / K`` of the look it reached; an anchor's bound is the larger. An independent reference
    for core.sequential."""
    from scipy.stats import beta

    def cp(k, n, level):
        return 0.0 if k == 0 else float(beta.ppf(level, k, n - k + 1))

    b = cert.bounds
    looks, K = b["looks"], len(b["anchors"])
    sizes, shares = looks["sizes"], looks["shares"]
    out = []
    for n_a, k_a in zip(b["anchor_samples"], b["anchor_votes"]):
        p = 0.0
        if looks["joint"] and n_a >= sizes[0]:
            p = cp(b["joint_votes"], sizes[0], cert.alpha * shares[0])
        for look, size in enumerate(sizes):
            if n_a == size and not (looks["joint"] and look == 0):
                p = max(p, cp(k_a, size, cert.alpha * shares[look] / K))
        out.append(p)
    return out


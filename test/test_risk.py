"""The risk of a frame's certificate (all its axes together) is at most the configured alpha.

A classifier with a known p_A: it thresholds the mean of the noisy image, and every rendered frame
is the same uniform grey, so class 1 has probability p = Phi((0.5 - t) / (sigma / sqrt(#values))) at
every pose, computed here in closed form. A frame's statement is wrong when any p_A lower bound it
used (any anchor, any axis) exceeds the true probability of its label. Over many frames (each with
its own noise seeds) the rate of wrong frames must stay within a binomial tolerance of alpha.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from conftest import MeanThresholdNet
from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.engine import FrameCertifier
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import cloud_from_rgbd

CAM = CameraIntrinsics(8, 6, 8.0, 8.0, 3.5, 2.5, "cam")
SIGMA, THRESHOLD, ALPHA = 0.5, 0.45, 0.2


def test_joint_failure_rate_of_a_frame_is_at_most_alpha(make_model_file):
    path = make_model_file(MeanThresholdNet(THRESHOLD), input_size=(3, 4))
    cfg = config_from_params({"model_path": str(path), "axes": ["tz", "ry"], "n0": 16, "n": 48, "alpha": ALPHA,
                              "sigma": SIGMA, "background": 0.5, "radius.tz": 0.001, "radius.ry": 0.001})
    eng = FrameCertifier(cfg, log=lambda *a: None)
    cloud = cloud_from_rgbd(np.ones(CAM.shape), np.full(CAM.shape + (3,), 0.5, np.float32), CAM)
    sd = SIGMA / math.sqrt(3 * 4)  # the mean of channel 0 over the 4x3 image the model sees
    p_true = {1: float(norm.cdf((0.5 - THRESHOLD) / sd)), 0: float(norm.cdf((THRESHOLD - 0.5) / sd))}
    frames, wrong, wrong_axis = 250, 0, {"tz": 0, "ry": 0}
    seeds = set()
    for k in range(frames):
        certs = eng.process(cloud, CAM, 1_700_000_000_000_000_000 + k * 33_000_000).certificates
        assert [c.alpha for c in certs] == [pytest.approx(ALPHA / 2)] * 2 and all(c.frame_alpha == ALPHA for c in certs)
        bad = [any(p > p_true[c.label] for p in c.p_a_lower) for c in certs]
        wrong += any(bad)
        for c, b in zip(certs, bad):
            wrong_axis[c.axis] += b
        seeds.update(c.seed for c in certs)
    assert len(seeds) == 2 * frames  # independent noise for every frame and axis
    tol = 3 * math.sqrt(ALPHA * (1 - ALPHA) / frames)
    assert wrong / frames <= ALPHA + tol, (wrong, wrong_axis)
    for axis, count in wrong_axis.items():  # each axis spends half of it
        assert count / frames <= ALPHA / 2 + 3 * math.sqrt(ALPHA / 2 * (1 - ALPHA / 2) / frames), (axis, count)
    assert wrong > 0  # the bounds are not vacuous: at this alpha some frames do fail

"""A time budget per frame (pws_ros.bridge.budget, FrameCertifier with time_budget_s): the sizing
arithmetic (never above the share given the cost model, never above the configured sizes, a function of
the budget and the measured costs only), the sizes fixed before any sample is drawn, 0 = off and a budget
that fits leave certificates unchanged, and a deliberately slow classifier keeps a frame within its budget."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
import torch

from pws_ros.bridge import budget as B
from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.engine import FrameCertifier
from pws_ros.core.cloud import cloud_from_rgbd
from pws_ros.core.model import LoadedModel

CONF = dict(n0=64, n=256, num_anchors=24, max_partitions=257, batch_size=64)


def costs(batch=0.01, image=1e-4, point=0.02, fixed=0.05) -> B.CostModel:
    return B.CostModel(batch_s=batch, image_s=image, point_s=point, fixed_s=fixed)


def predicted(c: B.CostModel, s: B.Sizes, per_point=False) -> float:
    anchors = s.max_partitions if per_point else s.num_anchors
    return c.axis_s(s.n0, anchors, s.n, s.max_partitions, CONF["batch_size"])


def test_a_share_that_fits_keeps_the_configured_sizes():
    c = costs()
    full = predicted(c, B.Sizes(64, 24, 256, 257, 0, 0, False, True))
    s = B.size_axis(full / B.SAFETY + 1e-9, c, **CONF)
    assert (s.n0, s.num_anchors, s.n, s.max_partitions, s.reduced, s.fits) == (64, 24, 256, 257, False, True)
    s = B.size_axis(full / B.SAFETY * 0.99, c, **CONF)   # just below: reduced
    assert s.reduced and s.fits and predicted(c, s) <= B.SAFETY * s.share_s


@pytest.mark.parametrize("per_point", [False, True])
def test_sizes_never_exceed_the_share_nor_the_configuration(per_point):
    rng = np.random.default_rng(0)
    fitted = 0
    for _ in range(300):
        c = costs(*(10.0 ** rng.uniform(-5, -1, 4)))
        conf = dict(n0=int(rng.integers(1, 200)), n=int(rng.integers(1, 2000)), num_anchors=int(rng.integers(1, 40)),
                    max_partitions=int(rng.integers(3, 400)), batch_size=int(rng.integers(1, 512)))
        share = float(10.0 ** rng.uniform(-2, 2))
        s = B.size_axis(share, c, per_point=per_point, **conf)
        assert 1 <= s.num_anchors <= conf["num_anchors"] and 1 <= s.n <= conf["n"]
        assert min(B.MIN_N0, conf["n0"]) <= s.n0 <= conf["n0"]
        assert B.MIN_POINTS <= s.max_partitions <= max(B.MIN_POINTS, conf["max_partitions"])
        anchors = s.max_partitions if per_point else s.num_anchors
        cost = c.axis_s(s.n0, anchors, s.n, s.max_partitions, conf["batch_size"])
        assert cost == pytest.approx(s.predicted_s)
        if s.fits:
            fitted += 1
            assert cost <= B.SAFETY * share * (1 + 1e-12)
        else:  # even the least work is above the share: the axis is not started
            least_anchors = conf["num_anchors"] if per_point else 1   # per_point: the grid frames are the estimates
            least = (min(B.MIN_N0, conf["n0"]), least_anchors, 1, B.MIN_POINTS)
            assert (s.n0, s.num_anchors, s.n, s.max_partitions) == least and cost > B.SAFETY * share
        assert B.size_axis(share, c, per_point=per_point, **conf) == s   # a function of its arguments only
    assert 30 < fitted < 300


def test_a_smaller_share_never_buys_more_work():
    c = costs()
    prev = None
    for share in np.geomspace(20.0, 0.5, 40):
        s = B.size_axis(float(share), c, **CONF)
        work = s.num_anchors * s.n
        if prev is not None:
            assert work <= prev[0] and s.max_partitions <= prev[1] and s.n0 <= prev[2]
        prev = (work, s.max_partitions, s.n0)
    assert prev[0] < 24 * 256 and prev[1] < 257 and prev[2] < 64


def test_the_call_count_bounds_the_weak_frame_branch():
    # the weak-frame branch spends num_anchors * n samples of one frame: never more calls than the anchors' sharing
    c = B.CostModel()
    for bs in (1, 7, 64, 256, 1000):
        for a in (1, 3, 24):
            for n in (1, 50, 256, 999):
                assert math.ceil(a * n / bs) <= c.batches(0, a, n, bs) - 0


def test_the_cost_model_moves_towards_what_it_observes():
    c = costs(batch=0.01, image=1e-3, point=0.02, fixed=0.1)

    class Cert:
        n0, num_bounds, classifier_calls, frames_rendered = 64, 4, 64 + 4 * 256, 40
        bounds = {"frontier_splits": 0}
        timings = {"inference": 0.0, "render": 0.1, "bounds": 0.1, "statistics": 0.0}

    Cert.timings["inference"] = 0.5 * c.inference_s(64, 4, 256, 64)   # twice as fast as predicted
    before = dataclasses.asdict(c)
    wall = 0.2 + Cert.timings["inference"] + 0.3
    # the first axis replaces the warm-up's figures: the calls twice as fast, 0.2 s for 40 points, 0.3 s fixed
    c.observe(Cert, wall_s=wall, batch_size=64)
    assert c.image_s == pytest.approx(0.5 * before["image_s"]) and c.batch_s == pytest.approx(0.5 * before["batch_s"])
    assert c.point_s == pytest.approx(0.2 / 40) and c.fixed_s == pytest.approx(0.3)
    assert c.updates == 1 and c.fine_updates == 1 and c.coarse_updates == 0
    # later axes are averaged in (EMA_WEIGHT): an axis with twice the geometry and fixed time
    Cert.timings = dict(Cert.timings, render=0.2, bounds=0.2)
    Cert.timings["inference"] = c.inference_s(64, 4, 256, 64)      # as predicted now
    c.observe(Cert, wall_s=0.4 + Cert.timings["inference"] + 0.6, batch_size=64)
    assert c.image_s == pytest.approx(0.5 * before["image_s"])
    assert c.point_s == pytest.approx((1 - B.EMA_WEIGHT) * 0.2 / 40 + B.EMA_WEIGHT * 0.4 / 40)
    assert c.fixed_s == pytest.approx((1 - B.EMA_WEIGHT) * 0.3 + B.EMA_WEIGHT * 0.6)
    assert c.updates == 2


# ---- the engine ---------------------------------------------------------------------------

def box_scene(intr, seed=0):
    h, w = intr.height, intr.width
    depth = np.full((h, w), 2.0)
    depth[h // 4: 3 * h // 4, w // 4: 5 * w // 8] = 1.2
    rgb = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgb[..., 0] = 230
    return cloud_from_rgbd(depth, rgb, intr)


FAST = {"n0": 16, "n": 32, "batch_size": 64, "axes": ["tz", "ry"]}


def test_zero_is_off_and_a_budget_that_fits_changes_no_certificate(make_model_file, small_camera):
    path = str(make_model_file(input_size=(24, 32)))
    cloud = box_scene(small_camera)
    off = FrameCertifier(config_from_params({**FAST, "model_path": path}), log=lambda *a: None)
    ample = FrameCertifier(config_from_params({**FAST, "model_path": path, "time_budget_s": 3600.0}), log=lambda *a: None)
    for stamp in (5, 6):
        a = off.process(cloud, small_camera, stamp).certificates
        b = ample.process(cloud, small_camera, stamp).certificates
        for x, y in zip(a, b):
            assert x.status != "error", x.reason
            assert "time_budget" not in x.bounds and "budget" not in x.timings
            tb = y.bounds["time_budget"]
            assert tb["reduced"] is False and (tb["num_anchors"], tb["n"]) == (24, 32) and tb["frame_budget_s"] == 3600.0
            assert 0 < tb["spent_s"] < tb["share_s"] and y.timings["budget"] == tb["share_s"]
            assert (x.p_a_lower, x.radius, x.label, x.n, x.classifier_calls, x.num_partitions) == \
                   (y.p_a_lower, y.radius, y.label, y.n, y.classifier_calls, y.num_partitions)
    assert ample.budget.costs.ready and ample.budget.costs.updates == 4


def test_sizes_are_fixed_before_any_sample_is_drawn(make_model_file, small_camera, monkeypatch):
    from pws_ros.core import smoothing

    path = str(make_model_file(input_size=(24, 32)))
    eng = FrameCertifier(config_from_params({"n0": 16, "n": 100_000, "batch_size": 64, "axes": ["tz", "ry"], "model_path": path,
                                             "time_budget_s": 4.0}), log=lambda *a: None)
    eng.budget.costs = costs(batch=1e-3, image=3e-4, point=0.02, fixed=0.1)   # a known (slowish) machine
    events = []
    size_for = eng.budget.size

    def sized(share, *a, **k):
        s = size_for(share, *a, **k)
        events.append(("sized", s))
        return s

    real = smoothing.SmoothedClassifier.sample_counts
    real_votes = smoothing.SmoothedClassifier.common_votes

    def counted(self, frames, num, *a, **k):
        events.append(("sample", int(num)))
        return real(self, frames, num, *a, **k)

    def counted_votes(self, frames, num, *a, **k):
        events.append(("sample", int(num)))
        return real_votes(self, frames, num, *a, **k)

    monkeypatch.setattr(eng.budget, "size", sized)
    monkeypatch.setattr(smoothing.SmoothedClassifier, "sample_counts", counted)
    monkeypatch.setattr(smoothing.SmoothedClassifier, "common_votes", counted_votes)
    res = eng.process(box_scene(small_camera), small_camera, 7)
    kinds = [e[0] for e in events]
    assert kinds[0] == "sized" and kinds.count("sized") == 2
    second = kinds.index("sized", 1)
    for (start, stop), cert in zip(((0, second), (second, len(events))), res.certificates):
        s = events[start][1]
        assert s.reduced and s.n < 100_000 and cert.status != "error", cert.reason
        samples = [e[1] for e in events[start + 1:stop]]
        assert samples[0] == s.n0 and all(k <= s.num_anchors * s.n for k in samples[1:])   # the sized n0, then n
        K = len(cert.bounds["anchors"])
        spread = s.num_anchors * s.n // K if cert.bounds["spread_estimation"] else s.n   # CertifyConfig.spread_estimation
        looks = cert.bounds["looks"]["sizes"]   # the joint first look of min(n_first, n), then n (core.sequential)
        assert cert.n in {spread, s.n * s.num_anchors, *looks} and cert.bounds["time_budget"]["n"] == s.n
        assert looks[-1] in (spread, s.n, s.n * s.num_anchors)


class SlowNet(torch.nn.Module):
    """MeanThresholdNet on the red channel that sleeps ``delay`` seconds per call (a slow classifier)."""

    def __init__(self, delay: float):
        super().__init__()
        self.delay = delay

    def forward(self, x):
        time.sleep(self.delay)
        m = x[:, 0].mean(dim=(1, 2))
        return torch.stack([0.5 - m, m - 0.5], dim=1)


def test_a_slow_classifier_keeps_each_frame_within_its_budget(small_camera):
    model = LoadedModel(SlowNet(0.05), ["c0", "c1"], (24, 32), "slow")   # time mostly asleep: robust to a busy machine
    # 6 s: the least work of an axis (the geometry of 3 grid points and one call) fits its share with room
    # even on a loaded machine (at 3 s and load 5 the measured geometry alone filled the share: an ERROR)
    budget = 6.0
    cfg = config_from_params({"n0": 64, "n": 256, "batch_size": 64, "axes": ["tz", "ry"], "time_budget_s": budget})
    eng = FrameCertifier(cfg, log=lambda *a: None, model=model)
    # the configured work: 64 + 24 * 256 samples = 97 calls per axis, about 5 s of sleep alone on each axis
    assert eng.budget.costs.inference_s(64, 24, 256, 64) > budget / 2   # measured by the warm-up at start
    cloud = box_scene(small_camera)
    for stamp in range(2):
        t0 = time.perf_counter()
        res = eng.process(cloud, small_camera, stamp)
        wall = time.perf_counter() - t0 - res.timings.get("startup", 0.0)   # start-up work (the warm-ups) is not the frame's
        assert wall <= 1.1 * budget and res.timings["total"] <= 1.1 * budget, (wall, [c.bounds.get("time_budget") for c in res.certificates])
        for c in res.certificates:
            tb = c.bounds["time_budget"]
            assert c.status != "error", c.reason
            assert tb["reduced"] and tb["num_anchors"] * tb["n"] < 24 * 256
            assert c.classifier_calls <= tb["n0"] + tb["num_anchors"] * tb["n"] and c.n0 == tb["n0"]
        # each axis' share is what the axes before it left of the frame's budget (split over the axes to come)
        spent = 0.0
        for k, c in enumerate(res.certificates):
            tb = c.bounds["time_budget"]
            assert tb["share_s"] <= (budget - spent) / (len(res.certificates) - k) + 1e-9
            spent += tb["spent_s"]
    assert any(c.radius > 0 for c in res.certificates)


def test_a_budget_below_the_least_work_answers_over_budget(small_camera):
    """Lack of time alone is never an ERROR: the least work of the coarsest level runs, flagged over budget
    with the time it took, and the message states the numbers it compares (correctly)."""
    model = LoadedModel(SlowNet(0.05), ["c0", "c1"], (24, 32), "slow")
    eng = FrameCertifier(config_from_params({"n0": 64, "n": 256, "batch_size": 64, "axes": ["tz"], "time_budget_s": 0.05}),
                         log=lambda *a: None, model=model)
    (c,) = eng.process(box_scene(small_camera), small_camera, 1).certificates
    tb = c.bounds["time_budget"]
    assert c.status != "error", c.reason
    assert tb["fits"] is False and tb["over_budget"] is True and tb["spent_s"] > tb["share_s"]
    assert (tb["n0"], tb["num_anchors"], tb["n"], tb["max_partitions"]) == (B.MIN_N0, 1, B.answer_n(eng.config.alpha), B.MIN_POINTS)
    assert tb["frontier_rounds"] == 0 and tb["coarsened"] is True   # 32x24 at factor 1: only the frontier to coarsen
    assert tb["predicted_s"] > tb["target_s"] == pytest.approx(B.SAFETY * tb["share_s"])
    assert f"took {tb['spent_s']:.3g} s of this axis' {tb['share_s']:.3g} s share" in c.reason
    assert f"predicted at {tb['predicted_s']:.3g} s, more than the {tb['target_s']:.3g} s" in c.reason
    assert c.classifier_calls <= tb["n0"] + tb["n"]


def test_a_slow_geometry_is_coarsened_and_still_answers(monkeypatch):
    """A configured geometry far too slow for the share (a cost model saying 5 s a grid point at render
    factor 2): the axis runs at render factor 1 (measured by its own warm-up), records that imaging and
    the level, and answers within its share; the warm-ups are start-up work, not charged to the frame."""
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.bridge.sizing import FrameBudget
    from conftest import MeanThresholdNet

    cam = CameraIntrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5, frame_id="cam")
    model = LoadedModel(MeanThresholdNet(0.5), ["c0", "c1"], (24, 32), "m")
    eng = FrameCertifier(config_from_params({"n0": 16, "n": 64, "batch_size": 64, "axes": ["tz", "ry"], "time_budget_s": 8.0}),
                         log=lambda *a: None, model=model)
    real = FrameBudget.warm_up_geometry
    warmed = []

    def slow_configured(self, cloud, imaging, axis, dense_cloud=None, coarse=False, timed=True):
        real(self, cloud, imaging, axis, dense_cloud, coarse, timed)
        time.sleep(0.5)   # a slow warm-up: start-up work, never in the frame's budget or time
        warmed.append((imaging.factor, coarse))
        if timed and not coarse:
            self.costs.set_geometry(0.1, 5.0)

    monkeypatch.setattr(FrameBudget, "warm_up_geometry", slow_configured)
    res = eng.process(box_scene(cam), cam, 3)
    assert warmed == [(2, False), (2, False), (1, True), (1, True)]   # measured on tz; ry's lazy initialisation paid too
    assert res.timings["startup"] >= 1.0 and res.timings["total"] < 8.0
    for c in res.certificates:
        tb = c.bounds["time_budget"]
        assert c.status != "error", c.reason
        assert tb["coarsened"] and tb["render_factor"] == 1 and c.bounds["imaging"]["factor"] == 1
        assert c.bounds["imaging"]["decimate"] == 2 and tb["fits"] and tb["share_s"] > (8.0 - 1.0) / 2
    assert any(c.radius > 0 for c in res.certificates)
    assert eng.budget.costs.coarse_point_s < 5.0 and eng.budget.costs.point_s == pytest.approx(5.0)   # each level learns its own


def test_a_reduced_budget_spends_its_estimation_samples_on_the_anchors_placed(small_camera, monkeypatch):
    """Under a budget that shrinks the work, the num_anchors * n estimation samples it sized go to the K
    anchors placed (n = num_anchors * n // K), in one call made after the placement; the sizes and the
    Bonferroni K are those of the certificate."""
    from pws_ros.core import smoothing
    from conftest import MeanThresholdNet

    model = LoadedModel(MeanThresholdNet(0.5), ["c0", "c1"], (24, 32), "m")
    eng = FrameCertifier(config_from_params({"n0": 16, "n": 2000, "batch_size": 64, "axes": ["tz", "ry"], "time_budget_s": 4.0}),
                         log=lambda *a: None, model=model)
    eng.budget.costs = costs(batch=1e-3, image=3e-4, point=0.02, fixed=0.1)   # a known (slowish) machine: the sizes shrink
    # as if observed already: the axes are averaged in (EMA_WEIGHT), not put in place of these figures
    eng.budget.costs.updates = eng.budget.costs.fine_updates = eng.budget.costs.coarse_updates = 1
    calls = []
    real = smoothing.SmoothedClassifier.sample_counts
    real_votes = smoothing.SmoothedClassifier.common_votes
    monkeypatch.setattr(smoothing.SmoothedClassifier, "sample_counts",
                        lambda self, frames, num, *a, **k: calls.append((len(frames), int(num))) or real(self, frames, num, *a, **k))
    monkeypatch.setattr(smoothing.SmoothedClassifier, "common_votes",
                        lambda self, frames, num, *a, **k: calls.append((len(frames), int(num))) or real_votes(self, frames, num, *a, **k))
    for cert in eng.process(box_scene(small_camera), small_camera, 7).certificates:
        tb = cert.bounds["time_budget"]
        K = len(cert.bounds["anchors"])
        assert tb["reduced"] and cert.status != "error", cert.reason
        assert cert.bounds["spread_estimation"] is True and cert.radius < eng.config.radius_for(cert.axis)   # short of the request
        assert cert.n == tb["num_anchors"] * tb["n"] // K > tb["n"]
        assert (K, cert.n) in calls and cert.classifier_calls == tb["n0"] + K * cert.n


def test_spreading_is_off_by_default_and_where_the_anchors_reach(small_camera):
    """The core's rule (CertifyConfig.spread_estimation): off, n per anchor; on, n_est = num_anchors * n // K
    only where the placed anchors are predicted to fall short of the radius (a frame they cover pays n)."""
    from conftest import MeanThresholdNet
    from pws_ros.core.certify import CertifyConfig, certify

    model = LoadedModel(MeanThresholdNet(0.5), ["c0", "c1"], (24, 32), "m")
    cloud = box_scene(small_camera)
    base = CertifyConfig(sigma=0.5, n0=16, n=100, num_anchors=5, batch_size=64, max_partitions=9, n_first=0)   # n per anchor
    off = certify(cloud, small_camera, model, "tz", 0.05, config=base)
    on = certify(cloud, small_camera, model, "tz", 0.05, config=dataclasses.replace(base, spread_estimation=True))
    assert off.n == 100 and off.bounds["spread_estimation"] is False
    K = len(on.bounds["anchors"])
    assert on.bounds["spread_estimation"] is True and on.n == 5 * 100 // K > 100 and on.classifier_calls == 16 + K * on.n
    near = certify(cloud, small_camera, model, "tz", 1e-5, config=dataclasses.replace(base, spread_estimation=True))
    assert near.radius == pytest.approx(1e-5) and near.bounds["spread_estimation"] is False and near.n == 100


def test_the_levels_coarsen_in_order_and_fall_back_to_the_configured_imaging():
    """size_work: the configured geometry while its least work fits, then render factor 1, then fewer frontier
    rounds; a coarse imaging not measured keeps the configured one (with fewer rounds); nothing fits: the
    least work of the last level, fits False. A function of its arguments only."""
    c = costs(batch=0.01, image=0.01, point=0.5, fixed=0.2)
    c.coarse_point_s, c.coarse_fixed_s = 0.1, 0.1
    conf = dict(CONF, min_n=8)
    order = []
    for share in (200.0, 20.0, 6.0, 3.0, 1.0, 0.1):
        s = B.size_work(share, c, can_coarsen=True, **conf)
        order.append((s.coarse, s.frontier_rounds, s.fits))
        assert s == B.size_work(share, c, can_coarsen=True, **conf)
        if s.fits:
            assert s.predicted_s <= B.SAFETY * share
    assert order[0] == (False, 4, True) and order[-1] == (True, 0, False)
    assert order == sorted(order, key=lambda o: (o[0], -o[1], not o[2]))   # never back to a finer level for less time
    assert any(o[:2] == (True, 4) for o in order)
    unmeasured = costs(batch=0.01, image=0.01, point=0.5, fixed=0.2)
    s = B.size_work(12.0, unmeasured, can_coarsen=True, **conf)
    assert not s.coarse and s.fits and s.frontier_rounds < 4
    assert B.size_work(12.0, c, can_coarsen=False, **conf).coarse is False

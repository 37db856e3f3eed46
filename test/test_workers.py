"""Several pipeline workers on one input stream (pws_ros.bridge.workers): every stamp goes to exactly
one worker under both rules, the thread split, and certificates that do not depend on which worker
makes them (the pipeline nodes themselves: test_nodes_logic.py::test_two_pipeline_workers_*)."""
from __future__ import annotations

import numpy as np
import pytest

from pws_ros.bridge.config import config_from_params
from pws_ros.bridge.engine import FrameCertifier
from pws_ros.bridge.workers import StampAssignment, splitmix64, threads_per_worker
from pws_ros.core.cloud import cloud_from_rgbd
from pws_ros.core.errors import PwsError

T0 = 1_700_000_000_000_000_000


@pytest.mark.parametrize("period_ns", [0, 33_333_333, 100_000_000])
@pytest.mark.parametrize("workers", [1, 2, 3, 7])
def test_every_stamp_goes_to_exactly_one_worker(workers, period_ns):
    rng = np.random.default_rng(workers)
    stamps = np.concatenate([T0 + np.arange(500) * 33_333_333 + rng.integers(-2_000_000, 2_000_000, 500),
                             rng.integers(0, 2**62, 500), np.arange(50)])
    each = [StampAssignment(workers, i, period_ns) for i in range(workers)]
    for s in stamps.tolist():
        owners = [i for i, a in enumerate(each) if a.mine(s)]
        assert owners == [each[0].worker_of(s)] and 0 <= owners[0] < workers
        assert StampAssignment(workers, 0, period_ns).worker_of(s) == owners[0]   # a pure function of the stamp
    counts = np.bincount([each[0].worker_of(s) for s in stamps.tolist()], minlength=workers)
    assert counts.min() > 0.6 * len(stamps) / workers   # no worker starves


def test_the_period_rule_is_a_round_robin_on_a_regular_camera():
    a = StampAssignment(2, 0, 100_000_000)
    stamps = [T0 + k * 100_000_000 + 1_000 for k in range(20)]   # 10 Hz, as bags/demo
    owners = [a.worker_of(s) for s in stamps]
    assert owners[0::2] == [owners[0]] * 10 and owners[1::2] == [1 - owners[0]] * 10
    assert len({splitmix64(s) % 2 for s in stamps}) == 2   # the hash rule splits them too (not in turn)


def test_bad_assignments_are_refused():
    for args in ((0, 0, 0), (2, 2, 0), (2, -1, 0), (2, 0, -5)):
        with pytest.raises(PwsError):
            StampAssignment(*args)
    with pytest.raises(PwsError, match="worker_index 2 must be below num_workers 2"):
        config_from_params({"num_workers": 2, "worker_index": 2})
    a = StampAssignment.from_config(config_from_params({"num_workers": 3, "worker_index": 1, "worker_period_s": 0.1}))
    assert (a.num_workers, a.worker_index, a.period_ns) == (3, 1, 100_000_000)


def test_threads_per_worker():
    assert [threads_per_worker(n, 16) for n in (1, 2, 3, 4, 16, 40)] == [16, 8, 5, 4, 1, 1]
    assert threads_per_worker(2, 2) == 1 and threads_per_worker(1, 2) == 2


def test_certificates_do_not_depend_on_the_worker(make_model_file, small_camera):
    """Two workers, each certifying its own stamps, give the certificates one worker gives for them."""
    path = str(make_model_file(input_size=(24, 32)))
    base = {"n0": 16, "n": 32, "batch_size": 64, "axes": ["tz", "ry"], "model_path": path, "worker_period_s": 0.1}
    h, w = small_camera.height, small_camera.width

    def frame(k):
        depth = np.full((h, w), 2.0)
        depth[6:18, 8 + k:20 + k] = 1.2
        rgb = np.random.default_rng(k).integers(0, 256, (h, w, 3), dtype=np.uint8)
        rgb[..., 0] = 200 + 10 * k
        return cloud_from_rgbd(depth, rgb, small_camera)

    stamps = [T0 + k * 100_000_000 for k in range(4)]
    single = FrameCertifier(config_from_params(base), log=lambda *a: None)
    workers = [FrameCertifier(config_from_params({**base, "num_workers": 2, "worker_index": i}), log=lambda *a: None)
               for i in range(2)]
    made = {}
    for k, s in enumerate(stamps):
        mine = [wk for wk in workers if StampAssignment.from_config(wk.config).mine(s)]
        assert len(mine) == 1
        made[s] = mine[0].process(frame(k), small_camera, s).certificates
    assert {StampAssignment.from_config(wk.config).worker_of(s) for s in stamps for wk in workers[:1]} == {0, 1}
    for k, s in enumerate(stamps):
        ref = single.process(frame(k), small_camera, s).certificates
        for a, b in zip(ref, made[s]):
            assert a.status != "error", a.reason
            ja, jb = a.to_dict(), b.to_dict()
            ja.pop("timings"), jb.pop("timings")
            assert ja == jb

"""pws_ros.bench.throughput on a tiny recording: the frames of a bag as the replay assembles them, the
looped stamps, two worker processes splitting the stamps with the pipeline's rule (each stamp once,
certificates equal to one worker's), and the budget table's rows."""
from __future__ import annotations

import pytest

from pws_ros.bench import throughput as TP
from pws_ros.bridge.config import config_from_params


@pytest.fixture(scope="module")
def setup(tmp_path_factory, make_model_file_module):
    from pws_ros.sim.record import record

    bag = record(tmp_path_factory.mktemp("bags") / "sim", frames=3, width=32, height=24, views_per_scene=1)
    cfg = config_from_params({"model_path": str(make_model_file_module), "axes": ["tz"], "radius.tz": 0.002, "n0": 16, "n": 32})
    return bag, cfg


@pytest.fixture(scope="module")
def make_model_file_module(tmp_path_factory):
    import torch

    from pws_ros.core.model import save_model
    from pws_ros.sim import CLASS_NAMES

    class Net(torch.nn.Module):
        def forward(self, x):
            m = x.mean(dim=(2, 3))
            return torch.cat([m, torch.zeros(x.shape[0], len(CLASS_NAMES) - 3)], dim=1)

    return save_model(Net(), tmp_path_factory.mktemp("m") / "m.pt", list(CLASS_NAMES), input_size=(24, 32))


def test_bag_frames_and_loops(setup):
    bag, cfg = setup
    frames = TP.bag_frames(bag, cfg)
    assert len(frames) == 3 and [f[0] for f in frames] == sorted(f[0] for f in frames)
    assert all(len(f[1]) > 0 and f[2].width == 32 for f in frames)
    loop = TP.looped(frames, 3)
    stamps = [f[0] for f in loop]
    assert len(stamps) == 9 and len(set(stamps)) == 9 and stamps == sorted(stamps)
    assert TP.bag_frames(bag, cfg, max_frames=2)[-1][0] == frames[1][0]


def test_two_workers_split_the_stamps_and_agree_with_one(setup):
    bag, cfg = setup
    frames = TP.looped(TP.bag_frames(bag, cfg), 2)
    period = frames[1][0] - frames[0][0]
    one = TP.run_workers(cfg, frames, 1, period)
    two = TP.run_workers(cfg, frames, 2, period)
    assert one["frames"] == two["frames"] == 6
    assert [n for _i, _w, n, _t in two["per_worker"]] == [3, 3]   # the round robin on the frame period
    assert two["certs"] == one["certs"]
    assert all(c[0]["status"] != "error" for c in one["certs"].values())


def test_budget_rows(setup):
    bag, cfg = setup
    rows = TP.budget_rows(cfg, TP.bag_frames(bag, cfg, max_frames=1), 30.0)
    (row,) = rows
    assert row["axis"] == "tz" and row["none"]["share_s"] is None and row["budget"]["share_s"] > 0
    assert row["budget"]["radius"] == row["none"]["radius"]   # an ample budget keeps the configured sizes

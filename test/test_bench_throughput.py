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


def test_live_mode_without_rclpy_says_so(monkeypatch, capsys):
    """``--live`` needs ROS 2: without rclpy it exits 2 with the one-line reason (before reading the bag)."""
    from pws_ros.nodes import _common

    monkeypatch.setattr(_common, "rclpy_available", lambda: False)
    assert TP.main(["--live", "--seconds", "1"]) == 2
    assert "--live: rclpy (ROS 2 Jazzy) is not importable" in capsys.readouterr().err


def test_live_certificate_values_leave_out_timings_and_worker(tmp_path):
    """Two workers' certificates of one stamp compare equal on what they state, whatever their timings
    and node (what ``--live`` compares across runs)."""
    from pws_ros.bridge import msgbuild
    from pws_ros.nodes.live import CERT_COMPARED, certificate_values

    T = msgbuild.rosbags_types()
    statuses = []
    for node, ms in (("/pipeline_0", "12.5"), ("/pipeline_1", "99.0")):
        values = [T.KeyValue(key=k, value="1") for k in msgbuild.DIAGNOSTIC_KEYS]
        values = [T.KeyValue(key=kv.key, value=ms if kv.key in ("latency_ms", "compute_ms") else kv.value) for kv in values]
        values.append(T.KeyValue(key="node", value=node))
        statuses.append(T.DiagnosticArray(header=msgbuild.make_header(T, 5, "cam"), status=[
            T.DiagnosticStatus(level=0, name="pws/tz", message="m", hardware_id="cam", values=values)]))
    a, b = (certificate_values(s) for s in statuses)
    assert a == b and set(a["tz"]) == set(CERT_COMPARED)


def test_budget_zero_skips_the_budget_comparison(setup, tmp_path, capsys):
    """--budget 0: the workers alone (it crashed with a KeyError); a negative budget is refused by name."""
    import yaml

    bag, cfg = setup
    conf = tmp_path / "c.yaml"
    conf.write_text(yaml.safe_dump({"pipeline": {"ros__parameters": {"model_path": cfg.model_path, "axes": ["tz"],
                                                                     "radius.tz": 0.002, "n0": 16, "n": 32}}}))
    assert TP.main([str(bag), "--workers", "1", "--loops", "1", "--budget", "0", "--config", str(conf)]) == 0
    out = capsys.readouterr().out
    assert "frames/min" in out and "time budget" not in out
    assert TP.main([str(bag), "--budget", "-1", "--config", str(conf)]) == 2
    assert "--budget must be >= 0" in capsys.readouterr().err

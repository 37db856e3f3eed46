"""``pws replay``: offline certification of rosbag2 recordings, the result bag, the summary, the
report, the realtime policy, and bad recordings (synthetic and real)."""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import LinearNet, shared_path
from pws_ros.bagio import BagReader, mcap_decoded_messages
from pws_ros.bridge import msgbuild, msgconv
from pws_ros.bridge.msgbuild import DIAGNOSTIC_KEYS, parse_certification
from pws_ros.commands import replay as cmd
from pws_ros.core.errors import PwsError
from pws_ros.replay import RealtimeScheduler, ReplayOptions, default_out, replay
from pws_ros.sim import CLASS_NAMES

TINY = ["--axes", "tz", "--radius", "tz=2mm", "--n0", "16", "--n", "32", "--quiet"]
TIMING_KEYS = {"latency_ms", "compute_ms"}
TOPIC_COLOR = "/camera/color/image_raw"
TOPIC_DEPTH = "/camera/aligned_depth_to_color/image_raw"
TOPIC_INFO = "/camera/color/camera_info"
TOPIC_POINTS = "/camera/depth/color/points"
TOPIC_TRUTH = "/pws/ground_truth"


class ConstNet(torch.nn.Module):
    """Always the same class (logits independent of the image): p_A = 1 for that class."""

    def __init__(self, num_classes: int, k: int):
        super().__init__()
        self.register_buffer("bias", torch.nn.functional.one_hot(torch.tensor(k), num_classes).float() * 10.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(1, 2, 3))[:, None] * 0.0 + self.bias[None, :]


# ---- fixtures ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def models(tmp_path_factory):
    from pws_ros.core.model import save_model

    d = tmp_path_factory.mktemp("models")
    names = list(CLASS_NAMES)
    return {
        "linear": save_model(LinearNet(len(names), seed=1), d / "linear.pt", names, input_size=(24, 32)),
        "const1": save_model(ConstNet(len(names), 1), d / "const1.pt", names, input_size=(24, 32)),
    }


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    """3 frames of the procedural world, 32x24, scenes 0, 1, 2 (classes 0, 1, 2), with ground truth."""
    from pws_ros.sim.record import record

    return record(tmp_path_factory.mktemp("bags") / "sim", frames=3, width=32, height=24, views_per_scene=1)


@pytest.fixture(scope="module")
def sim_msgs(sim_bag):
    """(topic, msgtype, log_time, decoded, raw bytes) of the sim bag, in log order."""
    with BagReader(sim_bag) as bag:
        return [(m.topic, m.msgtype, m.log_time_ns, bag.deserialize(m), bytes(m.data)) for m in bag.messages()]


def run_cli(argv, capsys):
    parser = argparse.ArgumentParser(prog="pws")
    sub = parser.add_subparsers(dest="command")
    cmd.register(sub)
    args = parser.parse_args(["replay", *[str(a) for a in argv]])
    rc = args.func(args)
    out, err = capsys.readouterr()
    return rc, out, err


def write_bag(path: Path, items, storage: str = "mcap"):
    """``items``: (topic, msgtype, log_time, msg (rosbags) or raw CDR bytes)."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin

    T = msgbuild.rosbags_types()
    ts = T.typestore
    conns = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3) as w:
        for topic, msgtype, t, msg in items:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            data = msg if isinstance(msg, (bytes, bytearray)) else ts.serialize_cdr(msg, msgtype)
            w.write(conns[topic], int(t), data)
    return path


def certifications(out: Path) -> list[tuple[int, int, dict]]:
    """(log time, header stamp, parsed payload) of every ``/certification`` message, via rosbags."""
    res = []
    with BagReader(out) as bag:
        for m in bag.messages(["/certification"]):
            msg = bag.deserialize(m)
            res.append((m.log_time_ns, msgconv.header_stamp_ns(msg), parse_certification(msg)))
    return res


def without_timing(payload: dict) -> dict:
    return {axis: {k: v for k, v in vals.items() if k not in TIMING_KEYS} for axis, vals in payload.items()}


def stamps_of(msgs, topic=TOPIC_COLOR) -> list[int]:
    return [msgconv.header_stamp_ns(d) for t, _ty, _lt, d, _raw in msgs if t == topic]


# ---- the main job ----------------------------------------------------------------------------------

def test_replay_writes_one_certification_per_frame_readable_by_both_readers(sim_bag, sim_msgs, models, tmp_path, capsys):
    out, report = tmp_path / "out", tmp_path / "report"
    rc, stdout, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], "--axes", "tz,ry", "--radius", "tz=2mm,ry=0.05deg",
                               "--n0", "16", "--n", "32", "--quiet", "--report", report], capsys)
    assert rc == 0, err
    src = stamps_of(sim_msgs)
    # rosbags: one certification per frame, header = source stamp = log time, the documented keys
    certs = certifications(out)
    assert [c[1] for c in certs] == src and [c[0] for c in certs] == src
    for _lt, _st, payload in certs:
        assert set(payload) == {"tz", "ry"}
        assert payload["tz"]["unit"] == "m" and payload["ry"]["unit"] == "rad"
        assert payload["tz"]["requested_radius"] == pytest.approx(0.002)
        assert payload["ry"]["requested_radius"] == pytest.approx(math.radians(0.05))
        assert payload["tz"]["hardware_id"] == "camera_color_optical_frame"
    # the independent mcap + mcap_ros2 reader decodes every topic, with the same keys in order
    dec = list(mcap_decoded_messages(out))
    topics = {t for t, _s, _lt, _d in dec}
    assert {"/certification", "/certification/markers", "/plan/poses/tz", "/plan/poses/ry"} <= topics
    cert_msgs = [d for t, _s, _lt, d in dec if t == "/certification"]
    assert len(cert_msgs) == 3
    for d in cert_msgs:
        assert [st.name for st in d.status] == ["pws/tz", "pws/ry"]
        for st in d.status:
            assert tuple(kv.key for kv in st.values)[: len(DIAGNOSTIC_KEYS)] == DIAGNOSTIC_KEYS
    poses = [d for t, _s, _lt, d in dec if t == "/plan/poses/tz"]
    assert len(poses) == 3 and all(len(p.poses) == certs[0][2]["tz"]["num_partitions"] for p in poses[:1])
    # the summary table on stdout
    assert "frames: 3 seen, 3 processed" in stdout and "clean acc." in stdout and "certified accuracy vs radius (tz, m)" in stdout
    # the report
    names = sorted(p.name for p in report.iterdir())
    assert names == ["certified_accuracy_vs_radius.png", "frames.csv", "frames.png", "summary.json"]
    for png in ("certified_accuracy_vs_radius.png", "frames.png"):
        assert (report / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import csv

    rows = list(csv.DictReader((report / "frames.csv").open()))
    assert len(rows) == 6 and {r["axis"] for r in rows} == {"tz", "ry"}
    summary = json.loads((report / "summary.json").read_text())
    assert summary["frames"]["seen"] == 3 and summary["frames"]["processed"] == 3 and summary["frames"]["with_truth"] == 3
    # brute force: accuracy from the bag's labels and the ground truth
    truth = {int(st): int(lbl) for st, lbl in ((r["stamp_ns"], r["truth_label"]) for r in rows)}
    for axis in ("tz", "ry"):
        right = [c[2][axis]["label"] == truth[c[1]] for c in certs]
        assert summary["axes"][axis]["clean_accuracy"] == pytest.approx(sum(right) / 3)
        cert_right = [c[2][axis]["certified"] and ok for c, ok in zip(certs, right)]
        assert summary["axes"][axis]["certified_accuracy"] == pytest.approx(sum(cert_right) / 3)
        radii = [c[2][axis]["radius"] for c in certs]
        assert summary["axes"][axis]["radius_mean"] == pytest.approx(float(np.mean(radii)))
        assert summary["axes"][axis]["radius_median"] == pytest.approx(float(np.median(radii)))


def test_accuracy_against_ground_truth(sim_bag, models, tmp_path):
    """A classifier that always says class 1 is right on exactly the frame of scene 1."""
    res = replay(ReplayOptions(bag=sim_bag, config=cmd.build_config(_args(models["const1"])), write_output=False, quiet=True))
    assert res.exit_code == 0
    a = res.summary["axes"]["tz"]
    assert a["with_truth"] == 3 and a["clean_accuracy"] == pytest.approx(1 / 3)
    labels = [r.truth_label for r in res.records]
    assert labels == [0, 1, 2]
    assert [r.correct["tz"] for r in res.records] == [False, True, False]
    certified_right = sum(r.cert("tz").certified and r.correct["tz"] for r in res.records)
    assert a["certified_accuracy"] == pytest.approx(certified_right / 3)
    curve = dict((round(r, 12), acc) for r, acc in a["certified_accuracy_vs_radius"])
    rad = res.records[1].cert("tz").radius
    for r, acc in curve.items():  # brute force: only frame 1 can count, and only up to its radius
        assert acc == pytest.approx((1 / 3) if r <= rad + 1e-12 else 0.0)


def _args(model, *extra):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    cmd.register(sub)
    return parser.parse_args(["replay", "x", "--model", str(model), *TINY, *extra])


def test_same_bag_twice_same_seed_gives_identical_results(sim_bag, models, tmp_path, capsys):
    outs = []
    for k in range(2):
        out = tmp_path / f"run{k}"
        rc, _o, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY, "--seed", "7"], capsys)
        assert rc == 0, err
        outs.append([(lt, st, without_timing(p)) for lt, st, p in certifications(out)])
    assert outs[0] == outs[1] and len(outs[0]) == 3
    # p_A bounds are really there (not a vacuous comparison)
    assert all(0.0 < p["tz"]["p_a_lower"] <= 1.0 for _lt, _st, p in outs[0])


def test_results_equal_the_engine_run_directly(sim_bag, sim_msgs, models, tmp_path, capsys):
    """The replay is the node's logic: converting frame k ourselves and calling FrameCertifier gives
    the same certificate as the bag holds for stamp k."""
    from pws_ros.bridge.engine import FrameCertifier

    out = tmp_path / "out"
    rc, _o, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY], capsys)
    assert rc == 0, err
    by_stamp = {st: p for _lt, st, p in certifications(out)}
    cfg = cmd.build_config(_args(models["linear"]))
    engine = FrameCertifier(cfg, log=lambda *a: None)
    msgs = {}
    for t, _ty, _lt, d, _raw in sim_msgs:
        msgs.setdefault(msgconv.header_stamp_ns(d), {})[t] = d
    for stamp, m in msgs.items():
        cloud, intr = msgconv.cloud_from_rgbd(m[TOPIC_DEPTH], m[TOPIC_COLOR], m[TOPIC_INFO])
        (cert,) = engine.process(cloud, intr, stamp).certificates
        got = by_stamp[stamp]["tz"]
        assert got["label"] == cert.label and got["radius"] == pytest.approx(cert.radius, rel=1e-8)
        assert got["p_a_lower"] == pytest.approx(cert.min_p_a_lower, rel=1e-8)
        assert got["num_partitions"] == cert.num_partitions and got["status"] == cert.status


def test_copy_inputs_cloud_preview_and_namespace(sim_bag, sim_msgs, models, tmp_path, capsys):
    out = tmp_path / "out"
    rc, _o, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY, "--copy-inputs", "--write-cloud",
                           "--preview", "--preview-every", "1", "--namespace", "robot1", "--max-frames", "2"], capsys)
    assert rc == 0, err
    with BagReader(out) as bag:
        got = {}
        for m in bag.messages():
            got.setdefault(m.topic, []).append((m.log_time_ns, bytes(m.data), m))
        # copied inputs are byte-identical, at their recorded log times (the frames that were read)
        for topic in (TOPIC_COLOR, TOPIC_DEPTH, TOPIC_INFO, TOPIC_TRUTH):
            src = [(lt, raw) for t, _ty, lt, _d, raw in sim_msgs if t == topic]
            assert [(lt, raw) for lt, raw, _m in got[topic]] == src[: len(got[topic])]
            assert len(got[topic]) >= 2
        assert len(got["/robot1/certification"]) == 2
        clouds = [bag.deserialize(m) for _lt, _raw, m in got["/robot1/cloud"]]
        infos = [bag.deserialize(m) for _lt, _raw, m in got["/robot1/cloud/camera_info"]]
        previews = [bag.deserialize(m) for _lt, _raw, m in got["/robot1/rendered/preview"]]
    # the cloud is the frame's one-frame cloud: one point per valid depth pixel
    depth0 = next(d for t, _ty, _lt, d, _raw in sim_msgs if t == TOPIC_DEPTH)
    valid = int(np.count_nonzero(msgconv.depth_to_meters(depth0) > 0))
    assert clouds[0].width * clouds[0].height == valid
    assert (infos[0].width, infos[0].height) == (32, 24)
    assert len(previews) >= 2 and previews[0].encoding == "rgb8" and (previews[0].width, previews[0].height) == (32, 24)


def test_default_out_and_overwrite_rules(sim_bag, models, tmp_path, capsys):
    assert default_out(sim_bag) == sim_bag.resolve().parent / "sim_pws"
    assert default_out(tmp_path / "x" / "talker.mcap") == (tmp_path / "x").resolve() / "talker_pws"
    out = tmp_path / "out"
    rc, _o, _e = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY, "--max-frames", "1"], capsys)
    assert rc == 0
    rc, _o, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY], capsys)
    assert rc == 2 and "already exists" in err and "--overwrite" in err
    rc, _o, err = run_cli([sim_bag, "--out", out, "--model", models["linear"], *TINY, "--overwrite", "--max-frames", "2"], capsys)
    assert rc == 0 and len(certifications(out)) == 2
    keep = tmp_path / "notes"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    rc, _o, err = run_cli([sim_bag, "--out", keep, "--model", models["linear"], *TINY, "--overwrite"], capsys)
    assert rc == 2 and "refusing" in err and (keep / "notes.txt").read_text() == "mine"


def test_json_output_and_max_frames(sim_bag, models, capsys):
    rc, stdout, err = run_cli([sim_bag, "--no-output", "--model", models["linear"], *TINY, "--json", "--max-frames", "2"], capsys)
    assert rc == 0, err
    s = json.loads(stdout)
    assert s["frames"]["seen"] == 2 and s["frames"]["processed"] == 2 and s["out"] is None
    assert s["axes"]["tz"]["frames"] == 2 and s["config"]["n0"] == 16 and s["inputs"]["color"] == TOPIC_COLOR


# ---- the realtime policy ---------------------------------------------------------------------------

def tick_reference(arrivals: list[int], durations: list[int]):
    """LatestSlot + one worker, simulated tick by tick (durations >= 1)."""
    n = len(arrivals)
    horizon = (max(arrivals) if arrivals else 0) + sum(durations) + 2
    current, busy_until, slot = None, None, None
    processed, dropped = [], []
    k = 0
    for t in range(horizon):
        if current is not None and busy_until == t:
            current = None
        if current is None and slot is not None:
            current, busy_until, slot = slot, t + durations[slot], None
            processed.append((current, t))
        while k < n and arrivals[k] == t:
            if current is None and slot is None:
                current, busy_until = k, t + durations[k]
                processed.append((k, t))
            else:
                if slot is not None:
                    dropped.append(slot)
                slot = k
            k += 1
    return processed, dropped


def run_scheduler(arrivals, durations):
    processed, dropped = [], []

    def process(i, start):
        processed.append((i, start))
        return durations[i]

    s = RealtimeScheduler(process, on_drop=dropped.append)
    for i, t in enumerate(arrivals):
        s.arrive(i, t)
    s.finish()
    assert s.dropped == len(dropped) and s.processed == len(processed)
    return processed, dropped


def test_realtime_scheduler_matches_a_tick_simulation():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=300, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, 6), st.integers(1, 9)), min_size=0, max_size=25))
    def check(items):
        gaps, durations = zip(*items) if items else ((), ())
        arrivals = list(np.cumsum(gaps).astype(int)) if items else []
        ref = tick_reference(arrivals, list(durations))
        got = run_scheduler([float(a) for a in arrivals], list(durations))
        assert got[0] == [(i, float(t)) for i, t in ref[0]]
        assert got[1] == ref[1]
        assert len(got[0]) + len(got[1]) == len(arrivals)

    check()


def test_realtime_replay_drops_what_the_live_node_would(sim_bag, models, tmp_path):
    """Frames every 0.1 s, each certification 'takes' 0.25 s: frame 0 runs, frame 1 waits and is
    replaced by frame 2 (dropped), frame 2 runs when frame 0 is done (latency 0.25 + 0.25 - 0.2 s)."""
    out = tmp_path / "rt"
    res = replay(ReplayOptions(bag=sim_bag, config=cmd.build_config(_args(models["linear"])), out=out, realtime=True,
                               quiet=True, cost_fn=lambda rec: 0.25))
    assert res.exit_code == 0
    assert res.summary["frames"]["seen"] == 3 and res.summary["frames"]["processed"] == 2
    assert res.summary["frames"]["dropped_realtime"] == 1
    certs = certifications(out)
    t0 = certs[0][1]
    assert [(st - t0) / 1e9 for _lt, st, _p in certs] == pytest.approx([0.0, 0.2])
    assert certs[1][2]["tz"]["latency_ms"] == pytest.approx(300.0, abs=1e-3)
    assert certs[0][2]["tz"]["latency_ms"] == pytest.approx(250.0, abs=1e-3)


# ---- stamp order ----------------------------------------------------------------------------------

def test_messages_are_processed_in_stamp_order(sim_msgs, models, tmp_path):
    """A recording whose log order is not the stamp order (frame 2 logged before frame 1) is
    certified in stamp order, and every frame still finds its CameraInfo and colour."""
    stamps = sorted(set(stamps_of(sim_msgs)))
    order = {stamps[0]: 0, stamps[2]: 1, stamps[1]: 2}
    items = []
    for t, ty, lt, d, raw in sim_msgs:
        st = msgconv.header_stamp_ns(d)
        items.append((order[st] * 1000 + len(items), t, ty, raw))
    items.sort()
    bag = write_bag(tmp_path / "shuffled", [(t, ty, lt, raw) for lt, t, ty, raw in items])
    res = replay(ReplayOptions(bag=bag, config=cmd.build_config(_args(models["linear"])), out=tmp_path / "out", quiet=True))
    assert res.exit_code == 0 and res.summary["frames"]["seen"] == 3
    assert [c[1] for c in certifications(tmp_path / "out")] == stamps
    assert [r.stamp_ns for r in res.records] == stamps


# ---- bad recordings ------------------------------------------------------------------------------

def _resized_depth(d, w=16, h=12):
    T = msgbuild.rosbags_types()
    return msgbuild.image_from_numpy(msgbuild.copy_header(T, d.header), np.full((h, w), 1000, np.uint16), T)


def test_mismatched_depth_and_colour_sizes(sim_msgs, models, tmp_path, capsys):
    stamps = sorted(set(stamps_of(sim_msgs)))
    # every frame broken: nothing certified -> exit 2 with the reason, the ERROR statuses still written
    items = [(t, ty, lt, _resized_depth(d) if t == TOPIC_DEPTH else raw) for t, ty, lt, d, raw in sim_msgs if t != TOPIC_POINTS]
    bag = write_bag(tmp_path / "allbad", items)
    rc, _o, err = run_cli([bag, "--out", tmp_path / "o1", "--model", models["linear"], *TINY], capsys)
    assert rc == 2
    assert "nothing could be certified" in err and "not registered (different sizes)" in err
    certs = certifications(tmp_path / "o1")
    assert len(certs) == 3 and all(p["tz"]["status"] == "error" and p["tz"]["level"] == 2 for _lt, _st, p in certs)
    # the same with the organized cloud beside it: the cloud is used instead (what can be certified is)
    items = [(t, ty, lt, _resized_depth(d) if t == TOPIC_DEPTH else raw) for t, ty, lt, d, raw in sim_msgs]
    bag = write_bag(tmp_path / "withcloud", items)
    rc, stdout, err = run_cli([bag, "--out", tmp_path / "o3", "--model", models["linear"], *TINY], capsys)
    assert rc == 0, err
    assert "using the point cloud" in err and "input (pointcloud2)" in stdout
    assert [p["tz"]["status"] != "error" for _lt, _st, p in certifications(tmp_path / "o3")] == [True] * 3
    # one frame broken: the others are certified, exit 0, the bad one is counted
    items = [(t, ty, lt, _resized_depth(d) if t == TOPIC_DEPTH and msgconv.header_stamp_ns(d) == stamps[1] else raw)
             for t, ty, lt, d, raw in sim_msgs]
    bag = write_bag(tmp_path / "onebad", items)
    rc, stdout, err = run_cli([bag, "--out", tmp_path / "o2", "--model", models["linear"], *TINY], capsys)
    assert rc == 0, err
    assert "1 input errors" in stdout and "not registered" in err
    status = [p["tz"]["status"] for _lt, _st, p in certifications(tmp_path / "o2")]
    assert status[1] == "error" and status[0] != "error" and status[2] != "error"


def test_missing_topics_and_empty_bags(sim_msgs, models, tmp_path, capsys):
    # colour + CameraInfo only (no depth, no cloud)
    items = [(t, ty, lt, raw) for t, ty, lt, _d, raw in sim_msgs if t in (TOPIC_COLOR, TOPIC_INFO)]
    bag = write_bag(tmp_path / "nodepth", items)
    rc, _o, err = run_cli([bag, "--out", tmp_path / "o1", "--model", models["linear"], *TINY], capsys)
    assert rc == 2 and "no camera input" in err and "no depth image" in err and TOPIC_COLOR in err
    assert not (tmp_path / "o1").exists()
    # depth + colour without CameraInfo
    items = [(t, ty, lt, raw) for t, ty, lt, _d, raw in sim_msgs if t in (TOPIC_COLOR, TOPIC_DEPTH)]
    bag = write_bag(tmp_path / "noinfo", items)
    rc, _o, err = run_cli([bag, "--out", tmp_path / "o2", "--model", models["linear"], *TINY], capsys)
    assert rc == 2 and "no sensor_msgs/CameraInfo" in err
    # an empty bag, and a bag whose topics have no messages
    bag = write_bag(tmp_path / "empty", [])
    rc, _o, err = run_cli([bag, "--out", tmp_path / "o3", "--model", models["linear"], *TINY], capsys)
    assert rc == 2 and "is empty" in err
    # a topic given by flag that is not there
    rc, _o, err = run_cli([tmp_path / "noinfo", "--info-topic", "/nope", "--model", models["linear"], *TINY, "--no-output"], capsys)
    assert rc == 2 and "--info-topic /nope: no such topic" in err


def test_truncated_recording_certifies_the_complete_frames(sim_msgs, models, tmp_path, capsys):
    from mcap.writer import CompressionType, Writer

    ts = msgbuild.rosbags_types().typestore
    f = tmp_path / "cut.mcap"
    with f.open("wb") as fh:
        w = Writer(fh, chunk_size=8192, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="test")
        sids, cids = {}, {}
        for t, ty, lt, _d, raw in sim_msgs:
            if ty not in sids:
                sids[ty] = w.register_schema(name=ty, encoding="ros2msg", data=ts.generate_msgdef(ty, ros_version=2)[0].encode())
            if t not in cids:
                cids[t] = w.register_channel(topic=t, message_encoding="cdr", schema_id=sids[ty])
            w.add_message(channel_id=cids[t], log_time=lt, data=raw, publish_time=lt)
        w.finish()
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * 0.8)])
    rc, stdout, err = run_cli([f, "--out", tmp_path / "out", "--model", models["linear"], *TINY, "--cloud-topic", TOPIC_POINTS], capsys)
    assert rc == 0, err
    assert "truncated or corrupt" in err
    n = len(certifications(tmp_path / "out"))
    assert 1 <= n < 3


def test_unknown_and_service_types_do_not_stop_the_replay(sim_msgs, models, tmp_path, capsys):
    from mcap.writer import Writer

    ts = msgbuild.rosbags_types().typestore
    f = tmp_path / "mixed.mcap"
    with f.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sids, cids = {}, {}
        extra = [("/svc/_service_event", "my_srvs/srv/Do_Event", "int32 a\n---\nint32 b\n"),
                 ("/weird", "odd_pkg/msg/Broken", "float64[ x")]
        for topic, ty, text in extra:
            sids[ty] = w.register_schema(name=ty, encoding="ros2msg", data=text.encode())
            cids[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sids[ty])
        for t, ty, lt, _d, raw in sim_msgs:
            if ty not in sids:
                sids[ty] = w.register_schema(name=ty, encoding="ros2msg", data=ts.generate_msgdef(ty, ros_version=2)[0].encode())
            if t not in cids:
                cids[t] = w.register_channel(topic=t, message_encoding="cdr", schema_id=sids[ty])
            w.add_message(channel_id=cids[t], log_time=lt, data=raw, publish_time=lt)
            for topic, _ty, _text in extra:
                w.add_message(channel_id=cids[topic], log_time=lt, data=b"\x00\x01\x00\x00\x07\x00\x00\x00", publish_time=lt)
        w.finish()
    rc, stdout, err = run_cli([f, "--out", tmp_path / "out", "--model", models["linear"], *TINY], capsys)
    assert rc == 0, err
    assert "my_srvs/srv/Do_Event" in err and "odd_pkg/msg/Broken" in err
    assert len(certifications(tmp_path / "out")) == 3


def test_method_pws_regenerates_the_scene_or_refuses(sim_bag, sim_msgs, models, tmp_path, capsys):
    rc, stdout, err = run_cli([sim_bag, "--no-output", "--model", models["linear"], *TINY, "--method", "pws", "--max-frames", "1", "--json"], capsys)
    assert rc == 0, err
    s = json.loads(stdout)
    assert s["config"]["method"] == "pws" and s["axes"]["tz"]["errors"] == 0 and s["frames"]["processed"] == 1
    # without ground truth there is no entire cloud: refused with a clear message, nothing written
    items = [(t, ty, lt, raw) for t, ty, lt, _d, raw in sim_msgs if t != TOPIC_TRUTH]
    bag = write_bag(tmp_path / "notruth", items)
    rc, _o, err = run_cli([bag, "--out", tmp_path / "o", "--model", models["linear"], *TINY, "--method", "pws"], capsys)
    assert rc == 2 and "method pws needs the entire scene cloud" in err and "pws_of" in err
    assert not (tmp_path / "o").exists()


def test_bad_model_and_bad_options_exit_2_before_writing(sim_bag, tmp_path, capsys):
    rc, _o, err = run_cli([sim_bag, "--out", tmp_path / "o", "--model", tmp_path / "missing.pt", *TINY], capsys)
    assert rc == 2 and "missing.pt" in err and not (tmp_path / "o").exists()
    rc, _o, err = run_cli([sim_bag, "--out", tmp_path / "o", "--axes", "tz,ry", "--radius", "0.01"], capsys)
    assert rc == 2 and "axis=value" in err
    rc, _o, err = run_cli([sim_bag, "--out", tmp_path / "o", "--axes", "tz", "--radius", "tz=3deg"], capsys)
    assert rc == 2 and "measured in m" in err
    rc, _o, err = run_cli([sim_bag, "--out", tmp_path / "o", "--n0", "0"], capsys)
    assert rc == 2 and "n0" in err
    rc, _o, err = run_cli([tmp_path / "nothing_here", "--no-output"], capsys)
    assert rc == 2 and "bag not found" in err



def test_outputs_that_cannot_be_made_are_refused_before_the_run(sim_bag, tmp_path, capsys, monkeypatch):
    """--out, --report and --video under a file, or in a folder this process may not write, exit 2 with one line
    naming the path, before any frame (a report lost after hours of work, or a traceback, before)."""
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    for opt, path in (("--out", afile / "o"), ("--report", afile / "rep"), ("--video", afile / "v.mp4")):
        args = [sim_bag, opt, path] + ([] if opt == "--out" else ["--no-output"])
        rc, out, err = run_cli(args, capsys)
        assert rc == 2 and str(afile) in err and "is a file" in err and "Traceback" not in err, (opt, err)
        assert "frames" not in out
    rc, _o, err = run_cli([sim_bag, "--no-output", "--report", afile], capsys)
    assert rc == 2 and "exists and is not a folder" in err
    import os as os_

    locked = tmp_path / "locked"
    locked.mkdir()
    real = os_.access
    monkeypatch.setattr(os_, "access", lambda p, mode, **kw: False if Path(p) == locked else real(p, mode, **kw))
    rc, _o, err = run_cli([sim_bag, "--no-output", "--report", locked / "rep"], capsys)
    assert rc == 2 and f"the folder {locked} is not writable" in err

def test_parse_radius_units():
    assert cmd.parse_radius("tz=5mm,ry=0.25deg", ["tz", "ry"]) == pytest.approx({"tz": 0.005, "ry": math.radians(0.25)})
    assert cmd.parse_radius("0.01", ["tz"]) == {"tz": 0.01}
    assert cmd.parse_radius("rx=0.002", ["tz", "rx"]) == {"rx": 0.002}
    assert cmd.parse_radius("tx=1cm", ["tx"]) == pytest.approx({"tx": 0.01})
    for bad in ("tz=-1", "tz=abc", "tz=1furlong", "qq=1", ""):
        with pytest.raises(PwsError):
            cmd.parse_radius(bad, ["tz"])
    # a radius for an axis not certified (a typo would be ignored), or one axis twice, is refused, naming it
    with pytest.raises(PwsError, match="axis ry is not certified"):
        cmd.parse_radius("ry=0.25deg", ["tz"])
    with pytest.raises(PwsError, match="tz is given twice"):
        cmd.parse_radius("tz=0.01,tz=0.02", ["tz"])


def test_help_explains_everything(capsys):
    parser = argparse.ArgumentParser(prog="pws")
    sub = parser.add_subparsers()
    cmd.register(sub)
    with pytest.raises(SystemExit):
        parser.parse_args(["replay", "--help"])
    text = capsys.readouterr().out
    for needle in ("--out", "--config", "--axes", "--radius", "--method", "--coverage", "--n0", "--sigma", "--alpha", "--seed",
                   "--device", "--model", "--classes", "--max-frames", "--report", "--realtime", "--copy-inputs", "--quiet",
                   "--json", "--cloud-topic", "--depth-topic", "--color-topic", "--info-topic", "certification",
                   "plan/poses", "Exit status", "ground truth", "MCAP", "sqlite3", "split"):
        assert needle in text, needle


# ---- real recordings -------------------------------------------------------------------------------


def test_real_realsense_depth_is_registered_with_the_recorded_extrinsics(models, tmp_path, capsys):
    """Not registered (depth fx 390, colour fx 613), but the recorder's extrinsics are in the bag: the
    depth is registered into the colour camera (said once) and certified. Its depth and colour are
    101.6 ms apart: with the default sync they pair as each other's nearest (one warning names the skew),
    and --sync-max-skew 0 refuses them (more in test_registration_inputs.py)."""
    out = tmp_path / "o"
    rc, _o, err = run_cli([shared_path("realsense_single_rgbd"), "--out", out, "--model", models["linear"],
                           *[a for a in TINY if a != "--quiet"]], capsys)
    assert rc == 0, err
    assert err.count("depth registered into the colour camera") == 1 and "/device_0/sensor_1/Color_0/tf/0" in err
    assert err.count("101.6 ms apart") == 1
    ((_lt, _stamp, payload),) = certifications(out)
    assert payload["tz"]["status"] in ("certified", "not_certified", "abstain")


def test_real_kinect_organized_cloud_is_certified(models, tmp_path, capsys):
    out = tmp_path / "o"
    rc, stdout, err = run_cli([shared_path("kinect_organized_cloud"), "--out", out, "--model", models["linear"], "--axes", "tz",
                               "--radius", "tz=0.1mm", "--n0", "8", "--n", "16", "--quiet"], capsys)
    assert rc == 0, err
    ((lt, stamp, payload),) = certifications(out)
    assert lt == stamp and payload["tz"]["status"] in ("certified", "not_certified", "abstain")
    assert payload["tz"]["hardware_id"] == "camera_rgb_optical_frame"
    assert "/camera/depth_registered/points" in stdout


@pytest.mark.parametrize("bag", [("rosbag2_written", "rosbag2_tests_resources_mcap_bag_with_topics_and_service_events"),
                                 ("rosbag2_written", "rosbag2_py_test_resources_mcap_talker"),
                                 ("rosbag2_written", "rosbag2_py_test_resources_sqlite3_talker", "talker.db3"),
                                 ("rosbag2_written", "rosbag2_py_test_resources_mcap_wbag")])
def test_real_bags_without_camera_data_name_the_problem(bag, models, tmp_path, capsys):
    rc, _o, err = run_cli([shared_path(*bag), "--out", tmp_path / "o", "--model", models["linear"], *TINY], capsys)
    assert rc == 2
    last = err.strip().splitlines()[-1]
    assert "no camera input" in last and "the bag holds" in last
    if "service_events" in bag[-1]:
        assert "test_msgs/srv/BasicTypes_Event" in err  # skipped with a warning, not a crash
    assert not (tmp_path / "o").exists()


def test_shipped_demo_bag(models, tmp_path, capsys):
    demo = Path(__file__).resolve().parents[1] / "bags" / "demo"
    assert (demo / "metadata.yaml").is_file(), "bags/demo (the shipped recording) is missing"
    rc, stdout, err = run_cli([demo, "--no-output", "--model", models["linear"], *TINY, "--max-frames", "2", "--json"], capsys)
    assert rc == 0, err
    s = json.loads(stdout)
    assert s["frames"]["processed"] == 2 and s["frames"]["with_truth"] == 2
    # 640x480 RGB-D without a PointCloud2: the one-frame cloud comes from the aligned depth + CameraInfo
    assert s["inputs"]["mode"] == "rgbd" and s["inputs"]["depth"] == "/camera/aligned_depth_to_color/image_raw"


# ---- storage formats, split bags, config files, the pws entry point ------------------------------

def _write_mcap(path: Path, items):
    from mcap.writer import Writer

    ts = msgbuild.rosbags_types().typestore
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sids, cids = {}, {}
        for t, ty, lt, raw in items:
            if ty not in sids:
                sids[ty] = w.register_schema(name=ty, encoding="ros2msg", data=ts.generate_msgdef(ty, ros_version=2)[0].encode())
            if t not in cids:
                cids[t] = w.register_channel(topic=t, message_encoding="cdr", schema_id=sids[ty])
            w.add_message(channel_id=cids[t], log_time=lt, data=raw, publish_time=lt)
        w.finish()
    return path


def test_same_results_from_sqlite3_split_and_bare_recordings(sim_bag, sim_msgs, models, tmp_path, capsys):
    base = tmp_path / "base"
    assert run_cli([sim_bag, "--out", base, "--model", models["linear"], *TINY], capsys)[0] == 0
    expect = [(st, without_timing(p)) for _lt, st, p in certifications(base)]
    items = [(t, ty, lt, raw) for t, ty, lt, _d, raw in sim_msgs]
    sqlite = write_bag(tmp_path / "sq", items, storage="sqlite3")
    split = tmp_path / "split"
    split.mkdir()
    _write_mcap(split / "part_0.mcap", items[: len(items) // 2])
    _write_mcap(split / "part_1.mcap", items[len(items) // 2:])
    bare = next(sim_bag.glob("*.mcap"))
    for k, src in enumerate((sqlite, next(sqlite.glob("*.db3")), split, bare)):
        out = tmp_path / f"o{k}"
        rc, _o, err = run_cli([src, "--out", out, "--model", models["linear"], *TINY], capsys)
        assert rc == 0, err
        assert [(st, without_timing(p)) for _lt, st, p in certifications(out)] == expect, src


def test_config_file_and_the_pws_entry_point(sim_bag, models, tmp_path, capsys):
    from pws_ros import cli

    conf = tmp_path / "params.yaml"
    conf.write_text("/**:\n  ros__parameters:\n    axes: [ry]\n    radius:\n      ry: 0.001\n    n0: 16\n    n: 24\n"
                    f"    seed: 3\n    model_path: {models['linear']}\n")
    rc = cli.main(["replay", str(sim_bag), "--config", str(conf), "--no-output", "--quiet", "--json", "--max-frames", "1"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    s = json.loads(out)
    assert s["config"]["axes"] == ["ry"] and s["config"]["n"] == 24 and s["config"]["seed"] == 3
    assert s["config"]["radius"] == {"ry": 0.001} and list(s["axes"]) == ["ry"]
    # options override the file
    rc = cli.main(["replay", str(sim_bag), "--config", str(conf), "--n", "20", "--axes", "tz", "--radius", "1mm", "--no-output",
                   "--quiet", "--json", "--max-frames", "1"])
    s = json.loads(capsys.readouterr().out)
    assert rc == 0 and s["config"]["n"] == 20 and s["config"]["radius"] == {"tz": 0.001}
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    n0: -4\n")
    rc = cli.main(["replay", str(sim_bag), "--config", str(bad), "--no-output"])
    assert rc == 2 and "n0" in capsys.readouterr().err


def test_max_partitions_caps_the_cost_per_frame(sim_bag, models, capsys):
    rc, stdout, err = run_cli([sim_bag, "--no-output", "--model", models["linear"], "--axes", "tz,ry", "--radius", "tz=5cm,ry=0.05deg",
                               "--n0", "16", "--n", "32", "--max-partitions", "3", "--quiet", "--json"], capsys)
    assert rc == 0, err  # plans needing more frames are made coarser, never refused
    s = json.loads(stdout)
    assert s["axes"]["tz"]["errors"] == 0 and s["axes"]["ry"]["errors"] == 0

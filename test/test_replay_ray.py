"""``pws replay --workers N`` (pws_ros.replay.distributed): the frames as Ray tasks on a local instance
give the serial run's certificates, written once each in stamp order by the driver, with at most 2N
frames in flight; a worker process killed mid-run loses nothing and writes nothing twice; the output
opens with the independent mcap reader. Skipped where Ray (the optional extra .[ray]) is not installed."""
from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

import ray  # noqa: E402  (in the test extra: the Ray tests run wherever the tests do)

from pws_ros.bagio import BagReader  # noqa: E402
from pws_ros.bridge import msgconv  # noqa: E402
from pws_ros.bridge.config import config_from_params  # noqa: E402
from pws_ros.bridge.msgbuild import parse_certification  # noqa: E402
from pws_ros.replay import ReplayOptions, replay  # noqa: E402
from pws_ros.replay.distributed import RayReplay, replay_ray  # noqa: E402

VOLATILE = {"latency_ms", "compute_ms", "node"}


@pytest.fixture(scope="module")
def local_ray():
    """One local instance for the module (RayReplay uses it instead of starting its own)."""
    ray.init(num_cpus=2, include_dashboard=False, logging_level="warning", log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from pws_ros.sim.record import record

    return record(tmp_path_factory.mktemp("bags") / "sim", frames=6, width=64, height=48, views_per_scene=1)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    import torch

    from pws_ros.core.model import save_model
    from pws_ros.sim import CLASS_NAMES

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            g = torch.Generator().manual_seed(3)
            self.fc = torch.nn.Linear(3, len(CLASS_NAMES))
            with torch.no_grad():
                self.fc.weight.copy_(torch.randn(len(CLASS_NAMES), 3, generator=g))

        def forward(self, x):
            return self.fc(x.mean(dim=(2, 3)))

    return save_model(Net(), tmp_path_factory.mktemp("models") / "m.pt", list(CLASS_NAMES), input_size=(24, 32))


def options(bag, model, out, **extra):
    cfg = config_from_params({"model_path": str(model), "axes": ["tz", "ry"], "n0": 32, "n": 128, "batch_size": 64})
    return ReplayOptions(bag=Path(bag), config=cfg, out=out, overwrite=True, quiet=True, **extra)


def certifications(out: Path) -> list[tuple[int, dict]]:
    got = []
    with BagReader(out) as b:
        for m in b.messages(["/certification"]):
            msg = b.deserialize(m)
            parsed = parse_certification(msg)
            for v in parsed.values():
                for k in VOLATILE:
                    v.pop(k)
            got.append((msgconv.header_stamp_ns(msg), parsed))
    return got


def mcap_stamps(out: Path) -> list[int]:
    """Header stamps of /certification read with the independent mcap + mcap_ros2 reader."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (path,) = sorted(Path(out).glob("*.mcap"))
    stamps = []
    with open(path, "rb") as f:
        for _schema, channel, _message, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            if channel.topic == "/certification":
                stamps.append(decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec)
    return stamps


@pytest.fixture(scope="module")
def serial(bag, model, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "out"
    res = replay(options(bag, model, out))
    assert res.exit_code == 0 and len(res.records) == 6
    return certifications(out)


def test_ray_replay_equals_the_serial_run(local_ray, bag, model, serial, tmp_path):
    out = tmp_path / "out"
    rr = RayReplay(options(bag, model, out), workers=2)
    res = rr.run()
    assert res.exit_code == 0 and len(res.records) == 6
    got = certifications(out)
    assert [s for s, _ in got] == sorted(s for s, _ in serial)   # each frame once, in stamp order
    assert got == serial and any(v["radius"] > 0 for _s, p in got for v in p.values())
    assert mcap_stamps(out) == [s for s, _ in got]
    w = res.summary["workers"]
    assert w["workers"] == 2 and w["max_in_flight"] == 4 and 1 <= w["peak_in_flight"] <= 4
    assert all(pid != os.getpid() for pid in rr.task_pids.values())   # certified in worker processes


def _parent(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("PPid:"):
                return int(line.split()[1])
    return 0


def _ours(pid: int) -> bool:
    """``pid`` descends from this test process (its Ray instance's raylet started it)."""
    me = os.getpid()
    for _ in range(16):
        pid = _parent(pid)
        if pid == me:
            return True
        if pid <= 1:
            return False
    return False


def _certify_pids() -> list[int]:
    """Workers of this test's Ray instance running a frame now (Ray titles them ray::_certify)."""
    pids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/cmdline", "rb") as f:
                    if f.read().startswith(b"ray::_certify") and _ours(int(d)):
                        pids.append(int(d))
            except OSError:
                continue
    return pids


def test_a_worker_killed_mid_run_loses_no_frame_and_writes_none_twice(local_ray, bag, model, serial, tmp_path):
    out = tmp_path / "out"
    rr = RayReplay(options(bag, model, out), workers=2)
    box = {}
    thread = threading.Thread(target=lambda: box.setdefault("res", rr.run()))
    thread.start()
    killed = None
    end = time.monotonic() + 120
    while killed is None and thread.is_alive() and time.monotonic() < end:
        pids = _certify_pids()
        if pids:
            killed = pids[0]
            os.kill(killed, signal.SIGKILL)   # a worker this test's Ray instance started, by its pid
        time.sleep(0.01)
    thread.join(300)
    assert killed is not None, "no frame was seen running in a worker"
    res = box["res"]
    assert res.exit_code == 0 and len(res.records) == 6
    got = certifications(out)
    assert got == serial                     # nothing lost, nothing written twice, the same certificates
    assert mcap_stamps(out) == [s for s, _ in serial]
    # the killed worker was running a frame: Ray re-ran it elsewhere (without the retry the run fails with
    # a WorkerCrashedError); no result came from the dead process after it died
    with pytest.raises(ProcessLookupError):
        os.kill(killed, 0)


def test_replay_ray_refuses_what_it_cannot_do(bag, model, tmp_path):
    from pws_ros.core.errors import PwsError

    with pytest.raises(PwsError, match="--realtime"):
        replay_ray(options(bag, model, tmp_path / "o", realtime=True), 2)
    with pytest.raises(PwsError, match="--workers must be >= 1"):
        replay_ray(options(bag, model, tmp_path / "o"), 0)


def test_cli_ray_address_needs_workers(bag, model, capsys):
    from pws_ros.cli import main

    rc = main(["replay", str(bag), "--model", str(model), "--no-output", "--quiet", "--ray-address", "auto"])
    assert rc == 2 and "--ray-address needs --workers" in capsys.readouterr().err


def _is_loopback(host: str) -> bool:
    import ipaddress

    ip = ipaddress.ip_address(host.split("%")[0])
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


@pytest.mark.slow
def test_a_local_instance_listens_on_loopback_only(bag, model, tmp_path):
    """`pws replay BAG --workers 2` (no --ray-address): every listening socket of the replay's process tree
    (driver, gcs_server, raylet, agents, workers), sampled while it runs, is on 127.0.0.0/8 (or ::1); none
    on every interface (0.0.0.0, ::) nor on the machine's network address."""
    import subprocess
    import sys

    import psutil

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("RAY_ADDRESS", None)
    cmd = [sys.executable, "-m", "pws_ros.cli", "replay", str(bag), "--workers", "2", "--no-output", "--quiet", "--model", str(model),
           "--axes", "tz", "--n0", "8", "--n", "16", "--anchors", "2", "--max-frames", "3"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seen: dict[tuple[str, int], str] = {}
    try:
        while proc.poll() is None:
            try:
                tree = [psutil.Process(proc.pid)] + psutil.Process(proc.pid).children(recursive=True)
            except psutil.Error:
                break
            for p in tree:
                try:
                    for c in p.net_connections(kind="inet"):
                        if c.status == psutil.CONN_LISTEN:
                            seen[(c.laddr.ip, c.laddr.port)] = p.name()
                except psutil.Error:
                    continue
            time.sleep(0.2)
        err = proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-2000:]
    names = set(seen.values())
    assert any("gcs" in n for n in names) and any("raylet" in n for n in names), seen   # Ray's own servers were seen
    outside = {f"{ip}:{port} ({name})" for (ip, port), name in seen.items() if not _is_loopback(ip)}
    assert not outside, f"listening outside 127.0.0.0/8: {sorted(outside)}"

"""Crash-safe output: `pws replay` stopped by SIGTERM closes a bag (and a --video) that independent readers
read up to the last finished frame and says it was interrupted; a writer killed without any clean-up
(SIGKILL-like) still leaves every flushed frame readable; signals never cut a frame's writes."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pws_ros.replay.interrupt import Interrupted, StopSignals

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo"
T0 = 1_700_000_000_000_000_000


def _env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), OMP_NUM_THREADS="1")


def _mcap_certifications(out: Path) -> list:
    """The certification messages of a bag, read with the ``mcap`` package alone (no rosbags)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (f,) = sorted(out.glob("*.mcap"))
    with f.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [m for _s, ch, _m, m in reader.iter_decoded_messages() if ch.topic == "/certification"]


def _sigterm_after_first_frame(cmd: list[str], cwd: Path, wait_s: float, settle_s: float = 0.0) -> tuple[int, str, str, float]:
    """Run the replay ``cmd``; once its first of the demo's 8 frames is done (and ``settle_s`` more), send SIGTERM.
    Returns the exit status, stdout, stderr and the seconds from the signal to the exit."""
    proc = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err_lines: list[str] = []
    first_frame = threading.Event()

    def read_stderr():
        for line in proc.stderr:
            err_lines.append(line)
            if "pws replay: 1/8 frames" in line:
                first_frame.set()

    out_chunks: list[str] = []
    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    out_reader = threading.Thread(target=lambda: out_chunks.append(proc.stdout.read()), daemon=True)
    out_reader.start()  # each pipe has one reader only (communicate() would race the stderr thread)
    try:
        assert first_frame.wait(wait_s), f"no frame finished within {wait_s:g} s:\n" + "".join(err_lines)
        time.sleep(settle_s)
        assert proc.poll() is None, "the replay ended before it could be interrupted"
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(10)
    out_reader.join(10)
    return proc.returncode, "".join(out_chunks), "".join(err_lines), took


def test_sigterm_closes_a_readable_bag_and_a_summary_marked_interrupted(make_model_file, tmp_path):
    assert DEMO.exists(), "the shipped demo bag bags/demo is missing"  # shipped: required, not skipped
    model = make_model_file(input_size=(24, 32))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "pws_ros.cli", "replay", str(DEMO), "--out", str(out), "--axes", "tz", "--radius", "tz=2mm",
           "--n0", "16", "--n", "256", "--model", str(model), "--progress-interval", "0", "--json",
           "--report", str(tmp_path / "report"), "--video", str(tmp_path / "v.mp4")]
    returncode, stdout, stderr, _took = _sigterm_after_first_frame(cmd, tmp_path, wait_s=60)
    assert returncode == 143, stderr
    assert "pws replay: interrupted: stopped by SIGTERM after" in stderr
    summary = json.loads(stdout)
    done = summary["frames"]["processed"]
    assert summary["interrupted"] == "SIGTERM" and summary["exit_code"] == 143 and 1 <= done < 8  # bags/demo has 8 frames
    assert "interrupted by SIGTERM" in summary["title"]
    assert json.loads((tmp_path / "report" / "summary.json").read_text())["interrupted"] == "SIGTERM"
    # --video: the overlay of every frame done, renamed from its temporary name at the clean close
    import cv2

    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    pictures = 0
    while cap.read()[0]:
        pictures += 1
    cap.release()
    assert pictures == done and summary["video"] == {"path": str(tmp_path / "v.mp4"), "frames": done}
    assert not list(tmp_path.glob(".v.partial*"))
    # the independent mcap reader: one complete certification per frame done, nothing of the dropped frame
    certs = _mcap_certifications(out)
    assert len(certs) == done and all(len(c.status) == 1 and c.status[0].name.endswith("tz") for c in certs)
    keys = [kv.key for kv in certs[0].status[0].values]
    assert "radius" in keys and "p_a_lower" in keys
    # rosbags (metadata.yaml + summary written by the clean close)
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as r:
        conns = [c for c in r.connections if c.topic == "/certification"]
        assert sum(1 for _ in r.messages(connections=conns)) == done


def test_a_killed_writer_leaves_the_flushed_frames_readable(tmp_path):
    """No clean-up at all (os._exit, as after SIGKILL or an OOM kill): the frames flushed before are
    in complete chunks; BagReader and the mcap stream reader read them, the half-written one is absent."""
    out = tmp_path / "killed"
    script = f"""
import os
from pws_ros.bagio import BagWriter
from pws_ros.bridge import msgbuild
T = msgbuild.rosbags_types()
w = BagWriter({str(out)!r}, typestore=T.typestore).open()
for k in range(3):
    hdr = msgbuild.make_header(T, {T0} + k, "cam")
    w.write("/certification", T.DiagnosticArray(header=hdr, status=[]), {T0} + k)
    assert w.flush()
w.write("/certification", T.DiagnosticArray(header=msgbuild.make_header(T, {T0} + 9, "cam"), status=[]), {T0} + 9)
os._exit(0)
"""
    subprocess.run([sys.executable, "-c", script], env=_env(), check=True, timeout=60)
    assert not (out / "metadata.yaml").exists()  # written only by a clean close
    from pws_ros.bagio import BagReader

    with BagReader(out) as bag:
        stamps = [m.log_time_ns for m in bag.messages()]
    assert stamps == [T0, T0 + 1, T0 + 2]
    from mcap.stream_reader import StreamReader
    from mcap.records import Message

    got = []
    with next(out.glob("*.mcap")).open("rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Message):
                    got.append(rec.log_time)
        except Exception:  # the file ends without a footer
            pass
    assert got == [T0, T0 + 1, T0 + 2]


def test_signals_wait_for_the_end_of_a_section():
    before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    with StopSignals() as stop:
        with pytest.raises(Interrupted) as info:
            with stop.section():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                finished = True  # the section is never cut
        assert finished and info.value.signame == "SIGTERM" and info.value.exit_code == 143
        os.kill(os.getpid(), signal.SIGINT)  # a second signal during the clean-up is only noted
        time.sleep(0.05)
    with StopSignals() as stop2:
        with pytest.raises(Interrupted) as info2:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
        assert info2.value.exit_code == 130 and stop2.signame == "SIGINT"
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before  # handlers restored


def test_sigterm_while_a_frames_axes_run_at_once_exits_143_with_the_bag_closed(tmp_path):
    """With the axes of a frame in threads of their own (``axis_threads``), SIGTERM mid-frame still exits with 143 at once,
    the bag closed: the axes still inside torch do not abort the exit (``pws_ros.cli.run``)."""
    out = tmp_path / "out"
    conf = tmp_path / "threads.yaml"
    conf.write_text("pipeline:\n  ros__parameters:\n    axis_threads: 2\n")
    # the shipped model and sizes (about 2-3 s a frame): the signal comes while both axes are inside torch
    cmd = [sys.executable, "-m", "pws_ros.cli", "replay", str(DEMO), "--out", str(out), "--config", str(conf),
           "--progress-interval", "0", "--json"]
    # (1 s after the first frame: the second frame's axes under way)
    returncode, stdout, stderr, took = _sigterm_after_first_frame(cmd, tmp_path, wait_s=120, settle_s=1.0)
    assert returncode == 143, stderr
    assert "terminate called" not in stderr and "stopped by SIGTERM after" in stderr
    summary = json.loads(stdout)
    done = summary["frames"]["processed"]
    assert summary["exit_code"] == 143 and 1 <= done < 8
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as r:
        conns = [c for c in r.connections if c.topic == "/certification"]
        assert sum(1 for _ in r.messages(connections=conns)) == done
    assert took < 30, f"the exit took {took:.1f} s"


def test_a_stopped_ceiling_prints_the_frames_it_finished_and_exits_with_the_signal(tmp_path):
    """`pws ceiling` stopped by SIGTERM (as by Ctrl-C) is not an error: it prints the table of the frames it
    finished, says how many, and exits 143 (before: "the ceiling run failed", exit 2, no table)."""
    cmd = [sys.executable, "-m", "pws_ros.cli", "ceiling", str(DEMO), "--no-model", "--size", "90x160", "--axes", "tz",
           "--max-frames", "8"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:   # the first frame has begun (its imaging is described), then a little more
            if "surfel imaging" in line:
                break
        time.sleep(1.5)
        assert proc.poll() is None, "the ceiling ended before it could be stopped"
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    done = [ln for ln in out.splitlines() if ln.split()[1:2] == ["tz"]]   # the table's rows: frame, axis, ...
    assert "frame axis" in out and len(done) < 8
    assert f"interrupted (SIGTERM) after {len(done)} frame(s)" in err and "Traceback" not in err

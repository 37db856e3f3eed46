"""Progress (pws_ros.replay.progress_log): a tqdm bar on a terminal, plain periodic lines elsewhere, nothing
with --quiet; and the lines a real `pws replay` writes when stderr is a pipe."""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pws_ros.replay.progress_log import Progress

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo"


class FakeTTY(io.StringIO):
    def isatty(self):
        return True


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_log_lines_every_interval_with_rate_eta_and_note():
    clock, out = Clock(), io.StringIO()
    p = Progress(10, label="pws replay", interval_s=30, stream=out, clock=clock)
    assert p.mode == "log"  # not a terminal
    for _ in range(4):  # 4 frames, 10 s each: one line once 30 s have passed
        clock.t += 10
        p.update(1, note="last: tz ok")
    lines = out.getvalue().splitlines()
    assert lines == ["pws replay: 3/10 frames (30%), 0.10 frames/s, elapsed 00:30, ETA 01:10, last: tz ok"]
    clock.t += 5
    p.close()  # a last line with the final state
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and lines[1].startswith("pws replay: 4/10 frames (40%), 0.09 frames/s, elapsed 00:45")
    p.close()
    assert len(out.getvalue().splitlines()) == 2


def test_log_lines_without_total_and_through_a_logger():
    clock, got = Clock(), []
    p = Progress(None, label="x", interval_s=0, emit=got.append, clock=clock, stream=io.StringIO())
    clock.t += 2
    p.update(1)
    p.close()  # nothing new since the last line: no repeat
    assert got == ["1 frames, 0.50 frames/s, elapsed 00:02"]


def test_update_to_follows_a_done_total_callback():
    clock, out = Clock(), io.StringIO()
    p = Progress(label="certify", unit="images", interval_s=0, stream=out, clock=clock)
    clock.t += 1
    p.update_to(50, 200)
    clock.t += 1
    p.update_to(200, 200)
    assert p.count == 200 and p.total == 200
    assert out.getvalue().splitlines()[-1].startswith("certify: 200/200 images (100%), 100.00 images/s")


def test_bar_on_a_terminal_and_nothing_when_off():
    tty = FakeTTY()
    p = Progress(4, label="pws replay", stream=tty)
    assert p.mode == "bar"
    p.update(2, note="last: tz ok")
    p.close()
    text = tty.getvalue()
    assert "pws replay" in text and "2/4" in text and "\r" in text  # drawn in place by tqdm
    for stream in (FakeTTY(), io.StringIO()):
        q = Progress(4, stream=stream, mode="off", interval_s=0)
        q.update(4)
        q.close()
        assert stream.getvalue() == ""
    with pytest.raises(ValueError):
        Progress(mode="loud")


def test_replay_writes_progress_lines_when_stderr_is_not_a_terminal(make_model_file, tmp_path):
    assert DEMO.exists(), "the shipped demo bag bags/demo is missing"  # shipped: required, not skipped
    model = make_model_file(input_size=(24, 32))
    cmd = [sys.executable, "-m", "pws_ros.cli", "replay", str(DEMO), "--no-output", "--axes", "tz", "--radius", "tz=2mm",
           "--n0", "16", "--n", "32", "--model", str(model), "--max-frames", "3", "--progress-interval", "0"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), OMP_NUM_THREADS="1")
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if re.match(r"pws replay: \d+/3 frames", ln)]
    assert [ln.split()[2] for ln in lines] == ["1/3", "2/3", "3/3"], r.stderr
    assert all(re.search(r"frames/s, elapsed \d\d:\d\d, ETA \d\d:\d\d, last: tz ", ln) for ln in lines), lines
    assert "\r" not in r.stderr  # plain lines, no bar
    quiet = subprocess.run(cmd + ["--quiet"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert quiet.returncode == 0 and not re.search(r"\d+/3 frames", quiet.stderr), quiet.stderr

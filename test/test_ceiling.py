"""``pws ceiling``: the never-changing classifier, the rows pairing it with a model, the advice, the CLI."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pws_ros.bridge.config import PwsConfig
from pws_ros.core.errors import PwsError
from conftest import recomputed_p_a_lower
from pws_ros.replay import ReplayOptions
from pws_ros.replay.ceiling import CeilingRow, advice, ceiling, never_changing_model

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "bags" / "demo"
TINY = dict(axes=("tz",), radius_tz=0.002, n0=8, n=32, num_anchors=4)


def test_never_changing_model_answers_class_0_whatever_the_image():
    m = never_changing_model((9, 16))
    x = torch.rand(5, 3, 9, 16) * 10 - 5
    out = m(x)
    assert out.shape == (5, 2) and torch.all(out.argmax(1) == 0)
    with pytest.raises(PwsError, match="expects 16x9"):
        m(torch.rand(1, 3, 8, 16))


def test_ceiling_rows_pair_the_never_changing_classifier_with_the_model():
    from pws_ros.core.model import load_model

    model = load_model(REPO / "bags" / "models" / "classifier_sigma0.50.pt")
    opts = ReplayOptions(bag=DEMO, config=PwsConfig(**TINY), write_output=False, max_frames=1, quiet=True)
    rows, top, got = ceiling(opts, model)
    (row,) = rows
    (cert,) = top.records[0].certificates
    # every anchor of the ceiling run has the largest p_A bound its votes allow (all for the label: the joint
    # look's bound, docs/certificate.md), recomputed from what the certificate records
    assert cert.bounds["anchor_votes"] == cert.bounds["anchor_samples"] and cert.bounds["looks"]["joint"]
    assert cert.bounds["joint_votes"] == cert.bounds["looks"]["sizes"][0]
    assert np.allclose(cert.p_a_lower, recomputed_p_a_lower(cert)) and cert.class_name == "always"
    assert row.axis == "tz" and row.requested == 0.002 and row.ceiling == cert.radius > 0
    (mcert,) = got.records[0].certificates
    assert row.model == mcert.radius and row.model_class == mcert.class_name != "always"
    assert math.isfinite(row.model_s) and math.isfinite(row.ceiling_s)
    # another input size than the model's is refused (the two radii would be about different images)
    with pytest.raises(PwsError, match="differs from the model's input"):
        ceiling(opts, model, input_size=(45, 80))


def test_advice_names_what_limits():
    def row(c, m=math.nan):
        return CeilingRow(0, 0, "tz", "m", 0.01, c, 1.0, "x", m, 1.0, "y")

    assert "the imaging limits" in advice([row(0.001, 0.0005)])[0]
    assert "the model limits" in advice([row(0.01, 0.001)])[0]
    assert "reaches most" in advice([row(0.01, 0.009)])[0]
    assert advice([row(0.01)]) == ["tz: median ceiling 100% of the requested radius"]


def test_cli_json_and_bad_input():
    cmd = [sys.executable, "-m", "pws_ros.cli", "ceiling", str(DEMO), "--max-frames", "1", "--axes", "tz", "--radius", "tz=2mm",
           "--n0", "8", "--n", "32", "--anchors", "4", "--quiet"]
    p = subprocess.run(cmd + ["--no-model", "--size", "90x160", "--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout)
    assert [r["axis"] for r in d["rows"]] == ["tz"] and d["rows"][0]["model"] is None and 0 < d["rows"][0]["ceiling_share"] <= 1
    p = subprocess.run(cmd + ["--no-model"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "needs the classifier's input size" in p.stderr
    p = subprocess.run(cmd[:-1] + ["--no-model", "--size", "90x160"], capture_output=True, text=True, timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("pws ")]
    assert p.returncode == 0 and lines and all(ln.startswith("pws ceiling: ") for ln in lines), p.stderr   # not "pws replay"
    p = subprocess.run(cmd + ["--size", "16x"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "expected HxW" in p.stderr


def test_cli_several_recordings_one_table(tmp_path):
    other = tmp_path / "other_recording"
    other.symlink_to(DEMO, target_is_directory=True)
    cmd = [sys.executable, "-m", "pws_ros.cli", "ceiling", str(DEMO), str(other), "--max-frames", "1", "--axes", "tz",
           "--radius", "tz=2mm", "--n0", "8", "--n", "32", "--anchors", "4", "--quiet", "--no-model", "--size", "90x160"]
    p = subprocess.run(cmd + ["--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    rows = json.loads(p.stdout)["rows"]
    assert [r["recording"] for r in rows] == [str(DEMO), str(other)]
    assert rows[0]["ceiling"] == rows[1]["ceiling"] > 0    # the same frame, seeded: the same ceiling
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    table = p.stdout.splitlines()
    assert table[1].startswith("recording") and table[2].startswith(str(DEMO)) and table[3].startswith(str(other))
    assert "tz: median ceiling" in p.stdout and p.stdout.count("median ceiling") == 1   # one median over both
    p = subprocess.run(cmd[:5] + [str(tmp_path / "missing")] + cmd[6:], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "missing" in p.stderr


def test_cli_puts_the_whole_frame_beside_a_working_volume():
    """With a working volume the table has the whole frame's ceiling beside the volume's. A volume that holds
    every point of the frame draws the same images, so both ceilings are equal; without one there is no column."""
    cmd = [sys.executable, "-m", "pws_ros.cli", "ceiling", str(DEMO), "--max-frames", "1", "--axes", "tz", "--radius", "tz=2mm",
           "--n0", "8", "--n", "32", "--anchors", "4", "--quiet", "--no-model", "--size", "90x160"]
    p = subprocess.run(cmd + ["--working-volume", "0,1000", "--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    (row,) = json.loads(p.stdout)["rows"]
    assert row["whole"] == row["ceiling"] > 0 and row["whole_share"] == row["ceiling_share"]
    p = subprocess.run(cmd + ["--working-volume", "0,1000"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "whole frame" in p.stdout.splitlines()[1] and "on the whole frame)" in p.stdout, p.stdout
    p = subprocess.run(cmd + ["--json"], capture_output=True, text=True, timeout=300)
    assert json.loads(p.stdout)["rows"][0]["whole"] is None
    p = subprocess.run(cmd + ["--working-volume", "2,1"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "must be larger than near" in p.stderr, p.stderr

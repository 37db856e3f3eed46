"""The labelled real-task path on a tiny synthetic folder made here: `pws import frames` -> `pws finetune`
with a new head for the label set (1 epoch, clips held out whole) -> `pws replay --report` on the
held-out clips. The counts of correct and certified frames are checked against the labels this test
wrote (by stamp), not against the report's own arithmetic (small radii: 100 samples per bound at
sigma 0.12 keep the test short); bad labelled input is one line naming the
frame, with no model written.

The two classes are a plane of saturated colour (red or blue, a little texture) 0.8 m before the
camera: a new linear head on the demo classifier's outputs separates them after one epoch."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from conftest import REPO
from pws_ros.bagio import BagReader
from pws_ros.bridge import msgconv
from pws_ros.cli import main as pws_main

MODEL = REPO / "bags" / "models" / "classifier_sigma0.25.pt"
H, W = 36, 48
CLIPS = {"G01_red/clip1": 4, "G01_red/clip2": 3, "G02_blue/clip1": 4, "G02_blue/clip2": 3}
COLOURS = {"red": (220, 30, 30), "blue": (30, 30, 220)}
REGEX = "^G[0-9]+_(?P<label>[^/]+)/"
SIGMA = 0.12
CAMERA = ["--intrinsics", "40,40,23.5,17.5"]


@pytest.fixture(autouse=True)
def _two_threads():
    n = torch.get_num_threads()
    torch.set_num_threads(min(2, n))
    yield
    torch.set_num_threads(n)


def make_folder(root: Path) -> None:
    rng = np.random.default_rng(5)
    for clip, n in CLIPS.items():
        colour = np.asarray(COLOURS[clip.split("_")[1].split("/")[0]], dtype=np.int64)
        (root / clip / "rgb").mkdir(parents=True)
        (root / clip / "depth_raw").mkdir()
        for i in range(1, n + 1):
            rgb = np.clip(colour + rng.integers(-20, 21, (H, W, 3)), 0, 255).astype(np.uint8)
            cv2.imwrite(str(root / clip / "rgb" / f"frame_{i:03d}.png"), rgb[..., ::-1])
            np.save(root / clip / "depth_raw" / f"frame_{i:03d}.npy", np.full((H, W), 800, np.uint16))   # 0.8 m in mm
    (root / "depth_metadata.json").write_text(json.dumps({"depth_scale": 0.001}))


def run(argv, capsys) -> tuple[int, str, str]:
    rc = pws_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def labels_by_stamp(bag: Path) -> dict[int, tuple[str, str]]:
    """stamp -> (label, clip), read back from the recording's ground truth with the project's bag reader."""
    out = {}
    with BagReader(bag) as r:
        for m in r.messages(["/pws/ground_truth"]):
            msg = r.deserialize(m)
            values = {kv.key: kv.value for kv in msg.status[0].values}
            out[msgconv.header_stamp_ns(msg)] = (values["class_name"], values["clip"])
    return out


def test_import_finetune_new_head_replay_report_counts_against_labels(tmp_path, capsys):
    root = tmp_path / "data"
    make_folder(root)
    rec, held = tmp_path / "all", tmp_path / "held"
    assert run(["import", "frames", root, "--out", rec, *CAMERA, "--label-regex", REGEX, "--quiet"], capsys)[0] == 0
    assert run(["import", "frames", root, "--out", held, *CAMERA, "--label-regex", REGEX, "--clips", "*/clip2", "--quiet"],
               capsys)[0] == 0
    truth = labels_by_stamp(held)
    assert sorted(c for _l, c in truth.values()) == ["G01_red/clip2"] * 3 + ["G02_blue/clip2"] * 3

    model = tmp_path / "gest.pt"
    rc, text, err = run(["finetune", rec, "--model", MODEL, "--new-head", "--input-size", "24x32", "--holdout-clips", "clip2",
                         "--sigma", SIGMA, "--epochs", "1", "--views", "1", "--batch-size", "4", "--lr", "3e-3", "--eval-samples", "20",
                         "--consistency", "1", "--out", model, "--quiet", "--json"], capsys)
    assert rc == 0, err
    report = json.loads(text)
    assert report["classes"] == ["blue", "red"] and report["new_head"]
    (r,) = report["recordings"]
    assert (r["trained_on"], r["held_out"]) == (8, 6) and r["held_out_clips"] == ["G01_red/clip2", "G02_blue/clip2"]
    assert all(row["clip"].endswith("/clip2") for row in report["per_frame"])
    assert [line.strip() for line in model.with_suffix(".classes.txt").read_text().splitlines()] == ["blue", "red"]
    # the report's accuracies, recounted from its per-frame rows against the labels of the clips
    rows = report["per_frame"]
    everything = labels_by_stamp(rec)
    assert sorted(row["stamp_ns"] for row in rows) == sorted(s for s, (_l, c) in everything.items() if c.endswith("/clip2"))
    want = {row["stamp_ns"]: everything[row["stamp_ns"]][0] for row in rows}
    assert [row["truth"] for row in rows] == [want[row["stamp_ns"]] for row in rows]
    clean_right = sum(row["clean_after"] == want[row["stamp_ns"]] for row in rows)
    assert report["after"]["clean_accuracy_vs_truth"] == pytest.approx(clean_right / 6)
    assert report["after"]["accuracy_vs_truth"] == pytest.approx(sum(row["after"]["top"] == want[row["stamp_ns"]] for row in rows) / 6)
    assert clean_right == 6, rows        # red and blue planes: separable after one epoch

    out = tmp_path / "report"
    rc, text, err = run(["replay", held, "--model", model, "--sigma", SIGMA, "--n0", "32", "--n", "100", "--anchors", "2",
                         "--radius", "tz=0.0012,ry=0.025deg",
                         "--no-output", "--report", out, "--json", "--quiet"], capsys)
    assert rc == 0, err
    summary = json.loads(text)
    with open(out / "frames.csv", newline="") as fh:
        csv_rows = list(csv.DictReader(fh))
    assert len(csv_rows) == 6 * 2
    for axis in ("tz", "ry"):
        mine = [row for row in csv_rows if row["axis"] == axis]
        assert sorted(int(row["stamp_ns"]) for row in mine) == sorted(truth)
        correct = [row for row in mine if row["class_name"] == truth[int(row["stamp_ns"])][0]]
        certified = [row for row in correct if row["certified"] == "1"]
        s = summary["axes"][axis]
        assert s["with_truth"] == 6
        assert s["clean_accuracy"] == pytest.approx(len(correct) / 6)
        assert s["certified_accuracy"] == pytest.approx(len(certified) / 6)
        assert len(correct) == 6 and len(certified) >= 3, (axis, mine)
    assert (out / "summary.json").exists() and list(out.glob("*.png"))


def _bad_case(tmp_path: Path, capsys, case: str) -> tuple[list, str]:
    root = tmp_path / "data"
    make_folder(root)
    rec = tmp_path / "all"
    if case == "frame without a label":
        # labels for the first frames of the two first clips only (`pws import labels`); the others keep none
        assert run(["import", "frames", root, "--out", tmp_path / "first", *CAMERA, "--label-regex", REGEX, "--quiet"], capsys)[0] == 0
        (tmp_path / "l.csv").write_text("0,0.05,red\n1.1,1.15,blue\n")
        assert run(["import", "labels", tmp_path / "first", "--csv", tmp_path / "l.csv", "--relative", "--replace", "--out", rec,
                    "--quiet"], capsys)[0] == 0
        return ["--model", MODEL, "--new-head"], "no label"
    assert run(["import", "frames", root, "--out", rec, *CAMERA, "--label-regex", REGEX, "--quiet"], capsys)[0] == 0
    if case == "label outside the model's classes":
        return ["--model", MODEL], "label 'red' is not one of the model's 12 classes"
    if case == "held-out clip matches nothing":
        return ["--model", MODEL, "--new-head", "--holdout-clips", "clip9"], "--holdout-clips clip9 matches no clip"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["frame without a label", "label outside the model's classes", "held-out clip matches nothing"])
def test_bad_labelled_input_is_one_line_and_writes_no_model(tmp_path, capsys, case):
    extra, expect = _bad_case(tmp_path, capsys, case)
    model = tmp_path / "m.pt"
    rc, _text, err = run(["finetune", tmp_path / "all", *extra, "--input-size", "24x32", "--sigma", SIGMA, "--epochs", "1",
                          "--views", "0", "--out", model, "--quiet"], capsys)
    assert rc == 2, err
    assert err.startswith("pws finetune: error: ") and err.count("\n") == 1, err
    assert expect in err, err
    if case != "held-out clip matches nothing":
        assert str(tmp_path / "all") in err and "frame" in err
    assert not model.exists()


def test_real_task_table_reads_the_curve_and_names_what_limited_each_frame():
    """bench/real_task: the certified accuracy at 0/25/50/75/100% of the radius is read off the replay's
    21-point curve, and each certificate's limit follows the rule written out here."""
    from pws_ros.bench.real_task import at_fractions, limited_by

    req = 0.01
    curve = [[req * i / 20, 1.0 - i / 40] for i in range(21)]
    assert at_fractions(curve, req) == [1.0, 1.0 - 5 / 40, 1.0 - 10 / 40, 1.0 - 15 / 40, 0.5]
    row = {"correct": "1", "status": "not_certified", "radius": "0.004"}
    assert limited_by({**row, "correct": "0"}, 0.01, req) == "model (wrong class)"
    assert limited_by({**row, "status": "abstain", "radius": ""}, 0.01, req) == "model (abstained)"
    assert limited_by({**row, "status": "certified", "radius": "0.01"}, 0.01, req) == "reached"
    assert limited_by(row, 0.0042, req) == "ceiling"        # 0.004 >= 90% of the ceiling 0.0042
    assert limited_by(row, 0.01, req) == "model"            # the imaging allowed the whole radius


def test_small_cnn_backbone_with_clean_share_and_augment_trains_and_exports(tmp_path, capsys):
    """--backbone small_cnn (from scratch, grey levels) with --clean-share and --augment: one epoch on the tiny
    folder writes a model file of the label set that takes the input size and records the settings (red and
    blue planes have one grey level: no accuracy is asked of a grey-level model here)."""
    from pws_ros.core.model import load_model

    root = tmp_path / "data"
    make_folder(root)
    rec = tmp_path / "all"
    assert run(["import", "frames", root, "--out", rec, *CAMERA, "--label-regex", REGEX, "--quiet"], capsys)[0] == 0
    model = tmp_path / "small.pt"
    rc, text, err = run(["finetune", rec, "--backbone", "small_cnn", "--input-size", "24x32", "--holdout-clips", "clip2",
                         "--sigma", SIGMA, "--epochs", "1", "--views", "1", "--batch-size", "4", "--eval-samples", "5",
                         "--clean-share", "0.25", "--augment", "--out", model, "--quiet", "--json"], capsys)
    assert rc == 0, err
    report = json.loads(text)
    assert report["classes"] == ["blue", "red"] and report["new_head"]
    assert report["training"]["clean_share"] == 0.25 and report["training"]["augment"] is True
    assert report["training"]["lr"] == pytest.approx(3e-3)
    m = load_model(model)
    assert list(m.class_names) == ["blue", "red"] and m.meta.get("backbone") == "small_cnn"
    assert tuple(m(torch.rand(2, 3, 24, 32)).shape) == (2, 2)
    rc, _text, err = run(["finetune", rec, "--backbone", "small_cnn", "--holdout-clips", "clip2", "--clean-share", "1",
                          "--out", tmp_path / "x.pt", "--quiet"], capsys)
    assert rc == 2 and "--clean-share" in err and not (tmp_path / "x.pt").exists()


def test_augment_keeps_the_background_and_gains_the_drawn_pixels():
    """Trainer.augment: without a shift or scale the background pixels stay the background exactly and the
    drawn ones change by a gain within the documented range; with them the image stays in [0, 1]."""
    import pws_ros.finetune.train as T

    t = T.Trainer.__new__(T.Trainer)
    t.background = 0.5
    x = torch.full((4, 3, 12, 16), 128 / 255)
    x[:, :, 3:8, 4:10] = 0.3
    saved = (T.AUG_SHIFT, T.AUG_SCALE)
    try:
        T.AUG_SHIFT, T.AUG_SCALE = 0.0, 0.0
        y = t.augment(x.clone(), torch.Generator().manual_seed(0))
    finally:
        T.AUG_SHIFT, T.AUG_SCALE = saved
    bg = torch.ones_like(x, dtype=torch.bool)
    bg[:, :, 3:8, 4:10] = False
    assert torch.allclose(y[bg], x[bg], atol=1e-6)
    ratio = y[:, :, 3:8, 4:10] / 0.3
    assert ((ratio > 0.6 * 0.8 - 1e-6) & (ratio < 1.4 * 1.2 + 1e-6)).all() and not torch.allclose(ratio, torch.ones_like(ratio))
    moved = t.augment(x.clone(), torch.Generator().manual_seed(1))
    assert moved.shape == x.shape and float(moved.min()) >= 0.0 and float(moved.max()) <= 1.0


def test_a_ceiling_file_of_other_settings_is_refused(tmp_path):
    """bench/real_task --ceiling FILE: a file measured at another sigma (or, where it records them, another
    input size or other options) would put another imaging's ceiling beside the model: refused, naming the
    file and what differs; one of these settings is read."""
    from pws_ros.bench.real_task import _check_ceiling

    here = {"recording": "/data/held", "size": [60, 80], "sigma": 0.25, "options": ["--window", "0.3"]}
    path = tmp_path / "ceiling.json"
    old_style = {"sigma": 0.35, "rows": [{"recording": "/data/held"}]}     # `pws ceiling --json` as written before
    with pytest.raises(SystemExit, match=r"ceiling\.json was measured with other settings: sigma 0\.35 \(here 0\.25\)"):
        _check_ceiling(path, old_style, here)
    _check_ceiling(path, dict(old_style, sigma=0.25), here)
    with pytest.raises(SystemExit, match=r"options \['--window', '0\.5'\]"):
        _check_ceiling(path, {"made_with": dict(here, options=["--window", "0.5"])}, here)
    with pytest.raises(SystemExit, match=r"size \[120, 160\]"):
        _check_ceiling(path, {"made_with": dict(here, size=[120, 160])}, here)
    _check_ceiling(path, {"made_with": dict(here)}, here)

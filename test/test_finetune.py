"""pws finetune: a noise-fragile model tuned on the demo recording gains agreement under noise on
held-out frames; the hold-out is never trained on; an interrupted run resumed gives the same weights;
bad input is one line and exit 2.

The tiny model is the shipped demo classifier trained at sigma 0.25, tuned and measured at sigma 1.0
(before tuning it loses its clean prediction on most held-out demo frames at that noise)."""
from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import REPO
from pws_ros.cli import main as pws_main
from pws_ros.finetune import FinetuneOptions, finetune
from pws_ros.finetune import train as ft_train
from pws_ros.finetune.cache import RecordingCache, _read_lines
from pws_ros.replay.options import load_replay_config

DEMO = REPO / "bags" / "demo"
MODEL = REPO / "bags" / "models" / "classifier_sigma0.25.pt"
SIGMA = 1.0


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One thread for every run here (the module-scoped baseline included): equal weights are compared bit for bit."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def options(tmp: Path, **kw) -> FinetuneOptions:
    base = dict(bags=[DEMO], model=MODEL, out=tmp / "tuned.pt", config=load_replay_config(REPO / "config" / "pws.yaml"),
                sigma=SIGMA, holdout=0.5, views=2, epochs=3, batch_size=4, use_truth=False, eval_samples=50, seed=3,
                progress=False, log=lambda level, msg: None)
    base.update(kw)
    return FinetuneOptions(**base)


def weights(path: Path) -> dict[str, torch.Tensor]:
    from pws_ros.core.model import quiet_jit

    with quiet_jit():   # (torch.jit.load warns that TorchScript is deprecated, as the package's own loads do not)
        return dict(torch.jit.load(str(path)).state_dict())


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    """One uninterrupted run (label-free), recording which cached frames the training read."""
    tmp = tmp_path_factory.mktemp("finetune")
    read: list[tuple[int, int]] = []
    orig = ft_train.TrainSet.batch

    def spy(self, items):
        for f in (np.asarray(items) // self.views).tolist():
            ci, k = self.frames[f]
            read.append((int(ci), int(self.caches[ci].frames[k]["stamp_ns"])))
        return orig(self, items)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ft_train.TrainSet, "batch", spy)
        result = finetune(options(tmp, keep_work=True))
    return tmp, result, read


def test_tuning_gains_agreement_under_noise_on_heldout_frames(baseline):
    _tmp, result, _read = baseline
    assert result.exit_code == 0 and result.model_path.is_file() and result.report_path.is_file()
    r = json.loads(result.report_path.read_text())
    before, after = r["before"], r["after"]
    assert before["frames"] == after["frames"] == 4
    # measured against the untuned model on the same held-out frames and the same noise draws
    assert after["p_teacher_mean"] > before["p_teacher_mean"] + 0.2, (before, after)
    assert after["agreement"] > before["agreement"], (before, after)
    assert after["p_a_quantiles"]["q50"] >= 0.5
    # the model file is the contract: loads, records sigma and what it was tuned on, runs on the frames
    from pws_ros.core.model import load_model

    m = load_model(result.model_path)
    assert m.meta["sigma"] == SIGMA and m.meta["finetune"]["mode"] == "classifier"
    assert m.meta["finetune"]["recordings"][0]["held_out"] == 4 and m.meta["finetune"]["from_sigma"] == 0.25
    assert m.input_size == (90, 160) and len(m.class_names) == 12


def test_heldout_frames_are_never_trained_on(baseline):
    _tmp, result, read = baseline
    held = {row["stamp_ns"] for row in result.report["per_frame"]}
    trained = {stamp for _ci, stamp in read}
    assert len(held) == 4 and len(trained) == 4 and not held & trained
    assert max(trained) < min(held)          # by time: the last part of the recording is held out
    first = result.report["recordings"][0]
    assert first["trained_on"] + first["held_out"] == first["frames"] == 8


def test_split_by_time():
    def cache(n):
        return RecordingCache(0, "rec", Path("."), np.zeros((n, 1, 2, 2, 3), np.uint8), np.zeros((n, 2), np.float32),
                              [{"index": i} for i in range(n)])

    assert cache(8).split(0.2) == (range(0, 6), range(6, 8))
    assert cache(10).split(0.2) == (range(0, 8), range(8, 10))
    assert cache(2).split(0.2) == (range(0, 1), range(1, 2))
    for n, h in ((1, 0.2), (8, 0.9)):
        with pytest.raises(Exception, match="too few"):
            cache(n).split(h)


def test_teacher_stability_marks_frames_whose_answer_noise_or_motion_changes():
    """Three frames, checked against answers worked out by hand: frame 0's teacher looks at a pixel far
    from its threshold (stable), frame 1's at a pixel on the threshold (noise flips it about half the
    time), frame 2's motion view changes that pixel (motion flips it)."""
    from pws_ros.finetune.evaluate import STABILITY_SAMPLES, stability_summary, summarize, teacher_stability

    views = np.zeros((3, 2, 4, 4, 3), np.uint8)
    views[0, :, 0, 0, 0] = 200            # far above the threshold in both views
    views[1, :, 0, 0, 0] = 128            # 128/255 = 0.50196: the threshold, within noise of 0.01
    views[2, 0, 0, 0, 0] = 200
    views[2, 1, 0, 0, 0] = 10             # the motion view crosses the threshold
    cache = RecordingCache(0, "rec", Path("."), views, np.zeros((3, 2), np.float32), [{"index": i} for i in range(3)])

    def teacher(x):                        # class 1 where the pixel is at least 128/255, else 0
        above = (x[:, 0, 0, 0] >= 128 / 255).float()
        return torch.stack([1 - above, above], dim=1)

    top = np.array([1, 1, 1])
    st = teacher_stability(teacher, [cache], [(0, 0), (0, 1), (0, 2)], top, seed=0, device=torch.device("cpu"))
    assert st["noise"][0] == 1.0 and st["noise"][2] == 1.0
    assert 0.1 <= st["noise"][1] <= 0.9, st["noise"]          # about half of the copies fall below
    assert list(st["motion"]) == [1.0, 1.0, 0.0]
    assert list(st["stable"]) == [True, False, False]
    assert list(st["motion_views"]) == [1, 1, 1]
    summ = stability_summary(st)
    assert summ["stable_frames"] == 1 and summ["frames"] == 3 and summ["samples"] == STABILITY_SAMPLES
    assert summ["frames_with_motion_views"] == 3
    # a recording evaluated without motion views: only the noise is tested, and the summary says so
    alone = RecordingCache(0, "rec", Path("."), views[:, :1].copy(), np.zeros((3, 1), np.float32), [{"index": i} for i in range(3)])
    st0 = teacher_stability(teacher, [alone], [(0, 0), (0, 2)], top[:2], seed=0, device=torch.device("cpu"))
    assert list(st0["motion_views"]) == [0, 0] and list(st0["stable"]) == [True, True]
    assert stability_summary(st0)["frames_with_motion_views"] == 0
    counts = np.array([[0, 10], [10, 0], [0, 10]])         # a smoothed answer: 1, 0, 1
    out = summarize(counts, top, np.full(3, -1), sigma=0.25, stable=st["stable"])
    assert out["agreement"] == pytest.approx(2 / 3) and out["agreement_on_stable"] == 1.0 and out["stable_frames"] == 1


def test_report_states_the_teachers_stability(baseline):
    _tmp, result, _read = baseline
    r = result.report
    st = r["teacher_stability"]
    assert st["frames"] == 4 and 0 <= st["stable_frames"] <= 4
    assert sum(row["teacher_stable"] for row in r["per_frame"]) == st["stable_frames"]
    assert ("agreement_on_stable" in r["after"]) and r["after"]["stable_frames"] == st["stable_frames"]


def test_resume_after_interrupt_gives_the_same_weights(baseline, tmp_path):
    _tmp, base, _read = baseline
    stop_at = 4   # mid-epoch (3 steps an epoch): the checkpoint is the one written on SIGINT

    def interrupt(step):
        if step == stop_at:
            os.kill(os.getpid(), signal.SIGINT)

    first = finetune(options(tmp_path, on_step=interrupt))
    assert first.exit_code == 130 and first.interrupted == "SIGINT" and "--resume" in first.message
    assert not (tmp_path / "tuned.pt").exists()
    state = torch.load(tmp_path / "tuned.pt.work" / "checkpoint.pt", weights_only=True)
    assert state["step"] == stop_at and state["total"] == 9
    steps = []
    second = finetune(options(tmp_path, resume=True, on_step=steps.append))
    assert second.exit_code == 0 and steps == list(range(stop_at + 1, 10))
    a, b = weights(base.model_path), weights(second.model_path)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert second.report["after"] == base.report["after"]
    assert not (tmp_path / "tuned.pt.work").exists()   # removed after a finished run


def test_interrupt_while_caching_frames_resumes_at_the_next_frame(baseline, tmp_path, monkeypatch):
    from pws_ros.finetune import cache as ft_cache

    _tmp, base, _read = baseline
    orig, calls = ft_cache.FramePreparer._one, []

    def one(self, rec, frame, rec_index):
        calls.append(frame.index)
        if frame.index == 3 and len(calls) == 4:
            os.kill(os.getpid(), signal.SIGTERM)   # after frame 2 is committed, while frame 3 is rendered
        return orig(self, rec, frame, rec_index)

    monkeypatch.setattr(ft_cache.FramePreparer, "_one", one)
    first = finetune(options(tmp_path))
    assert first.exit_code == 143 and first.interrupted == "SIGTERM" and "caching" in first.message
    assert len(_read_lines(tmp_path / "tuned.pt.work" / "rec000" / "frames.jsonl")) == 3   # frames 0-2 committed
    second = finetune(options(tmp_path, resume=True))
    assert second.exit_code == 0 and calls[4:] == [3, 4, 5, 6, 7]   # the resumed run renders from frame 3 on
    a, b = weights(base.model_path), weights(second.model_path)
    assert all(torch.equal(a[k], b[k]) for k in a) and second.report["after"] == base.report["after"]


def test_another_seed_gives_other_weights(baseline, tmp_path):
    _tmp, base, _read = baseline
    other = finetune(options(tmp_path, seed=4, epochs=1))
    a, b = weights(base.model_path), weights(other.model_path)
    assert any(not torch.equal(a[k], b[k]) for k in a)


def test_cache_drops_a_line_cut_by_a_kill(tmp_path):
    p = tmp_path / "frames.jsonl"
    p.write_text('{"index": 0}\n{"index": 1}\n{"ind')
    assert _read_lines(p) == [{"index": 0}, {"index": 1}]


def test_denoiser_mode_writes_a_model_and_a_denoiser(tmp_path):
    from pws_ros.core.model import load_denoiser, load_model

    res = finetune(options(tmp_path, mode="denoiser", epochs=1, denoiser_channels=8, denoiser_depth=3, eval_samples=8))
    assert res.exit_code == 0 and res.report["mode"] == "denoiser"
    model = load_model(res.model_path)
    den = load_denoiser(tmp_path / "tuned.denoiser.pt")
    clf = load_model(MODEL)
    x = torch.rand(2, 3, 90, 160)
    assert torch.allclose(model(x), clf(den(x)), atol=1e-5)
    assert model.meta["finetune"]["mode"] == "denoiser" and den.meta["sigma"] == SIGMA


# ---- bad input: one line, exit 2 ----------------------------------------------------------------

def run_cli(argv, capsys):
    rc = pws_main(["finetune", *[str(a) for a in argv]])
    out, err = capsys.readouterr()
    return rc, out, err


def _bag_without_camera(path: Path) -> Path:
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin

    from pws_ros.bagio import BagReader
    from pws_ros.bridge import msgbuild

    ts = msgbuild.rosbags_types().typestore
    with BagReader(DEMO) as bag, Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/pws/ground_truth", "diagnostic_msgs/msg/DiagnosticArray", typestore=ts)
        for m in bag.messages(["/pws/ground_truth"]):
            w.write(conn, m.log_time_ns, bytes(m.data))
    return path


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad_model = tmp_path / "bad.pt"
    bad_model.write_text("not a model")
    out = tmp_path / "o.pt"
    common = ["--out", out, "--quiet", "--views", "1", "--epochs", "1", "--eval-samples", "4"]
    cases = [
        ([DEMO, "--model", bad_model, "--sigma", "0.5"], "is not a TorchScript archive"),
        ([DEMO, "--model", MODEL, "--sigma", "0"], "--sigma must be a positive number"),
        ([DEMO, "--model", MODEL, "--sigma", "-1"], "--sigma must be a positive number"),
        ([_bag_without_camera(tmp_path / "nocam"), "--model", MODEL, "--sigma", "0.5"], "no camera input"),
        ([DEMO, "--model", MODEL, "--sigma", "0.5", "--max-frames", "1"], "too few to hold the last 20% out"),
        ([DEMO, "--model", MODEL, "--sigma", "0.5", "--holdout", "1"], "--holdout must lie strictly between 0 and 1"),
        ([tmp_path / "missing", "--model", MODEL, "--sigma", "0.5"], "recording not found"),
        ([DEMO, "--model", MODEL, "--sigma", "0.5", "--device", "cuda:99"], "cuda"),
    ]
    for argv, words in cases:
        rc, stdout, err = run_cli([*argv, *common, "--overwrite"], capsys)
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1 and lines[0].startswith("pws finetune: error:") and words in lines[0], (argv, err)
        assert not out.exists() and stdout == ""
    # a refused input leaves no work folder behind (it would block the next run: "exists, pass --resume")
    fresh = ["--out", tmp_path / "o2.pt", *common[2:]]   # (a case above cached a frame: its work folder stays, for --resume)
    rc, _o, err = run_cli([_bag_without_camera(tmp_path / "nocam2"), "--model", MODEL, "--sigma", "0.5", *fresh], capsys)
    assert rc == 2 and "no camera input" in err and not (tmp_path / "o2.pt.work").exists()
    afile = tmp_path / "afile"
    afile.write_text("")
    rc, _o, err = run_cli([DEMO, "--model", MODEL, "--sigma", "0.5", "--out", afile / "o.pt", "--quiet"], capsys)
    assert rc == 2 and "is a file, not a folder" in err and "Traceback" not in err


def test_existing_work_folder_needs_resume_or_overwrite(tmp_path, capsys):
    (tmp_path / "o.pt.work").mkdir()
    (tmp_path / "o.pt.work" / "manifest.json").write_text("{}")
    rc, _out, err = run_cli([DEMO, "--model", MODEL, "--out", tmp_path / "o.pt", "--sigma", "0.5"], capsys)
    assert rc == 2 and "--resume" in err and "--overwrite" in err


def test_help_explains(capsys):
    with pytest.raises(SystemExit) as exc:
        pws_main(["finetune", "--help"])
    text = capsys.readouterr().out
    assert exc.value.code == 0
    for words in ("teacher", "without labels", "--holdout", "--resume", "--mode", "denoiser", "report", "pws replay --model"):
        assert words in text, words


def _tiny_bench(tmp_path, extra=()):
    import torch.nn as nn

    import cv2

    from pws_ros.core.model import save_model
    from test_import_tum import tum_folder

    if not (tmp_path / "seq").exists():
        tum_folder(tmp_path / "seq", n=5)
        ramp = (5000 + 80 * np.arange(64)[None, :] + 40 * np.arange(48)[:, None]).astype(np.uint16)   # 1.0 - 1.7 m, smooth
        for f in (tmp_path / "seq" / "depth").glob("*.png"):
            cv2.imwrite(str(f), ramp)
    if not (tmp_path / "tiny.pt").exists():
        torch.manual_seed(0)
        net = nn.Sequential(nn.Conv2d(3, 4, 3, 2, 1), nn.BatchNorm2d(4), nn.ReLU(), nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(4, 3))
        save_model(net, tmp_path / "tiny.pt", ["a", "b", "c"], input_size=(18, 32))
    return [str(tmp_path / "seq"), "--work", str(tmp_path / "work"), "--model", str(tmp_path / "tiny.pt"), "--sigmas", "0.5",
            "--frames", "5", "--eval-samples", "8", "--epochs", "1", "--views", "1", "--holdout", "0.4", "--json", "--border", "0",
            "--config", str(REPO / "config" / "pws.yaml"), "--n0", "8", "--n", "16", "--anchors", "2", *extra]


def test_benchmark_script_runs_on_a_tiny_model(tmp_path, capsys, monkeypatch):
    """pws_ros.bench.finetune_bench end to end on a synthetic TUM-format sequence and a tiny model
    (the EfficientNet-Lite0 run itself is too long for the test machine): agreement, then per certified
    frame and axis the tuned model's radius next to the ceiling of pws_ros.replay.ceiling; --resume
    reuses what bench.json holds."""
    from pws_ros.bench import finetune_bench as fb
    from pws_ros.bagio.reader import BagReader

    from pws_ros.importing.tum import convert

    work = tmp_path / "work"
    args = _tiny_bench(tmp_path, ["--eval", str(tmp_path / "one"), "--certify-heldout", "1"])
    assert convert(tmp_path / "seq", tmp_path / "one", frames=1) == 1      # another recording, one frame
    calls = []
    real = fb.certify_recording
    monkeypatch.setattr(fb, "certify_recording", lambda bag, *a, **k: calls.append(Path(bag)) or real(bag, *a, **k))
    rc = fb.main(args)
    out, err = capsys.readouterr()
    assert rc == 0, err
    rows = json.loads(out)
    entry = rows["sigmas"]["0.5"]
    assert entry["heldout"]["after"]["frames"] == 2 and entry["frames"][0]["trained_on"] == 3
    (rec,) = entry["recordings"].values()
    assert rec["original"]["frames"] == rec["tuned"]["frames"] == 1
    assert (work / "bench.json").is_file() and (work / "tuned_sigma0.50.pt").is_file()
    # certification: one held-out frame (of the two, spread evenly: the second) and the frame of --eval, per axis
    cert = entry["certified"]
    assert set(cert) == {"held-out", str(tmp_path / "one")}
    report = json.loads(Path(entry["report"]).read_text())
    held_stamps = [f["stamp_ns"] for f in report["per_frame"]]
    assert [r["stamp_ns"] for r in cert["held-out"]] == [held_stamps[1]] * 2       # tz and ry of that frame, nothing else
    assert {r["teacher"] for r in cert["held-out"]} == {report["per_frame"][1]["teacher"]}
    with BagReader(work / "heldout_sigma0.50") as reader:                            # the bag certified holds only that frame
        assert {m.log_time_ns for m in reader.messages()} == {held_stamps[1]}
    assert len(cert[str(tmp_path / "one")]) == 2
    for r in cert["held-out"] + cert[str(tmp_path / "one")]:
        assert r["axis"] in ("tz", "ry") and r["ceiling"] > 0 and r["requested"] > 0
        assert r["model"] is not None and r["model"] >= 0
        assert r["ratio"] == pytest.approx(r["model"] / r["ceiling"])
    med = entry["certified_medians"]
    assert set(med) == {"tz", "ry"} and med["tz"]["frames"] == 2
    assert med["tz"]["ratio_median"] == pytest.approx(float(np.median(
        [r["ratio"] for rs in cert.values() for r in rs if r["axis"] == "tz"])))
    text = fb.table(rows)
    assert "ceiling" in text and "median radius / ceiling" in text and "held-out" in text
    assert rec["teacher_stability"]["frames_with_motion_views"] == 0          # --eval recordings: no motion views
    assert entry["heldout"]["teacher_stability"]["frames_with_motion_views"] == 2
    assert "no motion views there: stable means under the noise alone" in text
    assert len(calls) == 2
    # --resume: nothing is tuned, evaluated or certified again; the same rows come back
    monkeypatch.setattr(fb, "evaluate_recording", lambda *a, **k: pytest.fail("evaluated again"))
    import pws_ros.finetune as ft
    monkeypatch.setattr(ft, "finetune", lambda *a, **k: pytest.fail("tuned again"))
    rc = fb.main(args + ["--resume"])
    again = json.loads(capsys.readouterr().out)
    assert rc == 0 and len(calls) == 2
    assert again["sigmas"]["0.5"]["certified"] == cert and again["sigmas"]["0.5"]["heldout"] == entry["heldout"]
    # --resume with another --certify-heldout certifies the held-out frames again (both now), the rest is kept
    rc = fb.main(_tiny_bench(tmp_path, ["--eval", str(tmp_path / "one"), "--certify-heldout", "2", "--resume"]))
    third = json.loads(capsys.readouterr().out)["sigmas"]["0.5"]["certified"]
    assert rc == 0 and calls[2:] == [work / "heldout_sigma0.50"]
    assert sorted({r["stamp_ns"] for r in third["held-out"]}) == sorted(held_stamps)
    assert third[str(tmp_path / "one")] == cert[str(tmp_path / "one")]


def test_benchmark_resume_retunes_when_the_settings_differ(tmp_path, capsys):
    """A tuned model of other settings (here 2 epochs instead of 1) is not reused by --resume."""
    from pws_ros.bench import finetune_bench as fb

    assert fb.main(_tiny_bench(tmp_path, ["--no-certify"])) == 0
    first = json.loads(capsys.readouterr().out)["sigmas"]["0.5"]
    assert first["certified"] == {}
    assert fb.main(_tiny_bench(tmp_path, ["--no-certify", "--resume", "--epochs", "2"])) == 0
    second = json.loads(capsys.readouterr().out)["sigmas"]["0.5"]
    from pws_ros.core.model import load_model
    assert load_model(tmp_path / "work" / "tuned_sigma0.50.pt").meta["finetune"]["epochs"] == 2
    assert second["heldout"]["after"]["frames"] == 2


def test_pick_evenly():
    from pws_ros.bench.finetune_bench import pick_evenly

    assert pick_evenly(list(range(16)), 3) == [0, 8, 15]     # round(7.5) = 8 (banker's rounding)
    assert pick_evenly([1, 2], 5) == [1, 2] and pick_evenly([1, 2, 3], 1) == [2] and pick_evenly([1], 0) == []

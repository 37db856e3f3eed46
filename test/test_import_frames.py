"""`pws import frames` and `pws import labels`: a labelled folder of RGB-D clips made here, imported,
and read back with the project's bag reader; every value checked against what the test wrote (depth
in metres, colours, intrinsics, stamps laid end to end, label and clip of each frame); bad input is a
one-line error naming the file, with nothing left at OUT."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pws_ros.bagio import BagReader
from pws_ros.bridge import msgconv
from pws_ros.cli import main as pws_main

H, W = 24, 32
COLOR = "/camera/color/image_raw"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/color/camera_info"
TRUTH = "/pws/ground_truth"
# clip -> (label, frame count, depth scale in metres per unit, depth storage)
CLIPS = {"bottle/clip1": ("bottle", 2, 0.00025, "npy"), "cup/clipA": ("cup", 3, 0.001, "npy"),
         "cup/clipB": ("cup", 2, 0.00025, "png")}
GESTURE_REGEX = "^G[0-9]+_(?P<label>[^/]+)/"


def make_folder(root: Path) -> dict[str, dict]:
    """The clips of CLIPS under ``root``; returns per colour file (relative path) its rgb, raw depth, scale."""
    rng = np.random.default_rng(1)
    frames = {}
    for clip, (_label, n, scale, kind) in CLIPS.items():
        rgb_dir = root / clip / "rgb"
        depth_dir = root / clip / ("depth_raw" if kind == "npy" else "depth")
        rgb_dir.mkdir(parents=True)
        depth_dir.mkdir()
        if clip == "cup/clipA":   # its own scale (depth_metadata.json); the others take the folder's
            (root / clip / "depth_metadata.json").write_text(json.dumps({"depth_scale": scale, "unit": "m"}))
        for i in range(1, n + 1):
            rgb = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
            raw = rng.integers(500, 4000, (H, W)).astype(np.uint16)
            raw[0, 0] = 0                     # no depth
            raw[5, 7] = round(1.234 / scale)  # 1.234 m
            cv2.imwrite(str(rgb_dir / f"frame_{i:03d}.png"), rgb[..., ::-1])   # PNGs hold BGR
            if kind == "npy":
                np.save(depth_dir / f"frame_{i:03d}.npy", raw)
            else:
                cv2.imwrite(str(depth_dir / f"frame_{i:03d}.png"), raw)
            frames[f"{clip}/rgb/frame_{i:03d}.png"] = {"rgb": rgb, "raw": raw, "scale": scale}
    (root / "depth_metadata.json").write_text(json.dumps({"depth_scale": 0.00025}))
    return frames


def read_back(bag: Path) -> dict[int, dict]:
    """stamp -> {topic: decoded message}, read with pws_ros.bagio.BagReader."""
    out: dict[int, dict] = {}
    with BagReader(bag) as r:
        for m in r.messages():
            msg = r.deserialize(m)
            stamp = msgconv.header_stamp_ns(msg)
            assert m.log_time_ns == stamp
            out.setdefault(stamp, {})[m.topic] = msg
    return out


def truth_values(msg) -> dict[str, str]:
    (status,) = msg.status
    assert status.name == "ground_truth"
    return {kv.key: kv.value for kv in status.values}


def run(argv, capsys) -> tuple[int, str, str]:
    rc = pws_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def nothing_at(out: Path) -> bool:
    """OUT absent and no hidden partial folder beside it."""
    return not out.exists() and not list(out.parent.glob(f".{out.name}.partial-*"))


@pytest.fixture
def folder(tmp_path):
    root = tmp_path / "data"
    return root, make_folder(root)


def test_import_reads_back_depth_colour_intrinsics_stamps_labels_and_clips(folder, tmp_path, capsys):
    root, files = folder
    out = tmp_path / "rec"
    rc, text, err = run(["import", "frames", root, "--out", out, "--intrinsics", "30,31,15.5,11.5", "--rate", "10", "--gap", "0.5",
                         "--start", "100", "--quiet"], capsys)
    assert rc == 0, err
    assert "7 frame(s) from 3 clip(s)" in text and "bottle 2, cup 5" in text
    got = read_back(out)
    # clips in name order, frames 0.1 s apart by position, 0.5 s between clips
    order = [("bottle/clip1", 0, 1), ("bottle/clip1", 1, 2), ("cup/clipA", 0, 1), ("cup/clipA", 1, 2), ("cup/clipA", 2, 3),
             ("cup/clipB", 0, 1), ("cup/clipB", 1, 2)]
    clip_start = {"bottle/clip1": 100.0, "cup/clipA": 100.0 + 0.2 + 0.5, "cup/clipB": 100.7 + 0.3 + 0.5}
    expect_stamps = [int(round((clip_start[c] + k * 0.1) * 1e9)) for c, k, _ in order]
    assert sorted(got) == expect_stamps
    for stamp, (clip, k, number) in zip(expect_stamps, order):
        msgs = got[stamp]
        assert set(msgs) == {COLOR, DEPTH, INFO, TRUTH}
        ref = files[f"{clip}/rgb/frame_{number:03d}.png"]
        np.testing.assert_array_equal(msgconv.image_to_numpy(msgs[COLOR]), ref["rgb"])
        depth = msgs[DEPTH]
        assert depth.encoding == "16UC1"
        metres = msgconv.image_to_numpy(depth).astype(np.float64) / 1000.0
        assert metres[0, 0] == 0.0 and metres[5, 7] == pytest.approx(1.234, abs=1e-12)
        np.testing.assert_allclose(metres, ref["raw"] * ref["scale"], atol=0.0005 + 1e-12)
        info = msgs[INFO]
        assert (info.width, info.height) == (W, H)
        assert list(info.k) == [30.0, 0.0, 15.5, 0.0, 31.0, 11.5, 0.0, 0.0, 1.0]
        assert depth.header.frame_id == msgs[COLOR].header.frame_id == info.header.frame_id
        v = truth_values(msgs[TRUTH])
        assert v == {"class_name": CLIPS[clip][0], "clip": clip, "clip_index": str(list(CLIPS).index(clip)),
                     "frame_index": str(k), "file": f"{clip}/rgb/frame_{number:03d}.png"}


def test_replay_and_finetune_read_the_labels(folder, tmp_path, capsys):
    """The truth as pws replay --report and pws finetune read it (their readers, no model needed)."""
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.finetune.frames import RecordingFrames

    root, _files = folder
    classes = tmp_path / "classes.txt"
    classes.write_text("plate\ncup\nbottle\n")
    out = tmp_path / "rec"
    rc, _text, err = run(["import", "frames", root, "--out", out, "--intrinsics", "30,30,15.5,11.5", "--classes", classes, "--quiet"], capsys)
    assert rc == 0, err
    seen = []
    with RecordingFrames(out, PwsConfig()) as rec:
        assert rec.inputs.truth == TRUTH and rec.inputs.depth == DEPTH and rec.inputs.color == COLOR
        for f in rec:
            assert rec.convert(f) is not None
            seen.append((f.truth.class_name, f.truth.label, f.truth.values["clip"]))
    assert seen == [("bottle", 2, "bottle/clip1")] * 2 + [("cup", 1, "cup/clipA")] * 3 + [("cup", 1, "cup/clipB")] * 2


def test_selection_gesture_regex_and_csv_labels(tmp_path, capsys):
    root = tmp_path / "g"
    for clip in ("G01_call/clip02", "G01_call/clip04", "G10_three/clip04"):
        (root / clip / "rgb").mkdir(parents=True)
        (root / clip / "depth_raw").mkdir()
        for i in range(1, 4):
            cv2.imwrite(str(root / clip / "rgb" / f"frame_{i:03d}.png"), np.full((H, W, 3), 10 * i, np.uint8))
            np.save(root / clip / "depth_raw" / f"frame_{i:03d}.npy", np.full((H, W), 1000, np.uint16))
    out = tmp_path / "f2"
    rc, _t, err = run(["import", "frames", root, "--out", out, "--intrinsics", "615,615,320,240", "--depth-scale", "0.001",
                       "--label-regex", GESTURE_REGEX, "--clips", "*/clip04", "--frames", "2", "--quiet", "--start", "0", "--gap", "1"], capsys)
    assert rc == 0, err
    got = read_back(out)
    # frame_002 is position 1 of its clip: 1/30 s in; the second clip starts 3/30 s + 1 s after the first
    period = 33_333_333   # 1/30 s in ns
    assert sorted(got) == [period, 3 * period + 10**9 + period]
    assert [truth_values(got[s][TRUTH])["class_name"] for s in sorted(got)] == ["call", "three"]
    assert [truth_values(got[s][TRUTH])["clip"] for s in sorted(got)] == ["G01_call/clip04", "G10_three/clip04"]
    # a CSV: a folder row for the whole clip, a file row that overrides it
    csv = tmp_path / "labels.csv"
    csv.write_text("file,label\nG01_call,waving\nG01_call/clip04/rgb/frame_003.png,fist\nG10_three,three\n")
    out2 = tmp_path / "csv"
    rc, _t, err = run(["import", "frames", root, "--out", out2, "--intrinsics", "615,615,320,240", "--depth-scale", "0.001",
                       "--labels", csv, "--quiet"], capsys)
    assert rc == 0, err
    got = read_back(out2)
    labels = [(truth_values(got[s][TRUTH])["file"], truth_values(got[s][TRUTH])["class_name"]) for s in sorted(got)]
    assert labels == [(f"G01_call/clip02/rgb/frame_00{i}.png", "waving") for i in (1, 2, 3)] + \
        [("G01_call/clip04/rgb/frame_001.png", "waving"), ("G01_call/clip04/rgb/frame_002.png", "waving"),
         ("G01_call/clip04/rgb/frame_003.png", "fist")] + [(f"G10_three/clip04/rgb/frame_00{i}.png", "three") for i in (1, 2, 3)]


def _corrupt(root: Path, case: str, tmp_path: Path) -> tuple[list, str]:
    """Spoil the folder for one bad-input case: (extra arguments, the text the error must hold)."""
    a = root / "cup/clipA"
    if case == "no label (regex)":
        return ["--label-regex", "^cup/"], str(root / "bottle/clip1/rgb/frame_001.png")
    if case == "no label (csv)":
        (tmp_path / "l.csv").write_text("cup,cup\n")
        return ["--labels", tmp_path / "l.csv"], str(root / "bottle/clip1/rgb/frame_001.png")
    if case == "label outside the classes":
        (tmp_path / "c.txt").write_text("cup\nplate\n")
        return ["--classes", tmp_path / "c.txt"], str(root / "bottle/clip1/rgb/frame_001.png") + ": label 'bottle' is not one of"
    if case == "sizes differ":
        np.save(a / "depth_raw/frame_002.npy", np.ones((H // 2, W // 2), np.uint16))
        return [], f"{a / 'depth_raw/frame_002.npy'} (16x12) and {a / 'rgb/frame_002.png'} (32x24) differ in size"
    if case == "missing depth file":
        (a / "depth_raw/frame_003.npy").unlink()
        return [], f"{a / 'rgb/frame_003.png'}: no depth file {a / 'depth_raw/frame_003'}"
    if case == "depth scale 0":
        return ["--depth-scale", "0"], "--depth-scale: the depth scale must be positive"
    if case == "depth scale negative (json)":
        (a / "depth_metadata.json").write_text('{"depth_scale": -0.001}')
        return [], f"{a / 'depth_metadata.json'}: the depth scale must be positive"
    if case == "unreadable colour image":
        (a / "rgb/frame_002.png").write_bytes(b"not a png")
        return [], f"{a / 'rgb/frame_002.png'}: not a readable image"
    if case == "unreadable depth file":
        (a / "depth_raw/frame_001.npy").write_bytes(b"garbage")
        return [], f"{a / 'depth_raw/frame_001.npy'}: not a readable .npy array"
    if case == "8-bit depth picture":
        d = root / "cup/clipB/depth/frame_001.png"
        cv2.imwrite(str(d), np.zeros((H, W), np.uint8))
        return [], f"{d}: not a depth image"
    if case == "camera file of another size":
        from pws_ros.core.camera import CameraIntrinsics

        CameraIntrinsics(640, 480, 615, 615, 320, 240).to_yaml(tmp_path / "cam.yaml")
        return ["--camera-info", tmp_path / "cam.yaml"], f"is 32x24 but camera file {tmp_path / 'cam.yaml'} is for 640x480 images"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["no label (regex)", "no label (csv)", "label outside the classes", "sizes differ", "missing depth file",
                                  "depth scale 0", "depth scale negative (json)", "unreadable colour image", "unreadable depth file",
                                  "8-bit depth picture", "camera file of another size"])
def test_bad_input_names_the_file_and_leaves_nothing(folder, tmp_path, capsys, case):
    root, _files = folder
    extra, expect = _corrupt(root, case, tmp_path)
    out = tmp_path / "out"
    camera = [] if "--camera-info" in extra else ["--intrinsics", "30,30,15.5,11.5"]
    rc, _text, err = run(["import", "frames", root, "--out", out, *camera, "--quiet", *extra], capsys)
    assert rc == 2
    assert err.startswith("pws import: error: ") and err.count("\n") == 1, err
    assert expect in err, err
    assert nothing_at(out)


def test_existing_out_is_refused_and_an_interrupt_leaves_nothing(folder, tmp_path, capsys, monkeypatch):
    root, _files = folder
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    args = ["import", "frames", root, "--out", out, "--intrinsics", "30,30,15.5,11.5", "--quiet"]
    rc, _t, err = run(args, capsys)
    assert rc == 2 and "already exists" in err and (out / "notes.txt").read_text() == "mine"
    rc, _t, err = run([*args, "--overwrite"], capsys)
    assert rc == 2 and "not a rosbag2 bag directory" in err and (out / "notes.txt").read_text() == "mine"
    # Ctrl-C on the third frame: nothing at OUT
    from pws_ros.importing import write

    real, calls = write.read_color, []

    def stop_on_third(path):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(path)

    monkeypatch.setattr(write, "read_color", stop_on_third)
    new = tmp_path / "new"
    rc, _t, err = run([*args[:4], new, *args[5:]], capsys)
    assert rc == 130 and nothing_at(new)


def _recording_without_labels(tmp_path: Path, capsys) -> tuple[Path, list[int]]:
    from test_import_tum import tum_folder

    tum_folder(tmp_path / "seq", n=5)   # frames 0.033 s apart
    bag = tmp_path / "plain"
    rc, _t, err = run(["import", "tum", tmp_path / "seq", "--out", bag, "--quiet"], capsys)
    assert rc == 0, err
    stamps = sorted(read_back(bag))
    assert len(stamps) == 5 and all(abs(b - a - 33_000_000) < 1000 for a, b in zip(stamps, stamps[1:]))
    return bag, stamps


def test_labels_attach_round_trip(tmp_path, capsys):
    bag, stamps = _recording_without_labels(tmp_path, capsys)
    # frames 0.033 s apart: relative intervals for frames 0-1 and 3, a stamp in ns for frame 4; frame 2 stays unlabelled
    csv = tmp_path / "labels.csv"
    csv.write_text("start,end,label,clip\n0,0.04,cup,a\n0.09,0.1,mug,b\n")
    out = tmp_path / "labelled"
    rc, text, err = run(["import", "labels", bag, "--csv", csv, "--relative", "--out", out, "--quiet"], capsys)
    assert rc == 0, err
    assert "3 labelled from 2 row(s)" in text
    got, before = read_back(out), read_back(bag)
    assert sorted(got) == stamps
    labels = {s: (truth_values(m[TRUTH])["class_name"], truth_values(m[TRUTH])["clip"]) for s, m in got.items() if TRUTH in m}
    assert labels == {stamps[0]: ("cup", "a"), stamps[1]: ("cup", "a"), stamps[3]: ("mug", "b")}
    for s in stamps:   # every other message copied unchanged
        for topic in (COLOR, DEPTH, INFO):
            np.testing.assert_array_equal(np.asarray(got[s][topic].data if topic != INFO else got[s][topic].k),
                                          np.asarray(before[s][topic].data if topic != INFO else before[s][topic].k))
    # the labelled copy already has labels: refused unless --replace; a stamp row in ns (frames.csv's stamp_ns)
    csv2 = tmp_path / "stamps.csv"
    csv2.write_text(f"stamp_ns,label\n{stamps[4] + 3_000_000},plate\n")
    rc, _t, err = run(["import", "labels", out, "--csv", csv2, "--out", tmp_path / "again", "--quiet"], capsys)
    assert rc == 2 and "already has ground truth on /pws/ground_truth" in err and nothing_at(tmp_path / "again")
    rc, _t, err = run(["import", "labels", out, "--csv", csv2, "--out", tmp_path / "again", "--replace", "--quiet"], capsys)
    assert rc == 0, err
    got = read_back(tmp_path / "again")
    assert {s: truth_values(m[TRUTH])["class_name"] for s, m in got.items() if TRUTH in m} == {stamps[4]: "plate"}


@pytest.mark.parametrize("rows, expect", [
    ("start,end,label\n5,6,cup\n", ":2: no frame from"),
    ("0.5,cup\n", ":1: no frame within 0.02 s of"),
    ("start,end,label\n0,0.04,cup\n0.03,0.05,mug\n", ":3: frame"),
    ("when,label\n0,cup\n", ":1: unknown column(s) when"),
    ("start,end,label\n0.04,0,cup\n", ":2: the end comes before the start"),
])
def test_labels_bad_rows_name_the_line(tmp_path, capsys, rows, expect):
    bag, _stamps = _recording_without_labels(tmp_path, capsys)
    csv = tmp_path / "labels.csv"
    csv.write_text(rows)
    out = tmp_path / "labelled"
    rc, _t, err = run(["import", "labels", bag, "--csv", csv, "--relative", "--out", out, "--quiet"], capsys)
    assert rc == 2 and f"{csv}{expect}" in err, err
    assert nothing_at(out)


def test_help_explains_with_the_gesture_example(capsys):
    for sub, words in (("frames", ("--label-regex", GESTURE_REGEX, "D435", "615", "/pws/ground_truth", "--clips", "--frames")),
                       ("labels", ("stamp,label", "start,end,label", "--relative", "stamp_ns")),
                       ("tum", ("associations.txt", "tum1"))):
        with pytest.raises(SystemExit) as exc:
            pws_main(["import", sub, "--help"])
        text = capsys.readouterr().out
        assert exc.value.code == 0
        for w in words:
            assert w in text, (sub, w)

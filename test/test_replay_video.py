"""Issue 35: ``pws replay --video``: the overlay picture of every frame of the demo recording, read back
with OpenCV and checked against the ``certification`` messages of the same run by its pixels: one bar
per axis, its coloured share = certified radius / requested radius, green when certified, orange when
not (the documented layout and colours of docs/ros2.md, written out here); a certified and a
not-certified frame. Also: the label topic of the output bag, the mp4 file, nothing half written."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_replay import certifications, models, run_cli  # noqa: F401 (models: a fixture)

DEMO = Path(__file__).resolve().parents[1] / "bags" / "demo"
# docs/ros2.md, "The overlay image": the colours of a bar, and its empty part
GREEN, ORANGE, RED, TRACK = (40, 200, 40), (255, 150, 0), (220, 30, 30), (60, 60, 110)
# the linear test model on the demo, axes tz and ry at the shipped radii: frame 0 certified on both axes,
# frame 1 not on tz (about 0.68 of the radius)
FAST = ["--axes", "tz,ry", "--n0", "16", "--n", "32", "--max-frames", "2", "--quiet"]


def bars(rgb: np.ndarray) -> list[tuple[float, tuple[int, int, int], int]]:
    """(filled share, fill colour, length in px) of every bar of a picture, top to bottom, measured from its
    pixels: a horizontal run (>= 100 px) of one bar colour followed by the track colour, the same on each of
    its rows."""
    colours = [GREEN, ORANGE, RED]
    found, last = [], None
    for row in rgb:
        key = None
        is_track = np.all(row == TRACK, axis=1)
        is_fill = {c: np.all(row == c, axis=1) for c in colours}
        bar = is_track | np.logical_or.reduce(list(is_fill.values()))
        idx = np.flatnonzero(bar)
        if len(idx) >= 100:
            runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
            run = max(runs, key=len)
            if len(run) >= 100:
                x0, x1 = run[0], run[-1] + 1
                fill_colour = next((c for c in colours if is_fill[c][x0]), None)
                filled = int(is_fill[fill_colour][x0:x1].sum()) if fill_colour else 0
                if not is_track[x0 + filled:x1].all():   # not a fill then a track: not a bar
                    continue
                key = (int(x0), int(x1), filled, fill_colour)
        if key is not None and key != last:
            found.append(key)
        last = key
    return [(filled / (x1 - x0), colour, x1 - x0) for x0, x1, filled, colour in found]


def test_the_pictures_show_what_was_certified(models, tmp_path, capsys):  # noqa: F811
    out, video = tmp_path / "out", tmp_path / "frames"
    rc, _stdout, err = run_cli([DEMO, "--out", out, "--video", video, "--model", models["linear"], *FAST], capsys)
    assert rc == 0, err
    import cv2

    pngs = sorted(video.glob("*.png"))
    certs = certifications(out)
    assert [int(p.stem.split("_")[1]) for p in pngs] == [stamp for _lt, stamp, _c in certs] and len(pngs) == 2
    assert not list(tmp_path.glob(".*partial*"))
    kinds = set()
    for png, (_lt, stamp, payload) in zip(pngs, certs):
        rgb = cv2.imread(str(png), cv2.IMREAD_COLOR)[:, :, ::-1]
        measured = bars(rgb)
        assert len(measured) == 2, (png, measured)
        for (share, colour, length), axis in zip(measured, ("tz", "ry")):
            c = payload[axis]
            assert colour == (GREEN if c["certified"] else ORANGE if c["level"] == 1 else RED)
            expected = min(1.0, c["radius"] / c["requested_radius"])
            assert share == pytest.approx(expected, abs=1.0 / length), (axis, share, expected)
        every_axis = all(payload[a]["certified"] for a in ("tz", "ry"))
        kinds.add(every_axis)
        # the view above the panel is the classifier's alpha = 0 frame, not a blank one
        assert rgb[: rgb.shape[0] // 2].std() > 10
    assert kinds == {True, False}, "the run should hold a certified and a not-certified frame"
    # the output bag's certified_label: exactly the frames certified on every axis
    from pws_ros.bagio import BagReader
    from pws_ros.bridge import msgconv

    with BagReader(out) as bag:
        labelled = [msgconv.header_stamp_ns(bag.deserialize(m)) for m in bag.messages(["/certified_label"])]
    assert labelled == [stamp for _lt, stamp, p in certs if all(p[a]["certified"] for a in p)]


def test_an_mp4_video_holds_every_frame(models, tmp_path, capsys):  # noqa: F811
    path = tmp_path / "run.mp4"
    rc, stdout, err = run_cli([DEMO, "--no-output", "--video", path, "--video-fps", "5", "--model", models["linear"],
                               *FAST[:-1]], capsys)
    assert rc == 0, err
    assert f"video: {path} (2 frames)" in stdout
    import cv2

    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(5.0)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == 2 and frames[0].shape[1] == 640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mp4"]   # the temporary name is gone


def test_nothing_half_written_and_the_overwrite_rules(models, tmp_path, capsys):  # noqa: F811
    from pws_ros.replay.video import OverlayVideo

    v = OverlayVideo(tmp_path / "v.mp4")
    v.add(np.zeros((40, 64, 3), np.uint8), 1)
    assert not (tmp_path / "v.mp4").exists() and (tmp_path / ".v.partial.mp4").exists()   # until closed
    v.hold(np.zeros((40, 64, 3), np.uint8), 2)
    v.discard()                                       # the frame in flight of a stopped replay
    assert v.close() == tmp_path / "v.mp4" and v.frames == 1 and not (tmp_path / ".v.partial.mp4").exists()
    assert OverlayVideo(tmp_path / "empty").close() is None and not list(tmp_path.glob(".empty*"))
    # an existing path needs --overwrite, and --overwrite replaces only a video or a folder of PNGs
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "notes.txt").write_text("mine")
    for path, extra, message in [(tmp_path / "v.mp4", [], "already exists"),
                                 (tmp_path / "keep", ["--overwrite"], "replaces a video file or a folder of PNG files only"),
                                 (tmp_path / "v.mov", [], "give a .mp4 or .avi file, or a folder")]:
        rc, _out, err = run_cli([DEMO, "--no-output", "--video", path, *extra, "--model", models["linear"], *FAST], capsys)
        assert rc == 2 and message in err, err
    assert (tmp_path / "keep" / "notes.txt").read_text() == "mine"

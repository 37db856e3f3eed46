"""The TUM-format converter (`pws import tum`, pws_ros.importing.tum), read back with the independent mcap reader."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pws_ros.cli import main as pws_main
from pws_ros.importing.tum import TOPICS


def main(argv: list[str]) -> int:
    """`pws import tum SRC OUT [options]` (OUT given as --out)."""
    src, out, *rest = argv
    return pws_main(["import", "tum", src, "--out", out, "--quiet", *rest])


def tum_folder(root: Path, n: int = 3, assoc: bool = True) -> tuple[list[float], list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    times, depths, colours = [], [], []
    for i in range(n):
        t = 1305031102.1 + 0.033 * i
        d = rng.integers(0, 20000, (48, 64)).astype(np.uint16)
        d[0, 0] = 0
        c = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), d)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), c)
        times.append(t)
        depths.append(d)
        colours.append(c)
    if assoc:
        (root / "associations.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png {t + 0.001:.6f} depth/{t:.6f}.png\n" for t in times))
    else:
        (root / "rgb.txt").write_text("# colour\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in times))
        (root / "depth.txt").write_text("".join(f"{t + 0.002:.6f} depth/{t:.6f}.png\n" for t in times))
    return times, depths, colours


def read_back(out: Path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    files = sorted(out.glob("*.mcap"))
    assert files, list(out.iterdir())
    got: dict[str, list] = {}
    for f in files:
        with open(f, "rb") as fh:
            for _schema, channel, _message, msg in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
                got.setdefault(channel.topic, []).append(msg)
    return got


@pytest.mark.parametrize("assoc", [True, False])
def test_converts_and_reads_back_independently(tmp_path, assoc):
    times, depths, colours = tum_folder(tmp_path / "seq", assoc=assoc)
    assert main([str(tmp_path / "seq"), str(tmp_path / "bag"), "--calibration", "tum1"]) == 0
    got = read_back(tmp_path / "bag")
    assert {k: len(v) for k, v in got.items()} == {TOPICS["depth"]: 3, TOPICS["color"]: 3, TOPICS["info"]: 3}
    for i, t in enumerate(times):
        d, c, info = got[TOPICS["depth"]][i], got[TOPICS["color"]][i], got[TOPICS["info"]][i]
        stamp = d.header.stamp.sec * 10**9 + d.header.stamp.nanosec
        assert abs(stamp - t * 1e9) < 2e3   # the colour image's time
        assert (d.encoding, d.width, d.height, c.encoding) == ("16UC1", 64, 48, "rgb8")
        mm = np.frombuffer(bytes(d.data), dtype=np.uint16).reshape(48, 64)
        expect = np.round(depths[i].astype(np.float64) / 5.0)      # 1/5000 m -> mm
        np.testing.assert_array_equal(mm, expect.astype(np.uint16))
        assert mm[0, 0] == 0                                        # no depth stays no depth
        rgb = np.frombuffer(bytes(c.data), dtype=np.uint8).reshape(48, 64, 3)
        np.testing.assert_array_equal(rgb, colours[i][..., ::-1])  # written from BGR PNGs
        assert (info.k[0], info.k[4], info.width) == (517.3, 516.5, 64)


def test_bad_folders_are_clear_errors(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), str(tmp_path / "bag")]) == 2
    assert "neither associations.txt nor rgb.txt + depth.txt" in capsys.readouterr().err
    tum_folder(tmp_path / "seq")
    (tmp_path / "seq" / "associations.txt").write_text("1.0 rgb/x.png\n")
    assert main([str(tmp_path / "seq"), str(tmp_path / "bag2")]) == 2
    assert "expected 't1 file1 t2 file2'" in capsys.readouterr().err

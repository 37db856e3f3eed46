"""bench/geometry: rows per frame and axis with stage timings and whole certificates; the comparison finds a
changed field and a missing certificate. No timing is asserted."""
import json
from pathlib import Path

from pws_ros.bench.geometry import STAGES, compare, main

DEMO = Path(__file__).resolve().parents[1] / "bags" / "demo"


def test_measure_and_compare_on_the_demo(tmp_path, capsys):
    out = tmp_path / "now.json"
    assert main(["--recording", f"demo={DEMO}", "--size", "12x16", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert {r["axis"] for r in rows} == {"tz", "ry"} and all(r["frame"] == 0 for r in rows)
    for r in rows:
        assert set(r["timings"]) == set(STAGES) and r["timings"]["total"] > 0
        assert r["certificate"]["status"] in ("certified", "not_certified") and "timings" not in r["certificate"]
    printed = capsys.readouterr().out
    assert "demo frame 0 tz" in printed and "of the radius" in printed
    # the same file: every certificate the same
    assert main(["--compare", str(out), str(out)]) == 0
    assert "0 of 2 certificates differ" in capsys.readouterr().out
    # a changed radius and a missing axis are found
    changed = json.loads(out.read_text())["rows"]
    changed[0]["certificate"]["radius"] *= 0.5
    lines, bad = compare(rows, changed[:1])
    assert bad == 2
    assert any("DIFFERS in radius" in s for s in lines) and any("only in the first file" in s for s in lines)


def test_bad_arguments_name_what_is_wrong(tmp_path, capsys):
    import pytest

    for argv, word in ((["--recording", "x", "--out", str(tmp_path / "o.json")], "NAME=DIR"),
                       (["--recording", f"x={tmp_path}", "--size", "big", "--out", str(tmp_path / "o.json")], "HxW"),
                       (["--out", str(tmp_path / "o.json")], "--recording")):
        with pytest.raises(SystemExit):
            main(argv)
        assert word in capsys.readouterr().err

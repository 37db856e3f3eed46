"""The replay summary / report (pws_ros.replay.report) against brute force."""
from __future__ import annotations

import csv
import json
import random

import pytest

from pws_ros.core.result import Certificate
from pws_ros.replay.report import FrameRecord, format_table, radius_grid, summarize, write_report

STATUSES = ("certified", "not_certified", "abstain", "error")


def _cert(axis, status, radius, label, requested):
    return Certificate(axis=axis, unit="m" if axis.startswith("t") else "rad", method="pws_of", coverage="pairwise",
                       requested_radius=requested, status=status, certified=status == "certified",
                       radius=requested if status == "certified" else (0.0 if status in ("abstain", "error") else radius),
                       label=label, class_name=f"c{label}", p_a_lower=[0.9] if status != "error" else [], n=32, n0=16,
                       reason="boom" if status == "error" else "")


def random_records(rng: random.Random, n: int, requested: dict[str, float]):
    recs = []
    for i in range(n):
        truth = rng.randrange(3) if rng.random() < 0.8 else None
        certs, correct, compute = [], {}, {}
        for axis, b in requested.items():
            status = rng.choice(STATUSES)
            c = _cert(axis, status, rng.choice([0.0, b / 4, b / 2, 3 * b / 4]), rng.randrange(3), b)
            certs.append(c)
            compute[axis] = rng.uniform(1, 100)
            if truth is not None:
                correct[axis] = c.status != "error" and c.label == truth
        recs.append(FrameRecord(i, 10**9 + i * 10**8, "cam", "rgbd", certs, compute, rng.uniform(1, 200), 1.0,
                                truth_label=truth, truth_class="" if truth is None else f"c{truth}", correct=correct))
    return recs


@pytest.mark.parametrize("seed", range(5))
def test_summary_matches_brute_force(seed):
    rng = random.Random(seed)
    requested = {"tz": 0.01, "ry": 0.004}
    recs = random_records(rng, rng.randrange(1, 30), requested)
    s = summarize(recs, axes=list(requested), units={"tz": "m", "ry": "rad"}, requested=requested, frames_seen=len(recs) + 2,
                  dropped=2, wall_s=3.0)
    assert s["frames"]["seen"] == len(recs) + 2 and s["frames"]["processed"] == len(recs) and s["frames"]["dropped_realtime"] == 2
    json.dumps(s, allow_nan=False)  # strictly JSON
    for axis, b in requested.items():
        a = s["axes"][axis]
        certs = [r.cert(axis) for r in recs]
        for st, key in zip(STATUSES, ("certified", "not_certified", "abstained", "errors")):
            assert a[key] == sum(c.status == st for c in certs)
        ran = [c.radius for c in certs if c.status != "error"]
        if ran:
            assert a["radius_mean"] == pytest.approx(sum(ran) / len(ran))
            srt = sorted(ran)
            mid = len(srt) // 2
            med = srt[mid] if len(srt) % 2 else (srt[mid - 1] + srt[mid]) / 2
            assert a["radius_median"] == pytest.approx(med)
        else:
            assert a["radius_mean"] is None
        with_truth = [r for r in recs if r.truth_label is not None]
        assert a["with_truth"] == len(with_truth)
        if with_truth:
            n = len(with_truth)
            assert a["clean_accuracy"] == pytest.approx(sum(r.correct[axis] for r in with_truth) / n)
            assert a["certified_accuracy"] == pytest.approx(sum(r.correct[axis] and r.cert(axis).certified for r in with_truth) / n)
            for r_, acc in a["certified_accuracy_vs_radius"]:
                ok = sum(1 for r in with_truth if r.correct[axis] and r.cert(axis).status in ("certified", "not_certified")
                         and r.cert(axis).radius >= r_ - 1e-12)
                assert acc == pytest.approx(ok / n)
            curve = [acc for _r, acc in a["certified_accuracy_vs_radius"]]
            assert all(x >= y - 1e-12 for x, y in zip(curve, curve[1:]))  # non-increasing in the radius
            assert curve[-1] == pytest.approx(a["certified_accuracy"])
        else:
            assert a["clean_accuracy"] is None and a["certified_accuracy_vs_radius"] is None
    table = format_table(s)
    assert "tz" in table and "ry" in table and "frames:" in table


def test_radius_grid_ends_at_the_requested_radius():
    g = radius_grid(0.01)
    assert g[0] == 0.0 and g[-1] == pytest.approx(0.01) and len(g) == 21 and g == sorted(g)


def test_write_report_files(tmp_path):
    recs = random_records(random.Random(3), 6, {"tz": 0.01})
    s = summarize(recs, axes=["tz"], units={"tz": "m"}, requested={"tz": 0.01}, frames_seen=6)
    files = write_report(tmp_path / "rep", recs, s, ["tz"])
    assert sorted(p.name for p in files) == ["certified_accuracy_vs_radius.png", "frames.csv", "frames.png", "summary.json"]
    rows = list(csv.DictReader((tmp_path / "rep" / "frames.csv").open()))
    assert len(rows) == 6 and [int(r["frame"]) for r in rows] == list(range(6))
    assert [r["status"] for r in rows] == [r_.cert("tz").status for r_ in recs]
    assert json.loads((tmp_path / "rep" / "summary.json").read_text())["axes"]["tz"]["frames"] == 6
    for name in ("certified_accuracy_vs_radius.png", "frames.png"):
        assert (tmp_path / "rep" / name).read_bytes()[:4] == b"\x89PNG"
    # no ground truth, no frames: still a valid (empty) report
    empty = summarize([], axes=["tz"], units={"tz": "m"}, requested={"tz": 0.01}, frames_seen=0)
    write_report(tmp_path / "rep2", [], empty, ["tz"])
    assert (tmp_path / "rep2" / "frames.png").exists()


def test_the_summary_counts_what_the_time_budget_did():
    """Under a time budget the summary says how many axes were reduced, coarsened and over their share (by
    how much at most), the frames over the budget, the longest frame and the start-up work left out."""
    def budgeted(axis, spent, share, reduced, coarsened):
        c = _cert(axis, "not_certified", 0.001, 0, 0.01)
        c.bounds["time_budget"] = {"frame_budget_s": 10.0, "share_s": share, "spent_s": spent, "reduced": reduced,
                                   "coarsened": coarsened, "over_budget": spent > share}
        return c

    recs = [FrameRecord(0, 10**9, "cam", "rgbd", [budgeted("tz", 4.0, 4.9, True, True), budgeted("ry", 6.5, 4.9, True, True)],
                        {}, 10.5e3, 10.5e3, startup_ms=7000.0),
            FrameRecord(1, 2 * 10**9, "cam", "rgbd", [budgeted("tz", 2.0, 4.9, False, False), budgeted("ry", 2.0, 4.9, True, False)],
                        {}, 4.2e3, 4.2e3)]
    s = summarize(recs, axes=["tz", "ry"], units={"tz": "m", "ry": "rad"}, requested={"tz": 0.01, "ry": 0.004}, frames_seen=2)
    b = s["time_budget"]
    assert (b["axes"], b["reduced"], b["coarsened"], b["axes_over_share"], b["frames_over_budget"]) == (4, 3, 2, 1, 1)
    assert b["most_over_share_s"] == pytest.approx(1.6) and b["longest_frame_s"] == pytest.approx(10.5) and b["startup_s"] == 7.0
    assert "time budget 10 s per frame: longest frame 10.5 s, 1 frame(s) over; of 4 axes 3 reduced, 2 coarsened, 1 over" in format_table(s)
    plain = summarize(recs[:0], axes=["tz"], units={"tz": "m"}, requested={"tz": 0.01}, frames_seen=0)
    assert "time_budget" not in plain

"""``pws_ros.core.metrics``: "certified at radius r" (closed interval for PwS, open for CMS), and the replay
report and the bench report counting the same certificates alike (brute force written here)."""
from __future__ import annotations

import random

import pytest

from pws_ros.core import metrics
from pws_ros.bench import tables as bench_report
from pws_ros.core.result import Certificate
from pws_ros.replay.report import FrameRecord, radius_grid, summarize


def test_certified_at_closed_for_pws_open_for_cms():
    for m in ("pws", "pws_l", "pws_of"):
        assert metrics.certified_at("certified", 0.01, m, 0.01)          # [-0.01, 0.01] is covered
        assert metrics.certified_at("not_certified", 0.005, m, 0.005)
        assert not metrics.certified_at("not_certified", 0.005, m, 0.0051)
        assert metrics.certified_at("certified", 0.01 * (1 - 1e-12), m, 0.01)  # a grid point a few ulps off
        assert metrics.certified_at("not_certified", 0.0, m, 0.0)         # a prediction at the recorded pose
    assert not metrics.certified_at("certified", 0.01, "cms", 0.01)       # Cohen: only |alpha| < R
    assert metrics.certified_at("certified", 0.01, "cms", 0.0099)
    assert metrics.certified_at("not_certified", 0.003, "cms", 0.0)
    for st in ("abstain", "error"):
        for m in ("pws_of", "cms"):
            assert not metrics.certified_at(st, 1.0, m, 0.0)


def _cert(axis, method, status, radius, requested):
    return Certificate(axis=axis, unit="m", method=method, coverage="cms" if method == "cms" else "anchors",
                       requested_radius=requested, status=status,
                       certified=status == "certified" and (radius > requested if method == "cms" else radius >= requested),
                       radius=radius, label=1, class_name="c1", p_a_lower=[0.9], n=32, n0=16)


@pytest.mark.parametrize("seed", range(4))
def test_replay_and_bench_reports_count_alike(seed):
    rng = random.Random(seed)
    b = 0.01
    grid = radius_grid(b)
    recs, bench_recs = [], []
    for i in range(rng.randrange(3, 25)):
        method = rng.choice(["pws_of", "cms"])
        status = rng.choice(["certified", "not_certified", "abstain", "error"])
        radius = 0.0 if status in ("abstain", "error") else (b if status == "certified" and method != "cms"
                                                             else rng.choice(grid[1:]))  # often exactly a grid point
        c = _cert("tz", method, status, radius, b)
        correct = status != "error" and rng.random() < 0.7
        recs.append(FrameRecord(i, 10**9 + i, "cam", "rgbd", [c], {"tz": 1.0}, 1.0, 1.0, truth_label=1, correct={"tz": correct}))
        bench_recs.append({"method": method, "status": status, "radius": radius, "correct": correct, "radius_requested": b})
    s = summarize(recs, axes=["tz"], units={"tz": "m"}, requested={"tz": b}, frames_seen=len(recs))["axes"]["tz"]
    n = len(recs)
    for (g, acc), r in zip(s["certified_accuracy_vs_radius"], grid):
        assert g == r
        brute = 0
        for rec in bench_recs:
            if not rec["correct"] or rec["status"] in ("abstain", "error"):
                continue
            if (rec["radius"] > r) if rec["method"] == "cms" else (rec["radius"] >= r * (1 - 1e-9)):
                brute += 1
        assert acc == brute / n
        assert bench_report.accuracy(bench_recs, r) == (brute, n)
    # the certificate's own verdict at the requested radius agrees with "certified at b"
    assert s["certified_accuracy"] == bench_report.accuracy(bench_recs)[0] / n


def test_a_cms_radius_on_a_grid_point_does_not_certify_that_point():
    """The replay report once counted a CMS certificate of radius R as certified at R (>=); Cohen's
    guarantee is for |alpha| < R only."""
    b = 0.01
    g = radius_grid(b)[10]
    c = _cert("tz", "cms", "not_certified", g, b)
    rec = FrameRecord(0, 10**9, "cam", "rgbd", [c], {"tz": 1.0}, 1.0, 1.0, truth_label=1, correct={"tz": True})
    s = summarize([rec], axes=["tz"], units={"tz": "m"}, requested={"tz": b}, frames_seen=1)["axes"]["tz"]
    curve = dict((round(r / b * 20), acc) for r, acc in s["certified_accuracy_vs_radius"])
    assert curve[9] == 1.0 and curve[10] == 0.0
    frac = dict((round(r / b * 20), acc) for r, acc in s["certified_fraction_vs_radius"])
    assert frac[9] == 1.0 and frac[10] == 0.0


def test_curve_mean_and_statistics():
    outs = [metrics.Outcome("certified", 1.0, "pws_of"), metrics.Outcome("not_certified", 0.5, "pws_of"),
            metrics.Outcome("abstain", 0.0, "pws_of"), metrics.Outcome("certified", 1.0, "pws_of", correct=False)]
    # radii k/8: the first certifies all 8, the second k = 1..4
    assert metrics.curve_mean(outs, 1.0, 8) == pytest.approx((8 + 4) / (8 * 4))
    assert metrics.accuracy_curve(outs, [0.0, 0.5, 0.75]) == [0.5, 0.5, 0.25]
    assert metrics.mean([1.0, float("nan"), None, 3.0]) == 2.0 and metrics.mean([float("inf")]) is None
    assert metrics.median([3.0, 1.0, float("nan"), 2.0, 10.0]) == 2.5 and metrics.median([]) is None

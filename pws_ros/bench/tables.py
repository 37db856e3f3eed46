"""The numbers of ``pws bench``: every table of the report computed from the measured records (the
results dict, stored as ``bench.json``), and the extrapolated duration of a full run. No prose and no
formatting here (:mod:`.verdicts` judges the paper's claims on these tables, :mod:`.render` writes them);
"certified at radius r" is :mod:`pws_ros.core.metrics`'s definition.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..core import metrics
from ..core.motion import PAPER_RADIUS
from .settings import PAPER_CMS_SAMPLES, PRESETS
from .shipped import summarize_shipped

CURVE_STEPS = 8  # radius curves at b * k / 8


# ------------------------------------------------------------------------------------------------
# statistics and accuracy of bench records
# ------------------------------------------------------------------------------------------------
def mean(xs) -> float:
    """:func:`pws_ros.core.metrics.mean`, NaN where there is no finite value."""
    m = metrics.mean(xs)
    return float("nan") if m is None else m


def median(xs) -> float:
    """:func:`pws_ros.core.metrics.median`, NaN where there is no finite value."""
    m = metrics.median(xs)
    return float("nan") if m is None else m


def _outcome(rec: dict) -> metrics.Outcome:
    return metrics.Outcome(rec.get("status"), float(rec.get("radius") or 0.0), rec.get("method"), bool(rec.get("correct")))


def certified_at(rec: dict, r: float) -> bool:
    """Correct and certified at radius ``r`` (:mod:`pws_ros.core.metrics`) for a bench record."""
    o = _outcome(rec)
    return o.correct and o.certified_at(r)


def accuracy(records: list[dict], r: float | None = None) -> tuple[int, int]:
    """(certified at ``r`` and correct, total) (default ``r``: each record's requested radius)."""
    if r is None:
        return sum(1 for x in records if certified_at(x, x["radius_requested"])), len(records)
    return metrics.certified_correct([_outcome(x) for x in records], r)


def curve_mean(records: list[dict], radius: float) -> float:
    """Mean certified accuracy over the radii ``radius * k / 8``, ``k = 1..8`` (area under the curve)."""
    return metrics.curve_mean([_outcome(x) for x in records], radius, CURVE_STEPS)


def radius_curve(records: list[dict], radii: list[float]) -> list[float]:
    """Certified accuracy of ``records`` at each of ``radii`` (0 for no records)."""
    return metrics.accuracy_curve([_outcome(x) for x in records], radii)


def curve_radii(radius: float) -> list[float]:
    """The radii ``radius * k / 8``, ``k = 0..8``, of the radius curves."""
    return metrics.radius_grid(radius, CURVE_STEPS + 1)


def acc_value(kn) -> float:
    """``k / n`` of an ``(k, n)`` accuracy pair (NaN for ``n = 0``)."""
    k, n = kn
    return k / n if n else float("nan")


def _sel(records, **kw) -> list[dict]:
    return [r for r in records if all(r.get(k) == v for k, v in kw.items())]


# ------------------------------------------------------------------------------------------------
# tables as data (also stored in the JSON)
# ------------------------------------------------------------------------------------------------
def summarize(res: dict) -> dict[str, Any]:
    """Every table of the report, as data (stored in ``bench.json`` under ``summary``)."""
    s = res["settings"]
    out: dict[str, Any] = {}
    plans = res["plans"]["records"]
    # frames needed
    frames = []
    for axis in s["plan_axes"]:
        row = {"axis": axis, "radius": PAPER_RADIUS[axis]}
        for m in ("pws", "pws_l", "pws_of"):
            recs = _sel(plans, axis=axis, method=m)
            ns = [r["num_partitions"] for r in recs if r.get("num_partitions") is not None]
            row[m] = {"median": median(ns), "min": min(ns) if ns else None, "max": max(ns) if ns else None, "scenes": len(ns),
                      "failed": len(recs) - len(ns), "plan_seconds": mean(r["seconds"] for r in recs),
                      "ratio_to_cms": median(ns) / PAPER_CMS_SAMPLES if ns else None,
                      "lemma1_holds": sum(1 for r in recs if r.get("lemma1_holds")), "cloud_points": median(r["cloud_points"] for r in recs) if recs else None}
        frames.append(row)
    out["frames"] = frames
    out["shipped"] = summarize_shipped(res)
    cert = res["certificates"]
    axes = s["cert_axes"]
    acc = []
    for m in ("pws", "pws_l", "pws_of"):
        for cov in ("paper", "pairwise", "anchors"):
            row = {"method": m, "coverage": cov}
            for axis in axes:
                row[axis] = accuracy(_sel(cert, method=m, coverage=cov, axis=axis))
            acc.append(row)
    row = {"method": "cms", "coverage": "cms"}
    for axis in axes:
        row[axis] = accuracy(_sel(cert, method="cms", axis=axis))
    acc.append(row)
    out["certified_accuracy"] = acc
    diag = []
    for axis in axes:
        b = PAPER_RADIUS[axis]
        for m in ("pws", "pws_l", "pws_of"):
            for cov in ("paper", "pairwise", "anchors"):
                recs = [r for r in _sel(cert, method=m, coverage=cov, axis=axis) if r.get("status") != "error"]
                diag.append({"axis": axis, "method": m, "coverage": cov, "curve_mean": curve_mean(recs, b),
                             "M": mean(r.get("M") for r in recs), "R_min": mean(r.get("R_min") for r in recs),
                             "min_p_a_lower": mean(r.get("min_p_a_lower") for r in recs),
                             "radius_fraction": mean(r["radius"] / b for r in recs if r.get("status") != "abstain"),
                             "segments_covered": mean((r.get("segments_covered") or 0) / max(1, r.get("num_partitions", 1) - 1)
                                                      for r in recs if r.get("segments_covered") is not None),
                             "num_partitions": mean(r.get("num_partitions") for r in recs)})
        recs = _sel(cert, method="cms", axis=axis)
        diag.append({"axis": axis, "method": "cms", "coverage": "cms", "curve_mean": curve_mean(recs, b),
                     "cms_radius_fraction": mean(r["radius"] / b for r in recs)})
    out["bounds"] = diag
    # costs
    costs = []
    for axis in axes:
        cms = _sel(cert, method="cms", axis=axis)
        cms_calls, cms_time = mean(r.get("classifier_calls") for r in cms), mean(r.get("timings", {}).get("total") for r in cms)
        for m in ("pws", "pws_l", "pws_of", "cms"):
            for cov in (("paper", "pairwise", "anchors") if m != "cms" else ("cms",)):
                recs = [r for r in _sel(cert, method=m, coverage=cov, axis=axis) if "timings" in r]
                if not recs:
                    continue
                calls = mean(r["classifier_calls"] for r in recs)
                tt = {k: mean(r["timings"][k] for r in recs) for k in ("plan", "render", "inference", "statistics", "total")}
                costs.append({"axis": axis, "method": m, "coverage": cov, "num_partitions": mean(r.get("num_partitions") for r in recs),
                              "planned_partitions": median(r.get("planned_partitions") for r in recs) if m != "cms" else None,
                              "capped": sum(1 for r in recs if r.get("capped_from")),
                              "refined": sum(1 for r in recs if r.get("refined_from")), "classifier_calls": calls,
                              "calls_ratio_to_cms": calls / cms_calls if cms_calls else None, "timings": tt,
                              "time_ratio_to_cms": tt["total"] / cms_time if cms_time else None,
                              "overhead_ratio": mean(r.get("overhead_ratio") for r in recs), "count": len(recs)})
    out["costs"] = costs
    # radius curves
    curves = {}
    for axis in axes:
        b = PAPER_RADIUS[axis]
        rs = curve_radii(b)
        c = {"radii": rs}
        for m in ("pws", "pws_l", "pws_of"):
            for cov in ("paper", "pairwise", "anchors"):
                c[f"{m}/{cov}"] = radius_curve(_sel(cert, method=m, coverage=cov, axis=axis), rs)
        c["cms"] = radius_curve(_sel(cert, method="cms", axis=axis), rs)
        curves[axis] = c
    out["curves"] = curves
    # sigma
    sig = []
    for sigma in s["sigmas"]:
        recs = [r for r in res["sigma"] if sigma_of(r) == sigma]
        row = {"sigma": sigma, "classifier": recs[0].get("classifier") if recs else None, "note": recs[0].get("note") if recs else ""}
        for axis in axes:
            pw = _sel(recs, coverage="pairwise", axis=axis)
            b = PAPER_RADIUS[axis]
            row[axis] = {"pairwise_half": accuracy(pw, b / 2), "pairwise_quarter": accuracy(pw, b / 4), "pairwise": accuracy(pw),
                         "paper": accuracy(_sel(recs, coverage="paper", axis=axis)), "benign": accuracy(pw, 0.0),
                         "min_p_a_lower": mean(r.get("min_p_a_lower") for r in pw), "M": mean(r.get("M") for r in pw),
                         "R_min": mean(r.get("R_min") for r in pw)}
        sig.append(row)
    out["sigma"] = sig
    # partitions
    parts = []
    for N in s["partition_counts"]:
        recs = [r for r in res["partitions"] if r.get("grid") == N]
        pw = _sel(recs, coverage="pairwise")
        parts.append({"num_partitions": N, "pairwise": accuracy(pw), "paper": accuracy(_sel(recs, coverage="paper")),
                      "curve_mean": curve_mean(pw, PAPER_RADIUS[s["partition_axis"]]),
                      "min_p_a_lower": mean(r.get("min_p_a_lower") for r in pw), "M": mean(r.get("M") for r in pw),
                      "R_min": mean(r.get("R_min") for r in pw), "classifier_calls": mean(r.get("classifier_calls") for r in pw),
                      "seconds": mean(r["timings"]["total"] for r in pw)})
    out["partitions"] = parts
    # empirical
    emp = []
    for axis in axes:
        recs = _sel(res["empirical"], axis=axis)
        n = len(recs)
        emp.append({"axis": axis, "n": n, "certified": sum(r["certified_correct"] for r in recs),
                    "robust": sum(r["robust_correct"] for r in recs), "benign": sum(r["benign_correct"] for r in recs),
                    "clean": sum(r["clean_correct"] for r in recs),
                    "perturbed_correct_fraction": mean(r["perturbed_correct_fraction"] for r in recs)})
    out["empirical"] = emp
    # denoiser
    den = []
    drecs = [r for r in res["denoiser"] if "error" not in r or r.get("coverage")]
    for key in s["denoiser_classifiers"]:
        for use in (False, True):
            recs = [r for r in drecs if r.get("classifier") == key and r.get("denoiser") == use]
            if not recs:
                continue
            row = {"classifier": key, "denoiser": use}
            for axis in s["denoiser_axes"]:
                pw = _sel(recs, coverage="pairwise", axis=axis)
                row[axis] = {"pairwise": accuracy(pw), "paper": accuracy(_sel(recs, coverage="paper", axis=axis)),
                             "benign": accuracy(pw, 0.0), "min_p_a_lower": mean(r.get("min_p_a_lower") for r in pw),
                             "seconds": mean(r["timings"]["total"] for r in pw if "timings" in r)}
            den.append(row)
    out["denoiser"] = den
    out["denoiser_errors"] = [r["error"] for r in res["denoiser"] if "error" in r and not r.get("coverage")]
    return out


def sigma_of(r: dict) -> float:
    return float(r.get("sigma"))


# ------------------------------------------------------------------------------------------------
# full-run estimate
# ------------------------------------------------------------------------------------------------
def estimate_full_seconds(res: dict) -> dict[str, float]:
    """A rough extrapolation of the ``full`` preset's duration on this machine from this run's measured
    per-plan times and effective classifier-call rate (not a measurement)."""
    full = PRESETS["full"]
    plans = res["plans"]["records"]
    t_plan = 0.0
    for axis in full.plan_axes:
        for m in ("pws", "pws_l", "pws_of"):
            secs = [r["seconds"] for r in plans if r["axis"] == axis and r["method"] == m]
            if not secs:
                secs = [r["seconds"] for r in plans if r["method"] == m]
            per = float(np.mean(secs)) if secs else 0.0
            if m == "pws":
                count = max(full.pws_plan_scenes, full.cert_scenes if axis in full.cert_axes else 0)
            else:
                count = full.plan_scenes
            t_plan += per * count
    t_plan += sum(r["seconds"] for r in res["plans"].get("run_lengths", [])) / max(1, len(res["plans"].get("run_lengths", []))) \
        * full.run_length_scenes * len(full.run_length_axes)
    # classifier work: calls at the measured pure throughput, plus the measured per-certificate render/statistics overhead
    cert = [r for r in res["certificates"] if "timings" in r]
    thr = res["throughput"]
    cps = thr["classifier"]["calls_per_second"]
    den_cps = thr.get("denoiser+classifier", {}).get("calls_per_second", cps)
    overhead = {}
    for m in ("pws", "pws_l", "pws_of", "cms"):
        xs = [r["timings"]["render"] + r["timings"]["statistics"] for r in cert if r["method"] == m and r["coverage"] in ("pairwise", "cms")]
        overhead[m] = float(np.mean(xs)) if xs else 0.0
    planned = {}
    for axis in full.cert_axes:
        for m in ("pws", "pws_l", "pws_of"):
            ns = [r["num_partitions"] for r in plans if r["axis"] == axis and r["method"] == m and r.get("num_partitions")]
            n_med = int(np.median(ns)) if ns else full.cert_max_partitions
            planned[(axis, m)] = min(full.cert_max_partitions, max(full.cert_min_partitions, n_med))
    calls, den_calls, t_over = 0.0, 0.0, 0.0
    for axis in full.cert_axes:
        for m in ("pws", "pws_l", "pws_of"):
            N = planned[(axis, m)]
            calls += 2 * full.n0 + N * full.n + full.num_anchors * full.anchor_n
            t_over += 2 * overhead[m]
        calls += full.cms_n0 + full.cms_n
        t_over += overhead["cms"]
        calls += (len(full.sigmas) - 1) * (full.n0 + planned[(axis, "pws_of")] * full.n)
        calls += (full.empirical_perturbations + 1) * full.empirical_n
    calls += sum(full.n0 + N * full.n for N in full.partition_counts)
    for axis in full.denoiser_axes:
        per = full.n0 + planned[(axis, "pws_of")] * full.denoiser_n
        calls += len(full.denoiser_classifiers) * per
        den_calls += len(full.denoiser_classifiers) * per
    t_calls = full.cert_scenes * (calls / cps + den_calls / den_cps + t_over)
    return {"planning_seconds": t_plan, "classifier_calls": float(full.cert_scenes * (calls + den_calls)),
            "denoised_calls": float(full.cert_scenes * den_calls), "calls_per_second": cps, "denoiser_calls_per_second": den_cps,
            "certification_seconds": t_calls, "total_seconds": t_plan + t_calls}

"""Rendering of ``pws bench``'s results: the PNG plots and the markdown report, from the tables of
:mod:`.tables` and the verdicts of :mod:`.verdicts` (nothing is computed here but layout)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..core.motion import PAPER_RADIUS, UNITS
from .verdicts import why_not_full_radius
from .settings import PAPER_CMS_SAMPLES, PRESETS
from .tables import sigma_of, acc_value, curve_radii, radius_curve
from .shipped import render_shipped
from .text import METHOD_NAMES, fmt, fmt_n, frac, mebibytes, radius_str, table


# ------------------------------------------------------------------------------------------------
# plots
# ------------------------------------------------------------------------------------------------
def make_plots(res: dict, summ: dict, out_dir: Path) -> list[str]:
    """The report's PNG plots in ``out_dir``; returns their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
        files.append(name)

    colors = {"pws": "tab:blue", "pws_l": "tab:orange", "pws_of": "tab:green", "cms": "tab:red"}
    # frames needed
    fig, ax = plt.subplots(figsize=(7, 3.6))
    axes = [r["axis"] for r in summ["frames"]]
    x = np.arange(len(axes))
    for k, m in enumerate(("pws", "pws_l", "pws_of")):
        vals = [r[m]["median"] for r in summ["frames"]]
        ax.bar(x + (k - 1) * 0.27, [v if math.isfinite(v) else 0 for v in vals], 0.27, label=METHOD_NAMES[m], color=colors[m])
    ax.axhline(PAPER_CMS_SAMPLES, color=colors["cms"], ls="--", label=f"CMS ({PAPER_CMS_SAMPLES:,} samples)")
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{a}\n±{radius_str(a, PAPER_RADIUS[a])}" for a in axes])
    ax.set_ylabel("frames (median over scenes)")
    ax.set_title("Frames needed per certificate")
    ax.legend(fontsize=7)
    save(fig, "frames.png")
    # radius curves
    cax = list(summ["curves"])
    fig, axs = plt.subplots(1, len(cax), figsize=(4.2 * len(cax), 3.4), squeeze=False)
    for a, axis in zip(axs[0], cax):
        c = summ["curves"][axis]
        rr = [radius_str(axis, r) for r in c["radii"]]
        xs = np.array(c["radii"]) * (1000 if UNITS[axis] == "m" else 180 / math.pi)
        for m in ("pws", "pws_l", "pws_of"):
            a.plot(xs, c[f"{m}/pairwise"], marker="o", ms=3, color=colors[m], label=f"{METHOD_NAMES[m]} pairwise")
            a.plot(xs, c[f"{m}/anchors"], ls=":", color=colors[m], label=f"{METHOD_NAMES[m]} anchors")
        a.plot(xs, c["cms"], color=colors["cms"], ls="--", label="CMS")
        a.set_xlabel(f"{axis} radius ({'mm' if UNITS[axis] == 'm' else 'deg'})")
        a.set_ylabel("certified accuracy")
        a.set_ylim(-0.02, 1.02)
        a.set_title(f"{axis} (certified at ±{rr[-1]})")
    axs[0][0].legend(fontsize=6)
    save(fig, "radius_curves.png")
    # sigma
    fig, axs = plt.subplots(1, len(cax), figsize=(4.2 * len(cax), 3.2), squeeze=False)
    for a, axis in zip(axs[0], cax):
        b = PAPER_RADIUS[axis]
        rs = curve_radii(b)
        xs = np.array(rs) * (1000 if UNITS[axis] == "m" else 180 / math.pi)
        for sg in res["settings"]["sigmas"]:
            recs = [r for r in res["sigma"] if sigma_of(r) == sg and r["axis"] == axis and r["coverage"] == "pairwise"]
            a.plot(xs, radius_curve(recs, rs), marker="o", ms=3, label=f"σ={sg:g}")
        a.set_xlabel(f"{axis} radius ({'mm' if UNITS[axis] == 'm' else 'deg'})")
        a.set_ylabel("certified accuracy (PwS-OF)")
        a.set_ylim(-0.02, 1.02)
        a.legend(fontsize=7)
    save(fig, "sigma.png")
    # partitions
    fig, ax = plt.subplots(figsize=(5, 3.2))
    Ns = [p["num_partitions"] for p in summ["partitions"]]
    ax.plot(Ns, [acc_value(p["pairwise"]) for p in summ["partitions"]], marker="o", label="certified accuracy (pairwise)")
    ax.plot(Ns, [acc_value(p["paper"]) for p in summ["partitions"]], marker="s", ls="--", label="certified accuracy (paper rule)")
    ax.plot(Ns, [p["min_p_a_lower"] for p in summ["partitions"]], marker="^", ls=":", label="mean min p_A lower")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("number of partitions N")
    ax.set_ylim(-0.02, 1.02)
    ax.legend(fontsize=7)
    ax.set_title(f"PwS-OF, {res['settings']['partition_axis']}")
    save(fig, "partitions.png")
    # time breakdown
    costs = [c for c in summ["costs"] if c["coverage"] in ("pairwise", "anchors", "cms")]
    fig, ax = plt.subplots(figsize=(8, 3.6))
    labels = [f"{c['axis']} {METHOD_NAMES[c['method']]}\n{c['coverage']}" for c in costs]
    bottom = np.zeros(len(costs))
    for stage in ("plan", "render", "inference", "statistics"):
        vals = np.array([c["timings"][stage] for c in costs])
        ax.bar(range(len(costs)), vals, bottom=bottom, label=stage)
        bottom += vals
    ax.set_xticks(range(len(costs)), labels, fontsize=6)
    ax.set_ylabel("seconds per certificate (mean)")
    ax.legend(fontsize=7)
    save(fig, "time_breakdown.png")
    # scaling
    sc = res["scaling"]
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.3))
    rows = sc["vs_partitions"]
    axs[0].plot([r["num_partitions"] for r in rows], [r["timings"]["total"] for r in rows], marker="o", label="time (s)")
    axs[0].set_xscale("log")
    axs[0].set_yscale("log")
    axs[0].set_xlabel("partitions N")
    axs[0].set_ylabel("seconds per certificate")
    axm = axs[0].twinx()
    axm.plot([r["num_partitions"] for r in rows], [(r["peak_bytes"] or 0) / 2**20 for r in rows], marker="s", color="tab:gray", ls="--")
    axm.set_ylabel("peak RSS growth (MiB)", color="tab:gray")
    rows = [r for r in sc["vs_image_size"] if "timings" in r]
    axs[1].plot([r["width"] * r["height"] for r in rows], [r["timings"]["total"] for r in rows], marker="o", label="certify")
    axs[1].plot([r["width"] * r["height"] for r in rows], [r["plan_seconds"] for r in rows], marker="s", label="plan (PwS-OF)")
    axs[1].set_xscale("log")
    axs[1].set_yscale("log")
    axs[1].set_xlabel("pixels")
    axs[1].legend(fontsize=7)
    rows = sc["vs_cloud_size"]
    axs[2].plot([r["cloud_points"] for r in rows], [r["timings"]["total"] for r in rows], marker="o", label="certify (fixed grid)")
    axs[2].plot([r["cloud_points"] for r in rows], [r.get("plan_seconds", float("nan")) for r in rows], marker="s", label="plan (PwS)")
    axs[2].set_xscale("log")
    axs[2].set_yscale("log")
    axs[2].set_xlabel("cloud points")
    axs[2].legend(fontsize=7)
    from matplotlib.ticker import NullFormatter

    for a in axs:
        a.xaxis.set_minor_formatter(NullFormatter())
        a.yaxis.set_minor_formatter(NullFormatter())
    axm.yaxis.set_minor_formatter(NullFormatter())
    fig.suptitle(f"Scaling ({sc['axis']}, n = {sc['n']})", fontsize=9)
    save(fig, "scaling.png")
    return files


# ------------------------------------------------------------------------------------------------
# markdown
# ------------------------------------------------------------------------------------------------
def render_markdown(res: dict, summ: dict, cl: list[dict], est: dict, plots: list[str]) -> str:
    """``report.md``: the settings, the claims, every table of ``summ`` and the plots."""
    s = res["settings"]
    mi = res["machine"]
    L: list[str] = []
    w, h = res["image_size"]
    L.append(f"# `pws bench` report ({s['preset']})\n")
    L.append(f"Measured by `pws bench{' --quick' if s['preset'] == 'quick' else ''}` in {res['total_seconds']:.0f} s "
             f"({res['total_seconds'] / 60:.1f} min) on {mi['cpu']} ({mi['usable_cpus']} usable CPUs, {mi['torch_threads']} torch thread{'s' if mi['torch_threads'] != 1 else ''}, "
             f"device {mi['device']}), load average at start {fmt(mi['load_average_start'][0]) if mi.get('load_average_start') else '—'}. "
             f"Python {mi['python']}, torch {mi['torch']}, numpy {mi['numpy']}, pws_ros {mi.get('pws_ros')}. "
             f"Every number below is a measurement from this run (all records are in `bench.json`).\n")
    L.append("## Settings\n")
    for note in s["notes"]:
        L.append(f"- **{note}**")
    L.append(f"- world: `pws_ros.sim` held-out scenes (seed i, class i mod 12, view 7i mod 24), images {w}×{h}, dense cloud "
             f"{s['samples_per_pixel']:g} samples per pixel footprint; classifier `classifier_sigma0.50.pt` for every method "
             f"(models: {', '.join(k for k, v in res['models'].items() if v)}).")
    L.append(f"- planning: {s['plan_scenes']} scenes × axes {', '.join(s['plan_axes'])} at the paper's radii; PwS (dense cloud) on the "
             f"{s['cert_scenes']} certified scenes for {', '.join(s['cert_axes'])} and on {s['pws_plan_scenes']} scene(s) for every axis; "
             f"PwS-OF δ = {res['delta_px']:g} px.")
    L.append(f"- certification: {s['cert_scenes']} scenes × {', '.join(s['cert_axes'])}; σ = 0.5, n0 = {s['n0']}, n = {s['n']} per partition "
             f"frame (paper/pairwise), {s['num_anchors']} anchors × {s['anchor_n']} (anchors), α = {s['alpha']:g} with Bonferroni over the "
             f"bounds used; grids with more than {s['cert_max_partitions']} partitions certified on the uniform "
             f"{s['cert_max_partitions']}-partition grid; CMS n0 = {s['cms_n0']}, n = {s['cms_n']} on the dense cloud; seed {s['seed']}.")
    L.append(f"- full run (`pws bench`, no `--quick`): {PRESETS['full'].notes[0]}; expected duration {PRESETS['full'].expected_minutes}. "
             f"Extrapolated from this run's measured costs: ≈ {est['total_seconds'] / 3600:.1f} h on this machine "
             f"({fmt_n(est['classifier_calls'])} classifier calls at the measured throughput, {fmt_n(est['denoised_calls'])} of them "
             f"through the denoiser, the measured render overhead per certificate, and {est['planning_seconds'] / 3600:.1f} h of planning).")
    thr = res["throughput"]
    L.append(f"- pure classifier throughput: {thr['classifier']['calls_per_second']:.0f} images/s"
             + (f"; denoiser + classifier {thr['denoiser+classifier']['calls_per_second']:.0f} images/s" if "denoiser+classifier" in thr else "")
             + f" (batch {s['batch_size']}).\n")
    # claims
    L.append("## The paper's claims on our world\n")
    L.append(f"(a)-(f): the paper's imaging (one point, one pixel) rendered at the classifier's {w}×{h}, as the paper does; "
             "(g): the shipped defaults (surfel imaging, 640×480 camera), see the next section.\n")
    L.append(table(["", "claim", "verdict", "evidence"], [[f"({c['id']})", c["claim"], f"**{c['verdict']}**", c["evidence"]] for c in cl]))
    L.append("")
    for c in cl:
        if c["why"]:
            L.append(f"- ({c['id']}) {c['why']}")
    L.append("")
    # table 1
    L.extend(render_shipped(summ.get("shipped") or []))
    L.append("## Frames needed per certificate (Table 1 analogue, paper imaging)\n")
    L.append(f"Planned number of partitions N (median [min–max] over scenes, planning only). PwS: entire dense cloud, exact "
             f"consistent intervals; PwS-L / PwS-OF: one-frame cloud. Ratio: median N / {PAPER_CMS_SAMPLES:,} (the CMS sample count "
             f"of the paper's Table 1; this run's CMS used {s['cms_n0'] + s['cms_n']}). Paper (MetaRoom): tz 10 mm 3.5k / 5.1k / 5.9k, "
             f"ry 0.25° 3.4k / 5.0k / 6.1k.\n")
    rows = []
    for r in summ["frames"]:
        row = [r["axis"], radius_str(r["axis"], r["radius"])]
        for m in ("pws", "pws_l", "pws_of"):
            x = r[m]
            if x["scenes"] == 0:
                row.append("not planned in this preset" if not x["failed"] else f"failed ({x['failed']})")
                row.append("—")
                continue
            row.append(f"{fmt_n(x['median'])} [{fmt_n(x['min'])}–{fmt_n(x['max'])}] ({x['scenes']} sc.)" + (f", {x['failed']} failed" if x["failed"] else ""))
            row.append(f"{x['ratio_to_cms']:.3g}")
        row.append(" / ".join(f"{r[m]['plan_seconds']:.2f}" for m in ("pws", "pws_l", "pws_of")))
        rows.append(row)
    L.append(table(["axis", "radius", "PwS N", "/CMS", "PwS-L N", "/CMS", "PwS-OF N", "/CMS", "plan s (PwS / L / OF)"], rows))
    rl = res["plans"].get("run_lengths", [])
    if rl:
        L.append("\nConsistent-run lengths of the dense cloud (what sets PwS's step), as fractions of the radius b, and the N each "
                 "quantile would give as the step:\n")
        L.append(table(["scene", "axis", "runs", "shortest", "0.01%", "0.1%", "1%", "median", "N at 0.1%", "N at 1%"],
                       [[r["scene"], r["axis"], f"{r['num_runs']:,}"] + [f"{r['quantiles'][k] / r['radius']:.2e}" for k in ("0.0", "0.0001", "0.001", "0.01", "0.5")]
                        + [fmt_n(r["partitions_at_quantile"]["0.001"]), fmt_n(r["partitions_at_quantile"]["0.01"])] for r in rl]))
    L.append("\n![frames](frames.png)\n")
    # table 2
    L.append(f"## Certified accuracy at the paper's radii (Tables 2-3 analogue, paper imaging at {w}×{h})\n")
    L.append("Fraction of scenes whose smoothed prediction is correct and certified on the whole interval. The paper rule is "
             "decided on the pairwise run's own counts and bounds (identical to `certify(coverage='paper')`).\n")
    hdr = ["method", "coverage"] + [f"{a} ±{radius_str(a, PAPER_RADIUS[a])}" for a in s["cert_axes"]]
    L.append(table(hdr, [[METHOD_NAMES[r["method"]], r["coverage"]] + [frac(*r[a]) for a in s["cert_axes"]] for r in summ["certified_accuracy"]]))
    L.append("\nWhat the certificates rested on (means over scenes): M = max_i sqrt(B_i / 2) over the sound per-segment bounds B_i, "
             "R_min = the smallest Cohen radius σΦ⁻¹(p_A) used, the certified sub-interval as a fraction of b, and the mean "
             "certified accuracy over the radii b/8 .. b (area under the curve below):\n")
    L.append(table(["axis", "method", "coverage", "N used", "mean M", "mean R_min", "mean min p_A", "certified radius / b", "segments covered",
                    "accuracy over b/8..b"],
                   [[d["axis"], METHOD_NAMES[d["method"]], d["coverage"], fmt(d.get("num_partitions")), fmt(d.get("M")), fmt(d.get("R_min")),
                     fmt(d.get("min_p_a_lower")), fmt(d.get("radius_fraction", d.get("cms_radius_fraction"))), fmt(d.get("segments_covered")),
                     f"{d['curve_mean']:.2f}"] for d in summ["bounds"]]))
    L.append("\nFor CMS the certified radius / b is its motion-space radius R over b. " + why_not_full_radius(res, summ) + "\n")
    L.append("\nCertified accuracy against the radius (read off each certificate's certified sub-interval, pairwise coverage):\n")
    for axis, c in summ["curves"].items():
        ks = [0, 2, 4, 6, 8]
        L.append(table([axis] + [radius_str(axis, c["radii"][k]) for k in ks],
                       [[f"{METHOD_NAMES[m]} pairwise"] + [f"{c[m + '/pairwise'][k]:.2f}" for k in ks] for m in ("pws", "pws_l", "pws_of")]
                       + [["CMS"] + [f"{c['cms'][k]:.2f}" for k in ks]]))
        L.append("")
    L.append("![radius curves](radius_curves.png)\n")
    # costs
    L.append("## Cost per certificate\n")
    L.append("Means over the certified scenes. Ratios are to CMS on the same scenes in this run. Overhead = total time / pure "
             "classifier time for the same number of calls (at the measured pure throughput). Plan time is the planning measured "
             "in the Table 1 stage (PwS: on the dense cloud).\n")
    rows = []
    for c in summ["costs"]:
        t = c["timings"]
        note = ""
        if c["capped"] or c.get("refined"):
            note = f" (median planned {fmt_n(c['planned_partitions'])}: {c['capped']} capped, {c.get('refined', 0)} refined)"
        rows.append([c["axis"], METHOD_NAMES[c["method"]], c["coverage"], fmt(c["num_partitions"]) + note,
                     fmt_n(c["classifier_calls"]), fmt(c["calls_ratio_to_cms"]), fmt(t["total"]), fmt(c["time_ratio_to_cms"]),
                     fmt(t["plan"]), fmt(t["render"]), fmt(t["inference"]), fmt(t["statistics"]), fmt(c["overhead_ratio"])])
    L.append(table(["axis", "method", "coverage", "N used", "calls", "calls/CMS", "time s", "time/CMS", "plan", "render", "inference",
                    "statistics", "overhead"], rows))
    L.append("\n![time breakdown](time_breakdown.png)\n")
    # ablations
    L.append("## Ablations\n")
    L.append("### Noise level σ (PwS-OF)\n")
    rows = []
    for r in summ["sigma"]:
        for axis in s["cert_axes"]:
            x = r[axis]
            rows.append([f"{r['sigma']:g}", f"classifier_sigma{r['classifier']}.pt", axis, frac(*x["benign"]), frac(*x["pairwise_quarter"]),
                         frac(*x["pairwise_half"]), frac(*x["pairwise"]), frac(*x["paper"]), fmt(x["min_p_a_lower"]), fmt(x["M"]), fmt(x["R_min"])])
    L.append(table(["σ", "classifier", "axis", "r = 0", "b/4", "b/2", "b (pairwise)", "b (paper)", "mean min p_A", "mean M", "mean R_min"], rows))
    notes = sorted({r["note"] for r in summ["sigma"] if r.get("note")})
    if notes:
        L.append("\n" + ". ".join(notes) + ".")
    L.append("\n![sigma](sigma.png)\n")
    L.append(f"### Number of partitions (PwS-OF, {s['partition_axis']}, explicit uniform grids, n = {s['n']})\n")
    L.append(table(["N", "certified at b (pairwise)", "certified at b (paper)", "accuracy over b/8..b (pairwise)", "mean min p_A", "mean M",
                    "mean R_min", "calls", "time s"],
                   [[p["num_partitions"], frac(*p["pairwise"]), frac(*p["paper"]), f"{p['curve_mean']:.2f}", fmt(p["min_p_a_lower"]), fmt(p["M"]), fmt(p["R_min"]),
                     fmt_n(p["classifier_calls"]), fmt(p["seconds"])] for p in summ["partitions"]]))
    L.append("\n![partitions](partitions.png)\n")
    L.append("### Certified vs empirical robust vs benign accuracy (PwS-OF, one-frame cloud)\n")
    L.append(f"Empirical robust: the smoothed prediction (majority of {s['empirical_n']} noisy samples) at "
             f"{s['empirical_perturbations']} uniform motions in [-b, b] all equal the label; benign: the same at α = 0; clean: the "
             "base classifier without noise at α = 0.\n")
    L.append(table(["axis", "certified", "empirical robust", "benign", "clean", "mean fraction of perturbations correct"],
                   [[e["axis"], frac(e["certified"], e["n"]), frac(e["robust"], e["n"]), frac(e["benign"], e["n"]), frac(e["clean"], e["n"]),
                     fmt(e["perturbed_correct_fraction"])] for e in summ["empirical"]]))
    L.append(f"\n### Denoiser (PwS-OF, σ = 0.5, n = {s['denoiser_n']} per partition frame with and without it)\n")
    if summ["denoiser"]:
        rows = []
        for r in summ["denoiser"]:
            for axis in s["denoiser_axes"]:
                x = r[axis]
                rows.append([f"classifier_sigma{r['classifier']}.pt", "yes" if r["denoiser"] else "no", axis, frac(*x["benign"]),
                             frac(*x["pairwise"]), frac(*x["paper"]), fmt(x["min_p_a_lower"]), fmt(x["seconds"])])
        L.append(table(["classifier", "denoiser", "axis", "r = 0", "certified (pairwise)", "certified (paper)", "mean min p_A", "time s"], rows))
    else:
        L.append("Not measured: " + "; ".join(summ["denoiser_errors"]))
    # scaling
    sc = res["scaling"]
    L.append(f"\n## Scaling (scene {sc['scene']}, {sc['axis']} ±{radius_str(sc['axis'], sc['radius'])}, n0 = n = {sc['n']})\n")
    L.append("Peak memory is the growth of the process's resident set during the call (sampled every 4 ms)"
             + (" and the CUDA peak allocation" if res["machine"]["device"].startswith("cuda") else "") + ".\n")
    L.append("Against the number of partitions (PwS-OF, one-frame cloud, `certify` streaming):\n")
    L.append(table(["N", "total s", "render", "inference", "statistics", "calls", "peak MiB"],
                   [[r["num_partitions"], fmt(r["timings"]["total"]), fmt(r["timings"]["render"]), fmt(r["timings"]["inference"]),
                     fmt(r["timings"]["statistics"]), r["classifier_calls"], mebibytes(r["peak_bytes"])] for r in sc["vs_partitions"]]))
    L.append("\nAgainst the image size (the same scene re-rendered; the classifier is applied at each size for timing only, its "
             "predictions there are meaningless):\n")
    L.append(table(["size", "points", "plan s (PwS-OF)", "planned N", "certify s (fixed N)", "render", "inference", "peak MiB"],
                   [[f"{r['width']}×{r['height']}", fmt(r.get("cloud_points")), fmt(r.get("plan_seconds")), fmt(r.get("planned_partitions")),
                     fmt(r["timings"]["total"]) if "timings" in r else r.get("error", "—"),
                     fmt(r["timings"]["render"]) if "timings" in r else "—", fmt(r["timings"]["inference"]) if "timings" in r else "—",
                     mebibytes(r.get("peak_bytes"))] for r in sc["vs_image_size"]]))
    L.append("\nAgainst the cloud size (random subsets of the dense cloud; PwS planning and PwS certification on a fixed grid):\n")
    L.append(table(["points", "plan s (PwS)", "planned N", "plan peak MiB", "certify s", "render", "statistics", "peak MiB"],
                   [[fmt(r["cloud_points"]), fmt(r.get("plan_seconds")), fmt(r.get("planned_partitions")), mebibytes(r.get("plan_peak_bytes")),
                     fmt(r["timings"]["total"]), fmt(r["timings"]["render"]), fmt(r["timings"]["statistics"]), mebibytes(r["peak_bytes"])]
                    for r in sc["vs_cloud_size"]]))
    L.append("\n![scaling](scaling.png)\n")
    L.append("## Run\n")
    L.append(table(["stage", "seconds"], [[k, f"{v:.1f}"] for k, v in res["stage_seconds"].items()] + [["total", f"{res['total_seconds']:.1f}"]]))
    L.append("")
    return "\n".join(L) + "\n"

"""Certified accuracy of a classifier on held-out labelled frames, with the ceiling beside it
(docs/real_task.md):

    python3 -m pws_ros.bench.real_task HELD_OUT_RECORDING --model M.pt --sigma S --out DIR \\
        [--methods pws_of,cms] [--finetune-report M.finetune.json] [-- extra pws replay/ceiling options]

Runs ``pws replay --report`` once per method and ``pws ceiling --no-model`` on the same frames with the
same options, and writes DIR/real_task.json, DIR/real_task.md (per method and axis: the base
classifier's clean accuracy from the finetune report when given, the smoothed classifier's accuracy
at radius 0, certified accuracy at 0 / 25 / 50 / 75 / 100% of the requested radius, abstentions,
seconds per certificate; the ceiling's share of frames certified at those radii; per frame whether
the ceiling or the model limited it) and DIR/certified_accuracy.png (certified accuracy against
radius per axis, each method and the ceiling)."""
from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

from ..cli import main as pws_main

FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)
CEILING_OPTS = {"--config", "--axes", "--radius", "--sigma", "--n0", "--n", "--alpha", "--anchors", "--render-factor", "--seed",
                "--batch-size", "--working-volume", "--window", "--background", "--device", "--max-frames"}


def _run(argv: list[str]) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = pws_main([str(a) for a in argv])
    if rc != 0:
        raise SystemExit(f"real_task: `pws {' '.join(map(str, argv))}` failed (exit {rc})")
    return json.loads(out.getvalue())


def _ceiling_args(extra: list[str]) -> list[str]:
    """The options of ``extra`` that ``pws ceiling`` takes too (each with its value)."""
    out, i = [], 0
    while i < len(extra):
        if extra[i] in CEILING_OPTS:
            out += extra[i:i + 2]
            i += 2
        else:
            i += 1
    return out if "--max-frames" in out else out + ["--max-frames", "1000000"]   # pws ceiling measures 3 frames by default


def at_fractions(curve: list[list[float]], requested: float) -> list[float]:
    """Certified accuracy of a (radius, accuracy) curve at FRACTIONS of the requested radius."""
    return [next(a for r, a in curve if abs(r - f * requested) <= 1e-9 * max(1.0, requested)) for f in FRACTIONS]


def _check_ceiling(path: Path, ceil: dict, made_with: dict) -> None:
    """A ceiling file read instead of measured must be of these frames, this sigma and, where it says, this
    input size and these options: else its column would be another imaging's, silently."""
    got = ceil.get("made_with")
    if got is None:   # an older file, or `pws ceiling --json` itself: its sigma and recording are all it states
        got = {"sigma": ceil.get("sigma"), "recording": (ceil.get("rows") or [{}])[0].get("recording")}
    bad = [f"{k} {got[k]!r} (here {made_with[k]!r})" for k in made_with if got.get(k) is not None and got[k] != made_with[k]]
    if bad:
        raise SystemExit(f"real_task: the ceiling file {path} was measured with other settings: {'; '.join(bad)}: "
                         "remove it (it is measured again) or give another --ceiling")


def limited_by(row: dict, ceiling: float | None, requested: float) -> str:
    """What limited one certificate: reached (the whole radius), the model (wrong class, abstained, or a
    radius under 90% of the ceiling), or the ceiling (the imaging)."""
    if row["correct"] != "1":
        return "model (wrong class)"
    if row["status"] == "abstain":
        return "model (abstained)"
    radius = float(row["radius"] or 0.0)
    if radius >= requested * (1 - 1e-9):
        return "reached"
    if ceiling is not None and radius >= 0.9 * ceiling:
        return "ceiling"
    return "model"


def report(held: Path, model: Path, sigma: float, out: Path, methods: list[str], extra: list[str],
           finetune_report: Path | None = None, ceiling_file: Path | None = None, reuse: bool = False) -> dict[str, Any]:
    """See the module doc; ``ceiling_file``: the ``pws ceiling --json`` of the same frames and imaging
    (made here, and written to DIR/ceiling.json, when absent: models of one input size share it); ``reuse``:
    a method whose report folder DIR/METHOD is complete is read, not replayed again."""
    out.mkdir(parents=True, exist_ok=True)
    from ..core.model import load_model

    size = load_model(model).input_size
    made_with = {"recording": str(held), "size": [int(size[0]), int(size[1])], "sigma": float(sigma),
                 "options": [str(a) for a in _ceiling_args(extra)]}
    if ceiling_file is not None and Path(ceiling_file).is_file():
        ceil = json.loads(Path(ceiling_file).read_text())
        _check_ceiling(Path(ceiling_file), ceil, made_with)
    else:
        ceil = _run(["ceiling", held, "--no-model", "--size", f"{size[0]}x{size[1]}", "--sigma", sigma, "--json", "--quiet",
                     *_ceiling_args(extra)])
        ceil["made_with"] = made_with
        (Path(ceiling_file) if ceiling_file is not None else out / "ceiling.json").write_text(json.dumps(ceil, indent=1) + "\n")
    ceiling = {(r["stamp_ns"], r["axis"]): r for r in ceil["rows"]}
    base = None
    if finetune_report is not None:
        base = json.loads(Path(finetune_report).read_text())["after"].get("clean_accuracy_vs_truth")
    result: dict[str, Any] = {"recording": str(held), "model": str(model), "sigma": sigma, "options": extra,
                              "base_clean_accuracy": base, "fractions": list(FRACTIONS), "methods": {}}
    for method in methods:
        rdir = out / method
        if reuse and (rdir / "summary.json").is_file() and (rdir / "frames.csv").is_file():
            summary = json.loads((rdir / "summary.json").read_text())
        else:
            summary = _run(["replay", held, "--model", model, "--sigma", sigma, "--method", method, "--no-output", "--report", rdir,
                            "--json", "--quiet", "--overwrite", *extra])
        with open(rdir / "frames.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        axes = {}
        for axis, s in summary["axes"].items():
            req = float(s["requested_radius"])
            mine = [r for r in rows if r["axis"] == axis]
            frames = []
            for r in mine:
                c = ceiling.get((int(r["stamp_ns"]), axis))
                cr = None if c is None else float(c["ceiling"])
                frames.append({"stamp_ns": int(r["stamp_ns"]), "truth": r["truth_class"], "class": r["class_name"],
                               "status": r["status"], "radius_share": float(r["radius"] or 0) / req,
                               "ceiling_share": None if cr is None else cr / req, "limited_by": limited_by(r, cr, req),
                               "seconds": float(r["compute_ms"]) / 1000.0})
            shares = [f["ceiling_share"] for f in frames if f["ceiling_share"] is not None]
            axes[axis] = {"requested_radius": req, "unit": s["unit"], "frames": s["with_truth"],
                          "smoothed_accuracy": s["clean_accuracy"],
                          "certified_accuracy": at_fractions(s["certified_accuracy_vs_radius"], req),
                          "ceiling": [sum(1 for v in shares if v >= f - 1e-9) / max(1, len(shares)) for f in FRACTIONS],
                          "abstained": s["abstained"], "seconds_per_certificate": (s["compute_ms_mean"] or 0) / 1000.0,
                          "curve": s["certified_accuracy_vs_radius"], "per_frame": frames,
                          "limited_by": {k: sum(1 for f in frames if f["limited_by"] == k) for k in sorted({f["limited_by"] for f in frames})}}
        result["methods"][method] = {"axes": axes, "seconds_per_frame": summary["time"]["per_frame_ms_mean"] / 1000.0}
    (out / "real_task.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "real_task.md").write_text("\n".join(table(result)) + "\n")
    plot(out / "certified_accuracy.png", result)
    return result


def _pct(v: Any) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def table(result: dict) -> list[str]:
    lines = ["| method | axis | base clean acc. | smoothed acc. | certified 0 / 25 / 50 / 75 / 100% of the radius | ceiling 0 / 25 / 50 / 75 / 100% "
             "| abstained | s per cert. | limited by |", "|---|---|---|---|---|---|---|---|---|"]
    for method, m in result["methods"].items():
        for axis, a in m["axes"].items():
            lim = ", ".join(f"{k} {v}" for k, v in a["limited_by"].items())
            lines.append(f"| {method} | {axis} | {_pct(result['base_clean_accuracy'])} | {_pct(a['smoothed_accuracy'])} | "
                         + " / ".join(_pct(v) for v in a["certified_accuracy"]) + " | "
                         + " / ".join(_pct(v) for v in a["ceiling"]) + f" | {a['abstained']}/{a['frames']} | "
                         f"{a['seconds_per_certificate']:.1f} | {lim} |")
    return lines


def plot(path: Path, result: dict) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    axes = list(next(iter(result["methods"].values()))["axes"])
    fig = Figure(figsize=(5 * len(axes), 3.6))
    FigureCanvasAgg(fig)
    for i, axis in enumerate(axes):
        ax = fig.add_subplot(1, len(axes), i + 1)
        for method, m in result["methods"].items():
            a = m["axes"][axis]
            req = a["requested_radius"]
            ax.plot([100 * r / req for r, _ in a["curve"]], [100 * v for _, v in a["curve"]], marker=".", label=method)
        a = next(iter(result["methods"].values()))["axes"][axis]
        ax.plot([100 * f for f in FRACTIONS], [100 * v for v in a["ceiling"]], "k--", label="ceiling")
        ax.set_xlabel(f"radius, % of the requested ±{a['requested_radius']:.4g} {a['unit']}")
        ax.set_ylabel("certified accuracy, %")
        ax.set_title(f"{axis}, sigma {result['sigma']}")
        ax.set_ylim(-3, 103)
        ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(str(path), dpi=100)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(prog="python3 -m pws_ros.bench.real_task", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("held", help="the held-out labelled recording (e.g. `pws import frames --clips '*/clip04'`)")
    p.add_argument("--model", required=True)
    p.add_argument("--sigma", type=float, required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--methods", default="pws_of,cms")
    p.add_argument("--finetune-report", default=None, help="the model's .finetune.json: its base clean accuracy on the held-out clips")
    p.add_argument("--ceiling", default=None, metavar="JSON", help="the ceiling of these frames and this imaging (pws ceiling "
                                                                   "--json): read when it exists, else measured and written there")
    p.add_argument("--reuse", action="store_true", help="read a method's finished report folder instead of replaying it again")
    a = p.parse_args(argv)
    result = report(Path(a.held), Path(a.model), a.sigma, Path(a.out), [m for m in a.methods.split(",") if m], extra,
                    Path(a.finetune_report) if a.finetune_report else None, Path(a.ceiling) if a.ceiling else None,
                    a.reuse)
    print("\n".join(table(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

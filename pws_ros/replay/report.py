"""Per-frame records of a replay, their summary (table / JSON) and the ``--report`` folder.

:class:`FrameRecord` is what one certified input frame produced. :func:`summarize` reduces a list of
records to a JSON-able dict: frame counts, per axis the certified / not certified / abstained /
error counts, the certified radius (mean, median), the time per certificate, and, when ground truth
is known, clean accuracy, certified accuracy and certified accuracy vs radius. :func:`format_table`
prints it; :func:`write_report` writes ``frames.csv``, ``summary.json`` and two PNG plots
(matplotlib's Agg canvas: no display, no pyplot state).

Definitions (per axis, over the frames with ground truth; error frames count as wrong):

- clean accuracy: the smoothed classifier's top class at the recorded pose (the ``n0`` selection
  samples) is the true class;
- certified accuracy at radius r: that class is right and the certificate is certified at r
  (:mod:`pws_ros.core.metrics`: no abstention, no error, and its certified radius covers ``[-r, r]``); at
  the requested radius this is "certified and correct";
- fraction certified at radius r (without ground truth): the same over the frames that did not error,
  correctness aside.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..core import metrics
from ..core.jsonable import jsonable
from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_ERROR, STATUS_NOT_CERTIFIED, Certificate

CSV_COLUMNS = (
    "frame", "stamp_ns", "time_s", "frame_id", "source", "axis", "unit", "status", "certified", "label", "class_name",
    "truth_label", "truth_class", "correct", "radius", "requested_radius", "p_a_lower", "num_partitions",
    "classifier_calls", "compute_ms", "latency_ms", "reason",
)
CURVE_POINTS = 21


@dataclass
class FrameRecord:
    """One processed input frame: its certificates (config axis order) and what they cost."""

    index: int
    stamp_ns: int
    frame_id: str
    source: str
    certificates: list[Certificate]
    compute_ms: dict[str, float] = field(default_factory=dict)   # per axis
    latency_ms: float = float("nan")                             # publish time minus source stamp
    total_ms: float = float("nan")                               # conversion + every axis
    input_error: str = ""
    truth_label: int | None = None
    truth_class: str = ""
    correct: dict[str, bool] = field(default_factory=dict)       # axis -> top class is right (with ground truth)
    startup_ms: float = 0.0   # start-up work the engine did in this frame (warm-ups, batch size check): not in total_ms

    def cert(self, axis: str) -> Certificate | None:
        return next((c for c in self.certificates if c.axis == axis), None)

    @property
    def has_truth(self) -> bool:
        return self.truth_label is not None or bool(self.truth_class)


def radius_grid(requested: float, points: int = CURVE_POINTS) -> list[float]:
    return metrics.radius_grid(requested, points)


def axis_summary(records: Sequence[FrameRecord], axis: str, unit: str, requested: float) -> dict[str, Any]:
    certs = [(r, r.cert(axis)) for r in records]
    certs = [(r, c) for r, c in certs if c is not None]
    status = [c.status for _, c in certs]
    ran = [(r, c) for r, c in certs if c.status != STATUS_ERROR]
    out: dict[str, Any] = {
        "unit": unit,
        "requested_radius": requested,
        "frames": len(certs),
        "certified": status.count(STATUS_CERTIFIED),
        "not_certified": status.count(STATUS_NOT_CERTIFIED),
        "abstained": status.count(STATUS_ABSTAIN),
        "errors": status.count(STATUS_ERROR),
        "radius_mean": metrics.mean([c.radius for _, c in ran]),
        "radius_median": metrics.median([c.radius for _, c in ran]),
        "compute_ms_mean": metrics.mean([r.compute_ms.get(axis, float("nan")) for r, _ in ran]),
        "compute_ms_median": metrics.median([r.compute_ms.get(axis, float("nan")) for r, _ in ran]),
        "num_partitions_mean": metrics.mean([c.num_partitions for _, c in ran if c.num_partitions]),
        "classifier_calls_mean": metrics.mean([c.classifier_calls for _, c in ran]),
    }
    truth = [(r, c) for r, c in certs if r.has_truth]
    out["with_truth"] = len(truth)
    if truth:
        n = len(truth)
        right = [(r, c) for r, c in truth if c.status != STATUS_ERROR and r.correct.get(axis, False)]
        predicted = [(r, c) for r, c in right if c.status in (STATUS_CERTIFIED, STATUS_NOT_CERTIFIED)]
        out["clean_accuracy"] = len(right) / n
        out["certified_accuracy"] = sum(1 for _, c in predicted if c.certified) / n
        grid = radius_grid(requested)
        outcomes = [metrics.Outcome.of(c, c.status != STATUS_ERROR and r.correct.get(axis, False)) for r, c in truth]
        out["certified_accuracy_vs_radius"] = [list(p) for p in zip(grid, metrics.accuracy_curve(outcomes, grid))]
    else:
        out["clean_accuracy"] = None
        out["certified_accuracy"] = None
        out["certified_accuracy_vs_radius"] = None
    grid = radius_grid(requested)
    out["certified_fraction_vs_radius"] = [list(p) for p in zip(grid, metrics.accuracy_curve(
        [metrics.Outcome.of(c) for _, c in ran], grid))] if ran else None
    return out


def summarize(records: Sequence[FrameRecord], *, axes: Sequence[str], units: dict[str, str], requested: dict[str, float],
              frames_seen: int, dropped: int = 0, wall_s: float | None = None, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON-able summary of a replay (see the module docstring for the definitions)."""
    frames = {
        "seen": int(frames_seen),
        "processed": len(records),
        "dropped_realtime": int(dropped),
        "input_errors": sum(1 for r in records if r.input_error),
        "all_axes_certified": sum(1 for r in records if r.certificates and all(c.certified for c in r.certificates)),
        "any_error": sum(1 for r in records if any(c.status == STATUS_ERROR for c in r.certificates)),
        "with_truth": sum(1 for r in records if r.has_truth),
    }
    stamps = [r.stamp_ns for r in records]
    span = (max(stamps) - min(stamps)) / 1e9 if len(stamps) > 1 else 0.0
    cert_ms = [r.compute_ms.get(a, float("nan")) for r in records for a in axes
               if r.cert(a) is not None and r.cert(a).status != STATUS_ERROR]
    out: dict[str, Any] = {
        "frames": frames,
        "axes": {a: axis_summary(records, a, units[a], requested[a]) for a in axes},
        "time": {
            "wall_s": wall_s,
            "recording_span_s": span,
            "per_certificate_ms_mean": metrics.mean(cert_ms),
            "per_certificate_ms_median": metrics.median(cert_ms),
            "per_frame_ms_mean": metrics.mean([r.total_ms for r in records if not r.input_error]),
            "latency_ms_mean": metrics.mean([r.latency_ms for r in records]),
        },
    }
    errors: dict[str, int] = {}
    for r in records:
        for c in r.certificates:
            if c.status == STATUS_ERROR:
                key = " ".join(str(c.reason).split())[:200]
                errors[key] = errors.get(key, 0) + 1
    out["error_reasons"] = dict(sorted(errors.items(), key=lambda kv: -kv[1]))
    budgeted = [c.bounds["time_budget"] for r in records for c in r.certificates if "time_budget" in (c.bounds or {})]
    if budgeted:
        out["time_budget"] = budget_summary(records, budgeted)
    if extra:
        out.update(extra)
    return jsonable(out, inf="null")


def budget_summary(records: Sequence[FrameRecord], budgeted: list[dict[str, Any]]) -> dict[str, Any]:
    """Under a time budget: the axes sized, reduced, coarsened (budget.Level) and over their share, the
    frames over the budget, the longest frame and the start-up work left out of the frames."""
    budget = float(budgeted[0]["frame_budget_s"])
    over = [t["spent_s"] - t["share_s"] for t in budgeted if t.get("over_budget")]
    frame_s = [r.total_ms / 1000.0 for r in records if not r.input_error]
    return {"frame_budget_s": budget, "axes": len(budgeted), "reduced": sum(bool(t["reduced"]) for t in budgeted),
            "coarsened": sum(bool(t.get("coarsened")) for t in budgeted), "axes_over_share": len(over),
            "most_over_share_s": max(over) if over else 0.0, "frames_over_budget": sum(1 for f in frame_s if f > budget),
            "longest_frame_s": max(frame_s) if frame_s else None, "startup_s": sum(r.startup_ms for r in records) / 1000.0}


# ---- text table ---------------------------------------------------------------------------

def _num(v: Any, fmt: str = ".4g", none: str = "-") -> str:
    if v is None:
        return none
    if isinstance(v, float) and not math.isfinite(v):
        return none
    return format(v, fmt)


def _pct(v: Any) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def _table(rows: list[list[str]], header: list[str]) -> list[str]:
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    line = lambda cells: "  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
    return [line(header), line(["-" * w for w in widths])] + [line(r) for r in rows]


def format_table(summary: dict[str, Any]) -> str:
    """The human summary printed at the end of ``pws replay``."""
    f = summary["frames"]
    lines = []
    head = summary.get("title")
    if head:
        lines.append(head)
    setup = summary.get("setup")
    if setup:
        lines.append(setup)
    lines.append(f"frames: {f['seen']} seen, {f['processed']} processed, {f['dropped_realtime']} dropped (realtime), "
                  f"{f['input_errors']} input errors, {f['all_axes_certified']} certified on every axis")
    rows = []
    for axis, a in summary["axes"].items():
        u = a["unit"]
        rows.append([axis, f"±{a['requested_radius']:.4g} {u}", str(a["certified"]), str(a["not_certified"]), str(a["abstained"]),
                     str(a["errors"]), f"{_num(a['radius_mean'])} / {_num(a['radius_median'])} {u}",
                     f"{_num(a['compute_ms_mean'], '.0f')} / {_num(a['compute_ms_median'], '.0f')}",
                     _pct(a["clean_accuracy"]), _pct(a["certified_accuracy"])])
    lines += _table(rows, ["axis", "requested", "certified", "not cert.", "abstained", "errors", "radius mean / median",
                           "ms per cert. mean / median", "clean acc.", "cert. acc."])
    for axis, a in summary["axes"].items():
        curve = a.get("certified_accuracy_vs_radius")
        if curve:
            pts = [curve[i] for i in range(0, len(curve), max(1, (len(curve) - 1) // 4))]
            if pts[-1] is not curve[-1]:
                pts.append(curve[-1])
            lines.append(f"certified accuracy vs radius ({axis}, {a['unit']}): "
                         + "  ".join(f"{r:.4g}: {_pct(acc)}" for r, acc in pts)
                         + f"  (over {a['with_truth']} frames with ground truth)")
    t = summary["time"]
    speed = ""
    if t.get("wall_s") and t.get("recording_span_s"):
        speed = f", {t['recording_span_s'] / t['wall_s']:.2f}x real time"
    lines.append(f"time: {_num(t.get('wall_s'), '.1f')} s wall for {_num(t.get('recording_span_s'), '.1f')} s of recording{speed}; "
                 f"{_num(t.get('per_frame_ms_mean'), '.0f')} ms per frame, {_num(t.get('per_certificate_ms_mean'), '.0f')} ms per "
                 "certificate (means; a frame's axes may run at the same time: axis_threads)")
    b = summary.get("time_budget")
    if b:
        lines.append(f"time budget {b['frame_budget_s']:g} s per frame: longest frame {_num(b['longest_frame_s'], '.1f')} s, "
                     f"{b['frames_over_budget']} frame(s) over; of {b['axes']} axes {b['reduced']} reduced, {b['coarsened']} coarsened, "
                     f"{b['axes_over_share']} over their share (at most {b['most_over_share_s']:.2f} s); start-up work "
                     f"{b['startup_s']:.1f} s (not in the frames)")
    if summary.get("error_reasons"):
        top = list(summary["error_reasons"].items())[:3]
        lines.append("errors: " + "; ".join(f"{n}x {reason}" for reason, n in top))
    if summary.get("out"):
        lines.append(f"output: {summary['out']}")
    return "\n".join(lines)


# ---- report folder ------------------------------------------------------------------------

def frame_rows(records: Sequence[FrameRecord]) -> list[dict[str, Any]]:
    """One row per frame and axis (the columns of :data:`CSV_COLUMNS`)."""
    t0 = min((r.stamp_ns for r in records), default=0)
    rows = []
    for r in records:
        for c in r.certificates:
            rows.append({
                "frame": r.index, "stamp_ns": r.stamp_ns, "time_s": f"{(r.stamp_ns - t0) / 1e9:.6f}", "frame_id": r.frame_id,
                "source": r.source, "axis": c.axis, "unit": c.unit, "status": c.status, "certified": int(bool(c.certified)),
                "label": c.label, "class_name": c.class_name,
                "truth_label": "" if r.truth_label is None else r.truth_label, "truth_class": r.truth_class,
                "correct": "" if c.axis not in r.correct else int(r.correct[c.axis]),
                "radius": f"{c.radius:.9g}", "requested_radius": f"{c.requested_radius:.9g}",
                "p_a_lower": f"{c.min_p_a_lower:.9g}", "num_partitions": c.num_partitions, "classifier_calls": c.classifier_calls,
                "compute_ms": f"{r.compute_ms.get(c.axis, float('nan')):.3f}", "latency_ms": f"{r.latency_ms:.3f}",
                "reason": " ".join(str(c.reason).split()),
            })
    return rows


def write_csv(path: str | Path, records: Sequence[FrameRecord]) -> Path:
    path = Path(path)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(CSV_COLUMNS))
        w.writeheader()
        w.writerows(frame_rows(records))
    return path


def _figure(nrows: int, ncols: int, size: tuple[float, float]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100)
    FigureCanvasAgg(fig)
    axs = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axs


def _legend(ax, loc: str) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc=loc)
    else:
        ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes, color="0.5")


def plot_accuracy_vs_radius(path: str | Path, summary: dict[str, Any]) -> Path:
    """Certified accuracy vs radius per axis (with ground truth), else the certified fraction vs radius."""
    axes = summary["axes"]
    n = max(1, len(axes))
    fig, axs = _figure(1, n, (4.2 * n, 3.4))
    for k, (axis, a) in enumerate(axes.items()):
        ax = axs[0][k]
        curve = a.get("certified_accuracy_vs_radius")
        label = "certified accuracy"
        if not curve:
            curve, label = a.get("certified_fraction_vs_radius"), "fraction certified (no ground truth)"
        if curve:
            xs, ys = [p[0] for p in curve], [p[1] for p in curve]
            ax.step(xs, ys, where="post", color="C0", label=label)
            ax.plot(xs, ys, "o", color="C0", markersize=3)
        if a.get("clean_accuracy") is not None:
            ax.axhline(a["clean_accuracy"], color="C2", linestyle="--", linewidth=1, label="clean accuracy")
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel(f"radius ({a['unit']})")
        ax.set_ylabel(label)
        ax.set_title(f"{axis}: ±{a['requested_radius']:.4g} {a['unit']} requested")
        ax.grid(True, alpha=0.3)
        _legend(ax, "lower left")
    fig.tight_layout()
    fig.savefig(str(path))
    return Path(path)


def plot_frames(path: str | Path, records: Sequence[FrameRecord], axes: Sequence[str]) -> Path:
    """Per-frame certified radius (as a fraction of the requested one) and latency over time."""
    fig, axs = _figure(2, 1, (8.0, 5.6))
    t0 = min((r.stamp_ns for r in records), default=0)
    top, bottom = axs[0][0], axs[1][0]
    for k, axis in enumerate(axes):
        pts = [((r.stamp_ns - t0) / 1e9, r.cert(axis)) for r in records]
        pts = [(t, c) for t, c in pts if c is not None]
        ok = [(t, c.radius / c.requested_radius if c.requested_radius > 0 else 0.0) for t, c in pts if c.status != STATUS_ERROR]
        bad = [t for t, c in pts if c.status == STATUS_ERROR]
        if ok:
            top.plot([p[0] for p in ok], [p[1] for p in ok], "o-", color=f"C{k}", markersize=3, label=f"{axis}")
        if bad:
            top.plot(bad, [0.0] * len(bad), "x", color=f"C{k}", label=f"{axis} error")
        lat = [((r.stamp_ns - t0) / 1e9, r.compute_ms.get(axis, float("nan"))) for r in records if not r.input_error]
        if lat:
            bottom.plot([p[0] for p in lat], [p[1] for p in lat], ".-", color=f"C{k}", label=f"compute {axis}")
    lat = [((r.stamp_ns - t0) / 1e9, r.latency_ms) for r in records]
    if lat:
        bottom.plot([p[0] for p in lat], [p[1] for p in lat], "s-", color="k", markersize=3, label="latency (frame)")
    top.set_ylabel("certified radius / requested")
    top.set_ylim(-0.05, 1.1)
    top.grid(True, alpha=0.3)
    _legend(top, "lower right")
    top.set_title("per-frame certified radius")
    bottom.set_xlabel("time since first frame (s, source stamps)")
    bottom.set_ylabel("ms")
    bottom.grid(True, alpha=0.3)
    _legend(bottom, "upper right")
    bottom.set_title("latency and compute time per certificate")
    fig.tight_layout()
    fig.savefig(str(path))
    return Path(path)


def write_report(directory: str | Path, records: Sequence[FrameRecord], summary: dict[str, Any], axes: Sequence[str]) -> list[Path]:
    """``frames.csv``, ``summary.json``, ``certified_accuracy_vs_radius.png``, ``frames.png`` in ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    files = [write_csv(d / "frames.csv", records)]
    p = d / "summary.json"
    p.write_text(json.dumps(summary, indent=2, sort_keys=False) + "\n")
    files.append(p)
    files.append(plot_accuracy_vs_radius(d / "certified_accuracy_vs_radius.png", summary))
    files.append(plot_frames(d / "frames.png", records, axes))
    return files


__all__ = ["CSV_COLUMNS", "FrameRecord", "axis_summary", "format_table", "frame_rows", "plot_accuracy_vs_radius",
           "plot_frames", "radius_grid", "summarize", "write_csv", "write_report"]

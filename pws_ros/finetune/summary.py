"""The human summary of a finished ``pws finetune`` run (:func:`summary_lines`)."""
from __future__ import annotations

from .options import FinetuneResult


def summary_lines(result: FinetuneResult) -> list[str]:
    """The human summary of a finished run."""
    r = result.report
    if result.interrupted or "before" not in r:
        return [result.message] if result.message else []
    b, a = r["before"] or {"p_a_quantiles": {}}, r["after"]

    def q(d: dict, key: str) -> str:
        v = d.get(key)
        return "-" if v is None else f"{v:.3f}"

    target = "the label" if r.get("new_head") else "the teacher"
    lines = [f"model: {result.model_path}" + "".join(f"\n  also: {p}" for p in result.extra_files),
             f"report: {result.report_path}",
             f"held-out frames: {a['frames']} at sigma {r['sigma']:g}, {r['eval_samples']} noise samples each",
             f"{'':28s}{'before':>10s}{'after':>10s}",
             f"{'agreement with ' + target:28s}{q(b, 'agreement'):>10s}{q(a, 'agreement'):>10s}",
             f"{'p_A median':28s}{q(b['p_a_quantiles'], 'q50'):>10s}{q(a['p_a_quantiles'], 'q50'):>10s}",
             f"{'p_A 10% quantile':28s}{q(b['p_a_quantiles'], 'q10'):>10s}{q(a['p_a_quantiles'], 'q10'):>10s}",
             f"{'p_' + ('label' if r.get('new_head') else 'teacher') + ' mean':28s}{q(b, 'p_teacher_mean'):>10s}{q(a, 'p_teacher_mean'):>10s}"]
    st = r.get("teacher_stability")
    if st:
        lines.append(f"{'agreement, stable frames':28s}{q(b, 'agreement_on_stable'):>10s}{q(a, 'agreement_on_stable'):>10s}"
                     f"   ({st['stable_frames']} of {st['frames']} held-out frames: the teacher keeps its answer under "
                     f"noise sigma {st['sigma']:g} and the motion views; on the others no smoothed classifier can be expected to agree)")
    if "accuracy_vs_truth" in a:
        lines.append(f"{'clean accuracy (labels)':28s}{q(b, 'clean_accuracy_vs_truth'):>10s}{q(a, 'clean_accuracy_vs_truth'):>10s}"
                     "   (the base classifier on the clean frames)")
        lines.append(f"{'smoothed accuracy (labels)':28s}{q(b, 'accuracy_vs_truth'):>10s}{q(a, 'accuracy_vs_truth'):>10s}")
    s, m = r["seconds"], r["memory"]
    lines.append(f"time: frames {s['frames']:.0f} s, training {s['training']:.0f} s (all runs of a resumed one), this run "
                 f"{s['total']:.0f} s; peak memory "
                 f"{m['peak_rss_mb']:.0f} MB" + (f", GPU {m['peak_cuda_mb']:.0f} MB" if "peak_cuda_mb" in m else ""))
    return lines


__all__ = ["summary_lines"]

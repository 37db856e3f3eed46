"""The summary and the verdict of a replay run."""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

from ..core.motion import UNITS
from ..core.result import STATUS_ERROR
from .report import summarize
from .options import InputTopics
from .schedule import closest_gap_ms


def replay_summary(rp: Any, inputs: InputTopics, out: Path | None, dropped: int, wall: float, extra_frames: dict,
                   bag_info: dict, counts: dict) -> dict[str, Any]:
    """The summary dict of a finished run (written as summary.json, printed as the table)."""
    cfg = rp.config
    axes = list(cfg.axes)
    s = summarize(rp.records, axes=axes, units={a: UNITS[a] for a in axes}, requested={a: cfg.radius_for(a) for a in axes},
                  frames_seen=rp.frames_seen, dropped=dropped, wall_s=wall)
    s["frames"].update(extra_frames)
    s["title"] = f"pws replay {bag_info['path']}" + (f" -> {out}" if out else " (no output bag)")
    coverage = f"coverage {cfg.coverage}, " if cfg.method != "cms" else ""  # cms has no coverage rule
    s["setup"] = (f"method {cfg.method}, {coverage}imaging {cfg.imaging}, sigma {cfg.sigma:g}, n0 {cfg.n0}, n {cfg.n}, "
                  f"risk alpha {cfg.alpha:g} per frame ({cfg.alpha / max(1, len(axes)):g} per axis), "
                  f"seed {cfg.seed}, device {rp.engine.device}, {'realtime policy' if rp.opts.realtime else 'every frame'}; "
                  + inputs.describe())
    s["bag"] = bag_info
    s["out"] = str(out) if out else None
    s["output_topics"] = counts
    s["inputs"] = {"mode": inputs.mode, **inputs.roles()}
    s["config"] = {"method": cfg.method, "coverage": cfg.coverage if cfg.method != "cms" else None, "axes": axes, "radius": {a: cfg.radius_for(a) for a in axes},
                   "imaging": cfg.imaging, "sigma": cfg.sigma, "n0": cfg.n0, "n": cfg.n, "alpha": cfg.alpha,
                   # the risk of each frame's whole statement (all axes), and what each axis spends of it
                   "frame_alpha": cfg.alpha, "alpha_per_axis": cfg.alpha / max(1, len(axes)),
                   "num_anchors": cfg.num_anchors, "seed": cfg.seed, "device": rp.engine.device,
                   "batch_size": cfg.batch_size, "batch_size_used": getattr(rp.engine, "batch_size", cfg.batch_size),
                   "model_path": cfg.model_path, "realtime": rp.opts.realtime,
                   "dense_cloud": cfg.dense_cloud_path if cfg.method == "pws" else None}
    s["warnings"] = list(rp.warnings)
    return s

def replay_verdict(rp: Any, inputs: InputTopics) -> tuple[int, str]:
    """(exit code, message): 0 if some axis of some frame got a certificate, else 2 and why not."""
    done = any(c.status != STATUS_ERROR for r in rp.records for c in r.certificates)
    if done:
        return 0, ""
    problems = list(dict.fromkeys(rp.problems))
    if not rp.records:
        why = []
        if problems:
            why.append(problems[0])
        if inputs.mode in ("rgbd", "auto") and inputs.depth:
            gap = closest_gap_ms(rp.stamps["depth"], rp.stamps["color"])
            tol = max(rp.config.sync_tolerance_s, rp.config.sync_max_skew_s) * 1000.0
            if not rp.stamps["depth"] or not rp.stamps["color"]:
                why.append(f"no {'depth' if not rp.stamps['depth'] else 'colour'} message could be read")
            elif gap is not None and gap > tol:
                why.append(f"depth and colour stamps never came within sync_tolerance_s = {rp.config.sync_tolerance_s:g} s "
                           f"nor sync_max_skew_s = {rp.config.sync_max_skew_s:g} s (closest pair {gap:.1f} ms apart; "
                           "see --sync-tolerance and --sync-max-skew)")
        if inputs.mode in ("pointcloud2", "auto") and inputs.points and not rp.stamps["points"]:
            why.append(f"no message on {inputs.points} could be read")
        return 2, "nothing could be certified: no complete input frame" + (": " + "; ".join(why) if why else "")
    reasons = Counter(c.reason for r in rp.records for c in r.certificates)
    top, n = reasons.most_common(1)[0]
    head = problems[0] if problems and all(r.input_error for r in rp.records) else top
    return 2, f"nothing could be certified: every frame failed ({len(rp.records)} frame(s)): {head}"

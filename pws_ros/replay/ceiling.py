"""What a camera allows: the certificate *ceiling* of a recording next to the radius a model gets.

The ceiling of a frame and axis is the radius a classifier that **never changes its answer** gets
(:func:`never_changing_model`: constant logits, so every noise sample votes for one class and every
anchor's ``p_A`` lower bound is the largest the sample sizes allow). It is set by the imaging (the
camera, the input size, the render factor, the depth fill), the requested radius, the plan and the
anchor budget (``n0``, ``n``, ``num_anchors``, ``alpha``, ``sigma``) — not by any model. The radius a
real model gets is at most about that, and lower by how much its answer changes under noise of ``sigma``.

Reading the two side by side (:func:`advice`): a low ceiling says the camera, the input size, the
requested radius or ``sigma`` must change (a larger ``sigma`` gives larger Cohen radii to every anchor;
a smaller input shows less of each motion); a high ceiling and a low model radius say the model is not
robust to the noise (``pws finetune``, a denoiser, or a smaller ``sigma``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..core.errors import require
from ..core.model import LoadedModel
from .options import ReplayOptions, ReplayResult

NEVER_CHANGING_CLASSES = ["always", "never"]


class _Constant(torch.nn.Module):
    """Logits (B, 2) that do not depend on the image: the top class is always class 0."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tensor([5.0, 0.0], dtype=x.dtype, device=x.device).expand(x.shape[0], 2)


def never_changing_model(input_size: tuple[int, int] | None) -> LoadedModel:
    """A classifier that never changes its answer, taking ``input_size`` = (H, W) images (None: any)."""
    size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
    return LoadedModel(_Constant().eval(), list(NEVER_CHANGING_CLASSES), size, "never-changing classifier",
                       {"ceiling": True})


@dataclass
class CeilingRow:
    """One frame and axis: the requested radius, the ceiling and (with a model) the model's radius."""

    frame: int
    stamp_ns: int
    axis: str
    unit: str
    requested: float
    ceiling: float
    ceiling_s: float
    ceiling_status: str
    model: float = math.nan
    model_s: float = math.nan
    model_status: str = ""
    model_class: str = ""
    model_p_a: float = math.nan
    recording: str = ""
    whole: float = math.nan       # with a working volume: the ceiling of the whole frame (no volume), beside it
    whole_s: float = math.nan

    def share(self, value: float) -> float:
        return value / self.requested if self.requested > 0 else math.nan

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["ceiling_share"] = self.share(self.ceiling)
        d["model_share"] = self.share(self.model)
        d["whole_share"] = self.share(self.whole)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def _radii(result: ReplayResult) -> dict[tuple[int, str], Any]:
    return {(r.index, c.axis): (r, c) for r in result.records for c in r.certificates}


def stopped(result: ReplayResult) -> str:
    """The signal that stopped a run (SIGINT, SIGTERM), or ''."""
    return str(result.summary.get("interrupted") or "")


def ceiling(opts: ReplayOptions, model: LoadedModel | None, *, input_size: tuple[int, int] | None = None,
            run=None) -> tuple[list[CeilingRow], ReplayResult, ReplayResult | None]:
    """Replay ``opts`` (no output bag) with the never-changing classifier of ``input_size`` (default: the
    model's), then with ``model`` (None: the ceiling alone); the rows pair them by frame and axis. With a
    working volume configured, the ceiling of the whole frame (no volume) is measured too and put beside it.
    A run stopped by a signal (:func:`stopped`) ends it: the rows are those of the frames it finished.
    ``run`` is the replay function (tests)."""
    from . import replay as _replay

    run = run or _replay
    size = input_size or (model.input_size if model is not None else None)
    require(size is not None, "the ceiling needs the classifier's input size: give a model that declares it, or --size HxW")
    base = replace(opts, write_output=False, report_dir=None)
    top = run(replace(base, model=never_changing_model(size), denoiser=None))
    require(stopped(top) or (top.exit_code == 0 and top.records), f"the ceiling run failed: {top.message}")
    got = None
    if model is not None and not stopped(top):   # (a stopped run: the rows of the frames it finished)
        require(model.input_size is None or tuple(model.input_size) == tuple(size),
                f"--size {size[1]}x{size[0]} differs from the model's input {model.input_size[1]}x{model.input_size[0]}: "
                "the ceiling and the model's radii would be about different images")
        got = run(replace(base, model=model))
        require(got.exit_code == 0 or stopped(got), f"the model's run failed: {got.message}")
    theirs = _radii(got) if got is not None else {}
    whole = {}
    if opts.config.working_volume is not None and not any(stopped(r) for r in (top, got) if r is not None):
        no_volume = opts.config.with_params({f"working_volume.{k}": 0.0 for k in ("near", "far", "x_min", "x_max", "y_min", "y_max", "window")})
        frame = run(replace(base, config=no_volume, model=never_changing_model(size), denoiser=None))
        require(frame.exit_code == 0 and frame.records, f"the whole frame's ceiling run failed: {frame.message}")
        whole = _radii(frame)
    rows = []
    for (index, axis), (rec, c) in _radii(top).items():
        row = CeilingRow(index, rec.stamp_ns, axis, c.unit, float(c.requested_radius), float(c.radius),
                         float(c.timings.get("total", math.nan)), c.status)
        if (index, axis) in theirs:
            _r, m = theirs[(index, axis)]
            row.model, row.model_s, row.model_status = float(m.radius), float(m.timings.get("total", math.nan)), m.status
            row.model_class, row.model_p_a = m.class_name, float(m.min_p_a_lower)
        if (index, axis) in whole:
            _r, w = whole[(index, axis)]
            row.whole, row.whole_s = float(w.radius), float(w.timings.get("total", math.nan))
        rows.append(row)
    for row in rows:
        row.recording = str(opts.bag)
    return rows, top, got


def advice(rows: list[CeilingRow]) -> list[str]:
    """One line per axis: the median ceiling and model radius (share of the request) and what limits."""
    out = []
    for axis in dict.fromkeys(r.axis for r in rows):
        sel = [r for r in rows if r.axis == axis]
        top = float(np.median([r.share(r.ceiling) for r in sel]))
        line = f"{axis}: median ceiling {top:.0%} of the requested radius"
        frame = [r.share(r.whole) for r in sel if math.isfinite(r.whole)]
        if frame:
            line += f" in the working volume ({float(np.median(frame)):.0%} on the whole frame)"
        mod = [r.share(r.model) for r in sel if math.isfinite(r.model)]
        if mod:
            m = float(np.median(mod))
            line += f", the model {m:.0%}"
            if top < 0.5:
                line += (" - the imaging limits it: request a smaller radius, raise sigma, use a smaller model input, "
                         "or render_factor 0")
            elif m < 0.5 * top:
                line += " - the model limits it: its answer changes under noise of this sigma (pws finetune, a denoiser, a smaller sigma)"
            else:
                line += " - the model reaches most of what the camera allows"
        elif top < 0.5:
            line += " - the imaging limits it: request a smaller radius, raise sigma, or use a smaller model input"
        out.append(line)
    return out


def format_rows(rows: list[CeilingRow]) -> str:
    """The rows as a table; a first column names the recording when they come from several."""
    names = [r.recording for r in rows]
    width = max(len(n) for n in names) if len(set(names)) > 1 else 0
    rec = (lambda n: f"{n:<{width}} ") if width else (lambda n: "")
    volume = any(math.isfinite(r.whole) for r in rows)   # a working volume: its ceiling, and the whole frame's beside it
    head = rec("recording") + f"{'frame':>5} {'axis':>4} {'requested':>11} {'ceiling':>18} " \
        + (f"{'whole frame':>18} " if volume else "") + f"{'model':>18}  {'class, p_A':<24}"
    lines = [head]
    for r in rows:
        ceil = f"{r.share(r.ceiling):5.0%} {r.ceiling_s:5.1f} s"
        frame = (f"{r.share(r.whole):5.0%} {r.whole_s:5.1f} s" if math.isfinite(r.whole) else "-") if volume else ""
        mod = f"{r.share(r.model):5.0%} {r.model_s:5.1f} s" if math.isfinite(r.model) else "-"
        cls = f"{r.model_class}, {r.model_p_a:.3f}" if r.model_status else ""
        lines.append(rec(r.recording) + f"{r.frame:>5} {r.axis:>4} {r.requested:>9.4g} {r.unit:<1} {ceil:>18} "
                     + (f"{frame:>18} " if volume else "") + f"{mod:>18}  {cls:<24}")
    return "\n".join(lines)


__all__ = ["CeilingRow", "NEVER_CHANGING_CLASSES", "advice", "ceiling", "format_rows", "never_changing_model"]

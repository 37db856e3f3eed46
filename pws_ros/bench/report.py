"""The report of ``pws bench``: ``bench.json`` (the measured records, the tables, the claims, the
full-run estimate) and ``report.md`` with its PNG plots.

- :mod:`.tables`: the numbers (every table as data, computed from the records);
- :mod:`.verdicts`: the verdicts on the paper's claims, with their evidence and why;
- :mod:`.render`: the plots and the markdown (with :mod:`.text` for numbers and tables).

Everything is computed from the measured records; nothing is typed in by hand except the paper's own
numbers (quoted for comparison) and the wording of the claims.
"""
from __future__ import annotations

import json
from pathlib import Path

from ..core.jsonable import jsonable
from .verdicts import claims
from .render import make_plots, render_markdown
from .tables import estimate_full_seconds, summarize


def write_report(res: dict, out_dir: str | Path) -> dict[str, Path]:
    """Write ``bench.json``, ``report.md`` and the plots of ``res`` into ``out_dir``; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summ = summarize(res)
    cl = claims(res, summ)
    est = estimate_full_seconds(res)
    plots = make_plots(res, summ, out_dir)
    res = dict(res)
    res["summary"] = summ
    res["claims"] = cl
    res["full_run_estimate"] = est
    res["plots"] = plots
    json_path = out_dir / "bench.json"
    json_path.write_text(json.dumps(jsonable(res, inf="clamp"), indent=1, allow_nan=False) + "\n")
    md_path = out_dir / "report.md"
    md_path.write_text(render_markdown(res, summ, cl, est, plots))
    return {"json": json_path, "report": md_path, **{p: out_dir / p for p in plots}}


__all__ = ["write_report"]

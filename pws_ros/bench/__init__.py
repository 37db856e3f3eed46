"""``pws bench``: PwS, PwS-L and PwS-OF against the CMS baseline on the procedural world, side by side,
and the paper's qualitative claims checked on it (see :mod:`.settings` for what each preset measures)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from .verdicts import claims
from .report import write_report
from .tables import summarize
from .grids import capped_plan, grid_plan, paper_rule
from .machine import PeakMemory
from .runner import Bench
from .settings import FULL, PRESETS, QUICK, SMOKE, BenchSettings, scene_ids


def run_bench(settings: BenchSettings, models_dir: str | Path, out_dir: str | Path, device: str = "cpu",
              log: Callable[[str], None] | None = None) -> dict[str, Path]:
    """Measure everything ``settings`` asks for with the models in ``models_dir`` and write
    ``report.md``, ``bench.json`` and the PNG plots into ``out_dir``. Returns the written paths."""
    bench = Bench(settings, models_dir, device=device, log=log)
    results = bench.run()
    return write_report(results, out_dir)


def stderr_log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


__all__ = ["FULL", "PRESETS", "QUICK", "SMOKE", "Bench", "BenchSettings", "PeakMemory", "capped_plan", "claims", "grid_plan",
           "paper_rule", "run_bench", "scene_ids", "stderr_log", "summarize", "write_report"]

"""How the bench report writes numbers and tables (markdown), shared by :mod:`.verdicts` and :mod:`.render`."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..core.motion import UNITS

METHOD_NAMES = {"pws": "PwS", "pws_l": "PwS-L", "pws_of": "PwS-OF", "cms": "CMS"}


def radius_str(axis: str, r: float) -> str:
    if UNITS[axis] == "m":
        return f"{r * 1000:g} mm"
    return f"{math.degrees(r):.3g}°"


def fmt(x, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    ax = abs(x)
    if ax != 0 and (ax >= 1e5 or ax < 1e-3):
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}"


def fmt_n(x) -> str:
    """A count: 3, 1,135, 68.3k, 2.18M."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    x = float(x)
    if x >= 1e6:
        return f"{x / 1e6:.3g}M"
    if x >= 1e4:
        return f"{x / 1e3:.3g}k"
    return f"{x:,.0f}" if x == round(x) else f"{x:,.1f}"


def frac(k: int, n: int) -> str:
    return "—" if n == 0 else f"{k / n:.2f} ({k}/{n})"


def table(header: list[str], rows: list[list[Any]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        out.append("| " + " | ".join(str(c) for c in r) + " |")
    return "\n".join(out)


def mebibytes(b) -> str:
    return "—" if b is None else f"{b / 2**20:.1f}"

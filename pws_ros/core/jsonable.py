"""Plain JSON values from what the package produces (numpy scalars and arrays, tuples, paths, NaN/inf).

One encoder for every JSON the package writes: certificates (:mod:`.result`), the replay summary
(:mod:`pws_ros.replay.report`), the plan bundles of the four-process scheme (:mod:`pws_ros.bridge.scheme`) and
``bench.json`` (:mod:`pws_ros.bench.report`). They differ only in how an infinity is written, which
``inf`` selects:

- ``"clamp"``: ``+-1e308`` (a number that still compares and plots; certificates, bench);
- ``"null"``: ``null``, like NaN (the replay summary: no infinite statistic is meaningful there);
- ``"string"``: ``"inf"`` / ``"-inf"`` (the plan bundle, whose parser reads them back exactly).

NaN is always ``null``. Mappings get string keys, tuples become lists, ``Path`` a string; numpy
scalars become Python scalars and arrays (any size, also 1 element) nested lists, element by element
(so NaN/inf inside an array are encoded like any other); anything else with ``tolist()`` (a torch
tensor) likewise.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

INF_MODES = ("clamp", "null", "string")


def _infinity(x: float, inf: str) -> Any:
    if inf == "clamp":
        return 1e308 if x > 0 else -1e308
    if inf == "string":
        return "inf" if x > 0 else "-inf"
    return None


def jsonable(obj: Any, *, inf: str = "clamp") -> Any:
    """``obj`` as plain JSON types (see the module docstring; ``inf`` in :data:`INF_MODES`)."""
    if inf not in INF_MODES:
        raise ValueError(f"inf must be one of {', '.join(INF_MODES)}, got {inf!r}")
    return _encode(obj, inf)


def _encode(obj: Any, inf: str) -> Any:
    if isinstance(obj, dict):
        return {str(k): _encode(v, inf) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_encode(v, inf) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):  # numpy scalar (np.float64 too) or array, torch tensor
        return _encode(obj.tolist(), inf)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else _infinity(obj, inf)
    return obj


__all__ = ["INF_MODES", "jsonable"]

"""The one JSON encoder (pws_ros.core.jsonable): what each infinity mode writes, and that numpy arrays of
any size (NaN/inf inside included), numpy scalars, tuples and paths come out as plain JSON."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pws_ros.core.jsonable import jsonable

INF = float("inf")


@pytest.mark.parametrize("mode,pos,neg", [("clamp", 1e308, -1e308), ("null", None, None), ("string", "inf", "-inf")])
def test_infinity_modes(mode, pos, neg):
    obj = {"a": INF, "b": [-INF, float("nan")], "c": np.array([1.0, np.inf, -np.inf, np.nan]), "d": np.float64(-np.inf)}
    out = jsonable(obj, inf=mode)
    assert out == {"a": pos, "b": [neg, None], "c": [1.0, pos, neg, None], "d": neg}
    json.dumps(out, allow_nan=False)  # strictly JSON


def test_plain_types():
    obj = {1: (np.int64(3), np.float32(0.5), np.bool_(True)), "p": Path("/x/y"), "one": np.array([2.5]), "zero_d": np.array(4.0),
           "m": np.eye(2, dtype=np.float32), "empty": np.zeros(0), "s": "text", "n": None, "f": 0.1}
    out = jsonable(obj)
    assert out == {"1": [3, 0.5, True], "p": "/x/y", "one": [2.5], "zero_d": 4.0, "m": [[1.0, 0.0], [0.0, 1.0]], "empty": [],
                   "s": "text", "n": None, "f": 0.1}
    assert type(out["1"][0]) is int and type(out["1"][1]) is float and type(out["1"][2]) is bool and type(out["zero_d"]) is float
    with pytest.raises(ValueError):
        jsonable(1.0, inf="big")


def test_plan_bundle_writes_infinities_as_strings():
    """The scheme writes "inf"/"-inf" (strict JSON; ``float()`` reads them back)."""
    from pws_ros.bridge import scheme
    from pws_ros.core.camera import CameraIntrinsics
    from pws_ros.core.partition import Plan

    cam = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5, "cam")
    alphas = np.linspace(-0.01, 0.01, 5)
    plan = Plan(method="pws_of", axis="tz", radius=0.01, delta_alpha=0.005, num_partitions=5, alphas=alphas,
                details={"bound": INF, "low": -INF})
    text = scheme.plan_bundle_to_json(scheme.PlanBundle(7, "cam", "pws_of", cam, ["tz"], {"tz": plan}, {}))
    assert '"bound": "inf"' in text and '"low": "-inf"' in text
    back = scheme.plan_bundle_from_json(text).plans["tz"]
    assert float(back.details["bound"]) == INF and float(back.details["low"]) == -INF
    assert np.array_equal(back.alphas, alphas)

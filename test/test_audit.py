"""``pws audit`` / :func:`pws_ros.core.audit.audit_bounds`: finds the violations of a wrong bound, none of a sound one.

The audit is first checked on an analytic toy imaging model (a 1x1 image whose value is ``alpha``: every
distance is known in closed form), then on the paper imaging model with the real bounds and with a
deliberately wrong bound (half the reported one), then end to end on the shipped ``bags/sample_view``.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pws_ros.cli import main
from pws_ros.core.audit import audit_bounds, segment_poses
from pws_ros.core.bounds import segment_values
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from pws_ros.core.partition import make_grid
from pws_ros.core.render import Renderer

ROOT = Path(__file__).resolve().parents[1]
VIEW = ROOT / "bags" / "sample_view"


class Ramp:
    """Toy imaging model: a 1x1 image, all three channels equal to alpha."""

    def render_batch(self, alphas):
        a = np.asarray(alphas, np.float64)
        return np.repeat(a[:, None, None, None], 3, axis=3).astype(np.float32)


class RampBounds:
    """Bounds for :class:`Ramp` on a unit grid, times ``scale``: on ``[k, k+1]``
    ``3 (a - k)^2 + 3 (a - k - 1)^2 <= 3`` (at the ends) and ``3 (a - y)^2 <= 3 max((k - y)^2, (k + 1 - y)^2)``."""

    def __init__(self, scale=1.0):
        self.scale = scale

    def pair_bound_sq(self, frames, k0=0):
        return np.full(len(frames) - 1, 3.0 * self.scale)

    def anchor_dist_sq(self, frames, anchor, k0=0):
        y = float(anchor[0, 0, 0])
        k = k0 + np.arange(len(frames) - 1, dtype=np.float64)
        return 3.0 * np.maximum((k - y) ** 2, (k + 1 - y) ** 2) * self.scale


def test_audit_on_an_analytic_model():
    alphas = np.arange(5, dtype=np.float64)  # 4 unit segments
    rep = audit_bounds(Ramp(), alphas, RampBounds(), anchor_alphas=[0.0, 2.0], poses_per_segment=16)
    assert rep.ok and rep.segments == 4 and rep.poses_checked == 4 * 16 and rep.checks == 3 * 4 * 16
    assert rep.worst_ratio == pytest.approx(1.0)  # reached at the segment ends
    many = audit_bounds(Ramp(), alphas, RampBounds(), anchor_alphas=[0.0], poses_per_segment=150)  # > one chunk
    assert many.ok and many.poses_checked == 4 * 150 and many.checks == 2 * 4 * 150
    # 1% too small: only the poses near where the bound is reached are flagged
    rep = audit_bounds(Ramp(), alphas, RampBounds(0.99), anchor_alphas=[0.0, 2.0], poses_per_segment=16)
    assert not rep.ok and rep.worst_ratio == pytest.approx(1 / 0.99)
    for v in rep.violations:
        k = v.segment
        assert k <= v.alpha <= k + 1
        if v.kind == "pair":
            assert v.measured == pytest.approx(3 * (v.alpha - k) ** 2 + 3 * (v.alpha - k - 1) ** 2)
            assert v.measured > 0.99 * 3
        else:
            y = [0.0, 2.0][v.anchor]
            assert v.measured == pytest.approx(3 * (v.alpha - y) ** 2)
            assert v.measured > 0.99 * 3 * max((k - y) ** 2, (k + 1 - y) ** 2)
    kinds = {v.kind for v in rep.violations}
    assert kinds == {"pair", "anchor"}
    # every segment's pair bound is reached at both ends, so every segment has a violation
    assert {v.segment for v in rep.violations if v.kind == "pair"} == {0, 1, 2, 3}


def test_segment_poses_cover_ends_and_neighbours():
    rng = np.random.default_rng(0)
    a = segment_poses(0.1, 0.2, 20, rng)
    assert len(a) == 20 and a[0] == 0.1 and a[-1] == 0.2 and np.all((a >= 0.1) & (a <= 0.2))
    assert np.nextafter(0.1, 1) in a and np.nextafter(0.2, 0) in a
    assert len(segment_poses(0.1, 0.2, 2, rng)) == 2


class Scaled:
    """A deliberately wrong bound: the reported one times ``scale``."""

    def __init__(self, values, scale):
        self.values, self.scale = values, scale

    def pair_bound_sq(self, frames, k0=0):
        return self.scale * self.values.pair_bound_sq(frames, k0)

    def anchor_dist_sq(self, frames, anchor, k0=0):
        return self.scale * self.values.anchor_dist_sq(frames, anchor, k0)


CAM = CameraIntrinsics(width=16, height=12, fx=16.0, fy=16.0, cx=7.5, cy=5.5)


def small_scene():
    rng = np.random.default_rng(3)
    z = np.concatenate([rng.uniform(1.0, 1.3, 40), rng.uniform(2.0, 3.0, 80)])
    pts = np.stack([rng.uniform(-0.5, 0.5, len(z)) * z, rng.uniform(-0.4, 0.4, len(z)) * z, z], axis=1)
    return Cloud(pts, rng.random((len(z), 3)).astype(np.float32))


@pytest.mark.parametrize("axis", ["tx", "tz", "ry"])
def test_audit_finds_a_halved_bound_and_passes_the_real_one(axis):
    cloud = small_scene()
    radius = {"tx": 0.1, "tz": 0.3, "ry": 0.08}[axis]
    alphas = make_grid(radius, radius / 5)
    values = segment_values(cloud, CAM, axis, alphas, 0.0)
    rend = Renderer(cloud, CAM, axis)
    anchors = alphas[[0, 5, 10]]
    rep = audit_bounds(rend, alphas, values, anchor_alphas=anchors, poses_per_segment=32, seed=1)
    assert rep.ok, rep.violations[:3]
    assert rep.poses_checked == 10 * 32 and 0.5 < rep.worst_ratio <= 1.0
    bad = audit_bounds(rend, alphas, Scaled(values, 0.5), anchor_alphas=anchors, poses_per_segment=32, seed=1)
    assert not bad.ok and {v.kind for v in bad.violations} == {"pair", "anchor"}
    assert bad.worst_ratio == pytest.approx(2 * rep.worst_ratio)
    # every flagged pose really is above the wrong bound, by the audit's own measurement
    assert all(v.measured > v.bound for v in bad.violations)


def test_audit_refuses_bad_input():
    from pws_ros.core.errors import PwsError

    with pytest.raises(PwsError, match="at least 2"):
        audit_bounds(Ramp(), [0.0], RampBounds())
    with pytest.raises(PwsError, match="increasing"):
        audit_bounds(Ramp(), [0.0, 0.0, 1.0], RampBounds())
    with pytest.raises(PwsError, match="returned shape"):
        audit_bounds(Ramp(), [0.0, 1.0, 2.0], type("B", (), {"pair_bound_sq": lambda self, f, k0: np.zeros(5)})())


def scene_args(axis="tz", radius="0.01"):
    return ["audit", "--cloud", str(VIEW / "cloud.npz"), "--camera", str(VIEW / "camera.yaml"), "--axis", axis,
            "--radius", radius, "--method", "pws_of"]


def test_cli_audit_on_the_sample_view():
    # in a subprocess, as a user runs it (and so its memory churn stays out of this test process)
    proc = subprocess.run([sys.executable, "-m", "pws_ros.cli"] + scene_args() + ["--json"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    assert d["ok"] and d["num_violations"] == 0 and d["violations"] == []
    assert d["poses_checked"] >= 1000 and d["axis"] == "tz" and d["num_partitions"] >= 3
    assert 0.0 < d["worst_ratio"] <= 1.0


def test_cli_audit_exit_1_on_a_wrong_bound(capsys, monkeypatch):
    import pws_ros.core.bounds as bounds_mod

    real = bounds_mod.segment_values
    monkeypatch.setattr(bounds_mod, "segment_values", lambda *a, **k: Scaled(real(*a, **k), 0.5))
    assert main(scene_args() + ["--min-poses", "50", "--poses-per-segment", "4", "--imaging", "paper"]) == 1
    out = capsys.readouterr().out
    assert "VIOLATIONS" in out and "VIOLATION segment" in out


def test_cli_audit_surfel_imaging_exit_1_on_a_wrong_bound(capsys, monkeypatch):
    import pws_ros.core.imaging as imaging_mod

    real = imaging_mod.segment_hulls
    monkeypatch.setattr(imaging_mod, "segment_hulls", lambda *a, **k: Scaled(real(*a, **k), 0.5))
    assert main(scene_args() + ["--min-poses", "50", "--poses-per-segment", "4"]) == 1
    assert "VIOLATIONS" in capsys.readouterr().out


def test_cli_audit_bad_input(capsys, tmp_path):
    assert main(["audit", "--cloud", str(tmp_path / "missing.npz"), "--camera", str(VIEW / "camera.yaml"),
                 "--axis", "tz", "--radius", "0.01"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pws audit: error:") and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as exc:
        main(scene_args(radius="-1"))
    assert exc.value.code == 2

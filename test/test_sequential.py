"""The anchors' estimation in looks (core.sequential): a joint first look, then individual looks.

Independent references: the bounds are recomputed from the votes with scipy's Beta quantile and plain
loops (the joint count: draws on which every anchor kept the label), at the levels docs/certificate.md
states (alpha * 0.9 for the joint look, alpha * 0.1 / K for the individual one). The risk is checked by
simulation on anchors whose true p_A is known, with the noise draws shared (one latent uniform per draw)
as the certifier shares them: the share of runs in which any reported bound exceeds its anchor's true
p_A stays below alpha. End to end on the demo: fewer classifier calls, the same or a larger radius.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import beta

from pws_ros.core.sequential import FIRST_LOOK_SHARE, estimate, futile, joint_looks, single


def _cp_lower(k: int, n: int, level: float) -> float:
    return 0.0 if k == 0 else float(beta.ppf(level, k, n - k + 1))


class _Streams:
    """``K`` anchors, each draw ``j`` one latent uniform ``u_j`` shared by all (common noise): anchor ``a``
    keeps the label when ``u_j < p_a`` (``shared``) or on its own uniform (not shared). Records every call."""

    def __init__(self, p, rng, shared=True, total=4096):
        self.p = np.asarray(p, float)
        K = len(self.p)
        u = rng.random(total) if shared else None
        self.votes = (u[None, :] < self.p[:, None]) if shared else (rng.random((K, total)) < self.p[:, None])
        self.pos = np.zeros(K, int)
        self.calls = 0

    def __call__(self, idx, m):
        idx = np.asarray(idx)
        out = np.stack([self.votes[a, self.pos[a]:self.pos[a] + m] for a in idx])
        self.pos[idx] += m
        self.calls += len(idx) * m
        return out


def test_the_bounds_are_the_beta_quantiles_of_the_votes_at_the_stated_levels():
    rng = np.random.default_rng(3)
    alpha, K = 0.05, 5
    looks = joint_looks(64, 256)
    assert looks.sizes == (64, 256) and looks.joint and looks.shares == (FIRST_LOOK_SHARE, 1 - FIRST_LOOK_SHARE)
    s = _Streams([0.999, 0.99, 0.9, 0.8, 0.999], rng)
    est = estimate(s, K, looks, alpha, go_on=lambda p: p < 0.95, budget=10_000)
    votes = s.votes
    # the joint look: draws 0..63 on which every anchor kept the label, at alpha * share (no division by K)
    joint = sum(1 for j in range(64) if all(votes[a, j] for a in range(K)))
    assert est.joint_votes == joint
    assert est.joint_lower == pytest.approx(_cp_lower(joint, 64, alpha * FIRST_LOOK_SHARE), rel=1e-9, abs=1e-12)
    for a in range(K):
        n_a = int(est.samples[a])
        k_a = sum(1 for j in range(n_a) if votes[a, j])
        assert est.votes[a] == k_a
        want = _cp_lower(joint, 64, alpha * FIRST_LOOK_SHARE)
        if n_a == 256:   # went on: its own bound at the second look's level, the larger of the two kept
            want = max(want, _cp_lower(k_a, 256, alpha * (1 - FIRST_LOOK_SHARE) / K))
        assert est.p_lower[a] == pytest.approx(want, rel=1e-9, abs=1e-12)
    # exactly the anchors the rule named after the first look went on (budget ample)
    first = np.full(K, _cp_lower(joint, 64, alpha * FIRST_LOOK_SHARE))
    assert list(np.flatnonzero(est.samples == 256)) == list(np.flatnonzero(first < 0.95))


def test_one_individual_look_is_the_fixed_n_statistics():
    rng = np.random.default_rng(4)
    alpha, K, n = 0.01, 6, 200
    s = _Streams(rng.uniform(0.7, 1.0, K), rng, shared=False)
    est = estimate(s, K, single(n), alpha, go_on=lambda p: np.ones(K, bool), budget=K * n)
    assert list(est.samples) == [n] * K and est.joint_votes == -1
    for a in range(K):
        assert est.p_lower[a] == pytest.approx(_cp_lower(int(s.votes[a, :n].sum()), n, alpha / K), rel=1e-9, abs=1e-12)


def test_the_budget_caps_the_second_look_in_anchor_order():
    rng = np.random.default_rng(5)
    K = 8
    s = _Streams([0.9] * K, rng)
    est = estimate(s, K, joint_looks(64, 256), 0.01, go_on=lambda p: np.ones(K, bool), budget=K * 64 + 3 * 192 + 100)
    assert list(est.samples) == [256, 256, 256] + [64] * 5 and s.calls == K * 64 + 3 * 192


def _simulate(p, shared, looks, alpha, trials, seed):
    rng = np.random.default_rng(seed)
    K = len(p)
    bad = 0
    for _ in range(trials):
        s = _Streams(p, rng, shared=shared, total=looks.last)
        est = estimate(s, K, looks, alpha, go_on=lambda q: q < 0.97, budget=K * looks.last)
        bad += bool(np.any(est.p_lower > np.asarray(p)))
    return bad / trials


@pytest.mark.parametrize("shared", [True, False])
def test_the_risk_of_every_bound_together_is_at_most_alpha(shared):
    """alpha 0.3 (so that the test can see a violation): anchors of equal p_A (shared draws: the joint
    rate equals p_A and the joint bound is as tight as it gets) or independent ones; 1500 runs each.
    Bounds computed at 2.4 times the stated level push the same simulation over alpha: the test sees the
    risk, not only its sign."""
    alpha, trials = 0.3, 1500
    p = [0.93] * 4 if shared else [0.97, 0.96, 0.95, 0.98]
    rate = _simulate(p, shared, joint_looks(64, 256), alpha, trials, seed=11 if shared else 12)
    sd = math.sqrt(alpha * (1 - alpha) / trials)
    assert rate <= alpha + 3 * sd, rate
    if shared:   # the same bounds computed at 2.4 times their stated level: the simulation sees it
        wrong = _simulate(p, shared, joint_looks(64, 256), 2.4 * alpha, trials, seed=11)
        assert wrong > alpha + 3 * sd, (wrong, rate)


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, 256), m=st.integers(1, 255), total=st.integers(256, 6144))
def test_futility_only_when_the_end_is_all_but_out_of_reach(k, m, total):
    """Stopping for futility is always sound (it abstains); it must not stop where the votes so far, carried
    on at their own rate, would pass 1/2 at the end."""
    k = min(k, m)
    if futile(k, m, total, 0.01):
        k_end = k + int(math.ceil(k / m * (total - m)))
        assert _cp_lower(min(k_end, total), total, 0.01) <= 0.5 + 1e-12


def test_an_abstaining_centre_stops_the_axis_early():
    """A centre whose votes are split: the axis stops at the centre, every other anchor unestimated."""
    rng = np.random.default_rng(6)
    K = 10
    s = _Streams([0.4] + [0.99] * (K - 1), rng, shared=False, total=8192)
    est = estimate(s, K, single(6144), 0.01, go_on=lambda p: np.ones(K, bool), budget=6144, chunk=256)
    assert est.p_lower[0] <= 0.5 and np.all(est.samples[1:] == 0) and s.calls <= 512 and est.futile


def test_demo_fewer_calls_same_or_larger_radius():
    """Two demo frames (shipped model, shipped defaults, both axes): the joint first look against n samples
    each at alpha / K (n_first 0, the fixed-n statistics), side by side."""
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.replay import ReplayOptions
    from pws_ros.replay.run import replay

    bag = Path(__file__).resolve().parents[1] / "bags" / "demo"
    out = {}
    for n_first in (0, 64):
        res = replay(ReplayOptions(bag=bag, config=PwsConfig(n_first=n_first), write_output=False, quiet=True, max_frames=2))
        out[n_first] = [c for rec in res.records for c in rec.certificates]
    assert len(out[0]) == len(out[64]) == 4
    for old, new in zip(out[0], out[64]):
        assert old.axis == new.axis and new.label == old.label
        assert new.radius >= old.radius - 1e-12
        assert new.bounds["looks"]["joint"] and new.bounds["joint_votes"] >= 0
        assert old.bounds["looks"] == {"sizes": [256], "shares": [1.0], "joint": False}
    assert sum(c.classifier_calls for c in out[64]) <= 0.6 * sum(c.classifier_calls for c in out[0])

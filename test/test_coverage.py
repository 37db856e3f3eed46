"""The coverage rules (pws_ros.core.coverage) against their definitions, written out with plain loops."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import itertools

from pws_ros.core.coverage import (AdaptiveAnchorsRule, AnchorsRule, PairwiseRule, PaperRule, coverage_rule, covered_radius,
                                   packing_bound)
from pws_ros.core.errors import PwsError


def ref_paper(B, R, centre):
    """Largest j: for the segments centre-j .. centre+j-1 and frames centre-j .. centre+j, max sqrt(B/2) < min R."""
    best = 0
    for j in range(1, centre + 1):
        if centre + j > len(B):
            break
        m = max(math.sqrt(B[i] / 2) for i in range(centre - j, centre + j))
        r = min(R[i] for i in range(centre - j, centre + j + 1))
        if m < r:
            best = j
        else:
            break
    return best


def ref_symmetric(covered, centre):
    j = 0
    while centre - j - 1 >= 0 and centre + j < len(covered) and covered[centre - j - 1] and covered[centre + j]:
        j += 1
    return j


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), half=st.integers(1, 12), K=st.integers(1, 6))
def test_rules_against_loops(seed, half, K):
    rng = np.random.default_rng(seed)
    N = 2 * half + 1
    centre = half
    B = rng.uniform(0, 2, N - 1)
    R = rng.uniform(0, 1.5, N)
    j, n = PaperRule().reach(R, centre, pair_bound_sq=B)
    assert j == ref_paper(B, R, centre) and n == 2 * j
    covered = [B[i] < R[i] ** 2 + R[i + 1] ** 2 for i in range(N - 1)]
    j, n = PairwiseRule().reach(R, centre, pair_bound_sq=B)
    assert j == ref_symmetric(covered, centre) and n == sum(covered)
    D2 = rng.uniform(0, 2, (K, N - 1))
    Ra = rng.uniform(0, 1.5, K)
    covered = [any(D2[a, i] < Ra[a] ** 2 for a in range(K)) for i in range(N - 1)]
    j, n = AnchorsRule(K).reach(Ra, centre, anchor_dist_sq=D2)
    assert j == ref_symmetric(covered, centre) and n == sum(covered)


def test_estimation_frames_and_names():
    assert list(PaperRule().estimation_indices(5)) == [0, 1, 2, 3, 4]
    assert list(PairwiseRule().estimation_indices(3)) == [0, 1, 2]
    idx = AnchorsRule(3).estimation_indices(9)
    assert 4 in idx and len(idx) == 3   # the centre is always an anchor
    assert coverage_rule("anchors", 5) == AnchorsRule(5) and coverage_rule("paper").name == "paper"
    adaptive = coverage_rule("anchors", 5, imaging="surfel")
    assert isinstance(adaptive, AdaptiveAnchorsRule) and adaptive.adaptive and adaptive.num_anchors == 5
    assert not any(coverage_rule(c, 5, imaging="paper").adaptive for c in ("paper", "pairwise", "anchors"))
    assert coverage_rule("pairwise", imaging="surfel") == PairwiseRule()
    with pytest.raises(PwsError, match="unknown coverage rule"):
        coverage_rule("mystery")


def ref_covered_radius(covered, alphas):
    """Largest grid value c (or 0) such that [-c, c] lies in the grid and every segment meeting (-c, c) is covered."""
    best = 0.0
    for c in sorted({abs(float(a)) for a in alphas}):
        if c > alphas[-1] or -c < alphas[0]:
            continue
        if all(covered[i] for i in range(len(covered)) if alphas[i] < c and alphas[i + 1] > -c):
            best = max(best, c)
    return best


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), left=st.integers(1, 8), right=st.integers(1, 8), K=st.integers(1, 4))
def test_covered_radius_and_adaptive_rule_against_loops(seed, left, right, K):
    rng = np.random.default_rng(seed)
    # an asymmetric refined grid with alpha = 0 at index `left`
    alphas = np.concatenate([-np.cumsum(rng.uniform(0.1, 1.0, left))[::-1], [0.0], np.cumsum(rng.uniform(0.1, 1.0, right))])
    covered = rng.uniform(size=left + right) < 0.8
    assert covered_radius(covered, alphas, left) == ref_covered_radius(covered, alphas)
    D2 = rng.uniform(0, 2, (K, left + right))
    R = rng.uniform(0, 1.5, K)
    cov_ref = [any(D2[a, i] < R[a] ** 2 for a in range(K)) for i in range(left + right)]
    radius, cov = AdaptiveAnchorsRule(K).radius(R, D2, alphas, left)
    assert list(cov) == cov_ref and radius == ref_covered_radius(cov_ref, alphas)


def min_cover(points, R):
    """Fewest of the points whose open balls of radius R contain every point (brute force over subsets)."""
    n = len(points)
    for k in range(1, n + 1):
        for sub in itertools.combinations(range(n), k):
            if all(any(math.dist(points[p], points[a]) < R for a in sub) for p in range(n)):
                return k
    return n


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 7), R=st.floats(0.05, 2.0))
def test_packing_bound_is_a_lower_bound(seed, n, R):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 3, (n, 2, 1, 1)).astype(np.float32)   # frames: (n, C, H, W)
    flat = [tuple(float(v) for v in p.reshape(-1)) for p in pts]
    k = packing_bound(pts, R)
    assert 1 <= k <= min_cover(flat, R)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 40), tie=st.booleans())
def test_packing_bound_picks_as_comparing_every_pair(seed, n, tie):
    """The greedy picks with the triangle-inequality shortcut are those of comparing each frame with every picked one
    (written out here with float64 sums of squares), on random walks of frames; with ``tie``, 2R is the distance of one
    pair as computed (comparisons at the threshold itself)."""
    rng = np.random.default_rng(seed)
    frames = np.cumsum(rng.normal(0, 0.05, (n, 6, 5, 3)), axis=0).astype(np.float32)
    flat = [f.astype(np.float64).reshape(-1) for f in frames]
    if tie:
        i, j = sorted(rng.choice(n, 2, replace=False))
        R = math.sqrt(float(np.sum((flat[i] - flat[j]) ** 2))) / 2
    else:
        R = float(rng.uniform(0.01, 1.0))
    lim = (2.0 * R) ** 2
    picked = []
    for x in flat:
        ok = True
        for y in picked:
            if float(np.sum((x - y) ** 2)) < lim:
                ok = False
        if ok:
            picked.append(x)
    assert packing_bound(frames, R) == len(picked)


def test_packing_bound_exact_on_a_spaced_line():
    pts = np.arange(6, dtype=np.float32).reshape(6, 1, 1, 1)      # spacing 1
    assert packing_bound(pts, 0.5) == 6                           # no ball of radius 0.5 holds two of them
    assert packing_bound(pts, 0.51) == 3                          # 0, 2, 4 are >= 1.02 apart; 1 ball per pair
    assert packing_bound(pts[:0], 1.0) == 0

"""The coverage rules (pws_ros.core.coverage) against their definitions, written out with plain loops."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.coverage import AnchorsRule, PairwiseRule, PaperRule, coverage_rule
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
    with pytest.raises(PwsError, match="unknown coverage rule"):
        coverage_rule("mystery")

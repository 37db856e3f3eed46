"""core.distance_rows: the anchors' distance rows answered by a lower bound where no comparison can need the
exact value. Checked against the distances summed in plain float64 loops here (not HullValues.dist_sq)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pws_ros.core.distance_rows import DistanceRows, _lower_bounds
from pws_ros.core.surfel_bounds import HullValues


def _case(seed: int, S: int = 12, h: int = 5, w: int = 7, spread: float = 0.05, offset: float = 0.0, points: bool = False):
    """A path of frames and boxes around each segment's two end frames (as the bounds are: both ends inside);
    ``points``: every box one value (its segment's first frame), where the bound is the distance itself."""
    rng = np.random.default_rng(seed)
    f = np.clip(rng.random((1, h, w, 3)) + offset + np.cumsum(rng.normal(0, spread, (S + 1, h, w, 3)), axis=0), -100, 100)
    f = f.astype(np.float32)
    widen = rng.random((S, h, w, 3)).astype(np.float32) * 0.02 * (rng.random((S, h, w, 1)) < 0.3)
    lo = np.minimum(f[:-1], f[1:]) - widen
    hi = np.maximum(f[:-1], f[1:]) + widen[::-1]
    if points:
        lo = hi = f[:-1]
    return f, HullValues(np.linspace(-1, 1, S + 1), lo.astype(np.float32), hi.astype(np.float32), np.zeros((S, h, w), bool))


def _brute(f, hv):
    """D_i(x_j)^2 without the safety factor, one segment and frame at a time, float64."""
    out = np.zeros((len(f), hv.num_segments))
    for j in range(len(f)):
        y = f[j].astype(np.float64).ravel()
        for i in range(hv.num_segments):
            lo = hv.lo[i].astype(np.float64).ravel()
            hi = hv.hi[i].astype(np.float64).ravel()
            s = 0.0
            for a, b, c in zip(y, lo, hi):
                s += max((a - b) ** 2, (c - a) ** 2)
            out[j, i] = s
    return out


@pytest.mark.parametrize("seed,offset,points", [(0, 0.0, False), (1, 0.0, False), (2, 50.0, False), (3, -0.5, False),
                                               (4, 0.0, True), (5, 20.0, True)])
def test_lower_bounds_are_below_the_distances(seed, offset, points):
    f, hv = _case(seed, offset=offset, points=points)
    L = _lower_bounds(hv, f)
    ref = _brute(f, hv)
    assert L.shape == ref.shape
    assert np.all(L <= ref)
    # and not uselessly low: the distance itself where the boxes are points, within a few per cent elsewhere
    ratio = L / np.maximum(ref, 1e-300)
    assert np.median(ratio) > (0.999999 if points else 0.5)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10**6), st.floats(0.0, 2.0), st.sampled_from([1, 3, 4]))
def test_rows_compare_as_the_exact_rows(seed, t_frac, block):
    """Every comparison with a radius up to the threshold comes out as the exact value's; calls where some
    segment may be below it are the exact ones, bit for bit."""
    f, hv = _case(seed, S=9, h=3, w=4, spread=0.1)
    exact = np.stack([hv.dist_sq(f[j]) for j in range(len(f))])
    thr = float(np.quantile(exact, 0.3)) * t_frac
    d = DistanceRows(hv, f, thr)
    for j in range(len(f)):
        for i0 in range(0, hv.num_segments, block):
            got = d.row(j, i0, i0 + block)
            want = hv.dist_sq(f[j], slice(i0, i0 + block))
            if (j, i0, min(i0 + block, hv.num_segments)) in d.approx:
                assert np.all(got >= thr) and np.all(got <= want)
            else:
                assert np.array_equal(got, want)
            for t_sq in (0.0, thr * 0.5, thr * 0.999, thr):
                assert np.array_equal(got < t_sq, want < t_sq)


def test_complete_and_max_min_give_the_exact_values():
    f, hv = _case(7, S=20, h=4, w=6, spread=0.08)
    exact = np.stack([hv.dist_sq(f[j]) for j in range(len(f))])
    thr = float(np.quantile(exact, 0.05))
    d = DistanceRows(hv, f, thr)
    idx = [0, 6, 13, 20]
    rows = np.stack([np.concatenate([d.row(j, i0, i0 + 4) for i0 in range(0, hv.num_segments, 4)]) for j in idx])
    assert d.approx, "the case must leave some blocks to the bound"
    assert not np.array_equal(rows, exact[idx])
    # a larger radius: every block that could hold a value below it is made exact
    big = float(np.quantile(exact, 0.4))
    d.complete(rows, idx, big)
    assert np.array_equal(rows < big, exact[idx] < big)
    assert np.array_equal(rows < thr, exact[idx] < thr)
    # the largest distance of a segment to its nearest anchor: the exact rows' value, bit for bit
    want = float(exact[idx].min(axis=0).max())
    assert d.max_min(rows, idx) == want
    # and a threshold above every value makes every row exact
    d.complete(rows, idx, float("inf"))
    assert np.array_equal(rows, exact[idx])


def test_a_zero_threshold_answers_every_call_by_the_bound_until_completed():
    f, hv = _case(11, S=6, h=3, w=3)
    exact = np.stack([hv.dist_sq(f[j]) for j in range(len(f))])
    d = DistanceRows(hv, f, 0.0)
    rows = np.stack([d.row(j, 0, None) for j in (0, 3)])
    assert d.exact_calls == 0
    assert d.max_min(rows, (0, 3)) == float(exact[[0, 3]].min(axis=0).max())

"""Estimating the anchors' ``p_A``: a joint first look, then individual looks, the risk split over every look.

The ``K`` anchors share their noise draws (common random numbers: sample ``j`` of every anchor adds the
same noise image). Their samples are drawn in *looks*: ``sizes = (n_1 < n_2 < ...)`` samples in all after
each look, look ``l`` spending the share ``shares[l]`` of the frame-axis risk ``alpha`` (the shares sum to 1).

* **Joint first look** (``joint``): with ``Z_j = 1`` when *every* anchor keeps the label under noise draw
  ``j``, the ``Z_j`` are i.i.d. Bernoulli(``q``) with ``q = P(all anchors keep it) <= p_A`` of each anchor.
  One Clopper-Pearson lower bound on ``q`` at the level ``shares[0] * alpha`` is a lower bound on every
  anchor's ``p_A`` at once: no Bonferroni division by ``K``. Where the classifier keeps its answer under
  noise on all anchors (as it must for a large radius), 128 joint samples give the radius 256 samples give
  with ``alpha / 24`` (σ 0.5, α 0.01: 0.89 against 0.94 at three quarters of the risk).
* **Individual looks**: anchor ``a``'s Clopper-Pearson bound of its first ``sizes[l]`` votes at the level
  ``shares[l] * alpha / K``. Whether an anchor goes on to the next look is decided from what was seen so
  far (its bound falls short of the radius it was placed for); an anchor's ``p_A`` bound is the largest
  of the bounds it has.

**Why it holds.** Think of every anchor's sample stream as drawn to the end: each bound is a fixed function
of a fixed prefix of the streams (the joint one of all ``K`` streams' first ``n_1`` draws, an individual
one of one stream's first ``sizes[l]``), so it fails with probability at most its level, whatever the
stopping rule. The joint bound and the ``K`` individual bounds of every look fail together with
probability at most ``sum_l shares[l] * alpha = alpha``; on the complement every bound computed holds, so
does each anchor's largest, whichever looks were made. A look not made spends risk that is simply not
used, and stopping for *futility* (:func:`futile`: the axis abstains) needs no correction: abstaining is
always sound. The anchors (``K``) and the looks are fixed from the bounds and the selection samples
before any estimation sample is drawn.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .errors import require
from .smoothing import clopper_pearson_lower, clopper_pearson_upper

FIRST_LOOK = 64          # samples of the joint first look (config n_first)
FIRST_LOOK_SHARE = 0.9   # of the risk, the share the joint first look spends (the rest: the individual last look)
FUTILITY_LEVEL = 1e-3    # an axis stops (abstains) once p_A at the centre is this sure to be too small


@dataclass(frozen=True)
class Looks:
    """Sample counts after each look (increasing), the share of the risk each spends, and whether the first
    look's bound is the joint one over all anchors."""

    sizes: tuple[int, ...]
    shares: tuple[float, ...]
    joint: bool = False

    def __post_init__(self):
        require(len(self.sizes) >= 1 and len(self.sizes) == len(self.shares), "looks need as many shares as sizes")
        require(all(int(a) < int(b) for a, b in zip(self.sizes, self.sizes[1:])) and int(self.sizes[0]) >= 1,
                f"look sizes must increase from >= 1, got {self.sizes}")
        require(all(s > 0 for s in self.shares) and abs(sum(self.shares) - 1.0) <= 1e-9,
                f"look shares must be positive and sum to 1, got {self.shares}")

    @property
    def last(self) -> int:
        return int(self.sizes[-1])

    def level(self, look: int, alpha: float, K: int) -> float:
        """The level of look ``look``'s bound (one of ``K`` individual bounds; the joint bound is one bound)."""
        joint = self.joint and look == 0
        return float(alpha) * float(self.shares[look]) / (1 if joint else max(1, int(K)))

    def lower(self, k, look: int, alpha: float, K: int):
        """The Clopper-Pearson lower bound of ``k`` votes of ``sizes[look]`` at the look's level."""
        return clopper_pearson_lower(k, int(self.sizes[look]), self.level(look, alpha, K))

    def to_dict(self) -> dict:
        return {"sizes": [int(x) for x in self.sizes], "shares": [float(x) for x in self.shares], "joint": bool(self.joint)}


def single(n: int) -> Looks:
    """One individual look of ``n`` samples (fixed-n estimation at ``alpha / K``)."""
    return Looks((int(n),), (1.0,))


def joint_looks(n_first: int, n: int) -> Looks:
    """A joint first look of ``n_first`` samples (FIRST_LOOK_SHARE of the risk), then an individual look of
    ``n`` for the anchors it leaves short (the rest); one joint look of ``n`` when ``n_first >= n``."""
    if int(n_first) >= int(n):
        return Looks((int(n),), (1.0,), joint=True)
    return Looks((int(n_first), int(n)), (FIRST_LOOK_SHARE, 1.0 - FIRST_LOOK_SHARE), joint=True)


def joint_rate(k0: int, n0: int, K: int) -> float:
    """A planning guess of the joint vote rate of ``K`` anchors from the selection's ``k0`` of ``n0``: each
    anchor that keeps the label at the selection's rate, their misses on different draws (``1 - K (1 -
    k0 / n0)``, at least 0). Soundness never rests on it."""
    return max(0.0, 1.0 - int(K) * (1.0 - int(k0) / max(1, int(n0))))


def futile(k: int, m: int, total: int, alpha: float) -> bool:
    """Whether ``total`` samples at level ``alpha`` are all but sure to leave the p_A bound at or below 1/2,
    after ``k`` votes of ``m``: even if the remaining ``total - m`` votes came at the rate of p_A's upper
    bound at FUTILITY_LEVEL, the bound would be <= 1/2. Stopping then abstains, which is always sound."""
    if m >= total:
        return True
    p_hi = float(clopper_pearson_upper(int(k), int(m), FUTILITY_LEVEL))
    k_end = int(k) + int(np.ceil(p_hi * (int(total) - int(m))))
    return float(clopper_pearson_lower(min(k_end, int(total)), int(total), float(alpha))) <= 0.5


@dataclass
class Estimate:
    """What the bounds rest on: per anchor its bound, samples and votes for the label; the joint votes."""

    p_lower: np.ndarray
    samples: np.ndarray
    votes: np.ndarray
    joint_votes: int = -1          # -1: no joint look
    joint_lower: float = 0.0
    futile: bool = False           # the centre stopped for futility (its bound not computed: 0)

    def to_dict(self) -> dict:
        return {"anchor_samples": [int(x) for x in self.samples], "anchor_votes": [int(x) for x in self.votes],
                "joint_votes": int(self.joint_votes), "joint_lower": float(self.joint_lower), "futile": bool(self.futile)}


def estimate(votes_of: Callable[[np.ndarray, int], np.ndarray], K: int, looks: Looks, alpha: float,
             go_on: Callable[[np.ndarray], np.ndarray], budget: int, chunk: int | None = None) -> Estimate:
    """The anchors' p_A bounds (index 0: the centre).

    ``votes_of(idx, m)``: ``(len(idx), m)`` bools, whether each of ``m`` new samples of each anchor in ``idx``
    keeps the label, the anchors of one call sharing their noise draws (an anchor's samples continue its
    stream). With a joint first look, every anchor's first look is drawn at once and the joint bound taken.
    Else the centre's looks come first: an axis whose centre cannot be certified stops there (drawn ``chunk``
    samples at a time, sooner where :func:`futile` says so; every other anchor unestimated, its bound 0: the
    axis abstains), then the other anchors' first look. Then, look after look, the anchors ``go_on(p_lower)``
    names (a boolean mask; anchors at the previous look only) while ``budget`` samples in all allow (in
    anchor order)."""
    K = int(K)
    k = np.zeros(K, np.int64)
    used = np.zeros(K, np.int64)
    p = np.zeros(K, np.float64)
    out = Estimate(p, used, k)
    first = int(looks.sizes[0])
    if looks.joint:
        v = np.asarray(votes_of(np.arange(K), first), bool).reshape(K, first)
        k += v.sum(axis=1)
        used[:] = first
        out.joint_votes = int(v.all(axis=0).sum())
        out.joint_lower = float(looks.lower(out.joint_votes, 0, alpha, K))
        p[:] = out.joint_lower
    else:
        # the centre first, look by look, until its bound passes 1/2 (in draws of at most ``chunk``, stopping
        # for futility between them: the axis then abstains)
        step = max(1, int(chunk or first))
        last_level = looks.level(len(looks.sizes) - 1, alpha, K)
        for look, size in enumerate(looks.sizes):
            while used[0] < size:
                m = min(int(size) - int(used[0]), step)
                k[0] += int(np.asarray(votes_of(np.array([0]), m), bool).sum())
                used[0] += m
                if used[0] < size and futile(int(k[0]), int(used[0]), looks.last, last_level):
                    out.futile = True
                    return out
            p[0] = max(p[0], float(looks.lower(int(k[0]), look, alpha, K)))
            if p[0] > 0.5 or futile(int(k[0]), int(used[0]), looks.last, last_level):
                break
        if p[0] <= 0.5:
            return out
        rest = np.flatnonzero(used == 0)
        if len(rest):
            k[rest] += np.asarray(votes_of(rest, first), bool).reshape(len(rest), first).sum(axis=1)
            used[rest] = first
            p[rest] = np.maximum(p[rest], np.asarray(looks.lower(k[rest], 0, alpha, K), np.float64).reshape(-1))
    left = int(budget) - int(used.sum())
    for look in range(1, len(looks.sizes)):
        prev, size = int(looks.sizes[look - 1]), int(looks.sizes[look])
        want = np.flatnonzero(np.asarray(go_on(p.copy()), bool) & (used == prev))
        want = want[:max(0, left // (size - prev))]
        if not len(want):
            break
        k[want] += np.asarray(votes_of(want, size - prev), bool).reshape(len(want), size - prev).sum(axis=1)
        used[want] = size
        left -= len(want) * (size - prev)
        p[want] = np.maximum(p[want], np.asarray(looks.lower(k[want], look, alpha, K), np.float64).reshape(-1))
    return out


__all__ = ["FIRST_LOOK", "FIRST_LOOK_SHARE", "FUTILITY_LEVEL", "Estimate", "Looks", "estimate", "futile", "joint_looks",
           "joint_rate", "single"]

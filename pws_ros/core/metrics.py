"""What the reports count, defined once: "certified at radius r", certified accuracy, its curve
against the radius, and the summary statistics (used by :mod:`pws_ros.replay.report` for ``pws replay`` and
:mod:`pws_ros.bench.report` for ``pws bench``).

**Certified at radius r** (a certificate, for every motion in ``[-r, r]``, ``r >= 0``): the
certificate made a prediction (status ``certified`` or ``not_certified``; ``abstain`` and ``error``
never are) and its certified radius covers ``r``, where (see :class:`~pws_ros.core.result.Certificate`):

- PwS, PwS-L, PwS-OF: ``radius`` is the largest covered *closed* sub-interval ``[-radius, radius]`` of
  the partition grid, so ``r`` is covered iff ``radius >= r``. The comparison allows a relative
  :data:`RADIUS_RTOL`: grid points are computed (``b * k / K``) and may sit a few ulps off ``r``;
  a certified certificate is certified at its requested radius.
- CMS: ``radius`` is the Cohen radius ``R``, which guarantees the prediction on the *open* interval
  ``|alpha| < R`` (:func:`pws_ros.core.cms.certify_cms` certifies a requested radius iff it is ``< R``),
  so ``r`` is covered iff ``R > r``.

**Certified accuracy at r**: the fraction of frames (with ground truth) that are certified at ``r``
*and* correct (the predicted class is the true one); abstentions and errors count as wrong. At
``r = 0`` it is the accuracy of the smoothed prediction at the recorded pose ("benign accuracy").
"""
from __future__ import annotations

import math
from typing import Any, Iterable, NamedTuple, Sequence

import numpy as np

from .result import STATUS_ABSTAIN, STATUS_ERROR

RADIUS_RTOL = 1e-9


def covers(radius: float, r: float, method: str) -> bool:
    """Whether a certified ``radius`` (of ``method``) covers every motion in ``[-r, r]`` (module docstring)."""
    if method == "cms":
        return radius > r
    return radius >= r * (1 - RADIUS_RTOL)


def certified_at(status: str, radius: float, method: str, r: float) -> bool:
    """A certificate (its ``status``, ``radius``, ``method``) is certified at radius ``r``."""
    return status not in (STATUS_ABSTAIN, STATUS_ERROR) and covers(radius, r, method)


class Outcome(NamedTuple):
    """What the accuracy of one certificate depends on (``correct``: its class is the true one)."""

    status: str
    radius: float
    method: str
    correct: bool = True

    @classmethod
    def of(cls, cert: Any, correct: bool = True) -> "Outcome":
        """From a :class:`~pws_ros.core.result.Certificate`."""
        return cls(cert.status, float(cert.radius), cert.method, bool(correct))

    def certified_at(self, r: float) -> bool:
        return certified_at(self.status, self.radius, self.method, r)


def certified_correct(outcomes: Iterable[Outcome], r: float) -> tuple[int, int]:
    """(certified at ``r`` and correct, total)."""
    outcomes = list(outcomes)
    return sum(1 for o in outcomes if o.correct and o.certified_at(r)), len(outcomes)


def radius_grid(radius: float, points: int) -> list[float]:
    """``points`` radii ``radius * k / (points - 1)``, ``k = 0 .. points - 1`` (the last is ``radius``)."""
    return [radius * k / (points - 1) for k in range(points)]


def accuracy_curve(outcomes: Sequence[Outcome], radii: Sequence[float]) -> list[float]:
    """Certified accuracy at each radius (0 for no outcomes)."""
    return [certified_correct(outcomes, r)[0] / max(1, len(outcomes)) for r in radii]


def curve_mean(outcomes: Sequence[Outcome], radius: float, steps: int) -> float:
    """Mean certified accuracy over the radii ``radius * k / steps``, ``k = 1 .. steps`` (the area under
    the curve, in units of ``radius``); NaN for no outcomes."""
    if not outcomes:
        return float("nan")
    return float(np.mean(accuracy_curve(outcomes, radius_grid(radius, steps + 1)[1:])))


# ---- summary statistics (finite values only; None where there is none) ----------------------

def finite(values: Iterable[Any]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def mean(values: Iterable[Any]) -> float | None:
    v = finite(values)
    return sum(v) / len(v) if v else None


def median(values: Iterable[Any]) -> float | None:
    v = finite(values)
    return float(np.median(v)) if v else None


__all__ = ["Outcome", "RADIUS_RTOL", "accuracy_curve", "certified_at", "certified_correct", "covers", "curve_mean",
           "finite", "mean", "median", "radius_grid"]

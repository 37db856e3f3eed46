"""The result of one certification (any method), shared by the CLI, the nodes, replay and bench."""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from .jsonable import jsonable

STATUS_CERTIFIED = "certified"        # the smoothed prediction holds on the whole requested range
STATUS_NOT_CERTIFIED = "not_certified"  # a prediction was made but the range is not (fully) covered
STATUS_ABSTAIN = "abstain"            # no class has p_A > 1/2 at the original pose
STATUS_ERROR = "error"                # could not certify at all (bad input, missing frames, ...)


@dataclass
class Certificate:
    """What a certificate states and what it rests on.

    ``radius`` is the largest symmetric sub-interval ``[-radius, radius]`` of the partition grid that
    is covered (motion units ``unit``); ``certified`` is True iff it reaches ``requested_radius``.
    ``p_a_lower`` holds the one-sided Clopper-Pearson lower bounds actually used (one per partition,
    or one per anchor), each at confidence ``1 - alpha / num_bounds`` (Bonferroni).
    """

    axis: str
    unit: str
    method: str                       # pws | pws_l | pws_of | cms
    coverage: str                     # paper | pairwise | anchors | cms
    requested_radius: float
    status: str
    certified: bool
    radius: float
    label: int = -1
    class_name: str = ""
    p_a_lower: list[float] = field(default_factory=list)
    sigma: float = float("nan")       # pixel noise sigma (PwS*) or motion sigma (CMS)
    n0: int = 0
    n: int = 0
    alpha: float = 0.01
    num_bounds: int = 0               # Bonferroni divisor
    num_partitions: int = 0
    delta_alpha: float = float("nan")
    frames_rendered: int = 0
    classifier_calls: int = 0
    bounds: dict[str, Any] = field(default_factory=dict)   # M, R, max pair bound, ...
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage: plan, render, inference, statistics, total
    reason: str = ""
    seed: int | None = None
    imaging: str = ""                 # surfel | paper (core.imaging): what the certified frames are
    filled_points: int = 0            # points of the one-frame cloud whose depth was filled (depth_fill), not measured
    working_volume: str = ""          # the part of the cloud that is drawn (core.volume; docs/imaging.md 4a); "" = all of it
    plan: Any = field(default=None, repr=False, compare=False)   # the core.partition.Plan it rests on (not serialised)
    frame_alpha: float | None = None  # risk of the whole frame's statement (all its axes together)

    @property
    def min_p_a_lower(self) -> float:
        return float(min(self.p_a_lower)) if self.p_a_lower else float("nan")

    def to_dict(self, full: bool = True) -> dict[str, Any]:
        d = asdict(replace(self, plan=None))
        d.pop("plan")
        d["min_p_a_lower"] = self.min_p_a_lower
        if not full and len(self.p_a_lower) > 16:
            d["p_a_lower"] = f"{len(self.p_a_lower)} values, min {self.min_p_a_lower:.6g}"
        return jsonable(d, inf="clamp")

    def to_json(self, **kw) -> str:
        return json.dumps(self.to_dict(), **kw)

    def summary(self) -> str:
        """One human line: what was certified and what it rests on."""
        head = f"{self.method}/{self.coverage} {self.axis} ±{self.requested_radius:g} {self.unit}: {self.status}"
        if self.status == STATUS_ERROR:
            return f"{head} ({self.reason})"
        s = (f"{head}; label {self.label} ({self.class_name}), certified radius {self.radius:g} {self.unit}, "
             f"min p_A {self.min_p_a_lower:.4f}, N={self.num_partitions}, n0={self.n0}, n={self.n}, "
             f"alpha={self.alpha:g} over {self.num_bounds} bound(s), sigma={self.sigma:g}, calls={self.classifier_calls}, "
             f"{self.timings.get('total', float('nan')):.2f}s")
        return s + (f" — {self.reason}" if self.reason else "")


def error_certificate(axis: str, unit: str, method: str, coverage: str, radius: float, reason: str, **kw) -> Certificate:
    return Certificate(axis=axis, unit=unit, method=method, coverage=coverage, requested_radius=radius,
                       status=STATUS_ERROR, certified=False, radius=0.0, reason=reason, **kw)

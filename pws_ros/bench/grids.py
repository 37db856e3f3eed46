"""Grids the bench certifies on (capped or explicit) and the paper rule read off a pairwise run."""
from __future__ import annotations


import numpy as np

from ..core.coverage import PaperRule, cohen_radii
from ..core.errors import require
from ..core.motion import UNITS
from ..core.partition import Plan, make_grid
from ..core.result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED

PLAN_CAP = 10_000_000          # larger plans are reported as "> PLAN_CAP" (the grid alone would not fit)


def capped_plan(plan: Plan, cap: int, floor: int = 3) -> Plan:
    """The plan itself when it has between ``floor`` and ``cap`` partitions; else the uniform grid of
    ``cap`` (coarser: still sound, because certification rests on the rendered per-segment bounds, not
    on the plan) or ``floor`` partitions (finer: resolves the certified-radius curve)."""
    if floor <= plan.num_partitions <= cap:
        return plan
    target = cap if plan.num_partitions > cap else floor
    m = (target - 1) // 2
    alphas = make_grid(plan.radius, plan.radius / m, max_partitions=target)
    key = "capped_from" if plan.num_partitions > cap else "refined_from"
    details = {key: int(plan.num_partitions), "planned_delta_alpha": float(plan.delta_alpha),
               "lemma1_holds": None if key == "capped_from" else plan.details.get("lemma1_holds"),
               "plan_seconds": plan.details.get("plan_seconds", 0.0)}
    return Plan(plan.method, plan.axis, plan.radius, float(alphas[1] - alphas[0]), len(alphas), alphas, plan.unit, details)


def grid_plan(method: str, axis: str, radius: float, num_partitions: int) -> Plan:
    """An explicit uniform grid of ``num_partitions`` (odd) motions on ``[-radius, radius]``."""
    m = (int(num_partitions) - 1) // 2
    alphas = make_grid(radius, radius / m, max_partitions=int(num_partitions))
    return Plan(method, axis, radius, float(alphas[1] - alphas[0]), len(alphas), alphas, UNITS[axis], {"explicit_grid": True})


def paper_rule(p_a_lower, pair_bound_sq, alphas, sigma: float) -> tuple[str, bool, float]:
    """The paper's coverage rule (Theorem 1 with the sound per-segment bounds: ``max sqrt(B_i / 2) <
    min R_i`` over the symmetric sub-interval) read off a pairwise run: the same counts, the same
    Bonferroni level, so the same decision :func:`certify` would make with ``coverage='paper'``.
    Returns ``(status, certified, radius)``."""
    alphas = np.asarray(alphas, dtype=np.float64)
    p = np.asarray(p_a_lower, dtype=np.float64).reshape(-1)
    require(len(p) == len(alphas), "paper rule needs one p_A bound per partition")
    R = cohen_radii(p, sigma)
    centre = int(np.searchsorted(alphas, 0.0))
    j, _ = PaperRule().reach(R, centre, pair_bound_sq=pair_bound_sq)
    if not R[centre] > 0:
        return STATUS_ABSTAIN, False, 0.0
    certified = j == centre
    return (STATUS_CERTIFIED if certified else STATUS_NOT_CERTIFIED), certified, float(alphas[centre + j])


def timing_of(t: dict[str, float]) -> dict[str, float]:
    return {k: float(t.get(k, 0.0)) for k in ("plan", "render", "inference", "statistics", "total")}


# ------------------------------------------------------------------------------------------------
# the bench

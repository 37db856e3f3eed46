"""What both certification paths share (:mod:`.certify`, every frame estimated, and :mod:`.anchored`, the
adaptive anchors): the configuration of a certification (:class:`CertifyConfig`), the memory one segment of
bounds and one frame take and the share of the ceiling they may use (:func:`segment_bytes`,
:func:`bounds_bytes`), and the certificate of a covered interval (:func:`_conclude`). A module of its own so
that :mod:`.certify` can dispatch to :mod:`.anchored` without an import circle; every name here is also
importable from :mod:`.certify`."""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .coverage import COVERAGES, FRONTIER_ROUNDS
from .errors import require
from .imaging import DEFAULT_RENDER_FACTOR, IMAGING_KINDS, UNCOVERED, Imaging
from .model import LoadedModel
from .motion import UNITS
from .partition import DEFAULT_FRAME_BUDGET, DEFAULT_STEP_PX, Plan
from .result import STATUS_ABSTAIN, STATUS_CERTIFIED, STATUS_NOT_CERTIFIED, Certificate
from .sequential import FIRST_LOOK
from .smoothing import SmoothedClassifier
from .volume import WorkingVolume


@dataclass
class CertifyConfig:
    sigma: float = 0.5
    n0: int = 100
    n: int = 1000
    alpha: float = 0.01
    seed: int = 0
    device: str = "cpu"
    batch_size: int = 500
    coverage: str = "anchors"
    num_anchors: int = 24
    background: float = 0.0
    uncovered: str = "frame"   # surfel: what a pixel no surfel covers shows (core.imaging.UNCOVERED)
    max_partitions: int = DEFAULT_FRAME_BUDGET
    max_memory_mb: float = 2048.0
    min_partitions: int = 0
    delta: float | None = None
    cms_sigma: float | None = None
    chunk: int = 128
    imaging: str = "surfel"
    border: int = -1
    step_px: float = DEFAULT_STEP_PX
    render_factor: int = DEFAULT_RENDER_FACTOR
    # anchors coverage: where the anchors placed are predicted to fall short of the radius, the estimation
    # samples the axis was sized for (num_anchors * n) are spread over the K anchors placed (n_est =
    # num_anchors * n // K), fixed before any estimation sample is drawn; off: n per anchor. A time budget
    # that shrinks the sizes turns it on (they pay for num_anchors * n samples; bridge.budget)
    spread_estimation: bool = False
    # surfel: only the points inside are drawn (core.volume; docs/imaging.md section 4a); None: every point
    working_volume: WorkingVolume | None = None
    # surfel: rounds a side of the frontier refinement once the radii are known (.coverage.frontier_reach);
    # fewer rounds cost fewer bounds and may leave a smaller radius (a time budget lowers it, bridge.budget)
    frontier_rounds: int = FRONTIER_ROUNDS
    # anchors coverage: samples of an anchor's first look (core.sequential): the anchors are placed for what
    # n_first samples certify where that covers more per sample than n, up to num_anchors * n // n_first of
    # them; an anchor whose first look falls short gets the rest of its n. 0 (or >= n): n samples each
    n_first: int = FIRST_LOOK

    def validate(self) -> "CertifyConfig":
        require(math.isfinite(self.sigma) and self.sigma > 0, f"sigma must be positive, got {self.sigma}")
        require(int(self.n0) >= 1 and int(self.n) >= 1, f"n0 and n must be >= 1, got n0={self.n0}, n={self.n}")
        require(0 < self.alpha < 1, f"alpha must lie in (0, 1), got {self.alpha}")
        require(self.coverage in COVERAGES, f"unknown coverage rule {self.coverage!r}: expected one of {', '.join(COVERAGES)}")
        require(int(self.num_anchors) >= 1, f"num_anchors must be >= 1, got {self.num_anchors}")
        require(int(self.batch_size) >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        require(int(self.min_partitions) >= 0, f"min_partitions must be >= 0, got {self.min_partitions}")
        require(math.isfinite(self.background), f"background must be finite, got {self.background}")
        require(self.uncovered in UNCOVERED, f"unknown uncovered rule {self.uncovered!r}: expected one of {', '.join(UNCOVERED)}")
        require(self.imaging in IMAGING_KINDS, f"unknown imaging model {self.imaging!r}: expected one of {', '.join(IMAGING_KINDS)}")
        require(self.working_volume is None or self.imaging == "surfel",
                "a working volume needs surfel imaging (imaging: paper draws every point)")
        require(math.isfinite(self.step_px) and self.step_px > 0, f"step_px must be positive, got {self.step_px}")
        require(int(self.render_factor) >= 0, f"render_factor must be >= 0 (0: the camera's resolution), got {self.render_factor}")
        require(int(self.n_first) >= 0, f"n_first must be >= 0 (0: one look of n samples), got {self.n_first}")
        require(int(self.frontier_rounds) >= 0, f"frontier_rounds must be >= 0, got {self.frontier_rounds}")
        require(math.isfinite(self.max_memory_mb) and self.max_memory_mb >= 64,
                f"max_memory_mb must be at least 64, got {self.max_memory_mb}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def segment_bytes(imaging: Imaging) -> int:
    """Memory one segment of the surfel bounds and one frame take at the classifier's input size."""
    h, w = imaging.out_shape
    return h * w * (3 * 4 * 2 + 1) + h * w * 3 * 4


def bounds_bytes(config: CertifyConfig) -> int:
    """The share of ``max_memory_mb`` the per-segment bounds and frames of one axis may take (half; the
    renderer streams its chunks within the rest): a refined grid stays within it, a larger plan is an
    ERROR naming the ceiling, never an out-of-memory kill."""
    return int(config.max_memory_mb * 2**20 / 2)


def _label_name(model: LoadedModel, label: int) -> str:
    try:
        return model.class_names[label]
    except (IndexError, AttributeError, TypeError):
        return f"class_{label}"


def _conclude(plan: Plan, centre: int, reach: float, est_pos: dict[int, int], p_lower: np.ndarray, R: np.ndarray, label: int,
              model: LoadedModel, config: CertifyConfig, method: str, sc: SmoothedClassifier, bounds: dict[str, Any],
              timings: dict[str, float], t_start: float, frames_rendered: int, n_est: int | None = None) -> Certificate:
    """The certificate of a covered interval ``[-reach, reach]`` (``reach`` = ``plan.radius``: certified)."""
    axis = plan.axis
    centre_ok = (R[est_pos[centre]] > 0) if centre in est_pos else False
    radius = float(reach) if centre_ok else 0.0
    certified = bool(centre_ok and radius >= plan.radius)
    if not centre_ok:
        status, reason = STATUS_ABSTAIN, f"p_A lower bound at the original pose is {p_lower[est_pos[centre]]:.4f} <= 0.5"
    elif certified:
        status, reason = STATUS_CERTIFIED, ""
    else:
        status = STATUS_NOT_CERTIFIED
        reason = f"covered up to ±{radius:g} {UNITS[axis]} of ±{plan.radius:g} ({config.coverage} rule)"
    timings["total"] = time.perf_counter() - t_start
    if "coarsened_from" in plan.details:
        bounds["coarsened_from"] = plan.details["coarsened_from"]
    return Certificate(axis=axis, unit=UNITS[axis], method=method, coverage=config.coverage,
                       requested_radius=float(plan.radius), status=status, certified=certified, radius=radius,
                       label=label, class_name=_label_name(model, label), p_a_lower=[float(p) for p in p_lower],
                       sigma=float(config.sigma), n0=int(config.n0), n=int(config.n if n_est is None else n_est), alpha=float(config.alpha),
                       num_bounds=len(p_lower), num_partitions=plan.num_partitions, delta_alpha=float(plan.delta_alpha),
                       frames_rendered=frames_rendered, classifier_calls=int(sc.calls), bounds=bounds, timings=timings,
                       reason=reason, seed=int(config.seed), plan=plan)

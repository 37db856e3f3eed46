"""Partition planning: the uniform grid of camera motions for PwS, PwS-L and PwS-OF.

All three methods pick a step ``delta_alpha`` and partition ``[-b, b]`` uniformly with a grid that
starts at ``-b``, ends at ``+b`` and contains ``0`` (``num_partitions = 2 ceil(b / delta_alpha) + 1``).

* **PwS** (Thm 1, entire cloud): ``delta_alpha = min`` length of the consistent camera-motion intervals
  ``U_{P,r,s}`` (runs of one winning point at one pixel), computed exactly from the pixel-crossing
  events of :mod:`.sweep` (not read off a grid).
* **PwS-L** (Thm 2): ``delta_alpha = min_{r,s} min_P |rho(P, sup U) - rho(P, inf U)|_inf / L_P`` with the
  Lipschitz constant ``L_P`` of the projection along the axis.
* **PwS-OF** (Thm 3, one-frame cloud, delta-convexity): ``delta_alpha = min_{r,s} [min_P 1/(L_P + C_delta)] *
  [min_P (|rho(P, sup U) - rho(P, inf U)|_inf - 2 delta)]`` with ``C_delta`` from Lemma D.2 (errata fixed:
  ``rz`` uses the sign of its own rotation matrix, ``ry`` uses ``delta^2 / f_x`` and the ``fx``/``fy`` roles of
  the derivation, ``delta`` is an input in pixels, not a quantile of the unknown complete cloud).

Consistent intervals are computed on ``[-4b, 4b]``; a run reaching either end of that window is longer
than ``3b`` and never limits ``delta_alpha <= b`` (the window is narrower where ``4b`` would bring a point
to depth 0, see :func:`planning_window`). The plan only decides how many frames are rendered:
soundness never rests on it, because certification uses the per-segment bounds of :mod:`.bounds`,
which hold whether or not Lemma 1 does (``details['lemma1_holds']`` reports which).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .camera import CameraIntrinsics
from .cloud import Cloud
from .errors import PwsError, require
from .motion import UNITS, lipschitz_constant, parse_axis, project
from .sweep import Visits, compute_visits, pixel_states

PLAN_METHODS = ("pws", "pws_l", "pws_of")
DEFAULT_DELTA_PX = 0.05
DEFAULT_MAX_PARTITIONS = 20000
DEFAULT_FRAME_BUDGET = 257  # max_partitions of a certificate (config, CLI): frames rendered per axis
DEFAULT_STEP_PX = 0.25
# PwS-L leaves out visits spanning at most this many pixels: a point grazing a pixel corner (or sitting
# in the 1e-6 px overlap of two footprints) would otherwise ask for ~1e6x more frames for a change the
# rendered bounds account for anyway.
MIN_VISIT_EXTENT_PX = 1e-4


@dataclass
class Plan:
    method: str
    axis: str
    radius: float
    delta_alpha: float
    num_partitions: int
    alphas: np.ndarray
    unit: str = ""
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["alphas"] = [float(a) for a in self.alphas]
        return d

    def to_json(self, path=None, **kw) -> str:
        text = json.dumps(self.to_dict(), **kw)
        if path is not None:
            from pathlib import Path

            Path(path).write_text(text)
        return text

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Plan":
        try:
            alphas = np.asarray(d["alphas"], dtype=np.float64)
            plan = cls(str(d["method"]), parse_axis(d["axis"]), float(d["radius"]), float(d["delta_alpha"]),
                       int(d["num_partitions"]), alphas, str(d.get("unit", "")), dict(d.get("details", {})))
        except KeyError as exc:
            raise PwsError(f"plan lacks field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise PwsError(f"malformed plan: {exc}") from None
        validate_grid(plan.alphas, plan.radius)
        require(plan.num_partitions == len(plan.alphas), f"plan says {plan.num_partitions} partitions but lists {len(plan.alphas)} alphas")
        return plan

    @classmethod
    def load(cls, path) -> "Plan":
        from pathlib import Path

        p = Path(path)
        require(p.is_file(), f"plan file not found: {p}")
        try:
            return cls.from_dict(json.loads(p.read_text()))
        except json.JSONDecodeError as exc:
            raise PwsError(f"plan file {p} is not valid JSON: {exc}") from None


def check_radius(radius: float) -> float:
    try:
        r = float(radius)
    except (TypeError, ValueError):
        raise PwsError(f"radius must be a number, got {radius!r}") from None
    require(math.isfinite(r) and r > 0, f"radius must be positive and finite, got {radius}")
    return r


def grid_size(radius: float, delta_alpha: float) -> int:
    """Number of partitions ``2 ceil(radius / delta_alpha) + 1`` of the uniform grid with step ``<= delta_alpha``."""
    return 2 * max(1, math.ceil(radius / delta_alpha * (1 - 1e-12))) + 1


def make_grid(radius: float, delta_alpha: float, max_partitions: int = DEFAULT_MAX_PARTITIONS) -> np.ndarray:
    """Uniform grid from ``-radius`` to ``+radius`` containing 0, step ``<= delta_alpha``; a grid that would
    need more than ``max_partitions`` frames is made coarser (the largest odd size within the cap): the
    per-segment bounds count every extra value a coarser segment shows, so it stays sound, only looser."""
    radius = check_radius(radius)
    require(delta_alpha > 0 and math.isfinite(delta_alpha), f"delta_alpha must be positive, got {delta_alpha}")
    require(int(max_partitions) >= 3, f"max_partitions must be >= 3, got {max_partitions}")
    m = min((grid_size(radius, delta_alpha) - 1) // 2, (int(max_partitions) - 1) // 2)
    alphas = radius * np.arange(-m, m + 1, dtype=np.float64) / m
    alphas[0], alphas[m], alphas[-1] = -radius, 0.0, radius  # exact ends (radius * m / m can miss by an ulp)
    return alphas


def validate_grid(alphas: np.ndarray, radius: float) -> None:
    a = np.asarray(alphas, dtype=np.float64)
    require(a.ndim == 1 and len(a) >= 2, "a plan needs at least two motion values")
    require(bool(np.all(np.isfinite(a))), "plan motion values must be finite")
    require(bool(np.all(np.diff(a) > 0)), "plan motion values must be strictly increasing")
    require(abs(a[0] + radius) <= 1e-12 * max(1, radius) and abs(a[-1] - radius) <= 1e-12 * max(1, radius),
            f"plan grid must start at -{radius:g} and end at +{radius:g}, got [{a[0]:g}, {a[-1]:g}]")
    require(bool(np.any(a == 0.0)), "plan grid must contain alpha = 0 (the original pose)")


@dataclass
class Runs:
    """Consistent intervals: point ``point[i]`` wins pixel ``pix[i]`` on ``[start[i], end[i]]``."""

    pix: np.ndarray
    point: np.ndarray
    start: np.ndarray
    end: np.ndarray
    hole_min_length: float  # shortest background (hole) run inside the window, inf if none


def consistent_runs(points: np.ndarray, intr: CameraIntrinsics, axis: str, radius: float, window: float = 4.0) -> Runs:
    """Runs of one winner per pixel over ``[-window*b, window*b]`` that intersect ``(-b, b)`` and do not
    reach the window's ends."""
    lo, hi = -window * radius, window * radius
    st = pixel_states(points, intr, axis, lo, hi)
    w = st.winner
    newrun = np.concatenate([[True], (st.pix[1:] != st.pix[:-1]) | (w[1:] != w[:-1])])
    rid = np.cumsum(newrun) - 1
    nr = rid[-1] + 1 if len(rid) else 0
    r_start = np.full(nr, np.inf)
    r_end = np.full(nr, -np.inf)
    np.minimum.at(r_start, rid, st.start)
    np.maximum.at(r_end, rid, st.end)
    r_pix = st.pix[newrun]
    r_pt = w[newrun]
    tol = 1e-12 * max(abs(hi), 1e-9)
    inner = (r_start > lo + tol) & (r_end < hi - tol) & (r_end > -radius) & (r_start < radius)
    holes = inner & (r_pt < 0)
    hole_min = float((r_end - r_start)[holes].min()) if holes.any() else math.inf
    keep = inner & (r_pt >= 0)
    return Runs(r_pix[keep], r_pt[keep], r_start[keep], r_end[keep], hole_min)


def inner_visits(points: np.ndarray, intr: CameraIntrinsics, axis: str, radius: float, window: float = 4.0):
    """In-pixel visits over ``[-window*b, window*b]`` that intersect ``(-b, b)`` and do not reach the window ends."""
    lo, hi = -window * radius, window * radius
    v = compute_visits(points, intr, axis, lo, hi)
    tol = 1e-12 * max(abs(hi), 1e-9)
    keep = (v.t0 > lo + tol) & (v.t1 < hi - tol) & (v.t1 > -radius) & (v.t0 < radius)
    return Visits(v.point[keep], v.row[keep], v.col[keep], v.t0[keep], v.t1[keep])


def c_delta(points: np.ndarray, intr: CameraIntrinsics, axis: str, radius: float, delta: float) -> float:
    """``C_delta`` of Lemma D.2 for the one-frame cloud ``points`` (errata fixed, see module doc)."""
    X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
    fx, fy, b = intr.fx, intr.fy, radius
    if axis in ("tx", "ty"):
        return 0.0
    if axis == "tz":
        den = Z - b
        require(bool(np.all(den > 0)), f"tz radius {b:g} m reaches a point of the cloud (min depth {Z.min():.3g} m)")
        return float(np.max(delta / den))
    if axis == "rz":
        return max(fx / fy, fy / fx) * delta
    best = 0.0
    for th in (-b, b):
        c, s = math.cos(th), math.sin(th)
        if axis == "rx":
            depth = -Y * s + Z * c
            num = np.abs(Y * c + Z * s)
            require(bool(np.all(depth > 0)), "rx rotation turns a point behind the camera")
            t1 = (delta / fy) * (fx * np.abs(X) + fy * num) / depth
            t2 = 2 * delta * num / depth
            best = max(best, float(np.max(np.maximum(t1, t2))))
            sq = delta**2 / fy
        else:  # ry: roles of x and y swapped with respect to rx
            depth = X * s + Z * c
            num = np.abs(X * c - Z * s)
            require(bool(np.all(depth > 0)), "ry rotation turns a point behind the camera")
            t1 = 2 * delta * num / depth
            t2 = (delta / fx) * (fy * np.abs(Y) + fx * num) / depth
            best = max(best, float(np.max(np.maximum(t1, t2))))
            sq = delta**2 / fx
    return sq + best


def planning_window(points: np.ndarray, intr: CameraIntrinsics, axis: str, radius: float) -> float:
    """The planning window ``[-w b, w b]`` as a multiple ``w`` of the radius: 4, or less where a wider
    window would take a point to depth 0 (tz: any point, PwsError if ``b`` reaches one; rx, ry: a point
    in view at alpha = 0), where projections and L_P blow up. The window then stops half-way between
    ``b`` and the first such motion (at ``b`` if ``b`` already reaches it)."""
    X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
    if axis == "tz":
        limit = float(Z.min())
        require(limit > radius, f"tz radius {radius:g} m reaches the nearest point of the cloud ({limit:.3g} m)")
    elif axis in ("rx", "ry"):
        u, v, d = project(points, intr, axis, 0.0)
        seen = (d > 0) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        if not seen.any():
            return 4.0
        # depth = Z cos t + B sin t (B = -Y for rx, X for ry) vanishes first at atan2(B, Z) -+ pi/2
        phi = np.arctan2((-Y if axis == "rx" else X)[seen], Z[seen])
        limit = float(np.min(np.minimum(phi + 0.5 * math.pi, 0.5 * math.pi - phi)))
    else:
        return 4.0
    return max(1.0 + 1e-9, min(4.0, (radius + 0.5 * (limit - radius)) / radius))


def _grid_within(radius: float, delta_alpha: float, min_partitions: int, max_partitions: int,
                 details: dict[str, Any]) -> np.ndarray:
    """The grid of step ``delta_alpha``, refined to at least ``min_partitions`` and made coarser to at most
    ``max_partitions`` frames (recorded in ``details``)."""
    step = delta_alpha
    if min_partitions > 3:
        m_min = min(min_partitions // 2, (max_partitions - 1) // 2)  # 2 m + 1 >= min_partitions, <= max_partitions
        if radius / m_min < step:
            step = radius / m_min
            details["refined_for_min_partitions"] = int(min_partitions)
    if grid_size(radius, step) > max_partitions:
        details["coarsened_from"] = grid_size(radius, step)
    return make_grid(radius, step, max_partitions)


def plan_partitions(cloud: Cloud, intr: CameraIntrinsics, axis: str, radius: float, method: str = "pws_of",
                    delta: float | None = None, max_partitions: int = DEFAULT_MAX_PARTITIONS,
                    min_partitions: int = 0) -> Plan:
    """Plan the uniform partition of ``[-radius, radius]`` along ``axis`` with ``method``.

    ``cloud`` is the entire cloud for ``pws`` and the one-frame cloud for ``pws_of`` (``pws_l`` uses
    whichever it is given). ``delta`` (pixels) is the delta-convexity constant of PwS-OF.
    ``min_partitions`` (capped by ``max_partitions``) refines the grid to at least that many partitions when the method's
    ``delta_alpha`` asks for fewer (``plan.delta_alpha`` stays the method's value; ``details`` records
    the refinement). A finer grid is just as sound, and it tightens the per-segment bounds: where the
    method needs only a handful of frames (a motion of a pixel or less) the coverage rules need more.
    """
    t0 = time.perf_counter()
    axis = parse_axis(axis)
    radius = check_radius(radius)
    require(method in PLAN_METHODS, f"unknown planning method {method!r}: expected one of {', '.join(PLAN_METHODS)}")
    require(isinstance(max_partitions, int) and max_partitions >= 3, f"max_partitions must be an integer >= 3, got {max_partitions!r}")
    require(isinstance(min_partitions, int) and min_partitions >= 0, f"min_partitions must be an integer >= 0, got {min_partitions!r}")
    cloud.require_nonempty()
    pts = cloud.points[cloud.points[:, 2] > 0]
    window = planning_window(pts, intr, axis, radius)
    runs = consistent_runs(pts, intr, axis, radius, window)
    details: dict[str, Any] = {"num_runs": int(len(runs.pix)), "cloud_points": int(len(pts)), "window": window}
    lengths = runs.end - runs.start
    if method == "pws":
        delta_alpha = float(lengths.min()) if len(lengths) else math.inf
    else:
        # Lemmas 2/3 bound the time a point needs to cross its pixel (|rho(sup U) - rho(inf U)| / L_P):
        # read the extents off the in-pixel visits of the points (occlusion ignored, as in the paper).
        vis = inner_visits(pts, intr, axis, radius, window)
        P = pts[vis.point]
        u0, v0, _ = project(P, intr, axis, vis.t0)
        u1, v1, _ = project(P, intr, axis, vis.t1)
        extent = np.maximum(np.abs(u1 - u0), np.abs(v1 - v0))
        vis_pix = vis.row * intr.width + vis.col
        details["num_visits"] = int(len(vis))
        uniq, inv = np.unique(vis.point, return_inverse=True) if len(vis.point) else (np.zeros(0, int), np.zeros(0, int))
        L = lipschitz_constant(pts[uniq], intr, axis, -window * radius, window * radius)[inv] if len(uniq) else np.zeros(0)
        if method == "pws_l":
            ok = extent > MIN_VISIT_EXTENT_PX
            details["degenerate_visits"] = int((~ok).sum())
            ratio = extent[ok] / np.maximum(L[ok], 1e-300)
            delta_alpha = float(ratio.min()) if len(ratio) else math.inf
        else:
            d = DEFAULT_DELTA_PX if delta is None else float(delta)
            require(math.isfinite(d) and d > 0, f"delta must be a positive number of pixels, got {delta}")
            C = c_delta(pts, intr, axis, radius, d)
            details.update(delta_px=d, c_delta=C)
            # A visit that only clips a pixel corner spans <= 2 delta: Lemma 3's term is not positive
            # there. Such visits are counted and left out of the minimum (they only change how many
            # frames are rendered; the certificate rests on the rendered bounds, not on this plan).
            ok = extent > 2 * d
            details["degenerate_visits"] = int((~ok).sum())
            if ok.any():
                npix = intr.width * intr.height
                inv_l = np.full(npix, np.inf)
                np.minimum.at(inv_l, vis_pix[ok], 1.0 / (L[ok] + C))
                ext = np.full(npix, np.inf)
                np.minimum.at(ext, vis_pix[ok], extent[ok] - 2 * d)
                used = np.isfinite(ext)
                delta_alpha = float((inv_l[used] * ext[used]).min())
            else:
                delta_alpha = math.inf
    if not math.isfinite(delta_alpha) or delta_alpha > radius:
        delta_alpha = radius
    require(delta_alpha > 0, "a consistent interval of zero length was found (degenerate cloud: duplicate points?)")
    alphas = _grid_within(radius, delta_alpha, min_partitions, max_partitions, details)
    shortest = min(float(lengths.min()) if len(lengths) else math.inf, runs.hole_min_length)
    details["lemma1_holds"] = bool(shortest >= (alphas[1] - alphas[0]))  # every run (holes too) >= step
    details["min_run"] = shortest
    details["min_hole_run"] = runs.hole_min_length
    details["plan_seconds"] = time.perf_counter() - t0
    return Plan(method, axis, radius, delta_alpha, len(alphas), alphas, UNITS[axis], details)


def plan_step(cloud: Cloud, intr: CameraIntrinsics, axis: str, radius: float, method: str = "pws_of", *,
              step_px: float = DEFAULT_STEP_PX, max_partitions: int = DEFAULT_MAX_PARTITIONS,
              min_partitions: int = 0) -> Plan:
    """The plan of the surfel imaging model (:mod:`.imaging`): a uniform grid whose step moves no point of
    the cloud seen by ``intr`` (the native camera) by more than ``step_px`` pixels.

    The surfel bounds hold on any grid (they count every value a segment shows, Lemma 1 is not needed),
    so the step only trades frames for tightness: about half a native pixel per segment keeps the
    bounds close to the distances between neighbouring frames. ``L_P`` is the Lipschitz constant of
    :func:`.motion.lipschitz_constant`, over the points in front of the camera that project into (or
    within half a frame of) the image. More than ``max_partitions`` frames: a coarser grid
    (``details['coarsened_from']``), never a refusal; fewer than ``min_partitions``: refined.
    """
    t0 = time.perf_counter()
    axis = parse_axis(axis)
    radius = check_radius(radius)
    require(method in PLAN_METHODS, f"unknown planning method {method!r}: expected one of {', '.join(PLAN_METHODS)}")
    require(math.isfinite(step_px) and step_px > 0, f"step_px must be positive, got {step_px}")
    require(isinstance(max_partitions, int) and max_partitions >= 3, f"max_partitions must be an integer >= 3, got {max_partitions!r}")
    require(isinstance(min_partitions, int) and min_partitions >= 0, f"min_partitions must be an integer >= 0, got {min_partitions!r}")
    cloud.require_nonempty()
    pts = cloud.points[cloud.points[:, 2] > 0]
    u, v, _ = project(pts, intr, axis, 0.0)
    near = (u > -0.5 * intr.width) & (u < 1.5 * intr.width) & (v > -0.5 * intr.height) & (v < 1.5 * intr.height)
    pts = pts[near]
    details: dict[str, Any] = {"rule": "step", "imaging": "surfel", "step_px": float(step_px), "cloud_points": int(len(pts))}
    if axis == "tz" and len(pts):   # (the message only where it is needed: an empty cloud has no nearest point)
        nearest = float(pts[:, 2].min())
        require(nearest > radius, f"tz radius {radius:g} m reaches the nearest point of the cloud ({nearest:.3g} m)")
    L = float(lipschitz_constant(pts, intr, axis, -radius, radius).max()) if len(pts) else 0.0
    details["max_speed_px"] = L
    delta_alpha = radius if L <= 0 or not math.isfinite(L) else min(radius, step_px / L)
    alphas = _grid_within(radius, delta_alpha, min_partitions, max_partitions, details)
    details["plan_seconds"] = time.perf_counter() - t0
    return Plan(method, axis, radius, delta_alpha, len(alphas), alphas, UNITS[axis], details)

"""What the anchors' path needs of the imaging model (:mod:`.anchored`): the frames of a grid, the grid refined
for a target radius (:func:`refine_for_target`, within :func:`grid_cap`), the bounds of any grid inside the
plan's range with only a refinement's new segments bounded (:func:`refined_hulls`), and the frontier's
refinement; from the renderer (:class:`_RendererGeometry`: pipeline, replay, ``pws certify``; what bounded a grid
kept to decide its refinement's frames and bounds, :class:`.segment_covers.SegmentCovers`)
or from frames and bounds received for a fixed grid (:class:`_FixedGeometry`: the four-process certifier)."""
from __future__ import annotations

import functools
import time
from typing import Callable

import numpy as np
import torch

from .anchors import REFINE_FRACTION, refine_plan
from .certify_common import CertifyConfig, bounds_bytes, segment_bytes
from .coverage import frontier_reach, segment_covers
from .imaging import HullValues, Imaging, SurfelRenderer, hulls_within
from .motion import TRANSLATIONS, project
from .partition import Plan
from .segment_covers import SegmentCovers


class _RendererGeometry:
    """What the adaptive anchors need of the imaging model, from the renderer (pipeline, replay,
    ``pws certify``): frames of the plan, the plan refined for the target, bounds of any grid inside
    the plan's range, hence the frontier refinement."""

    def __init__(self, renderer: SurfelRenderer, config: CertifyConfig):
        self.renderer, self.config = renderer, config
        self._bounds_of = None
        self._last = None   # the last grid bounded and its HullValues (a refinement bounds only its new segments)
        self._covers = None  # what decided the bounds of the first grid bounded (its refinement's frames from it)
        self._prepared = None  # the grid prepare() bounded
        self._bounds_seconds = 0.0   # spent bounding inside refine() (pop_bounds_seconds)

    def start(self, plan: Plan) -> Plan:
        """The grid to begin with. A plan already at the grid cap leaves the refinement no room, so every
        other point is dropped (0 and both ends kept): the refinement puts points back where neighbouring
        frames differ by more than the target allows. Only the grid's tightness depends on it."""
        n = len(plan.alphas)
        if n < max(5, grid_cap(self.renderer.imaging, self.config)):
            return plan
        alphas = every_kth(plan.alphas, 2)
        return Plan(plan.method, plan.axis, plan.radius, float(np.diff(alphas).max()), len(alphas), alphas, plan.unit,
                    dict(plan.details, thinned_from=n))

    def prepare(self, plan: Plan) -> None:
        """The grid to begin with is bounded first: its frames, its refinement's and the refinement's bounds then
        come from what bounded it (:class:`.segment_covers.SegmentCovers`). Where the footprints barely move over
        its segments, a coarser grid of some of its points is bounded before it (:func:`coarse_grid`), and its
        segments are decided from that one's covers: the same bounds, in less time."""
        coarse = coarse_grid(self.renderer, plan.alphas, self._covers_bytes())
        if coarse is not None:
            self._bounds_grid(coarse)
        self.bounds(plan)
        self._prepared = plan.alphas

    def _render(self, alphas) -> Callable[[np.ndarray], torch.Tensor]:
        """What renders poses of ``alphas``: the kept covers where their grid holds them, else the renderer."""
        covers = self._covers
        return covers.render_batch if covers is not None and covers.holds(alphas) else self.renderer.render_batch

    def _covers_bytes(self) -> int:
        """The most a grid's covers may take: a quarter of the bounds' memory ceiling, at most COVERS_BYTES."""
        return min(COVERS_BYTES, bounds_bytes(self.config) // 4)

    def _new_covers(self, g: np.ndarray) -> SegmentCovers:
        """Covers for the grid ``g``, within :meth:`_covers_bytes`."""
        return SegmentCovers(self.renderer, g, self._covers_bytes())

    def frames(self, plan: Plan) -> np.ndarray:
        return self._render(plan.alphas)(plan.alphas).cpu().numpy()

    def refine(self, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
               keep: tuple[float, float] | None = None, share: float = 1.0) -> tuple[Plan, np.ndarray]:
        return refine_for_target(self.renderer, plan, frames, target, max_anchors, self.config, keep=keep, share=share,
                                 render=self._render_refined)

    def _render_refined(self, grid: np.ndarray, alphas: np.ndarray) -> torch.Tensor:
        """The new poses ``alphas`` of the refined grid ``grid``: the grid is bounded first (its bounds are asked for
        next, and kept: :meth:`bounds`), so that they are rendered from its own covers, whose segments are shorter and
        hold fewer candidates than the coarser grid's (the same frames, bit for bit: :class:`.segment_covers.SegmentCovers`).
        Where the refined grid's covers are not kept (beyond their memory ceiling), the coarser grid's render them, as
        before. The time of those bounds is kept apart (:meth:`pop_bounds_seconds`)."""
        coarser = self._render(alphas)   # (held: bounding the refined grid releases the coarser grid's covers)
        t0 = time.perf_counter()
        self._bounds_grid(grid)
        self._bounds_seconds += time.perf_counter() - t0
        covers = self._covers
        return (covers.render_batch if covers is not None and covers.holds(alphas) else coarser)(alphas)

    def pop_bounds_seconds(self) -> float:
        """The seconds spent bounding grids inside :meth:`refine` since the last call (a certificate counts them as
        bounds, not as rendering)."""
        t, self._bounds_seconds = self._bounds_seconds, 0.0
        return t

    def bounds(self, plan: Plan):
        return self._bounds_grid(plan.alphas)

    def _bounds_grid(self, g: np.ndarray):
        # one sweep over the plan's range bounds its grid here, the new segments of a refinement of it (the
        # bounds of a segment depend on its ends only) and, later, the frontier's finer segments
        fresh = (self._last is not None and self._covers is None and self._last[0] is self._prepared
                 and not np.array_equal(self._last[0], g))
        if self._last is None or (self._last[0][0], self._last[0][-1]) != (g[0], g[-1]) or fresh:
            # (fresh: the grid prepare() bounded kept no covers; this one is bounded anew and keeps its own)
            self._bounds_of = hulls_within(self.renderer, float(g[0]), float(g[-1]), max_bytes=bounds_bytes(self.config))
            # the grid's first surely covering surfels and candidates are kept (within a quarter of the bounds' memory
            # ceiling, at most COVERS_BYTES): the frames of a refinement of it, all inside its segments, are decided
            # from them (.segment_covers.SegmentCovers)
            covers = self._new_covers(g)
            self._last = (g, self._bounds_of(g, covers))
            self._covers = None if covers.dropped else covers
        elif not np.array_equal(self._last[0], g):
            covers, self._covers = self._covers, None
            if covers is not None and covers.decides(g):
                # the refinement's new segments, each inside one of the grid's, bounded from its covers
                # (SegmentCovers.decide), and what decided every segment kept in turn (a kept segment's copied): a
                # further refinement's frames and bounds come from them
                finer = self._new_covers(g)
                self._last = (g, refined_hulls(functools.partial(self._bounds_of, parent=covers), *self._last, g, (covers, finer)))
                self._covers = None if finer.dropped else finer
            else:   # the refinement's new segments bounded from every surfel (the covers are released)
                self._last = (g, refined_hulls(self._bounds_of, *self._last, g))
        return self._last[1]

    def frontier(self, anchor_frames: np.ndarray, R: np.ndarray, alphas: np.ndarray, covered: np.ndarray,
                 centre: int) -> tuple[float, list[float]]:
        return frontier_reach(segment_covers(self._bounds_of, anchor_frames, R), alphas, covered, centre,
                              rounds=int(self.config.frontier_rounds))


class _FixedGeometry:
    """The same from frames and bounds received for a fixed grid (the four-process certifier; the planner
    refined the grid for the largest possible target, :func:`anchor_grid`): nothing is refined further,
    and a covered run that stops inside a segment stops at its grid point (no frontier refinement)."""

    def __init__(self, frames: np.ndarray, hulls):
        self._frames, self._hulls = frames, hulls

    def frames(self, plan: Plan) -> np.ndarray:
        return self._frames

    def start(self, plan: Plan) -> Plan:
        return plan

    def prepare(self, plan: Plan) -> None:
        pass

    def refine(self, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
               keep: tuple[float, float] | None = None, share: float = 1.0) -> tuple[Plan, np.ndarray]:
        return plan, frames

    def bounds(self, plan: Plan):
        return self._hulls

    def pop_bounds_seconds(self) -> float:
        return 0.0

    frontier = None


COVERS_BYTES = 256 * 2**20   # the most a grid's kept covers may take (4 bytes per segment and native pixel, 16 per candidate)


def grid_cap(imaging: Imaging, config: CertifyConfig) -> int:
    """The most grid points a refined plan may have: ``max_partitions``, and as many frames and segment
    bounds as the memory ceiling holds (:func:`.certify_common.bounds_bytes`)."""
    return min(int(config.max_partitions), int(bounds_bytes(config) // max(1, segment_bytes(imaging))))


COARSE_MOTION = 0.3     # px the median surfel may move over a segment of the coarse grid (coarse_grid)
COARSE_STEPS = (8, 4)   # grid points per segment of the coarse grid, the largest that keeps within COARSE_MOTION


def coarse_grid(renderer: SurfelRenderer, g: np.ndarray, covers_bytes: int) -> np.ndarray | None:
    """Every ``k``-th point of the increasing grid ``g`` (``alpha = 0`` among them where ``g`` has it, both ends kept),
    to be bounded before ``g`` (:meth:`_RendererGeometry.prepare`), or None. Bounding a segment from every surfel costs
    about the same whether its footprints move a hundredth or a third of a pixel (:func:`.surfel_cover.first_covers`),
    and deciding a segment from its parent's covers costs a fraction of it along a translation
    (:meth:`.segment_covers.SegmentCovers.decide`, the same bounds bit for bit), so where the median surfel moves
    less than ``COARSE_MOTION`` px over ``k`` segments of ``g`` (from its centre at both ends of the grid, the segments
    taken as even) the grid is bounded from the covers of the coarse one. Measured on camera frames at 160x90 (tz,
    ``k`` = 4): the TUM frame's 129 points 1.2 -> 0.9 s, Kinect's 21 0.44 -> 0.35 s. Only the time depends on it. None
    along a rotation (deciding a segment from covers costs more there: four corners, two moving terms; the demo's ry
    grids 3.38 -> 3.56 s over two frames, the RealSense one 0.5 -> 0.6 s when forced; and there the two ways are equal
    by measurement only), where the grid is too short, or where its covers would not fit in ``covers_bytes``
    (:class:`.segment_covers.SegmentCovers`)."""
    if renderer.axis not in TRANSLATIONS:
        return None
    g = np.asarray(g, dtype=np.float64)
    n, P = len(g), renderer.num_points
    steps = [k for k in COARSE_STEPS if n >= 4 * k + 1]
    if P == 0 or not steps or SegmentCovers.first_bytes(renderer, n - 1) > covers_bytes:
        return None
    pts = renderer.points_np
    u0, v0, _ = project(pts, renderer.intr, renderer.axis, float(g[0]))
    u1, v1, _ = project(pts, renderer.intr, renderer.axis, float(g[-1]))
    with np.errstate(invalid="ignore"):
        move = np.maximum(np.abs(u1 - u0), np.abs(v1 - v0))
    move = move[np.isfinite(move)]
    if not len(move):
        return None
    per_segment = float(np.median(move)) / (n - 1)
    for k in steps:
        if k * per_segment <= COARSE_MOTION:
            return every_kth(g, k)
    return None


def every_kth(g: np.ndarray, k: int) -> np.ndarray:
    """Every ``k``-th point of the increasing grid ``g``, counted from ``alpha = 0`` (where ``g`` holds it), both ends
    kept."""
    n = len(g)
    centre = int(np.searchsorted(g, 0.0))
    return g[np.union1d(np.arange(centre % k, n, k), [0, n - 1])]


def refine_for_target(renderer: SurfelRenderer, plan: Plan, frames: np.ndarray, target: float, max_anchors: int,
                      config: CertifyConfig, reserve: int = 0, keep: tuple[float, float] | None = None,
                      share: float = 1.0, render: Callable[[np.ndarray, np.ndarray], torch.Tensor] | None = None) -> tuple[Plan, np.ndarray]:
    """The plan refined where consecutive frames differ by more than ``target / REFINE_FRACTION``
    (:func:`.anchors.refine_plan`), and its frames (only the new poses rendered). Anchors cover about 2
    target radii of rendered path each: no refinement farther than the budget reaches; the refined grid
    stays within :func:`grid_cap` less ``reserve`` points (never below the plan's own size) and adds at
    most ``share`` of the room that leaves. One round; :func:`_certify_anchored` asks for more where the
    anchors fall short. ``render(grid, alphas)``: the frames of the refined grid's new poses ``alphas`` (default the
    renderer's; the same frames from :class:`.segment_covers.SegmentCovers` of a bounded grid holding them)."""
    coarse = plan
    room = max(0, grid_cap(renderer.imaging, config) - int(reserve) - len(frames))
    plan = refine_plan(plan, frames, target / REFINE_FRACTION, len(frames) + int(share * room),
                       reach=(max_anchors + 1) * target, keep=keep)
    if len(plan.alphas) != len(frames):  # render only the new poses
        old = np.searchsorted(plan.alphas, coarse.alphas)
        new = np.setdiff1d(np.arange(len(plan.alphas)), old)
        full = np.empty((len(plan.alphas),) + frames.shape[1:], dtype=frames.dtype)
        full[old] = frames
        alphas = plan.alphas[new]
        full[new] = (renderer.render_batch(alphas) if render is None else render(plan.alphas, alphas)).cpu().numpy()
        frames = full
    return plan, frames


def refined_hulls(bounds_of, old_grid: np.ndarray, old, grid: np.ndarray, covers: tuple | None = None):
    """The HullValues of ``grid`` from those of ``old_grid`` (``old``): a segment of ``grid`` that is a segment
    of ``old_grid`` keeps its bounds (they depend on its two ends only); the runs of new segments are bounded
    by ``bounds_of`` (:func:`.imaging.hulls_within` over the same range). ``covers = (old's, grid's)``
    (:class:`.segment_covers.SegmentCovers`): the grid's are filled, a kept segment's copied from the old."""
    S = len(grid) - 1
    i = np.searchsorted(old_grid, grid[:-1])
    ok = i < len(old_grid) - 1
    kept = np.zeros(S, bool)
    kept[ok] = (old_grid[i[ok]] == grid[:-1][ok]) & (old_grid[i[ok] + 1] == grid[1:][ok])
    lo = np.empty((S,) + old.lo.shape[1:], old.lo.dtype)
    hi = np.empty_like(lo)
    constant = np.empty((S,) + old.constant.shape[1:], bool)
    lo[kept], hi[kept], constant[kept] = old.lo[i[kept]], old.hi[i[kept]], old.constant[i[kept]]
    if covers is not None:
        for k in np.flatnonzero(kept).tolist():
            covers[1].adopt(k, covers[0], int(i[k]))
    new = np.flatnonzero(~kept)
    if len(new):
        starts = new[np.r_[True, np.diff(new) > 1]]
        ends = new[np.r_[np.diff(new) > 1, True]] + 1
        for s, e in zip(starts, ends):
            part = bounds_of(grid[s:e + 1]) if covers is None else bounds_of(grid[s:e + 1], covers[1], at=int(s))
            lo[s:e], hi[s:e], constant[s:e] = part.lo, part.hi, part.constant
    values = HullValues(grid, lo, hi, constant, dict(old.details, segments=S))
    if covers is not None:
        covers[1].close(values)
    return values


__all__ = ["COARSE_MOTION", "COARSE_STEPS", "COVERS_BYTES", "coarse_grid", "every_kth", "grid_cap", "refine_for_target",
           "refined_hulls"]

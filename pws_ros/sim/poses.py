"""Camera poses in the procedural world: :class:`Pose`, the canonical views on rings around the
object (:func:`view_pose`, ``NUM_VIEWS`` of them, like MetaRoom's test views) and continuous random
poses for training (:func:`random_pose`). World frame: z up; camera optical frame: x right, y down,
z forward. ``scene`` is a :class:`~pws_ros.sim.world.Scene` (its ``target``, ``view_distance``,
``azimuth0`` and ``bound_radius``)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import PwsError, require
from .geometry import rot_z

NUM_VIEWS = 24  # 3 rings x 8 azimuths
RING_ELEVATIONS_DEG = (12.0, 24.0, 36.0)
RING_DISTANCE_FACTORS = (1.0, 1.12, 1.25)
MIN_DISTANCE, MAX_DISTANCE = 0.6, 2.5


@dataclass(frozen=True)
class Pose:
    """Camera pose in the world: ``R`` (world from optical frame, columns x right, y down, z
    forward) and centre ``C``. A world point ``P`` is at ``R.T @ (P - C)`` in the optical frame."""

    R: np.ndarray
    C: np.ndarray

    def to_camera(self, p: np.ndarray) -> np.ndarray:
        return (p - self.C) @ self.R

    def moved(self, R_rel: np.ndarray, t_rel: np.ndarray) -> "Pose":
        """The pose of a camera moved by ``(R_rel, t_rel)`` in its own optical frame."""
        return Pose(self.R @ R_rel, self.C + self.R @ np.asarray(t_rel, dtype=np.float64))


def look_at(C: np.ndarray, target: np.ndarray, roll: float = 0.0) -> Pose:
    C = np.asarray(C, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - C
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    R = np.stack([x, y, f], axis=1)
    if roll:
        R = R @ rot_z(roll)
    return Pose(R, C)


def orbit_pose(scene: Any, azimuth: float, elevation: float, distance: float, roll: float = 0.0,
               target_offset=(0.0, 0.0, 0.0)) -> Pose:
    t = scene.target + np.asarray(target_offset, dtype=np.float64)
    C = t + distance * np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
    return look_at(C, t, roll)


def view_pose(scene: Any, view_index: int) -> Pose:
    """Canonical view ``view_index`` in ``[0, NUM_VIEWS)``: ring ``view_index // 8`` (elevation
    12/24/36 degrees, distance growing with the ring), azimuth step 45 degrees."""
    try:
        view_index = int(view_index)
    except (TypeError, ValueError):
        raise PwsError(f"view index must be an integer, got {view_index!r}") from None
    require(0 <= view_index < NUM_VIEWS, f"view index must be in [0, {NUM_VIEWS}), got {view_index}")
    ring, k = divmod(view_index, 8)
    dist = float(np.clip(scene.view_distance * RING_DISTANCE_FACTORS[ring], MIN_DISTANCE, MAX_DISTANCE))
    return orbit_pose(scene, scene.azimuth0 + k * math.pi / 4, math.radians(RING_ELEVATIONS_DEG[ring]), dist)


def random_pose(scene: Any, rng: np.random.Generator, jitter: float = 1.0) -> Pose:
    """A continuous random pose around the object (training views): any azimuth, elevation 8-40
    degrees, distance 0.9-1.35 x the ring distance, small roll and look-at offsets."""
    az = rng.uniform(0, 2 * math.pi)
    el = math.radians(rng.uniform(8.0, 40.0))
    dist = float(np.clip(scene.view_distance * rng.uniform(0.9, 1.35), MIN_DISTANCE, MAX_DISTANCE))
    roll = math.radians(rng.normal(0, 2.5 * jitter))
    off = rng.normal(0, 0.06 * jitter, size=3) * scene.bound_radius
    return orbit_pose(scene, az, el, dist, roll, off)


__all__ = ["MAX_DISTANCE", "MIN_DISTANCE", "NUM_VIEWS", "Pose", "RING_DISTANCE_FACTORS", "RING_ELEVATIONS_DEG", "look_at",
           "orbit_pose", "random_pose", "view_pose"]

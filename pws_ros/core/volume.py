"""The working volume: the part of the one-frame cloud the imaging draws (docs/imaging.md, section 4a).

A robot's classifier usually needs what lies in its working range (a hand, an object on a table, a
person in front), not the room behind it; a textured background moves more under a small rotation than
any smoothed classifier can be certified for. A :class:`WorkingVolume` is a box in the recorded camera's
optical frame (x right, y down, z forward, metres):

    near <= Z <= far,   x_min <= X <= x_max (if set),   y_min <= Y <= y_max (if set),   and Z > 0

(closed bounds, float64, on the cloud's own coordinates). The imaging draws only the **measured** points
inside it (a point whose depth the depth fill made up is never inside), chosen **once, at alpha = 0**: a point inside moves with the camera as every point does, and keeps being
drawn when the motion carries it across a face; a point outside is never drawn. Pixels that no drawn
surfel covers show their uncovered value as usual (``uncovered: frame`` computes its table from the
drawn points, so what lies outside the volume shows ``background``). The renderer and the bounds both
take their points from :func:`.surfel.bin_cloud`, which applies the selection first: one rule for both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .errors import PwsError, require


@dataclass(frozen=True)
class WorkingVolume:
    """``near <= Z <= far`` (metres), and, where given, ``x_min <= X <= x_max`` and ``y_min <= Y <= y_max``
    (``x``, ``y``: ``(min, max)`` or None for no limit), in the recorded camera's optical frame."""

    near: float
    far: float
    x: tuple[float, float] | None = None
    y: tuple[float, float] | None = None
    window: float = 0.0   # > 0: per frame, only the nearest `window` metres of it, and the camera window around them

    def __post_init__(self) -> None:
        what = "working volume"
        require(isinstance(self.window, (int, float)) and math.isfinite(self.window) and self.window >= 0,
                f"{what}: window must be a depth band >= 0 m, got {self.window!r}")
        object.__setattr__(self, "window", float(self.window))
        require(all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (self.near, self.far)),
                f"{what}: near and far must be numbers, got near={self.near!r}, far={self.far!r}")
        require(math.isfinite(self.near) and math.isfinite(self.far), f"{what}: near and far must be finite, got "
                                                                       f"near={self.near!r}, far={self.far!r}")
        require(self.near >= 0, f"{what}: near must be >= 0 m, got {self.near!r}")
        require(self.far > self.near, f"{what}: far ({self.far!r} m) must be larger than near ({self.near!r} m)")
        for name, lim in (("x", self.x), ("y", self.y)):
            if lim is None:
                continue
            require(len(lim) == 2, f"{what}: {name} must be (min, max), got {lim!r}")
            lo, hi = lim
            require(math.isfinite(lo) and math.isfinite(hi), f"{what}: {name}_min and {name}_max must be finite, got {lim!r}")
            require(hi > lo, f"{what}: {name}_max ({hi!r} m) must be larger than {name}_min ({lo!r} m): a box of zero size")
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))
        for name in ("x", "y"):
            lim = getattr(self, name)
            if lim is not None:
                object.__setattr__(self, name, (float(lim[0]), float(lim[1])))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of ``points`` (N, 3) lie in the volume (the rule of the module text)."""
        p = np.asarray(points, dtype=np.float64)
        z = p[:, 2]
        inside = (z > 0) & (z >= self.near) & (z <= self.far)
        if self.x is not None:
            inside &= (p[:, 0] >= self.x[0]) & (p[:, 0] <= self.x[1])
        if self.y is not None:
            inside &= (p[:, 1] >= self.y[0]) & (p[:, 1] <= self.y[1])
        return inside

    def describe(self) -> str:
        text = f"depth {self.near:g}-{self.far:g} m"
        for name, lim in (("x", self.x), ("y", self.y)):
            if lim is not None:
                text += f", {name} {lim[0]:g} to {lim[1]:g} m"
        if self.window > 0:
            text += f", window: {self.window:g} m from its subject"
        return text

    def for_frame(self, points: np.ndarray, filled_mask: np.ndarray | None = None,
                  subject: np.ndarray | None = None) -> "WorkingVolume":
        """The volume of one frame when ``window`` > 0 (else itself): its far face moved to ``z0 + window``,
        ``z0`` the 2nd percentile of the depths of the frame's measured points inside the volume (robust to a
        few stray points) — of those in ``subject`` ((N,) bool, the window's subject: see
        :func:`.framing.window_subject`) where given: the subject and what is just behind it, e.g. a hand
        and arm before a room. Chosen once at ``alpha = 0`` from the depth, never from a label."""
        if self.window <= 0:
            return self
        p = np.asarray(points, dtype=np.float64)
        inside = self.contains(p)
        if filled_mask is not None:
            inside &= ~np.asarray(filled_mask, dtype=bool)
        if subject is not None and (inside & np.asarray(subject, dtype=bool)).any():
            inside &= np.asarray(subject, dtype=bool)
        if not inside.any():
            return replace(self, window=0.0)
        z0 = float(np.percentile(p[inside, 2], 2.0))
        return replace(self, far=max(min(self.far, z0 + self.window), self.near + 1e-6), window=0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"near": self.near, "far": self.far, "x_min": None if self.x is None else self.x[0],
                "x_max": None if self.x is None else self.x[1], "y_min": None if self.y is None else self.y[0],
                "y_max": None if self.y is None else self.y[1], "window": self.window}

    @classmethod
    def from_dict(cls, d: Any) -> "WorkingVolume | None":
        """The inverse of :meth:`to_dict`; None for None (no volume). PwsError naming a malformed entry."""
        if d is None:
            return None
        require(isinstance(d, dict), f"malformed working volume: expected a mapping, got {d!r}")
        try:
            lims = {}
            for name in ("x", "y"):
                lo, hi = d.get(f"{name}_min"), d.get(f"{name}_max")
                require((lo is None) == (hi is None), f"malformed working volume: {name}_min and {name}_max go together, got {d}")
                lims[name] = None if lo is None else (float(lo), float(hi))
            return cls(float(d["near"]), float(d["far"]), lims["x"], lims["y"], float(d.get("window") or 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise PwsError(f"malformed working volume {d!r}: {exc}") from None


def volume_from_limits(near: float, far: float, x_min: float = 0.0, x_max: float = 0.0, y_min: float = 0.0,
                       y_max: float = 0.0, window: float = 0.0) -> WorkingVolume | None:
    """The volume of the parameters ``working_volume.*``: None where ``far`` is 0 (no volume, every point is
    drawn); a lateral limit pair of 0 and 0 means none on that side. PwsError naming a bad combination."""
    lateral = {"x": (x_min, x_max), "y": (y_min, y_max)}
    if far == 0:
        set_ = [f"working_volume.{n}_min/{n}_max" for n, (lo, hi) in lateral.items() if (lo, hi) != (0, 0)]
        set_ += ["working_volume.window"] * (window != 0)
        require(near == 0 and not set_, f"working volume: {', '.join(['working_volume.near'] * (near != 0) + set_)} set but "
                                         f"working_volume.far is 0 (no working volume): set far, the far face in metres")
        return None
    return WorkingVolume(near, far, *(None if lim == (0, 0) else lim for lim in (lateral["x"], lateral["y"])), window=window)


VOLUME_BACKGROUND = 0.5   # mid-grey: what "automatic" background is with a working volume (0.0 without one)


def resolve_background(background: float, volume: WorkingVolume | None) -> float:
    """``background``, where a negative value means automatic: :data:`VOLUME_BACKGROUND` with a working
    volume (the outside takes most of the image; mid-grey keeps the contrast at a hand's silhouette low:
    measured, 0.0 instead cut the ceiling of real gesture frames from 100% to about a third), else 0.0."""
    if background >= 0:
        return float(background)
    return VOLUME_BACKGROUND if volume is not None else 0.0


def volume_text(volume: WorkingVolume | None) -> str:
    """What a certificate records of the volume: :meth:`WorkingVolume.describe`, or "" for none."""
    return "" if volume is None else volume.describe()


def count_inside(volume: WorkingVolume | None, points: np.ndarray, filled_mask: np.ndarray | None = None) -> tuple[int, int]:
    """``(measured, filled)``: how many points inside ``volume`` (all points when None) have a measured and
    a filled depth (``filled_mask``: which points were filled; None: none known)."""
    inside = np.ones(len(points), bool) if volume is None else volume.contains(points)
    filled = int(np.count_nonzero(inside & filled_mask)) if filled_mask is not None else 0
    return int(np.count_nonzero(inside)) - filled, filled


__all__ = ["VOLUME_BACKGROUND", "WorkingVolume", "count_inside", "resolve_background", "volume_from_limits", "volume_text"]

"""The object classes of the procedural world (:data:`CLASS_NAMES`) and their shapes: each class is a
few textured primitives in a local frame, z up, resting on z = 0, centred on the z axis."""
from __future__ import annotations

import math

import numpy as np

from ..core.errors import PwsError, require
from .geometry import Box, Cone, Cylinder, Primitive, Sphere, Texture, Torus, rot_x, rot_y, rot_z

CLASS_NAMES: tuple[str, ...] = (
    "crate",
    "barrel",
    "beach_ball",
    "traffic_cone",
    "ring",
    "chair",
    "table",
    "lamp",
    "snowman",
    "mushroom",
    "dumbbell",
    "block_tower",
)
NUM_CLASSES = len(CLASS_NAMES)


def class_index(name: str) -> int:
    require(name in CLASS_NAMES, f"unknown class {name!r}: expected one of {', '.join(CLASS_NAMES)}")
    return CLASS_NAMES.index(name)


# ------------------------------------------------------------------------------------------------
# object builders: local frame z up, resting on z = 0, centred on the z axis
# ------------------------------------------------------------------------------------------------
def _T(kind="solid", colors=((0.5, 0.5, 0.5),), **kw) -> Texture:
    return Texture(kind=kind, colors=tuple(tuple(float(x) for x in c) for c in colors), **kw)


def at(prim: Primitive, x=0.0, y=0.0, z=0.0, R=None) -> Primitive:
    prim.R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    prim.c = np.array([x, y, z], dtype=np.float64)
    return prim


def build_object(label: int, s: float, col) -> list[Primitive]:
    """Primitives of class ``label`` at scale ``s``; ``col(rgb)`` jitters a colour."""
    name = CLASS_NAMES[label]
    if name == "crate":
        h = 0.3 * s
        return [at(Box(texture=_T("stripes", [col((0.62, 0.40, 0.18)), col((0.48, 0.29, 0.11))], period=0.07 * s, axis=(1, 0, 0), grain=0.08), half=(h, h, h)), z=h)]
    if name == "barrel":
        r, hh = 0.25 * s, 0.36 * s
        return [at(Cylinder(texture=_T("stripes", [col((0.85, 0.1, 0.08))] * 3 + [col((0.2, 0.2, 0.22))], period=0.06 * s, axis=(0, 0, 1)), radius=r, half_height=hh), z=hh)]
    if name == "beach_ball":
        r = 0.36 * s
        tex = _T("segments", [col((0.1, 0.25, 0.9)), col((0.95, 0.95, 0.95)), col((0.95, 0.85, 0.1))], count=6)
        return [at(Sphere(texture=tex, radius=r), z=r)]
    if name == "traffic_cone":
        H, R = 0.75 * s, 0.24 * s
        cone = Cone(texture=_T("stripes", [col((1.0, 0.45, 0.0)), col((1.0, 0.45, 0.0)), col((0.97, 0.97, 0.97))], period=0.08 * s, axis=(0, 0, 1), offset=0.5), radius=R, height=H)
        base = Box(texture=_T("solid", [col((0.1, 0.1, 0.1))]), half=(0.28 * s, 0.28 * s, 0.02 * s))
        return [at(cone, z=0.04 * s), at(base, z=0.02 * s)]
    if name == "ring":
        Rm, rm = 0.3 * s, 0.09 * s
        torus = Torus(texture=_T("solid", [col((0.95, 0.75, 0.1))], grain=0.1), major=Rm, minor=rm)
        stand = Box(texture=_T("solid", [col((0.25, 0.15, 0.35))]), half=(0.18 * s, 0.12 * s, 0.05 * s))
        return [at(torus, z=Rm + rm + 0.06 * s, R=rot_x(math.pi / 2)), at(stand, z=0.05 * s)]
    if name == "chair":
        green = _T("solid", [col((0.1, 0.65, 0.25))], grain=0.06)
        legs = _T("solid", [col((0.2, 0.2, 0.2))])
        seat_z = 0.45 * s
        prims: list[Primitive] = [
            at(Box(texture=green, half=(0.25 * s, 0.25 * s, 0.03 * s)), z=seat_z),
            at(Box(texture=green, half=(0.25 * s, 0.03 * s, 0.3 * s)), y=-0.22 * s, z=seat_z + 0.33 * s),
        ]
        for sx in (-1, 1):
            for sy in (-1, 1):
                prims.append(at(Cylinder(texture=legs, radius=0.025 * s, half_height=0.21 * s), x=sx * 0.21 * s, y=sy * 0.21 * s, z=0.21 * s))
        return prims
    if name == "table":
        top = _T("checker", [col((0.95, 0.95, 0.95)), col((0.1, 0.1, 0.1))], period=0.1 * s)
        legs = _T("solid", [col((0.55, 0.1, 0.55))])
        prims = [at(Box(texture=top, half=(0.45 * s, 0.32 * s, 0.03 * s)), z=0.68 * s)]
        for sx in (-1, 1):
            for sy in (-1, 1):
                prims.append(at(Cylinder(texture=legs, radius=0.035 * s, half_height=0.33 * s), x=sx * 0.38 * s, y=sy * 0.25 * s, z=0.33 * s))
        return prims
    if name == "lamp":
        metal = _T("solid", [col((0.3, 0.35, 0.55))])
        shade = _T("stripes", [col((1.0, 0.95, 0.55)), col((0.95, 0.85, 0.35))], period=0.05 * s, axis=(0, 0, 1))
        return [
            at(Cylinder(texture=metal, radius=0.17 * s, half_height=0.025 * s), z=0.025 * s),
            at(Cylinder(texture=metal, radius=0.025 * s, half_height=0.42 * s), z=0.45 * s),
            at(Cone(texture=shade, radius=0.3 * s, height=0.38 * s), z=0.72 * s),
        ]
    if name == "snowman":
        white = _T("solid", [col((0.96, 0.96, 0.97))])
        buttons = _T("dots", [col((0.96, 0.96, 0.97)), col((0.05, 0.05, 0.05))], period=0.09 * s, radius=0.022 * s)
        return [
            at(Sphere(texture=white, radius=0.26 * s), z=0.26 * s),
            at(Sphere(texture=buttons, radius=0.19 * s), z=0.64 * s),
            at(Sphere(texture=white, radius=0.13 * s), z=0.92 * s),
            at(Cone(texture=_T("solid", [col((1.0, 0.5, 0.05))]), radius=0.03 * s, height=0.14 * s), x=0.11 * s, z=0.93 * s, R=rot_y(math.pi / 2)),
            at(Cylinder(texture=_T("solid", [col((0.08, 0.08, 0.1))]), radius=0.09 * s, half_height=0.07 * s), z=1.08 * s),
        ]
    if name == "mushroom":
        cap = _T("dots", [col((0.85, 0.08, 0.1)), col((0.97, 0.97, 0.9))], period=0.12 * s, radius=0.035 * s)
        stem = _T("solid", [col((0.93, 0.88, 0.72))])
        return [
            at(Cylinder(texture=stem, radius=0.09 * s, half_height=0.22 * s), z=0.22 * s),
            at(Cone(texture=cap, radius=0.4 * s, height=0.25 * s), z=0.4 * s),
        ]
    if name == "dumbbell":
        bell = _T("stripes", [col((0.05, 0.55, 0.6)), col((0.03, 0.35, 0.4))], period=0.05 * s, axis=(1, 0, 0))
        bar = _T("solid", [col((0.78, 0.78, 0.8))])
        r = 0.2 * s
        return [
            at(Sphere(texture=bell, radius=r), x=-0.38 * s, z=r),
            at(Sphere(texture=bell, radius=r), x=0.38 * s, z=r),
            at(Cylinder(texture=bar, radius=0.045 * s, half_height=0.4 * s), z=r, R=rot_y(math.pi / 2)),
        ]
    if name == "block_tower":
        cols = [col((0.85, 0.2, 0.75)), col((0.2, 0.8, 0.9)), col((0.7, 0.92, 0.15))]
        prims, z = [], 0.0
        for k, half in enumerate((0.24 * s, 0.18 * s, 0.13 * s)):
            prims.append(at(Box(texture=_T("solid", [cols[k]], grain=0.05), half=(half, half, half)), z=z + half, R=rot_z(0.45 * k)))
            z += 2 * half
        return prims
    raise PwsError(f"unknown class index {label}")  # pragma: no cover


__all__ = ["CLASS_NAMES", "NUM_CLASSES", "at", "build_object", "class_index"]

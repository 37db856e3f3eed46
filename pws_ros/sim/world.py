"""A seeded procedural indoor world: one object of one of :data:`CLASS_NAMES` in a textured room.

* :func:`make_scene` builds a scene from an integer seed (the class is ``seed % NUM_CLASSES``
  unless given); everything else (size, yaw, colours, lighting, room) comes from the seed.
* :func:`view_pose` places the camera on rings around the object (``NUM_VIEWS`` canonical views,
  like MetaRoom's test views); :func:`random_pose` draws a continuous pose (for training).
* :func:`raycast` is the "real camera": exact RGB-D at pixel centres.
* :func:`dense_cloud` samples every surface that can be seen within a margin of the view frustum
  (occluded parts included) densely enough that each pixel footprint gets several samples; colours
  are the same functions of the surface point as in the ray caster (Lambertian shading, no shadows).
* :func:`render_view` / :func:`dense_cloud_for` tie these together for ``(scene_seed, view_index)``.

World frame: z up, floor at z = 0. Camera optical frame: x right, y down, z forward.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.cloud import Cloud, cloud_from_rgbd
from ..core.errors import PwsError, require
from .geometry import Box, Cone, Cylinder, Primitive, Rect, Sphere, Texture, Torus, rot_x, rot_y, rot_z

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
NUM_VIEWS = 24  # 3 rings x 8 azimuths
RING_ELEVATIONS_DEG = (12.0, 24.0, 36.0)
RING_DISTANCE_FACTORS = (1.0, 1.12, 1.25)
MIN_DISTANCE, MAX_DISTANCE = 0.6, 2.5
FRAME_ID = "camera_color_optical_frame"

# A 1280x720 camera (RealSense-like); the default 160x90 view is this camera scaled by 1/8.
BASE_CAMERA = CameraIntrinsics(1280, 720, 920.0, 920.0, 639.5, 359.5, FRAME_ID)
DEFAULT_WIDTH, DEFAULT_HEIGHT = 160, 90


def default_intrinsics(width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT) -> CameraIntrinsics:
    """The 1280x720 base camera at ``width / 1280`` of its resolution with square pixels, centred, and
    ``height`` rows: ``BASE_CAMERA.scaled`` for 16:9 sizes; other sizes see more or less above and below
    (a 640x480 camera is the 160x90 view's camera at 4x its resolution, with 60 more rows each side)."""
    require(int(width) >= 8 and int(height) >= 8, f"image size must be at least 8x8, got {width}x{height}")
    require(int(width) <= 4096 and int(height) <= 4096, f"image size must be at most 4096x4096, got {width}x{height}")
    s = int(width) / BASE_CAMERA.width
    return CameraIntrinsics(int(width), int(height), BASE_CAMERA.fx * s, BASE_CAMERA.fy * s,
                            (BASE_CAMERA.cx + 0.5) * s - 0.5, int(height) / 2 - 0.5, FRAME_ID)


def class_index(name: str) -> int:
    require(name in CLASS_NAMES, f"unknown class {name!r}: expected one of {', '.join(CLASS_NAMES)}")
    return CLASS_NAMES.index(name)


# ------------------------------------------------------------------------------------------------
# object builders: local frame z up, resting on z = 0, centred on the z axis
# ------------------------------------------------------------------------------------------------
def _T(kind="solid", colors=((0.5, 0.5, 0.5),), **kw) -> Texture:
    return Texture(kind=kind, colors=tuple(tuple(float(x) for x in c) for c in colors), **kw)


def _at(prim: Primitive, x=0.0, y=0.0, z=0.0, R=None) -> Primitive:
    prim.R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    prim.c = np.array([x, y, z], dtype=np.float64)
    return prim


def _build_object(label: int, s: float, col) -> list[Primitive]:
    """Primitives of class ``label`` at scale ``s``; ``col(rgb)`` jitters a colour."""
    name = CLASS_NAMES[label]
    if name == "crate":
        h = 0.3 * s
        return [_at(Box(texture=_T("stripes", [col((0.62, 0.40, 0.18)), col((0.48, 0.29, 0.11))], period=0.07 * s, axis=(1, 0, 0), grain=0.08), half=(h, h, h)), z=h)]
    if name == "barrel":
        r, hh = 0.25 * s, 0.36 * s
        return [_at(Cylinder(texture=_T("stripes", [col((0.85, 0.1, 0.08))] * 3 + [col((0.2, 0.2, 0.22))], period=0.06 * s, axis=(0, 0, 1)), radius=r, half_height=hh), z=hh)]
    if name == "beach_ball":
        r = 0.36 * s
        tex = _T("segments", [col((0.1, 0.25, 0.9)), col((0.95, 0.95, 0.95)), col((0.95, 0.85, 0.1))], count=6)
        return [_at(Sphere(texture=tex, radius=r), z=r)]
    if name == "traffic_cone":
        H, R = 0.75 * s, 0.24 * s
        cone = Cone(texture=_T("stripes", [col((1.0, 0.45, 0.0)), col((1.0, 0.45, 0.0)), col((0.97, 0.97, 0.97))], period=0.08 * s, axis=(0, 0, 1), offset=0.5), radius=R, height=H)
        base = Box(texture=_T("solid", [col((0.1, 0.1, 0.1))]), half=(0.28 * s, 0.28 * s, 0.02 * s))
        return [_at(cone, z=0.04 * s), _at(base, z=0.02 * s)]
    if name == "ring":
        Rm, rm = 0.3 * s, 0.09 * s
        torus = Torus(texture=_T("solid", [col((0.95, 0.75, 0.1))], grain=0.1), major=Rm, minor=rm)
        stand = Box(texture=_T("solid", [col((0.25, 0.15, 0.35))]), half=(0.18 * s, 0.12 * s, 0.05 * s))
        return [_at(torus, z=Rm + rm + 0.06 * s, R=rot_x(math.pi / 2)), _at(stand, z=0.05 * s)]
    if name == "chair":
        green = _T("solid", [col((0.1, 0.65, 0.25))], grain=0.06)
        legs = _T("solid", [col((0.2, 0.2, 0.2))])
        seat_z = 0.45 * s
        prims: list[Primitive] = [
            _at(Box(texture=green, half=(0.25 * s, 0.25 * s, 0.03 * s)), z=seat_z),
            _at(Box(texture=green, half=(0.25 * s, 0.03 * s, 0.3 * s)), y=-0.22 * s, z=seat_z + 0.33 * s),
        ]
        for sx in (-1, 1):
            for sy in (-1, 1):
                prims.append(_at(Cylinder(texture=legs, radius=0.025 * s, half_height=0.21 * s), x=sx * 0.21 * s, y=sy * 0.21 * s, z=0.21 * s))
        return prims
    if name == "table":
        top = _T("checker", [col((0.95, 0.95, 0.95)), col((0.1, 0.1, 0.1))], period=0.1 * s)
        legs = _T("solid", [col((0.55, 0.1, 0.55))])
        prims = [_at(Box(texture=top, half=(0.45 * s, 0.32 * s, 0.03 * s)), z=0.68 * s)]
        for sx in (-1, 1):
            for sy in (-1, 1):
                prims.append(_at(Cylinder(texture=legs, radius=0.035 * s, half_height=0.33 * s), x=sx * 0.38 * s, y=sy * 0.25 * s, z=0.33 * s))
        return prims
    if name == "lamp":
        metal = _T("solid", [col((0.3, 0.35, 0.55))])
        shade = _T("stripes", [col((1.0, 0.95, 0.55)), col((0.95, 0.85, 0.35))], period=0.05 * s, axis=(0, 0, 1))
        return [
            _at(Cylinder(texture=metal, radius=0.17 * s, half_height=0.025 * s), z=0.025 * s),
            _at(Cylinder(texture=metal, radius=0.025 * s, half_height=0.42 * s), z=0.45 * s),
            _at(Cone(texture=shade, radius=0.3 * s, height=0.38 * s), z=0.72 * s),
        ]
    if name == "snowman":
        white = _T("solid", [col((0.96, 0.96, 0.97))])
        buttons = _T("dots", [col((0.96, 0.96, 0.97)), col((0.05, 0.05, 0.05))], period=0.09 * s, radius=0.022 * s)
        return [
            _at(Sphere(texture=white, radius=0.26 * s), z=0.26 * s),
            _at(Sphere(texture=buttons, radius=0.19 * s), z=0.64 * s),
            _at(Sphere(texture=white, radius=0.13 * s), z=0.92 * s),
            _at(Cone(texture=_T("solid", [col((1.0, 0.5, 0.05))]), radius=0.03 * s, height=0.14 * s), x=0.11 * s, z=0.93 * s, R=rot_y(math.pi / 2)),
            _at(Cylinder(texture=_T("solid", [col((0.08, 0.08, 0.1))]), radius=0.09 * s, half_height=0.07 * s), z=1.08 * s),
        ]
    if name == "mushroom":
        cap = _T("dots", [col((0.85, 0.08, 0.1)), col((0.97, 0.97, 0.9))], period=0.12 * s, radius=0.035 * s)
        stem = _T("solid", [col((0.93, 0.88, 0.72))])
        return [
            _at(Cylinder(texture=stem, radius=0.09 * s, half_height=0.22 * s), z=0.22 * s),
            _at(Cone(texture=cap, radius=0.4 * s, height=0.25 * s), z=0.4 * s),
        ]
    if name == "dumbbell":
        bell = _T("stripes", [col((0.05, 0.55, 0.6)), col((0.03, 0.35, 0.4))], period=0.05 * s, axis=(1, 0, 0))
        bar = _T("solid", [col((0.78, 0.78, 0.8))])
        r = 0.2 * s
        return [
            _at(Sphere(texture=bell, radius=r), x=-0.38 * s, z=r),
            _at(Sphere(texture=bell, radius=r), x=0.38 * s, z=r),
            _at(Cylinder(texture=bar, radius=0.045 * s, half_height=0.4 * s), z=r, R=rot_y(math.pi / 2)),
        ]
    if name == "block_tower":
        cols = [col((0.85, 0.2, 0.75)), col((0.2, 0.8, 0.9)), col((0.7, 0.92, 0.15))]
        prims, z = [], 0.0
        for k, half in enumerate((0.24 * s, 0.18 * s, 0.13 * s)):
            prims.append(_at(Box(texture=_T("solid", [cols[k]], grain=0.05), half=(half, half, half)), z=z + half, R=rot_z(0.45 * k)))
            z += 2 * half
        return prims
    raise PwsError(f"unknown class index {label}")  # pragma: no cover


# ------------------------------------------------------------------------------------------------
# scenes
# ------------------------------------------------------------------------------------------------
FLOORS = (
    (("checker", ((0.55, 0.55, 0.55), (0.42, 0.42, 0.44))), 0.5),
    (("stripes", ((0.78, 0.72, 0.62), (0.7, 0.64, 0.54))), 0.2),
    (("solid", ((0.35, 0.38, 0.45),)), 0.0),
)
WALLS = ((0.86, 0.86, 0.82), (0.76, 0.8, 0.86), (0.86, 0.8, 0.74), (0.8, 0.84, 0.78), (0.7, 0.7, 0.72))


@dataclass
class Scene:
    """One seeded scene: the object's primitives, the room, lighting and the viewing ring."""

    seed: int
    label: int
    class_name: str
    object_prims: list
    room_prims: list
    light_dir: np.ndarray
    ambient: float
    diffuse: float
    gain: np.ndarray
    target: np.ndarray           # look-at point (centre of the object's bounding box)
    bound_radius: float          # radius of a sphere around ``target`` holding the object
    view_distance: float         # camera-to-target distance of the first ring
    azimuth0: float
    room_half: tuple = field(default=(4.0, 4.0, 3.0))

    @property
    def prims(self) -> list:
        return list(self.object_prims) + list(self.room_prims)


def make_scene(seed: int, label: int | None = None) -> Scene:
    """The scene of ``seed`` (class ``seed % NUM_CLASSES`` unless ``label`` is given)."""
    try:
        seed = int(seed)
    except (TypeError, ValueError):
        raise PwsError(f"scene seed must be an integer, got {seed!r}") from None
    require(seed >= 0, f"scene seed must be >= 0, got {seed}")
    if label is None:
        label = seed % NUM_CLASSES
    require(0 <= int(label) < NUM_CLASSES, f"class label must be in [0, {NUM_CLASSES}), got {label}")
    label = int(label)
    rng = np.random.default_rng([20240917, seed, label])

    brightness = rng.uniform(0.85, 1.1)
    hue_jit = rng.uniform(-0.06, 0.06, size=3)

    def col(rgb):
        c = np.asarray(rgb, dtype=np.float64) * brightness + hue_jit * 0.5
        return tuple(np.clip(c, 0.0, 1.0))

    scale = rng.uniform(0.85, 1.2)
    obj_local = _build_object(label, scale, col)
    yaw = rng.uniform(0, 2 * math.pi)
    offset = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 0.0])
    object_prims = [p.placed(rot_z(yaw), offset) for p in obj_local]

    # bounding box / sphere of the object from surface samples (own rng: independent of counts)
    brng = np.random.default_rng([7, seed])
    pts = np.concatenate([p.sample(1500, brng)[0] for p in object_prims])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    target = 0.5 * (lo + hi)
    bound = float(np.linalg.norm(pts - target, axis=1).max())

    # room: floor, ceiling and 4 walls (normals into the room)
    hx, hy, hz = rng.uniform(3.6, 4.6), rng.uniform(3.6, 4.6), rng.uniform(2.7, 3.2)
    fi = int(rng.integers(len(FLOORS)))
    (fkind, fcols), fgrain = FLOORS[fi]
    floor_tex = Texture(kind=fkind, colors=fcols, period=float(rng.uniform(0.3, 0.6)), axis=(1.0, 0.0, 0.0), grain=fgrain * 0.3)
    wall_col = WALLS[int(rng.integers(len(WALLS)))]
    wall_tex = Texture(kind="stripes", colors=(wall_col,) * 7 + (tuple(0.8 * np.asarray(wall_col)),), period=0.4, axis=(0.0, 1.0, 0.0), grain=0.04)
    ceil_tex = Texture(kind="solid", colors=((0.92, 0.92, 0.9),))
    room: list[Primitive] = [
        _at(Rect(texture=floor_tex, half_u=hx, half_v=hy), 0.0, 0.0, 0.0),
        _at(Rect(texture=ceil_tex, half_u=hx, half_v=hy), 0.0, 0.0, hz, R=rot_x(math.pi)),
    ]
    # wall local frame: x along the wall, y up (texture stripes along local y = height), z inward
    for ang, dist, half_u in ((0.0, hy, hx), (math.pi / 2, hx, hy), (math.pi, hy, hx), (-math.pi / 2, hx, hy)):
        Rw = rot_z(ang) @ rot_x(-math.pi / 2)  # local x along the wall, local y down, local z inward
        centre = rot_z(ang) @ np.array([0.0, -dist, hz / 2])
        room.append(_at(Rect(texture=wall_tex, half_u=half_u, half_v=hz / 2), *centre, R=Rw))

    el = math.radians(rng.uniform(35, 75))
    az = rng.uniform(0, 2 * math.pi)
    light = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    ambient = float(rng.uniform(0.38, 0.52))
    diffuse = float((1.0 - ambient) * rng.uniform(0.8, 1.0))
    gain = rng.uniform(0.93, 1.07, size=3)

    fill = rng.uniform(0.55, 0.85)  # fraction of the vertical half field of view the object spans
    half_fov = math.atan((DEFAULT_HEIGHT / 2) / (BASE_CAMERA.fy / 8))
    dist = bound / math.tan(fill * half_fov)
    dist = float(np.clip(dist, MIN_DISTANCE, MAX_DISTANCE / RING_DISTANCE_FACTORS[-1]))
    return Scene(seed=seed, label=label, class_name=CLASS_NAMES[label], object_prims=object_prims, room_prims=room,
                 light_dir=light, ambient=ambient, diffuse=diffuse, gain=gain, target=target, bound_radius=bound,
                 view_distance=dist, azimuth0=float(rng.uniform(0, 2 * math.pi)), room_half=(hx, hy, hz))


# ------------------------------------------------------------------------------------------------
# camera poses
# ------------------------------------------------------------------------------------------------
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


def orbit_pose(scene: Scene, azimuth: float, elevation: float, distance: float, roll: float = 0.0,
               target_offset=(0.0, 0.0, 0.0)) -> Pose:
    t = scene.target + np.asarray(target_offset, dtype=np.float64)
    C = t + distance * np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
    return look_at(C, t, roll)


def view_pose(scene: Scene, view_index: int) -> Pose:
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


def random_pose(scene: Scene, rng: np.random.Generator, jitter: float = 1.0) -> Pose:
    """A continuous random pose around the object (training views): any azimuth, elevation 8-40
    degrees, distance 0.9-1.35 x the ring distance, small roll and look-at offsets."""
    az = rng.uniform(0, 2 * math.pi)
    el = math.radians(rng.uniform(8.0, 40.0))
    dist = float(np.clip(scene.view_distance * rng.uniform(0.9, 1.35), MIN_DISTANCE, MAX_DISTANCE))
    roll = math.radians(rng.normal(0, 2.5 * jitter))
    off = rng.normal(0, 0.06 * jitter, size=3) * scene.bound_radius
    return orbit_pose(scene, az, el, dist, roll, off)


# ------------------------------------------------------------------------------------------------
# ray casting ("the real camera")
# ------------------------------------------------------------------------------------------------
def pixel_rays(intr: CameraIntrinsics) -> np.ndarray:
    """Ray directions (H*W, 3) in the optical frame through pixel centres, with z = 1 (so the ray
    parameter is the depth)."""
    H, W = intr.shape
    rows, cols = np.mgrid[0:H, 0:W]
    x = (cols.reshape(-1) - intr.cx) / intr.fx
    y = (rows.reshape(-1) - intr.cy) / intr.fy
    return np.stack([x, y, np.ones_like(x)], axis=1)


def shade(scene: Scene, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    lam = np.clip(normal @ scene.light_dir, 0.0, None)
    c = albedo * (scene.ambient + scene.diffuse * lam)[:, None] * scene.gain[None, :]
    return np.clip(c, 0.0, 1.0)


def _surface_colors(scene: Scene, prim: Primitive, p_local: np.ndarray, n_world: np.ndarray) -> np.ndarray:
    return shade(scene, prim.albedo(p_local), n_world)


def cast(scene: Scene, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of world rays ``origins + t dirs``: ``t`` (inf where none) and colour (N, 3)."""
    prims = scene.prims
    n = len(dirs)
    best_t = np.full(n, np.inf)
    best_k = np.full(n, -1, dtype=np.int64)
    hits = []
    for k, prim in enumerate(prims):
        t, nw, pl = prim.intersect(origins, dirs)
        hits.append((nw, pl))
        better = t < best_t
        best_t = np.where(better, t, best_t)
        best_k = np.where(better, k, best_k)
    color = np.zeros((n, 3))
    for k, prim in enumerate(prims):
        m = best_k == k
        if m.any():
            nw, pl = hits[k]
            color[m] = _surface_colors(scene, prim, pl[m], nw[m])
    return best_t, color


def raycast(scene: Scene, pose: Pose, intr: CameraIntrinsics, max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact RGB-D at pixel centres: ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W) float32 metres
    (0 where nothing is hit or beyond ``max_depth``)."""
    H, W = intr.shape
    d_cam = pixel_rays(intr)
    d_world = d_cam @ pose.R.T
    o = np.broadcast_to(pose.C, d_world.shape)
    t, color = cast(scene, o, d_world)
    valid = np.isfinite(t)
    if max_depth is not None:
        valid &= t <= max_depth
    depth = np.where(valid, t, 0.0).astype(np.float32).reshape(H, W)
    rgb = np.round(color * 255.0).astype(np.uint8).reshape(H, W, 3)
    return rgb, depth


# ------------------------------------------------------------------------------------------------
# dense surface sampling
# ------------------------------------------------------------------------------------------------
def _in_margin(pc: np.ndarray, intr: CameraIntrinsics, margin: float, z_near: float) -> np.ndarray:
    z = pc[:, 2]
    ok = z > z_near
    zs = np.where(ok, z, 1.0)
    u = intr.fx * pc[:, 0] / zs + intr.cx + 0.5
    v = intr.fy * pc[:, 1] / zs + intr.cy + 0.5
    mw, mh = margin * intr.width, margin * intr.height
    return ok & (u >= -mw) & (u <= intr.width + mw) & (v >= -mh) & (v <= intr.height + mh)


def _density(pc: np.ndarray, nc: np.ndarray, intr: CameraIntrinsics, spp: float, z_near: float) -> np.ndarray:
    """Samples per square metre so that a pixel footprint holds about ``spp`` samples (more on
    oblique surfaces, by up to a factor 1/0.35)."""
    z = np.maximum(pc[:, 2], z_near)
    ray = pc / np.maximum(np.linalg.norm(pc, axis=1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("ij,ij->i", ray, nc))
    return spp * intr.fx * intr.fy * np.maximum(cos, 0.35) / (z * z)


def dense_cloud(scene: Scene, pose: Pose, intr: CameraIntrinsics, *, samples_per_pixel: float = 6.0,
                margin: float = 0.15, z_near: float = 0.05, seed: int = 0, max_points: int = 2_000_000) -> Cloud:
    """The entire surface-sampled cloud seen from ``pose`` (optical frame), occluded parts included.

    Only surfaces within ``margin`` (fraction of the image size) of the view frustum are sampled;
    the density makes a fronto-parallel pixel footprint hold ``samples_per_pixel`` samples on
    average. Points inside another solid of the object are dropped. Deterministic in ``seed``.
    """
    require(samples_per_pixel > 0, f"samples_per_pixel must be positive, got {samples_per_pixel}")
    require(margin >= 0, f"margin must be >= 0, got {margin}")
    rng = np.random.default_rng([31337, int(seed)])
    Rt = pose.R
    pts_all, col_all = [], []
    total = 0

    def accept(prim: Primitive, pw, nw, pl, rho_max):
        pc = (pw - pose.C) @ Rt
        nc = nw @ Rt
        keep = _in_margin(pc, intr, margin, z_near)
        rho = _density(pc, nc, intr, samples_per_pixel, z_near)
        keep &= rng.uniform(0, 1, size=len(pc)) * rho_max < rho
        return pc[keep], _surface_colors(scene, prim, pl[keep], nw[keep]), pw[keep]

    for k, prim in enumerate(scene.prims):
        is_room = isinstance(prim, Rect)
        if is_room:
            batches = _rect_tiles(prim, pose, intr, margin, z_near, samples_per_pixel, rng)
        else:
            pw, nw, _ = prim.sample(4000, rng)
            pc = (pw - pose.C) @ Rt
            ok = _in_margin(pc, intr, margin * 1.5 + 0.05, z_near)
            if not ok.any():
                continue
            rho_max = float(_density(pc[ok], (nw @ Rt)[ok], intr, samples_per_pixel, z_near).max()) * 1.25
            n = int(rng.poisson(prim.area * rho_max))
            batches = [(n, rho_max, None)]
        for n, rho_max, region in batches:
            if n <= 0:
                continue
            require(total + n <= 20 * max_points, "dense cloud would be too large: camera too close to a surface")
            if region is None:
                pw, nw, pl = prim.sample(n, rng)
            else:
                pl = region(n)
                pw = prim.to_world(pl)
                nw = np.broadcast_to(prim.R[:, 2], pw.shape)
            pc, cc, pw_kept = accept(prim, pw, nw, pl, rho_max)
            if not is_room:
                inside = np.zeros(len(pw_kept), dtype=bool)
                for j, other in enumerate(scene.object_prims):
                    if j != k:
                        inside |= other.contains(pw_kept, tol=1e-6)
                pc, cc = pc[~inside], cc[~inside]
            pts_all.append(pc)
            col_all.append(cc)
            total += n
    points = np.concatenate(pts_all) if pts_all else np.zeros((0, 3))
    colors = np.concatenate(col_all) if col_all else np.zeros((0, 3))
    require(len(points) <= max_points, f"dense cloud has {len(points)} points, more than max_points={max_points}")
    return Cloud(points, colors.astype(np.float32))


def _rect_tiles(rect: Rect, pose: Pose, intr, margin, z_near, spp, rng, tile: float = 0.2):
    """Split a rectangle into tiles; for each tile seen within the margin return
    ``(n_candidates, rho_max, sampler)`` with a per-tile density bound."""
    nu = max(1, int(math.ceil(2 * rect.half_u / tile)))
    nv = max(1, int(math.ceil(2 * rect.half_v / tile)))
    du, dv = 2 * rect.half_u / nu, 2 * rect.half_v / nv
    g = np.linspace(0.0, 1.0, 5)
    gu, gv = np.meshgrid(g, g, indexing="ij")
    iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    iu, iv = iu.reshape(-1), iv.reshape(-1)
    u0 = -rect.half_u + iu * du
    v0 = -rect.half_v + iv * dv
    # grid points of every tile: (T, 25, 3) local
    gx = u0[:, None] + gu.reshape(1, -1) * du
    gy = v0[:, None] + gv.reshape(1, -1) * dv
    pl = np.stack([gx, gy, np.zeros_like(gx)], axis=-1).reshape(-1, 3)
    pw = rect.to_world(pl)
    pc = (pw - pose.C) @ pose.R
    nc = np.broadcast_to(rect.R[:, 2] @ pose.R, pc.shape)
    ok = _in_margin(pc, intr, margin * 1.5 + 0.1, z_near).reshape(len(iu), -1)
    rho = _density(pc, nc, intr, spp, z_near).reshape(len(iu), -1)
    rho = np.where(ok, rho, 0.0)
    out = []
    for t in np.nonzero(ok.any(axis=1))[0]:
        rho_max = float(rho[t].max()) * 1.5
        n = int(rng.poisson(du * dv * rho_max))
        a, b = float(u0[t]), float(v0[t])

        def sampler(m, a=a, b=b):
            return np.stack([rng.uniform(a, a + du, m), rng.uniform(b, b + dv, m), np.zeros(m)], axis=1)

        out.append((n, rho_max, sampler))
    return out


# ------------------------------------------------------------------------------------------------
# views
# ------------------------------------------------------------------------------------------------
@dataclass
class View:
    """One rendered view of a scene and everything PwS needs about it."""

    rgb: np.ndarray             # (H, W, 3) uint8
    depth: np.ndarray           # (H, W) float32 metres, 0 where invalid
    intrinsics: CameraIntrinsics
    one_frame: Cloud            # one point per valid depth pixel (core cloud_from_rgbd)
    dense: Cloud | None         # entire surface-sampled cloud in this view's optical frame
    label: int
    class_name: str
    scene_seed: int
    view_index: int
    pose: Pose


def render_view(scene_seed: int, view_index: int, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT,
                *, dense: bool = True, samples_per_pixel: float = 6.0, max_depth: float | None = None) -> View:
    """RGB-D, one-frame cloud, dense cloud and label of canonical view ``view_index`` of scene
    ``scene_seed`` (deterministic)."""
    scene = make_scene(scene_seed)
    intr = default_intrinsics(width, height)
    pose = view_pose(scene, view_index)
    rgb, depth = raycast(scene, pose, intr, max_depth=max_depth)
    one = cloud_from_rgbd(depth, rgb, intr)
    dcloud = dense_cloud(scene, pose, intr, samples_per_pixel=samples_per_pixel, seed=scene.seed * NUM_VIEWS + int(view_index)) if dense else None
    return View(rgb=rgb, depth=depth, intrinsics=intr, one_frame=one, dense=dcloud, label=scene.label,
                class_name=scene.class_name, scene_seed=scene.seed, view_index=int(view_index), pose=pose)


def dense_cloud_for(scene_seed: int, view_index: int, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT,
                    samples_per_pixel: float = 6.0) -> Cloud:
    """The entire dense cloud of a recorded frame (``scene_seed``, ``view_index`` from its ground
    truth), regenerated exactly, in that frame's camera optical frame."""
    scene = make_scene(scene_seed)
    intr = default_intrinsics(width, height)
    return dense_cloud(scene, view_pose(scene, view_index), intr, samples_per_pixel=samples_per_pixel,
                       seed=scene.seed * NUM_VIEWS + int(view_index))

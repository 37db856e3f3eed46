"""A seeded procedural indoor world: one object of one of :data:`~pws_ros.sim.objects.CLASS_NAMES`
(:mod:`pws_ros.sim.objects`) in a textured room.

* :func:`make_scene` builds a scene from an integer seed (the class is ``seed % NUM_CLASSES``
  unless given); everything else (size, yaw, colours, lighting, room) comes from the seed.
* :mod:`pws_ros.sim.poses` places the camera on rings around the object (``view_pose``) or at a
  continuous random pose (``random_pose``, for training).
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
from .geometry import Primitive, Rect, Texture, rot_x, rot_z
from .objects import CLASS_NAMES, NUM_CLASSES, at, build_object
from .poses import MAX_DISTANCE, MIN_DISTANCE, NUM_VIEWS, RING_DISTANCE_FACTORS, Pose, view_pose

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
    obj_local = build_object(label, scale, col)
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
        at(Rect(texture=floor_tex, half_u=hx, half_v=hy), 0.0, 0.0, 0.0),
        at(Rect(texture=ceil_tex, half_u=hx, half_v=hy), 0.0, 0.0, hz, R=rot_x(math.pi)),
    ]
    # wall local frame: x along the wall, y up (texture stripes along local y = height), z inward
    for ang, dist, half_u in ((0.0, hy, hx), (math.pi / 2, hx, hy), (math.pi, hy, hx), (-math.pi / 2, hx, hy)):
        Rw = rot_z(ang) @ rot_x(-math.pi / 2)  # local x along the wall, local y down, local z inward
        centre = rot_z(ang) @ np.array([0.0, -dist, hz / 2])
        room.append(at(Rect(texture=wall_tex, half_u=half_u, half_v=hz / 2), *centre, R=Rw))

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

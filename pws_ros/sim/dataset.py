"""Labelled training / evaluation images of the procedural world (cached as .npz in a cache dir).

Training views use continuous random poses around training scenes (scene seeds from
:data:`TRAIN_SEED_BASE` on, disjoint from the held-out seeds ``0 ...`` that the demo recording and
the evaluation use). A fraction ``move_prob`` of the training views is re-rendered from its
one-frame cloud under a small random camera motion along a random axis (core renderer, holes =
``background``), so the classifier gets used to moved views as PwS renders them.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from ..core.cloud import cloud_from_rgbd
from ..core.errors import require
from ..core.motion import AXES
from ..core.render import render
from .objects import NUM_CLASSES
from .poses import NUM_VIEWS, random_pose, view_pose
from .world import default_intrinsics, make_scene, raycast

TRAIN_SEED_BASE = 1_000_000
DATA_VERSION = 1
# half-range of the random camera motion used for augmentation, per axis (metres / radians)
MOTION_RANGE = {"tx": 0.03, "ty": 0.03, "tz": 0.06, "rx": math.radians(1.5), "ry": math.radians(1.5), "rz": math.radians(3.0)}


def default_cache_dir() -> Path:
    return Path(os.environ.get("PWS_SIM_CACHE", Path(tempfile.gettempdir()) / "pws_sim_cache"))


def moved_view(rgb: np.ndarray, depth: np.ndarray, intr, axis: str, alpha: float, background: float = 0.0) -> np.ndarray:
    """The one-frame cloud of ``(rgb, depth)`` rendered after moving the camera by ``alpha`` along
    ``axis`` (uint8 (H, W, 3))."""
    cloud = cloud_from_rgbd(depth, rgb, intr)
    frame = render(cloud, intr, axis, [alpha], background=background)[0]
    return np.round(frame * 255.0).astype(np.uint8)


def _train_chunk(args) -> tuple[np.ndarray, np.ndarray]:
    seeds, views_per_scene, width, height, move_prob, rng_seed = args
    intr = default_intrinsics(width, height)
    rng = np.random.default_rng(rng_seed)
    imgs, labels = [], []
    for s in seeds:
        scene = make_scene(int(s))
        for _ in range(views_per_scene):
            rgb, depth = raycast(scene, random_pose(scene, rng), intr)
            if rng.uniform() < move_prob:
                axis = AXES[int(rng.integers(len(AXES)))]
                alpha = float(rng.uniform(-1, 1) * MOTION_RANGE[axis])
                rgb = moved_view(rgb, depth, intr, axis, alpha)
            imgs.append(rgb)
            labels.append(scene.label)
    return np.stack(imgs), np.asarray(labels, dtype=np.int64)


def _eval_chunk(args) -> tuple[np.ndarray, np.ndarray]:
    seeds, views, width, height = args
    intr = default_intrinsics(width, height)
    imgs, labels = [], []
    for s in seeds:
        scene = make_scene(int(s))
        for v in views:
            rgb, _ = raycast(scene, view_pose(scene, int(v)), intr)
            imgs.append(rgb)
            labels.append(scene.label)
    return np.stack(imgs), np.asarray(labels, dtype=np.int64)


def _run(fn, jobs, workers: int):
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # fork after torch/OpenMP use can hang the children
        with ctx.Pool(workers) as pool:
            parts = pool.map(fn, jobs)
    else:
        parts = [fn(j) for j in jobs]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _cached(key: dict, build, cache_dir: Path | None):
    if cache_dir is None:
        return build()
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    path = Path(cache_dir) / f"{key['kind']}_{digest}.npz"
    if path.is_file():
        try:
            with np.load(path) as d:
                return d["images"], d["labels"]
        except Exception:  # corrupt cache: rebuild
            pass
    images, labels = build()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, images=images, labels=labels)
    os.replace(tmp, path)
    return images, labels


def training_set(num_scenes: int, views_per_scene: int = 4, *, seed: int = 0, width: int = 160, height: int = 90,
                 move_prob: float = 0.4, workers: int = 1, cache_dir: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(images (N, H, W, 3) uint8, labels (N,))`` from ``num_scenes`` training scenes (classes
    balanced: consecutive seeds cycle through the classes)."""
    require(num_scenes > 0 and views_per_scene > 0, "training set needs at least one scene and one view")
    seeds = TRAIN_SEED_BASE + int(seed) * 100_000 + np.arange(int(num_scenes))
    chunk = max(1, int(math.ceil(len(seeds) / max(1, 4 * workers))))
    jobs = [(seeds[i : i + chunk], int(views_per_scene), int(width), int(height), float(move_prob), [int(seed), i])
            for i in range(0, len(seeds), chunk)]
    key = {"kind": "train", "v": DATA_VERSION, "n": int(num_scenes), "vps": int(views_per_scene), "seed": int(seed),
           "w": int(width), "h": int(height), "move": float(move_prob), "chunk": chunk}
    return _cached(key, lambda: _run(_train_chunk, jobs, workers), cache_dir)


def heldout_set(num_scenes_per_class: int, views=(0, 5, 10, 15, 20), *, width: int = 160, height: int = 90,
                workers: int = 1, cache_dir: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Canonical views of the held-out scenes ``0 .. NUM_CLASSES * num_scenes_per_class - 1``."""
    require(num_scenes_per_class > 0, "held-out set needs at least one scene per class")
    views = tuple(int(v) % NUM_VIEWS for v in views)
    seeds = np.arange(NUM_CLASSES * int(num_scenes_per_class))
    chunk = max(1, int(math.ceil(len(seeds) / max(1, 4 * workers))))
    jobs = [(seeds[i : i + chunk], views, int(width), int(height)) for i in range(0, len(seeds), chunk)]
    key = {"kind": "heldout", "v": DATA_VERSION, "n": int(num_scenes_per_class), "views": list(views), "w": int(width), "h": int(height)}
    return _cached(key, lambda: _run(_eval_chunk, jobs, workers), cache_dir)

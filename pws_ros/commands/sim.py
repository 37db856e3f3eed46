"""``pws sim``: the procedural RGB-D world (record a rosbag2 bag, export one view, list classes)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..core.errors import PwsError, require
from . import SUMMARIES
from .common import add_command_group


def register(subparsers) -> None:
    sub = add_command_group(subparsers, "sim", SUMMARIES["sim"],
                            "The seeded procedural world of pws_ros.sim (one object of one of 12 classes in a textured room).",
                            ("record", "view", "classes"))

    text = "write views as a rosbag2 bag (RGB, CameraInfo, aligned depth, organized cloud unless --no-points, ground truth)"
    r = sub.add_parser("record", help=text, description=f"pws sim record: {text}.")
    r.add_argument("--out", required=True, help="bag directory to create (must not exist)")
    r.add_argument("--frames", type=int, default=36, help="number of frames (default 36)")
    r.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (default mcap, zstd chunks)")
    r.add_argument("--seed", type=int, default=0, help="first scene seed; scenes seed, seed+1, ... (class = scene seed %% 12)")
    r.add_argument("--views-per-scene", type=int, default=3, help="consecutive frames per scene (default 3)")
    r.add_argument("--width", type=int, default=160, help="image width in pixels (default 160)")
    r.add_argument("--height", type=int, default=90, help="image height in pixels (default 90)")
    r.add_argument("--rate", type=float, default=10.0, help="frame rate of the stamps in Hz (default 10)")
    r.add_argument("--max-depth", type=float, default=None, help="depth beyond this (m) is invalid (0 / NaN), like a sensor's range (default: none)")
    r.add_argument("--no-compression", action="store_true", help="MCAP without zstd chunk compression")
    r.add_argument("--no-points", action="store_true",
                   help="leave out the organized PointCloud2 (RGB-D + CameraInfo + ground truth only; 16 B a pixel less)")
    r.set_defaults(func=run)

    text = "export one view: rgb.png, depth.png (16-bit mm), camera.yaml, cloud.npz, dense_cloud.npz, view.json"
    v = sub.add_parser("view", help=text, description=f"pws sim view: {text}.")
    v.add_argument("--seed", type=int, required=True, help="scene seed (class = seed %% 12)")
    v.add_argument("--view", type=int, default=0, help="canonical view index 0..23 (3 rings x 8 azimuths; default 0)")
    v.add_argument("--out-dir", required=True, help="output folder (created if missing)")
    v.add_argument("--width", type=int, default=160, help="image width in pixels (default 160)")
    v.add_argument("--height", type=int, default=90, help="image height in pixels (default 90)")
    v.add_argument("--samples-per-pixel", type=float, default=6.0, help="dense cloud density (samples per pixel footprint; default 6)")
    v.add_argument("--no-dense", action="store_true", help="skip the dense cloud")
    v.set_defaults(func=run)

    c = sub.add_parser("classes", help="print the class names, one per line", description="pws sim classes: print the class names, one per line.")
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cmd = getattr(args, "sim_command", None)
    if cmd == "record":
        return _record(args)
    if cmd == "view":
        return _view(args)
    if cmd == "classes":
        from ..sim import CLASS_NAMES

        print("\n".join(CLASS_NAMES))
        return 0
    raise PwsError(f"unknown sim command {cmd!r}")


def _record(args) -> int:
    from ..sim.record import record

    require(args.rate > 0, f"--rate must be positive, got {args.rate}")
    require(args.max_depth is None or args.max_depth > 0, f"--max-depth must be positive, got {args.max_depth}")

    def progress(i, n, view):
        if i == n or i % 10 == 0:
            print(f"  frame {i}/{n}: scene {view.scene_seed} view {view.view_index} ({view.class_name})", flush=True)

    out = record(args.out, args.frames, storage=args.storage, seed=args.seed, width=args.width, height=args.height,
                 views_per_scene=args.views_per_scene, period_s=1.0 / args.rate, max_depth=args.max_depth,
                 compress=not args.no_compression, points=not args.no_points, progress=progress)
    size = sum(f.stat().st_size for f in Path(out).iterdir() if f.is_file())
    what = "RGB-D, CameraInfo, ground truth" if args.no_points else "RGB-D, CameraInfo, PointCloud2, ground truth"
    print(f"wrote {out} ({args.frames} frames {args.width}x{args.height}, {what}; {args.storage}, {size / 1e6:.2f} MB)")
    return 0


def _view(args) -> int:
    import cv2

    from ..sim import render_view

    view = render_view(args.seed, args.view, args.width, args.height, dense=not args.no_dense, samples_per_pixel=args.samples_per_pixel)
    out = Path(args.out_dir)
    require(not out.exists() or out.is_dir(), f"--out-dir {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out / "rgb.png"), cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR)):
        raise PwsError(f"cannot write {out / 'rgb.png'}")
    from ..sim.record import depth_to_mm

    cv2.imwrite(str(out / "depth.png"), depth_to_mm(view.depth))
    view.intrinsics.to_yaml(out / "camera.yaml")
    view.one_frame.save(out / "cloud.npz")
    files = ["rgb.png", "depth.png", "camera.yaml", "cloud.npz"]
    if view.dense is not None:
        view.dense.save(out / "dense_cloud.npz")
        files.append("dense_cloud.npz")
    info = {"label": view.label, "class_name": view.class_name, "scene_seed": view.scene_seed, "view_index": view.view_index,
            "width": view.intrinsics.width, "height": view.intrinsics.height, "one_frame_points": len(view.one_frame),
            "dense_points": None if view.dense is None else len(view.dense), "depth_min_m": float(view.depth[view.depth > 0].min()) if (view.depth > 0).any() else None,
            "depth_max_m": float(view.depth.max())}
    (out / "view.json").write_text(json.dumps(info, indent=2) + "\n")
    files.append("view.json")
    print(f"scene {view.scene_seed} view {view.view_index}: {view.class_name} (label {view.label}); wrote {', '.join(files)} to {out}")
    return 0

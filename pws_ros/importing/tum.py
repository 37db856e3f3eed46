"""Convert a TUM-format RGB-D sequence into a rosbag2 (MCAP) recording that ``pws replay`` reads.

    python -m pws_ros.bench.rgbd_sequence SRC OUT [--frames N] [--calibration default|tum1|tum2|tum3]

``SRC`` is a folder in the layout of the TUM RGB-D benchmark: ``rgb/`` and ``depth/`` PNGs (colour
8-bit, depth 16-bit in units of 1/5000 m, 0 = no depth) and ``associations.txt`` (lines
``t_depth depth/x.png t_rgb rgb/y.png``, or the reverse order) or ``rgb.txt`` + ``depth.txt``
(then each colour image takes the depth image nearest in time). ``OUT`` becomes a rosbag2
directory with, per pair: ``/camera/aligned_depth_to_color/image_raw`` (16UC1, millimetres),
``/camera/color/image_raw`` (rgb8) and ``/camera/color/camera_info``, stamped with the colour
image's time. The depth is taken as registered to the colour camera, as the TUM sequences are.
Intrinsics: the TUM calibration of freiburg1/2/3 or the TUM default (fx = fy = 525, cx = 319.5,
cy = 239.5) for unknown cameras; the images are used as recorded (no undistortion).
For benchmarks on public recordings (the data stays outside the repository).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.errors import PwsError, require

DEPTH_SCALE = 5000.0   # TUM: depth PNG value / 5000 = metres
CALIBRATION = {        # fx, fy, cx, cy (TUM RGB-D benchmark, "intrinsic camera calibration")
    "default": (525.0, 525.0, 319.5, 239.5),
    "tum1": (517.3, 516.5, 318.6, 255.3),
    "tum2": (520.9, 521.0, 325.1, 249.7),
    "tum3": (535.4, 539.2, 320.1, 247.6),
}
TOPICS = {"depth": "/camera/aligned_depth_to_color/image_raw", "color": "/camera/color/image_raw",
          "info": "/camera/color/camera_info"}


def _read_list(path: Path) -> list[tuple[float, str]]:
    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            out.append((float(parts[0]), parts[1]))
        except (IndexError, ValueError):
            raise PwsError(f"{path}:{n}: expected 'timestamp file', got {line!r}") from None
    return out


def pairs(src: Path) -> list[tuple[float, Path, Path]]:
    """``(colour time, depth png, colour png)`` of the sequence, in time order (pairs whose files are
    missing, e.g. a folder holding part of a sequence, are left out)."""
    src = Path(src)
    require(src.is_dir(), f"{src} is not a folder")
    assoc = src / "associations.txt"
    out = []
    if assoc.is_file():
        for n, line in enumerate(assoc.read_text().splitlines(), 1):
            parts = line.split()
            if not parts or line.startswith("#"):
                continue
            require(len(parts) >= 4, f"{assoc}:{n}: expected 't1 file1 t2 file2', got {line!r}")
            (t1, f1), (t2, f2) = (parts[0], parts[1]), (parts[2], parts[3])
            if f1.startswith("rgb"):
                (t1, f1), (t2, f2) = (t2, f2), (t1, f1)
            try:
                out.append((float(t2), src / f1, src / f2))
            except ValueError:
                raise PwsError(f"{assoc}:{n}: bad timestamp in {line!r}") from None
    else:
        require((src / "rgb.txt").is_file() and (src / "depth.txt").is_file(),
                f"{src} has neither associations.txt nor rgb.txt + depth.txt (the TUM RGB-D layout)")
        depth = _read_list(src / "depth.txt")
        require(bool(depth), f"{src / 'depth.txt'} lists no image")
        dt = np.array([t for t, _ in depth])
        for t, f in _read_list(src / "rgb.txt"):
            j = int(np.argmin(np.abs(dt - t)))
            out.append((t, src / depth[j][1], src / f))
    out = [p for p in out if p[1].is_file() and p[2].is_file()]
    require(bool(out), f"{src}: no colour/depth pair whose two files exist")
    return sorted(out, key=lambda p: p[0])


def convert(src: Path, out: Path, *, frames: int | None = None, calibration: str = "default", overwrite: bool = False) -> int:
    """Write the bag; returns the number of frames written."""
    import cv2

    from ..bagio import BagWriter, prepare_output
    from ..bridge import msgbuild

    require(calibration in CALIBRATION, f"unknown calibration {calibration!r}: one of {', '.join(CALIBRATION)}")
    todo = pairs(src)[: frames or None]
    types = msgbuild.rosbags_types()
    prepare_output(Path(out), overwrite)
    writer = BagWriter(Path(out), typestore=types.typestore).open()
    n = 0
    try:
        for t, dpath, cpath in todo:
            depth = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
            bgr = cv2.imread(str(cpath), cv2.IMREAD_COLOR)
            require(depth is not None and depth.dtype == np.uint16 and depth.ndim == 2, f"{dpath}: not a 16-bit depth PNG")
            require(bgr is not None, f"{cpath}: not an image")
            require(depth.shape == bgr.shape[:2], f"{dpath} and {cpath} differ in size")
            h, w = depth.shape
            fx, fy, cx, cy = CALIBRATION[calibration]
            intr = CameraIntrinsics(w, h, fx, fy, cx, cy, "camera_color_optical_frame")
            mm = np.round(depth.astype(np.float64) * (1000.0 / DEPTH_SCALE))
            mm = np.where(depth == 0, 0, np.clip(mm, 0, 65535)).astype(np.uint16)
            stamp = int(round(t * 1e9))
            header = msgbuild.make_header(types, stamp, intr.frame_id)
            writer.write(TOPICS["info"], msgbuild.camera_info_from_intrinsics(header, intr, types), stamp)
            writer.write(TOPICS["depth"], msgbuild.image_from_numpy(header, mm, types, "16UC1"), stamp)
            writer.write(TOPICS["color"], msgbuild.image_from_numpy(header, bgr[..., ::-1].copy(), types, "rgb8"), stamp)
            n += 1
    finally:
        writer.close()
    return n


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pws_ros.bench.rgbd_sequence", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, help="TUM-format folder (rgb/, depth/, associations.txt or rgb.txt + depth.txt)")
    p.add_argument("out", type=Path, help="output rosbag2 directory")
    p.add_argument("--frames", type=int, default=None, help="convert the first N pairs only")
    p.add_argument("--calibration", choices=sorted(CALIBRATION), default="default",
                   help="intrinsics: TUM freiburg1/2/3 or the TUM default 525/525/319.5/239.5 (default)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    a = p.parse_args(argv)
    try:
        n = convert(a.src, a.out, frames=a.frames, calibration=a.calibration, overwrite=a.overwrite)
    except PwsError as exc:
        print(f"rgbd_sequence: error: {exc}", file=sys.stderr)
        return 2
    print(f"{a.out}: {n} frame(s) of {a.src}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

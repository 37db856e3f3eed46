"""A TUM-format RGB-D sequence to a rosbag2 (MCAP) recording (``pws import tum``).

``SRC`` is a folder in the layout of the TUM RGB-D benchmark: ``rgb/`` and ``depth/`` PNGs (colour
8-bit, depth 16-bit in units of 1/5000 m, 0 = no depth) and ``associations.txt`` (lines
``t_depth depth/x.png t_rgb rgb/y.png``, or the reverse order) or ``rgb.txt`` + ``depth.txt``
(then each colour image takes the depth image nearest in time). Each pair becomes one frame of
:mod:`.write` (the topics ``pws replay`` reads), stamped with the colour image's time. The depth is
taken as registered to the colour camera, as the TUM sequences are. Intrinsics: the TUM
calibration of freiburg1/2/3 or the TUM default (fx = fy = 525, cx = 319.5, cy = 239.5) for unknown
cameras; the images are used as recorded (no undistortion). No labels (no ground truth).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import PwsError, require
from .write import TOPICS, ImportFrame, Pinhole, write_frames

DEPTH_SCALE = 1.0 / 5000.0   # TUM: depth PNG value / 5000 = metres
CALIBRATION = {        # fx, fy, cx, cy (TUM RGB-D benchmark, "intrinsic camera calibration")
    "default": (525.0, 525.0, 319.5, 239.5),
    "tum1": (517.3, 516.5, 318.6, 255.3),
    "tum2": (520.9, 521.0, 325.1, 249.7),
    "tum3": (535.4, 539.2, 320.1, 247.6),
}


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


def convert(src: Path, out: Path, *, frames: int | None = None, calibration: str = "default", overwrite: bool = False,
            progress: Any = None) -> int:
    """Write the bag (whole or not at all); returns the number of frames written."""
    require(calibration in CALIBRATION, f"unknown calibration {calibration!r}: one of {', '.join(CALIBRATION)}")
    todo = pairs(src)[: frames or None]
    items = [ImportFrame(int(round(t * 1e9)), cpath, dpath, DEPTH_SCALE) for t, dpath, cpath in todo]
    write_frames(items, Path(out), Pinhole(*CALIBRATION[calibration], source=f"TUM calibration {calibration}"),
                 overwrite=overwrite, progress=progress)
    return len(items)


__all__ = ["CALIBRATION", "DEPTH_SCALE", "TOPICS", "convert", "pairs"]

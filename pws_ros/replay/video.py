"""``pws replay --video PATH``: the overlay picture (:func:`pws_ros.bridge.overlay.draw_overlay`) of every
replayed frame, the picture the nodes publish on ``certification/overlay``, as a video or a folder of PNGs.

``PATH`` ending in ``.mp4`` (``cv2.VideoWriter``, ``mp4v``) or ``.avi`` (``MJPG``): one video at ``fps``
frames per second, in stamp order; any other path without a suffix: a folder with one lossless PNG per
frame, ``<index>_<stamp_ns>.png`` (index from 0, six digits). Nothing is half written: everything goes to
a temporary name beside ``PATH`` (``.<name>.partial.mp4``, ``.<name>.partial/``) and is renamed to ``PATH``
by :meth:`OverlayVideo.close`, which a replay calls at its end, after a SIGINT/SIGTERM too (the frames
done, as the output bag). After a SIGKILL only the temporary name is left. A frame's picture is written
with the frame's other outputs (:meth:`pws_ros.replay.run.Replay._commit`): the frame in flight when a
replay is stopped is in neither.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import PwsError, require, require_creatable

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}
DEFAULT_FPS = 10.0


class OverlayVideo:
    """The overlay pictures of a replay, written to ``path`` (module docstring)."""

    def __init__(self, path: str | Path, *, overwrite: bool = False, fps: float = DEFAULT_FPS):
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        require(suffix in VIDEO_CODECS or not suffix,
                f"--video {self.path}: give a .mp4 or .avi file, or a folder (a path without a suffix) for PNGs")
        require(fps > 0 and np.isfinite(fps), f"--video-fps must be a positive number, got {fps}")
        self.is_video = suffix in VIDEO_CODECS
        self.fps = float(fps)
        self.overwrite = overwrite
        if self.path.exists():
            require(overwrite, f"--video {self.path} already exists: choose another path or pass --overwrite")
            require(self._replaceable(), f"--video {self.path}: --overwrite replaces a video file or a folder of PNG files "
                                         "only, and this is neither")
        require_creatable(self.path, "--video")   # (a file in place of its folder, or a folder not writable)
        require(self.path.parent.is_dir(), f"--video {self.path}: its folder {self.path.parent} does not exist")
        name = f".{self.path.stem}.partial{self.path.suffix}" if self.is_video else f".{self.path.name}.partial"
        self.partial = self.path.parent / name
        self.frames = 0
        self._writer: Any = None
        self._size: tuple[int, int] | None = None   # (W, H) of the video, from its first picture
        self._pending: tuple[np.ndarray, int] | None = None

    def _replaceable(self) -> bool:
        if self.is_video:
            return self.path.is_file()
        return self.path.is_dir() and all(p.is_file() and p.suffix.lower() == ".png" for p in self.path.iterdir())

    def hold(self, image: np.ndarray, stamp_ns: int) -> None:
        """The picture (uint8 RGB) of the frame in flight: written by :meth:`commit`, dropped by :meth:`discard`."""
        self._pending = (image, int(stamp_ns))

    def discard(self) -> None:
        self._pending = None

    def commit(self) -> None:
        """Write the picture of the frame just finished (if any)."""
        if self._pending is None:
            return
        image, stamp = self._pending
        self._pending = None
        self.add(image, stamp)

    def add(self, image: np.ndarray, stamp_ns: int) -> None:
        import cv2

        bgr = np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[:, :, ::-1])
        if self.is_video:
            if self._writer is None:
                self._size = (bgr.shape[1], bgr.shape[0])
                self._writer = cv2.VideoWriter(str(self.partial), cv2.VideoWriter_fourcc(*VIDEO_CODECS[self.path.suffix.lower()]),
                                               self.fps, self._size)
                if not self._writer.isOpened():
                    raise PwsError(f"--video {self.path}: OpenCV cannot write this video (codec "
                                   f"{VIDEO_CODECS[self.path.suffix.lower()]}); give a folder for PNGs instead")
            if (bgr.shape[1], bgr.shape[0]) != self._size:   # e.g. a frame without a view among frames with one
                bgr = cv2.resize(bgr, self._size, interpolation=cv2.INTER_NEAREST)
            self._writer.write(bgr)
        else:
            self.partial.mkdir(exist_ok=True)
            name = f"{self.frames:06d}_{int(stamp_ns)}.png"
            require(cv2.imwrite(str(self.partial / name), bgr), f"--video {self.path}: could not write {name}")
        self.frames += 1

    def close(self) -> Path | None:
        """Finish and rename the output to ``path``; returns it (None, and nothing left, when no frame was written)."""
        self._pending = None
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self.frames == 0:
            _remove(self.partial)
            return None
        if self.path.exists() and self.overwrite:
            _remove(self.path)
        os.replace(self.partial, self.path)
        return self.path


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def overlay_picture(engine: Any, certificates: list[Any], stamp_ns: int, result: Any = None, cloud: Any = None,
                    dense: Any = None, warn: Any = None) -> np.ndarray:
    """The overlay of one replayed frame: its α = 0 view (from its previews, else rendered from the cloud it was
    certified on: ``engine.source_cloud(cloud, dense)``) and its certificates. A view that cannot be made is
    left blank, and said once through ``warn(key, message)``."""
    from ..bridge.overlay import draw_overlay
    from ..bridge.preview import alpha0_view

    view = None
    if result is not None:
        try:
            view = alpha0_view(result, engine.source_cloud(cloud, dense) if cloud is not None else None, device=engine.device)
        except Exception as exc:  # noqa: BLE001 - the picture still shows the verdict
            if warn is not None:
                warn("overlay-view", f"--video: frame {stamp_ns} has no view ({type(exc).__name__}: {exc}); drawn blank")
    return draw_overlay(view, certificates, stamp_ns)


__all__ = ["DEFAULT_FPS", "OverlayVideo", "VIDEO_CODECS", "overlay_picture"]

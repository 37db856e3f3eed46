"""The frames a tuning run learns from, cached on disk: per input frame the reduced alpha = 0 frame of
the imaging model and ``views`` renders of the same one-frame cloud at random motions within the
configured radii (exactly what the certifier feeds the classifier, before the noise), the teacher's
probabilities on the clean alpha = 0 frame and the frame's ground truth, if any.

One folder per recording in the work folder: ``views.u8`` ((frames, 1 + views, H, W, 3) uint8, the
frames rounded to 1/255: at most 1/510 off, under 1% of any useful sigma), ``probs.f32`` ((frames, C)
float32), ``frames.jsonl`` (one line per cached frame, written last: the commit of that frame) and
``done.json`` when the recording is complete. Frames are appended one by one (memory stays bounded:
one cloud at a time), so an interrupted preparation resumes at the next frame.
"""
from __future__ import annotations

import fnmatch
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..core.errors import PwsError, require
from ..core.imaging import make_renderer
from .frames import RecordingFrames

CACHE_FORMAT = "pws_ros-finetune-cache-2"


def derive(seed: int, *parts: int) -> int:
    """A 63-bit seed from ``seed`` and integer parts (numpy SeedSequence): independent streams per use."""
    entropy = [int(seed) & 0xFFFFFFFFFFFFFFFF] + [int(p) & 0xFFFFFFFFFFFFFFFF for p in parts]
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0] >> np.uint64(1))


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path`` and rename it over ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


@dataclass
class RecordingCache:
    """The cached frames of one recording (read-only views into the files)."""

    index: int
    bag: str
    folder: Path
    views: np.ndarray            # (N, 1 + V, H, W, 3) uint8 memmap; view 0 is alpha = 0
    probs: np.ndarray            # (N, C) float32, the teacher on the clean alpha = 0 frame
    frames: list[dict]           # per frame: index, stamp_ns, truth_label, truth_class, teacher, motions
    info: dict = field(default_factory=dict)

    @property
    def count(self) -> int:
        return len(self.frames)

    def split(self, holdout: float) -> tuple[range, range]:
        """(train, held out): the last ``ceil(holdout * N)`` frames (by time) are held out."""
        n = self.count
        k = int(math.ceil(holdout * n - 1e-9))
        require(n >= 2 and 1 <= k < n,
                f"recording {self.bag} gave {n} usable frame(s): too few to hold the last {holdout:.0%} out and train on the "
                "rest (record longer, lower --stride, or raise --max-frames)")
        return range(0, n - k), range(n - k, n)


def split_by_clip(caches: list["RecordingCache"], patterns: list[str]) -> list[tuple[list[int], list[int]]]:
    """Per recording (train, held out): a frame is held out when its clip (ground truth ``clip``) matches
    one of ``patterns`` (fnmatch globs; ``clip04`` also matches ``*/clip04``): a clip is either trained on
    or held out, never both. PwsError when a frame has no clip, a pattern matches nothing, or either side
    would be empty."""
    used = {p: 0 for p in patterns}
    out = []
    for c in caches:
        train, held = [], []
        for k, f in enumerate(c.frames):
            clip = f.get("clip", "")
            require(bool(clip), f"recording {c.bag}: frame {f['stamp_ns']} has no clip on its ground truth: --holdout-clips "
                                "needs recordings made by `pws import frames` (or ground truth with a clip value)")
            hit = [p for p in patterns if fnmatch.fnmatchcase(clip, p) or fnmatch.fnmatchcase(clip, "*/" + p)]
            for p in hit:
                used[p] += 1
            (held if hit else train).append(k)
        out.append((train, held))
    unused = [p for p, n in used.items() if n == 0]
    require(not unused, f"--holdout-clips {','.join(unused)} matches no clip of the recordings")
    require(any(t for t, _ in out), "--holdout-clips holds out every frame: nothing is left to train on")
    require(any(h for _, h in out), "--holdout-clips holds out no frame")
    return out


def _frame_bytes(shape: tuple[int, ...]) -> int:
    return int(np.prod(shape))


def _open_cache(index: int, bag: str, folder: Path, shape: tuple[int, ...], classes: int, info: dict) -> RecordingCache:
    lines = _read_lines(folder / "frames.jsonl")
    n = len(lines)
    views = np.memmap(folder / "views.u8", dtype=np.uint8, mode="r", shape=(n,) + tuple(shape)) if n else \
        np.zeros((0,) + tuple(shape), np.uint8)
    probs = np.fromfile(folder / "probs.f32", dtype=np.float32, count=n * classes).reshape(n, classes) if n else \
        np.zeros((0, classes), np.float32)
    return RecordingCache(index, bag, folder, views, probs, lines, info)


def _read_lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if not line.endswith("\n"):
                break        # a line cut by a kill: that frame is not committed
            try:
                out.append(json.loads(line))
            except ValueError:
                break
    return out


def _truncate(path: Path, size: int) -> None:
    with open(path, "ab") as fh:
        fh.truncate(size)


class FramePreparer:
    """Renders and caches the frames of the recordings (see the module doc).

    ``teacher``: the :class:`~pws_ros.core.model.LoadedModel`; ``engine``: a
    :class:`~pws_ros.bridge.engine.FrameCertifier` whose ``imaging_for`` makes the imaging of each frame
    (the certifier's own: crop, render factor, border from the radii); ``stop``: the run's
    :class:`~pws_ros.replay.interrupt.StopSignals` (a frame is appended whole or not at all).
    """

    def __init__(self, opts: Any, teacher: Any, engine: Any, work: Path, *, device: torch.device, stop: Any,
                 warn: Callable[[str], None], info: Callable[[str], None], progress: Any = None):
        self.opts = opts
        self.teacher = teacher
        self.engine = engine
        self.work = work
        self.device = device
        self.stop = stop
        self.warn = warn
        self.info = info
        self.progress = progress
        self.config = engine.config
        self.shape: tuple[int, ...] | None = None   # (1 + V, H, W, 3)

    # -- the label of a frame's ground truth in the model's classes (replay's rule: by name, else by index) --
    def truth_label(self, truth: Any, where: str = "") -> tuple[int, str]:
        """A labelled run (ground truth used) needs every label among the model's classes and, for a new
        head, every frame labelled: PwsError naming the frame (``where``) and its file otherwise."""
        o = self.opts
        if truth is None or not o.use_truth or (not truth.class_name and truth.label is None):
            require(not o.fresh_head, f"{where}: no label (no /pws/ground_truth class_name near its stamp): a new head trains "
                                      "on labelled frames only (label every frame, e.g. `pws import labels`)")
            return -1, ""
        names = list(self.teacher.class_names)
        src = f" ({truth.values['file']})" if truth.values.get("file") else ""
        if truth.class_name in names:
            return names.index(truth.class_name), truth.class_name
        if truth.label is not None and 0 <= int(truth.label) < len(names):
            return int(truth.label), truth.class_name
        what = f"label {truth.class_name!r}" if truth.class_name else f"label index {truth.label}"
        raise PwsError(f"{where}{src}: {what} is not one of the model's {len(names)} classes ({', '.join(names[:12])}"
                       f"{', ...' if len(names) > 12 else ''}): train a new head for the label set (--new-head or --backbone), "
                       "or pass --no-truth to ignore the labels")

    def motions(self, rec_index: int, frame_index: int) -> list[tuple[str, float]]:
        """The random motions of one frame: an axis of the config and a value uniform in [-radius, radius]."""
        rng = np.random.default_rng(derive(self.opts.seed, 1, rec_index, frame_index))
        axes = list(self.config.axes)
        out = []
        for _ in range(int(self.opts.views)):
            axis = axes[int(rng.integers(len(axes)))]
            b = float(self.config.radius_for(axis))
            out.append((axis, float(rng.uniform(-b, b))))
        return out

    def render(self, cloud: Any, imaging: Any, motions: list[tuple[str, float]]) -> np.ndarray:
        """(1 + V, H, W, 3) float32: alpha = 0, then the motions (one renderer per axis used)."""
        first = motions[0][0] if motions else self.config.axes[0]
        by_axis: dict[str, list[int]] = {}
        for i, (axis, _a) in enumerate(motions):
            by_axis.setdefault(axis, []).append(i)
        by_axis.setdefault(first, [])
        out: list[np.ndarray | None] = [None] * (1 + len(motions))
        for axis, idx in by_axis.items():
            alphas = ([0.0] if axis == first else []) + [motions[i][1] for i in idx]
            r = make_renderer(cloud, imaging, axis, device=self.device)
            frames = r.render_batch(np.asarray(alphas, dtype=np.float64)).detach().cpu().numpy().astype(np.float32)
            k = 0
            if axis == first:
                out[0], k = frames[0], 1
            for j, i in enumerate(idx):
                out[1 + i] = frames[k + j]
        return np.stack(out)

    def prepare(self, rec_index: int, bag: Path) -> RecordingCache:
        folder = self.work / f"rec{rec_index:03d}"
        folder.mkdir(parents=True, exist_ok=True)
        done = folder / "done.json"
        classes = self.teacher.num_classes
        if done.exists():
            info = json.loads(done.read_text(encoding="utf-8"))
            shape = tuple(info["shape"])
            self._check_shape(shape, bag)
            cache = _open_cache(rec_index, str(bag), folder, shape, classes, info)
            self.info(f"{bag}: {cache.count} frames cached ({folder})")
            if self.progress is not None:
                self.progress.set_total((self.progress.total or 0) + cache.count)
                self.progress.update(cache.count)
            return cache
        lines = _read_lines(folder / "frames.jsonl")
        last = lines[-1]["index"] if lines else -1
        views_f, probs_f, lines_f = folder / "views.u8", folder / "probs.f32", folder / "frames.jsonl"
        if lines:
            shape = tuple(lines[0]["shape"])
            self._check_shape(shape, bag)
            _truncate(views_f, len(lines) * _frame_bytes(shape))
            _truncate(probs_f, len(lines) * classes * 4)
            with open(lines_f, "w", encoding="utf-8") as fh:   # drop a cut last line
                fh.writelines(json.dumps(d) + "\n" for d in lines)
            self.info(f"{bag}: resuming the frame cache after {len(lines)} frame(s)")
            if self.progress is not None:
                self.progress.update(len(lines))
        else:
            for f in (views_f, probs_f, lines_f):
                f.unlink(missing_ok=True)
        count = len(lines)
        with RecordingFrames(bag, self.opts.config, topics=self.opts.topics, stride=self.opts.stride,
                             max_frames=self.opts.max_frames, warn=self.warn) as rec, \
                open(views_f, "ab") as fv, open(probs_f, "ab") as fp, open(lines_f, "a", encoding="utf-8") as fl:
            self.info(f"{bag}: {rec.describe()}")
            if self.progress is not None and rec.estimated_frames:
                self.progress.set_total((self.progress.total or 0) + rec.estimated_frames)
            for frame in rec:
                if frame.index <= last:
                    continue
                item = self._one(rec, frame, rec_index)
                if item is None:
                    if self.progress is not None:
                        self.progress.update(1)
                    continue
                views, probs, meta = item
                with self.stop.section():
                    fv.write(views.tobytes())
                    fp.write(probs.tobytes())
                    fv.flush()
                    fp.flush()
                    fl.write(json.dumps(meta) + "\n")
                    fl.flush()
                count += 1
                if self.progress is not None:
                    self.progress.update(1)
            seen, skipped = rec.frames_seen, rec.input_errors
        require(count > 0, f"recording {bag}: no usable camera frame ({seen} input frame(s), {skipped} could not be converted)")
        shape = tuple(self.shape) if self.shape is not None else tuple(_read_lines(lines_f)[0]["shape"])
        info = {"format": CACHE_FORMAT, "bag": str(bag), "frames": count, "shape": list(shape), "classes": classes,
                "input_frames_seen": seen, "input_frames_skipped": skipped}
        atomic_write_text(done, json.dumps(info, indent=1) + "\n")
        return _open_cache(rec_index, str(bag), folder, shape, classes, info)

    def _check_shape(self, shape: tuple[int, ...], bag: Any) -> None:
        if self.shape is None:
            self.shape = tuple(shape)
        require(tuple(shape) == tuple(self.shape),
                f"recording {bag}: frames of shape {tuple(shape)} but the other recordings' are {self.shape} "
                "(the model declares no input size and the cameras differ): tune on recordings of one camera size")

    def _one(self, rec: RecordingFrames, frame: Any, rec_index: int) -> tuple[np.ndarray, np.ndarray, dict] | None:
        label, cname = self.truth_label(frame.truth, f"recording {rec.path}: frame {frame.stamp_ns}")   # bad labels first
        clip = frame.truth.values.get("clip", "") if frame.truth is not None else ""
        converted = rec.convert(frame)
        if converted is None:
            return None
        try:
            imaging = self.engine.imaging_for(converted.intrinsics, converted.cloud)
        except PwsError as exc:
            rec.input_errors += 1
            self.warn(f"{rec.path}: frame {frame.stamp_ns} skipped: {exc}")
            return None
        motions = self.motions(rec_index, frame.index)
        frames = self.render(converted.cloud, imaging, motions)
        del converted
        shape = tuple(frames.shape)
        if self.shape is None:
            self.shape = shape
        if shape != tuple(self.shape):
            rec.input_errors += 1
            self.warn(f"{rec.path}: frame {frame.stamp_ns} skipped: its frames are {shape[2]}x{shape[1]}, the others' "
                      f"{self.shape[2]}x{self.shape[1]}")
            return None
        x = torch.from_numpy(np.ascontiguousarray(frames[:1].transpose(0, 3, 1, 2)))
        logits = self.teacher(x.to(self.teacher.device)).detach().float().cpu()
        probs = torch.softmax(logits, dim=1)[0].numpy().astype(np.float32)
        u8 = np.clip(np.rint(frames * 255.0), 0, 255).astype(np.uint8)
        meta = {"index": int(frame.index), "stamp_ns": frame.stamp_ns, "teacher": int(np.argmax(probs)),
                "truth_label": int(label), "truth_class": cname, "clip": clip, "motions": [[a, v] for a, v in motions],
                "shape": list(shape)}
        return u8, probs, meta


__all__ = ["CACHE_FORMAT", "FramePreparer", "RecordingCache", "atomic_write_text", "derive", "split_by_clip"]

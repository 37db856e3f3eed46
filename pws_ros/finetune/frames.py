"""The camera frames of a recording, as ``pws replay`` sees them: the replay's bag reading, input
discovery, stamp ordering, the live nodes' input assembly and :func:`~pws_ros.bridge.inputs.convert`
(no second bag reader). Frames stream one at a time: nothing but the current one is held."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from ..bagio import BagReader
from ..bridge.config import PwsConfig
from ..bridge.inputs import InputAssembler, InputFrame, RawFrame, convert
from ..core.errors import PwsError, require
from ..replay.discovery import discover_inputs
from ..replay.options import GroundTruth, InputTopics
from ..replay.schedule import stamp_ordered
from ..replay.truth import load_ground_truth, truth_near


@dataclass
class RecordedFrame:
    """One complete input frame of a recording (``index`` counts the frames used, after the stride)."""

    index: int
    raw: RawFrame
    truth: GroundTruth | None

    @property
    def stamp_ns(self) -> int:
        return int(self.raw.stamp_ns)


class RecordingFrames:
    """``with RecordingFrames(path, config) as rec: for f in rec: frame = rec.convert(f)``.

    Opens the recording, finds its camera input (PwsError when it has none, as ``pws replay``), reads
    its ground truth when present, and yields every ``stride``-th complete frame in stamp order, at
    most ``max_frames``. :meth:`convert` turns one into its one-frame cloud and camera.
    """

    def __init__(self, path: str | Path, config: PwsConfig, *, topics: dict[str, str] | None = None, stride: int = 1,
                 max_frames: int | None = None, warn: Callable[[str], None] | None = None):
        self.path = Path(path)
        self.config = config
        self.topics = dict(topics or {})
        self.stride = max(1, int(stride))
        self.max_frames = max_frames
        self._warn = warn or (lambda _m: None)
        self.bag: BagReader | None = None
        self.inputs: InputTopics | None = None
        self.truth: dict[int, GroundTruth] = {}
        self._truth_stamps: list[int] = []
        self.assembler: InputAssembler | None = None
        self.frames_seen = 0
        self.input_errors = 0

    def __enter__(self) -> "RecordingFrames":
        require(self.path.exists(), f"recording not found: {self.path}")
        self.bag = BagReader(self.path, warn=self._warn).open()
        try:
            bag = self.bag
            require(bool(bag.topics), f"recording {self.path} is empty: it has no topics")
            require(bag.message_count != 0, f"recording {self.path} holds no messages (topics: {bag.describe()})")
            self.inputs = discover_inputs(bag, self.config, self.topics)
            for note in self.inputs.notes:
                self._warn(note)
            mode = self.inputs.mode
            from dataclasses import replace

            self.config = replace(self.config, input_mode=mode, depth_camera_info_topic=self.inputs.depth_info)
            if self.inputs.truth:
                self.truth = load_ground_truth(bag, self.inputs.truth, self._warn)
                self._truth_stamps = sorted(self.truth)
            self.assembler = InputAssembler(self.config)
            self.assembler.set_extrinsic(self.inputs.extrinsic)
        except BaseException:
            self.bag.close()
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.bag is not None:
            self.bag.close()

    def describe(self) -> str:
        return self.inputs.describe() if self.inputs is not None else ""

    @property
    def estimated_frames(self) -> int | None:
        """Frames this recording will give (from the message count of its colour or cloud topic), or None."""
        inp, bag = self.inputs, self.bag
        if inp is None or bag is None:
            return None
        topic = inp.color if inp.mode in ("rgbd", "auto") and inp.color else inp.points
        info = bag.topics.get(topic)
        if info is None or not info.count:
            return None
        n = -(-int(info.count) // self.stride)
        return min(n, self.max_frames) if self.max_frames else n

    def __iter__(self) -> Iterator[RecordedFrame]:
        require(self.bag is not None and self.inputs is not None, "RecordingFrames is used outside its with-block")
        bag, inputs, asm = self.bag, self.inputs, self.assembler
        roles = inputs.roles()
        roles.pop("truth", None)
        if inputs.mode == "rgbd":
            roles.pop("points", None)
        handlers = {"points": asm.on_points, "depth": asm.on_depth, "color": asm.on_color, "info": asm.on_info,
                    "depth_info": asm.on_depth_info}

        def messages():
            for role, _m, msg, _stamp in stamp_ordered(bag, roles, self._warn):
                yield handlers[role], msg
            yield (lambda _none: asm.flush()), None

        used = 0
        warned: set[str] = set()
        for handler, msg in messages():
            try:
                raw = handler(msg)
            except PwsError as exc:
                if str(exc) not in warned:
                    warned.add(str(exc))
                    self._warn(f"{self.path}: input: {exc}")
                continue
            if raw is None:
                continue
            self.frames_seen += 1
            if (self.frames_seen - 1) % self.stride:
                continue
            truth = truth_near(self.truth, self._truth_stamps, raw.stamp_ns, self.config.sync_tolerance_s)
            yield RecordedFrame(used, raw, truth)
            used += 1
            if self.max_frames is not None and used >= self.max_frames:
                return

    def convert(self, frame: RecordedFrame) -> InputFrame | None:
        """The frame's one-frame cloud and camera, or None (with one warning per distinct problem)."""
        try:
            return convert(frame.raw, self.config, self.assembler.fallback)
        except PwsError as exc:
            self.input_errors += 1
            if self.input_errors == 1 or self.input_errors % 100 == 0:
                self._warn(f"{self.path}: frame {frame.raw.stamp_ns} skipped: {exc} ({self.input_errors} skipped so far)")
            return None


__all__ = ["RecordedFrame", "RecordingFrames"]

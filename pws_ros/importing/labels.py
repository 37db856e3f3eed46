"""Labels for a recording made without them (``pws import labels``): a CSV of stamps and labels
turned into ``/pws/ground_truth`` messages, written with a copy of the recording into a new one.

The CSV: rows ``stamp,label`` (the label of the frame nearest to the stamp, within ``tolerance``)
or ``start,end,label`` (every frame from start to end, both included); ``#`` comments. Without a
header the columns are read in that order, in seconds; a header names them: ``stamp`` / ``start`` /
``end`` in seconds, ``stamp_ns`` / ``start_ns`` / ``end_ns`` in nanoseconds (the ``stamp_ns`` of
``pws replay``'s frames.csv), ``label``, and optionally ``clip`` (recorded as the frame's clip).
Stamps are the frames' header stamps, or with ``relative`` the time since the first frame.

A row that labels no frame, two rows giving one frame different labels, and a label outside the
classes are refused with the CSV line; frames no row covers keep no label.
"""
from __future__ import annotations

import bisect
import csv
from collections import Counter
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any, Sequence

from ..core.errors import PwsError, require

COLUMNS = {"stamp": ("stamp", 1e9), "stamp_s": ("stamp", 1e9), "stamp_ns": ("stamp", 1), "start": ("start", 1e9),
           "start_s": ("start", 1e9), "start_ns": ("start", 1), "end": ("end", 1e9), "end_s": ("end", 1e9),
           "end_ns": ("end", 1), "label": ("label", None), "clip": ("clip", None)}


@dataclass(frozen=True)
class LabelRow:
    line: int
    start_ns: int
    end_ns: int          # == start_ns for a stamp row
    label: str
    clip: str = ""
    is_interval: bool = False


def _ns(text: str, scale: float, where: str) -> int:
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise PwsError(f"{where}: not a number: {text!r}") from None
    require(value.is_finite(), f"{where}: not a finite number: {text!r}")
    return int((value * Decimal(int(scale))).to_integral_value())


def _is_number(text: str) -> bool:
    try:
        Decimal(text)
    except InvalidOperation:
        return False
    return True


def read_stamp_labels(path: Path) -> list[LabelRow]:
    """The rows of a stamp CSV (see the module docstring), stamps in nanoseconds as written."""
    path = Path(path)
    require(path.is_file(), f"label file not found: {path}")
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PwsError(f"cannot read label file {path}: {exc}") from None
    header: list[tuple[str, float | None]] | None = None
    out: list[LabelRow] = []
    for n, row in enumerate(rows, 1):
        cells = [c.strip() for c in row]
        where = f"{path}:{n}"
        if not any(cells) or cells[0].startswith("#"):
            continue
        if header is None and not out and not _is_number(cells[0]):
            unknown = [c for c in cells if c.lower() not in COLUMNS]
            require(not unknown, f"{where}: unknown column(s) {', '.join(unknown)}: expected stamp or start,end (seconds; "
                                 f"stamp_ns, start_ns, end_ns in nanoseconds), label and optionally clip")
            header = [COLUMNS[c.lower()] for c in cells]
            names = [h[0] for h in header]
            require("label" in names and (("stamp" in names) != ("start" in names and "end" in names)),
                    f"{where}: the header needs label and either stamp or start and end, got {','.join(cells)}")
            continue
        cols = header or ([("stamp", 1e9), ("label", None)] if len(cells) == 2 else [("start", 1e9), ("end", 1e9), ("label", None)])
        require(len(cells) == len(cols), f"{where}: expected {len(cols)} values ({','.join(c for c, _ in cols)}), got {','.join(row)!r}")
        v = {name: (cell if scale is None else _ns(cell, scale, where)) for (name, scale), cell in zip(cols, cells)}
        require(bool(v["label"]), f"{where}: empty label")
        if "stamp" in v:
            out.append(LabelRow(n, v["stamp"], v["stamp"], v["label"], v.get("clip", "")))
        else:
            require(v["end"] >= v["start"], f"{where}: the end comes before the start")
            out.append(LabelRow(n, v["start"], v["end"], v["label"], v.get("clip", ""), True))
    require(bool(out), f"label file {path} has no row (stamp,label or start,end,label)")
    return out


def assign_labels(rows: Sequence[LabelRow], stamps: Sequence[int], tolerance_ns: int, source: str) -> dict[int, LabelRow]:
    """``frame stamp -> row`` (``stamps`` sorted): an interval row labels the frames inside it, a stamp
    row the frame nearest to it within ``tolerance_ns``."""
    got: dict[int, LabelRow] = {}
    for r in rows:
        if r.is_interval:
            hit = stamps[bisect.bisect_left(stamps, r.start_ns): bisect.bisect_right(stamps, r.end_ns)]
        else:
            i = bisect.bisect_left(stamps, r.start_ns)
            near = [s for s in stamps[max(0, i - 1): i + 1] if abs(s - r.start_ns) <= tolerance_ns]
            hit = [min(near, key=lambda s: abs(s - r.start_ns))] if near else []
        require(bool(hit), f"{source}:{r.line}: no frame " + (f"from {r.start_ns} to {r.end_ns} ns" if r.is_interval else
                                                              f"within {tolerance_ns / 1e9:g} s of {r.start_ns} ns")
                + (f" (the frames run from {stamps[0]} to {stamps[-1]} ns)" if stamps else ""))
        for s in hit:
            old = got.get(s)
            if old is not None and (old.label, old.clip) != (r.label, r.clip):
                raise PwsError(f"{source}:{r.line}: frame {s} ns is labelled {r.label!r} here and {old.label!r} on line {old.line}")
            got[s] = r
    return got


def attach_labels(bag_path: Path, csv_path: Path, out: Path, *, classes: list[str] | None = None, classes_source: str = "",
                  relative: bool = False, tolerance_s: float = 0.02, replace: bool = False, topics: dict[str, str] | None = None,
                  overwrite: bool = False, progress: Any = None) -> dict[str, Any]:
    """A copy of the recording ``bag_path`` at ``out`` with ``/pws/ground_truth`` from ``csv_path``
    (whole or not at all). Returns what was written."""
    from ..bagio import BagReader, whole_bag
    from ..bridge import msgbuild, msgconv
    from ..bridge.config import PwsConfig
    from ..replay.discovery import discover_inputs
    from ..replay.interrupt import StopSignals
    from ..replay.options import GROUND_TRUTH_TOPIC, T_DIAGNOSTIC_ARRAY
    from ..replay.truth import truth_message
    from .write import HARDWARE_ID

    require(tolerance_s >= 0, f"--tolerance must be >= 0, got {tolerance_s:g}")
    require(Path(bag_path).exists(), f"recording not found: {bag_path}")
    rows = read_stamp_labels(csv_path)
    if classes is not None:
        for r in rows:
            require(r.label in classes, f"{csv_path}:{r.line}: label {r.label!r} is not one of the {len(classes)} classes of {classes_source}")
    types = msgbuild.rosbags_types()
    with BagReader(bag_path) as bag:
        require(bag.message_count != 0, f"recording {bag_path} holds no messages")
        inputs = discover_inputs(bag, PwsConfig(), topics)
        frame_topic = inputs.color or inputs.points
        old_truth = [t for t in bag.topics_of_type(T_DIAGNOSTIC_ARRAY, decodable_only=False)
                     if t == GROUND_TRUTH_TOPIC or t == inputs.truth]
        require(not old_truth or replace, f"{bag_path} already has ground truth on {', '.join(old_truth)}: "
                                          f"pass --replace to drop it and write the labels of {csv_path}")
        order: list[tuple[int, int]] = []     # (log time, header stamp) of the frame topic's messages, in order
        frame_ids: dict[int, str] = {}
        for m in bag.messages([frame_topic]):
            msg = bag.deserialize(m)
            order.append((m.log_time_ns, msgconv.header_stamp_ns(msg)))
            frame_ids.setdefault(order[-1][1], msgconv.frame_id_of(msg))
        stamps = sorted(frame_ids)
        require(bool(stamps), f"{bag_path}: no frame on {frame_topic}")
        shift = stamps[0] if relative else 0
        rows = [LabelRow(r.line, r.start_ns + shift, r.end_ns + shift, r.label, r.clip, r.is_interval) for r in rows]
        labelled = assign_labels(rows, stamps, int(round(tolerance_s * 1e9)), str(csv_path))
        labels: Counter = Counter()
        done: set[int] = set()
        copied = [t for t, info in bag.topics.items() if info.decodable and t not in old_truth]
        next_stamp = iter(order)
        with StopSignals(), whole_bag(out, overwrite=overwrite, typestore=types.typestore) as writer:
            for m in bag.messages(copied):
                writer.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns, bag.typestore_for(m.msgtype))
                if m.topic != frame_topic:
                    continue
                if progress is not None:
                    progress.update(1)
                log_time, stamp = next(next_stamp, (None, 0))
                if log_time != m.log_time_ns:   # not the first pass's order: decode this one again
                    stamp = msgconv.header_stamp_ns(bag.deserialize(m))
                row = labelled.get(stamp)
                if row is None or stamp in done:
                    continue
                done.add(stamp)
                values = {"class_name": row.label}
                if classes is not None:
                    values["label"] = str(classes.index(row.label))
                if row.clip:
                    values["clip"] = row.clip
                values["source"] = f"{Path(csv_path).name}:{row.line}"
                header = msgbuild.make_header(types, stamp, frame_ids[stamp])
                writer.write(GROUND_TRUTH_TOPIC, truth_message(types, header, values, hardware_id=HARDWARE_ID), m.log_time_ns)
                labels[row.label] += 1
    return {"out": str(out), "frames": len(stamps), "labelled": len(done), "labels": dict(sorted(labels.items())),
            "rows": len(rows), "frame_topic": frame_topic, "replaced": old_truth,
            "left_out": sorted(t for t, info in bag.topics.items() if not info.decodable)}

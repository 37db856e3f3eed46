"""A folder of labelled RGB-D clips (``pws import frames``): which files make each frame, and the
frame's clip, label, stamp and depth scale.

Layout: every folder under ROOT that holds a colour sub-folder (``rgb/``, ``--color-dir``) is a
**clip**, named by its path relative to ROOT (``G01_call/clip04``). Its colour images
(``.png``/``.jpg``) are its frames, in file-name order (numbers compared as numbers); each pairs with
the depth file of the same stem in the first of the depth sub-folders it has (``depth_raw/`` then
``depth/``, ``--depth-dir``): a ``.npy`` array or a 16-bit PNG / TIFF, registered to the colour image.

Depth scale (metres per stored unit): ``--depth-scale``, else ``depth_metadata.json``
(``{"depth_scale": 0.001}``) in the clip folder or in ROOT.

Label of a frame: from ``--labels CSV`` (rows ``file,label``: a colour image, or a folder above
it, relative to ROOT; the most specific row wins), else from the clip's name by ``--label-regex``
(its group ``label``, else its first group, else the whole match; default: the first folder, the
``<label>/<clip>/...`` layout).

Selection: ``--clips GLOB`` (clip names), ``--frames LIST`` (the last number of a file's stem).

Stamps: frames of a clip are ``1 / rate`` apart by their position in the clip (a selection keeps its
frames' times), clips follow one another in name order with ``gap`` seconds between them.
"""
from __future__ import annotations

import csv
import fnmatch
import json
import re
from dataclasses import dataclass
from pathlib import Path

from ..core.errors import PwsError, require
from .write import COLOR_SUFFIXES, DEPTH_SUFFIXES, ImportFrame, check_depth_scale

DEFAULT_LABEL_REGEX = r"^(?P<label>[^/]+)"
DEPTH_METADATA = "depth_metadata.json"
START_S = 1_700_000_000.0


@dataclass
class FolderLayout:
    """How ``pws import frames`` reads a folder (the command's options)."""

    color_dir: str = "rgb"
    depth_dirs: tuple[str, ...] = ("depth_raw", "depth")
    label_regex: str = DEFAULT_LABEL_REGEX
    labels_csv: Path | None = None
    classes: list[str] | None = None      # the model's classes: a label outside them is refused
    classes_source: str = ""
    depth_scale: float | None = None      # metres per depth unit; None: depth_metadata.json
    frames: set[int] | None = None        # keep the frames whose file-name number is one of these
    clips: str | None = None              # keep the clips whose name matches this glob
    rate_hz: float = 30.0
    gap_s: float = 1.0
    start_s: float = START_S


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def frame_number(path: Path) -> int | None:
    """The last number in a file's stem (``frame_008.png`` -> 8), None when it has none."""
    found = re.findall(r"\d+", Path(path).stem)
    return int(found[-1]) if found else None


def parse_frame_numbers(text: str) -> set[int]:
    """``8``, ``1-5,9`` -> the frame numbers (``--frames``)."""
    out: set[int] = set()
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        require(m is not None, f"--frames: expected numbers and ranges such as 8 or 1-5,9, got {text!r}")
        a, b = int(m.group(1)), int(m.group(2) or m.group(1))
        require(a <= b, f"--frames: the range {part.strip()} is empty")
        out.update(range(a, b + 1))
    return out


def read_labels_csv(path: Path, root: Path) -> dict[str, str]:
    """``relative posix path -> label`` of a ``file,label`` CSV (an optional header ``file,label``,
    ``#`` comments); every path must name a file or folder under ``root``."""
    path, root = Path(path), Path(root)
    require(path.is_file(), f"label file not found: {path}")
    out: dict[str, str] = {}
    where: dict[str, int] = {}
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PwsError(f"cannot read label file {path}: {exc}") from None
    for n, row in enumerate(rows, 1):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if n == 1 and cells[0].lower() == "file":
            continue
        require(len(cells) >= 2 and cells[0] and cells[1], f"{path}:{n}: expected 'file,label', got {','.join(row)!r}")
        p = Path(cells[0])
        if p.is_absolute():
            try:
                p = p.relative_to(root)
            except ValueError:
                raise PwsError(f"{path}:{n}: {cells[0]} is not under {root}") from None
        key = p.as_posix().strip("/")
        require((root / key).exists(), f"{path}:{n}: {cells[0]} is not a file or folder under {root}")
        if key in out and out[key] != cells[1]:
            raise PwsError(f"{path}:{n}: {cells[0]} is labelled {cells[1]!r} here and {out[key]!r} on line {where[key]}")
        out[key], where[key] = cells[1], n
    require(bool(out), f"label file {path} has no 'file,label' row")
    return out


def _csv_label(labels: dict[str, str], rel: str) -> str | None:
    parts = rel.split("/")
    for k in range(len(parts), 0, -1):
        label = labels.get("/".join(parts[:k]))
        if label is not None:
            return label
    return None


def _regex_label(regex: re.Pattern, clip: str) -> str | None:
    m = regex.search(clip)
    if m is None:
        return None
    label = m.group("label") if "label" in regex.groupindex else (m.group(1) if regex.groups else m.group(0))
    return label or None


def _depth_scale(layout: FolderLayout, clip: Path, root: Path) -> float:
    if layout.depth_scale is not None:
        return check_depth_scale(layout.depth_scale, "--depth-scale")
    for folder in (clip, root):
        meta = folder / DEPTH_METADATA
        if meta.is_file():
            try:
                data = json.loads(meta.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, ValueError) as exc:
                raise PwsError(f"{meta}: not readable JSON ({' '.join(str(exc).split())[:160]})") from None
            require(isinstance(data, dict) and "depth_scale" in data, f"{meta}: no \"depth_scale\" (metres per depth unit)")
            return check_depth_scale(data["depth_scale"], str(meta))
    raise PwsError(f"{clip}: no depth scale: give --depth-scale (metres per depth unit, e.g. 0.001 for millimetres) "
                   f"or put {DEPTH_METADATA} ({{\"depth_scale\": 0.001}}) in the clip folder or in {root}")


def find_clips(root: Path, color_dir: str) -> list[Path]:
    """The clip folders under ``root`` (those holding ``color_dir``), in name order (numbers as numbers)."""
    root = Path(root)
    require(root.is_dir(), f"{root} is not a folder")
    clips = {p.parent for p in root.rglob(color_dir) if p.is_dir()
             and not any(part.startswith(".") for part in p.relative_to(root).parts)}
    require(bool(clips), f"no clip in {root}: no folder under it holds a {color_dir!r} sub-folder of colour images (--color-dir)")
    return sorted(clips, key=lambda c: _natural(c.relative_to(root).as_posix()))


def plan_frames(root: Path, layout: FolderLayout) -> list[ImportFrame]:
    """The frames of ``root`` to write, in time order, each with its ground truth (label, clip, ...).
    Every check that needs no image read is done here: a frame without a label or depth file, a
    label outside the classes, a depth scale that is not positive, an empty selection."""
    root = Path(root)
    require(layout.rate_hz > 0, f"--rate must be positive, got {layout.rate_hz:g}")
    require(layout.gap_s >= 0, f"--gap must be >= 0, got {layout.gap_s:g}")
    labels = read_labels_csv(layout.labels_csv, root) if layout.labels_csv else None
    try:
        regex = re.compile(layout.label_regex)
    except re.error as exc:
        raise PwsError(f"--label-regex {layout.label_regex!r} is not a regular expression: {exc}") from None
    period = int(round(1e9 / layout.rate_hz))
    start = int(round(layout.start_s * 1e9))
    out: list[ImportFrame] = []
    clips = find_clips(root, layout.color_dir)
    names = [c.relative_to(root).as_posix() if c != root else root.name for c in clips]
    if layout.clips is not None:
        keep = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, layout.clips)]
        require(bool(keep), f"--clips {layout.clips!r} matches none of the {len(clips)} clips of {root} ({', '.join(names[:6])}"
                            f"{', ...' if len(names) > 6 else ''})")
        clips, names = [clips[i] for i in keep], [names[i] for i in keep]
    for clip_index, (clip, name) in enumerate(zip(clips, names)):
        colors = sorted((p for p in (clip / layout.color_dir).iterdir() if p.is_file() and p.suffix.lower() in COLOR_SUFFIXES),
                        key=lambda p: _natural(p.name))
        depth_dir = next((clip / d for d in layout.depth_dirs if (clip / d).is_dir()), None)
        require(depth_dir is not None or not colors,
                f"{clip}: no depth folder ({' or '.join(layout.depth_dirs)}; --depth-dir) beside {layout.color_dir}/")
        scale = _depth_scale(layout, clip, root) if colors else 0.0
        for index, color in enumerate(colors):
            if layout.frames is not None and frame_number(color) not in layout.frames:
                continue
            depth = next((depth_dir / (color.stem + s) for s in DEPTH_SUFFIXES if (depth_dir / (color.stem + s)).is_file()), None)
            require(depth is not None, f"{color}: no depth file {depth_dir / color.stem}{{{','.join(DEPTH_SUFFIXES)}}}")
            rel = color.relative_to(root).as_posix()
            if labels is not None:
                label = _csv_label(labels, rel)
                require(label is not None, f"{color}: no label: neither it nor a folder above it is in {layout.labels_csv}")
            else:
                label = _regex_label(regex, name)
                require(label is not None, f"{color}: no label: its clip {name!r} does not match --label-regex {layout.label_regex!r}")
            truth = {"class_name": label}
            if layout.classes is not None:
                require(label in layout.classes, f"{color}: label {label!r} is not one of the {len(layout.classes)} classes of "
                                                 f"{layout.classes_source} ({', '.join(layout.classes[:12])}{', ...' if len(layout.classes) > 12 else ''})")
                truth["label"] = str(layout.classes.index(label))
            truth.update(clip=name, clip_index=str(clip_index), frame_index=str(index), file=rel)
            out.append(ImportFrame(start + index * period, color, depth, scale, truth))
        start += len(colors) * period + int(round(layout.gap_s * 1e9))
    require(bool(out), f"{root}: no frame selected (colour images {', '.join(COLOR_SUFFIXES)} in {layout.color_dir}/"
                       + (f", --frames {','.join(map(str, sorted(layout.frames)[:8]))}" if layout.frames else "") + ")")
    return out


def load_classes(spec: str | Path) -> tuple[list[str], str]:
    """``--classes``: a class file (one name a line), or a model file whose class file is found beside it."""
    from ..core.model import find_class_file, read_class_file

    p = Path(spec)
    if p.suffix.lower() in (".pt", ".pth", ".ts", ".ptl"):
        require(p.is_file(), f"--classes: model file not found: {p}")
        found = find_class_file(p)
        require(found is not None, f"--classes: no class file beside model {p} ({p.stem}.classes.txt or classes.txt)")
        return read_class_file(found), f"class file {found}"
    return read_class_file(p), f"class file {p}"

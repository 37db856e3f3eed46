"""Storage detection, topic and message records shared by the reader and the writer."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable


MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}

WarnFn = Callable[[str], None]


def first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def storage_kind(path: Path) -> str | None:
    """``mcap`` / ``sqlite3`` from the suffix, else from the first bytes; None if neither."""
    kind = STORAGE_SUFFIXES.get(path.suffix.lower())
    if kind:
        return kind
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError:
        return None
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC):
        return "sqlite3"
    return None


@dataclass
class TopicInfo:
    """One topic of a bag: its type, message count (None if unknown) and own definition."""

    name: str
    msgtype: str
    count: int | None
    msgdef: str = ""
    msgdef_format: str = ""        # "msg" | "idl" | "" (none stored)
    digest: str = ""
    decodable: bool = False
    skip_reason: str = ""          # why it cannot be decoded (when not decodable)


@dataclass
class BagMessage:
    """One serialized message: topic, type, log (receive) time and its CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: Any                      # bytes or memoryview (CDR)
    source: str = ""               # storage file name


@dataclass
class Conn:
    key: Any
    topic: str
    msgtype: str
    msgdef: str
    fmt: str
    digest: str
    count: int | None


def used_types(fielddefs: dict[str, Any], roots: Iterable[str]) -> tuple[set[str], set[str]]:
    """``(defined, missing)``: the message types the ``roots`` are or use (recursively) that ``fielddefs`` defines,
    and those it does not."""
    from rosbags.typesys.base import Nodetype

    defined: set[str] = set()
    missing: set[str] = set()
    stack = list(roots)
    while stack:
        name = stack.pop()
        if name in defined or name in missing:
            continue
        if name not in fielddefs:
            missing.add(name)
            continue
        defined.add(name)
        for _fname, (ntype, detail) in fielddefs[name][1]:
            while ntype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                (ntype, detail), _size = detail
            if ntype == Nodetype.NAME:
                stack.append(detail)
    return defined, missing


def undefined_refs(fielddefs: dict[str, Any], msgtype: str) -> set[str]:
    """Message types ``msgtype`` uses (recursively) that ``fielddefs`` does not define."""
    return used_types(fielddefs, [msgtype])[1]

"""Robust rosbag2 reading and writing, without ROS.

:class:`BagReader` opens what people actually record:

- a bag directory with ``metadata.yaml`` (MCAP or sqlite3, split into several files, zstd
  ``file`` / ``message`` compression, MCAP chunk compression) through ``rosbags.rosbag2.Reader``;
- a bare ``.mcap`` or ``.db3`` file, or a directory of them without ``metadata.yaml``;
- damaged recordings: a truncated or unindexed MCAP file (no footer, e.g. the recorder was killed)
  is read record by record with the independent ``mcap`` stream reader up to the damage; a file that
  fails half-way stops with a warning; missing split files are skipped with a warning.

Messages come in log-time order (the files of a split bag are merged). Every connection's own
message definition is parsed into a typestore seeded with ROS 2 Jazzy, so custom types decode;
service-event types (``*/srv/*``) and definitions that do not parse are skipped with a warning
naming them (``rosbags.highlevel.AnyReader`` refuses the whole bag there: "Could not parse").
Messages are decoded only on request (:meth:`BagReader.deserialize`).

Also works around a rosbags 0.11 quirk: ``Reader.messages()`` matches the metadata's connections
with each file's by QoS too, and yields nothing where a recorder wrote different QoS text in the two
places (the rosbag2 talker test bags); here files are read one by one and matched by topic and type.

:class:`BagWriter` writes a rosbag2 MCAP bag (``Writer(version=9)``, Jazzy definitions, zstd
chunks) that opens with rosbags and with the ``mcap`` + ``mcap_ros2`` readers.
"""
from __future__ import annotations

import heapq
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from .core.errors import PwsError, require

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}

WarnFn = Callable[[str], None]


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def _storage_kind(path: Path) -> str | None:
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
class _Conn:
    key: Any
    topic: str
    msgtype: str
    msgdef: str
    fmt: str
    digest: str
    count: int | None


def _undefined_refs(fielddefs: dict[str, Any], msgtype: str) -> set[str]:
    """Message types ``msgtype`` uses (recursively) that ``fielddefs`` does not define."""
    from rosbags.typesys.base import Nodetype

    missing: set[str] = set()
    seen: set[str] = set()
    stack = [msgtype]
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        if name not in fielddefs:
            missing.add(name)
            continue
        for _fname, (ntype, detail) in fielddefs[name][1]:
            while ntype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                (ntype, detail), _size = detail
            if ntype == Nodetype.NAME:
                stack.append(detail)
    return missing


# ---- per-file sources ---------------------------------------------------------------------

class _StorageSource:
    """One storage file opened by rosbags (``McapReader`` / ``Sqlite3Reader``)."""

    def __init__(self, name: str, storage: Any, decompress: Callable[[Any], bytes] | None = None):
        from rosbags.interfaces import MessageDefinitionFormat

        self.name = name
        self.storage = storage
        self.decompress = decompress
        self.conns: list[_Conn] = []
        for c in storage.connections:
            fmt = {MessageDefinitionFormat.MSG: "msg", MessageDefinitionFormat.IDL: "idl"}.get(c.msgdef.format, "")
            self.conns.append(_Conn(c, c.topic, c.msgtype, c.msgdef.data if fmt else "", fmt, c.digest or "",
                                    int(c.msgcount) if c.msgcount is not None else None))

    def iterate(self, topics: set[str] | None) -> Iterator[BagMessage]:
        wanted = [c.key for c in self.conns if topics is None or c.topic in topics]
        if not wanted:
            return
        for conn, t, data in self.storage.messages(wanted):
            yield BagMessage(conn.topic, conn.msgtype, int(t), self.decompress(data) if self.decompress else data, self.name)

    def close(self) -> None:
        try:
            self.storage.close()
        except Exception:
            pass


class _McapStreamSource:
    """An MCAP file read record by record with the ``mcap`` library (truncated / unindexed files)."""

    def __init__(self, path: Path, warn: WarnFn):
        self.path = path
        self.name = path.name
        self.error = ""
        schemas: dict[int, tuple[str, str, str]] = {}
        channels: dict[int, tuple[str, int, str]] = {}
        counts: dict[int, int] = {}
        try:
            for rec in self._records():
                kind = type(rec).__name__
                if kind == "Schema":
                    schemas[rec.id] = (rec.name, rec.encoding, bytes(rec.data).decode("utf-8", "replace"))
                elif kind == "Channel":
                    channels[rec.id] = (rec.topic, rec.schema_id, rec.message_encoding)
                elif kind == "Message":
                    counts[rec.channel_id] = counts.get(rec.channel_id, 0) + 1
        except Exception as exc:  # the damage: keep what came before
            self.error = _first_line(exc) if str(exc) else f"{type(exc).__name__} (the file ends inside a record)"
        n = sum(counts.values())
        if self.error and not channels:
            raise PwsError(f"bag file {path.name} is not a readable MCAP file ({self.error})")
        if self.error:
            warn(f"bag file {path.name} is truncated or corrupt ({self.error}): using the {n} complete message(s) before the damage")
        self.conns: list[_Conn] = []
        for cid, (topic, sid, enc) in sorted(channels.items()):
            name, sfmt, text = schemas.get(sid, ("", "", ""))
            if enc != "cdr":
                warn(f"bag file {path.name}: topic {topic} uses message encoding {enc!r}, not cdr: skipped")
                continue
            fmt = {"ros2msg": "msg", "ros2idl": "idl"}.get(sfmt, "")
            self.conns.append(_Conn(cid, topic, name or "", text if fmt else "", fmt, "", counts.get(cid, 0)))

    def _records(self) -> Iterator[Any]:
        from mcap.stream_reader import StreamReader

        with self.path.open("rb") as f:
            yield from StreamReader(f, skip_magic=False, validate_crcs=True).records

    def iterate(self, topics: set[str] | None) -> Iterator[BagMessage]:
        want = {c.key: c for c in self.conns if topics is None or c.topic in topics}
        if not want:
            return
        try:
            for rec in self._records():
                if type(rec).__name__ == "Message" and rec.channel_id in want:
                    c = want[rec.channel_id]
                    yield BagMessage(c.topic, c.msgtype, int(rec.log_time), bytes(rec.data), self.name)
        except Exception:
            return  # already reported when the file was scanned

    def close(self) -> None:
        pass


# ---- the reader ---------------------------------------------------------------------------

class BagReader:
    """Read a rosbag2 recording robustly (see the module docstring).

    ``warn`` receives one-line warnings (also kept in :attr:`warnings`). Use as a context manager::

        with BagReader("bags/demo") as bag:
            for m in bag.messages({"/camera/color/image_raw"}):
                img = bag.deserialize(m)
    """

    def __init__(self, path: str | Path, *, warn: WarnFn | None = None):
        self.path = Path(path)
        self.warnings: list[str] = []
        self._warn_fn = warn
        self.sources: list[Any] = []
        self.files: list[str] = []   # storage files read (names), kept after close()
        self.topics: dict[str, TopicInfo] = {}
        self.storage = ""            # "mcap" | "sqlite3" | "mixed"
        self.layout = ""             # "directory" | "file"
        self.backend = ""            # "rosbags" (metadata.yaml) | "rosbags-files" (storage files one by one)
        self.recovered: list[str] = []  # files read record by record (truncated / unindexed MCAP)
        self.compression = ""        # "", "file", "message" (rosbag2 zstd modes); MCAP chunk compression is transparent
        self.metadata_count: int | None = None
        self.typestore: Any = None
        self.read_errors = 0
        self._meta_counts: dict[str, int] = {}
        self._errors: list[str] = []
        self._reader: Any = None
        self._open = False

    # ---- context ----
    def __enter__(self) -> "BagReader":
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def warn(self, message: str) -> None:
        self.warnings.append(message)
        if self._warn_fn is not None:
            self._warn_fn(message)

    # ---- open ----
    def open(self) -> "BagReader":
        p = self.path
        require(p.exists(), f"bag not found: {p}")
        if p.is_dir():
            self.layout = "directory"
            if (p / "metadata.yaml").is_file():
                self._open_directory(p)
            else:
                files = sorted(f for f in p.iterdir() if f.is_file() and _storage_kind(f) is not None)
                require(bool(files), f"{p} is not a rosbag2 bag: it has no metadata.yaml and no .mcap or .db3 file")
                self.warn(f"bag {p} has no metadata.yaml: reading its {len(files)} storage file(s) directly")
                self._open_files(files)
        else:
            self.layout = "file"
            self._open_files([p])
        require(bool(self.sources), f"cannot read bag {p}: " + ("; ".join(self._errors) if self._errors else "no readable storage file"))
        self.files = [s.name for s in self.sources]
        kinds = {getattr(s, "kind", "") for s in self.sources}
        self.storage = kinds.pop() if len(kinds) == 1 else "mixed"
        self._collect_topics()
        self._build_typestore()
        self._open = True
        return self

    def _open_directory(self, p: Path) -> None:
        from rosbags.rosbag2 import Reader

        try:
            reader = Reader(p)
            reader.open()
        except Exception as exc:
            self.warn(f"bag {p}: {_first_line(exc)}; reading its storage files one by one")
            files = sorted(f for f in p.iterdir() if f.is_file() and _storage_kind(f) is not None)
            require(bool(files), f"cannot read bag {p}: {_first_line(exc)}")
            self._open_files(files)
            return
        self._reader = reader
        self.backend = "rosbags"
        storage = reader.storage
        self.compression = reader.compression_mode or ""
        decompress = None
        if self.compression == "message":
            from rosbags.rosbag2 import reader as _rr

            decompress = _rr.zstd.decompress
        self.metadata_count = int(reader.message_count)
        for c in reader.connections:
            self._meta_counts[c.topic] = self._meta_counts.get(c.topic, 0) + int(c.msgcount or 0)
        kind = "mcap"
        try:
            import yaml

            meta = yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            kind = str(meta.get("storage_identifier", "mcap"))
        except Exception:
            pass
        storages = getattr(storage, "storages", None) or [storage]
        for st in storages:
            src = _StorageSource(Path(str(getattr(st, "path", p))).name, st, decompress)
            src.kind = kind
            self.sources.append(src)

    def _open_files(self, files: Iterable[Path]) -> None:
        from rosbags.rosbag2.storage_mcap import McapReader
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        self.backend = self.backend or "rosbags-files"
        for f in files:
            kind = _storage_kind(f)
            if f.suffix.lower() == ".zstd":
                self.warn(f"bag file {f.name} is zstd-compressed but the bag has no readable metadata.yaml: skipped")
                continue
            if kind is None:
                self._errors.append(f"{f.name} is neither an MCAP nor an sqlite3 file")
                self.warn(f"{self._errors[-1]}: skipped")
                continue
            if kind == "mcap":
                try:
                    st = McapReader(f)
                    st.open()
                    src: Any = _StorageSource(f.name, st)
                except Exception as exc:
                    if f.stat().st_size == 0:
                        self._errors.append(f"bag file {f.name} is empty (0 bytes)")
                        self.warn(f"{self._errors[-1]}: skipped")
                        continue
                    self.warn(f"bag file {f.name}: {_first_line(exc)}; reading it record by record")
                    try:
                        src = _McapStreamSource(f, self.warn)
                    except PwsError as err:
                        self._errors.append(str(err))
                        self.warn(f"{err}: skipped")
                        continue
                    self.recovered.append(f.name)
            else:
                try:
                    st = Sqlite3Reader(f)
                    st.open()
                    src = _StorageSource(f.name, st)
                except Exception as exc:
                    self._errors.append(f"cannot read sqlite3 bag file {f.name}: {_first_line(exc)}")
                    self.warn(f"{self._errors[-1]}: skipped")
                    continue
            src.kind = kind
            self.sources.append(src)

    def _collect_topics(self) -> None:
        topics: dict[str, TopicInfo] = {}
        meta = self._meta_counts
        for src in self.sources:
            for c in src.conns:
                info = topics.get(c.topic)
                if info is None:
                    topics[c.topic] = TopicInfo(c.topic, c.msgtype, c.count, c.msgdef, c.fmt, c.digest)
                    continue
                if c.msgtype != info.msgtype:
                    self.warn(f"topic {c.topic} has two types ({info.msgtype}, {c.msgtype}): using {info.msgtype}")
                if c.count is not None:
                    info.count = (info.count or 0) + c.count
                if not info.msgdef and c.msgdef:
                    info.msgdef, info.msgdef_format = c.msgdef, c.fmt
        if meta:
            for name, n in meta.items():
                if name in topics:
                    topics[name].count = n
        self.topics = dict(sorted(topics.items()))

    def _build_typestore(self) -> None:
        """Jazzy definitions overridden by each connection's own; srv and unparseable types skipped."""
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        base = get_typestore(Stores.ROS2_JAZZY)
        own: dict[str, Any] = {}
        failed: dict[str, str] = {}
        by_type: dict[str, list[TopicInfo]] = {}
        for info in self.topics.values():
            by_type.setdefault(info.msgtype, []).append(info)
        for msgtype, infos in by_type.items():
            names = ", ".join(i.name for i in infos)
            if "/srv/" in msgtype:
                reason = f"service type {msgtype} (service events are not camera data)"
                failed[msgtype] = reason
                self.warn(f"skipping topic(s) {names}: {reason}")
                continue
            info = next((i for i in infos if i.msgdef), None)
            if info is None:
                continue  # no definition stored: Jazzy's, if it has one
            try:
                if info.msgdef_format == "idl":
                    sep = "=" * 80 + "\n"
                    typs: dict[str, Any] = {}
                    parts = info.msgdef.split(sep)[1:] if info.msgdef.startswith(sep + "IDL: ") else [None]
                    for part in parts:
                        typs.update(get_types_from_idl(part.split("\n", 1)[1] if part is not None else info.msgdef))
                else:
                    typs = get_types_from_msg(info.msgdef, msgtype)
                own.update(typs)
            except Exception as exc:
                if msgtype in base.types:
                    self.warn(f"the stored definition of {msgtype} (topic {names}) does not parse ({_first_line(exc)[:120]}); using ROS 2 Jazzy's")
                else:
                    failed[msgtype] = f"its definition does not parse ({_first_line(exc)[:120]})"
                    self.warn(f"skipping topic(s) {names}: type {msgtype}: {failed[msgtype]}")
        store = get_typestore(Stores.EMPTY)
        merged = dict(base.fielddefs)
        merged.update(own)
        try:
            store.register(merged)
        except Exception as exc:  # inconsistent definitions: fall back type by type
            self.warn(f"the bag's message definitions conflict ({_first_line(exc)[:120]}); decoding type by type")
            store = get_typestore(Stores.ROS2_JAZZY)
            for name, fd in own.items():
                try:
                    store.register({name: fd})
                except Exception:
                    failed.setdefault(name, "its definition conflicts with another type of the bag")
        for msgtype in list(own):
            missing = _undefined_refs(store.fielddefs, msgtype)
            if missing and msgtype not in failed:
                failed[msgtype] = f"its definition refers to undefined type(s) {', '.join(sorted(missing))}"
                names = ", ".join(i.name for i in by_type.get(msgtype, []))
                if names:
                    self.warn(f"skipping topic(s) {names}: type {msgtype}: {failed[msgtype]}")
        self.typestore = store
        self._jazzy = base
        self._own_types = set(own)
        self._use_jazzy: set[str] = set()
        for info in self.topics.values():
            if info.msgtype in failed:
                info.decodable, info.skip_reason = False, failed[info.msgtype]
            elif info.msgtype in store.types:
                info.decodable = True
            else:
                info.decodable = False
                info.skip_reason = f"unknown message type {info.msgtype} (no definition in the bag and not a ROS 2 Jazzy type)"
                self.warn(f"skipping topic {info.name}: {info.skip_reason}")

    def close(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:
                pass
            self._reader = None
        else:
            for s in self.sources:
                s.close()
        self.sources = []
        self._open = False

    # ---- queries ----
    @property
    def message_count(self) -> int | None:
        counts = [t.count for t in self.topics.values()]
        if counts and all(c is not None for c in counts):
            return int(sum(counts))  # type: ignore[arg-type]
        return self.metadata_count

    def topics_of_type(self, msgtype: str, decodable_only: bool = True) -> list[str]:
        return [t.name for t in self.topics.values() if t.msgtype == msgtype and (t.decodable or not decodable_only)]

    def describe(self) -> str:
        """``/a (pkg/msg/T, 3), /b (...)``: every topic, for messages naming what the bag holds."""
        if not self.topics:
            return "no topics"
        items = [f"{t.name} ({t.msgtype}, {t.count if t.count is not None else '?'})" for t in self.topics.values()]
        more = len(items) - 24
        return ", ".join(items[:24]) + (f" and {more} more" if more > 0 else "")

    # ---- messages ----
    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages of ``topics`` (all when None) in log-time order; a file that fails half-way stops
        with a warning (its earlier messages are kept)."""
        require(self._open, "the bag is not open")
        wanted = None if topics is None else set(topics)
        iters = [self._guarded(src, wanted) for src in self.sources]
        if len(iters) == 1:
            yield from iters[0]
        else:
            yield from heapq.merge(*iters, key=lambda m: m.log_time_ns)

    def _guarded(self, src: Any, wanted: set[str] | None) -> Iterator[BagMessage]:
        n = 0
        try:
            for m in src.iterate(wanted):
                n += 1
                yield m
        except Exception as exc:
            self.read_errors += 1
            self.warn(f"bag file {src.name} is corrupt or truncated: reading stopped after {n} message(s): {_first_line(exc)}")

    def first_messages(self, topics: Iterable[str], per_topic: int = 1, max_scan: int | None = None) -> dict[str, list[BagMessage]]:
        """The first ``per_topic`` messages of each topic (stops reading once every topic has them)."""
        want = {t for t in topics if t in self.topics}
        out: dict[str, list[BagMessage]] = {t: [] for t in want}
        if not want:
            return out
        scanned = 0
        for m in self.messages(want):
            lst = out[m.topic]
            if len(lst) < per_topic:
                lst.append(m)
            scanned += 1
            if all(len(v) >= per_topic for v in out.values()) or (max_scan is not None and scanned >= max_scan):
                break
        return out

    def typestore_for(self, msgtype: str) -> Any:
        """The typestore whose definition of ``msgtype`` matches the bag's bytes (to copy them)."""
        return self._jazzy if msgtype in self._use_jazzy else self.typestore

    def deserialize(self, m: BagMessage) -> Any:
        """The decoded message (rosbags dataclass); PwsError naming the topic when it cannot be decoded."""
        info = self.topics.get(m.topic)
        if info is not None and not info.decodable and info.msgtype == m.msgtype:
            raise PwsError(f"cannot decode topic {m.topic}: {info.skip_reason}")
        if m.msgtype in self._use_jazzy:
            return self._jazzy.deserialize_cdr(m.data, m.msgtype)
        try:
            return self.typestore.deserialize_cdr(m.data, m.msgtype)
        except Exception as exc:
            err = exc
        # a stored definition that does not match its own messages (seen in the wild): try Jazzy's
        if m.msgtype in self._own_types and m.msgtype in self._jazzy.types:
            try:
                out = self._jazzy.deserialize_cdr(m.data, m.msgtype)
            except Exception:
                pass
            else:
                self._use_jazzy.add(m.msgtype)
                self.warn(f"the definition of {m.msgtype} stored in the bag does not match its messages on {m.topic}: "
                          f"decoding with the ROS 2 Jazzy definition")
                return out
        raise PwsError(f"cannot decode a {m.msgtype} message on {m.topic} (log time {m.log_time_ns}): "
                       f"{_first_line(err)[:160]}") from None


# ---- writing ------------------------------------------------------------------------------

def prepare_output(path: str | Path, overwrite: bool = False) -> Path:
    """Make room for a new bag directory at ``path``: it must not exist, unless ``overwrite`` and it is
    an old bag directory (then it is deleted). A file or a folder that does not look like a bag is
    never deleted. Missing parent folders are created."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        require(overwrite, f"output {p} already exists: choose another --out or pass --overwrite")
        require(p.is_dir() and not p.is_symlink(), f"output {p} exists and is not a bag directory: refusing to overwrite it")
        entries = list(p.iterdir())
        bagish = all(e.is_file() and (e.name == "metadata.yaml" or _storage_kind(e) is not None or e.suffix.lower() in (".mcap", ".db3", ".zstd"))
                     for e in entries)
        require(bagish, f"output {p} exists and is not a rosbag2 bag directory (it holds other files): refusing to overwrite it")
        shutil.rmtree(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


class BagWriter:
    """A rosbag2 MCAP bag (version 9, zstd chunks) written with rosbags and ROS 2 Jazzy definitions.

    :meth:`write` serializes a rosbags message of :attr:`typestore` (topics are added on first use);
    :meth:`write_raw` copies CDR bytes with the definition of another typestore (``--copy-inputs``).

    Crash safety: rosbags keeps the open chunk (up to 1 MiB of messages) in memory and writes the
    summary, the footer and ``metadata.yaml`` only in :meth:`close`. :meth:`flush` closes the open
    chunk and flushes the file, so everything written before it is on disk in complete chunks: a
    process killed afterwards (SIGKILL, OOM) leaves an MCAP file without summary and footer that
    :class:`BagReader` and the ``mcap`` stream reader read up to the last flushed chunk (rosbags
    needs the summary and metadata.yaml: a copy repaired with ``mcap recover``); a clean :meth:`close` (what ``pws replay`` does on SIGINT/SIGTERM) leaves a
    complete bag.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False, compress: bool = True, typestore: Any = None):
        self.path = Path(path)
        self.overwrite = overwrite
        self.compress = compress
        if typestore is None:
            from rosbags.typesys import Stores, get_typestore

            typestore = get_typestore(Stores.ROS2_JAZZY)
        self.typestore = typestore
        self.counts: dict[str, int] = {}
        self._conns: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self._writer: Any = None

    def open(self) -> "BagWriter":
        from rosbags.rosbag2 import Writer
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

        prepare_output(self.path, self.overwrite)
        w = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if self.compress:
            w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            w.open()
        except Exception as exc:
            raise PwsError(f"cannot create output bag {self.path}: {_first_line(exc)}") from None
        self._writer = w
        return self

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._writer is not None

    def _conn(self, topic: str, msgtype: str, typestore: Any) -> Any:
        conn = self._conns.get(topic)
        if conn is None:
            require(self._writer is not None, "the output bag is not open")
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore)
            self._conns[topic] = conn
            self._types[topic] = msgtype
            self.counts[topic] = 0
        else:
            require(self._types[topic] == msgtype, f"topic {topic} already has type {self._types[topic]}, not {msgtype}")
        return conn

    def write(self, topic: str, msg: Any, log_time_ns: int, msgtype: str | None = None) -> None:
        msgtype = msgtype or getattr(msg, "__msgtype__", None)
        require(bool(msgtype), f"cannot tell the message type of {type(msg).__name__} for topic {topic}")
        conn = self._conn(topic, msgtype, self.typestore)
        self._writer.write(conn, int(log_time_ns), self.typestore.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    def write_raw(self, topic: str, msgtype: str, data: Any, log_time_ns: int, typestore: Any) -> None:
        conn = self._conn(topic, msgtype, typestore)
        self._writer.write(conn, int(log_time_ns), bytes(data))
        self.counts[topic] += 1

    def flush(self) -> bool:
        """Close the open MCAP chunk and flush the file (see the class docstring); False when this
        rosbags version does not expose its MCAP storage (then the data stays buffered until close)."""
        storage = getattr(self._writer, "storage", None)
        chunk = getattr(storage, "chunk", None)
        bio = getattr(storage, "bio", None)
        if chunk is None or bio is None or not hasattr(storage, "close_chunk") or not hasattr(chunk, "bio"):
            return False
        if chunk.bio.tell():
            storage.close_chunk()
        bio.flush()
        return True

    def close(self) -> None:
        w, self._writer = self._writer, None
        if w is not None:
            w.close()


# ---- independent verification -------------------------------------------------------------

def mcap_decoded_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, str, int, Any]]:
    """``(topic, schema name, log_time_ns, decoded)`` of every MCAP file of a bag, decoded with the
    independent ``mcap`` + ``mcap_ros2.decoder`` reader (not rosbags): a check that other tools
    (Foxglove, PlotJuggler, ``ros2 bag``) can read what we wrote."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    p = Path(path)
    files = sorted(p.glob("*.mcap")) if p.is_dir() else [p]
    require(bool(files), f"no .mcap file in {p}")
    want = None if topics is None else list(topics)
    for f in files:
        with f.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages(topics=want, log_time_order=True):
                yield channel.topic, schema.name if schema else "", int(message.log_time), decoded


__all__ = ["BagMessage", "BagReader", "BagWriter", "TopicInfo", "mcap_decoded_messages", "prepare_output"]

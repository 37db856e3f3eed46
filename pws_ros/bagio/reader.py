"""The reader (:class:`BagReader`)."""
from __future__ import annotations

import functools
import heapq
from pathlib import Path
from typing import Any, Iterable, Iterator

from ..core.errors import PwsError, require
from .common import BagMessage, TopicInfo, WarnFn, first_line, storage_kind, undefined_refs, used_types
from .sources import McapStreamSource, StorageSource


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
                files = sorted(f for f in p.iterdir() if f.is_file() and storage_kind(f) is not None)
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
            self.warn(f"bag {p}: {first_line(exc)}; reading its storage files one by one")
            files = sorted(f for f in p.iterdir() if f.is_file() and storage_kind(f) is not None)
            require(bool(files), f"cannot read bag {p}: {first_line(exc)}")
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
            src = StorageSource(Path(str(getattr(st, "path", p))).name, st, decompress)
            src.kind = kind
            self.sources.append(src)

    def _open_files(self, files: Iterable[Path]) -> None:
        from rosbags.rosbag2.storage_mcap import McapReader
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        self.backend = self.backend or "rosbags-files"
        for f in files:
            kind = storage_kind(f)
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
                    src: Any = StorageSource(f.name, st)
                except Exception as exc:
                    if f.stat().st_size == 0:
                        self._errors.append(f"bag file {f.name} is empty (0 bytes)")
                        self.warn(f"{self._errors[-1]}: skipped")
                        continue
                    self.warn(f"bag file {f.name}: {first_line(exc)}; reading it record by record")
                    try:
                        src = McapStreamSource(f, self.warn)
                    except PwsError as err:
                        self._errors.append(str(err))
                        self.warn(f"{err}: skipped")
                        continue
                    self.recovered.append(f.name)
            else:
                try:
                    st = Sqlite3Reader(f)
                    st.open()
                    src = StorageSource(f.name, st)
                except Exception as exc:
                    self._errors.append(f"cannot read sqlite3 bag file {f.name}: {first_line(exc)}")
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
                if msgtype in _jazzy().types:
                    self.warn(f"the stored definition of {msgtype} (topic {names}) does not parse ({first_line(exc)[:120]}); using ROS 2 Jazzy's")
                else:
                    failed[msgtype] = f"its definition does not parse ({first_line(exc)[:120]})"
                    self.warn(f"skipping topic(s) {names}: type {msgtype}: {failed[msgtype]}")
        store = get_typestore(Stores.EMPTY)
        # only the types the bag's topics and its own definitions are or use: registering makes a class of each (all of
        # Jazzy's: about a quarter of a second at every bag opened). Jazzy's definitions (their import: about 0.2 s) only
        # where the bag's own leave one out; those of the bag override them
        roots = [t for t in by_type if t not in failed] + list(own)
        merged = own
        used, missing = used_types(own, roots)
        if missing:
            merged = dict(_jazzy().fielddefs)
            merged.update(own)
            used, _ = used_types(merged, roots)
        try:
            store.register({name: merged[name] for name in used})
        except Exception as exc:  # inconsistent definitions: fall back type by type
            self.warn(f"the bag's message definitions conflict ({first_line(exc)[:120]}); decoding type by type")
            store = get_typestore(Stores.ROS2_JAZZY)
            for name, fd in own.items():
                try:
                    store.register({name: fd})
                except Exception:
                    failed.setdefault(name, "its definition conflicts with another type of the bag")
        for msgtype in list(own):
            missing = undefined_refs(store.fielddefs, msgtype)
            if missing and msgtype not in failed:
                failed[msgtype] = f"its definition refers to undefined type(s) {', '.join(sorted(missing))}"
                names = ", ".join(i.name for i in by_type.get(msgtype, []))
                if names:
                    self.warn(f"skipping topic(s) {names}: type {msgtype}: {failed[msgtype]}")
        self.typestore = store
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
            self.warn(f"bag file {src.name} is corrupt or truncated: reading stopped after {n} message(s): {first_line(exc)}")

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
        return _jazzy() if msgtype in self._use_jazzy else self.typestore

    def deserialize(self, m: BagMessage) -> Any:
        """The decoded message (rosbags dataclass); PwsError naming the topic when it cannot be decoded."""
        info = self.topics.get(m.topic)
        if info is not None and not info.decodable and info.msgtype == m.msgtype:
            raise PwsError(f"cannot decode topic {m.topic}: {info.skip_reason}")
        if m.msgtype in self._use_jazzy:
            return _jazzy().deserialize_cdr(m.data, m.msgtype)
        try:
            return self.typestore.deserialize_cdr(m.data, m.msgtype)
        except Exception as exc:
            err = exc
        # a stored definition that does not match its own messages (seen in the wild): try Jazzy's
        if m.msgtype in self._own_types and m.msgtype in _jazzy().types:
            try:
                out = _jazzy().deserialize_cdr(m.data, m.msgtype)
            except Exception:
                pass
            else:
                self._use_jazzy.add(m.msgtype)
                self.warn(f"the definition of {m.msgtype} stored in the bag does not match its messages on {m.topic}: "
                          f"decoding with the ROS 2 Jazzy definition")
                return out
        raise PwsError(f"cannot decode a {m.msgtype} message on {m.topic} (log time {m.log_time_ns}): "
                       f"{first_line(err)[:160]}") from None


@functools.lru_cache(maxsize=1)
def _jazzy() -> Any:
    """ROS 2 Jazzy's typestore (made once: its module defines a class per type)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)

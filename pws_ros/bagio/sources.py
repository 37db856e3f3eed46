"""Per-file message sources: rosbags storage plugins, and the independent MCAP stream reader for damaged files."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator

from ..core.errors import PwsError
from .common import BagMessage, Conn, WarnFn, first_line


# ---- per-file sources ---------------------------------------------------------------------

class StorageSource:
    """One storage file opened by rosbags (``McapReader`` / ``Sqlite3Reader``)."""

    def __init__(self, name: str, storage: Any, decompress: Callable[[Any], bytes] | None = None):
        from rosbags.interfaces import MessageDefinitionFormat

        self.name = name
        self.storage = storage
        self.decompress = decompress
        self.conns: list[Conn] = []
        for c in storage.connections:
            fmt = {MessageDefinitionFormat.MSG: "msg", MessageDefinitionFormat.IDL: "idl"}.get(c.msgdef.format, "")
            self.conns.append(Conn(c, c.topic, c.msgtype, c.msgdef.data if fmt else "", fmt, c.digest or "",
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


class McapStreamSource:
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
            self.error = first_line(exc) if str(exc) else f"{type(exc).__name__} (the file ends inside a record)"
        n = sum(counts.values())
        if self.error and not channels:
            raise PwsError(f"bag file {path.name} is not a readable MCAP file ({self.error})")
        if self.error:
            warn(f"bag file {path.name} is truncated or corrupt ({self.error}): using the {n} complete message(s) before the damage")
        self.conns: list[Conn] = []
        for cid, (topic, sid, enc) in sorted(channels.items()):
            name, sfmt, text = schemas.get(sid, ("", "", ""))
            if enc != "cdr":
                warn(f"bag file {path.name}: topic {topic} uses message encoding {enc!r}, not cdr: skipped")
                continue
            fmt = {"ros2msg": "msg", "ros2idl": "idl"}.get(sfmt, "")
            self.conns.append(Conn(cid, topic, name or "", text if fmt else "", fmt, "", counts.get(cid, 0)))

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

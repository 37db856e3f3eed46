"""Writing (:class:`BagWriter`, :func:`prepare_output`) and an independent MCAP reader to check what was written."""
from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

from ..core.errors import PwsError, require, require_creatable
from .common import first_line, storage_kind


# ---- writing ------------------------------------------------------------------------------

def prepare_output(path: str | Path, overwrite: bool = False) -> Path:
    """Make room for a new bag directory at ``path``: it must not exist, unless ``overwrite`` and it is
    an old bag directory (then it is deleted). A file or a folder that does not look like a bag is
    never deleted. Missing parent folders are created."""
    p = check_output(path, overwrite)
    if p.exists() or p.is_symlink():
        shutil.rmtree(p)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PwsError(f"cannot create output bag {p}: {first_line(exc)}") from None
    return p


def check_output(path: str | Path, overwrite: bool = False) -> Path:
    """What :func:`prepare_output` refuses, without deleting or creating anything."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        require(overwrite, f"output {p} already exists: choose another --out or pass --overwrite")
        require(p.is_dir() and not p.is_symlink(), f"output {p} exists and is not a bag directory: refusing to overwrite it")
        entries = list(p.iterdir())
        bagish = all(e.is_file() and (e.name == "metadata.yaml" or storage_kind(e) is not None or e.suffix.lower() in (".mcap", ".db3", ".zstd"))
                     for e in entries)
        require(bagish, f"output {p} exists and is not a rosbag2 bag directory (it holds other files): refusing to overwrite it")
    else:
        require_creatable(p, "output bag")
    return p


@contextmanager
def whole_bag(path: str | Path, *, overwrite: bool = False, typestore: Any = None) -> Iterator["BagWriter"]:
    """``with whole_bag(out) as writer:`` a :class:`BagWriter` whose bag appears at ``out`` only when
    the block ends without an exception. It is written in a hidden folder beside ``out``
    (``.NAME.partial-PID/NAME``, so the storage file is already named after ``out``) and renamed to
    ``out`` at the end; an existing ``out`` is refused (or, with ``overwrite``, replaced) before
    anything is written. An exception (a bad input, Ctrl-C) deletes the hidden folder: ``out`` is
    never half written. A SIGKILL leaves the hidden folder behind, never a partial ``out``."""
    out = check_output(path, overwrite)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    writer = BagWriter(tmp / out.name, typestore=typestore)
    try:
        writer.open()
        yield writer
        writer.close()
        prepare_output(out, overwrite)
        (tmp / out.name).rename(out)
    finally:
        writer.close()
        shutil.rmtree(tmp, ignore_errors=True)


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
            raise PwsError(f"cannot create output bag {self.path}: {first_line(exc)}") from None
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

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
chunks) that opens with rosbags and with the ``mcap`` + ``mcap_ros2`` readers; :func:`whole_bag`
writes one that appears only when complete (``pws import``).
"""
from __future__ import annotations

from .common import BagMessage, TopicInfo
from .reader import BagReader
from .writer import BagWriter, mcap_decoded_messages, prepare_output, whole_bag

__all__ = ["BagMessage", "BagReader", "BagWriter", "TopicInfo", "mcap_decoded_messages", "prepare_output", "whole_bag"]

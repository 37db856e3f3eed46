"""Certify a rosbag2 recording offline, exactly as the live ``pipeline`` node would, and write the
results as a bag (``pws replay``).

1. :class:`~pws_ros.bagio.BagReader` opens the recording (MCAP or sqlite3, directory or bare file,
   split, zstd, damaged files up to the damage).
2. :func:`discover_inputs` finds the camera input by message type (an organized ``PointCloud2``, or
   a depth ``Image`` + colour ``Image`` + ``CameraInfo``), unless topics are given; the ground truth
   of the procedural world (``/pws/ground_truth``) is read when present.
3. The input messages go, in header-stamp order, through the live nodes' front end
   (:class:`~pws_ros.bridge.inputs.InputAssembler`: stamp matching, CameraInfo pairing, source
   locking) and every complete frame through :func:`~pws_ros.bridge.inputs.convert` and
   :meth:`~pws_ros.bridge.engine.FrameCertifier.process` (plan, render, certify each axis).
   Default: every frame is certified (deterministic for a seed). ``realtime=True`` applies the live
   node's online policy on the recorded stamps: a frame that arrives while the (measured)
   certification of an earlier one would still run waits in a one-frame slot and is replaced (dropped)
   by a newer one, exactly as :class:`~pws_ros.bridge.sync.LatestSlot` does live.
4. Every processed frame is written as the ``pipeline`` node publishes it (the same list, in the same
   order, from :func:`pws_ros.bridge.outputs.frame_outputs`), with log time = the source stamp: ``certification``
   (DiagnosticArray), ``certification/markers`` (MarkerArray), ``plan/poses/<axis>`` (PoseArray);
   optionally ``cloud`` + ``cloud/camera_info``, ``rendered/preview`` and the input topics themselves.
   A frame's messages are written together once it is done, and the bag is flushed after each
   frame (:meth:`~pws_ros.bagio.BagWriter.flush`). SIGINT and SIGTERM stop the run cleanly
   (:mod:`.interrupt`): the frame in flight is dropped whole, the bag is closed (complete and
   readable up to the last finished frame), and the summary and report cover the frames done, with
   ``interrupted`` set and exit status 130 (SIGINT) or 143 (SIGTERM).

Method ``pws`` needs the entire scene cloud: ``dense_cloud_path`` from the config (a static scene), or,
for recordings of the procedural world, the cloud regenerated per frame by :mod:`pws_ros.sim` from
the ground truth's ``scene_seed`` / ``view_index``; otherwise the method is refused.

Modules: :mod:`.options` (what a run takes and returns), :mod:`.discovery` (which topics are the input),
:mod:`.truth` (ground truth), :mod:`.schedule` (stamp order, the online policy), :mod:`.run` (the run),
:mod:`.summary` (its summary and verdict), :mod:`.report` (the summary's numbers, table, CSV, JSON and
plots), :mod:`.progress_log` (the progress bar or lines, also used by ``pws certify``), :mod:`.interrupt`
(SIGINT/SIGTERM as a clean stop). "Certified at radius r" is :mod:`pws_ros.core.metrics` (shared with
``pws bench``).
"""
from __future__ import annotations

from .discovery import discover_inputs
from .options import GROUND_TRUTH_TOPIC, NODE_NAME, GroundTruth, InputTopics, ReplayOptions, ReplayResult, default_out, topic_name
from .run import Replay, replay
from .schedule import RealtimeScheduler, stamp_ordered
from .truth import load_ground_truth

__all__ = ["GROUND_TRUTH_TOPIC", "NODE_NAME", "GroundTruth", "InputTopics", "RealtimeScheduler", "Replay", "ReplayOptions",
           "ReplayResult", "default_out", "discover_inputs", "load_ground_truth", "replay", "stamp_ordered", "topic_name"]

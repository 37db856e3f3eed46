"""``pws import``: bring your own RGB-D data in as recordings that ``pws replay`` and ``pws finetune`` read.

- :mod:`.folder`: a folder of labelled clips (colour + depth images or ``.npy``, a label per frame
  from the folder name or a CSV, the clip of each frame) -> the frames to write (``pws import frames``);
- :mod:`.tum`: a TUM-format RGB-D sequence -> the frames to write (``pws import tum``);
- :mod:`.write`: frames -> a rosbag2 MCAP recording (the camera topics of ``config/pws.yaml`` and
  the labels on ``/pws/ground_truth``), whole or not at all;
- :mod:`.labels`: labels from a CSV of stamps attached to a recording made without them (``pws import labels``).
"""
from __future__ import annotations

from .folder import FolderLayout, plan_frames
from .labels import attach_labels
from .tum import convert as convert_tum
from .write import ImportFrame, Pinhole, write_frames

__all__ = ["FolderLayout", "ImportFrame", "Pinhole", "attach_labels", "convert_tum", "plan_frames", "write_frames"]

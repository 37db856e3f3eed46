"""ROS-free engine of pws_ros: cameras, motion, rendering, partition planning, smoothing,
certification, the CMS baseline and audits. Nothing below this package imports rclpy.

The names below are imported when first used (PEP 562), so that importing one light module of the
package (``pws_ros.core.errors``, as ``pws --help`` does) does not import torch."""
from __future__ import annotations

import importlib
from typing import Any

_WHERE = {"CameraIntrinsics": "camera", "Cloud": "cloud", "cloud_from_rgbd": "cloud", "PwsError": "errors", "AXES": "motion",
          "UNITS": "motion", "parse_axis": "motion", "Renderer": "render", "render": "render"}

__all__ = ["AXES", "UNITS", "CameraIntrinsics", "Cloud", "PwsError", "Renderer", "cloud_from_rgbd", "parse_axis", "render"]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

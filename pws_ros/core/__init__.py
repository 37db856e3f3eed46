"""ROS-free engine of pws_ros: cameras, motion, rendering, partition planning, smoothing,
certification, the CMS baseline and audits. Nothing below this package imports rclpy."""
from .camera import CameraIntrinsics
from .cloud import Cloud, cloud_from_rgbd
from .errors import PwsError
from .motion import AXES, UNITS, parse_axis
from .render import Renderer, render

__all__ = ["AXES", "UNITS", "CameraIntrinsics", "Cloud", "PwsError", "Renderer", "cloud_from_rgbd", "parse_axis", "render"]

"""A seeded procedural RGB-D world (ROS-free): scenes, exact ray-cast views, dense clouds,
rosbag2 recordings of it, and the data the demo models are trained on."""
from .objects import CLASS_NAMES, NUM_CLASSES
from .poses import NUM_VIEWS, Pose, random_pose, view_pose
from .world import BASE_CAMERA, FRAME_ID, Scene, View, default_intrinsics, dense_cloud, dense_cloud_for, make_scene, raycast, render_view

__all__ = [
    "BASE_CAMERA",
    "CLASS_NAMES",
    "FRAME_ID",
    "NUM_CLASSES",
    "NUM_VIEWS",
    "Pose",
    "Scene",
    "View",
    "default_intrinsics",
    "dense_cloud",
    "dense_cloud_for",
    "make_scene",
    "random_pose",
    "raycast",
    "render_view",
    "view_pose",
]

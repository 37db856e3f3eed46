"""Launch the four pws_ros nodes as separate processes (frames and bounds cross on topics).

    ros2 launch pws_ros pws_nodes.launch.py depth:=/camera/aligned_depth_to_color/image_raw \
        color:=/camera/color/image_raw camera_info:=/camera/color/camera_info

cloud_listener -> cloud, cloud/camera_info -> partition_planner -> plan/cloud, plan, plan/poses/<axis> ->
projector -> rendered/frames, rendered/bounds, rendered/errors, rendered/preview -> certifier ->
certification, certification/markers (+ /diagnostics from each). Same arguments as pws.launch.py but workers
(one chain of four nodes).
Prefer pws.launch.py (the pipeline) for speed: here every rendered frame is serialised.
"""
import importlib.util
import os

from launch import LaunchDescription
from launch.actions import OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _load_common():
    """The arguments, parameters and remaps of pws.launch.py (installed beside this file)."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "pws.launch.py")
    spec = importlib.util.spec_from_file_location("pws_ros_pws_launch", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_common = _load_common()
launch_arguments, common_parameters, input_remappings = _common.launch_arguments, _common.common_parameters, _common.input_remappings


def _node(executable, context, remap_inputs=False):
    return Node(
        package="pws_ros",
        executable=executable,
        name=executable,
        namespace=LaunchConfiguration("namespace"),
        parameters=common_parameters(),
        remappings=input_remappings(context) if remap_inputs else [],
        arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
        output="screen",
        emulate_tty=True,
    )


def _nodes(context, *args, **kwargs):
    return [_node("cloud_listener", context, remap_inputs=True), _node("partition_planner", context), _node("projector", context),
            _node("certifier", context)]


def generate_launch_description():
    return LaunchDescription(launch_arguments(workers=False) + [OpaqueFunction(function=_nodes)])

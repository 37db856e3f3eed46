"""Launch the pws_ros ``pipeline``: cloud listener, partition planner, projector and certifier in ONE
process (frames and bounds handed over in memory).

    ros2 launch pws_ros pws.launch.py use_sim_time:=true        # then: ros2 bag play bags/demo --clock
    ros2 launch pws_ros pws.launch.py depth:=/camera/camera/aligned_depth_to_color/image_raw \
        color:=/camera/camera/color/image_raw camera_info:=/camera/camera/color/camera_info
    ros2 launch pws_ros pws.launch.py points:=/kinect/depth_registered/points namespace:=robot1
    ros2 launch pws_ros pws.launch.py workers:=2                 # two pipelines share the input stream

Arguments: config_file, namespace, use_sim_time, log_level, workers, and the input topic remaps points,
depth, color, camera_info (each remaps the default input topic of config/pws.yaml, which are the
RealSense ROS 2 wrapper's names and those of the shipped demo recording bags/demo) and
depth_camera_info (the depth stream's CameraInfo; by default the camera_info beside ``depth``, so that
remapping depth alone moves it too).

workers:=N (default 1: one node named ``pipeline``) starts N pipeline processes ``pipeline_0`` ..
``pipeline_<N-1>`` with num_workers N and worker_index i: each certifies the frames whose stamp is
assigned to it (pws_ros.bridge.workers; worker_period_s in the config chooses the rule), all publish on
the same ``certification`` topic. Node-specific sections of the parameter file then need those names
(the ``/**`` section applies to all).
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

# default input topic of config/pws.yaml -> launch argument that remaps it
INPUT_REMAPS = {
    "/camera/depth/color/points": ("points", "PointCloud2 input (organized or not, xyz + optional packed rgb)"),
    "/camera/aligned_depth_to_color/image_raw": ("depth", "depth Image registered to the colour camera (16UC1 mm or 32FC1 m)"),
    "/camera/color/image_raw": ("color", "colour Image (rgb8, bgr8, rgba8, bgra8, mono8)"),
    "/camera/color/camera_info": ("camera_info", "CameraInfo of the colour camera"),
}


def launch_arguments(workers: bool = True):
    """The launch arguments; ``workers`` only where the launch file starts pipelines."""
    args = [
        DeclareLaunchArgument("config_file", default_value=PathJoinSubstitution([FindPackageShare("pws_ros"), "config", "pws.yaml"]),
                              description="ROS 2 parameter file (see config/pws.yaml for every parameter)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node(s) and their topics"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (set true with `ros2 bag play --clock`)"),
        DeclareLaunchArgument("log_level", default_value="info", description="ROS log level"),
    ]
    if workers:
        args.append(DeclareLaunchArgument("workers", default_value="1",
                                          description="pipeline processes sharing the input stream (each certifies the stamps assigned to it)"))
    for default, (arg, what) in INPUT_REMAPS.items():
        args.append(DeclareLaunchArgument(arg, default_value=default, description=f"input topic: {what}"))
    args.append(DeclareLaunchArgument("depth_camera_info", default_value="",
                                      description="input topic: CameraInfo of the depth stream (its intrinsics are "
                                                  "checked against the colour camera's); empty: the camera_info beside depth"))
    return args


# the config's depth_camera_info_topic 'auto' names the camera_info beside depth_topic: remapped with depth
DEPTH_INFO = "/camera/aligned_depth_to_color/camera_info"


def input_remappings(context):
    """The input remaps, performed in ``context``: each default input topic to its argument, and the depth
    CameraInfo to ``depth_camera_info``, or to the camera_info beside ``depth``."""
    out = [(default, LaunchConfiguration(arg).perform(context)) for default, (arg, _) in INPUT_REMAPS.items()]
    depth = LaunchConfiguration("depth").perform(context)
    info = LaunchConfiguration("depth_camera_info").perform(context) or f"{depth.rpartition('/')[0]}/camera_info"
    return out + [(DEPTH_INFO, info)]


def common_parameters():
    return [LaunchConfiguration("config_file"),
            {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)}]


def pipeline_node(name: str, extra_parameters: list, context):
    return Node(
        package="pws_ros",
        executable="pipeline",
        name=name,
        namespace=LaunchConfiguration("namespace"),
        parameters=common_parameters() + extra_parameters,
        remappings=input_remappings(context),
        arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
        output="screen",
        emulate_tty=True,
    )


def pipeline_nodes(workers: int, context):
    """One node ``pipeline`` (workers 1), else ``pipeline_0`` .. with num_workers and worker_index set."""
    if workers == 1:
        return [pipeline_node("pipeline", [], context)]
    return [pipeline_node(f"pipeline_{i}", [{"num_workers": workers, "worker_index": i}], context) for i in range(workers)]


def _pipelines(context, *args, **kwargs):
    text = LaunchConfiguration("workers").perform(context)
    try:
        workers = int(str(text).strip())
    except ValueError:
        raise RuntimeError(f"workers:={text!r} is not a whole number") from None
    if not 1 <= workers <= 1024:
        raise RuntimeError(f"workers:={workers} must lie in 1 .. 1024")
    return pipeline_nodes(workers, context)


def generate_launch_description():
    return LaunchDescription(launch_arguments() + [OpaqueFunction(function=_pipelines)])

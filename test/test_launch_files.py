"""The launch files: structure checked with recording stand-ins for the ``launch`` API (they only
record constructor arguments; rclpy is not involved; patched in for the test, so this runs whether
ROS 2 is installed or not), and loaded with the real ``launch`` package where ROS 2 is installed."""
from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch"
INPUTS = {"points": "/camera/depth/color/points", "depth": "/camera/aligned_depth_to_color/image_raw",
          "color": "/camera/color/image_raw", "camera_info": "/camera/color/camera_info"}
DEPTH_INFO = "/camera/aligned_depth_to_color/camera_info"


class _Rec:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _stub_modules() -> dict[str, types.ModuleType]:
    mods = {}
    for name in ("launch", "launch.actions", "launch.substitutions", "launch_ros", "launch_ros.actions",
                 "launch_ros.descriptions", "launch_ros.substitutions"):
        mods[name] = types.ModuleType(name)

    class LaunchDescription(_Rec):
        pass

    class LaunchConfiguration(_Rec):
        def perform(self, context):
            return context[self.args[0]]

    mods["launch"].LaunchDescription = LaunchDescription
    mods["launch.actions"].DeclareLaunchArgument = type("DeclareLaunchArgument", (_Rec,), {})
    mods["launch.actions"].OpaqueFunction = type("OpaqueFunction", (_Rec,), {})
    mods["launch.substitutions"].LaunchConfiguration = LaunchConfiguration
    mods["launch.substitutions"].PathJoinSubstitution = type("PathJoinSubstitution", (_Rec,), {})
    mods["launch_ros.actions"].Node = type("Node", (_Rec,), {})
    mods["launch_ros.descriptions"].ParameterValue = type("ParameterValue", (_Rec,), {})
    mods["launch_ros.substitutions"].FindPackageShare = type("FindPackageShare", (_Rec,), {})
    return mods


def _load(path: Path, monkeypatch):
    for name, mod in _stub_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def _split(ld, **values):
    """The declared arguments and the nodes, OpaqueFunctions evaluated with the arguments' defaults
    (``values`` override them)."""
    entities = list(ld.args[0])
    args = {e.args[0]: e.kwargs for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    context = {name: a.get("default_value") for name, a in args.items()}
    context.update(values)
    for e in list(entities):
        if type(e).__name__ == "OpaqueFunction":
            entities.extend(e.kwargs["function"](context))
    nodes = [e.kwargs for e in entities if type(e).__name__ == "Node"]
    return args, nodes


def test_pipeline_launch_structure(monkeypatch):
    args, nodes = _split(_load(LAUNCH / "pws.launch.py", monkeypatch))
    assert {"config_file", "namespace", "use_sim_time", "log_level"} <= set(args)
    assert all(args[a]["description"] for a in args)
    for arg, default in INPUTS.items():
        assert args[arg]["default_value"] == default
    (node,) = nodes
    assert node["package"] == "pws_ros" and node["executable"] == "pipeline" and node["name"] == "pipeline"
    remapped = dict(node["remappings"])
    assert remapped == {**{default: default for default in INPUTS.values()}, DEPTH_INFO: DEPTH_INFO}
    assert node["parameters"][0].args == ("config_file",)
    assert node["parameters"][1]["use_sim_time"].kwargs == {"value_type": bool}
    assert node["namespace"].args == ("namespace",)


def test_pipeline_launch_starts_one_node_per_worker(monkeypatch):
    ld = _load(LAUNCH / "pws.launch.py", monkeypatch)
    args, nodes = _split(ld, workers="3")
    assert args["workers"]["default_value"] == "1" and args["workers"]["description"]
    assert [n["name"] for n in nodes] == ["pipeline_0", "pipeline_1", "pipeline_2"]
    assert all(n["executable"] == "pipeline" and n["remappings"] for n in nodes)
    assert [n["parameters"][-1] for n in nodes] == [{"num_workers": 3, "worker_index": i} for i in range(3)]
    assert all(n["parameters"][0].args == ("config_file",) for n in nodes)
    for bad in ("0", "two", "2000"):
        with pytest.raises(RuntimeError, match="workers"):
            _split(ld, workers=bad)


@pytest.mark.parametrize("launch_file", ["pws.launch.py", "pws_nodes.launch.py"])
def test_remapping_depth_moves_its_camera_info_too(monkeypatch, launch_file):
    """The config's depth_camera_info_topic 'auto' names the camera_info beside depth_topic: a launch that remaps
    depth alone remaps that CameraInfo beside it (before, it stayed on the default topic: the depth intrinsics
    were never checked, an unregistered depth was held forever); depth_camera_info names it explicitly."""
    ld = _load(LAUNCH / launch_file, monkeypatch)
    _args, nodes = _split(ld, depth="/camera/camera/aligned_depth_to_color/image_raw")
    remapped = dict(nodes[0]["remappings"])
    assert remapped[INPUTS["depth"]] == "/camera/camera/aligned_depth_to_color/image_raw"
    assert remapped[DEPTH_INFO] == "/camera/camera/aligned_depth_to_color/camera_info"
    _args, nodes = _split(ld, depth_camera_info="/cam/depth/info")
    assert dict(nodes[0]["remappings"])[DEPTH_INFO] == "/cam/depth/info"


def test_four_process_launch_structure(monkeypatch):
    args, nodes = _split(_load(LAUNCH / "pws_nodes.launch.py", monkeypatch))
    assert {"config_file", "namespace", "use_sim_time", "points", "depth", "color", "camera_info"} <= set(args)
    assert "workers" not in args   # one chain of four nodes: an argument that changed nothing, before
    assert [n["executable"] for n in nodes] == ["cloud_listener", "partition_planner", "projector", "certifier"]
    assert nodes[0]["remappings"] and not any(n["remappings"] for n in nodes[1:])
    assert all(n["parameters"][0].args == ("config_file",) for n in nodes)


def test_default_topic_names_match_the_config():
    from pws_ros.bridge.config import PwsConfig, depth_info_topic

    cfg = PwsConfig()
    assert (cfg.points_topic, cfg.depth_topic, cfg.color_topic, cfg.camera_info_topic) == (
        INPUTS["points"], INPUTS["depth"], INPUTS["color"], INPUTS["camera_info"])
    assert depth_info_topic(cfg) == DEPTH_INFO


def test_setup_installs_launch_and_config():
    text = (REPO / "setup.py").read_text()
    assert 'glob("launch/*.py")' in text and 'glob("config/*.yaml")' in text


def test_package_xml_declares_what_the_nodes_import():
    """Every ROS package the nodes import (each message type's package, /tf_static's, rclpy's parameter
    descriptors, the share-directory lookup) is an exec_depend of package.xml, so rosdep installs it (without
    tf2_msgs the nodes silently skipped /tf_static: depth registration lost with no error)."""
    import xml.etree.ElementTree as ET

    from pws_ros.bridge.msgtypes import MESSAGE_TYPES
    from pws_ros.nodes._base import TF_MESSAGE_TYPE

    root = ET.parse(REPO / "package.xml").getroot()
    exec_deps = {e.text for e in root.iter("exec_depend")}
    needed = {t.split("/")[0] for t in [*MESSAGE_TYPES.values(), TF_MESSAGE_TYPE]}
    needed |= {"rclpy", "rcl_interfaces", "ament_index_python", "launch", "launch_ros", "python3-yaml"}
    assert needed <= exec_deps, sorted(needed - exec_deps)
    assert "python3-hypothesis" in {e.text for e in root.iter("test_depend")}


@pytest.mark.rclpy
def test_launch_files_load_with_the_real_launch_package():
    import launch_ros  # noqa: F401  (part of the ROS 2 install the rclpy marker requires; skipped with rclpy)
    from launch.launch_description_sources import get_launch_description_from_python_launch_file

    for name in ("pws.launch.py", "pws_nodes.launch.py"):
        ld = get_launch_description_from_python_launch_file(str(LAUNCH / name))
        names = {a.name for a in ld.get_launch_arguments()}
        assert {"config_file", "namespace", "use_sim_time", "points", "depth", "color", "camera_info"} <= names

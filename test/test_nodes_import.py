"""The node modules exist, compile and import without ROS; rclpy is imported nowhere else; main()
exits with a clear message where rclpy is missing."""
from __future__ import annotations

import ast
import importlib
import py_compile
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "pws_ros"
NODES = ("cloud_listener", "partition_planner", "projector", "certifier", "pipeline")
ROS_MODULES = ("rclpy", "rcl_interfaces", "launch", "launch_ros", "sensor_msgs", "std_msgs", "geometry_msgs",
               "diagnostic_msgs", "visualization_msgs", "builtin_interfaces")


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module" and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                out.add(arg.value.split(".")[0])
    return out


def test_the_ros_glue_defines_what_the_nodes_use():
    """``_ros`` (the one module importing rclpy) cannot be imported here: it must at least compile and
    define, at top level, every ``_ros.NAME`` the other node modules use (the rest import in the test below)."""
    glue = PKG / "nodes" / "_ros.py"
    py_compile.compile(str(glue), doraise=True)
    tree = ast.parse(glue.read_text())
    defined = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    defined |= {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
    used = set()
    for name in NODES + ("_common", "__init__"):
        for node in ast.walk(ast.parse((PKG / "nodes" / f"{name}.py").read_text())):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "_ros":
                used.add(node.attr)
            elif isinstance(node, ast.ImportFrom) and node.level == 1 and node.module == "_ros":
                used.update(a.name for a in node.names)
    assert used, "no node module uses _ros: the glue is dead code or this test is out of date"
    assert used <= defined, f"used from _ros but not defined there: {sorted(used - defined)}"


def test_rclpy_is_imported_only_in_the_nodes_package():
    offenders = []
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(REPO)
        ros = imported_modules(path) & set(ROS_MODULES)
        if ros and rel.parts[:2] != ("pws_ros", "nodes"):
            offenders.append(f"{rel}: {sorted(ros)}")
    assert not offenders, offenders


def test_only_the_ros_glue_module_imports_rclpy_at_top_level():
    for name in NODES + ("_common", "__init__"):
        tree = ast.parse((PKG / "nodes" / f"{name}.py").read_text())
        top = set()
        for node in tree.body:
            if isinstance(node, ast.Import):
                top.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                top.add(node.module.split(".")[0])
            elif isinstance(node, ast.ImportFrom) and node.level == 1 and node.module == "_ros":
                top.add("_ros")
        assert not (top & (set(ROS_MODULES) | {"_ros"})), f"{name}.py imports {top & set(ROS_MODULES)} at module level"


@pytest.mark.parametrize("name", NODES)
def test_node_modules_import_and_have_main(name):
    mod = importlib.import_module(f"pws_ros.nodes.{name}")
    assert callable(mod.main) and mod.NODE_NAME == name


def test_console_scripts_point_at_the_node_mains():
    text = (REPO / "setup.py").read_text()
    for name in NODES:
        assert f"{name} = pws_ros.nodes.{name}:main" in text


def test_main_without_rclpy_exits_with_a_clear_message():
    # rclpy hidden in the child process (as on a machine without ROS 2), so this runs with or without it
    code = ("import sys\n"
            "sys.modules['rclpy'] = None\n"
            "for name in %r:\n"
            "    mod = __import__('pws_ros.nodes.' + name, fromlist=['main'])\n"
            "    try:\n"
            "        mod.main([])\n"
            "    except SystemExit as exc:\n"
            "        print(name, exc.code)\n" % (NODES,))
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [w for name in NODES for w in (name, "2")]
    for name in NODES:
        assert f"{name}: rclpy (ROS 2 Jazzy) is not importable" in proc.stderr
    assert "Traceback" not in proc.stderr

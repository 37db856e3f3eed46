"""The package's import structure, read from the source with ``ast`` (nothing is imported):

- no import circle between modules of ``pws_ros`` (imports inside functions count: a lazy import is
  still an arrow, and a circle of lazy imports is still a circle);
- the layers point down: ``pws_ros.core`` (the ROS-free engine) imports none of bridge, nodes, replay,
  bagio, commands, bench, sim or cli; nothing but ``pws_ros.cli`` and the commands themselves imports
  ``pws_ros.commands`` (the CLI is the top layer: bench, replay, bridge, core never reach up into it);
- ``rclpy`` (and the other ROS 2 client packages) is imported only under ``pws_ros/nodes``.

A new circle or upward arrow fails here with the modules and lines that make it.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "pws_ros"
PACKAGE_DIR = ROOT / PACKAGE

# The core must not import these (they all sit above it).
CORE_MUST_NOT_IMPORT = ("bridge", "nodes", "replay", "bagio", "commands", "bench", "sim", "cli")
# Only these may import pws_ros.commands.
COMMANDS_IMPORTERS = ("pws_ros.cli", "pws_ros.commands")
# ROS 2 client packages: only pws_ros/nodes may import them.
ROS_PACKAGES = ("rclpy", "rosidl_runtime_py", "launch_ros", "builtin_interfaces", "sensor_msgs", "std_msgs",
                "diagnostic_msgs", "geometry_msgs", "visualization_msgs", "tf2_msgs", "tf2_ros")

# Known circles that another change is removing; listed here only while they exist (the test fails
# when a listed circle is gone, so the exception cannot outlive it: delete the entry then).
KNOWN_CIRCLES: list[frozenset[str]] = []


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE_DIR.rglob("*.py"))}


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute name of ``from <level dots><target> import ...`` written in ``module``."""
    if level == 0:
        return target or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (level - 1)] if level > 1 else base
    return ".".join(base + ([target] if target else []))


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported module, line) for every import statement of a module, anywhere in it. ``from X import
    y`` imports ``X.y`` when that is a module of the package, else ``X``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(name, is_package, node.level, node.module)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.append((sub if sub in modules else base, node.lineno))
    return out


def import_graph() -> tuple[dict[str, set[str]], dict[tuple[str, str], int]]:
    """Arrows between the package's own modules, and the line of each arrow."""
    modules = all_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    lines: dict[tuple[str, str], int] = {}
    for name, path in modules.items():
        for target, line in imports_of(name, path, modules):
            if target in modules and target != name:
                graph[name].add(target)
                lines.setdefault((name, target), line)
    return graph, lines


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:  # recursion depth is bounded by the number of modules (~150)
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _shortest_loop(start: str, graph: dict[str, set[str]], members: set[str]) -> list[str] | None:
    """A shortest import loop from ``start`` back to it inside ``members`` (breadth first)."""
    prev: dict[str, str] = {}
    frontier, seen = [start], {start}
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & members):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return path[::-1] + [start]
                if w not in seen:
                    seen.add(w)
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    return None


def _describe(comp: list[str], graph: dict[str, set[str]], lines: dict[tuple[str, str], int]) -> str:
    """The circle's modules and one shortest loop through them, with the line of each arrow."""
    loops = [loop for loop in (_shortest_loop(m, graph, set(comp)) for m in comp) if loop]
    loop = min(loops, key=len)
    steps = " -> ".join(f"{b} (line {lines[a, b]})" for a, b in zip(loop, loop[1:]))
    return f"{len(comp)} modules {{{', '.join(comp)}}}, e.g. {loop[0]} -> {steps}"


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_the_package_is_found():
    modules = all_modules()
    assert f"{PACKAGE}.core.certify" in modules and f"{PACKAGE}.cli" in modules
    graph, _ = import_graph()
    assert sum(len(v) for v in graph.values()) > 100  # the scanner sees the arrows


def test_no_import_circles():
    graph, lines = import_graph()
    comps = circles(graph)
    unexpected = [c for c in comps if frozenset(c) not in KNOWN_CIRCLES]
    assert not unexpected, "import circles:\n" + "\n".join(_describe(c, graph, lines) for c in unexpected)
    gone = [sorted(k) for k in KNOWN_CIRCLES if sorted(k) not in comps]
    assert not gone, f"known circles that no longer exist (remove them from KNOWN_CIRCLES): {gone}"


def test_the_core_imports_nothing_above_it():
    graph, lines = import_graph()
    above = tuple(f"{PACKAGE}.{p}" for p in CORE_MUST_NOT_IMPORT)
    bad = [f"{a} -> {b} (line {lines[a, b]})" for a in sorted(graph) if _in(a, f"{PACKAGE}.core")
           for b in sorted(graph[a]) if any(_in(b, p) for p in above)]
    assert not bad, "pws_ros.core imports from above it:\n" + "\n".join(bad)


def test_nothing_reaches_up_into_the_commands():
    graph, lines = import_graph()
    bad = [f"{a} -> {b} (line {lines[a, b]})" for a in sorted(graph) if not any(_in(a, p) for p in COMMANDS_IMPORTERS)
           for b in sorted(graph[a]) if _in(b, f"{PACKAGE}.commands")]
    assert not bad, "imports of pws_ros.commands from below it (core, bridge, replay, bench, ...):\n" + "\n".join(bad)


def test_ros_client_packages_only_in_the_nodes():
    modules = all_modules()
    bad = []
    for name, path in modules.items():
        if _in(name, f"{PACKAGE}.nodes"):
            continue
        for target, line in imports_of(name, path, modules):
            if target.split(".")[0] in ROS_PACKAGES:
                bad.append(f"{name} imports {target} (line {line})")
    assert not bad, "ROS 2 client packages imported outside pws_ros/nodes:\n" + "\n".join(bad)


@pytest.mark.parametrize("source, expected", [
    ({"a": {"b"}, "b": {"a"}, "c": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}, [["a", "b", "c"]]),
    ({"a": {"b"}, "b": set()}, []),
])
def test_the_circle_finder(source, expected):
    assert circles(source) == expected


def test_relative_imports_resolve(tmp_path):
    assert _resolve("pws_ros.core.model", False, 1, "errors") == "pws_ros.core.errors"
    assert _resolve("pws_ros.core.model", False, 2, "bridge.config") == "pws_ros.bridge.config"
    assert _resolve("pws_ros.replay", True, 1, "run") == "pws_ros.replay.run"
    assert _resolve("pws_ros.replay", True, 2, None) == "pws_ros"
    assert _resolve("pws_ros.bench.frame_timing", False, 2, "commands.replay") == "pws_ros.commands.replay"

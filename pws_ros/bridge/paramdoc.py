"""``config/pws.yaml`` and the parameter table of ``docs/ros2.md``, generated from
:data:`~pws_ros.bridge.params.PARAMS` (a test checks both files are up to date)."""
from __future__ import annotations

from typing import Any

import yaml

from .params import PARAMS, ParamSpec


def _yaml_value(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return yaml.safe_dump(v, default_style='"').strip() if (v == "" or any(c in v for c in ":#{}[],&*?|<>=!%@`'\"")) else v
    return str(v)


def _range_text(spec: ParamSpec) -> str:
    if spec.choices is not None:
        return "one of: " + ", ".join(spec.choices) if spec.kind == "str" else "each of: " + ", ".join(spec.choices)
    if spec.range is not None:
        lo, hi = spec.range
        return f"range [{lo:g}, {hi:g}]" + (f" {spec.unit}" if spec.unit else "")
    return ""


def render_params_yaml(config: Any = None) -> str:
    """``config/pws.yaml``: every parameter under ``/**: ros__parameters`` with its description,
    range or choices, and which nodes read it (values from ``config``, default the table's)."""
    lines = [
        "# pws_ros parameters (ROS 2 parameter file). Generated from pws_ros/bridge/params.py PARAMS:",
        "# the table is the single source of truth for names, defaults, ranges and descriptions.",
        "# '/**' applies to every node; add a section named after a node (e.g. 'certifier:') to override",
        "# a value for that node only. (ro) = read-only once the node runs; others can be set at run time",
        "# with 'ros2 param set' and are validated.",
        "/**:",
        "  ros__parameters:",
    ]
    params = config.to_params() if config is not None else {p.name: p.default for p in PARAMS}
    groups = {"radius": "requested certification radius b per axis: the motion range is [-b, b]",
              "working_volume": "surfel imaging: the working volume, the part of the one-frame cloud that is drawn "
                                "(docs/imaging.md section 4a); far: 0 = none"}
    opened = ""
    for spec in PARAMS:
        extra = _range_text(spec)
        meta = "; ".join(x for x in (extra, "(ro)" if spec.read_only else "", "nodes: " + ", ".join(spec.nodes)) if x)
        group, _, key = spec.name.rpartition(".")
        if group:   # dotted names nest, as ROS 2 parameter files write them
            if group != opened:
                lines.append(f"    # {groups[group]}")
                lines.append(f"    {group}:")
                opened = group
            lines.append(f"      # {spec.description}; {meta}")
            lines.append(f"      {key}: {_yaml_value(params[spec.name])}")
            continue
        opened = ""
        lines.append(f"    # {spec.description}; {meta}")
        lines.append(f"    {spec.name}: {_yaml_value(params[spec.name])}")
    return "\n".join(lines) + "\n"


def render_params_markdown() -> str:
    """The parameter table of ``docs/ros2.md`` (name, default, range or choices, nodes, description)."""
    rows = ["| parameter | default | range / choices | nodes | description |", "|---|---|---|---|---|"]
    short = {"cloud_listener": "L", "partition_planner": "Pl", "projector": "Pr", "certifier": "C", "pipeline": "P"}
    for spec in PARAMS:
        d = spec.default
        default = ", ".join(d) if isinstance(d, (list, tuple)) else ("" if d == "" else _yaml_value(d))
        rng = _range_text(spec).replace("one of: ", "").replace("each of: ", "")
        nodes = " ".join(short[n] for n in spec.nodes)
        ro = " (read-only)" if spec.read_only else ""
        rows.append(f"| `{spec.name}` | `{default}` | {rng} | {nodes} | {spec.description}{ro} |".replace("``", "(empty)"))
    return "\n".join(rows) + "\n"

__all__ = ["render_params_markdown", "render_params_yaml"]

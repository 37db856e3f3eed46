"""The validated parameter values of the node suite (:class:`PwsConfig`, built from the table
:data:`~pws_ros.bridge.params.PARAMS`), the cross-parameter rules, loading of ``config/pws.yaml`` and
finding shipped files.

``config/pws.yaml`` uses the ROS 2 parameter-file layout::

    /**:                      # every node (wildcard), or a node name such as "pipeline"
      ros__parameters:
        axes: [tz, ry]
        radius:
          tz: 0.010           # nested keys become dotted parameter names: radius.tz
        ...

Sections are merged in file order with node-specific sections (``pipeline``, ``/pws/pipeline`` ...)
overriding the wildcards when ``node_name`` is given.

The table, its validation and the generated files live in :mod:`pws_ros.bridge.params` and
:mod:`pws_ros.bridge.paramdoc`; their public names are importable from here too.
"""
from __future__ import annotations

import os
import sys
from dataclasses import field, fields, make_dataclass, replace
from pathlib import Path
from typing import Any, Iterable

from ..core.errors import PwsError, read_yaml_file, require
from .params import (COVERAGES, DEMO_MODEL, INFO_SYNC, INPUT_MODES, METHODS, NODES, PARAMS, QOS_PROFILES, SPECS, ParamSpec,
                     spec_table, validate_param, validate_params)
from .paramdoc import render_params_markdown, render_params_yaml

_TYPES = {"bool": bool, "int": int, "float": float, "str": str, "str_list": "tuple[str, ...]"}


class _ConfigMethods:
    """The methods of :class:`PwsConfig` (its fields come from the table)."""

    __slots__ = ()

    def radius_for(self, axis: str) -> float:
        return float(getattr(self, f"radius_{axis}"))

    @property
    def working_volume(self):
        """The :class:`~pws_ros.core.volume.WorkingVolume` of the ``working_volume.*`` parameters (None: far = 0,
        every point is drawn); PwsError naming a bad combination."""
        from ..core.volume import volume_from_limits

        return volume_from_limits(self.working_volume_near, self.working_volume_far, self.working_volume_x_min,
                                  self.working_volume_x_max, self.working_volume_y_min, self.working_volume_y_max,
                                  self.working_volume_window)

    @property
    def background_value(self) -> float:
        """``background`` with -1 (automatic) resolved: 0.5 with a working volume, else 0.0."""
        from ..core.volume import resolve_background

        return resolve_background(self.background, self.working_volume)

    @property
    def radii(self) -> dict[str, float]:
        return {a: self.radius_for(a) for a in self.axes}

    def to_params(self) -> dict[str, Any]:
        """``{dotted name: value}`` with list-valued parameters as lists (ROS parameter values)."""
        out = {}
        for spec in PARAMS:
            v = getattr(self, spec.attr)
            out[spec.name] = list(v) if isinstance(v, tuple) else v
        return out

    def with_params(self, params: dict[str, Any]) -> "PwsConfig":
        """A copy with some parameters changed (validated)."""
        return replace(self, **{SPECS[k].attr: v for k, v in validate_params(params).items()})

    def certify_config(self):
        """The core's ``CertifyConfig`` for these parameters (its fields of the same names; delta and
        cms_sigma 0 mean the core's default)."""
        from ..core.certify import CertifyConfig

        same = {f.name: getattr(self, f.name) for f in fields(CertifyConfig) if f.name in _ATTRS}
        same.update(delta=self.delta if self.delta > 0 else None, cms_sigma=self.cms_sigma if self.cms_sigma > 0 else None,
                    working_volume=self.working_volume, background=self.background_value)
        return CertifyConfig(**same)


_ATTRS = frozenset(p.attr for p in PARAMS)

PwsConfig = make_dataclass(
    "PwsConfig",
    [(p.attr, _TYPES[p.kind], field(default=tuple(p.default) if isinstance(p.default, list) else p.default)) for p in PARAMS],
    bases=(_ConfigMethods,), frozen=True, namespace={"__module__": __name__})
PwsConfig.__doc__ = ("Validated parameter values: one field per parameter of :data:`~pws_ros.bridge.params.PARAMS` "
                     "(attribute = parameter name with dots as underscores; default = the table's).")


def check_consistency(cfg: PwsConfig) -> None:
    """Cross-parameter rules (PwsError): pws needs a dense cloud; render size given in full; a worker index
    below the number of workers; a working volume of positive size, with surfel imaging."""
    require(not (cfg.method == "pws" and not cfg.dense_cloud_path),
            "method pws needs the entire scene cloud: set dense_cloud_path (or use pws_of / pws_l with the one-frame cloud)")
    require((cfg.render_width == 0) == (cfg.render_height == 0),
            f"render_width and render_height must both be 0 or both set, got {cfg.render_width}x{cfg.render_height}")
    require(cfg.worker_index < cfg.num_workers,
            f"worker_index {cfg.worker_index} must be below num_workers {cfg.num_workers} (workers are numbered from 0)")
    require(cfg.working_volume is None or cfg.imaging == "surfel",
            "working_volume needs imaging: surfel (imaging: paper draws every point): set working_volume.far to 0 or use surfel")
    require(not (cfg.method == "pws" and cfg.imaging == "surfel"),
            "method pws plans on the entire scene cloud, which has no depth pixels to make surfels of: set imaging: paper "
            "(or use pws_of / pws_l with the one-frame cloud)")


def config_from_params(params: dict[str, Any] | None = None, *, check: bool = True, ignore_unknown: Iterable[str] = ("use_sim_time",)) -> PwsConfig:
    """A :class:`PwsConfig` from ``{dotted name: value}`` (missing = default)."""
    params = dict(params or {})
    for k in list(params):
        if k in ignore_unknown or k.startswith("qos_overrides."):
            params.pop(k)
    cfg = PwsConfig().with_params(params)
    if check:
        check_consistency(cfg)
    return cfg

# ---- YAML ---------------------------------------------------------------------------------

def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> dotted keys (ROS parameter-file semantics)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _node_matches(section: str, node_name: str | None) -> bool:
    if section in ("/**", "**"):
        return True
    if node_name is None:
        return False
    s = section.strip("/")
    return s == node_name or s.endswith("/" + node_name) or s in (f"**/{node_name}",)


def params_from_yaml_dict(data: Any, node_name: str | None = None, source: str = "config") -> dict[str, Any]:
    """Parameters of ``node_name`` from a ROS 2 parameter-file mapping (wildcard sections first,
    then the node's own sections). Also accepts a bare ``{ros__parameters: {...}}`` or a flat mapping."""
    require(isinstance(data, dict), f"{source}: expected a mapping at the top level")
    if "ros__parameters" in data:
        require(isinstance(data["ros__parameters"], dict), f"{source}: ros__parameters must be a mapping")
        return flatten(data["ros__parameters"])
    sections = [(k, v) for k, v in data.items() if isinstance(v, dict) and "ros__parameters" in v]
    if not sections:  # a flat mapping of parameters
        return flatten(data)
    merged: dict[str, Any] = {}
    wild = [(k, v) for k, v in sections if str(k) in ("/**", "**")]
    own = [(k, v) for k, v in sections if str(k) not in ("/**", "**") and _node_matches(str(k), node_name)]
    # a file whose every section is for other nodes configures nothing here: surely a misnamed section (a
    # shared file of a robot stack has sections for other nodes too, and then one for these or '/**')
    require(any(_node_matches(str(k), n) for k, _ in sections for n in NODES),
            f"{source}: no section applies to pws_ros (sections: {', '.join(str(k) for k, _ in sections)}): "
            f"name one '/**' (every node) or after a node ({', '.join(NODES)})")
    for k, v in wild + own:
        body = v["ros__parameters"]
        require(isinstance(body, dict), f"{source}: {k}.ros__parameters must be a mapping")
        merged.update(flatten(body))
    return merged


def load_config(path: str | Path, node_name: str | None = None, overrides: dict[str, Any] | None = None,
                check: bool = True) -> PwsConfig:
    path = Path(path)
    data = read_yaml_file(path, "config file")
    params = params_from_yaml_dict(data or {}, node_name, source=f"config file {path}")
    params.update(overrides or {})
    try:
        return config_from_params(params, check=check)
    except PwsError as exc:
        raise PwsError(f"config file {path}: {exc}") from None


# ---- paths --------------------------------------------------------------------------------

def package_share_dirs() -> list[Path]:
    """Where shipped files may live: the ament share directory (if ROS is installed) and the source
    checkout (for ``pip install -e`` and tests)."""
    dirs: list[Path] = []
    try:  # ament_index_python is plain Python (no rclpy)
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        dirs.append(Path(get_package_share_directory("pws_ros")))
    except Exception:
        pass
    env = os.environ.get("PWS_ROS_SHARE")
    if env:
        dirs.append(Path(env))
    dirs.append(Path(sys.prefix) / "share" / "pws_ros")  # data_files of a pip install
    dirs.append(Path(__file__).resolve().parents[2])
    return dirs


def depth_info_topic(config: PwsConfig) -> str:
    """The depth stream's CameraInfo topic: ``depth_camera_info_topic``, where ``auto`` names the
    ``camera_info`` beside ``depth_topic`` (the image_transport convention), and "" means none."""
    name = config.depth_camera_info_topic
    if name != "auto":
        return name
    base, _, _ = config.depth_topic.rpartition("/")
    return f"{base}/camera_info" if base or config.depth_topic.startswith("/") else "camera_info"


def resolve_path(path: str | Path, what: str = "file") -> Path:
    """An existing file: absolute, relative to the current directory, or to a package share directory.

    PwsError naming every place looked at when none holds it.
    """
    p = Path(os.path.expanduser(str(path)))
    require(str(path).strip() != "", f"{what} path is empty")
    if p.is_absolute():
        require(p.exists(), f"{what} not found: {p}")
        return p
    tried = [Path.cwd() / p] + [d / p for d in package_share_dirs()]
    for cand in tried:
        if cand.exists():
            return cand
    raise PwsError(f"{what} not found: {path} (looked in {', '.join(str(t.parent) for t in tried)})")


def default_config_path() -> Path:
    return resolve_path("config/pws.yaml", "config file")


__all__ = ["COVERAGES", "DEMO_MODEL", "INFO_SYNC", "INPUT_MODES", "METHODS", "NODES", "PARAMS", "ParamSpec", "PwsConfig", "QOS_PROFILES",
           "SPECS", "check_consistency", "config_from_params", "default_config_path", "flatten", "load_config",
           "params_from_yaml_dict", "depth_info_topic", "render_params_markdown", "render_params_yaml", "resolve_path", "spec_table", "validate_param", "validate_params"]

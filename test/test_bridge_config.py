"""The parameter table, validation and config/pws.yaml loading (pws_ros.bridge.config)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import yaml

from pws_ros.bridge import config as C
from pws_ros.core.errors import PwsError
from pws_ros.core.motion import AXES, PAPER_RADIUS

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "config" / "pws.yaml"


def test_table_and_dataclass_agree():
    attrs = {f.name for f in dataclasses.fields(C.PwsConfig)}
    assert attrs == {p.attr for p in C.PARAMS}
    assert len({p.name for p in C.PARAMS}) == len(C.PARAMS)
    base = C.PwsConfig()
    for p in C.PARAMS:
        assert p.description and "\n" not in p.description
        assert set(p.nodes) <= set(C.NODES)
        value = getattr(base, p.attr)
        assert C.validate_param(p.name, list(value) if isinstance(value, tuple) else value) == value
        if p.range is not None:
            assert p.range[0] <= p.range[1] and p.kind in ("int", "float")


def test_demo_defaults():
    cfg = C.PwsConfig()
    assert cfg.axes == ("tz", "ry") and cfg.method == "pws_of" and cfg.coverage == "anchors"
    assert cfg.min_partitions == 0 and cfg.max_partitions == 257
    assert (cfg.imaging, cfg.border, cfg.step_px) == ("surfel", -1, 0.25)
    assert cfg.radius_tz == 0.010 and cfg.radius_ry == pytest.approx(math.radians(0.25))
    assert (cfg.sigma, cfg.n0, cfg.n, cfg.alpha) == (0.5, 64, 256, 0.01)
    assert cfg.model_path == "bags/models/classifier_sigma0.50.pt"
    assert cfg.radii == {"tz": 0.010, "ry": PAPER_RADIUS["ry"]}


def test_shipped_yaml_documents_every_parameter_with_the_table_defaults():
    text = SHIPPED.read_text()
    data = yaml.safe_load(text)
    params = C.params_from_yaml_dict(data, "pipeline")
    assert set(params) == {p.name for p in C.PARAMS}
    assert C.load_config(SHIPPED, "pipeline") == C.PwsConfig()
    for p in C.PARAMS:  # each parameter has its description as a comment
        assert p.description in text
    assert text == C.render_params_yaml(), "config/pws.yaml is generated: run render_params_yaml() after changing PARAMS"


@pytest.mark.parametrize("name,value,message", [
    ("sigma", 0.0, r"sigma=0\.0 is out of range"),
    ("sigma", "0.5", "must be a number"),
    ("sigma", math.nan, "must be finite"),
    ("n", 2.5, "must be an integer"),
    ("n", True, "must be an integer"),
    ("n0", 0, "out of range"),
    ("alpha", 0.7, "out of range"),
    ("method", "pws_x", "is not one of pws, pws_l, pws_of, cms"),
    ("coverage", "all", "is not one of paper, pairwise, anchors"),
    ("axes", ["tz", "yaw"], "'yaw' not in tx, ty, tz, rx, ry, rz"),
    ("axes", ["tz", "tz"], "lists an entry twice"),
    ("axes", [], "must not be empty"),
    ("radius.tz", -0.01, "out of range"),
    ("publish_cloud", 1, "must be true or false"),
    ("sigmaa", 0.5, "unknown parameter 'sigmaa' \\(did you mean 'sigma'\\?\\)"),
])
def test_validation_errors_name_the_parameter(name, value, message):
    with pytest.raises(PwsError, match=message):
        C.validate_param(name, value)


def test_normalisation():
    assert C.validate_param("axes", ["TZ", " ry"]) == ("tz", "ry")
    assert C.validate_param("axes", "tz, rx") == ("tz", "rx")
    assert C.validate_param("n", 100.0) == 100
    assert C.validate_param("sigma", 1) == 1.0 and isinstance(C.validate_param("sigma", 1), float)


def test_cross_parameter_rules():
    with pytest.raises(PwsError, match="method pws needs the entire scene cloud: set dense_cloud_path"):
        C.config_from_params({"method": "pws"})
    with pytest.raises(PwsError, match="set imaging: paper"):
        C.config_from_params({"method": "pws", "dense_cloud_path": "scene.npz"})
    assert C.config_from_params({"method": "pws", "dense_cloud_path": "scene.npz", "imaging": "paper"}).method == "pws"
    with pytest.raises(PwsError, match="render_width and render_height"):
        C.config_from_params({"render_width": 32})
    cfg = C.config_from_params({"use_sim_time": True, "qos_overrides./x.subscription.depth": 3})
    assert cfg == C.PwsConfig()


def test_node_sections_override_wildcards(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({
        "/**": {"ros__parameters": {"sigma": 0.25, "radius": {"tz": 0.02}, "axes": ["tx"]}},
        "certifier": {"ros__parameters": {"sigma": 0.75}},
        "/robot/pipeline": {"ros__parameters": {"n": 512}},
    }))
    assert C.load_config(p).sigma == 0.25
    cert = C.load_config(p, "certifier")
    assert cert.sigma == 0.75 and cert.radius_tz == 0.02 and cert.axes == ("tx",)
    assert C.load_config(p, "pipeline").n == 512 and C.load_config(p, "pipeline").sigma == 0.25
    assert C.load_config(p, "pipeline", overrides={"n": 8}).n == 8


def test_a_file_whose_sections_all_name_other_nodes_is_refused(tmp_path):
    """A parameter file with sections for other nodes only (a misnamed section, e.g. 'pws:') would configure
    nothing: refused, naming the sections and the valid names; one section of ours among others is fine."""
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"pws": {"ros__parameters": {"time_budget_s": 10.0}},
                                 "/robot/camera_driver": {"ros__parameters": {"fps": 30}}}))
    with pytest.raises(PwsError, match=r"no section applies to pws_ros \(sections: /robot/camera_driver, pws\).*'/\*\*'.*pipeline"):
        C.load_config(p, "pipeline")
    p.write_text(yaml.safe_dump({"/robot/camera_driver": {"ros__parameters": {"fps": 30}},
                                 "/robot/certifier": {"ros__parameters": {"time_budget_s": 10.0}}}))
    assert C.load_config(p, "certifier").time_budget_s == 10.0
    assert C.load_config(p, "pipeline").time_budget_s == C.PwsConfig().time_budget_s   # another node's section


def test_flat_and_bare_layouts(tmp_path):
    assert C.params_from_yaml_dict({"ros__parameters": {"radius": {"rx": 0.1}}}) == {"radius.rx": 0.1}
    assert C.params_from_yaml_dict({"sigma": 0.3, "radius": {"rz": 0.2}}) == {"sigma": 0.3, "radius.rz": 0.2}


def test_bad_files(tmp_path):
    with pytest.raises(PwsError, match="config file not found"):
        C.load_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(PwsError, match="is not valid YAML"):
        C.load_config(bad)
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("/**:\n  ros__parameters:\n    n0: -3\n")
    with pytest.raises(PwsError, match=r"wrong\.yaml: parameter n0=-3 is out of range"):
        C.load_config(wrong)
    notmap = tmp_path / "list.yaml"
    notmap.write_text("- 1\n- 2\n")
    with pytest.raises(PwsError, match="expected a mapping"):
        C.load_config(notmap)


def test_resolve_path(tmp_path, monkeypatch):
    f = tmp_path / "m.pt"
    f.write_text("x")
    assert C.resolve_path(str(f)) == f
    monkeypatch.chdir(tmp_path)
    assert C.resolve_path("m.pt") == tmp_path / "m.pt"
    # the installed package share (a colcon install), else the source checkout: the same file
    found = C.resolve_path("config/pws.yaml")
    assert found.name == "pws.yaml" and found.read_bytes() == (REPO / "config" / "pws.yaml").read_bytes()
    with pytest.raises(PwsError, match="model file not found: nope.pt"):
        C.resolve_path("nope.pt", "model file")
    with pytest.raises(PwsError, match="path is empty"):
        C.resolve_path("", "model file")


def test_spec_table_per_node():
    planner = {p.name for p in C.spec_table(["partition_planner"])}
    assert "axes" in planner and "batch_size" not in planner and "points_topic" not in planner
    # the planner refines the grid for the certifier's adaptive anchors: it reads what their target depends on
    assert {"coverage", "sigma", "n0", "n", "alpha", "num_anchors"} <= planner
    assert {p.name for p in C.spec_table(["pipeline"])} == {p.name for p in C.PARAMS if "pipeline" in p.nodes}
    assert all(f"radius.{a}" in planner for a in AXES)


def test_certify_config_mapping():
    cfg = C.config_from_params({"sigma": 0.25, "n0": 10, "n": 20, "delta": 0.0, "cms_sigma": 0.05})
    cc = cfg.certify_config()
    assert (cc.sigma, cc.n0, cc.n, cc.delta, cc.cms_sigma, cc.coverage) == (0.25, 10, 20, None, 0.05, "anchors")
    # every setting the core reads arrives, by its own name (written out: the mapping is by field name)
    given = {"alpha": 0.05, "seed": 7, "batch_size": 16, "coverage": "pairwise", "num_anchors": 4, "background": 0.3,
             "max_partitions": 100, "max_memory_mb": 512.0, "min_partitions": 5, "imaging": "paper", "border": 3,
             "step_px": 0.5, "render_factor": 1, "delta": 2.0, "cms_sigma": 0.0}
    cc = C.config_from_params(given).certify_config()
    assert {k: getattr(cc, k) for k in given} == {**given, "cms_sigma": None}
    assert cc.chunk == 128 and cc.device == "cpu"


def test_docs_ros2_is_in_sync_with_the_table_and_schema():
    from pws_ros.bridge.msgbuild import DIAGNOSTIC_EXTRA_KEYS, DIAGNOSTIC_KEYS

    text = (REPO / "docs" / "ros2.md").read_text()
    begin = "<!-- params:begin (generated by pws_ros.bridge.config.render_params_markdown) -->\n"
    table = text[text.index(begin) + len(begin): text.index("<!-- params:end -->")]
    assert table == C.render_params_markdown(), "docs/ros2.md parameter table is stale: regenerate it"
    for key in DIAGNOSTIC_KEYS:
        assert f"| `{key}` |" in text
    assert ", ".join(f"`{k}`" for k in DIAGNOSTIC_EXTRA_KEYS) in " ".join(text.split())
    for topic in ("certification", "certification/markers", "plan/poses/<axis>", "rendered/frames", "rendered/bounds",
                  "rendered/errors", "rendered/preview", "/diagnostics", "certified_label", "certification/overlay"):
        assert f"`{topic}`" in text


def test_depth_info_topic_follows_the_image_transport_convention():
    cfg = C.PwsConfig()
    assert cfg.depth_camera_info_topic == "auto"
    assert C.depth_info_topic(cfg) == "/camera/aligned_depth_to_color/camera_info"
    assert C.depth_info_topic(cfg.with_params({"depth_topic": "depth/image_rect_raw"})) == "depth/camera_info"
    assert C.depth_info_topic(cfg.with_params({"depth_topic": "image_raw"})) == "camera_info"
    assert C.depth_info_topic(cfg.with_params({"depth_topic": "/image_raw"})) == "/camera_info"
    assert C.depth_info_topic(cfg.with_params({"depth_camera_info_topic": "/d/info"})) == "/d/info"
    assert C.depth_info_topic(cfg.with_params({"depth_camera_info_topic": ""})) == ""

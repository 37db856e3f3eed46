"""What the commands say matches what they do: an empty --depth-info-topic turns the registration
check off, the cms setup line names no coverage rule, `pws plan` and `pws certify` with --method pws warn on
a one-frame cloud, and --max-partitions says what happens to a too-big plan."""
from __future__ import annotations

import numpy as np

from pws_ros import cli
from pws_ros.bridge import msgbuild
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.cloud import Cloud
from test_replay import TINY, TOPIC_INFO, certifications, models, run_cli, sim_bag, sim_msgs, write_bag  # noqa: F401

T = msgbuild.rosbags_types()
DEPTH_INFO = "/camera/aligned_depth_to_color/camera_info"


def test_empty_depth_info_topic_turns_the_registration_check_off(sim_msgs, models, tmp_path, capsys):  # noqa: F811
    # a depth CameraInfo whose focal length differs from the colour camera's: depth is "not registered"
    items = [(t, ty, lt, raw) for t, ty, lt, _d, raw in sim_msgs if t != "/camera/depth/color/points"]
    for t, ty, lt, d, _raw in sim_msgs:
        if t == TOPIC_INFO:
            k = list(d.k)
            k[0] *= 1.5
            other = T.CameraInfo(header=d.header, height=d.height, width=d.width, distortion_model=d.distortion_model,
                                 d=d.d, k=np.array(k), r=d.r, p=d.p, binning_x=0, binning_y=0, roi=d.roi)
            items.append((DEPTH_INFO, ty, lt, other))
    items.sort(key=lambda it: it[2])
    bag = write_bag(tmp_path / "unreg", items)
    rc, _out, err = run_cli([bag, "--out", tmp_path / "o1", "--model", models["linear"], *TINY], capsys)
    assert rc == 2 and "not registered" in err  # found beside the depth topic: checked and refused
    rc, out, err = run_cli([bag, "--out", tmp_path / "o2", "--model", models["linear"], "--depth-info-topic", "", "--json",
                            *TINY], capsys)
    assert rc == 0, err
    assert "not registered" not in err and DEPTH_INFO not in out
    assert [p["tz"]["status"] != "error" for _lt, _st, p in certifications(tmp_path / "o2")] == [True] * 3


def test_cms_setup_line_names_no_coverage(sim_bag, models, capsys):  # noqa: F811
    import json

    rc, out, err = run_cli([sim_bag, "--no-output", "--model", models["linear"], "--method", "cms", "--max-frames", "1", "--json",
                            *TINY], capsys)
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["setup"].startswith("method cms, imaging surfel, sigma") and "coverage" not in summary["setup"]
    assert summary["config"]["coverage"] is None
    rc, out, err = run_cli([sim_bag, "--no-output", "--model", models["linear"], "--max-frames", "1", "--json", *TINY], capsys)
    assert rc == 0 and "coverage anchors" in json.loads(out)["setup"]


def _write_scene(tmp_path, cloud: Cloud, cam: CameraIntrinsics, name: str):
    cloud.save(tmp_path / f"{name}.npz")
    cam.to_yaml(tmp_path / "camera.yaml")
    return ["plan", "--cloud", str(tmp_path / f"{name}.npz"), "--camera", str(tmp_path / "camera.yaml"), "--axis", "tz",
            "--radius", "0.002", "--json"]


def test_plan_pws_warns_on_a_one_frame_cloud(tmp_path, capsys, models):  # noqa: F811
    from pws_ros.sim.world import render_view

    v = render_view(0, 0, 32, 24, samples_per_pixel=4.0)
    one = _write_scene(tmp_path, v.one_frame, v.intrinsics, "one")
    dense = _write_scene(tmp_path, v.dense, v.intrinsics, "dense")
    assert cli.main(one + ["--method", "pws"]) == 0
    assert "needs the entire scene cloud" in capsys.readouterr().err
    assert cli.main(dense + ["--method", "pws"]) == 0
    assert "needs the entire scene cloud" not in capsys.readouterr().err
    assert cli.main(one + ["--method", "pws_of"]) == 0
    assert "entire scene" not in capsys.readouterr().err
    # pws certify loads its scene the same way: the same warning for method pws, none for pws_of
    certify = ["certify"] + one[1:-1] + ["--model", str(models["linear"]), "--n0", "8", "--n", "16", "--quiet"]
    for method, warned in (("pws", True), ("pws_of", False)):
        assert cli.main(certify + ["--method", method] + (["--imaging", "paper"] if method == "pws" else [])) == 0
        assert ("pws certify: warning: method pws needs the entire scene cloud" in capsys.readouterr().err) is warned
    # brute force: the one-frame cloud has one point per pixel at most, all inside the image
    seen = set()
    for x, y, z in np.asarray(v.one_frame.points, dtype=np.float64):
        c = int(np.floor(v.intrinsics.fx * x / z + v.intrinsics.cx + 0.5))
        r = int(np.floor(v.intrinsics.fy * y / z + v.intrinsics.cy + 0.5))
        assert 0 <= c < 32 and 0 <= r < 24 and (r, c) not in seen
        seen.add((r, c))


def test_max_partitions_help_says_what_happens(capsys):
    for command in ("replay", "plan"):
        try:
            cli.main([command, "--help"])
        except SystemExit:
            pass
        text = " ".join(capsys.readouterr().out.split())
        assert "made coarser (fewer frames" in text and "never refused" in text, command
        assert "at once" not in text


def test_certify_command_takes_its_batch_size_from_the_engines_check(tmp_path, capsys, models, monkeypatch):  # noqa: F811
    """`pws certify` runs the same batch size check as the nodes and `pws replay` (bridge.sizing.choose_batch_size),
    on the size of the frames its classifier gets, and certifies with the batch size it returns."""
    from pws_ros.bridge import sizing
    from pws_ros.core import anchored as core_anchored  # the adaptive anchors' path, which `pws certify` takes here
    from pws_ros.sim.world import render_view

    v = render_view(0, 0, 32, 24, samples_per_pixel=4.0)
    one = _write_scene(tmp_path, v.one_frame, v.intrinsics, "one")
    asked, used = [], []
    monkeypatch.setattr(sizing, "choose_batch_size", lambda model, shape, bs, sigma, **k: asked.append((tuple(shape), bs)) or (3, 0.0))
    real = core_anchored.SmoothedClassifier
    monkeypatch.setattr(core_anchored, "SmoothedClassifier", lambda *a, **k: used.append(k["batch_size"]) or real(*a, **k))
    certify = ["certify"] + one[1:-1] + ["--model", str(models["linear"]), "--n0", "8", "--n", "16", "--batch-size", "64", "--quiet"]
    assert cli.main(certify) == 0
    from pws_ros.core.model import load_model

    size = load_model(str(models["linear"])).input_size
    assert asked == [(tuple(size) if size is not None else (24, 32), 64)] and used and set(used) == {3}

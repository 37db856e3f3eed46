"""Issue 35, live: both launch files as real ROS 2 processes on the demo recording played in a loop (each
frame restamped, 1 frame per second), with ``publish_overlay: true``, ``certification_to_diagnostics: true``
and a short ``certified_label_timeout_s``; the shipped certification defaults otherwise.

Asserted for each launch, against the ``certification`` messages of the same run, stamp by stamp:
``certified_label`` carries exactly the frames certified on every axis (with their class name and
label); every ``certification/overlay`` image has the stamp and frame id of a certification (and the
overlays drawn plus skipped are the frames certified); once the play stops, the certifying node's health
status WARNs that no frame was certified for longer than the timeout; the certifications also reach
``/diagnostics``, and where ``diagnostic_aggregator`` is installed its ``aggregator_node`` with
``config/diagnostic_aggregator.yaml`` shows them under ``PWS/Certification`` and the health under
``PWS/Nodes``. Needs rclpy, launch and launch_ros (ROS 2 Jazzy sourced): skipped otherwise. The nodes
run from this working tree, DDS on the loopback interface (:mod:`pws_ros.nodes.live`).

``PWS_LIVE_REPORT=<dir>`` writes ``<launch>.json`` (what was received) there.
"""
from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

import pytest
import yaml

from conftest import need_ros
from pws_ros.nodes.live import COLOR, DEPTH, DEPTH_INFO, INFO, REPO, Launch, Player, demo_frames, play_frame, ros_env, wait_for

pytestmark = [pytest.mark.rclpy, pytest.mark.slow]

CERTIFYING = {"pws.launch.py": "pipeline", "pws_nodes.launch.py": "certifier"}
TIMEOUT_S = 4.0          # certified_label_timeout_s of the run
WANT = 5                 # certifications to collect while the demo loops
LISTEN = {"/certified_label": "DiagnosticArray", "/certification/overlay": "Image", "/diagnostics_agg": "DiagnosticArray"}




def write_config(path: Path) -> Path:
    cfg = yaml.safe_load((REPO / "config" / "pws.yaml").read_text())
    params = cfg["/**"]["ros__parameters"]
    params.update({"model_path": str(REPO / params["model_path"]), "input_qos": "reliable", "publish_overlay": True,
                   "certified_label_timeout_s": TIMEOUT_S, "certification_to_diagnostics": True, "health_period_s": 0.5})
    path.write_text(yaml.safe_dump(cfg))
    return path


def aggregator(env: dict, root: Path) -> subprocess.Popen | None:
    """``diagnostic_aggregator``'s ``aggregator_node`` with config/diagnostic_aggregator.yaml, when installed."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    except ImportError:
        return None
    try:
        exe = Path(get_package_prefix("diagnostic_aggregator")) / "lib" / "diagnostic_aggregator" / "aggregator_node"
    except PackageNotFoundError:
        return None
    if not exe.exists():
        return None
    log = open(root / "aggregator.log", "wb")
    return subprocess.Popen([str(exe), "--ros-args", "--params-file", str(REPO / "config" / "diagnostic_aggregator.yaml")],
                            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=str(root), start_new_session=True)


def every_axis_certified(msg) -> bool:
    """The reference, from the ``certification`` message alone: every status OK and certified, one label."""
    statuses = [{kv.key: kv.value for kv in st.values} | {"level": int(st.level[0]) if isinstance(st.level, bytes) else int(st.level)}
                for st in msg.status]
    return bool(statuses) and all(s["level"] == 0 and s["certified"] == "true" for s in statuses) \
        and len({s["label"] for s in statuses}) == 1


def stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def run_live(launch_file: str, root: Path, monkeypatch) -> dict:
    domain = 100 + os.getpid() % 50
    env = ros_env(root, domain)
    for k in ("ROS_DOMAIN_ID", "CYCLONEDDS_URI", "RMW_IMPLEMENTATION", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(k, env[k])   # the test's own rclpy context: the same domain, loopback only
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    launch = Launch(launch_file, {"config_file": str(write_config(root / "live.yaml"))}, root, env)
    agg = aggregator(env, root)
    node = CERTIFYING[launch_file]
    player = None
    try:
        player = Player(domain, {INFO: "CameraInfo", DEPTH_INFO: "CameraInfo", DEPTH: "Image", COLOR: "Image"}, "live_player", LISTEN)
        assert wait_for(lambda: node in player.healthy_nodes() and player.subscribed((DEPTH, COLOR, INFO)), 120), launch.text()[-3000:]
        frames = [build for build, _label in demo_frames(player.T)]
        state = {"k": 0, "stop": False}
        base = time.time_ns() // 10**9 * 10**9

        def loop() -> None:   # the demo looped, one frame a second, as `ros2 bag play --loop` with a new timeline
            while not state["stop"]:
                play_frame(player, frames[state["k"] % len(frames)](base + state["k"] * 10**9))
                state["k"] += 1
                time.sleep(0.7)

        th = threading.Thread(target=loop, daemon=True)
        th.start()
        wait_for(lambda: len(player.certs) >= WANT, 300, 0.2)
        state["stop"] = True
        th.join(10)
        last = [len(player.certs), time.monotonic()]

        def settled() -> bool:   # no new certification for 6 s: the frame in flight is out
            if len(player.certs) != last[0]:
                last[:] = [len(player.certs), time.monotonic()]
            return time.monotonic() - last[1] > 6.0
        wait_for(settled, 120, 0.2)
        t_quiet = time.monotonic()

        def warned() -> list:
            with player.lock:
                return [st for h in player.health for st in h.status if st.name == f"{node}: health"
                        and st.message.startswith("no frame certified on every axis")]
        wait_for(lambda: bool(warned()), TIMEOUT_S + 15, 0.2)
        if agg is not None:
            wait_for(lambda: any("PWS/Nodes" in st.name for m in player.received["/diagnostics_agg"] for st in m.status), 10)
        with player.lock:
            health = [st for h in player.health for st in h.status if st.name == f"{node}: health"]
            forwarded = [h for h in player.health if h.status and h.status[0].name.startswith("pws/")]
            received = {t: list(v) for t, v in player.received.items()}
        return {"certs": player.messages(), "labels": received["/certified_label"], "overlays": received["/certification/overlay"],
                "agg": received["/diagnostics_agg"], "aggregator": agg is not None, "health": health, "warned": warned(),
                "forwarded": forwarded, "published": state["k"], "quiet_s": time.monotonic() - t_quiet, "log": launch.text()}
    finally:
        if player is not None:
            player.close()
        if agg is not None:
            agg.terminate()
            agg.wait(10)
        launch.stop()


@pytest.mark.parametrize("launch_file", list(CERTIFYING))
def test_certified_label_overlay_and_health_live(launch_file, tmp_path, monkeypatch):
    need_ros()
    r = run_live(launch_file, tmp_path, monkeypatch)
    certs = {}
    for m in r["certs"]:
        certs.setdefault(stamp(m), m)
    assert len(certs) >= 3, f"{len(certs)} certifications\n{r['log'][-3000:]}"
    # certified_label: exactly the frames certified on every axis, with their class and label
    labels = {stamp(m): m for m in r["labels"]}
    assert len(labels) == len(r["labels"])
    assert set(labels) == {s for s, m in certs.items() if every_axis_certified(m)}
    assert labels, "no demo frame was certified on every axis"
    for s, m in labels.items():
        values = {kv.key: kv.value for kv in m.status[0].values}
        first = {kv.key: kv.value for kv in certs[s].status[0].values}
        assert m.status[0].name == "pws/certified_label" and m.status[0].message == first["class_name"] == values["class_name"]
        assert values["label"] == first["label"] and m.header.frame_id == certs[s].header.frame_id
    # the overlay: images at the stamps (and frame ids) of certifications; drawn + skipped = frames certified
    assert r["overlays"], "no overlay image"
    for img in r["overlays"]:
        assert stamp(img) in certs and img.header.frame_id == certs[stamp(img)].header.frame_id
        assert img.encoding == "rgb8" and img.width == 640 and img.height > 360
    last = {kv.key: kv.value for kv in r["health"][-1].values}
    assert int(last["overlays_published"]) + int(last["overlays_skipped"]) == int(last["frames_processed"]) >= len(r["overlays"])
    # the health status warns once no frame has been certified for longer than certified_label_timeout_s
    assert r["warned"], [(st.level, st.message) for st in r["health"][-3:]]
    assert int(r["warned"][-1].level[0] if isinstance(r["warned"][-1].level, bytes) else r["warned"][-1].level) == 1
    # certification_to_diagnostics: the certifications on /diagnostics too, and the aggregator's tree
    assert {stamp(m) for m in r["forwarded"]} == set(certs)
    if r["aggregator"]:
        names = {st.name for m in r["agg"] for st in m.status}
        assert any(n.startswith("/PWS/Certification/") for n in names) and f"/PWS/Nodes/{CERTIFYING[launch_file]}: health" in names, names
    out = os.environ.get("PWS_LIVE_REPORT")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / f"{launch_file}.json").write_text(json.dumps({
            "certifications": len(certs), "certified_labels": len(labels), "overlays": len(r["overlays"]),
            "frames_published": r["published"], "health_last": last, "warned": r["warned"][-1].message,
            "aggregator": r["aggregator"], "agg_names": sorted({st.name for m in r["agg"] for st in m.status})}, indent=1))

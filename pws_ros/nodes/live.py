"""Live ROS 2 graphs of this package started from Python, on this machine only: the launch files run as a
subprocess (``launch.LaunchService``, as ``ros2 launch`` does), a player node publishes recorded or
made-up frames and collects the ``certification`` messages. Used by ``test/test_live_flood.py`` and by
``python -m pws_ros.bench.throughput --live``.

DDS traffic stays on the loopback interface: :func:`ros_env` sets a ``ROS_DOMAIN_ID`` and a Cyclone DDS
configuration (interface ``lo``, no multicast, peer 127.0.0.1) for the launched processes; the caller
sets the same for its own rclpy context (:class:`Player` takes the domain). The nodes run from this
source tree: :func:`install_prefix` lays out a minimal ament install prefix (the package index entry,
package.xml and the console scripts, which import this ``pws_ros``), so no colcon build is involved.

rclpy is imported inside the functions that need it only: this module imports without ROS.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

REPO = Path(__file__).resolve().parents[2]
NODE_EXECUTABLES = ("cloud_listener", "partition_planner", "projector", "certifier", "pipeline")
DEPTH, COLOR, INFO = "/camera/aligned_depth_to_color/image_raw", "/camera/color/image_raw", "/camera/color/camera_info"
DEPTH_INFO, POINTS, TF_STATIC = "/camera/aligned_depth_to_color/camera_info", "/camera/depth/color/points", "/tf_static"
CYCLONE_LOOPBACK = ("<CycloneDDS><Domain id='any'><General><Interfaces><NetworkInterface name='lo'/></Interfaces>"
                    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
                    "<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
                    "</Discovery></Domain></CycloneDDS>")
LAUNCHER = """
import sys
from launch import LaunchService
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
path, args = sys.argv[1], dict(a.split(':=', 1) for a in sys.argv[2:])
service = LaunchService()
service.include_launch_description(IncludeLaunchDescription(PythonLaunchDescriptionSource(path), launch_arguments=args.items()))
sys.exit(service.run())
"""


def wait_for(cond: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return bool(cond())


def install_prefix(root: Path) -> Path:
    """A minimal ament install prefix of this source tree under ``root`` (what colcon installs from
    setup.py that launch needs: the package index entry, package.xml, the console scripts)."""
    prefix = Path(root) / "prefix"
    index = prefix / "share" / "ament_index" / "resource_index" / "packages"
    index.mkdir(parents=True, exist_ok=True)
    (index / "pws_ros").write_text("")
    share = prefix / "share" / "pws_ros"
    share.mkdir(parents=True, exist_ok=True)
    (share / "package.xml").write_text((REPO / "package.xml").read_text())
    lib = prefix / "lib" / "pws_ros"
    lib.mkdir(parents=True, exist_ok=True)
    for exe in NODE_EXECUTABLES:
        script = lib / exe
        script.write_text(f"#!{sys.executable}\nimport sys\nfrom pws_ros.nodes.{exe} import main\nsys.exit(main())\n")
        script.chmod(0o755)
    return prefix


def ros_env(root: Path, domain: int) -> dict[str, str]:
    """The environment of the launched processes: ``domain``, loopback-only Cyclone DDS, logs under
    ``root``, this source tree's nodes first on the ament prefix path."""
    env = dict(os.environ)
    env.update({"ROS_DOMAIN_ID": str(int(domain)), "CYCLONEDDS_URI": CYCLONE_LOOPBACK, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                "PYTHONUNBUFFERED": "1", "RCUTILS_COLORIZED_OUTPUT": "0",
                "ROS_LOG_DIR": str(Path(root) / "ros_log"), "ROS_HOME": str(Path(root) / "ros_home"),
                "AMENT_PREFIX_PATH": os.pathsep.join(p for p in (str(install_prefix(root)), env.get("AMENT_PREFIX_PATH", "")) if p),
                "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)})
    env.pop("ROS_LOCALHOST_ONLY", None)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    return env


def children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if ppid == pid:
                out.append(int(d.name))
    return out


def node_processes(launch_pid: int) -> dict[str, int]:
    """``{executable or node name: pid}`` of the node processes a launch started (its children running a
    pws_ros script; ``pipeline`` workers are told apart by their ``__node:=`` remap)."""
    found = {}
    for pid in children(launch_pid):
        try:
            argv = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
        except OSError:
            continue
        exe = next((os.path.basename(a) for a in argv[:3] if os.path.basename(a) in NODE_EXECUTABLES and "pws_ros" in a), None)
        if exe is not None:
            name = next((a.split(":=", 1)[1] for a in argv if a.startswith("__node:=")), exe)
            found[name] = pid
    return found


def status_kb(pid: int, key: str) -> int:
    """A ``/proc/<pid>/status`` value in kB (``VmHWM``: peak RSS, ``VmRSS``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


class Launch:
    """A launch file of ``launch/`` started as a subprocess (its own session), output into ``log_path``."""

    def __init__(self, launch_file: str, args: dict[str, str], root: Path, env: dict[str, str]):
        self.log_path = Path(root) / f"{launch_file}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(REPO / "launch" / launch_file)]
                                     + [f"{k}:={v}" for k, v in args.items()],
                                     env=env, stdout=self._log, stderr=subprocess.STDOUT, cwd=str(root), start_new_session=True)

    def text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def nodes(self) -> dict[str, int]:
        return node_processes(self.proc.pid)

    def stop(self, timeout: float = 30.0) -> int:
        """SIGINT to the whole process group (a terminal's Ctrl-C: every node gets it, then launch's own)."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._log.close()
        return self.proc.returncode


class Player:
    """An rclpy node of its own context on ``domain``: reliable publishers on ``topics`` ({topic: type
    name of :func:`rclpy_types`}), and the ``certification`` and ``/diagnostics`` messages received (and
    those of ``listen``, {topic: type name}, in ``received[topic]``)."""

    def __init__(self, domain: int, topics: dict[str, str], name: str = "pws_player", listen: dict[str, str] | None = None):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        from ._ros import qos, rclpy_types

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(domain))
        self.T = rclpy_types()
        self.node = rclpy.create_node(name, context=self.context)
        self.pubs = {topic: self.node.create_publisher(getattr(self.T, kind), topic, qos("tf_static" if topic == TF_STATIC else "reliable", 100))
                     for topic, kind in topics.items()}
        self.certs: list[tuple[float, Any]] = []    # (monotonic receive time, message)
        self.health: list[Any] = []
        self.lock = threading.Lock()
        self.node.create_subscription(self.T.DiagnosticArray, "/certification", self._cert, qos("reliable", 100))
        self.node.create_subscription(self.T.DiagnosticArray, "/diagnostics", self._health, qos("reliable", 100))
        self.received: dict[str, list[Any]] = {topic: [] for topic in (listen or {})}
        for topic, kind in (listen or {}).items():
            self.node.create_subscription(getattr(self.T, kind), topic, lambda m, t=topic: self._got(t, m), qos("reliable", 100))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context was shut down under the spin
            pass

    def _cert(self, msg: Any) -> None:
        with self.lock:
            self.certs.append((time.monotonic(), msg))

    def _health(self, msg: Any) -> None:
        with self.lock:
            self.health.append(msg)

    def _got(self, topic: str, msg: Any) -> None:
        with self.lock:
            self.received[topic].append(msg)

    def publish(self, topic: str, msg: Any) -> None:
        self.pubs[topic].publish(msg)

    def subscribed(self, topics) -> bool:
        return all(self.pubs[t].get_subscription_count() > 0 for t in topics)

    def healthy_nodes(self) -> set[str]:
        with self.lock:
            return {st.name.split(":")[0] for h in self.health for st in h.status}

    def messages(self) -> list[Any]:
        with self.lock:
            return [m for _t, m in self.certs]

    def certified_stamps(self) -> list[int]:
        from ..bridge import msgconv

        return [msgconv.stamp_to_ns(m.header.stamp) for m in self.messages()]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
        self.thread.join(5)


def demo_frames(T: Any, bag: Path | None = None, points: bool = False) -> list[tuple[Callable[[int], list], int | None]]:
    """The frames of a recording (default ``bags/demo``; read with this package's bag reader) as
    ``(build, label)``: ``build(stamp)`` gives the frame's messages (rclpy types ``T``) restamped: the
    CameraInfo (also as the aligned depth's), depth and colour, or with ``points`` the organized cloud a
    driver publishes (depth filled as the nodes do); ``label`` is the recording's ground truth, if any."""
    from ..bagio.reader import BagReader
    from ..bridge import msgbuild, msgconv
    from ..core.cloud import cloud_from_rgbd

    frames: dict[int, dict] = {}
    with BagReader(bag or REPO / "bags" / "demo") as r:
        for m in r.messages():
            msg = r.deserialize(m)
            has_header = hasattr(msg, "header")
            stamp = msgconv.header_stamp_ns(msg) if has_header else m.log_time_ns
            f = frames.setdefault(stamp, {"frame_id": msgconv.frame_id_of(msg) if has_header else ""})
            if m.topic == INFO:
                f["cam"] = msgconv.intrinsics_from_camera_info(msg)
            elif m.topic in (DEPTH, COLOR):
                f[m.topic] = (msgconv.image_to_numpy(msg), msg.encoding)
            elif m.topic == "/pws/ground_truth":
                label = {kv.key: kv.value for kv in msg.status[0].values}.get("label", "")   # absent: a label by name only (pws import)
                f["label"] = int(label) if label.lstrip("-").isdigit() else None
    out = []
    for stamp in sorted(frames):
        f = frames[stamp]
        if not {"cam", DEPTH, COLOR} <= set(f):
            continue

        def build(new_stamp: int, f: dict = f) -> list:
            hdr = msgbuild.make_header(T, new_stamp, f["frame_id"])
            info = msgbuild.camera_info_from_intrinsics(hdr, f["cam"], T)
            if points:
                depth_m = np.where(f[DEPTH][0] > 0, f[DEPTH][0] / 1000.0, np.nan)
                cloud = cloud_from_rgbd(depth_m, f[COLOR][0], f["cam"], fill="row")
                shape = f[DEPTH][0].shape if len(cloud) == f[DEPTH][0].size else None
                return [(INFO, info), (POINTS, msgbuild.cloud_to_pointcloud2(hdr, cloud, T, organized_shape=shape))]
            return [(INFO, info), (DEPTH_INFO, info), (DEPTH, msgbuild.image_from_numpy(hdr, f[DEPTH][0], T, encoding=f[DEPTH][1])),
                    (COLOR, msgbuild.image_from_numpy(hdr, f[COLOR][0], T, encoding=f[COLOR][1]))]
        out.append((build, f.get("label")))
    return out


def play_frame(player: Player, msgs: list, settle_s: float = 0.3) -> None:
    """A frame's CameraInfos, then (``settle_s`` later, so that they are taken before the images:
    callbacks of different topics run in no fixed order) its images or cloud."""
    for topic, msg in msgs:
        if topic in (INFO, DEPTH_INFO):
            player.publish(topic, msg)
    if settle_s > 0:
        time.sleep(settle_s)
    for topic, msg in msgs:
        if topic not in (INFO, DEPTH_INFO):
            player.publish(topic, msg)


# ---- live throughput: N pipeline workers on the looped demo ------------------------------------

CERT_COMPARED = ("label", "class_name", "certified", "radius", "p_a_lower", "n", "alpha", "num_partitions",
                 "classifier_calls", "status", "method", "coverage", "n0", "num_bounds", "frames_rendered", "reason")


def certificate_values(msg: Any) -> dict[str, dict[str, Any]]:
    """``{axis: the values a certificate states}`` (not its timings, nor the worker that made it)."""
    from ..bridge import msgbuild

    return {axis: {k: v.get(k) for k in CERT_COMPARED} for axis, v in msgbuild.parse_certification(msg).items()}


def run_live_workers(workers: int, seconds: float, root: Path, config_path: Path, bag: Path | None = None,
                     domain: int | None = None, rate_hz: float = 10.0, warmup_timeout: float = 300.0,
                     base_stamp: int = 1_900_000_000 * 10**9) -> dict[str, Any]:
    """``pws.launch.py workers:=<workers>`` on the recording looped at ``rate_hz`` (each frame restamped
    ``base_stamp + k / rate_hz``, the same schedule every run, as ``ros2 bag play --loop`` with a new
    timeline): once every worker certified a frame, certifications are counted for ``seconds``."""
    from ..bridge import msgconv

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    domain = int(domain if domain is not None else 120 + os.getpid() % 60)
    env = ros_env(root, domain)
    for k in ("CYCLONEDDS_URI", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION"):
        os.environ[k] = env[k]   # this process's own rclpy context (the player): loopback only as well
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    launch = Launch("pws.launch.py", {"config_file": str(config_path), "workers": str(workers)}, root, env)
    player = None
    try:
        names = ["pipeline"] if workers == 1 else [f"pipeline_{i}" for i in range(workers)]
        player = Player(domain, {INFO: "CameraInfo", DEPTH_INFO: "CameraInfo", DEPTH: "Image", COLOR: "Image"})
        if not wait_for(lambda: player.healthy_nodes() >= set(names) and player.subscribed((DEPTH, COLOR, INFO)), 120):
            raise RuntimeError(f"the workers did not come up: {launch.text()[-2000:]}")
        frames = [build for build, _label in demo_frames(player.T, bag)]
        period = int(round(1e9 / rate_hz))
        msgs = [build(base_stamp) for build in frames]       # built once, restamped per publication
        state = {"k": 0, "stop": False}

        def play() -> None:
            t0 = time.monotonic()
            while not state["stop"]:
                k = state["k"]
                stamp = base_stamp + k * period
                for topic, msg in msgs[k % len(msgs)]:
                    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp // 10**9, stamp % 10**9
                    player.publish(topic, msg)
                state["k"] = k + 1
                time.sleep(max(0.0, t0 + (k + 1) * period / 1e9 - time.monotonic()))

        th = threading.Thread(target=play, daemon=True)
        th.start()

        def workers_seen() -> set[str]:
            from ..bridge import msgbuild

            seen = set()
            for m in player.messages():
                for v in msgbuild.parse_certification(m).values():
                    seen.add(str(v.get("node", "")).split("/")[-1])
            return seen
        if not wait_for(lambda: set(names) <= workers_seen(), warmup_timeout, 0.2):
            raise RuntimeError(f"not every worker certified a frame within {warmup_timeout} s: {workers_seen()}")
        t_start = time.monotonic()
        n_start = len(player.certs)
        load0 = os.getloadavg()
        time.sleep(seconds)
        t_end = time.monotonic()
        load1 = os.getloadavg()
        state["stop"] = True
        th.join(5)
        with player.lock:
            window = [m for t, m in player.certs[n_start:] if t <= t_end]
            all_msgs = [m for _t, m in player.certs]
        per_node: dict[str, int] = {}
        from ..bridge import msgbuild
        for m in window:
            node = str(next(iter(msgbuild.parse_certification(m).values())).get("node", "")).split("/")[-1]
            per_node[node] = per_node.get(node, 0) + 1
        certs = {msgconv.stamp_to_ns(m.header.stamp): certificate_values(m) for m in all_msgs}
        return {"workers": workers, "window_s": round(t_end - t_start, 1), "certified": len(window),
                "frames_per_min": 60.0 * len(window) / (t_end - t_start), "per_worker": per_node,
                "frames_published": state["k"], "loadavg": [round(x, 2) for x in load0 + load1], "certs": certs}
    finally:
        if player is not None:
            player.close()
        launch.stop()


def live_throughput(worker_counts: list[int], seconds: float, config_path: Path | None = None, bag: Path | None = None,
                    root: Path | None = None) -> dict[str, Any]:
    """:func:`run_live_workers` for each worker count in turn, and whether the certificates of every stamp
    certified by two runs are equal."""
    import tempfile

    import yaml

    root = Path(root or tempfile.mkdtemp(prefix="pws_live_"))
    src = Path(config_path or REPO / "config" / "pws.yaml")
    cfg = yaml.safe_load(src.read_text())
    params = cfg.setdefault("/**", {}).setdefault("ros__parameters", {})
    model = Path(params.get("model_path", "bags/models/classifier_sigma0.50.pt"))
    params["model_path"] = str(model if model.is_absolute() else REPO / model)
    params["input_qos"] = "reliable"   # whole 640x480 images over DDS: no lost fragments
    config = root / "live.yaml"
    config.write_text(yaml.safe_dump(cfg))
    runs = [run_live_workers(int(w), seconds, root / f"w{w}", config, bag) for w in worker_counts]
    base = runs[0]
    for r in runs:
        common = sorted(set(r["certs"]) & set(base["certs"]))
        r["common_stamps"] = len(common)
        r["equal_certificates"] = sum(r["certs"][s] == base["certs"][s] for s in common)
        r["speedup"] = r["frames_per_min"] / base["frames_per_min"] if base["frames_per_min"] > 0 else float("nan")
    return {"config": str(src), "runs": runs}

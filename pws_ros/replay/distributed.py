"""``pws replay --workers N``: the frames of a recording as Ray tasks (the optional extra ``.[ray]``).

The driver reads the bag, assembles the frames in stamp order exactly as the serial replay does, and
converts each (depth + colour -> cloud); a frame is then a Ray task (:func:`_certify_task`) that runs
:meth:`~pws_ros.bridge.engine.FrameCertifier.process` in a worker process (one engine per process and
configuration, loaded by its first task). The driver alone writes the output bag: a finished frame
waits until every earlier frame is written, then goes through the serial replay's own
:meth:`~pws_ros.replay.run.Replay.process` (the engine's result handed in), so records, report and
messages are those of the serial run. What Ray provides and nothing here re-implements:

- scheduling: tasks on a local instance started with ``num_cpus = N`` (each task one CPU; Ray sets one
  torch/OpenMP thread per worker), or on an existing cluster (``--ray-address``, the user's to configure);
  the local instance is this machine's alone: its node address is the loopback one, so its GCS, raylet,
  agents and worker processes listen on 127.0.0.1 only (:func:`loopback_node`; on a robot a Ray instance
  listening on every interface would be a cluster endpoint on the robot's network);
- bounded memory: at most ``2 N`` frames are submitted and not yet written (``ray.wait`` on the oldest);
- retries: a task whose worker process dies is re-run by Ray (``max_retries``); its result arrives once,
  and the driver writes each frame once, in order;
- results through the object store.

Certificates equal the serial run's: the noise of a frame and axis is seeded from (seed, stamp, axis).
What differs: ``latency_ms`` / the time per frame are the task's wall time, and with ``audit_every`` each
worker process audits every k-th frame it certifies.
"""
from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from typing import Any, Iterator

from ..bridge.inputs import RawFrame, convert
from ..core.errors import require
from .options import ReplayOptions, ReplayResult
from .run import Replay

MAX_RETRIES = 3          # Ray re-runs a frame whose worker process died this many times
IN_FLIGHT_PER_WORKER = 2  # frames submitted and not yet written, per worker

_ENGINES: dict[Any, Any] = {}   # per worker process: one engine per configuration


def _worker_log(level: str, message: str) -> None:
    if level in ("warn", "error"):
        import sys

        print(f"[pws worker {os.getpid()} {level}] {message}", file=sys.stderr)


def _certify(config: Any, cloud: Any, intrinsics: Any, stamp_ns: int, dense: Any, frame_id: str, preview_every: int):
    """One frame in a worker process: (FrameResult, wall seconds less the engine's start-up work, pid)."""
    from ..bridge.engine import FrameCertifier

    engine = _ENGINES.get(config)
    if engine is None:
        engine = _ENGINES[config] = FrameCertifier(config, log=_worker_log)
    t0 = time.perf_counter()
    result = engine.process(cloud, intrinsics, stamp_ns, dense_cloud=dense, frame_id=frame_id, preview_every=preview_every)
    return result, time.perf_counter() - t0 - result.timings.get("startup", 0.0), os.getpid()


LOCAL_ONLY_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"   # Ray's switch: "0" = a local-only instance on the loopback address


@contextmanager
def loopback_node() -> Iterator[None]:
    """While a local Ray instance starts: Ray's local-only mode, whose node address is the loopback one
    (``services.get_node_ip_address``), so that the GCS, the raylet, the agents and the worker processes
    listen on 127.0.0.1 only (measured with Ray 2.60: without it they listen on every interface and on the
    machine's network address). Ray reads the switch (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, its default on
    macOS and Windows) from the environment when it is imported, and the processes it starts inherit it; a
    driver that imported Ray before gets the same value for the start. Both are restored afterwards."""
    saved_env = os.environ.get(LOCAL_ONLY_ENV)
    os.environ[LOCAL_ONLY_ENV] = "0"
    constants = sys.modules.get("ray._private.ray_constants")
    saved = getattr(constants, "ENABLE_RAY_CLUSTER", None)
    if constants is not None:
        constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        if saved_env is None:
            os.environ.pop(LOCAL_ONLY_ENV, None)
        else:
            os.environ[LOCAL_ONLY_ENV] = saved_env
        if constants is not None:
            constants.ENABLE_RAY_CLUSTER = saved


def ray_available() -> str:
    """"" when Ray imports, else why not (the extra is not installed)."""
    try:
        import ray  # noqa: F401
    except ImportError as exc:
        return f"Ray is not installed ({exc}): pip install 'pws_ros[ray]' (or pip install 'ray>=2')"
    return ""


class RayReplay(Replay):
    """A replay whose frames run as Ray tasks (use :func:`replay_ray`)."""

    def __init__(self, opts: ReplayOptions, workers: int, address: str | None = None):
        super().__init__(opts)
        require(int(workers) >= 1, f"--workers must be >= 1, got {workers}")
        require(not opts.realtime, "--realtime simulates the one live worker: it cannot be combined with --workers")
        require(opts.model is None and opts.denoiser is None,
                "--workers loads the model in every worker from its file: give a model path, not a loaded model")
        why = ray_available()
        require(not why, why)
        self.workers = int(workers)
        self.address = address
        self.in_flight_cap = IN_FLIGHT_PER_WORKER * self.workers
        self.task_pids: dict[int, int] = {}   # stamp -> the pid of the worker whose result was written
        self.peak_in_flight = 0
        self._given: Any = None               # the FrameResult handed to Replay.process

    # the driver's engine never certifies: Replay.process receives the task's result through it
    def _engine(self, config, truth_ok):
        engine = super()._engine(config, truth_ok)
        require(not self.regenerate, "--workers does not regenerate the scene cloud of method pws: give --dense-cloud")
        engine.process = self._given_result
        return engine

    def _given_result(self, *args: Any, **kwargs: Any) -> Any:
        result, self._given = self._given, None
        require(result is not None, "internal error: no task result for this frame")
        return result

    def run(self) -> ReplayResult:
        import ray

        started = False
        if not ray.is_initialized():
            if self.address:
                ray.init(address=self.address, log_to_driver=True, logging_level="warning")
            else:
                with loopback_node():
                    ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=True, logging_level="warning")
            started = True
        try:
            return super().run()
        finally:
            if started:
                ray.shutdown()

    def _loop(self, bag, inputs) -> None:
        import ray

        opts = self.opts
        task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_certify)
        config_ref = ray.put(self.config)
        pending: list[tuple[RawFrame, Any]] = []      # in stamp order: (frame, ObjectRef or None)
        done: dict[Any, Any] = {}                     # ObjectRef -> (FrameResult, wall, pid)
        preview = self.config.preview_every if opts.preview else 0

        def write_ready(block: bool) -> None:
            while pending:
                raw, ref = pending[0]
                if ref is not None and ref not in done:
                    if not block:
                        return
                    waiting = [r for _raw, r in pending if r is not None and r not in done]
                    ready, _ = ray.wait(waiting, num_returns=1)
                    for r in ready:
                        done[r] = ray.get(r)
                    continue
                pending.pop(0)
                if ref is None:       # the conversion failed: the serial path writes the error record
                    self.process(raw)
                else:
                    result, wall, pid = done.pop(ref)
                    self._given = result
                    rec, _ = self.process(raw)
                    rec.total_ms = rec.latency_ms = 1000.0 * wall
                    self.task_pids[raw.stamp_ns] = pid
                self._commit()
                self.bar.update(1)
                block = False   # one written: submit more before waiting again

        for raw in self._frames(bag, inputs):
            ref = None
            try:
                frame = convert(raw, self.config, self.assembler.fallback)
            except Exception:  # noqa: BLE001 - written as the serial replay writes it (Replay.process)
                frame = None
            if frame is not None:
                frame_id = str(getattr(raw.header, "frame_id", "") or "")
                ref = task.remote(config_ref, frame.cloud, frame.intrinsics, int(raw.stamp_ns), None, frame_id, preview)
            pending.append((raw, ref))
            self.peak_in_flight = max(self.peak_in_flight, len(pending))
            write_ready(block=len(pending) >= self.in_flight_cap)
            if opts.max_frames is not None and self.frames_seen >= opts.max_frames:
                break
        while pending:
            write_ready(block=True)
        return None

    def _summary(self, inputs, out, dropped, wall, extra_frames, bag_info, counts):
        summary = super()._summary(inputs, out, dropped, wall, extra_frames, bag_info, counts)
        summary["workers"] = {"backend": "ray", "workers": self.workers, "address": self.address or "local",
                              "max_in_flight": self.in_flight_cap, "peak_in_flight": self.peak_in_flight,
                              "worker_processes": len(set(self.task_pids.values()))}
        return summary


def replay_ray(options: ReplayOptions, workers: int, address: str | None = None) -> ReplayResult:
    """:func:`~pws_ros.replay.replay` with the frames as Ray tasks on ``workers`` CPUs (a local instance)
    or on the cluster at ``address``. PwsError when Ray is not installed."""
    return RayReplay(options, workers, address).run()


__all__ = ["IN_FLIGHT_PER_WORKER", "LOCAL_ONLY_ENV", "MAX_RETRIES", "RayReplay", "loopback_node", "ray_available", "replay_ray"]

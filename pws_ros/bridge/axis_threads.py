"""A frame's axes at the same time (``axis_threads``): how many (:func:`axis_workers`), and the daemon threads that run
them (:func:`at_once`), for :meth:`.engine.FrameCertifier.process`. Each axis keeps its own renderer, plan and noise
seed, so its certificate is the one it gets alone (``test_bridge_engine.py``); only a frame's latency changes."""
from __future__ import annotations

import functools
import importlib
import threading
from typing import Any, Callable

AXIS_THREAD = "pws-axis-"   # the name of the threads of a frame's axes (at_once), then a number


def axis_workers(axes: int, setting: int, budgeted: bool = False) -> int:
    """How many of ``axes`` axes run at the same time: ``setting`` (``axis_threads``; 0: one per axis, at most torch's
    intra-op threads, which several workers on one machine divide among themselves); one under a time budget (its axes
    share the frame's time in turn) or for one axis."""
    if budgeted or axes < 2:
        return 1
    k = int(setting)
    if k == 0:
        import torch

        k = torch.get_num_threads()
    return max(1, min(int(axes), k))


@functools.lru_cache(maxsize=1)
def axis_imports() -> None:
    """What an axis imports when first used, imported here once before axes run in threads of their own (a module
    that two threads import first waits for one of them; modules importing each other from two threads could
    deadlock)."""
    for name in ("anchors", "audit", "bounds", "certify", "cms", "coverage", "imaging", "render"):
        importlib.import_module(f"..core.{name}", __package__)


_LEFT = threading.Event()   # set once a wait in at_once was left by an exception (a signal): its threads ran on


def axes_left_running() -> bool:
    """Whether a frame was left while its axes ran (a signal raised in :func:`at_once`'s wait, the only way its threads
    outlive it): they may still be inside torch, or only just ending, and the interpreter's teardown then aborts
    (``pws_ros.cli.run``)."""
    return _LEFT.is_set()


def at_once(fn: Callable[[int], Any], n: int, workers: int) -> list:
    """``[fn(0), ..., fn(n - 1)]``, computed by ``workers`` daemon threads (each takes the next ``k`` when it is free);
    the first exception of any is raised here once all have ended. Daemon threads and an interruptible wait: a signal
    that stops the caller (``pws replay``'s SIGINT or SIGTERM) is raised here at once, and what is left of the frame
    never holds up the process' exit (a pool's threads are joined at exit)."""
    results: list = [None] * n
    errors: list = [None] * n
    todo = iter(range(n))
    lock = threading.Lock()

    def work() -> None:
        while True:
            with lock:
                k = next(todo, None)
            if k is None:
                return
            try:
                results[k] = fn(k)
            except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread below
                errors[k] = exc

    threads = [threading.Thread(target=work, name=f"{AXIS_THREAD}{i}", daemon=True) for i in range(max(1, min(n, workers)))]
    try:   # (a signal may come while they start, too)
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    except BaseException:
        _LEFT.set()
        raise
    for exc in errors:
        if exc is not None:
            raise exc
    return results


__all__ = ["AXIS_THREAD", "at_once", "axes_left_running", "axis_imports", "axis_workers"]

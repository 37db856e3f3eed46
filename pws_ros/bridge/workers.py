"""Several pipeline processes on one input stream: which worker certifies which stamp, and how many
torch threads each may use (ROS-free; the ``pipeline`` node and ``pws_ros.bench.throughput`` use it).

Every worker subscribes to the same inputs, assembles the same frames and keeps only those whose stamp
is assigned to it (:class:`StampAssignment`): a pure function of the stamp, so every stamp goes to
exactly one worker and no coordinator is needed. Each worker keeps its own latest-only mailbox (a frame
of its own replaces its older waiting one). Certificates do not depend on which worker makes them: the
noise of a frame and axis is seeded from (seed, stamp, axis) alone.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable

_MASK = (1 << 64) - 1


def splitmix64(x: int) -> int:
    """A 64-bit mix of ``x`` (SplitMix64's finaliser): neighbouring stamps land far apart."""
    z = (int(x) + 0x9E3779B97F4A7C15) & _MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
    return z ^ (z >> 31)


@dataclass(frozen=True)
class StampAssignment:
    """Stamp -> worker: ``(stamp_ns // period_ns) % num_workers`` with a period (round robin on a camera
    of that period), else ``splitmix64(stamp_ns) % num_workers`` (any rate, balanced on average)."""

    num_workers: int = 1
    worker_index: int = 0
    period_ns: int = 0

    def __post_init__(self) -> None:
        from ..core.errors import require

        require(int(self.num_workers) >= 1, f"num_workers must be >= 1, got {self.num_workers}")
        require(0 <= int(self.worker_index) < int(self.num_workers),
                f"worker_index {self.worker_index} must lie in 0 .. {int(self.num_workers) - 1}")
        require(int(self.period_ns) >= 0, f"the worker period must be >= 0, got {self.period_ns} ns")

    @classmethod
    def from_config(cls, config: Any) -> "StampAssignment":
        return cls(int(config.num_workers), int(config.worker_index), int(round(float(config.worker_period_s) * 1e9)))

    def worker_of(self, stamp_ns: int) -> int:
        n = int(self.num_workers)
        if n == 1:
            return 0
        if self.period_ns > 0:
            return int((int(stamp_ns) // int(self.period_ns)) % n)
        return int(splitmix64(int(stamp_ns)) % n)

    def mine(self, stamp_ns: int) -> bool:
        return self.worker_of(stamp_ns) == int(self.worker_index)

    def describe(self) -> str:
        rule = f"(stamp // {self.period_ns / 1e9:g} s) mod {self.num_workers}" if self.period_ns > 0 else f"hash(stamp) mod {self.num_workers}"
        return f"worker {self.worker_index} of {self.num_workers}: certifies the stamps with {rule} = {self.worker_index}"


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads_per_worker(num_workers: int, cores: int | None = None) -> int:
    """``max(1, cores // num_workers)``: N workers on one machine do not fight over its cores."""
    return max(1, int(cores if cores is not None else available_cores()) // max(1, int(num_workers)))


def set_torch_threads(num_workers: int, log: Callable[[str, str], None] | None = None, cores: int | None = None) -> int | None:
    """Limit torch's intra-op threads to :func:`threads_per_worker` when there are several workers (one
    worker keeps torch's default); returns the number set, or None."""
    if int(num_workers) <= 1:
        return None
    import torch

    k = threads_per_worker(num_workers, cores)
    torch.set_num_threads(k)
    if log is not None:
        log("info", f"{num_workers} workers on {cores if cores is not None else available_cores()} cores: {k} torch thread(s) each")
    return k


__all__ = ["StampAssignment", "available_cores", "set_torch_threads", "splitmix64", "threads_per_worker"]

"""The machine a bench ran on: CPU, versions, load, and peak memory while a stage runs."""
from __future__ import annotations

import os
import platform
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch



def _rss_bytes() -> int | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


class PeakMemory:
    """Peak growth of this process's resident memory while the block runs (sampled every few ms
    from ``/proc/self/statm``), and of CUDA memory (``torch.cuda.max_memory_allocated``) on a GPU.
    ``peak_bytes`` is None where the platform does not expose the RSS."""

    def __init__(self, device: torch.device, interval: float = 0.004):
        self.device = device
        self.interval = interval
        self.peak_bytes: int | None = None
        self.cuda_peak_bytes: int | None = None
        self._stop = threading.Event()

    def _poll(self) -> None:
        while not self._stop.is_set():
            r = _rss_bytes()
            if r is not None and r > self._max:
                self._max = r
            self._stop.wait(self.interval)

    def __enter__(self) -> "PeakMemory":
        self._base = _rss_bytes()
        self._max = self._base or 0
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._cuda_base = torch.cuda.memory_allocated(self.device)
        self._thread = threading.Thread(target=self._poll, daemon=True) if self._base is not None else None
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            r = _rss_bytes()
            self.peak_bytes = max(self._max, r or 0) - self._base
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.cuda_peak_bytes = int(torch.cuda.max_memory_allocated(self.device) - self._cuda_base)


def machine_info(device: torch.device) -> dict[str, Any]:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    try:
        mem = int(Path("/proc/meminfo").read_text().split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        mem = None
    import scipy

    info = {
        "platform": platform.platform(), "python": sys.version.split()[0], "cpu": cpu, "cpu_count": os.cpu_count(),
        "usable_cpus": affinity, "memory_bytes": mem, "torch": torch.__version__, "numpy": np.__version__,
        "scipy": scipy.__version__, "torch_threads": torch.get_num_threads(), "device": str(device),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    try:
        import matplotlib

        info["matplotlib"] = matplotlib.__version__
    except ImportError:  # pragma: no cover
        info["matplotlib"] = None
    if device.type == "cuda":
        info["cuda_device"] = torch.cuda.get_device_name(device)
        info["cuda_version"] = torch.version.cuda
    try:
        from .. import __version__

        info["pws_ros"] = __version__
    except ImportError:  # pragma: no cover
        info["pws_ros"] = None
    return info


def sha256_16(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def display_path(p: Path) -> str:
    """``p`` relative to the working directory when it lies below it (keeps committed reports machine-neutral)."""
    try:
        return str(Path(p).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)

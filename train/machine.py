"""The machine a result was measured on: CPU, cores, memory, Python, torch, GPU."""

from __future__ import annotations

import datetime as dt
import os
import platform
from typing import Any

import torch


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity; all cores where that is
    unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: Set by runners that start several lcrl training processes at once (the benchmark
#: runners that train configurations side by side): how many share the cores.
PROCESSES_VARIABLE = "LCRL_PROCESSES"


def default_threads(helpers: int = 0) -> int:
    """Torch threads for a training process that does not say: ``OMP_NUM_THREADS`` where it
    is set, otherwise the available cores divided among the ``LCRL_PROCESSES`` training
    processes running at once and the ``helpers`` processes this one starts on the same
    machine (local Ray workers), at least 1: never more busy threads than cores, since two
    2-thread processes on two cores run several times slower than two 1-thread ones."""
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) > 0:
        return int(omp)
    try:
        processes = max(1, int(os.environ.get(PROCESSES_VARIABLE, "1")))
    except ValueError:
        processes = 1
    return max(1, available_cores() // (processes + max(0, helpers)))


def set_threads(threads: int = 0, helpers: int = 0) -> int:
    """Set torch's intra-op threads: ``threads``, or :func:`default_threads` for 0.
    Returns the number set."""
    n = threads if threads > 0 else default_threads(helpers)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def machine() -> dict[str, Any]:
    """CPU, cores, memory, Python and torch versions, GPU if any."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gib = None
    try:
        with open("/proc/meminfo") as f:
            mem_gib = round(int(f.readline().split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gib,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def machine_line(info: dict[str, Any]) -> str:
    """One-line machine description for figure captions and tables."""
    gpu = f", {info['gpu']}" if "gpu" in info else ""
    return (
        f"{info['cpu']}, {info['cores']} cores, {info['memory_gib']} GiB{gpu}; "
        f"Python {info['python']}, torch {info['torch']} ({info['torch_threads']} threads); "
        f"{info['date']}"
    )

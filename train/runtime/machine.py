"""The machine a result was measured on: CPU, cores, memory, Python, torch, GPU."""

from __future__ import annotations

import datetime as dt
import os
import platform
import sys
import time
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
    machine (local Ray workers), at least 1, and no more than the cores other busy
    processes leave (:func:`busy_cores`): never more busy threads than cores, since a
    2-thread run beside another busy process on two cores runs several times slower than
    a 1-thread one."""
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) > 0:
        return int(omp)
    raw = os.environ.get(PROCESSES_VARIABLE, "")
    try:
        processes = max(1, int(raw or "1"))
    except ValueError:
        processes = 1
    share = max(1, available_cores() // (processes + max(0, helpers)))
    if raw:  # a runner said how many run at once: their load is already counted
        return share
    # other busy processes (another training run, a test suite): the cores they leave
    return max(1, min(share, available_cores() - busy_cores()))


#: How long :func:`busy_cores` watches the CPUs (seconds).
BUSY_SAMPLE_S = 0.3


def _cpu_jiffies() -> tuple[int, int] | None:
    """(busy, total) jiffies over all CPUs since boot (``/proc/stat``); None where the
    platform has no such file."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 4:
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    total = sum(fields[:8])  # guest time is already counted in user
    return total - idle, total


def _others_busy(
    first: tuple[int, int], second: tuple[int, int], mine: Any, mine_after: Any
) -> int:
    """Cores other processes kept busy between two ``/proc/stat`` readings, from the CPU
    time of all cores and this process's own (``os.times()`` at the same instants)."""
    if second[1] <= first[1]:
        return 0
    busy, total = second[0] - first[0], second[1] - first[1]
    cpus = os.cpu_count() or 1
    own = (mine_after.user - mine.user) + (mine_after.system - mine.system)
    elapsed = max(1e-6, mine_after.elapsed - mine.elapsed)
    others = busy / total * cpus - own / elapsed
    return max(0, min(cpus, round(others)))


def busy_cores(sample_s: float = BUSY_SAMPLE_S) -> int:
    """Cores other processes keep busy now: the CPU time spent outside this process while
    watching ``/proc/stat`` for ``sample_s`` seconds, in cores, rounded. Where that file is
    missing, the 1-minute load average, rounded (0 where the platform has neither).

    The load average lags: a busy process that ended a minute ago still counts in it, and
    a run started right after one would take one thread where it could have had all."""
    first = _cpu_jiffies()
    if first is None or sample_s <= 0:
        try:
            return round(os.getloadavg()[0])
        except (AttributeError, OSError):
            return 0
    mine = os.times()
    time.sleep(sample_s)
    second = _cpu_jiffies()
    mine_after = os.times()
    if second is None:
        return 0
    return _others_busy(first, second, mine, mine_after)


def automatic_threads(threads: int) -> bool:
    """Whether a process given ``--torch-threads threads`` chooses its threads itself:
    0, with neither ``OMP_NUM_THREADS`` nor ``LCRL_PROCESSES`` set."""
    return threads <= 0 and not any(
        os.environ.get(name, "").strip() for name in ("OMP_NUM_THREADS", PROCESSES_VARIABLE)
    )


class ThreadWatcher:
    """Torch's threads chosen again while a run trains, from the load of the moment.

    :func:`set_threads` chooses once, as a run starts. A run that took both cores of an
    idle machine collapses when another busy process starts beside it (two threads where
    one core is free run several times slower than one). Every ``every_s`` seconds
    :meth:`poll` reads how many cores other processes kept busy since the last poll (the
    CPU time of all cores in ``/proc/stat`` less this process's own, with no waiting) and
    sets the threads to the cores they left free: fewer when another run starts, the
    process's share again when it ends. Nothing happens between polls but a clock read.

    Args:
        helpers: processes this one starts on the same machine (local Ray workers).
        every_s: seconds between two readings.
        clock, jiffies, times: the clock, the ``/proc/stat`` reader and ``os.times``
            (replaceable in tests).
    """

    def __init__(
        self,
        helpers: int = 0,
        every_s: float = 20.0,
        clock: Any = time.monotonic,
        jiffies: Any = None,
        times: Any = os.times,
    ) -> None:
        self.share = max(1, available_cores() // (1 + max(0, helpers)))
        self.every_s = float(every_s)
        self._clock, self._times = clock, times
        self._jiffies = jiffies or _cpu_jiffies
        self._last = (self._clock(), self._jiffies(), self._times())
        #: How many times the threads were changed.
        self.changes = 0

    def poll(self) -> int | None:
        """Choose again where ``every_s`` seconds have passed; returns the new number of
        threads where it changed, else None."""
        now = self._clock()
        if now - self._last[0] < self.every_s:
            return None
        reading, times = self._jiffies(), self._times()
        before, before_times = self._last[1], self._last[2]
        self._last = (now, reading, times)
        if reading is None or before is None:
            return None
        others = _others_busy(before, reading, before_times, times)
        target = max(1, min(self.share, available_cores() - others))
        if target == torch.get_num_threads():
            return None
        torch.set_num_threads(target)
        self.changes += 1
        return target


def set_threads(threads: int = 0, helpers: int = 0) -> int:
    """Set torch's intra-op threads: ``threads``, or :func:`default_threads` for 0 (with
    a note where other busy processes leave fewer cores than this process's share).
    Returns the number set."""
    n = threads if threads > 0 else default_threads(helpers)
    if threads <= 0 and not os.environ.get("OMP_NUM_THREADS", "").strip():
        full = max(1, available_cores() // (1 + max(0, helpers)))
        if n < full and not os.environ.get(PROCESSES_VARIABLE):
            print(
                f"lcrl: note: other processes keep some of the {available_cores()} cores "
                f"busy: {n} torch thread{'s' if n > 1 else ''} (--torch-threads sets it)",
                file=sys.stderr,
            )
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


def apply_threads(threads: int) -> int:
    """``--torch-threads`` of a command: refused in one line when negative, else
    :func:`set_threads` (0: automatic). Returns the number set."""
    from lcrl.errors import LcrlError

    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise LcrlError(f"--torch-threads must be >= 0 (0: automatic), got {threads}")
    return set_threads(threads)


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what the platform says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_features(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's widest vector instructions and whether it multiplies bfloat16 natively,
    from ``/proc/cpuinfo`` (``"avx2"``, ``"avx512"``, ``"avx512, bf16"``; ``""`` where
    unknown). The same float32 SAC update took 6.5 ms on one machine of this kind and 11.2
    ms on another (`update_floor`), so result files name them."""
    try:
        with open(cpuinfo) as f:
            flags = next(
                (line.split(":", 1)[1].split() for line in f if line.startswith("flags")), []
            )
    except OSError:
        return ""
    wide = next((w for w in ("avx512f", "avx2", "avx") if w in flags), "")
    out = [wide.removesuffix("f")] if wide else []
    if "avx512_bf16" in flags or "amx_bf16" in flags:
        out.append("bf16")
    return ", ".join(out)


def machine() -> dict[str, Any]:
    """CPU, cores, memory, Python and torch versions, GPU if any."""
    cpu = cpu_name()
    mem_gib = None
    try:
        with open("/proc/meminfo") as f:
            mem_gib = round(int(f.readline().split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cpu_features": cpu_features(),
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
    features = f" ({info['cpu_features']})" if info.get("cpu_features") else ""
    return (
        f"{info['cpu']}{features}, {info['cores']} cores, {info['memory_gib']} GiB{gpu}; "
        f"Python {info['python']}, torch {info['torch']} ({info['torch_threads']} threads); "
        f"{info['date']}"
    )

"""Memory known up front: what the large arrays of a run will take, checked before they
are allocated.

The replay buffer's arrays are allocated empty and filled as episodes arrive (the
operating system commits a page when it is first written), so a buffer too large for the
machine used to start, run for hours and be killed by the kernel once it filled up; one
larger still ended at once in a numpy traceback. Now the trainers estimate the bytes of
their buffers (camera frames included), of the frames ``lcrl perception train`` loads and
of the demonstrations behavioural cloning caches, and :func:`check_memory` compares them
with the memory the machine has available: above it the run is refused in one line that
names the figure and the option to change; above :data:`WARN_SHARE` of it, a warning.
"""

from __future__ import annotations

import os
import sys

from lcrl.errors import LcrlError

#: The share of the available memory above which a run is warned (it may still fit, but
#: leaves little for the rest of the machine).
WARN_SHARE = 0.6


def available_bytes() -> int | None:
    """The memory the machine can give a new process now (``MemAvailable`` of
    ``/proc/meminfo``, capped by a cgroup limit where one is set); None where unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        avail = None
    if avail is None and hasattr(os, "sysconf"):
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError):
            avail = None
    limit = _cgroup_room()
    if limit is not None:
        avail = limit if avail is None else min(avail, limit)
    return avail


def _cgroup_room() -> int | None:
    """What a cgroup v2 memory limit leaves (limit minus current use); None without one."""
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            text = f.read().strip()
        if text == "max":
            return None
        with open("/sys/fs/cgroup/memory.current") as f:
            return max(0, int(text) - int(f.read().strip()))
    except (OSError, ValueError):
        return None


def fmt_bytes(n: float) -> str:
    """``1.5 GiB``, ``320 MiB``."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def check_memory(
    need: int,
    what: str,
    option: str,
    unit_bytes: int = 0,
    unit: str = "slots",
    available: int | None = None,
) -> None:
    """Refuse ``need`` bytes for ``what`` where the machine does not have them.

    Args:
        need: the estimated bytes.
        what: what they are for (``the replay buffer (1,000,000 slots of 2,312 bytes)``).
        option: the option that sets the size (``--buffer.capacity``).
        unit_bytes: bytes per unit of that option: the message then says how many fit
            in :data:`WARN_SHARE` of the memory available.
        unit: what the option counts (``slots``), for that message.
        available: the bytes available (default: :func:`available_bytes`).

    Raises:
        LcrlError: ``need`` exceeds what is available.
    """
    room = available_bytes() if available is None else available
    if room is None:
        return
    fix = f"lower {option}"
    if unit_bytes > 0:
        fix += f" (about {int(WARN_SHARE * room // unit_bytes):,} {unit} fit comfortably)"
    if need > room:
        raise LcrlError(
            f"{what} needs {fmt_bytes(need)}, more than the {fmt_bytes(room)} this machine has "
            f"available: {fix}"
        )
    if need > WARN_SHARE * room:
        print(
            f"lcrl: warning: {what} will take {fmt_bytes(need)} of the {fmt_bytes(room)} "
            f"available ({need / room:.0%}), leaving little for the rest: {fix} if the "
            "machine runs short",
            file=sys.stderr,
        )

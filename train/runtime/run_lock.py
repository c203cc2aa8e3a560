"""One process per run folder: a lock that names its holder and dies with it.

A training run (``lcrl train``, ``--resume``, ``lcrl distill``) takes ``OUT/.lock`` before
it writes or removes anything in its folder. A second process that wants the folder is
refused at once with the holder's process id and command. The lock is an operating-system
file lock (``flock``), so it is released when its process ends in any way, SIGKILL and
crashes included: the next run finds the file, sees that nobody holds it, takes it over
and says whose it was. ``lcrl eval --out`` refuses to write inside a folder held by a
training run.

:func:`check_output_file` refuses, before any work, a file a command could not write.

Where ``fcntl`` is missing (Windows), the holder's process id stands in for the file
lock: a folder is held while the process it names is alive.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from lcrl.errors import LcrlError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

#: The lock file inside a run folder.
LOCK_NAME = ".lock"

#: The locks this process holds: resolved folder -> open file descriptor.
_HELD: dict[Path, int] = {}
#: Folders :func:`lock_run` created, by the folder locked (innermost first).
_MADE: dict[Path, list[Path]] = {}


@dataclass(frozen=True)
class Holder:
    """Who holds (or last held) a run folder."""

    pid: int
    host: str
    command: str
    started: float

    def describe(self) -> str:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started))
        where = "" if self.host == socket.gethostname() else f" on {self.host}"
        return f"process {self.pid}{where} ({self.command}, since {when})"


def _read(path: Path) -> Holder | None:
    try:
        data = json.loads(path.read_text())
        return Holder(int(data["pid"]), str(data["host"]), str(data["command"]), data["started"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _command() -> str:
    args = [Path(sys.argv[0]).name, *sys.argv[1:]] if sys.argv and sys.argv[0] else ["python"]
    text = " ".join(args)
    return text if len(text) <= 120 else text[:117] + "..."


def _try_lock(fd: int) -> bool:
    """Take the file lock of ``fd`` without waiting; False where another process has it."""
    if fcntl is None:  # pragma: no cover - Windows
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def holder(folder: str | Path) -> Holder | None:
    """The live process that holds ``folder``'s lock (``None``: nobody, or this process)."""
    path = Path(folder) / LOCK_NAME
    if not path.is_file() or Path(folder).resolve() in _HELD:
        return None
    who = _read(path)
    if fcntl is None:  # pragma: no cover - Windows
        return who if who is not None and who.pid != os.getpid() and _alive(who.pid) else None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        if _try_lock(fd):
            return None
    finally:
        os.close(fd)  # closing releases a lock this probe took
    return who or Holder(-1, "?", "an unknown command", time.time())


def lock_run(folder: str | Path, what: str = "--out") -> str:
    """Take ``folder``'s lock for this process (again, if it has it already).

    Args:
        folder: the run folder (created by the caller).
        what: how the user named it, for the message (``--out``).

    Returns:
        A note to print when the lock of a process that is no longer running was taken
        over; empty otherwise.

    Raises:
        LcrlError: another live process holds the folder; the message names it.
    """
    key = Path(folder).resolve()
    if key in _HELD:
        return ""
    path = key / LOCK_NAME
    made = [p for p in (key, *key.parents) if not p.exists()]
    try:
        key.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise LcrlError(f"cannot lock the run folder {folder}: {e.strerror or e}") from None
    previous = _read(path)
    taken = _try_lock(fd)
    if taken and fcntl is None and previous is not None:  # pragma: no cover - Windows
        taken = previous.pid == os.getpid() or not _alive(previous.pid)
    if not taken:
        os.close(fd)
        who = previous.describe() if previous else "another process"
        raise LcrlError(
            f"{what} {folder} is in use by {who}: wait for it to end, stop it, or choose "
            "another folder"
        )
    me = Holder(os.getpid(), socket.gethostname(), _command(), time.time())
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me.__dict__).encode(), 0)
    except OSError:  # a full disk: the lock holds all the same, without its holder's name
        pass
    _HELD[key] = fd
    _MADE[key] = made
    if previous is not None and previous.pid != me.pid and not _alive(previous.pid):
        return f"took over {folder}: its lock was left by {previous.describe()}, no longer running"
    return ""


def unlock_run(folder: str | Path) -> None:
    """Release ``folder``'s lock if this process holds it. The file stays, emptied: a
    lock file that still names a process is one its holder never released (it died)."""
    key = Path(folder).resolve()
    _MADE.pop(key, None)
    fd = _HELD.pop(key, None)
    if fd is not None:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)  # released in order: no holder to report
        with contextlib.suppress(OSError):
            os.close(fd)


def abandon_locks() -> None:
    """Release every lock this process still holds (a command that failed before its run
    began), and remove each such folder again where :func:`lock_run` created it and it
    holds nothing but the lock: a refused run leaves no folder behind."""
    for key in list(_HELD):
        made = _MADE.get(key, [])
        unlock_run(key)
        if key in made and [p.name for p in key.iterdir()] == [LOCK_NAME]:
            with contextlib.suppress(OSError):
                (key / LOCK_NAME).unlink()
        for folder in made:  # innermost first; only the empty ones go
            with contextlib.suppress(OSError):
                folder.rmdir()


def refuse_if_training(path: str | Path, option: str) -> None:
    """Refuse to write ``path`` inside a run folder that a live process holds.

    Raises:
        LcrlError: naming the option, the folder and its holder.
    """
    p = Path(path).resolve()
    for folder in (p, *p.parents):
        who = holder(folder)
        if who is not None:
            raise LcrlError(
                f"{option} {path} is inside {folder}, which {who.describe()} is writing: "
                "write elsewhere, or wait for it to end"
            )


def check_output_file(path: str | Path, option: str) -> None:
    """Refuse an output file that cannot be written, before any work is done: a folder, a
    path below a file, or a path in a folder that cannot be written. Creates nothing.

    Args:
        path: the file the command will write.
        option: the option that names it (``--json``), for the message.

    Raises:
        LcrlError: naming the option, the path and the problem.
    """
    p = Path(path)
    if p.is_dir():
        raise LcrlError(f"{option} {p} is a folder: name a file, e.g. {p / 'eval.json'}")
    folder = next(q for q in (*p.parents, Path(".")) if q.exists())
    if not folder.is_dir():
        raise LcrlError(f"{option} {p} cannot be written: {folder} is a file, not a folder")
    if not os.access(folder, os.W_OK):
        raise LcrlError(f"{option} {p} cannot be written: the folder {folder} is not writable")

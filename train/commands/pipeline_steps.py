"""How a camera pipeline runs its stages' commands: child processes that signals reach,
and the ``keep`` stage's copy of the final policy."""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lcrl.errors import LcrlError

if TYPE_CHECKING:
    from train.commands.pipeline_settings import CameraPipeline


class Signals:
    """SIGINT and SIGTERM passed on to the stages' processes; the pipeline stops after them."""

    def __init__(self) -> None:
        self.procs: set[subprocess.Popen] = set()
        self.signum: int | None = None
        self.stopping = False
        """A stage failed: the others stop and start no more commands."""
        self.lock = threading.Lock()

    def handle(self, signum: int, frame: Any) -> None:
        self.signum = self.signum or signum
        self.stop(signum)  # the lock is not taken here: a handler must not wait on it

    def stop(self, signum: int) -> None:
        """Send ``signum`` to every stage's process still running."""
        for proc in list(self.procs):
            if proc.poll() is None:
                proc.send_signal(signum)

    def check(self) -> None:
        """Raise where the pipeline is stopping: a signal came, or a stage beside failed.

        Raises:
            RunInterrupted: with the signal's status (SIGTERM's where a stage failed).
        """
        if self.signum is not None or self.stopping:
            from train.training.trainer import RunInterrupted

            raise RunInterrupted(self.signum or signal.SIGTERM)

    def start(self, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        """Start a stage's command, unless the pipeline is stopping (checked under the
        lock that :meth:`stop` is sent under, so no process starts unsignalled)."""
        with self.lock:
            self.check()
            proc = subprocess.Popen(argv, env=env)
            self.procs.add(proc)
        if self.signum is not None:  # a signal came while it started
            proc.send_signal(self.signum)
        return proc


#: Seconds between progress-bar updates of a stage whose output goes to a file or pipe
#: (a log then holds one line per half minute, not one per step).
LOG_BAR_INTERVAL = 30


def child_env(terminal: bool) -> dict[str, str]:
    """The stages' environment: this one, with progress bars slowed down when the output
    is not a terminal (``TQDM_MININTERVAL``)."""
    import os

    env = dict(os.environ)
    if not terminal:
        env.setdefault("TQDM_MININTERVAL", str(LOG_BAR_INTERVAL))
    return env


def run_command(args: list[str], signals: Signals) -> float:
    """Run ``lcrl ARGS`` in a child process; its seconds.

    Raises:
        LcrlError: the command failed (its status and the command are named).
        RunInterrupted: the pipeline was stopped by a signal (its status is the signal's).
    """
    argv = [sys.executable, "-m", "train.commands.entry", *args]
    print(f"  $ lcrl {shlex.join(args)}", flush=True)
    t0 = time.perf_counter()
    proc = signals.start(argv, child_env(sys.stdout.isatty()))
    try:
        status = proc.wait()
    finally:
        signals.procs.discard(proc)
    signals.check()
    if status != 0:
        raise LcrlError(f"the command `lcrl {shlex.join(args)}` failed (status {status})")
    return time.perf_counter() - t0


def keep_policy(p: CameraPipeline, signals: Signals) -> float:
    """Copy the final student's latest checkpoint (weights and configs, no replay data or
    optimiser state) with the canonical reader on by default, fit its reader if needed,
    and seal it: a folder ``lcrl act`` / ``lcrl eval`` / ``lcrl.load`` take."""
    from lcrl.checkpoint import find_latest
    from train.environments.text_reading import READER_CACHE
    from train.policies.loading import keep_checkpoint

    t0 = time.perf_counter()
    if find_latest(Path(p.out) / "student") is None:
        raise LcrlError(f"no student in {p.out}/student: run the stage student first")
    dest = keep_checkpoint(Path(p.out) / "student", p.keep or Path(p.out) / "kept", p.reader)
    if p.reader and not (dest / READER_CACHE).is_dir():  # fitted once, kept beside it
        run_command(
            ["act", str(dest), "--instruction", "reach the red cube", "--episodes", "1"], signals
        )
    return time.perf_counter() - t0


__all__ = ["LOG_BAR_INTERVAL", "Signals", "child_env", "keep_policy", "run_command"]

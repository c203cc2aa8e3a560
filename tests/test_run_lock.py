"""One process per run folder: a second one is refused, naming the first; a lock left by a
dead process is taken over; ``lcrl eval --out`` does not write into a run in training."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from helpers import cli, error_line, hold
from test_stopping import TINY, Run, latest_step, log_steps

from train.runtime.run_lock import LOCK_NAME, holder, lock_run, unlock_run

ROOT = Path(__file__).resolve().parent.parent


def second(out: Path, *extra: str, timeout: float = 60) -> subprocess.CompletedProcess:
    args = ["train", "state2d", "--out", str(out), "--total-steps", "400", *TINY, *extra]
    return subprocess.run(
        [sys.executable, "-m", "train.commands.entry", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_a_second_training_process_is_refused_and_the_first_goes_on(tmp_path, one_thread):
    out = tmp_path / "run"
    first = Run(out)
    first.wait_for(first.logged)
    pid = first.proc.pid
    for extra in ((), ("--overwrite",), ("--resume",)):
        t0 = time.monotonic()
        done = second(out, *extra)
        assert done.returncode == 2, done.stderr
        line = error_line(done.stderr)
        assert f"in use by process {pid}" in line and "train state2d" in line, line
        assert "Traceback" not in done.stderr
        assert time.monotonic() - t0 < 30
    # lcrl eval --out into the folder in training is refused too
    assert first.proc.poll() is None
    rows = len(log_steps(out / "progress.csv"))
    first.wait_for(lambda: len(log_steps(out / "progress.csv")) > rows)  # it trains on
    first.proc.send_signal(signal.SIGKILL)
    assert first.finish() == -signal.SIGKILL
    steps = log_steps(out / "progress.csv")
    assert steps == sorted(set(steps))  # one writer: no row twice, one header
    assert (out / "progress.csv").read_text().count("step,") == 1


def test_a_lock_left_by_a_dead_process_is_taken_over(tmp_path, one_thread):
    out = tmp_path / "run"
    first = Run(out, "--checkpoint-every", "100")
    first.wait_for(lambda: (out / "latest.json").is_file())
    pid = first.proc.pid
    first.proc.send_signal(signal.SIGKILL)
    first.finish()
    assert (out / LOCK_NAME).is_file()  # the file stays; nobody holds it
    assert holder(out) is None
    done = second(out, "--resume", "--total-steps", str(latest_step(out) + 100))
    assert done.returncode == 0, done.stderr
    assert f"its lock was left by process {pid}" in done.stderr
    assert "no longer running" in done.stderr


def test_eval_out_inside_a_run_in_training_is_refused(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli("train", "state2d", "--out", str(run), "--total-steps", "200", *TINY) == 0
    proc = hold(run)
    try:
        assert cli("eval", str(run), "--episodes", "1", "--out", str(run / "evals" / "x")) == 2
        line = error_line(capsys.readouterr().err)
        assert f"which process {proc.pid}" in line and "is writing" in line
        assert not (run / "evals").exists()
        # the same command with --out elsewhere evaluates while the run trains
        assert cli("eval", str(run), "--episodes", "1", "--out", str(tmp_path / "e")) == 0
        # and a training process of this one is refused the folder
        assert cli("train", "state2d", "--out", str(run), "--resume", "--total-steps", "400") == 2
        assert f"in use by process {proc.pid}" in error_line(capsys.readouterr().err)
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)
    assert cli("train", "state2d", "--out", str(run), "--resume", "--total-steps", "300") == 0


def test_the_lock_is_reentrant_in_its_process_and_released_on_unlock(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    assert lock_run(folder) == ""
    assert lock_run(folder) == ""  # this process again: fine
    assert holder(folder) is None  # this process does not block itself
    unlock_run(folder)
    proc = hold(folder)
    try:
        who = holder(folder)
        assert who is not None and who.pid == proc.pid
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)
    assert holder(folder) is None
    note = lock_run(folder)
    assert f"left by process {proc.pid}" in note
    unlock_run(folder)

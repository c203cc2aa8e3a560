"""Stopping a run, by signal or by kill, loses at most the steps since its last checkpoint.

Real ``lcrl train`` processes get real signals: SIGTERM saves like Ctrl-C (exit 143); a
second signal while the checkpoint is written does not cut it short; after SIGKILL,
``--resume`` removes the half-written checkpoint folder and cuts the logs back to the
checkpoint's step. To put a signal inside a checkpoint write, the process under test
slows its writes down (:data:`RUNNER`); everything else is the real command.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import cli

from lcrl.checkpoint import find_latest, load_checkpoint

ROOT = Path(__file__).resolve().parent.parent
#: Runs ``lcrl ARGS`` after making each weights write wait SLOW seconds (printing
#: "writing" first) and each evaluation of the training loop wait SLOW_EVAL seconds
#: (printing "evaluating" first): ``python -c RUNNER SLOW SLOW_EVAL ARGS...``.
RUNNER = """
import sys, time
import safetensors.torch
slow, slow_eval = float(sys.argv[1]), float(sys.argv[2])
if slow:
    write = safetensors.torch.save_file
    def slow_write(*args, **kwargs):
        print("writing", flush=True)
        time.sleep(slow)
        return write(*args, **kwargs)
    safetensors.torch.save_file = slow_write
if slow_eval:
    import train.training.trainer
    evaluate = train.training.trainer.evaluate
    def slow_evaluate(*args, **kwargs):
        print("evaluating", flush=True)
        time.sleep(slow_eval)
        return evaluate(*args, **kwargs)
    train.training.trainer.evaluate = slow_evaluate
from train.commands.cli import main
main(sys.argv[3:])
"""
TINY = [
    "--learning-starts", "100",
    "--batch-size", "16",
    "--eval-every", "0",
    "--eval-episodes", "2",
    "--checkpoint-every", "0",
    "--log-every", "50",
    "--buffer.capacity", "20000",
    "--agent.net.hidden", "16", "16",
    "--collect.envs", "1",  # one environment: the steps named are the steps stopped at
    "--no-progress",
    "--no-tensorboard",
]  # fmt: skip


class Run:
    """A real ``lcrl train state2d`` process writing to ``out``; its stdout and stderr go
    to files in ``out``'s parent."""

    def __init__(
        self,
        out: Path,
        *extra: str,
        slow: float = 0.0,
        slow_eval: float = 0.0,
        steps: int = 100_000,
    ) -> None:
        self.out = out
        self.stdout = out.parent / f"{out.name}.out"
        self.stderr = out.parent / f"{out.name}.err"
        args = ["train", "state2d", "--out", str(out), "--total-steps", str(steps), *TINY]
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        with self.stdout.open("w") as o, self.stderr.open("w") as e:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", RUNNER, str(slow), str(slow_eval), *args, *extra],
                cwd=ROOT,
                stdout=o,
                stderr=e,
                env=env,
            )

    def wait_for(self, ready, timeout: float = 120.0) -> None:
        """Poll until ``ready()`` holds (the process must still run)."""
        end = time.monotonic() + timeout
        while not ready():
            if self.proc.poll() is not None:
                raise AssertionError(f"the run ended early: {self.err()}")
            if time.monotonic() > end:
                self.proc.kill()
                raise AssertionError(f"timed out; stdout: {self.out_text()}")
            time.sleep(0.05)

    def logged(self, rows: int = 2) -> bool:
        """progress.csv holds at least ``rows`` rows."""
        return len(log_steps(self.out / "progress.csv")) >= rows

    def finish(self, timeout: float = 120.0) -> int:
        return self.proc.wait(timeout=timeout)

    def out_text(self) -> str:
        return self.stdout.read_text()

    def err(self) -> str:
        return self.stderr.read_text()


def log_steps(path: Path) -> list[int]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [int(float(row["step"])) for row in csv.DictReader(f) if row.get("step")]


def latest_step(out: Path) -> int:
    return int(load_checkpoint(find_latest(out)).meta["step"])


def resume(out: Path, steps: int) -> int:
    return cli("train", "state2d", "--out", str(out), "--resume", "--total-steps", str(steps))


def test_sigterm_saves_like_ctrl_c_and_resumes(tmp_path, one_thread):
    run = Run(tmp_path / "run")
    run.wait_for(run.logged)
    run.proc.send_signal(signal.SIGTERM)
    assert run.finish() == 143
    assert "by SIGTERM: saved" in run.out_text() and "--resume" in run.out_text()
    assert "Traceback" not in run.err()
    step = latest_step(run.out)
    assert step >= 100 and step % 50 == 0  # episodes of 50 steps: a whole number of them
    assert resume(run.out, step + 50) == 0
    assert latest_step(run.out) == step + 50


@pytest.mark.parametrize("second", [signal.SIGINT, signal.SIGTERM])
def test_a_second_signal_during_the_save_keeps_the_checkpoint(tmp_path, second):
    run = Run(tmp_path / "run", slow=1.5)
    run.wait_for(run.logged)
    run.proc.send_signal(signal.SIGINT)
    run.wait_for(lambda: "writing" in run.out_text())
    run.proc.send_signal(second)  # in the middle of the write
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130
    err = run.err()
    assert "while the checkpoint is written: it is completed first" in err
    assert "Exception ignored" not in err and "Traceback" not in err
    ckpt = load_checkpoint(find_latest(run.out))  # complete, and the one latest.json names
    assert ckpt.meta["step"] >= 100 and ckpt.has_arrays()
    assert "by SIGINT: saved" in run.out_text()


def rows(path: Path) -> list[str]:
    return path.read_text().splitlines()


def test_resume_after_sigkill_cleans_up_and_cuts_the_logs(tmp_path, one_thread):
    out = tmp_path / "run"
    extra = ("--checkpoint-every", "200", "--log-every", "20", "--eval-every", "100")
    run = Run(out, *extra, slow=3.0)
    # killed in the middle of the second checkpoint's write, after rows past the first
    run.wait_for(lambda: (out / "latest.json").is_file())
    # two safetensors files per checkpoint: the third write is the second checkpoint's
    run.wait_for(lambda: run.out_text().count("writing") >= 3)
    run.proc.send_signal(signal.SIGKILL)
    assert run.finish() == -signal.SIGKILL
    stale = list((out / "checkpoints").glob(".*.tmp-*"))
    assert stale, "the kill left no half-written folder"
    kept = latest_step(out)
    assert kept == 200
    # rows of the lost segment: progress past the checkpoint, evaluations at 300 and 400
    assert max(log_steps(out / "progress.csv")) > kept
    assert log_steps(out / "eval.csv") == [100, 200, 300, 400]
    before = {name: rows(out / name) for name in ("progress.csv", "eval.csv")}

    assert resume(out, kept + 200) == 0
    assert not list((out / "checkpoints").glob(".*"))
    steps = log_steps(out / "progress.csv")
    assert steps == sorted(set(steps)) and steps[-1] == kept + 200  # no step twice
    # each evaluation once: the killed segment's rows at 300 and 400 were cut, and the
    # resumed run wrote its own
    assert log_steps(out / "eval.csv") == [100, 200, 300, 400]
    for name, old in before.items():  # the header and rows up to the checkpoint, as written
        n = 1 + sum(1 for step in log_steps(out / name) if step <= kept)
        assert rows(out / name)[:n] == old[:n]


def test_a_stop_during_an_evaluation_runs_it_on_resume(tmp_path, one_thread):
    """Stopped during the periodic evaluation at step 200: the checkpoint is at 200 and
    the resumed run evaluates at 200 before it trains on, so eval.csv has every row."""
    out = tmp_path / "run"
    run = Run(out, "--eval-every", "100", slow_eval=3.0)
    run.wait_for(lambda: run.out_text().count("evaluating") >= 2)  # the one at step 200
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130
    assert "Traceback" not in run.err()
    assert latest_step(out) == 200
    assert load_checkpoint(find_latest(out)).meta["eval_pending"] is True
    assert log_steps(out / "eval.csv") == [100]
    assert resume(out, 300) == 0
    assert log_steps(out / "eval.csv") == [100, 200, 300]
    assert load_checkpoint(find_latest(out)).meta["eval_pending"] is False


def test_resume_below_the_checkpoint_changes_nothing(tmp_path, capsys, one_thread):
    out = tmp_path / "run"
    assert cli("train", "state2d", "--out", str(out), "--total-steps", "150", *TINY) == 0
    files = ("progress.csv", "eval.csv", "latest.json", "report.md")
    before = {name: (out / name).read_bytes() for name in files}
    capsys.readouterr()
    for steps in ("100", "150"):
        assert resume(out, int(steps)) == 0
        err = capsys.readouterr().err
        assert "already at step 150" in err and "nothing to do" in err
    assert {name: (out / name).read_bytes() for name in files} == before
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["step_000000150"]


def test_progress_log_widens_its_header_for_columns_that_start_later(tmp_path):
    from train.training.trainer import CsvLog

    path = tmp_path / "progress.csv"
    log = CsvLog(path)
    log.write({"step": 1000, "success": 0.0})
    log.write({"step": 2000, "success": 0.1, "critic_loss": 0.5, "q": 1.25})
    log.write({"step": 3000, "success": 0.2, "critic_loss": 0.25, "q": 2.0})
    lines = path.read_text().splitlines()
    assert lines == [
        "step,success,critic_loss,q",
        "1000,0,,",
        "2000,0.1,0.5,1.25",
        "3000,0.2,0.25,2",
    ]
    again = CsvLog(path)  # a resumed run keeps the widened header
    again.write({"step": 4000, "success": 0.3, "critic_loss": 0.125, "q": 3.0})
    assert path.read_text().splitlines()[-1] == "4000,0.3,0.125,3"


#: ``lcrl train`` whose start-up (loading the encoder, building scenes) takes 60 s: it
#: prints "starting" and sleeps inside the command, before any training loop exists.
SLOW_START = """
import sys, time
import train.commands.cli
def slow_train(argv):
    print("starting", flush=True)
    time.sleep(60)
train.commands.cli._train = slow_train
train.commands.cli.main(["train", "state2d"])
"""


@pytest.mark.parametrize(("sig", "status", "said"), [
    (signal.SIGINT, 130, "lcrl: interrupted"),
    (signal.SIGTERM, 143, "lcrl: interrupted by SIGTERM"),
])  # fmt: skip
def test_a_signal_during_start_up_stops_a_command_started_in_the_background(sig, status, said):
    # A shell script's `lcrl train ... &` starts lcrl with SIGINT ignored; a kill -INT
    # during start-up was lost and the run trained on.
    proc = subprocess.Popen(
        [sys.executable, "-c", SLOW_START],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    assert proc.stdout.readline().strip() == "starting"
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("the command ignored the signal") from None
    assert proc.returncode == status
    assert said in err and "Traceback" not in err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize("delay", [0.3, 1.5, 4.0])
def test_a_signal_at_any_instant_of_start_up_stops_the_console_script(tmp_path, sig, delay):
    """The real ``lcrl`` entry point (imports, tyro, the encoder, the env) started in the
    background with SIGINT ignored: a signal while it imports (0.3 s), while it parses
    and builds (1.5 s) or as it begins to train (4 s) stops it within seconds, with one
    line, the signal's status and no traceback."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "train.commands.entry", "train", "lang2d-quick", "--out", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--no-progress", "--no-tensorboard", "--torch-threads", "1"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    time.sleep(delay)
    proc.send_signal(sig)
    sent = time.monotonic()
    try:
        stdout, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        stdout, err = proc.communicate()  # what it said, to tell where it was
        raise AssertionError(
            f"the command ignored {sig.name} sent after {delay} s; stdout ends "
            f"{stdout[-800:]!r}, stderr ends {err[-2000:]!r}"
        ) from None
    assert time.monotonic() - sent < 10
    assert proc.returncode == 128 + sig, (stdout, err)
    assert "Traceback" not in err and "Exception ignored" not in err
    said = [line for line in (stdout + err).splitlines() if sig.name in line]
    assert len(said) == 1 and said[0].startswith(("lcrl: interrupted", "interrupted at"))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_where_python_drops_exceptions_is_raised_at_the_next_safe_point(sig):
    """A signal that lands in a weakref callback (the import system's module-lock
    clean-up) or a ``__del__``, where a raised exception would be printed and dropped, is
    sent again and raised a moment later; anywhere else it is raised at once."""
    from train.commands import cli as commands
    from train.training.trainer import RunInterrupted

    raised = KeyboardInterrupt if sig == signal.SIGINT else RunInterrupted
    space: dict = {"sys": sys}
    exec(
        compile("def cb():\n    return sys._getframe()", "<frozen importlib._bootstrap>", "exec"),
        space,
    )
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    commands.stop_on_signals()
    try:
        with pytest.raises(raised):
            commands._stopped(sig, sys._getframe())  # a plain frame: at once
        for frame in (space["cb"](), _del_frame()):
            with pytest.raises(raised):
                commands._stopped(sig, frame)  # returns: nothing raised here
                deadline = time.monotonic() + 5
                while time.monotonic() < deadline:  # ... but the signal comes again
                    time.sleep(0.01)
                raise AssertionError("the deferred signal never came")
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _del_frame():
    """A frame of a ``__del__`` method."""
    frames = []

    class Dropped:
        def __del__(self):
            frames.append(sys._getframe())

    Dropped()
    return frames[0]


def test_a_second_signal_raises_again_when_the_first_never_reached_the_loop(capsys):
    """A library's catch-all (a simulator wrapping the interrupt in its own error) can
    swallow the first signal's exception; the next signal must stop the run, not wait for
    a final save that never comes."""
    from train.training.trainer import RunInterrupted, StopSignals

    with StopSignals() as stops:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        except RunInterrupted:
            pass  # swallowed on its way up
        with pytest.raises(RunInterrupted) as raised:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        assert raised.value.signum == signal.SIGTERM
        stops.received = True  # the loop has it now: a further signal waits for the save
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
    assert "SIGINT while the checkpoint is written" in capsys.readouterr().err


def test_a_signal_during_a_periodic_save_waits_for_it_and_prints_nothing(capsys):
    """The first signal inside a checkpoint write is held silently and raised as the write
    ends, so the run prints its one ``interrupted at`` line and nothing else; a second
    signal during the final save is the only case that says more."""
    from train.training.trainer import RunInterrupted, StopSignals

    with StopSignals() as stops:
        with pytest.raises(RunInterrupted) as raised, stops.holding():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            saved = True
        assert saved and raised.value.signum == signal.SIGINT
        assert capsys.readouterr().err == ""
        with stops.holding():  # the final save, now that the run is stopping
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    assert "SIGTERM while the checkpoint is written" in capsys.readouterr().err

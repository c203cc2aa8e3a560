"""Shared helpers of the learning and speed benchmarks: machine description, results files."""

from __future__ import annotations

import csv
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from train.runtime.machine import PROCESSES_VARIABLE, available_cores, machine, machine_line

__all__ = [
    "RESULTS_DIR",
    "caption",
    "command",
    "die_with_parent",
    "final_eval",
    "git_commit",
    "machine",
    "machine_line",
    "run_jobs",
    "save_figure",
    "save_json",
    "save_markdown",
    "side_by_side_env",
    "success_bars",
]

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def die_with_parent() -> None:
    """In a child process a benchmark starts (``preexec_fn`` of a ``Popen``, initializer of
    a process pool): receive SIGTERM when the benchmark dies, however it dies, so that
    stopping a benchmark stops its runs too (an ``lcrl`` run saves its checkpoint on
    SIGTERM) instead of leaving them training alone. Linux only; elsewhere nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        return
    libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG


def side_by_side_env(processes: int = 2, **extra: str) -> dict[str, str]:
    """The environment of a child lcrl process that trains beside ``processes - 1`` others:
    ``LCRL_PROCESSES`` (so each takes its share of the cores as torch threads, see
    :func:`train.runtime.machine.default_threads`) and the same share for OpenMP and MKL, so that
    no more threads are busy than there are cores; plus ``extra`` variables."""
    threads = str(max(1, available_cores() // max(1, processes)))
    env = dict(os.environ)
    env.update({PROCESSES_VARIABLE: str(processes), "OMP_NUM_THREADS": threads})
    env.update(MKL_NUM_THREADS=threads, **extra)
    return env


def run_jobs(jobs: Sequence[tuple[str, list[str], Path]], parallel: int = 2) -> None:
    """Run commands ``parallel`` at a time, each with its share of the cores
    (:func:`side_by_side_env`): ``jobs`` are ``(name, argv, log file)``. A failed job stops
    the benchmark with its log named; the others finish first."""
    todo = list(jobs)
    running: list[tuple[str, subprocess.Popen, Any]] = []
    failed: list[str] = []
    while todo or running:
        while todo and len(running) < parallel and not failed:
            name, argv, log_path = todo.pop(0)
            log_path.parent.mkdir(parents=True, exist_ok=True)
            log = open(log_path, "w")  # noqa: SIM115
            print("== " + shlex.join(argv), flush=True)
            proc = subprocess.Popen(
                argv,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=side_by_side_env(parallel),
                preexec_fn=die_with_parent,
            )
            running.append((name, proc, log))
        if failed and not running:
            break
        time.sleep(2)
        for item in list(running):
            name, proc, log = item
            if proc.poll() is None:
                continue
            running.remove(item)
            log.close()
            if proc.returncode != 0:
                failed.append(f"{name} failed: see {log.name}")
            else:
                print(f"{name} done", flush=True)
    if failed:
        raise SystemExit("; ".join(failed))


def final_eval(out: Path, episodes: int, sets: Sequence[str]) -> dict[str, Any]:
    """The last evaluation in a run's eval.csv (``episodes`` per set): success per set
    with its 95% Wilson interval and per family."""
    from train.evaluation.eval_suite import wilson_interval

    with (out / "eval.csv").open() as f:
        row = list(csv.DictReader(f))[-1]
    result: dict[str, Any] = {"step": int(row["step"])}
    for name in sets:
        rate = float(row[f"{name}/success"])
        low, high = wilson_interval(round(rate * episodes), episodes)
        families = {
            k.split("/", 1)[1]: float(v)
            for k, v in row.items()
            if k.startswith(f"{name}/") and k != f"{name}/success" and v != ""
        }
        result[name] = {"success": rate, "ci": [round(low, 3), round(high, 3)], **families}
    return result


def command() -> str:
    """The command line that ran this benchmark, as typed from the repository root:
    ``python -m benchmarks.NAME ...`` for a module run, else the script's relative path."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    args = [shlex.quote(a) for a in sys.argv[1:]]
    if spec is not None and spec.name:
        return " ".join(["python", "-m", spec.name.removesuffix(".__main__"), *args])
    script = Path(sys.argv[0]).resolve()
    root = RESULTS_DIR.parent.parent
    shown = script.relative_to(root) if script.is_relative_to(root) else Path(sys.argv[0])
    return " ".join(["python", shlex.quote(str(shown)), *args])


def git_commit() -> str:
    """The commit the results were measured on, ``+changes`` when the tree differs from it
    (``unknown`` outside a git checkout)."""
    root = RESULTS_DIR.parent.parent
    try:  # check_output and call: a test that fakes subprocess.run leaves them alone
        head = subprocess.check_output(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=root,
            text=True,
            stderr=subprocess.DEVNULL,
        ).strip()
        dirty = subprocess.call(
            ["git", "diff", "--quiet", "HEAD", "--", ".", ":!benchmarks/results"],
            cwd=root,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+changes" if dirty else "")


def save_json(name: str, payload: dict[str, Any]) -> Path:
    """Write ``results/<name>.json``, with the ``git`` commit the figures were measured on
    and the ``date`` added where the payload does not give them."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    payload = {**payload}
    payload.setdefault("git", git_commit())
    payload.setdefault("date", time.strftime("%Y-%m-%d"))
    path.write_text(json.dumps(payload, indent=1))
    return path


def save_markdown(
    name: str, title: str, body: str, info: dict[str, Any], cmd: str | None = None
) -> Path:
    """Write ``results/<name>.md`` with the command (``cmd``, default this process's) and
    machine above ``body``."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.md"
    cmd = cmd or command()
    path.write_text(f"# {title}\n\nCommand: `{cmd}`\n\nMachine: {machine_line(info)}\n\n{body}\n")
    return path


#: Caption font size (points) and the width of one of its characters, in points.
CAPTION_SIZE, CAPTION_CHAR = 6, 6 * 0.55


def caption(fig: Any, info: dict[str, Any], cmd: str | None = None) -> None:
    """Put the command and machine under a matplotlib figure, the command wrapped at
    spaces to the figure's width."""
    import textwrap

    width = max(40, int(fig.get_figwidth() * 72 * 0.98 / CAPTION_CHAR))
    lines = textwrap.wrap(cmd or command(), width, break_on_hyphens=False)
    text = "\n".join([*lines, machine_line(info)])
    fig.text(0.01, 0.01, text, fontsize=CAPTION_SIZE, va="bottom")


def save_figure(name: str, fig: Any, info: dict[str, Any], cmd: str | None = None) -> Path:
    """Caption a matplotlib figure with the command (default this process's) and machine,
    write ``results/<name>.png`` and close it."""
    import matplotlib.pyplot as plt

    caption(fig, info, cmd)
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def success_bars(ax: Any, names: list[str], results: list[dict], episodes: int, **bar: Any) -> None:
    """Bars of ``lcrl eval`` success rates with their 95% intervals as whiskers."""
    ax.bar(names, [r["success"] for r in results], **bar)
    for i, r in enumerate(results):
        ax.plot([i, i], r["ci"], c="k", lw=1)
    ax.set(ylim=(0, 1.02), ylabel=f"success ({episodes} episodes, 95% CI)")

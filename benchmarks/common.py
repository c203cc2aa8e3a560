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
    "LCRL",
    "REQUIRED_KEYS",
    "RESULTS_DIR",
    "add_arm_options",
    "add_report_only",
    "by_machine",
    "caption",
    "child_env",
    "command",
    "curve",
    "die_with_parent",
    "eval_headline",
    "evaluate",
    "final_eval",
    "git_commit",
    "keep_timings",
    "machine",
    "machine_kind",
    "machine_line",
    "new_figure",
    "publish",
    "record_once",
    "reported_variants",
    "run_dir",
    "run_jobs",
    "run_logged",
    "run_seconds",
    "save_figure",
    "save_json",
    "save_markdown",
    "side_by_side_env",
    "success_bars",
    "train_arms",
    "tried_entries",
    "verdict",
]

RESULTS_DIR = Path(__file__).resolve().parent / "results"
#: The ``lcrl`` command as a benchmark starts it: this interpreter, the console's module.
LCRL = [sys.executable, "-m", "train.commands.cli"]


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


def one_thread_worker() -> None:
    """Initializer of a worker process that trains beside others (``ProcessPoolExecutor``):
    one torch thread, and one for OpenMP and MKL; it dies with the benchmark.

    ``OMP_NUM_THREADS`` is what keeps the one thread: a trainer that is not told its
    threads takes :func:`train.runtime.machine.default_threads`, which reads it. Without
    it, workers started together each saw the other core idle and took both, and two
    2-thread runs on two cores trained about ten times slower than two 1-thread runs.
    """
    os.environ.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    import torch

    torch.set_num_threads(1)
    die_with_parent()


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


def eval_headline(docs: dict[str, dict[str, Any]]) -> dict[str, float]:
    """The headline of results made of ``lcrl eval`` documents (``eval.json``), one per
    name: each name's success on each instruction set, as ``NAME_SET``."""
    return {
        f"{name}_{set_name}": round(float(result["success"]), 3)
        for name, doc in docs.items()
        for set_name, result in doc.get("sets", {}).items()
    }


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


#: Keys every result file carries (``command`` is this process's command unless given).
REQUIRED_KEYS = ("headline", "command", "machine", "tried", "git", "date")


def reported_variants(payload: dict[str, Any]) -> list[str]:
    """The variants a result reports side by side (its ``arms`` or ``variants``): each was
    tried, so each is listed under ``tried``."""
    return [
        f"{key.rstrip('s')} {name}"
        for key in ("arms", "variants")
        if isinstance(payload.get(key), dict)
        for name in payload[key]
    ]


def tried_entries(previous: Sequence[str], given: Sequence[str], run: str) -> list[str]:
    """A result's ``tried``: what earlier runs of it tried, what this run lists, and this
    run itself, in that order and each once. A result rewritten by a new run keeps the
    record of every variant tried before it."""
    entries: list[str] = []
    for entry in [*previous, *given, run]:
        if entry not in entries:
            entries.append(entry)
    return entries


def machine_kind(info: dict[str, Any]) -> str:
    """A machine's CPU and its instruction sets, as ``by_machine`` names it."""
    cpu, features = info.get("cpu", "unknown CPU"), info.get("cpu_features")
    return f"{cpu} ({features})" if features else cpu


def by_machine(old: dict[str, Any], payload: dict[str, Any], keys: Sequence[str]) -> dict:
    """The latest ``keys`` of the headline on each kind of machine the result was measured
    on: the file's earlier record (or, in a file from before the record, its own headline),
    with this run's figures under this machine's kind."""
    table = dict(old.get("by_machine") or {})
    if not table and isinstance(old.get("machine"), dict) and "headline" in old:
        table[machine_kind(old["machine"])] = {
            **{k: old["headline"][k] for k in keys if k in old["headline"]},
            "git": old.get("git"),
            "date": old["machine"].get("date", old.get("date")),
        }
    table[machine_kind(payload["machine"])] = {
        **{k: payload["headline"][k] for k in keys if k in payload["headline"]},
        "git": payload["git"],
        "date": payload["machine"].get("date", payload["date"]),
    }
    return table


def save_json(
    name: str,
    payload: dict[str, Any],
    tried: Sequence[str] = (),
    by_machine_keys: Sequence[str] = (),
) -> Path:
    """Write ``results/<name>.json``. The payload gives its ``headline`` and ``machine``;
    the harness adds the ``command`` (this process's, unless given), the ``git`` commit the
    figures were measured on, the ``date`` and ``tried``: the variants ``tried`` (and the
    payload's own ``tried``) after those the file already listed, then this run. With
    ``by_machine_keys``, ``by_machine`` keeps those headline keys of the latest run on each
    kind of machine (:func:`by_machine`): a speed measured on one CPU does not replace
    another CPU's."""
    from lcrl.errors import LcrlError

    missing = [key for key in ("headline", "machine") if key not in payload]
    if missing:
        raise LcrlError(f"result {name}: the payload has no {' or '.join(missing)}")
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    payload = {**payload}
    payload.setdefault("command", command())
    payload.setdefault("git", git_commit())
    payload.setdefault("date", time.strftime("%Y-%m-%d"))
    previous: list[str] = []
    old: dict[str, Any] = {}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
            previous = list(old.get("tried", []))
        except (ValueError, AttributeError):
            previous, old = [], {}
    if by_machine_keys:
        payload["by_machine"] = by_machine(old, payload, by_machine_keys)
    run = f"{payload['command']} (git {payload['git']}, {payload['date']})"
    given = [*payload.get("tried", []), *reported_variants(payload), *tried]
    payload["tried"] = tried_entries(previous, given, run)
    path.write_text(json.dumps(payload, indent=1) + "\n")
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
#: Lines of command a caption holds (the room under the figure); a longer command is cut
#: there, whole in the Markdown and JSON beside the figure.
CAPTION_LINES = 2


def caption(fig: Any, info: dict[str, Any], cmd: str | None = None) -> None:
    """Put the command and machine under a matplotlib figure, the command wrapped at
    spaces to the figure's width (at most :data:`CAPTION_LINES` lines of it)."""
    import textwrap

    width = max(40, int(fig.get_figwidth() * 72 * 0.98 / CAPTION_CHAR))
    more = " ... (the whole command: the .md beside)"
    lines = textwrap.wrap(cmd or command(), width, break_on_hyphens=False)
    if len(lines) > CAPTION_LINES:
        lines = [*lines[: CAPTION_LINES - 1], lines[CAPTION_LINES - 1][: width - len(more)] + more]
    text = "\n".join([*lines, machine_line(info)])
    fig.text(0.01, 0.01, text, fontsize=CAPTION_SIZE, va="bottom")


def save_figure(
    name: str,
    fig: Any,
    info: dict[str, Any],
    cmd: str | None = None,
    rect: tuple[float, float, float, float] | None = (0, 0.08, 1, 1),
) -> Path:
    """Lay out a matplotlib figure in ``rect`` (the room above its caption; None: as it
    is), caption it with the command (default this process's) and machine, write
    ``results/<name>.png`` and close it."""
    import matplotlib.pyplot as plt

    if rect is not None:
        fig.tight_layout(rect=rect)
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


def new_figure(**subplots: Any) -> tuple[Any, Any]:
    """A matplotlib figure and its axes (``plt.subplots(**subplots)``) drawn off screen."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(**subplots)


def verdict(reached: dict[str, bool]) -> str:
    """``"a reached, b NOT reached"``: each target by name and whether it was reached."""
    return ", ".join(f"{k} {'reached' if v else 'NOT reached'}" for k, v in reached.items())


def run_logged(argv: Sequence[str], log_path: Path, what: str) -> float:
    """Run one command with its output in ``log_path`` (stopped if the benchmark dies);
    a failure stops the benchmark naming the log. Returns its wall-clock seconds."""
    print("== " + shlex.join(argv), flush=True)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(log_path, "w") as log:
        code = subprocess.run(
            list(argv), stdout=log, stderr=subprocess.STDOUT, preexec_fn=die_with_parent
        ).returncode
    if code != 0:
        raise SystemExit(f"the {what} run failed: see {log_path}")
    return time.perf_counter() - start


def run_dir(args: Any, arm: str, seed: int) -> Path:
    """The run folder of one (arm, seed) of a benchmark: ``WORK/ARM-sSEED``."""
    return Path(args.work) / f"{arm}-s{seed}"


def train_arms(args: Any, argv: Any, arms: Sequence[str] | None = None) -> None:
    """Train every (arm, seed) of ``arms`` (default ``args.arms``) and ``args.seeds`` whose
    :func:`run_dir` has not finished (no ``report.md``), ``args.parallel`` at a time
    (:func:`run_jobs`). ``argv(arm, seed, out)`` is the ``lcrl`` command line after
    :data:`LCRL`; its log is the folder's name plus ``.log``."""
    jobs = []
    for seed in args.seeds:
        for arm in args.arms if arms is None else arms:
            out = run_dir(args, arm, seed)
            if not (out / "report.md").is_file():
                cmd = [*LCRL, *argv(arm, seed, out)]
                jobs.append((f"{arm}-s{seed}", cmd, out.with_suffix(".log")))
    run_jobs(jobs, args.parallel)


def record_once(path: Path, argv: Sequence[str]) -> Path:
    """A dataset ``lcrl ARGV --out PATH`` records, recorded only when it is not there."""
    if not path.is_file():
        cmd = [*LCRL, *argv, "--out", str(path), "--no-progress"]
        run_jobs([("record", cmd, path.with_suffix(".log"))], 1)
    return path


def keep_to_act(run: str | Path, dest: str | Path) -> str:
    """Keep run ``run``'s final policy in ``dest`` to act and be evaluated again
    (:func:`train.policies.loading.keep_checkpoint`: weights and configs, no critics,
    replay or optimiser state); returns the folder."""
    from train.policies.loading import keep_checkpoint

    return str(keep_checkpoint(run, dest, None, acting_only=True))


def keep_timings(name: str, results: dict[str, Any], keys: Sequence[str] = ("seconds",)) -> None:
    """Runs read back from their folders (which do not say how long they trained) keep the
    ``keys`` that the previous ``results/<name>.json`` measured for the same curve."""
    path = RESULTS_DIR / f"{name}.json"
    if not path.exists():
        return
    old = json.loads(path.read_text()).get("runs", {})
    for run, res in results.items():
        prev = old.get(run, {})
        if res["seconds"] is None and prev.get("seconds") and prev.get("curve") == res["curve"]:
            res.update({key: prev[key] for key in keys if key in prev})


def publish(
    name: str,
    payload: dict[str, Any],
    title: str,
    body: str,
    fig: Any = None,
    tried: Sequence[str] = (),
    rect: tuple[float, float, float, float] | None = (0, 0.08, 1, 1),
) -> None:
    """Write a result: ``results/<name>.json`` (:func:`save_json`), ``.md`` under ``title``
    and, given a figure, ``.png`` (laid out in ``rect``, above its caption); then say where
    they are."""
    save_json(name, payload, tried)
    save_markdown(name, title, body, payload["machine"], payload.get("command"))
    if fig is not None:
        save_figure(name, fig, payload["machine"], payload.get("command"), rect)
    print(f"wrote benchmarks/results/{name}.{{json,md{',png' if fig is not None else ''}}}")


def child_env() -> dict[str, str]:
    """Two runs share the cores (one torch thread each on two cores), offscreen rendering."""
    return side_by_side_env(2, MUJOCO_GL="egl")


def evaluate(
    run: Path, episodes: int, sets: Sequence[str], seed: int = 0, env: dict | None = None
) -> dict:
    """``lcrl eval`` of a run's final checkpoint on the instruction ``sets``, at evaluation
    ``seed`` (another seed than 0 writes ``eval-seed<seed>.json`` beside the run's
    ``final-eval.json``): success per set. ``env``: the child's environment (default
    :func:`child_env`)."""
    path = run / (f"eval-seed{seed}.json" if seed else "final-eval.json")
    cmd = [*LCRL, "eval", str(run), "--episodes", str(episodes), "--json", str(path)]
    cmd += ["--sets", *sets, *(("--seed", str(seed)) if seed else ()), "--no-progress"]
    env = child_env() if env is None else env
    subprocess.run(cmd, check=True, env=env, preexec_fn=die_with_parent)
    return json.loads(path.read_text())["sets"]


def run_seconds(run: Path) -> float:
    """How long a finished run trained: from its config.json (written when it starts) to
    its report.md (written when it ends)."""
    return (run / "report.md").stat().st_mtime - (run / "config.json").stat().st_mtime


def curve(run: Path) -> list[dict[str, float]]:
    """The periodic evaluations of a run (the rows of its eval.csv; none without one)."""
    path = run / "eval.csv"
    if not path.is_file():
        return []
    with path.open() as f:
        return [{k: float(v) for k, v in row.items() if v != ""} for row in csv.DictReader(f)]


def add_report_only(parser: Any, what: str) -> None:
    """``--report-only``: run nothing, rebuild the results from ``what``."""
    parser.add_argument(
        "--report-only", action="store_true", help=f"run nothing: rebuild the results from {what}"
    )


def add_arm_options(
    parser: Any, arms: Sequence[str], work: str, seeds: Sequence[int] = (0, 1, 2)
) -> None:
    """The options of a benchmark over arms and seeds: ``--arms``, ``--seeds``,
    ``--eval-episodes``, ``--parallel`` (runs at a time, one thread each) and ``--work``."""
    parser.add_argument("--arms", nargs="+", choices=list(arms), default=list(arms))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(seeds))
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--work", default=work)

"""Multi-task RL on the 2D tabletop: task ids against language goals, with and without PCGrad.

Run from the repository root::

    python benchmarks/multitask.py --parallel   # the 4 runs, 2 side by side, 30k steps each
    python benchmarks/multitask.py --runs ids ids-pcgrad ids-gradnorm --seeds 0 1 2 --reuse
    python benchmarks/multitask.py --runs lang lang-pcgrad --seeds 0 1 2 --parallel --reuse
    python benchmarks/multitask.py --steps 1000 --eval-episodes 16   # a quick check
    python benchmarks/multitask.py --report-only   # rebuild the results from runs/bench/

The same 8 tasks (``train.configs.presets.TASKS_2D``: 4 reach and 4 push instructions of the 2D
split's training set) are learned four ways, with the same seed, budget and collection (one
environment, batch 256):

``ids``
    the ``lang2d-tasks`` preset: one-hot task ids, each task rewarded by its own rule
    captioner check, no relabelling (multi-task RL).
``ids-pcgrad``
    the same with PCGrad on the critic and actor gradients.
``lang``
    the ``lang2d-tasks-lang`` preset: the same tasks as language goals (frozen text
    embeddings), relabelled in hindsight among the 8 instructions (language HER).
``lang-pcgrad``
    the same with PCGrad.
``ids-gradnorm``
    task ids with GradNorm task weights (``--agent.multitask.weighting gradnorm``).

With ``--runs ids ids-pcgrad ids-gradnorm --seeds 0 1 2`` the ``headline`` holds
``uniform_mean``, ``pcgrad_mean`` and ``gradnorm_mean``: the final mean success over the
seeds of the three task-balancing arms; with ``--runs lang lang-pcgrad`` it holds
``language_mean`` and ``language_pcgrad_mean`` the same way. The runs an invocation does
not train stay in the file with the command and date that gave them, so the two
invocations together give the whole headline.

Every run measures gradient conflict between the tasks every 10 updates (the presets'
``conflict_every``; PCGrad runs measure it at every update, before projecting), so all
four report the same statistic: the mean pairwise cosine similarity of the tasks' critic
and actor gradients and the fraction of task pairs whose gradients conflict (negative dot
product), averaged over the run.

The table gives, for the final evaluation (episodes run round robin over the tasks, fixed
layouts), the success of every task and the mean over all episodes with 95% Wilson
intervals. Results go to ``benchmarks/results/multitask.{json,md,png}``; the runs
themselves to ``runs/bench/multitask-<run>/`` (not kept in the repository). ``--reuse``
reads a finished run there instead of training it again when its config is the same. Runs
write a checkpoint with their replay buffer at every evaluation, and a run stopped before
its budget (the machine shut down) goes on from its last checkpoint when the same command
runs again; its time is the training seconds of all its parts (``train_s`` of eval.csv).
With ``--reuse`` the runs already finished are kept, so the 9 task-balancing runs (11 to
20 minutes each at one thread, two side by side) may span several sessions of the same
command. ``--keep DIR`` keeps every run of the invocation to act in ``DIR/<run>/seedS``
(weights and configs: about 0.5 MB each); ``benchmarks/models/multitask`` holds those of
the figures in the file.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import multiprocessing
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from benchmarks.common import (
    RESULTS_DIR,
    add_report_only,
    command,
    keep_timings,
    keep_to_act,
    machine,
    one_thread_worker,
    save_figure,
    save_json,
    save_markdown,
)
from benchmarks.learning_curves import resumable, reusable
from train.configs.config import TrainConfig
from train.configs.presets import PRESETS
from train.environments.tasks import task_texts
from train.evaluation.eval_suite import wilson_interval
from train.training.loop import Trainer

NAME = "multitask"
TITLE = "Multi-task RL on the 2D tabletop: 8 tasks as task ids or language goals, PCGrad"
#: Run name -> (preset, PCGrad, task weighting).
RUNS: dict[str, tuple[str, bool, str]] = {
    "ids": ("lang2d-tasks", False, "fixed"),
    "ids-pcgrad": ("lang2d-tasks", True, "fixed"),
    "ids-gradnorm": ("lang2d-tasks", False, "gradnorm"),
    "lang": ("lang2d-tasks-lang", False, "fixed"),
    "lang-pcgrad": ("lang2d-tasks-lang", True, "fixed"),
}
#: How every arm collects and samples, whatever its preset ships: one environment at batch
#: 256, the settings the arms of benchmarks/results/multitask.json were measured with
#: (``lang2d-tasks-lang`` has shipped 8 environments at batch 128 since; task ids have not).
COLLECTION = {"envs": 1, "batch_size": 256}
#: The runs of the first version of this benchmark (``--runs`` default).
DEFAULT_RUNS = ["ids", "ids-pcgrad", "lang", "lang-pcgrad"]
#: The headline's three task-balancing arms over task ids: key -> run.
BALANCING = {"uniform_mean": "ids", "pcgrad_mean": "ids-pcgrad", "gradnorm_mean": "ids-gradnorm"}
#: The headline's language-goal arms (language HER among the 8 tasks): key -> run.
LANGUAGE = {"language_mean": "lang", "language_pcgrad_mean": "lang-pcgrad"}
#: Gradient-conflict columns of progress.csv, as (network, statistic, column).
CONFLICT = [
    (net, stat, f"grad/{net}_{stat}")
    for net in ("critic", "actor")
    for stat in ("cos_mean", "conflict")
]


def run_folder(name: str, seed: int = 0) -> Path:
    """Where run ``name`` trains (seed 0 in the folder of the first version)."""
    return Path("runs/bench") / f"{NAME}-{name}{f'-s{seed}' if seed else ''}"


def run_config(
    name: str, steps: int | None, seed: int, eval_episodes: int, device: str
) -> TrainConfig:
    """The training config of one run. A ``steps`` budget below the presets' learning
    start and evaluation interval shrinks them to fit (a quick check of the script)."""
    preset, pcgrad, weighting = RUNS[name]
    cfg: TrainConfig = PRESETS[preset][1]
    total = steps or cfg.total_steps
    learning_starts = min(cfg.learning_starts, total // 4)
    eval_every = cfg.eval_every if total >= 2 * cfg.eval_every else max(total // 2, 1)
    cfg = dataclasses.replace(
        cfg,
        out=str(run_folder(name, seed)),
        # every arm collects alike: the presets' own collection differs since
        # lang2d-tasks-lang ships 8 environments at batch 128 (see COLLECTION)
        collect=dataclasses.replace(cfg.collect, envs=COLLECTION["envs"]),
        batch_size=COLLECTION["batch_size"],
        total_steps=total,
        learning_starts=learning_starts,
        eval_every=eval_every,
        eval_episodes=eval_episodes,
        # a checkpoint with the replay buffer at every evaluation: a run stopped with the
        # session goes on from there next time (train_one)
        checkpoint_every=eval_every,
        keep_checkpoints=1,
        save_buffer=True,
        progress=False,
        seed=seed,
    )
    cfg.agent = dataclasses.replace(
        cfg.agent,
        seed=seed,
        device=device,
        multitask=dataclasses.replace(cfg.agent.multitask, pcgrad=pcgrad, weighting=weighting),
    )
    return cfg


def train_one(cfg: TrainConfig) -> float:
    """Train one run: from its last checkpoint when the folder holds the same run stopped
    before its budget, from scratch otherwise; returns this process's wall-clock seconds."""
    t0 = time.perf_counter()
    if resumable(cfg, Path(cfg.out)):
        print(f"== resuming {cfg.out}", flush=True)
        cfg = dataclasses.replace(cfg, resume=True)
    else:
        shutil.rmtree(cfg.out, ignore_errors=True)
    Trainer(cfg).run()
    return time.perf_counter() - t0


def _rows(path: Path, until: int) -> list[dict[str, float]]:
    """A run's CSV log as floats, up to step ``until``."""
    if not path.exists():
        return []
    with path.open() as f:
        rows = [
            {k: float(v) if v not in ("", None) else math.nan for k, v in r.items()}
            for r in csv.DictReader(f)
        ]
    return [r for r in rows if r["step"] <= until]


def per_task_counts(episodes: int, num_tasks: int) -> list[int]:
    """Evaluation episodes of each task when ``episodes`` run round robin over the tasks."""
    return [episodes // num_tasks + (i < episodes % num_tasks) for i in range(num_tasks)]


def _interval(successes: int, n: int) -> dict[str, Any]:
    low, high = wilson_interval(successes, n)
    return {
        "success": successes / n if n else math.nan,
        "successes": successes,
        "episodes": n,
        "low": low,
        "high": high,
    }


def summarise(name: str, cfg: TrainConfig, seconds: float | None) -> dict[str, Any]:
    """A run's figures from its folder: evaluation curve, final per-task and mean success
    with Wilson intervals, and the gradient conflict it measured (up to its budget)."""
    folder = Path(cfg.out)
    tasks = task_texts(cfg.env)
    curve = _rows(folder / "eval.csv", cfg.total_steps)
    if not curve:
        raise SystemExit(f"no evaluation in {folder}/eval.csv: train the run first")
    final = curve[-1]
    counts = per_task_counts(cfg.eval_episodes, len(tasks))
    per_task = []
    for i, (text, n) in enumerate(zip(tasks, counts, strict=True)):
        rate = final.get(f"tasks/{i}", math.nan)
        k = 0 if math.isnan(rate) else round(rate * n)
        per_task.append({"id": i, "instruction": text, **_interval(k, n)})
    total = sum(t["successes"] for t in per_task)
    progress = _rows(folder / "progress.csv", cfg.total_steps)
    conflict = {}
    for _, _, column in CONFLICT:
        values = [r[column] for r in progress if not math.isnan(r.get(column, math.nan))]
        conflict[column.removeprefix("grad/")] = float(np.mean(values)) if values else None
    return {
        "preset": RUNS[name][0],
        "goal_type": cfg.env.goal_type,
        "pcgrad": cfg.agent.multitask.pcgrad,
        "weighting": cfg.agent.multitask.weighting,
        "seed": cfg.seed,
        "total_steps": int(final["step"]),
        # training seconds over every session the run took, evaluations excluded
        "seconds": final["train_s"] if not math.isnan(final.get("train_s", math.nan)) else seconds,
        "final": {"mean": _interval(total, sum(counts)), "tasks": per_task},
        "conflict": conflict,
        "curve": [
            {k: v for k, v in r.items() if k == "step" or k.startswith(("train/", "tasks/"))}
            for r in curve
        ],
        "conflict_curve": [
            {"step": r["step"], **{c: r.get(c, math.nan) for _, _, c in CONFLICT}} for r in progress
        ],
    }


def carry_over(results: dict[str, Any], names: set[str], path: Path | None = None) -> None:
    """Runs of the previous results that this invocation does not train (another run
    name, e.g. ``lang`` beside a task-balancing invocation) stay in the file, each with
    the command and date that produced it (``kept_from``), so a partial invocation never
    drops figures that the rest of the documentation quotes."""
    path = path or RESULTS_DIR / f"{NAME}.json"
    if not path.exists():
        return
    old = json.loads(path.read_text())
    source = {"command": old.get("command"), "date": old.get("machine", {}).get("date")}
    for key, res in old.get("runs", {}).items():
        name = res.get("run", key)
        if key in results or name in names:
            continue
        results[key] = {"run": name, **res, "kept_from": res.get("kept_from", source)}


def balance(r: dict[str, Any]) -> str:
    """How a run balanced its tasks."""
    if r.get("weighting") == "gradnorm":
        return "GradNorm"
    return "PCGrad" if r["pcgrad"] else "uniform"


def _cell(st: dict[str, Any]) -> str:
    return f"{st['success']:.2f} [{st['low']:.2f}, {st['high']:.2f}]"


def _num(x: float | None) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def markdown(results: dict[str, Any], tasks: tuple[str, ...], episodes: int) -> str:
    """The two tables: runs (mean success, conflict, time) and success per task."""
    lines = [
        "| run | goals | balancing | steps | mean success [95% CI] | critic cos | critic conflict "
        "| actor cos | actor conflict | train time |",
        "|---|---|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in results.items():
        c = r["conflict"]
        goals = "task ids" if r["goal_type"] == "task" else "language (HER)"
        secs = f"{r['seconds']:.0f} s" if r.get("seconds") else "n/a"
        lines.append(
            f"| {name} | {goals} | {balance(r)} | {r['total_steps']:,} | "
            f"{_cell(r['final']['mean'])} | {_num(c['critic_cos_mean'])} | "
            f"{_num(c['critic_conflict'])} | {_num(c['actor_cos_mean'])} | "
            f"{_num(c['actor_conflict'])} | {secs} |"
        )
    lines += [
        "",
        "Mean success: all final evaluation episodes "
        f"({episodes}, round robin over the {len(tasks)} tasks, fixed layouts). cos: mean "
        "pairwise cosine similarity of the tasks' gradients; conflict: fraction of task pairs "
        "with a negative dot product; both averaged over the run's measurements (before any "
        "PCGrad projection).",
        "",
        "| task | " + " | ".join(results) + " |",
        "|---|" + "---|" * len(results),
    ]
    for i, text in enumerate(tasks):
        cells = [_cell(r["final"]["tasks"][i]) for r in results.values()]
        lines.append(f"| {i}: {text} | " + " | ".join(cells) + " |")
    lines += ["", "Success per task with 95% Wilson intervals over that task's episodes."]
    kept = {k: r["kept_from"] for k, r in results.items() if r.get("kept_from")}
    for key, src in kept.items():
        cmd = src.get("command") or "an earlier version of this benchmark"
        lines.append(f"\n`{key}` is kept from an earlier invocation ({src.get('date')}): {cmd}.")
    return "\n".join(lines)


def figure(results: dict[str, Any], tasks: tuple[str, ...], info: dict[str, Any]) -> Path:
    """Evaluation curves, final success per task, gradient conflict over training."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), gridspec_kw={"width_ratios": [1, 1.6, 1]})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    width = 0.8 / max(len(results), 1)
    x = np.arange(len(tasks))
    for k, (name, r) in enumerate(results.items()):
        colour = colours[k % len(colours)]
        ax = axes[0]
        steps = [c["step"] for c in r["curve"]]
        ax.plot(
            steps,
            [c["train/success"] for c in r["curve"]],
            marker="o",
            ms=3,
            color=colour,
            label=name,
        )
        per = r["final"]["tasks"]
        ys = np.array([t["success"] for t in per])
        err = np.array(
            [[t["success"] - t["low"] for t in per], [t["high"] - t["success"] for t in per]]
        )
        offset = (k - (len(results) - 1) / 2) * width
        axes[1].bar(x + offset, ys, width, yerr=err, capsize=2, color=colour, label=name)
        cc = r["conflict_curve"]
        steps = [c["step"] for c in cc]
        critic = [c["grad/critic_conflict"] for c in cc]
        actor = [c["grad/actor_conflict"] for c in cc]
        axes[2].plot(steps, critic, marker="o", ms=3, color=colour, label=f"{name} critic")
        axes[2].plot(steps, actor, "--", marker="x", ms=3, color=colour, label=f"{name} actor")
    axes[0].set_title("evaluation, mean over tasks", fontsize=9)
    axes[0].set_xlabel("environment steps")
    axes[0].set_ylabel("success rate")
    axes[1].set_title("final success per task (95% Wilson)", fontsize=9)
    labels = [f"{i}: {t}" for i, t in enumerate(tasks)]
    axes[1].set_xticks(x, labels, rotation=30, ha="right", fontsize=7)
    axes[2].set_title("fraction of conflicting task pairs", fontsize=9)
    axes[2].set_xlabel("environment steps")
    for ax in axes:
        ax.set_ylim(-0.02, 1.02)
        ax.legend(fontsize=6)
    fig.suptitle(TITLE, fontsize=10)
    return save_figure(NAME, fig, info, rect=(0, 0.06, 1, 1))


def balancing_headline(results: dict[str, Any]) -> dict[str, Any]:
    """``uniform_mean``, ``pcgrad_mean`` and ``gradnorm_mean``: the final mean success of
    the task-id runs of each balancing, averaged over the seeds that ran (with its
    spread); ``language_mean`` and ``language_pcgrad_mean`` the same of the language-goal
    runs."""
    from train.evaluation.report import spread

    out: dict[str, Any] = {}
    for key, run in {**BALANCING, **LANGUAGE}.items():
        values = [r["final"]["mean"]["success"] for r in results.values() if r["run"] == run]
        if values:
            sp = spread(values)
            out[key] = round(sp["mean"], 3)
            out[key.replace("_mean", "_std")] = round(sp["std"], 3)
            out[key.replace("_mean", "_seeds")] = sp["runs"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=None, help="override the step budget")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--eval-episodes", type=int, default=160, help="per evaluation")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument(
        "--runs", nargs="+", choices=sorted(RUNS), default=DEFAULT_RUNS, help="a subset of runs"
    )
    parser.add_argument(
        "--parallel",
        type=int,
        nargs="?",
        const=2,
        default=1,
        help="runs trained side by side, one process and one thread each (2 without a value)",
    )
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="read a finished run with the same config in runs/bench/multitask-<run> (cut at "
        "this budget) instead of training it again",
    )
    parser.add_argument(
        "--keep",
        default="",
        help="keep every run of this invocation to act (weights and configs, no critics or "
        "replay) in KEEP/<run>/seedS",
    )
    parser.add_argument("--note", default="", help="what changed since the file's last figures")
    add_report_only(parser, "the runs in runs/bench/")
    args = parser.parse_args(argv)
    info = machine()
    keys = {
        (name, seed): name if len(args.seeds) == 1 else f"{name}-s{seed}"
        for seed in args.seeds
        for name in args.runs
    }
    configs = {
        key: run_config(name, args.steps, seed, args.eval_episodes, args.device)
        for (name, seed), key in keys.items()
    }
    seconds: dict[str, float | None] = {}
    todo = {}
    for key, cfg in configs.items():
        if args.report_only:
            seconds[key] = None
        elif args.reuse and reusable(cfg, Path(cfg.out)) is not None:
            print(f"== {key}: reusing {cfg.out}")
            seconds[key] = None
        else:
            todo[key] = cfg
    if args.parallel > 1 and len(todo) > 1:
        info["torch_threads"] = 1
        ctx = multiprocessing.get_context("spawn")
        workers = min(args.parallel, len(todo))
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=one_thread_worker) as pool:
            futures = {key: pool.submit(train_one, cfg) for key, cfg in todo.items()}
            seconds.update({key: f.result() for key, f in futures.items()})
    else:
        for key, cfg in todo.items():
            print(f"== {key}: {cfg.out}", flush=True)
            seconds[key] = train_one(cfg)
    results = {}
    for (name, seed), key in keys.items():
        results[key] = {"run": name, **summarise(name, configs[key], seconds[key])}
        if args.keep:
            results[key]["kept"] = keep_to_act(
                configs[key].out, Path(args.keep) / name / f"seed{seed}"
            )
    keep_timings(NAME, results)
    carry_over(results, set(args.runs))
    any_cfg = next(iter(configs.values()))
    tasks = task_texts(any_cfg.env)
    payload: dict[str, Any] = {"suite": NAME}
    headline = balancing_headline(results)
    if headline:
        payload["headline"] = headline
    payload.update(
        command=command(), machine=info, seeds=args.seeds, tasks=list(tasks), runs=results
    )
    if args.note:
        payload["note"] = args.note
    save_json(NAME, payload)
    table = markdown(results, tasks, any_cfg.eval_episodes)
    if headline:
        table = (
            "Final mean success over seeds: "
            + ", ".join(
                f"{k.removesuffix('_mean').replace('_', ' ')} {headline[k]:.3f} ± "
                f"{headline[k.replace('_mean', '_std')]:.3f} "
                f"({headline[k.replace('_mean', '_seeds')]} seeds)"
                for k in {**BALANCING, **LANGUAGE}
                if k in headline
            )
            + " (uniform, pcgrad and gradnorm: task ids).\n\n"
            + table
        )
    if args.note:
        table += f"\n\n## What changed in this measurement\n\n{args.note}"
    print(table)
    save_markdown(NAME, TITLE, table, info)
    figure(results, tasks, info)
    print(f"saved benchmarks/results/{NAME}.{{json,md,png}}")
    return 0


if __name__ == "__main__":
    from train.training.trainer import RunInterrupted

    try:
        raise SystemExit(main())
    except RunInterrupted as stop:  # the run saved its checkpoint; the same command goes on
        raise SystemExit(f"stopped ({stop}); run the same command to go on") from None

"""Learning curves that the project must show, with their targets.

Run from the repository root (needs ``pip install -e '.[bench]'`` for Fetch)::

    python benchmarks/learning_curves.py fetch-reach   # SAC + HER, FetchReach-v4, 10k steps
    python benchmarks/learning_curves.py lang2d --parallel  # language HER vs none, 100k
    python benchmarks/learning_curves.py robosuite-reach --parallel  # robosuite, 50k

``fetch-reach``: SAC + HER (future, k=4) on gymnasium-robotics ``FetchReach-v4``; target:
at least 90% success over 50 evaluation episodes within 10,000 environment steps.

``robosuite-reach``: the robosuite Panda tabletop with reach instructions and privileged
state observations, SAC + language HER against no relabelling, 50,000 steps; target: at
least 80% success on seen instructions.

``robosuite-reach-long``: the same language-HER run alone, for 100,000 steps (one
process, about 70 minutes on one core).

``robosuite-push`` (push instructions, 100,000 steps: the reach run's budget) and
``robosuite-image`` (reach instructions from 64x64 camera images and proprioception; a
CPU budget of 5,000 steps and 2,000 updates at batch 64, about 30 minutes on one core)
report what the same learner reaches there; their targets are the reach target.

``lang2d``: the 2D tabletop with language goals (reach and push families), SAC with
language hindsight relabelling against the same run without relabelling (``k=0``); both
let the scripted controller act 20% of the training episodes (the preset's
``scripted_fraction``; those steps count in the budget). Target: at least 80% success on
seen instructions within 100,000 steps, the baseline far below. Held-out word
combinations and unseen phrasings are reported too. ``lang2d-rl`` is the relabelling run
with every training episode the policy's.

``lang2d-learned``: the ``lang2d`` runs relabelled by the learned models of
``python benchmarks/captioning.py`` (from 64x64 camera frames, no privileged state):
``learned`` (learned captioner proposes the goals, learned reward model gives the
rewards), ``learned-captions`` (the learned captions are the rewards too, as in HIGhER),
next to the rule captioner's ``her`` and ``no-her``, same seed, 50,000 steps; target: the
learned run at 60% on seen instructions, about twice the run without relabelling.
``--reuse`` reads ``her`` and ``no-her`` from the ``lang2d`` suite's runs when their config
is the same (cut at 50,000 steps) instead of training them again::

    python benchmarks/captioning.py
    python benchmarks/learning_curves.py lang2d-learned --parallel --reuse

Each run writes ``benchmarks/results/<suite>.{json,md,png}``; the training runs themselves
go to ``runs/bench/`` (not kept in the repository).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import multiprocessing
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks.common import (
    keep_timings,
    machine,
    one_thread_worker,
    save_figure,
    save_json,
    save_markdown,
)
from train.configs.config import BufferConfig, RelabelConfig, TrainConfig
from train.configs.presets import PRESETS
from train.environments.tasks import EnvConfig
from train.training.loop import Trainer

#: The learned captioner and reward model of ``python benchmarks/captioning.py``.
LEARNED_CHECKPOINT = "runs/bench/captioner-lang2d"

SUITES: dict[str, dict[str, Any]] = {
    "fetch-reach": {
        "title": "SAC + HER on FetchReach-v4",
        "runs": {"her": ("fetch-reach", {})},
        "eval_every": 1_000,
        "eval_episodes": 50,
        "target": ("her", "all", 0.90, 10_000),
    },
    "lang2d": {
        "title": "Language HER on the 2D tabletop (reach, push)",
        "runs": {
            "her": ("lang2d", {}),
            "no-her": ("lang2d", {"buffer": BufferConfig(k=0)}),
        },
        "eval_every": 10_000,
        "eval_episodes": 100,
        "target": ("her", "train", 0.80, 100_000),
    },
    "lang2d-learned": {
        "title": "Language HER on the 2D tabletop: rule vs learned relabelling (reach, push)",
        "runs": {
            "her": ("lang2d", {}),
            "learned": (
                "lang2d",
                {"relabel": RelabelConfig("learned", "learned", LEARNED_CHECKPOINT)},
            ),
            "learned-captions": (
                "lang2d",
                {"relabel": RelabelConfig("learned", "captioner", LEARNED_CHECKPOINT)},
            ),
            "no-her": ("lang2d", {"buffer": BufferConfig(k=0)}),
        },
        "steps": 50_000,
        "eval_every": 10_000,
        "eval_episodes": 100,
        "target": ("learned", "train", 0.60, 50_000),
        "needs": LEARNED_CHECKPOINT,
        "reuse": "lang2d",
    },
    "lang2d-rl": {
        "title": "Language HER on the 2D tabletop (reach, push), no scripted episodes",
        "runs": {"her": ("lang2d-rl", {})},
        "eval_every": 10_000,
        "eval_episodes": 100,
        "target": ("her", "train", 0.80, 100_000),
    },
    "robosuite-reach": {
        "title": "Language HER on the robosuite Panda tabletop (reach, privileged state)",
        "runs": {
            "her": ("robosuite", {"env": EnvConfig(kind="robosuite", families=("reach",))}),
            "no-her": (
                "robosuite",
                {
                    "env": EnvConfig(kind="robosuite", families=("reach",)),
                    "buffer": BufferConfig(k=0),
                },
            ),
        },
        "eval_every": 5_000,
        "eval_episodes": 50,
        "target": ("her", "train", 0.80, 50_000),
        "steps": 50_000,
    },
    "robosuite-reach-long": {
        "title": "Language HER on the robosuite Panda tabletop (reach, privileged state), 100k",
        "runs": {
            "her": ("robosuite", {"env": EnvConfig(kind="robosuite", families=("reach",))}),
        },
        "eval_every": 10_000,
        "eval_episodes": 50,
        "target": ("her", "train", 0.80, 100_000),
        "steps": 100_000,
    },
    "robosuite-push": {
        "title": "Language HER on the robosuite Panda tabletop (push, privileged state)",
        "runs": {
            "her": ("robosuite", {"env": EnvConfig(kind="robosuite", families=("push",))}),
        },
        "eval_every": 10_000,
        "eval_episodes": 50,
        "target": ("her", "train", 0.80, 100_000),
        "steps": 100_000,
    },
    "robosuite-image": {
        "title": "Language HER on the robosuite Panda tabletop from 64x64 camera images (reach)",
        "runs": {
            "her": (
                "robosuite-image",
                {
                    "env": EnvConfig(
                        kind="robosuite", families=("reach",), image_obs=True, image_size=64
                    ),
                    # A CPU budget: one SAC update on 256 images of 64x64 takes about 3 s
                    # on one core, so this run makes 2,000 updates of 64 images.
                    "batch_size": 64,
                    "updates_per_step": 0.5,
                    "learning_starts": 1_000,
                },
            ),
        },
        "eval_every": 2_500,
        "eval_episodes": 30,
        "target": ("her", "train", 0.80, 5_000),
        "steps": 5_000,
    },
}


def run_config(
    preset: str,
    overrides: dict[str, Any],
    out: Path,
    suite: dict[str, Any],
    steps: int | None,
    seed: int,
) -> TrainConfig:
    """The training config of one run of a suite."""
    cfg: TrainConfig = dataclasses.replace(PRESETS[preset][1], **overrides)
    cfg = dataclasses.replace(
        cfg,
        out=str(out),
        eval_every=suite["eval_every"],
        eval_episodes=suite["eval_episodes"],
        checkpoint_every=0,
        save_buffer=False,
        progress=False,
        seed=seed,
        total_steps=steps or cfg.total_steps,
    )
    cfg.agent = dataclasses.replace(cfg.agent, seed=seed)
    return cfg


#: Config fields that do not change what a run learns up to a given step.
NOT_LEARNING = (
    "out",
    "total_steps",
    "progress",
    "overwrite",
    "resume",
    "tensorboard",
    "checkpoint_every",
    "keep_checkpoints",
    "save_buffer",
    "torch_threads",
)


def same_config(cfg: TrainConfig, folder: Path) -> bool:
    """Whether the run in ``folder`` was trained with ``cfg`` (apart from
    :data:`NOT_LEARNING`; options added since it was saved count as their defaults)."""
    saved_path = folder / "config.json"
    if not saved_path.exists():
        return False
    saved = json.loads(saved_path.read_text())
    wanted = json.loads(json.dumps(dataclasses.asdict(cfg)))
    for key in NOT_LEARNING:
        saved.pop(key, None)
        wanted.pop(key, None)
    saved = {k: v for k, v in saved.items() if k in wanted}  # derived fields (resolved_algo)
    _fill_defaults(saved, wanted, json.loads(json.dumps(dataclasses.asdict(TrainConfig()))))
    return saved == wanted


def resumable(cfg: TrainConfig, folder: Path) -> bool:
    """Whether ``folder`` holds a checkpoint of a run trained with ``cfg`` that stopped
    before ``cfg.total_steps``: training it goes on from there (``--resume``)."""
    from lcrl.checkpoint import CheckpointError, find_latest

    try:
        latest = find_latest(folder)
        step = int(json.loads((latest / "meta.json").read_text())["step"]) if latest else None
    except (CheckpointError, OSError, KeyError, ValueError):
        return False
    return step is not None and step < cfg.total_steps and same_config(cfg, folder)


def reusable(cfg: TrainConfig, folder: Path) -> list[dict[str, float]] | None:
    """The evaluation curve of a finished run in ``folder`` trained with the same config
    as ``cfg`` (apart from :data:`NOT_LEARNING`) for at least ``cfg.total_steps`` steps,
    cut at that budget; None if there is no such run."""
    saved_path, eval_path = folder / "config.json", folder / "eval.csv"
    if not saved_path.exists() or not eval_path.exists() or not same_config(cfg, folder):
        return None
    if int(json.loads(saved_path.read_text())["total_steps"]) < cfg.total_steps:
        return None
    curve = read_eval(folder)
    if not curve or curve[-1]["step"] < cfg.total_steps:
        return None
    # the evaluation that ends the budget is the first at or after it
    end = next(i for i, r in enumerate(curve) if r["step"] >= cfg.total_steps)
    return curve[: end + 1]


def _fill_defaults(saved: dict[str, Any], wanted: dict[str, Any], default: Any) -> None:
    """Options added after a run was saved count as the defaults it ran with."""
    for key, value in wanted.items():
        base = default.get(key) if isinstance(default, dict) else None
        if key not in saved:
            if isinstance(default, dict) and key in default and value == base:
                saved[key] = value
        elif isinstance(value, dict) and isinstance(saved[key], dict):
            _fill_defaults(saved[key], value, base)


def run_one(job: tuple[Any, ...]) -> dict[str, Any]:
    """Train one configuration (:func:`run_config`'s arguments) and return its evaluation
    curve."""
    preset, out = job[0], job[2]
    cfg = run_config(*job)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    Trainer(cfg).run()
    seconds = time.perf_counter() - t0
    rows = read_eval(out)
    return {
        "preset": preset,
        "k": cfg.buffer.k,
        "seconds": seconds,
        "curve": rows,
        "total_steps": cfg.total_steps,
    }


def read_eval(out: Path) -> list[dict[str, float]]:
    """The evaluation curve a run wrote to ``out/eval.csv``."""
    with (out / "eval.csv").open() as f:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]


def read_run(preset: str, overrides: dict[str, Any], out: Path) -> dict[str, Any]:
    """A finished or stopped run's curve, from its folder (no timing)."""
    if not (out / "eval.csv").exists():
        raise SystemExit(f"no evaluations in {out}: train the suite first")
    cfg: TrainConfig = dataclasses.replace(PRESETS[preset][1], **overrides)
    curve = read_eval(out)
    return {
        "preset": preset,
        "k": cfg.buffer.k,
        "seconds": None,
        "curve": curve,
        "total_steps": int(curve[-1]["step"]) if curve else 0,
    }


def headline(
    results: dict[str, dict[str, Any]], reached: float | None, set_name: str
) -> dict[str, Any]:
    """The first step at which the target run reached its target, and each run's final
    success on every instruction set it was evaluated on."""
    head: dict[str, Any] = {"first_step_reached": reached}
    for name, run in results.items():
        last = run["curve"][-1] if run.get("curve") else {}
        for key, value in last.items():
            if key.endswith("/success") and value is not None:
                head[f"{name}_{key.split('/')[0]}"] = round(float(value), 3)
    return head


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("suite", choices=sorted(SUITES))
    parser.add_argument("--steps", type=int, default=None, help="override the step budget")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--parallel",
        action="store_true",
        help="train the runs side by side, one process and one thread each",
    )
    parser.add_argument(
        "--eval-episodes", type=int, default=None, help="override the episodes per evaluation set"
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: rebuild the results from the evaluations already in runs/bench/ "
        "(e.g. of a run stopped early)",
    )
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="read runs that the suite's 'reuse' suite already trained with the same config "
        "(runs/bench/<that suite>-<run>), cut at this budget, instead of training them again",
    )
    args = parser.parse_args(argv)
    suite = dict(SUITES[args.suite])
    needs = suite.get("needs")
    if needs and not args.report_only and not (Path(needs) / "meta.json").exists():
        raise SystemExit(
            f"the {args.suite} suite needs the learned models in {needs}: run "
            "python benchmarks/captioning.py first"
        )
    if args.eval_episodes:
        suite["eval_episodes"] = args.eval_episodes
    info = machine()
    if args.parallel and len(suite["runs"]) > 1:
        info["torch_threads"] = 1  # each run's process (see _one_thread)
    results: dict[str, Any] = {}
    jobs = {
        name: (
            preset,
            overrides,
            Path("runs/bench") / f"{args.suite}-{name}",
            suite,
            args.steps or suite.get("steps"),
            args.seed,
        )
        for name, (preset, overrides) in suite["runs"].items()
    }
    if args.reuse and suite.get("reuse"):
        for name in list(jobs):
            folder = Path("runs/bench") / f"{suite['reuse']}-{name}"
            curve = reusable(run_config(*jobs[name]), folder)
            if curve is None:
                print(f"== {name}: no finished run with the same config in {folder}")
                continue
            print(f"== {name}: reusing {folder} up to step {int(curve[-1]['step'])}")
            preset, overrides = jobs.pop(name)[:2]
            results[name] = {
                "preset": preset,
                "k": read_run(preset, overrides, folder)["k"],
                "seconds": None,
                "curve": curve,
                "total_steps": int(curve[-1]["step"]),
                "reused_from": str(folder),
            }
    if args.report_only:
        results.update({name: read_run(*job[:2], job[2]) for name, job in jobs.items()})
        keep_timings(args.suite, results, ("seconds", "total_steps"))
    elif args.parallel and len(jobs) > 1:
        # One process per run, one torch thread each, so that the runs share the machine.
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(len(jobs), mp_context=ctx, initializer=one_thread_worker) as pool:
            futures = {name: pool.submit(run_one, job) for name, job in jobs.items()}
            results.update({name: f.result() for name, f in futures.items()})
    else:
        for name, job in jobs.items():
            print(f"== {name}: preset {job[0]} {job[1] or ''}", flush=True)
            results[name] = run_one(job)
    results = {name: results[name] for name in suite["runs"] if name in results}
    run_name, set_name, threshold, budget = suite["target"]
    curve = results[run_name]["curve"]
    key = f"{set_name}/success"
    reached = next((r["step"] for r in curve if r[key] >= threshold and r["step"] <= budget), None)
    payload = {
        "suite": args.suite,
        "headline": headline(results, reached, set_name),
        "machine": info,
        "target": {
            "run": run_name,
            "set": set_name,
            "success": threshold,
            "within": budget,
            "first_step_reached": reached,
            "met": reached is not None,
        },
        "runs": results,
    }
    save_json(args.suite, payload, tried=[f"run {name}" for name in results])

    sets = [k.split("/")[0] for k in curve[0] if k.endswith("/success")]
    lines = [
        "| run | step | " + " | ".join(sets) + " | per family (seen) |",
        "|---|---:|" + "---:|" * len(sets) + "---|",
    ]
    for name, res in results.items():
        for r in res["curve"]:
            fams = ", ".join(
                f"{k.split('/')[1]} {v:.2f}"
                for k, v in r.items()
                if k.startswith(f"{sets[0]}/") and not k.endswith("/success")
            )
            lines.append(
                f"| {name} | {int(r['step'])} | "
                + " | ".join(f"{r[f'{s}/success']:.2f}" for s in sets)
                + f" | {fams} |"
            )
    lines.append("")
    verdict = f"first reached at step {reached}" if reached is not None else "NOT reached"
    lines.append(
        f"Target: {set_name} success >= {threshold:.0%} within {budget:,} steps "
        f"({run_name}): {verdict}."
    )
    for name, res in results.items():
        if res.get("reused_from"):
            lines.append(
                f"- {name}: read from {res['reused_from']} (trained by `learning_curves.py "
                f"{suite['reuse']}` with the same config), cut at step {res['total_steps']:,}"
            )
            continue
        if res["seconds"] is None:
            lines.append(
                f"- {name}: evaluated up to step {res['total_steps']:,} (rebuilt from "
                f"runs/bench/{args.suite}-{name}; no timing)"
            )
            continue
        lines.append(
            f"- {name}: {res['total_steps']:,} steps in {res['seconds']:.0f} s "
            f"({res['total_steps'] / res['seconds']:.0f} steps/s incl. evaluation)"
        )
    table = "\n".join(lines)
    print(table)
    save_markdown(args.suite, suite["title"], table, info)

    # one colour per run, one line style per instruction set
    fig, ax = plt.subplots(figsize=(8.5, 4.4))
    styles = {"train": "-", "all": "-", "heldout": "--", "paraphrase": ":"}
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, res) in enumerate(results.items()):
        for s in sets:
            xs = [r["step"] for r in res["curve"]]
            ys = [r[f"{s}/success"] for r in res["curve"]]
            width = 2.0 if s in ("train", "all") else 1.0
            colour = colours[i % len(colours)]
            ax.plot(xs, ys, styles.get(s, "-"), color=colour, marker="o", ms=3, lw=width,
                    label=f"{name}: {s}")  # fmt: skip
    ax.axhline(threshold, color="grey", lw=0.8)
    ax.axvline(budget, color="grey", lw=0.8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(suite["title"], fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    save_figure(args.suite, fig, info)
    print(f"saved benchmarks/results/{args.suite}.{{json,md,png}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

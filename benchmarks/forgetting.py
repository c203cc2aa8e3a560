"""Forgetting in sequential training on the 2D tabletop: naive, experience replay and EWC,
same stages, seeds and budget.

    python benchmarks/forgetting.py                      # reach then push, 3 seeds
    python benchmarks/forgetting.py --steps 4000 --seeds 0 --eval-episodes 20   # a check

Arms (``--arms``): ``naive`` (``--sequential.stages reach push``: the buffer starts empty
at each stage), ``replay`` (``--sequential.replay R``), ``ewc`` (``--sequential.ewc W``
with the Fisher of the networks' outputs, ``--sequential.ewc-fisher output``) and
``ewc-loss`` (``--sequential.ewc W_LOSS`` with the empirical Fisher of the losses).
Each trains ``lcrl train lang2d`` with those stages, one run per seed, two at a time with
one torch thread each; finished runs (their ``sequential.json`` and ``report.md``) are
kept, so an interrupted benchmark goes on where it stopped.

Writes ``benchmarks/results/forgetting.{json,md,png}``: ``headline.forgetting_naive``,
``forgetting_replay``, ``forgetting_ewc`` and ``forgetting_ewc_loss``, each the mean over
seeds of the mean drop of the earlier stage's success from its best (target: replay and
EWC below naive), with the spread over seeds, the success matrices and the backward and
forward transfer.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from benchmarks.common import (
    add_arm_options,
    machine,
    new_figure,
    run_dir,
    save_figure,
    save_json,
    save_markdown,
    train_arms,
)
from train.evaluation.report import spread

NAME = "forgetting"
ARMS = ("naive", "replay", "ewc", "ewc-loss")


def arm_args(arm: str, args: argparse.Namespace) -> list[str]:
    """The ``lcrl train`` options of an arm."""
    out = ["--sequential.stages", *args.stages]
    if arm == "replay":
        out += ["--sequential.replay", str(args.replay)]
    elif arm == "ewc":
        out += ["--sequential.ewc", str(args.ewc), "--sequential.ewc-fisher", "output"]
    elif arm == "ewc-loss":
        out += ["--sequential.ewc", str(args.ewc_loss), "--sequential.ewc-fisher", "loss"]
    return out


def key(arm: str) -> str:
    """The headline key of an arm."""
    return "forgetting_" + arm.replace("-", "_")


def run_all(args: argparse.Namespace) -> None:
    """Train every (arm, seed) without a finished run, ``--parallel`` at a time."""

    def argv(arm: str, seed: int, out: Path) -> list[str]:
        cmd = ["train", "lang2d", "--out", str(out), "--seed", str(seed)]
        cmd += ["--total-steps", str(args.steps), "--eval-every", "0"]
        cmd += ["--eval-episodes", str(args.eval_episodes), "--checkpoint-every", "0"]
        return [*cmd, "--overwrite", "--no-progress", "--no-tensorboard", *arm_args(arm, args)]

    train_arms(args, argv)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stages", nargs="+", default=["reach", "push"])
    add_arm_options(parser, ARMS, "runs/bench/forgetting")
    parser.add_argument("--steps", type=int, default=60_000, help="all stages together")
    parser.add_argument("--replay", type=int, default=10_000, help="replay arm's memory")
    parser.add_argument("--ewc", type=float, default=100.0, help="EWC arm's weight")
    parser.add_argument("--ewc-loss", type=float, default=100.0, help="ewc-loss arm's weight")
    args = parser.parse_args(argv)

    run_all(args)
    info = machine()
    arms: dict[str, Any] = {}
    for arm in args.arms:
        runs = {
            s: json.loads((run_dir(args, arm, s) / "sequential.json").read_text())
            for s in args.seeds
        }
        metrics = {
            k: spread([r["metrics"][k] for r in runs.values()])
            for k in ("forgetting", "backward_transfer", "forward_transfer", "final_mean")
        }
        arms[arm] = {"metrics": metrics, "per_seed": {str(s): r for s, r in runs.items()}}
    headline = {key(arm): round(arms[arm]["metrics"]["forgetting"]["mean"], 3) for arm in args.arms}
    headline["seeds"] = len(args.seeds)
    # below naive on the mean over seeds, and on most seeds seed for seed (a mean a hair
    # below naive with most seeds above it is noise, not a mitigation)
    wins = {
        arm: sum(
            arms[arm]["per_seed"][str(s)]["metrics"]["forgetting"]
            < arms["naive"]["per_seed"][str(s)]["metrics"]["forgetting"]
            for s in args.seeds
        )
        for arm in args.arms
        if arm != "naive" and "naive" in args.arms
    }
    reached = {
        key(arm): headline[key(arm)] < headline["forgetting_naive"] and 2 * n > len(args.seeds)
        for arm, n in wins.items()
    }
    save_json(
        NAME,
        {
            "headline": headline,
            "target": "forgetting_replay and forgetting_ewc below forgetting_naive (mean over "
            "seeds, and on most seeds against naive on the same seed)",
            "seeds_below_naive": wins,
            "reached": reached,
            "machine": info,
            "settings": vars(args),
            "arms": arms,
        },
    )
    fams = next(iter(next(iter(arms.values()))["per_seed"].values()))["families"]
    lines = [
        "| arm | forgetting | backward transfer | forward transfer | final mean success |",
        "|---|---:|---:|---:|---:|",
    ]
    for arm, a in arms.items():
        m = a["metrics"]
        lines.append(
            f"| {arm} | "
            + " | ".join(
                f"{m[k]['mean']:.3f} ± {m[k]['std']:.3f}"
                for k in ("forgetting", "backward_transfer", "forward_transfer", "final_mean")
            )
            + " |"
        )
    lines += [
        "",
        "Success matrices (mean over seeds; rows: before training, after each stage):",
        "",
    ]
    for arm, a in arms.items():
        rows = list(a["per_seed"].values())
        lines += [
            f"**{arm}**",
            "",
            "| after | " + " | ".join(fams) + " |",
            "|---|" + "---:|" * len(fams),
        ]
        for i, row in enumerate(rows[0]["rows"]):
            cells = [sum(r["rows"][i]["success"][f] for r in rows) / len(rows) for f in fams]
            lines.append(f"| {row['after']} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
        lines.append("")
    verdict = ", ".join(
        f"{key(arm)} {'reached' if reached[key(arm)] else 'NOT reached'} ({n} of "
        f"{len(args.seeds)} seeds below naive)"
        for arm, n in wins.items()
    )
    body = (
        f"Stages {' -> '.join(args.stages)} on `lang2d`, {args.steps} steps in all, seeds "
        f"{args.seeds}; replay memory {args.replay} transitions, EWC weight {args.ewc} (Fisher "
        f"of the outputs), ewc-loss weight {args.ewc_loss} (Fisher of the losses). "
        "Target: replay and EWC forget less than naive, on the mean and on most seeds: "
        f"**{verdict}**.\n\n" + "\n".join(lines)
    )
    save_markdown(NAME, "Forgetting in sequential training (lang2d)", body, info)

    fig, ax = new_figure(figsize=(6, 3.5))
    names = list(arms)
    means = [arms[a]["metrics"]["forgetting"]["mean"] for a in names]
    stds = [arms[a]["metrics"]["forgetting"]["std"] for a in names]
    ax.bar(
        names,
        means,
        yerr=stds,
        capsize=4,
        color=["tab:gray", "tab:blue", "tab:green", "tab:olive"][: len(names)],
    )
    for a_i, a in enumerate(names):
        for r in arms[a]["per_seed"].values():
            ax.plot(a_i, r["metrics"]["forgetting"], "k.", ms=4)
    ax.set(ylabel="forgetting (drop from best)", title="lang2d: " + " -> ".join(args.stages))
    save_figure(NAME, fig, info)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

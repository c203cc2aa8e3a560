"""Offline goal-conditioned RL from random play on the 2D tabletop, with and without
language hindsight relabelling.

    python benchmarks/offline.py                          # 3 seeds, every arm
    python benchmarks/offline.py --episodes 200 --updates 500 --seeds 0 --eval-episodes 10

Records ``--episodes`` uniformly random episodes of the ``lang2d`` preset's env (reach and
push; ``lcrl demos record --actor random``: no scripted or expert episode), then trains
each arm on that one file with ``lcrl train lang2d --offline FILE`` and evaluates it with
``--eval-episodes`` episodes per instruction set at the end:

* ``her``: TD3+BC with language hindsight relabelling (``--buffer.k 4``);
* ``crl``: contrastive RL with language hindsight relabelling;
* ``gcbc``: goal-conditioned behavioural cloning of the relabelled rows;
* ``norelabel``: TD3+BC on the recorded instructions only (``--buffer.k 0``).

One run per arm and seed, ``--parallel`` at a time with one torch thread each; a finished
run (its ``report.md``) is kept, so an interrupted benchmark goes on where it stopped.

Writes ``benchmarks/results/offline-lang2d.{json,md,png}``: ``headline.offline_her_seen``
(the best relabelling RL arm), ``gcbc_seen`` and ``no_relabel_seen`` (means over seeds of
the seen-instruction success), with per-seed figures, Wilson intervals and the spread.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from benchmarks.common import (
    add_arm_options,
    final_eval,
    machine,
    new_figure,
    record_once,
    run_dir,
    save_figure,
    save_json,
    save_markdown,
    train_arms,
    verdict,
)
from train.evaluation.report import spread

NAME = "offline-lang2d"
#: Each arm's ``lcrl train`` options.
ARMS: dict[str, list[str]] = {
    "her": ["--algo", "td3"],
    "crl": ["--algo", "crl", "--crl.negatives", "7"],
    "gcbc": ["--algo", "bc"],
    "norelabel": ["--algo", "td3", "--buffer.k", "0", "--buffer.random-fraction", "0"],
}
#: How figures and tables name the arms.
LABELS = {
    "her": "TD3+BC, HER",
    "crl": "CRL, HER",
    "gcbc": "GCBC (HER rows)",
    "norelabel": "TD3+BC, no relabelling",
}
#: Arms that learn with relabelling and a critic: the best is ``headline.offline_her_seen``.
HER_ARMS = ("her", "crl")
SETS = ("train", "heldout", "paraphrase")
FAMILIES = ("reach", "push")


def record(args: argparse.Namespace) -> Path:
    """The random-play file (recorded once)."""
    cmd = ["demos", "record", "--preset", "lang2d", "--actor", "random"]
    cmd += ["--episodes", str(args.episodes), "--seed", "100"]
    return record_once(Path(args.work) / f"play-{args.episodes}.h5", cmd)


def run_all(args: argparse.Namespace, data: Path) -> None:
    """Train every (arm, seed) without a finished run."""

    def argv(arm: str, seed: int, out: Path) -> list[str]:
        cmd = ["train", "lang2d", "--offline", str(data), "--out", str(out)]
        cmd += ["--seed", str(seed), "--total-steps", str(args.updates)]
        cmd += ["--eval-every", "0", "--eval-episodes", str(args.eval_episodes)]
        cmd += ["--checkpoint-every", "0", "--overwrite", "--no-progress"]
        return [*cmd, "--no-tensorboard", *ARMS[arm]]

    train_arms(args, argv)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arm_options(parser, list(ARMS), "runs/bench/offline")
    parser.add_argument("--episodes", type=int, default=5000, help="random-play episodes")
    parser.add_argument("--updates", type=int, default=10_000, help="per run")
    args = parser.parse_args(argv)

    data = record(args)
    run_all(args, data)
    info = machine()
    arms: dict[str, Any] = {}
    for arm in args.arms:
        runs = {s: final_eval(run_dir(args, arm, s), args.eval_episodes, SETS) for s in args.seeds}
        arms[arm] = {
            "options": ARMS[arm],
            **{name: spread([r[name]["success"] for r in runs.values()]) for name in SETS},
            "per_seed": {str(s): r for s, r in runs.items()},
        }
    her = [a for a in HER_ARMS if a in arms]
    best = max(her, key=lambda a: arms[a]["train"]["mean"]) if her else None
    headline: dict[str, Any] = {}
    if best is not None:
        headline["offline_her_seen"] = round(arms[best]["train"]["mean"], 3)
        headline["offline_her_algo"] = best
    if "gcbc" in arms:
        headline["gcbc_seen"] = round(arms["gcbc"]["train"]["mean"], 3)
    if "norelabel" in arms:
        headline["no_relabel_seen"] = round(arms["norelabel"]["train"]["mean"], 3)
    for arm in arms:
        headline[f"{arm}_seen"] = round(arms[arm]["train"]["mean"], 3)
        headline[f"{arm}_seen_std"] = round(arms[arm]["train"]["std"], 3)
    headline["seeds"] = len(args.seeds)
    headline["updates"] = args.updates
    headline["episodes"] = args.episodes

    # "clearly above": the HER arm's lowest seed above the baseline's highest
    reached: dict[str, bool] = {}
    if best is not None:
        for base in ("gcbc", "norelabel"):
            if base in arms:
                above = arms[best]["train"]["min"] > arms[base]["train"]["max"]
                reached[f"her_above_{base}"] = above
    save_json(
        NAME,
        {
            "headline": headline,
            "target": "offline_her_seen clearly above gcbc_seen and no_relabel_seen, 3 seeds "
            "(read here as: the HER arm's worst seed above the baseline's best seed)",
            "reached": reached,
            "machine": info,
            "settings": {**vars(args), "data": str(data)},
            "arms": arms,
        },
    )
    lines = [
        "| arm | options | seen | seen reach | seen push | held-out combinations | "
        "paraphrases | seen per seed |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for arm, a in arms.items():
        cells = [f"{a[n]['mean']:.2f} ± {a[n]['std']:.2f}" for n in SETS]
        runs = list(a["per_seed"].values())
        fams = [f"{sum(r['train'].get(f, 0.0) for r in runs) / len(runs):.2f}" for f in FAMILIES]
        per = ", ".join(
            f"{r['train']['success']:.2f} [{r['train']['ci'][0]:.2f}, {r['train']['ci'][1]:.2f}]"
            for r in runs
        )
        row = [LABELS[arm], f"`{' '.join(a['options'])}`", cells[0], *fams, *cells[1:], per]
        lines.append("| " + " | ".join(row) + " |")
    from lcrl.demos import DemoDataset

    with DemoDataset(data) as d:
        rates = d.meta.get("per_family", {})
    did = ", ".join(f"{f} {v['successes']}/{v['episodes']}" for f, v in rates.items())
    body = (
        f"How often random play did the instruction it was given: {did}; relabelling turns "
        "every episode into examples of what it did achieve, and push is rarely achieved "
        "by random motion at all, so push stays low for every arm.\n\n"
        f"{args.episodes} random-play episodes of `lang2d` (reach and push), {args.updates} "
        f"updates per run, seeds {args.seeds}, {args.eval_episodes} evaluation episodes per "
        f"set (mean ± sd over seeds; per seed with the 95% Wilson interval). Best relabelling "
        f"arm: `{best}`. Target, HER clearly above GCBC and no relabelling: "
        f"**{verdict(reached)}**.\n\n" + "\n".join(lines)
    )
    save_markdown(NAME, "Offline goal-conditioned RL from random play (lang2d)", body, info)

    fig, ax = new_figure(figsize=(7, 3.8))
    names = list(arms)
    width = 0.27
    for j, n in enumerate(SETS):
        xs = [i + (j - 1) * width for i in range(len(names))]
        ax.bar(
            xs,
            [arms[a][n]["mean"] for a in names],
            width,
            yerr=[arms[a][n]["std"] for a in names],
            capsize=3,
            label=n,
        )
        for x, a in zip(xs, names, strict=True):
            for r in arms[a]["per_seed"].values():
                ax.plot(x, r[n]["success"], "k.", ms=3)
    ax.set_xticks(range(len(names)), [LABELS[a] for a in names], fontsize=8)
    ax.set(ylim=(0, 1.02), ylabel="success (mean ± sd over seeds)")
    ax.set_title(f"lang2d offline from {args.episodes} random-play episodes")
    ax.legend(fontsize=7)
    save_figure(NAME, fig, info)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

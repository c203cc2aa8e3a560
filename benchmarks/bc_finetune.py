"""BC -> RL fine-tuning against BC alone and RL alone at the same environment budget, on
the 2D tabletop's push instructions.

    python benchmarks/bc_finetune.py                    # 100 demonstrations, 15k steps, 3 seeds
    python benchmarks/bc_finetune.py --demos 20 --steps 400 --bc-updates 200 --seeds 0 \\
        --eval-episodes 10                              # a check

Records ``--demos`` scripted push demonstrations of the ``lang2d`` preset's env (action
noise 0.3), then trains, per seed:

* ``bc``: behavioural cloning on the demonstrations alone (``lcrl train lang2d-bc``,
  ``--bc-updates`` updates): it sees only the demonstration steps;
* ``rl``: SAC with language HER from scratch, no scripted episodes, for as many
  environment steps as the demonstrations plus the fine-tuned run's online steps;
* ``finetuned``: ``--finetune.demos``: the demonstrations in the buffer, offline updates
  with a cloning actor, then ``--steps`` online steps with a decaying BC term.

Each run is evaluated with ``--eval-episodes`` episodes per instruction set at its end.
Runs go two at a time with one torch thread each; finished runs are kept.

Writes ``benchmarks/results/bc_finetune.{json,md,png}``: ``headline.finetuned_seen``,
``bc_seen`` and ``rl_seen`` (seen-instruction success, mean over seeds).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from benchmarks.common import (
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
from lcrl.demos import DemoDataset
from train.evaluation.report import spread

NAME = "bc_finetune"
ARMS = ("bc", "rl", "finetuned")
ARMS_ORDER = ("rl", "finetuned", "bc")  # the longest runs first
SETS = ("train", "heldout", "paraphrase")
COMMON = ["--env.families", "push", "--eval-every", "0", "--checkpoint-every", "0"]
COMMON += ["--overwrite", "--no-progress", "--no-tensorboard"]


def record(args: argparse.Namespace) -> Path:
    """The demonstration file (recorded once)."""
    cmd = ["demos", "record", "--preset", "lang2d", "--families", "push"]
    cmd += ["--episodes", str(args.demos), "--noise", "0.3", "--seed", "100"]
    return record_once(Path(args.work) / f"push-{args.demos}.h5", cmd)


def arm_command(arm: str, args: argparse.Namespace, seed: int, demos: Path, budget: int) -> list:
    """The ``lcrl train`` command of an arm."""
    out = ["--out", str(run_dir(args, arm, seed)), "--seed", str(seed)]
    out += ["--eval-episodes", str(args.eval_episodes), *COMMON]
    if arm == "bc":
        return ["train", "lang2d-bc", "--demos", str(demos), *out, "--total-steps",
                str(args.bc_updates)]  # fmt: skip
    online = ["--scripted-fraction", "0"]
    if arm == "rl":
        return ["train", "lang2d", *out, *online, "--total-steps", str(budget)]
    finetune = ["--finetune.demos", str(demos), "--finetune.decay-steps", str(args.decay_steps)]
    finetune += ["--finetune.pretrain-updates", str(args.pretrain_updates)]
    return ["train", "lang2d", *out, *online, "--total-steps", str(args.steps), *finetune]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--demos", type=int, default=100, help="scripted push episodes")
    parser.add_argument("--steps", type=int, default=15_000, help="fine-tuning online steps")
    parser.add_argument("--pretrain-updates", type=int, default=2000)
    parser.add_argument("--decay-steps", type=int, default=10_000)
    parser.add_argument("--bc-updates", type=int, default=5000)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--work", default="runs/bench/bc_finetune")
    args = parser.parse_args(argv)

    demos = record(args)
    with DemoDataset(demos) as data:
        demo_steps = data.num_steps
    budget = demo_steps + args.steps  # environment steps behind each RL arm
    train_arms(args, lambda arm, s, out: arm_command(arm, args, s, demos, budget), ARMS_ORDER)

    info = machine()
    arms: dict[str, Any] = {}
    for arm in ARMS:
        runs = {s: final_eval(run_dir(args, arm, s), args.eval_episodes, SETS) for s in args.seeds}
        arms[arm] = {
            "command": " ".join(arm_command(arm, args, args.seeds[0], demos, budget)),
            **{n: spread([r[n]["success"] for r in runs.values()]) for n in SETS},
            "per_seed": {str(s): r for s, r in runs.items()},
        }
    env_steps = {"bc": demo_steps, "rl": budget, "finetuned": budget}
    headline = {f"{arm}_seen": round(arms[arm]["train"]["mean"], 3) for arm in ARMS}
    headline.update(
        environment_steps=budget, demo_steps=demo_steps, online_steps=args.steps,
        seeds=len(args.seeds),
    )  # fmt: skip
    fine = arms["finetuned"]["train"]["mean"]
    reached = {
        "finetuned_above_bc": fine > arms["bc"]["train"]["mean"],
        "finetuned_above_rl": fine > arms["rl"]["train"]["mean"],
    }
    save_json(
        NAME,
        {
            "headline": headline,
            "target": "finetuned_seen above bc_seen and rl_seen at the same environment budget",
            "reached": reached,
            "machine": info,
            "settings": {**vars(args), "data": str(demos)},
            "environment_steps": env_steps,
            "arms": arms,
        },
    )
    lines = [
        "| arm | environment steps | seen (push) | held-out combinations | paraphrases | "
        "seen per seed, 95% interval |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for arm, a in arms.items():
        cells = [f"{a[n]['mean']:.2f}" + (f" ± {a[n]['std']:.2f}" if len(args.seeds) > 1 else "")
                 for n in SETS]  # fmt: skip
        per = ", ".join(
            f"{r['train']['success']:.2f} [{r['train']['ci'][0]:.2f}, {r['train']['ci'][1]:.2f}]"
            for r in a["per_seed"].values()
        )
        lines.append(f"| {arm} | {env_steps[arm]} | " + " | ".join(cells) + f" | {per} |")
    lines += ["", "Commands (from the repository root):", ""]
    lines += [f"- {arm}: `lcrl {a['command']}`" for arm, a in arms.items()]
    body = (
        f"{args.demos} scripted push demonstrations ({demo_steps} steps, action noise 0.3) of "
        f"`lang2d`; fine-tuning: {args.pretrain_updates} offline updates, then {args.steps} "
        f"online steps with the BC weight decaying over {args.decay_steps}; RL alone: "
        f"{budget} steps; seeds {args.seeds}; {args.eval_episodes} evaluation episodes per "
        f"set. Target, fine-tuned above BC alone and RL alone: **{verdict(reached)}**.\n\n"
        + "\n".join(lines)
    )
    save_markdown(NAME, "BC -> RL fine-tuning (lang2d push)", body, info)

    fig, ax = new_figure(figsize=(6, 3.6))
    names = list(arms)
    ax.bar(
        names,
        [a["train"]["mean"] for a in arms.values()],
        yerr=[a["train"]["std"] for a in arms.values()],
        capsize=4,
        color="tab:blue",
    )
    for i, a in enumerate(arms.values()):  # each seed, with its 95% Wilson interval
        for j, r in enumerate(a["per_seed"].values()):
            x = i + 0.12 * (j - (len(args.seeds) - 1) / 2)
            ax.plot([x, x], r["train"]["ci"], c="k", lw=0.8)
            ax.plot(x, r["train"]["success"], "k.", ms=4)
    ax.set(ylim=(0, 1.02), ylabel="seen success (mean ± sd; seeds, 95% CI)")
    ax.set_title(f"lang2d push, {budget} environment steps")
    save_figure(NAME, fig, info)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A preset's collection settings, chosen from time to success on seeds no headline uses.

    python -m benchmarks.preset_settings lang2d-quick --candidates "--collect.envs 8"

Trains ``lcrl train PRESET`` as shipped and with each candidate's options (``--candidates``,
one string of options each), on seeds that no headline uses (``--seeds``, 100 and 101: a
choice, not a figure to report), one run after another with the arms alternating within
each seed, each on ``--threads`` torch threads, all with the same evaluation schedule
(``--eval-every``, ``--eval-episodes``) and the same budget (``--total-steps``, default
the preset's own). Time to success is the training seconds
(evaluations excluded) of the first evaluation whose seen success reaches
``--threshold``; a run that never gets there counts its whole training time and is
marked. Finished runs are read, not trained again.

Writes ``benchmarks/results/preset-settings-PRESET.{json,md,png}``. The headline holds,
per arm, the median seconds to the threshold and the median final seen success, and the
arm that reached the threshold soonest without a lower final success (``chosen``: the
options a preset should ship).
"""

from __future__ import annotations

import argparse
import shlex
import statistics
from pathlib import Path
from typing import Any

from benchmarks.common import (
    LCRL,
    curve,
    machine,
    new_figure,
    run_logged,
    save_figure,
    save_json,
    save_markdown,
)
from benchmarks.time_to_success_vs_sb3 import success, time_to_success

SHIPPED = "as shipped"


def arm_name(options: str) -> str:
    return options.strip() or SHIPPED


def run_command(preset: str, options: str, seed: int, out: Path, args: Any) -> list[str]:
    return [
        *LCRL, "train", preset, "--out", str(out), "--overwrite", "--no-progress",
        "--seed", str(seed), "--agent.seed", str(seed),
        "--torch-threads", str(args.threads),
        "--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes),
        *(["--total-steps", str(args.total_steps)] if args.total_steps else []),
        *shlex.split(options),
    ]  # fmt: skip


def summarise(rows: list[dict[str, float]], threshold: float) -> dict[str, Any]:
    seconds, reached = time_to_success(rows, threshold)
    return {
        "seconds": round(seconds, 1),
        "reached": reached,
        "final_seen": success(rows[-1]) if rows else float("nan"),
        "steps": int(rows[-1]["step"]) if rows else 0,
    }


def choose(arms: dict[str, dict[str, Any]]) -> str:
    """The arm that reached the threshold on every seed soonest (median seconds), its
    median final success no lower than the shipped arm's by more than 0.02."""
    floor = arms[SHIPPED]["final_seen"] - 0.02
    fit = [a for a, v in arms.items() if v["all_reached"] and v["final_seen"] >= floor]
    return min(fit, key=lambda a: arms[a]["seconds"]) if fit else SHIPPED


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("preset")
    p.add_argument("--candidates", nargs="+", default=["--collect.envs 8"])
    p.add_argument("--seeds", nargs="+", type=int, default=[100, 101])
    p.add_argument("--threshold", type=float, default=0.8)
    p.add_argument("--eval-every", type=int, default=1000)
    p.add_argument("--eval-episodes", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--work", default="runs/bench/preset-settings")
    p.add_argument(
        "--name",
        default="",
        help="result file name (default preset-settings-PRESET), for a second screen of a preset",
    )
    p.add_argument(
        "--total-steps",
        type=int,
        default=0,
        help="train every arm for this many steps (0: the preset's own budget)",
    )
    args = p.parse_args(argv)
    options = ["", *args.candidates]
    runs: dict[str, dict[str, Any]] = {}
    for seed in args.seeds:
        for i, opts in enumerate(options):
            out = Path(args.work) / args.preset / f"arm{i}-s{seed}"
            if not (out / "report.md").is_file():
                cmd = run_command(args.preset, opts, seed, out, args)
                run_logged(cmd, out.with_suffix(".log"), f"{args.preset} {arm_name(opts)} s{seed}")
            rows = curve(out)
            runs[f"{arm_name(opts)} s{seed}"] = {
                "arm": arm_name(opts),
                "seed": seed,
                "curve": rows,
                **summarise(rows, args.threshold),
            }
    arms: dict[str, dict[str, Any]] = {}
    for opts in options:
        mine = [r for r in runs.values() if r["arm"] == arm_name(opts)]
        arms[arm_name(opts)] = {
            "seconds": statistics.median(r["seconds"] for r in mine),
            "final_seen": statistics.median(r["final_seen"] for r in mine),
            "all_reached": all(r["reached"] for r in mine),
            "per_seed": {r["seed"]: r["seconds"] for r in mine},
        }
    chosen = choose(arms)
    name = args.name or f"preset-settings-{args.preset}"
    info = machine()
    headline = {
        **{f"{a}_s": v["seconds"] for a, v in arms.items()},
        **{f"{a}_final_seen": v["final_seen"] for a, v in arms.items()},
        "chosen": chosen,
        "threshold": args.threshold,
        "seeds": args.seeds,
    }
    save_json(
        name,
        {
            "headline": headline,
            "machine": info,
            "arms": arms,
            "runs": {k: {x: y for x, y in v.items() if x != "curve"} for k, v in runs.items()},
            "protocol": "seeds no headline uses: this file chooses settings, it reports "
            "no headline figure of a policy",
            "tried": [f"lcrl train {args.preset} {arm_name(o)}" for o in options],
        },
    )
    lines = [
        f"`lcrl train {args.preset}`, training seconds to {args.threshold:.0%} seen success "
        f"(medians over seeds {args.seeds}, which no headline uses; "
        f"{args.threads} torch thread(s), evaluations excluded; "
        f"{f'{args.total_steps:,} steps' if args.total_steps else 'the preset budget'}).",
        "",
        "| options | seconds | per seed | final seen | every seed reached |",
        "|---|---:|---|---:|---|",
    ]
    for a, v in arms.items():
        per = ", ".join(f"{s}: {t:.0f}" for s, t in v["per_seed"].items())
        lines.append(
            f"| {a} | {v['seconds']:.0f} | {per} | {v['final_seen']:.2f} | {v['all_reached']} |"
        )
    lines += ["", f"Chosen: **{chosen}**."]
    save_markdown(name, f"Settings of {args.preset}", "\n".join(lines), info)
    fig, ax = new_figure(figsize=(6, 3.6))
    for key, r in runs.items():
        ax.plot([c["train_s"] for c in r["curve"]], [success(c) for c in r["curve"]], label=key)
    ax.axhline(args.threshold, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("training seconds")
    ax.set_ylabel("seen success")
    ax.legend(fontsize=6)
    save_figure(name, fig, info)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

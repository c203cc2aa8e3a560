"""Time to success on ``lang2d``: the wall-clock a user waits for 80% seen success, the
previous loop against the new default, same machine, seed and step budget.

    python benchmarks/time_to_success.py

Two runs of ``lcrl train lang2d`` with the same seed: ``new`` adds :data:`NEW_OPTIONS`
(8 environments stepped at once, batch 128), ``old`` adds :data:`OLD_OPTIONS` (the loop as
it was: one environment, batch 256); one update per environment step in both. They train
one after the other, each alone on the machine with the default torch threads (all
cores), and are evaluated every ``--eval-every`` steps on ``--eval-episodes`` episodes per
set. Time to success is the ``train_s`` of the first evaluation whose seen success reaches
``--threshold``: wall-clock training seconds, the evaluations themselves excluded.
Finished runs are kept, so an interrupted benchmark goes on where it stopped (``--fresh``
trains both again).

Writes ``benchmarks/results/time_to_success.{json,md,png}``. Headline: ``new_s`` (target
<= 480), ``old_s``, and ``final_seen_new`` / ``final_seen_old`` at the same step budget
(the new run's must not be below the old one's).

A fourth arm, ``preset``, is ``lcrl train lang2d`` exactly as shipped (no option added):
``headline.preset_s`` (target <= 300) and ``headline.final_seen_preset``. With
``--preset-seeds`` it trains once per seed (one after another, each alone), and the two
figures are the medians over those seeds (``headline.preset_s_per_seed`` lists them; a
seed that never reaches the threshold makes the median ``None`` when it is the middle one).

A third arm, ``bf16``, is the new settings with ``--agent.precision bf16`` (updates under
bfloat16 autocast); it reports ``headline.bf16_s`` and ``headline.final_seen_bf16``. An
arm not trained in this invocation (``--arms``) whose run folder is gone is kept from the
previous result file, marked ``kept_from`` with that file's date.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import shutil
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
from train.runtime.machine import available_cores

NAME = "time_to_success"
PRESET = "lang2d"
#: The loop the lang2d preset trained with before: one environment, batch 256.
OLD_OPTIONS = ["--collect.envs", "1", "--batch-size", "256", "--updates-per-step", "1"]
#: The new settings: 8 environments acting in one batched forward pass, batch 128 (an
#: update costs about 0.7 of one at 256, and a 50k-step run learned at least as fast per
#: step). Both arms name their settings, so the comparison holds whatever the preset says.
NEW_OPTIONS = ["--collect.envs", "8", "--batch-size", "128", "--updates-per-step", "1"]
#: The new settings with their updates under bfloat16 autocast.
BF16_OPTIONS = [*NEW_OPTIONS, "--agent.precision", "bf16"]
#: The preset exactly as shipped: no option added.
PRESET_OPTIONS: list[str] = []
OPTIONS = {"old": OLD_OPTIONS, "new": NEW_OPTIONS, "bf16": BF16_OPTIONS, "preset": PRESET_OPTIONS}
TARGET_S = 480.0
#: ``lcrl train lang2d`` as shipped, to 80% seen success.
TARGET_PRESET_S = 300.0


def run_folder(args: argparse.Namespace, arm: str, seed: int | None = None) -> str:
    """An arm's run folder: ``ARM`` at ``--seed``, ``ARM-sSEED`` at another seed."""
    return arm if seed is None or seed == args.seed else f"{arm}-s{seed}"


def run_args(args: argparse.Namespace, arm: str, seed: int | None = None) -> list[str]:
    """The ``lcrl train`` command of an arm (at ``--seed`` unless ``seed`` is given)."""
    seed = args.seed if seed is None else seed
    cmd = [*LCRL, "train", PRESET, "--out", str(Path(args.work) / run_folder(args, arm, seed))]
    cmd += ["--total-steps", str(args.steps), "--eval-every", str(args.eval_every)]
    cmd += ["--eval-episodes", str(args.eval_episodes), "--seed", str(seed)]
    cmd += ["--checkpoint-every", "0", "--overwrite", "--no-progress", "--no-tensorboard"]
    return cmd + OPTIONS[arm]


def run_threads(log: Path) -> int:
    """The torch threads a run took: the number its note names where the cores were busy
    when it started (``lcrl: note: ... N torch thread``), otherwise all available cores."""
    text = log.read_text() if log.is_file() else ""
    found = re.search(r"(\d+) torch threads? \(--torch-threads", text)
    return int(found.group(1)) if found else available_cores()


def first_success(rows: list[dict[str, float]], threshold: float) -> dict[str, float] | None:
    """The first evaluation whose seen success reaches ``threshold``."""
    return next((r for r in rows if r["train/success"] >= threshold), None)


def run_figures(work: Path, name: str, threshold: float) -> dict[str, Any]:
    """A finished run's figures: seconds and steps to ``threshold`` (None: never), final
    seen success and step, training seconds, torch threads and its evaluation curve."""
    rows = curve(work / name)
    hit = first_success(rows, threshold)
    return {
        "time_to_success_s": None if hit is None else hit["train_s"],
        "steps_to_success": None if hit is None else int(hit["step"]),
        "final_seen": rows[-1]["train/success"],
        "final_step": int(rows[-1]["step"]),
        "train_s": rows[-1]["train_s"],
        "torch_threads": run_threads(work / f"{name}.log"),
        "curve": rows,
    }


def seed_runs(work: Path, args: argparse.Namespace, seeds: list[int]) -> dict[int, dict]:
    """Each seed's preset run: :func:`run_figures` without the curve."""
    out = {}
    for seed in seeds:
        figures = run_figures(work, run_folder(args, "preset", seed), args.threshold)
        out[seed] = {k: v for k, v in figures.items() if k != "curve"}
    return out


def median_or_none(values: list[float | None]) -> float | None:
    """The median, a run that never got there counting as slower than every other; None
    when such a run is at or past the middle."""
    ordered = sorted(values, key=lambda v: math.inf if v is None else v)
    mid = ordered[(len(ordered) - 1) // 2 : len(ordered) // 2 + 1]
    if any(v is None for v in mid):
        return None
    return statistics.median(mid)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=60_000, help="step budget of both runs")
    parser.add_argument("--eval-every", type=int, default=2_500)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", default="runs/bench/time-to-success")
    parser.add_argument("--arms", nargs="+", default=["new", "old", "bf16"], choices=list(OPTIONS))
    parser.add_argument("--fresh", action="store_true", help="train finished runs again")
    parser.add_argument(
        "--preset-seeds",
        nargs="+",
        type=int,
        default=[],
        help="train the preset arm at each of these seeds; its figures are their medians",
    )
    args = parser.parse_args(argv)

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    preset_seeds = args.preset_seeds or [args.seed]
    for arm in args.arms:
        for seed in preset_seeds if arm == "preset" else [args.seed]:
            name = run_folder(args, arm, seed)
            run, cmd = work / name, run_args(args, arm, seed)
            done = (run / "report.md").is_file() and (run / "command.txt").is_file()
            if done and not args.fresh and (run / "command.txt").read_text() == shlex.join(cmd):
                print(f"== {name}: kept {run}", flush=True)
                continue
            shutil.rmtree(run, ignore_errors=True)
            run_logged(cmd, work / f"{name}.log", name)
            (run / "command.txt").write_text(shlex.join(cmd))

    info = machine()
    previous = Path(__file__).resolve().parent / "results" / f"{NAME}.json"
    before = json.loads(previous.read_text()) if previous.is_file() else {}
    arms: dict[str, dict] = {}
    replaced: list[str] = []
    for arm in OPTIONS:
        if arm not in args.arms and not (work / arm / "eval.csv").is_file():
            if arm in before.get("arms", {}):
                kept = before["arms"][arm]
                kept.setdefault("kept_from", before["machine"]["date"])
                arms[arm] = kept
                print(f"{arm}: kept from {kept['kept_from']}", flush=True)
            elif arm not in ("bf16", "preset"):
                raise SystemExit(f"no {arm} run in {work} and none in {previous}: train it")
            continue
        config = json.loads((work / arm / "config.json").read_text())
        arms[arm] = {
            "options": OPTIONS[arm],
            "collect_envs": config["collect"]["envs"],
            "updates_per_step": config["updates_per_step"],
            "batch_size": config["batch_size"],
            **run_figures(work, arm, args.threshold),
        }
        earlier = before.get("arms", {}).get(arm)
        if earlier and earlier.get("time_to_success_s") != arms[arm]["time_to_success_s"]:
            replaced.append(
                f"arm {arm} before this run ({before['machine']['date']}): "
                f"{earlier['time_to_success_s']} s to {args.threshold}, final seen "
                f"{earlier['final_seen']}, {earlier.get('torch_threads', '?')} torch thread(s)"
            )
        print(f"{arm}: {arms[arm]['time_to_success_s']} s to {args.threshold}", flush=True)
    new, old = arms["new"], arms["old"]
    headline = {
        "new_s": new["time_to_success_s"],
        "old_s": old["time_to_success_s"],
        "final_seen_new": new["final_seen"],
        "final_seen_old": old["final_seen"],
        "steps": args.steps,
    }
    if "bf16" in arms:
        headline["bf16_s"] = arms["bf16"]["time_to_success_s"]
        headline["final_seen_bf16"] = arms["bf16"]["final_seen"]
    reached = {
        "new_s": new["time_to_success_s"] is not None and new["time_to_success_s"] <= TARGET_S,
        "final_seen_new": new["final_seen"] >= old["final_seen"],
    }
    if "preset" in arms:
        preset_s = arms["preset"]["time_to_success_s"]
        headline["preset_s"] = preset_s
        headline["final_seen_preset"] = arms["preset"]["final_seen"]
        if len(preset_seeds) > 1 and "preset" in args.arms:
            per_seed = seed_runs(work, args, preset_seeds)
            headline["preset_s"] = preset_s = median_or_none(
                [r["time_to_success_s"] for r in per_seed.values()]
            )
            headline["final_seen_preset"] = statistics.median(
                r["final_seen"] for r in per_seed.values()
            )
            headline["preset_s_per_seed"] = {s: r["time_to_success_s"] for s, r in per_seed.items()}
            arms["preset"]["seeds"] = per_seed
        reached["preset_s"] = preset_s is not None and preset_s <= TARGET_PRESET_S
    save_json(
        NAME,
        {
            "headline": headline,
            "target": {
                "new_s": TARGET_S,
                "final_seen_new": "final_seen_old or above",
                "preset_s": TARGET_PRESET_S,
            },
            "reached": reached,
            "machine": info,
            "settings": {
                **vars(args),
                "old_options": OLD_OPTIONS,
                "new_options": NEW_OPTIONS,
                "bf16_options": BF16_OPTIONS,
                "preset": PRESET,
            },
            "arms": arms,
            "earlier_runs": [*before.get("earlier_runs", []), *replaced],
        },
        tried=replaced,
        by_machine_keys=("preset_s", "final_seen_preset", "preset_s_per_seed"),
    )

    def fmt(s: float | None) -> str:
        return "never" if s is None else f"{s:.0f} s ({s / 60:.1f} min)"

    lines = [
        f"| run | envs | updates/step | batch | torch threads "
        f"| time to {args.threshold:.0%} seen | steps "
        f"| final seen ({args.steps} steps) | training time |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for arm, a in arms.items():
        lines.append(
            f"| {arm}{' (kept)' if 'kept_from' in a else ''} | {a['collect_envs']} | "
            f"{a['updates_per_step']} | {a['batch_size']} | {a.get('torch_threads', '?')} | "
            f"{fmt(a['time_to_success_s'])} | {a['steps_to_success'] or '-'} | "
            f"{a['final_seen']:.2f} | {a['train_s']:.0f} s |"
        )
    verdicts = ", ".join(f"{k} {'reached' if v else 'NOT reached'}" for k, v in reached.items())
    body = (
        f"Targets: new_s <= {TARGET_S:.0f} s; preset_s (`lcrl train lang2d` as shipped) <= "
        f"{TARGET_PRESET_S:.0f} s; final seen of the new run not below the old "
        f"run's. **{verdicts}.**\n\nOld options: `{shlex.join(OLD_OPTIONS)}`; new options: "
        f"`{shlex.join(NEW_OPTIONS)}`; bf16: the new options and "
        "`--agent.precision bf16`.\n\n" + "\n".join(lines)
    )
    seeds = arms.get("preset", {}).get("seeds")
    if seeds:
        body += (
            f"\n\nThe preset arm at seeds {', '.join(map(str, seeds))}, one after another, each "
            "alone on the machine (the row above is seed "
            f"{args.seed}): "
            + "; ".join(
                f"seed {s}: {fmt(r['time_to_success_s'])} to {args.threshold:.0%}, final seen "
                f"{r['final_seen']:.2f}, {r['torch_threads']} torch thread(s)"
                for s, r in seeds.items()
            )
            + f". `headline.preset_s` is their median: {fmt(headline['preset_s'])}."
        )
    kept = {arm: a["kept_from"] for arm, a in arms.items() if "kept_from" in a}
    if kept:
        body += "\n\n" + " ".join(
            f"The {arm} run is kept from the previous result file ({date}): not trained again "
            "in this invocation."
            for arm, date in kept.items()
        )
    earlier = [*before.get("earlier_runs", []), *replaced]
    if earlier:
        body += (
            "\n\nEarlier runs of an arm, replaced by a later one (a run that started while the "
            "machine looked busy takes fewer torch threads):\n\n"
            + "\n".join(f"- {line}" for line in earlier)
        )
    save_markdown(NAME, "Time to 80% seen success on lang2d", body, info)

    fig, ax = new_figure(figsize=(6.5, 4))
    colours = {"old": "tab:gray", "new": "tab:blue", "bf16": "tab:cyan", "preset": "tab:red"}
    for arm, colour in colours.items():
        if arm not in arms:
            continue
        rows = arms[arm]["curve"]
        ax.plot(
            [r["train_s"] / 60 for r in rows],
            [r["train/success"] for r in rows],
            "o-",
            c=colour,
            label=f"{arm} ({fmt(arms[arm]['time_to_success_s'])})",
        )
    ax.axhline(args.threshold, c="k", lw=0.8, ls=":")
    ax.axvline(TARGET_S / 60, c="tab:gray", lw=0.8, ls="--", label="target of new: 8 min")
    if "preset" in arms:
        ax.axvline(
            TARGET_PRESET_S / 60, c="tab:red", lw=0.8, ls=":", label="target of preset: 5 min"
        )
    ax.set(xlabel="training wall-clock (min)", ylabel="seen success", ylim=(0, 1.02))
    ax.set_title("lang2d: time to success")
    ax.legend(loc="lower right", fontsize=8)
    save_figure(NAME, fig, info)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Do the shipped presets stay stable on seeds no result has used?

    python -m benchmarks.preset_stability

Trains ``lang2d``, ``lang2d-grounded``, ``robosuite-reach`` and ``robosuite-image-reach``
exactly as shipped (``lcrl train PRESET --seed S --agent.seed S``), each to its full
budget on the seeds :data:`SEEDS`, two runs at a time on one torch thread each. A run
*diverged* when its critic's mean Q left the return's bound (above the bound plus
:data:`Q_SLACK`, or below the lower bound minus it) at any logged step, or when its seen
success fell by more than :data:`DROP` below its best earlier evaluation.

Runs are resumable: a finished run is read, not retrained; a stopped one goes on with
``--resume``. The result file keeps every finished run (its verdict, curves and the commit
that trained it), so the runs of one machine add to those of another and a run recorded
there is not trained again (``--rerun`` trains it anew). ``--analyse`` only reads the runs
there are.

Writes ``benchmarks/results/preset-stability.{json,md,png}``; the headline holds ``runs``,
``diverged``, ``min_seen`` (per preset, the lowest final seen success of its seeds),
``planned`` (presets times seeds) and ``complete``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path
from typing import Any

from benchmarks.common import (
    RESULTS_DIR,
    command,
    git_commit,
    machine,
    run_jobs,
    save_figure,
    save_json,
    save_markdown,
)

NAME = "preset-stability"
PRESETS = ("lang2d", "lang2d-grounded", "robosuite-reach", "robosuite-image-reach")
#: Seeds of the environment and the learner, chosen before any run: no result used them.
SEEDS = (21, 22, 23)
#: How far mean Q may pass the bound before the run counts as diverged (targets are
#: clipped to the bound; the critic's own estimates may overshoot them a little).
Q_SLACK = 0.05
#: A fall of seen success below the run's best earlier evaluation that counts as divergence.
DROP = 0.2
WORK = Path("runs/stability")
#: Where the commit of the code that trains each run is written when the run starts.
COMMITS = "commits"
#: Curves kept per run in the result file (every n-th logged row, so that the figure can be
#: drawn again from the file alone).
KEPT_POINTS = 200


def recorded() -> dict[tuple[str, int], dict[str, Any]]:
    """The finished runs the result file holds, by (preset, seed)."""
    path = RESULTS_DIR / f"{NAME}.json"
    if not path.is_file():
        return {}
    runs = json.loads(path.read_text()).get("runs", [])
    return {(r["preset"], int(r["seed"])): r for r in runs if "curves" in r}


def run_folder(preset: str, seed: int) -> Path:
    return WORK / f"{preset}-s{seed}"


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def finished(out: Path, total: int) -> bool:
    """Whether a run reached its budget (its final evaluation is in eval.csv)."""
    rows = _rows(out / "eval.csv")
    return bool(rows) and int(float(rows[-1]["step"])) >= total


def commit_file(preset: str, seed: int) -> Path:
    """The file naming the commit of the code that trains a run (beside the run folders:
    ``--overwrite`` clears a run's own folder)."""
    return WORK / COMMITS / f"{preset}-s{seed}.txt"


def trained_by(preset: str, seed: int) -> str:
    """The commit of the code that trained a run (recorded when it started)."""
    path = commit_file(preset, seed)
    return path.read_text().strip() if path.is_file() else "unknown"


def job(preset: str, seed: int, total: int) -> tuple[str, list[str], Path] | None:
    """The command that trains (or resumes) one run; None when it is finished."""
    out = run_folder(preset, seed)
    if finished(out, total):
        return None
    record = commit_file(preset, seed)
    record.parent.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "train.commands.entry", "train", preset, "--out", str(out)]
    if (out / "latest.json").is_file():
        argv += ["--resume", "--total-steps", str(total)]
        before = trained_by(preset, seed)
        if before != git_commit():  # trained on by other code than the run began with
            record.write_text(f"{before}, resumed at {git_commit()}\n")
    else:
        argv += ["--seed", str(seed), "--agent.seed", str(seed), "--overwrite"]
        record.write_text(git_commit() + "\n")  # the code that trains it from the start
    argv += ["--no-progress"]
    return f"{preset} seed {seed}", argv, WORK / "logs" / f"{preset}-s{seed}.log"


def pending(
    presets: list[str],
    seeds: list[int],
    totals: dict[str, int],
    kept: dict[tuple[str, int], Any],
) -> list[tuple[str, list[str], Path]]:
    """The runs still to train, seed by seed, the longest first (so that two short ones
    finish beside a long one): none the result file holds, none finished here."""
    order = sorted(presets, key=lambda n: -totals[n])
    jobs = [job(n, s, totals[n]) for s in seeds for n in order if (n, s) not in kept]
    return [j for j in jobs if j is not None]


def bounds(preset: str) -> tuple[float, float]:
    """The return's bounds the preset's critic must stay within."""
    from lcrl.algos.base import value_bounds
    from train.configs.presets import PRESETS as ALL

    cfg = ALL[preset][1]
    # language goals: 0/1 success rewards that end the episode (LabelGoals)
    shift = cfg.agent.reward_shift
    return value_bounds((0.0 + shift, 1.0 + shift), cfg.sac.gamma, True)


def analyse(preset: str, seed: int) -> dict[str, Any]:
    """One run's curves and verdict."""
    out = run_folder(preset, seed)
    progress = [r for r in _rows(out / "progress.csv") if r.get("q")]
    evals = _rows(out / "eval.csv")
    lo, hi = bounds(preset)
    steps = [int(float(r["step"])) for r in progress]
    q = [float(r["q"]) for r in progress]
    q_max = [float(r["q_max"]) if r.get("q_max") else float("nan") for r in progress]
    seen = [(int(float(r["step"])), float(r["train/success"])) for r in evals]
    heldout = [float(r["heldout/success"]) for r in evals if r.get("heldout/success")]
    left = [s for s, v in zip(steps, q, strict=True) if v > hi + Q_SLACK or v < lo - Q_SLACK]
    best, fall = 0.0, 0.0
    for _, value in seen:
        fall = max(fall, best - value)
        best = max(best, value)
    every = max(1, len(steps) // KEPT_POINTS)
    return {
        "preset": preset,
        "seed": seed,
        "commit": trained_by(preset, seed),
        "curves": {
            "step": steps[::every],
            "q": [round(v, 4) for v in q[::every]],
            "q_max": [round(v, 4) for v in q_max[::every]],
        },
        "seen": seen,
        "final_seen": seen[-1][1] if seen else float("nan"),
        "final_heldout": heldout[-1] if heldout else float("nan"),
        "best_seen": best,
        "largest_fall": round(fall, 3),
        "q_peak": max(q) if q else float("nan"),
        "q_left_bound_at": left[:5],
        "bounds": [lo, hi],
        "diverged": bool(left) or fall > DROP,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    p.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    p.add_argument("--parallel", type=int, default=2, help="runs at a time (1 thread each)")
    p.add_argument("--analyse", action="store_true", help="only read the runs there are")
    p.add_argument("--rerun", action="store_true", help="train runs the result file holds")
    args = p.parse_args()
    from train.configs.presets import PRESETS as ALL

    info = machine()
    totals = {name: ALL[name][1].total_steps for name in args.presets}
    kept = {} if args.rerun else recorded()
    if not args.analyse:
        os.environ.setdefault("MUJOCO_GL", "egl")  # robosuite renders without a display
        run_jobs(pending(args.presets, args.seeds, totals, kept), parallel=args.parallel)
    runs = []
    for n in args.presets:
        for s in args.seeds:
            if finished(run_folder(n, s), totals[n]):
                runs.append(analyse(n, s))
            elif (n, s) in kept:
                runs.append(kept[(n, s)])
    write(runs, args, info)


def write(runs: list[dict[str, Any]], args: argparse.Namespace, info: dict[str, Any]) -> None:
    presets = list(dict.fromkeys(r["preset"] for r in runs))
    min_seen = {n: min(r["final_seen"] for r in runs if r["preset"] == n) for n in presets}
    diverged = [f"{r['preset']} seed {r['seed']}" for r in runs if r["diverged"]]
    planned = len(args.presets) * len(args.seeds)
    payload = {
        "headline": {
            "runs": len(runs),
            "diverged": len(diverged),
            "min_seen": min_seen,
            "planned": planned,
            "complete": len(runs) == planned,
        },
        # --analyse only reads what the command trains: the command is the one that does both
        "command": command().replace(" --analyse", ""),
        "machine": info,
        "seeds": list(args.seeds),
        "criteria": {
            "q_slack": Q_SLACK,
            "drop": DROP,
            "what": "diverged: mean Q of a progress.csv row outside the return's bounds by "
            "more than q_slack, or seen success below the run's best earlier evaluation by "
            "more than drop",
        },
        "diverged_runs": diverged,
        "tried": [
            "each preset exactly as shipped (lcrl train PRESET --seed S --agent.seed S), "
            f"seeds {list(args.seeds)} picked before any run; nothing was chosen among runs"
        ],
        "runs": runs,
    }
    save_json(NAME, payload)
    lines = [
        f"Seeds {', '.join(map(str, args.seeds))} (environment and learner), chosen before "
        "any run. A run diverged when its mean Q left the return's bounds by more than "
        f"{Q_SLACK}, or its seen success fell more than {DROP} below its best.",
        "",
        f"**{len(runs)} of {planned} planned runs finished, {len(diverged)} diverged**"
        + (f": {', '.join(diverged)}" if diverged else "."),
        "",
        "| preset | seed | final seen | final held-out | best seen | largest fall | "
        "peak mean Q | bounds | diverged | commit |",
        "|---|---:|---:|---:|---:|---:|---:|---|---|---|",
    ]
    for r in runs:
        lines.append(
            f"| {r['preset']} | {r['seed']} | {r['final_seen']:.2f} | {r['final_heldout']:.2f} "
            f"| {r['best_seen']:.2f} | {r['largest_fall']:.2f} | {r['q_peak']:.3f} | "
            f"[{r['bounds'][0]:g}, {r['bounds'][1]:g}] | {'yes' if r['diverged'] else 'no'} | "
            f"{r['commit']} |"
        )
    done = {(r["preset"], r["seed"]) for r in runs}
    missing = [f"{n} seed {s}" for n in args.presets for s in args.seeds if (n, s) not in done]
    if missing:
        lines += ["", f"Not yet trained to the full budget: {', '.join(missing)}."]
    lines += ["", "Lowest final seen success per preset: "]
    lines += [f"- {n}: {v:.2f}" for n, v in min_seen.items()]
    cmd = command().replace(" --analyse", "")
    save_markdown(NAME, "Shipped presets on new seeds", "\n".join(lines), info, cmd)
    if presets:
        figure(runs, presets, info)
    print(json.dumps(payload["headline"], indent=1))


def figure(runs: list[dict[str, Any]], presets: list[str], info: dict[str, Any]) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(presets), figsize=(4 * len(presets), 6.4), squeeze=False)
    for col, name in enumerate(presets):
        top, bottom = axes[0][col], axes[1][col]
        for r in (r for r in runs if r["preset"] == name):
            steps, seen = zip(*r["seen"], strict=True) if r["seen"] else ((), ())
            top.plot(steps, seen, marker="o", ms=3, label=f"seed {r['seed']}")
            curves = r["curves"]
            bottom.plot(curves["step"], curves["q"], lw=1, label=f"seed {r['seed']}")
            bottom.axhline(r["bounds"][1], c="k", ls="--", lw=0.8)
        top.set(title=name, ylim=(0, 1.02), ylabel="seen success", xlabel="step")
        bottom.set(ylabel="mean Q (dashed: bound)", xlabel="step")
        top.legend(fontsize=7)
    save_figure(NAME, fig, info, command().replace(" --analyse", ""), rect=(0, 0.06, 1, 1))


if __name__ == "__main__":
    main()

"""Language-conditioned behavioural cloning on the robosuite tabletop from scripted demos,
with and without hindsight instruction augmentation of the dataset.

1. ``lcrl demos record``: scripted-controller episodes on the Panda tabletop (privileged
   state observations, the ``robosuite`` preset's env) over five families, with action
   noise; failed episodes are kept without a segment for the instruction they missed.
2. ``lcrl demos relabel``: the rule captioner adds every training instruction each
   episode achieved, ending at the first step where it holds (DIAL-style augmentation).
3. ``lcrl train robosuite-bc`` twice on the same file, the same seed and the same number
   of updates: ``--bc.no-hindsight`` (given segments only) and ``--bc.hindsight`` (given +
   hindsight segments).
4. ``lcrl eval`` of both final checkpoints: success per family on seen instructions,
   held-out word combinations and paraphrases, with 95% Wilson intervals.

Results: ``benchmarks/results/bc-robosuite.{md,json,png}`` and each evaluation's
``eval.json`` / figures under ``benchmarks/results/bc-robosuite-<variant>/``.

    python benchmarks/bc.py                          # 400 demos, 20k updates, 100 episodes
    python benchmarks/bc.py --episodes 100 --steps 2000 --eval-episodes 20   # quick look
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from benchmarks.common import (
    RESULTS_DIR,
    add_report_only,
    die_with_parent,
    eval_headline,
    machine,
    save_figure,
    save_json,
    save_markdown,
    side_by_side_env,
)

ROOT = Path(__file__).resolve().parent.parent

FAMILIES = ("reach", "push", "lift", "put", "stack")
VARIANTS = {
    "given": ("given segments only", "--bc.no-hindsight"),
    "hindsight": ("given + hindsight segments", "--bc.hindsight"),
}
SETS = ("train", "heldout", "paraphrase")
LABELS = {"train": "seen", "heldout": "held-out combinations", "paraphrase": "paraphrases"}


def lcrl(*args: str, log: Path | None = None) -> None:
    """Run ``lcrl ARGS`` in a subprocess with one torch thread (two run side by side)."""
    env = side_by_side_env(2)
    cmd = [sys.executable, "-m", "train.commands.cli", *args]
    print("== lcrl " + " ".join(args), flush=True)
    with open(log or os.devnull, "w") as f:
        done = subprocess.run(
            cmd, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT, preexec_fn=die_with_parent
        )
    if done.returncode != 0:
        tail = log.read_text()[-2000:] if log else ""
        raise SystemExit(f"lcrl {' '.join(args)} failed ({done.returncode}):\n{tail}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=400, help="demos to record")
    parser.add_argument("--families", nargs="*", default=list(FAMILIES))
    parser.add_argument("--noise", type=float, default=0.3, help="scripted action noise")
    parser.add_argument("--max-episode-steps", type=int, default=100)
    parser.add_argument("--steps", type=int, default=20_000, help="BC gradient updates")
    parser.add_argument("--eval-episodes", type=int, default=100, help="episodes per set")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", default="data/bench", help="folder of the demo files")
    parser.add_argument("--runs", default="runs/bench", help="folder of the BC runs")
    parser.add_argument(
        "--reuse", action="store_true", help="keep demo files and finished runs already there"
    )
    add_report_only(parser, "the eval.json files already written")
    args = parser.parse_args(argv)
    info = machine()
    data = ROOT / args.data
    data.mkdir(parents=True, exist_ok=True)
    raw, aug = data / "demos-robosuite.h5", data / "demos-robosuite-hs.h5"
    env_flags = ["--env.families", *args.families]
    env_flags += ["--env.max-episode-steps", str(args.max_episode_steps)]
    timings: dict[str, float] = {}
    if not args.report_only:
        t0 = time.perf_counter()
        if not (args.reuse and raw.exists()):
            lcrl(
                "demos", "record", "--preset", "robosuite", "--families", *args.families,
                "--episodes", str(args.episodes), "--noise", str(args.noise),
                "--max-episode-steps", str(args.max_episode_steps), "--seed", str(args.seed),
                "--out", str(raw), "--overwrite", "--no-progress",
                log=data / "record.log",
            )  # fmt: skip
        timings["record_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        lcrl(
            "demos", "relabel", str(raw), "--out", str(aug), "--json", str(data / "relabel.json"),
            "--overwrite", "--no-progress", log=data / "relabel.log",
        )  # fmt: skip
        timings["relabel_s"] = time.perf_counter() - t0

        def run(variant: str) -> float:
            t = time.perf_counter()
            out = ROOT / args.runs / f"bc-robosuite-{variant}"
            if not (args.reuse and (out / "latest.json").exists()):
                out.mkdir(parents=True, exist_ok=True)
                lcrl(
                    "train", "robosuite-bc", "--demos", str(aug), VARIANTS[variant][1],
                    *env_flags, "--total-steps", str(args.steps), "--eval-every", "0",
                    "--eval-episodes", "10", "--checkpoint-every", "0", "--seed", str(args.seed),
                    "--agent.seed", str(args.seed), "--out", str(out), "--overwrite",
                    "--no-progress", "--no-tensorboard",
                    log=out.parent / f"bc-robosuite-{variant}.log",
                )  # fmt: skip
            lcrl(
                "eval", str(out), "--episodes", str(args.eval_episodes), "--num-envs", "1",
                "--out", str(RESULTS_DIR / f"bc-robosuite-{variant}"), "--no-progress",
                log=out.parent / f"bc-robosuite-{variant}-eval.log",
            )  # fmt: skip
            return time.perf_counter() - t

        with ThreadPoolExecutor(2) as pool:
            for variant, seconds in zip(VARIANTS, pool.map(run, VARIANTS), strict=True):
                timings[f"{variant}_s"] = seconds
    docs = {}
    for variant in VARIANTS:
        path = RESULTS_DIR / f"bc-robosuite-{variant}" / "eval.json"
        if not path.exists():
            raise SystemExit(f"no {path}: run the benchmark without --report-only first")
        docs[variant] = json.loads(path.read_text())
    counts = (
        json.loads((data / "relabel.json").read_text()) if (data / "relabel.json").exists() else {}
    )
    settings = vars(args)
    previous = RESULTS_DIR / "bc-robosuite.json"
    if args.report_only and previous.exists():  # keep the timings of the run that measured
        saved = json.loads(previous.read_text())
        timings = saved.get("timings", {})
    payload = {"machine": info, "settings": settings, "timings": timings}
    if aug.exists():
        counts["sources"] = hindsight_sources(aug)
    payload["headline"] = eval_headline(docs)
    save_json(
        "bc-robosuite",
        {**payload, "relabel": counts, "runs": docs},
        tried=[f"BC from {v}: {VARIANTS[v][0]}" for v in VARIANTS],
    )
    save_markdown(
        "bc-robosuite",
        "Language-conditioned BC from scripted robosuite demos, with and without hindsight "
        "instruction augmentation",
        _table(docs, counts, args, timings),
        info,
    )
    _figure(docs, args, info)
    print((RESULTS_DIR / "bc-robosuite.md").read_text())
    return 0


def hindsight_sources(path: Path) -> dict[str, Any]:
    """Where the hindsight segments of each family come from: the family of the episode's
    given instruction (``failed`` for episodes without a given segment), with the mean
    segment length of given and hindsight segments per family."""
    import numpy as np

    from lcrl.demos import HINDSIGHT, DemoDataset

    with DemoDataset(path) as data:
        segs = data.segments(hindsight=True)
        family = [text.split()[0] for text in data.instructions]
    given = {int(e): family[int(i)] for e, _, _, i, origin in segs if origin != HINDSIGHT}
    table: dict[str, dict[str, int]] = {}
    lengths: dict[str, dict[str, list[int]]] = {}
    for e, start, end, i, origin in segs:
        fam = family[int(i)]
        kind = "hindsight" if origin == HINDSIGHT else "given"
        lengths.setdefault(fam, {}).setdefault(kind, []).append(int(end - start))
        if origin == HINDSIGHT:
            src = given.get(int(e), "failed")
            table.setdefault(fam, {})[src] = table.get(fam, {}).get(src, 0) + 1
    mean_len = {
        fam: {kind: float(np.mean(v)) for kind, v in kinds.items()}
        for fam, kinds in lengths.items()
    }
    return {"from": table, "mean_length": mean_len}


def _cell(res: dict[str, Any] | None) -> str:
    if not res or not res.get("episodes"):
        return "-"
    lo, hi = res["ci"]
    return f"{res['success']:.2f} [{lo:.2f}, {hi:.2f}] (n={res['episodes']})"


def _table(
    docs: dict[str, Any], counts: dict[str, Any], args: argparse.Namespace, timings: dict
) -> str:
    lines = [
        f"{args.episodes} scripted demos (noise {args.noise}, at most {args.max_episode_steps} "
        f"steps, families {', '.join(args.families)}), privileged-state observations; "
        f"{args.steps} BC updates per run (MSE on the tanh mean, the `robosuite-bc` preset), "
        f"seed {args.seed}; {args.eval_episodes} evaluation episodes per set. Success with 95% "
        "Wilson intervals; n is the number of episodes (instructions) of that family.",
        "",
    ]
    per = counts.get("per_family", {})
    if counts:
        lines += [
            "Dataset: "
            + f"{counts.get('given_segments', '?')} given segments, "
            + f"{counts.get('hindsight_segments', '?')} hindsight segments added; "
            + ", ".join(
                f"{fam} {v.get('given', 0)} + {v.get('hindsight', 0)}"
                for fam, v in sorted(per.items())
                if isinstance(v, dict)
            ),
            "",
        ]
    sources = counts.get("sources")
    if sources:
        srcs = sorted({src for row in sources["from"].values() for src in row})
        lines += [
            "Where the hindsight segments come from (rows: the instruction's family; columns: "
            "the family of the demonstration it was found in) and mean segment lengths (steps):",
            "",
            "| family | " + " | ".join(srcs) + " | given length | hindsight length |",
            "|---" * (len(srcs) + 3) + "|",
        ]
        for fam in sorted(sources["mean_length"]):
            row = sources["from"].get(fam, {})
            ln = sources["mean_length"][fam]
            cells = [str(row.get(src, 0)) for src in srcs]
            cells += [
                f"{ln.get('given', float('nan')):.0f}",
                f"{ln.get('hindsight', float('nan')):.0f}",
            ]
            lines.append(f"| {fam} | " + " | ".join(cells) + " |")
        lines.append("")
    for name in SETS:
        lines += [f"## {LABELS[name]}", ""]
        lines += ["| family | " + " | ".join(VARIANTS[v][0] for v in VARIANTS) + " |"]
        lines += ["|---" * (len(VARIANTS) + 1) + "|"]
        fams = [*args.families, "all"]
        for fam in fams:
            cells = []
            for v in VARIANTS:
                res = docs[v]["sets"].get(name)
                cells.append(
                    _cell(res if fam == "all" else (res or {}).get("families", {}).get(fam))
                )
            lines.append(f"| {fam} | " + " | ".join(cells) + " |")
        lines.append("")
    if timings:
        lines.append(
            "Times (s, two runs side by side): "
            + ", ".join(f"{k[:-2]} {v:.0f}" for k, v in timings.items())
        )
    return "\n".join(lines)


def _figure(docs: dict[str, Any], args: argparse.Namespace, info: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, len(SETS), figsize=(13, 4.2), sharey=True)
    fams = [*args.families, "all"]
    x = np.arange(len(fams))
    width = 0.38
    for ax, name in zip(axes, SETS, strict=True):
        for k, v in enumerate(VARIANTS):
            res = docs[v]["sets"].get(name) or {}
            vals, lo, hi = [], [], []
            for fam in fams:
                r = res if fam == "all" else res.get("families", {}).get(fam)
                if r and r.get("episodes"):
                    vals.append(r["success"])
                    lo.append(r["success"] - r["ci"][0])
                    hi.append(r["ci"][1] - r["success"])
                else:
                    vals.append(np.nan)
                    lo.append(0.0)
                    hi.append(0.0)
            ax.bar(x + (k - 0.5) * width, vals, width, yerr=[lo, hi], capsize=3,
                   label=VARIANTS[v][0])  # fmt: skip
        ax.set_xticks(x, fams)
        ax.set_title(LABELS[name])
        ax.set_ylim(0, 1.05)
    axes[0].set_ylabel("success (95% Wilson interval)")
    axes[0].legend(loc="upper right", fontsize=8)
    fig.suptitle("Language-conditioned BC on the robosuite tabletop: hindsight augmentation")
    save_figure("bc-robosuite", fig, info, rect=(0, 0.08, 1, 0.95))


if __name__ == "__main__":
    raise SystemExit(main())

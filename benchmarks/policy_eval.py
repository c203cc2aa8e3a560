"""Seen instructions vs held-out word combinations vs unseen phrasings, in the report format.

Runs ``lcrl eval`` (with chains of 3 instructions) on the final checkpoints of the
100k-step language HER runs of the benchmarks: the 2D tabletop (``learning_curves.py
lang2d``) and the robosuite Panda tabletop from privileged state (``learning_curves.py
robosuite-reach-long``). Each evaluation's ``eval.json``, ``eval.md`` and figures go to
``benchmarks/results/policy-eval-<name>/``; the side-by-side table and bar chart to
``benchmarks/results/policy-eval.{md,json,png}``.

    python benchmarks/policy_eval.py                 # both runs, 100 chains per set
    python benchmarks/policy_eval.py --runs lang2d --episodes 50
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.common import (
    RESULTS_DIR,
    add_report_only,
    eval_headline,
    machine,
    save_figure,
    save_json,
    save_markdown,
)

#: name -> (run folder, what it is)
RUNS = {
    "lang2d": ("runs/bench/lang2d-her", "2D tabletop, reach and push, `lang2d` preset, 100k steps"),
    "robosuite": (
        "runs/bench/robosuite-reach-long-her",
        "robosuite Panda tabletop, reach, privileged state, 100k steps",
    ),
}
SETS = ("train", "heldout", "paraphrase")
LABELS = {"train": "seen", "heldout": "held-out combinations", "paraphrase": "paraphrases"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", nargs="*", default=list(RUNS), choices=list(RUNS))
    parser.add_argument("--episodes", type=int, default=100, help="chains per set")
    parser.add_argument("--chain", type=int, default=3)
    parser.add_argument("--num-envs", type=int, default=0, help="0: one per CPU core")
    add_report_only(parser, "the eval.json files already written")
    args = parser.parse_args(argv)
    from train.commands.cli import main as lcrl

    info = machine()
    missing = [RUNS[n][0] for n in args.runs if not (Path(RUNS[n][0]) / "latest.json").exists()]
    if missing and not args.report_only:
        raise SystemExit(
            f"no finished run in {', '.join(missing)}: train it first with "
            "python benchmarks/learning_curves.py lang2d --parallel / robosuite-reach-long"
        )
    docs: dict[str, Any] = {}
    for name in args.runs:
        folder, _ = RUNS[name]
        out = RESULTS_DIR / f"policy-eval-{name}"
        if args.report_only:
            if not (out / "eval.json").exists():
                raise SystemExit(f"--report-only: no {out / 'eval.json'}; evaluate first")
            docs[name] = json.loads((out / "eval.json").read_text())
            continue
        t0 = time.perf_counter()
        cmd = ["eval", folder, "--episodes", str(args.episodes), "--chain", str(args.chain)]
        cmd += ["--num-envs", str(args.num_envs), "--out", str(out), "--no-progress"]
        print("== lcrl " + " ".join(cmd), flush=True)
        lcrl(cmd)
        docs[name] = json.loads((out / "eval.json").read_text())
        docs[name]["seconds"] = time.perf_counter() - t0
    payload = {"headline": eval_headline(docs), "machine": info, "settings": vars(args)}
    save_json("policy-eval", {**payload, "runs": docs})
    save_markdown(
        "policy-eval",
        "Seen vs held-out combinations vs paraphrases (lcrl eval)",
        _table(docs, args),
        info,
    )
    _figure(docs, info)
    print(_table(docs, args))
    return 0


def _first(res: dict[str, Any] | None) -> dict[str, Any] | None:
    """Success and interval of the first instruction of each episode: with chains, the
    chains' length-1 figure (the plain evaluation); else the set's own."""
    if not res:
        return None
    chain = res.get("chain") or {}
    if chain.get("success"):
        return chain["success"][0]
    return res


def _cell(res: dict[str, Any] | None) -> str:
    res = _first(res)
    if not res or res.get("success") is None:
        return "-"
    low, high = res["ci"]
    return f"{res['success']:.2f} [{low:.2f}, {high:.2f}]"


def _table(docs: dict[str, Any], args: argparse.Namespace) -> str:
    lines = [
        "Success of each episode's first instruction (the plain evaluation: chain length 1) "
        f"with its 95% Wilson interval; {args.episodes} chains of up to {args.chain} "
        "instructions per set. The per-family figures below count every instruction "
        "attempted, a chain's later ones included (they start where the previous one "
        "ended, away from the reset layouts training saw). "
        "Per-family, per-slot-value and per-instruction figures are in each run's `eval.md`.",
        "",
        "| run | checkpoint step | " + " | ".join(LABELS[s] for s in SETS) + " |",
        "|---|---:|" + "---|" * len(SETS),
    ]
    for name, doc in docs.items():
        sets = doc["sets"]
        cells = " | ".join(_cell(sets.get(s)) for s in SETS)
        lines.append(f"| {RUNS[name][1]} | {doc['step']} | {cells} |")
    lines += [
        "",
        "| run | set | per family (every instruction) | chains: first k all succeeded "
        "| average length |",
        "|---|---|---|---|---:|",
    ]
    for name, doc in docs.items():
        for s in SETS:
            res = doc["sets"].get(s)
            if not res:
                continue
            fams = ", ".join(
                f"{f} {st['success']:.2f}"
                for f, st in res["families"].items()
                if st["success"] is not None
            )
            chain = res.get("chain") or {}
            rates = " ".join(f"{x['length']}: {x['success']:.2f}" for x in chain.get("success", []))
            avg = chain.get("average_length")
            avg_s = f"{avg:.2f}" if avg is not None else "-"
            lines.append(f"| {name} | {LABELS[s]} | {fams} | {rates} | {avg_s} |")
    lines += [""]
    for name in docs:
        lines.append(
            f"- {name}: [`policy-eval-{name}/eval.md`](policy-eval-{name}/eval.md), "
            f"![sets](policy-eval-{name}/sets.png) ![heatmap](policy-eval-{name}/heatmap.png)"
        )
    return "\n".join(lines)


def _figure(docs: dict[str, Any], info: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 3.8))
    width = 0.8 / max(1, len(SETS))
    x = np.arange(len(docs))
    for k, s in enumerate(SETS):
        rates, errs = [], [[], []]
        for doc in docs.values():
            res = _first(doc["sets"].get(s)) or {}
            rate = res.get("success")
            rates.append(rate if rate is not None else 0.0)
            low, high = res.get("ci", (rate or 0.0, rate or 0.0))
            errs[0].append(max(0.0, (rate or 0.0) - low))
            errs[1].append(max(0.0, high - (rate or 0.0)))
        ax.bar(x + (k - 1) * width, rates, width, yerr=errs, capsize=3, label=LABELS[s])
    ax.set_xticks(x, [n for n in docs])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("first-instruction success (95% CI)")
    ax.set_title("Language HER policies: seen vs held-out vs paraphrased instructions")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    save_figure("policy-eval", fig, info)


if __name__ == "__main__":
    sys.exit(main())

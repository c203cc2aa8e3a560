"""Choose among builds of a camera student on a validation seed, before any test seed.

    python -m benchmarks.camera_choice NAME=RUN NAME=RUN ... [--seed 1] [--episodes 150]

Evaluates each candidate (a ``lcrl distill`` run or checkpoint: the same build stopped at
another round, with another option, ...) with ``lcrl eval RUN --sets train heldout
--episodes N --seed S --canonical-reader``, two at a time on one torch thread each, and
chooses the one with the highest success pooled over both sets (seen instructions and
held-out word combinations, every family). ``--chain 2`` also runs ``N`` chains of two
seen instructions per candidate (``lcrl eval ... --chain 2 --sets train``) and pools a
whole chain achieved as one more success. The validation seed is one no headline
reports (one of ``benchmarks.protocol.VALIDATION_SEEDS``; the test seed of
``benchmarks.robosuite_camera`` is 7);
an evaluation already written is read, not run again.

Writes ``benchmarks/results/NAME.{json,md,png}`` (``--name``, default
``robosuite-camera-choice``); ``headline`` holds ``chosen``, the seed, and each
candidate's pooled, seen and held-out success.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from benchmarks.common import LCRL, machine, new_figure, publish, run_jobs
from benchmarks.protocol import VALIDATION_SEEDS
from lcrl.statistics import wilson_interval

FAMILIES = ("reach", "push", "lift", "put", "stack")
SETS = ("train", "heldout")


def candidates(entries: list[str]) -> dict[str, str]:
    """``NAME=RUN`` entries as a mapping, refused in one line when malformed."""
    out: dict[str, str] = {}
    for entry in entries:
        name, sep, run = entry.partition("=")
        if not sep or not name or not run:
            raise SystemExit(f"candidate {entry!r}: give NAME=RUN")
        if name in out:
            raise SystemExit(f"candidate {name!r} is named twice")
        out[name] = run
    if len(out) < 2:
        raise SystemExit("give two candidates or more to choose among")
    return out


def chain_success(doc: dict[str, Any]) -> tuple[float, int]:
    """The share of chains achieved whole in a ``lcrl eval --chain`` document, and how
    many chains ran."""
    chain = doc["sets"]["train"]["chain"]
    whole = next((c for c in chain["success"] if c["length"] == chain["length"]), None)
    return (whole["success"] if whole else 0.0), int(chain["chains"])


def summary(doc: dict[str, Any], chains: dict[str, Any] | None = None) -> dict[str, Any]:
    """Pooled, per-set and per-family success of one ``lcrl eval --json`` document (and
    of its chains, from a ``--chain`` document)."""
    sets = doc["sets"]
    wins = sum(sets[s]["success"] * sets[s]["episodes"] for s in SETS if s in sets)
    n = sum(sets[s]["episodes"] for s in SETS if s in sets)
    chain = None
    if chains is not None:
        chain = chain_success(chains)
        wins += chain[0] * chain[1]
        n += chain[1]
    out: dict[str, Any] = {
        "pooled": wins / n if n else float("nan"),
        "pooled_ci": list(wilson_interval(round(wins), n)) if n else [float("nan")] * 2,
        "episodes": n,
    }
    for s in SETS:
        if s in sets:
            out[s] = sets[s]["success"]
            out[f"{s}_families"] = {f: v["success"] for f, v in sets[s].get("families", {}).items()}
    if chain is not None:
        out["chain_links"] = chain_links(chains)
        out["chain"] = chain[0]
        out["chain_ci"] = list(wilson_interval(round(chain[0] * chain[1]), chain[1]))
    return out


def chain_links(chains: dict[str, Any]) -> dict[str, dict[str, list[int]]]:
    """Per family, ``[successes, attempts]`` of the chains' first instructions and of the
    later ones (each from where the one before it left the scene), from the episodes of a
    ``--chain`` document."""
    out: dict[str, dict[str, list[int]]] = {"first": {}, "later": {}}
    for episode in chains["sets"]["train"].get("episode_results", []):
        for k, attempt in enumerate(episode["attempts"]):
            if attempt.get("checked", True):
                tally = out["first" if k == 0 else "later"].setdefault(
                    attempt["slots"]["family"], [0, 0]
                )
                tally[0] += int(bool(attempt["success"]))
                tally[1] += 1
    return out


def choose(results: dict[str, dict[str, Any]]) -> str:
    """The candidate with the highest pooled success (the first named on a tie)."""
    return max(results, key=lambda name: results[name]["pooled"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("candidates", nargs="+", help="NAME=RUN, two or more")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=150)
    parser.add_argument("--work", default="runs/camera-choice")
    parser.add_argument("--name", default="robosuite-camera-choice")
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument(
        "--chain", type=int, default=0, help="also chains of this many seen instructions"
    )
    parser.add_argument("--note", default="", help="what the candidates are, for the report")
    parser.add_argument(
        "--title", default="Choosing a camera student on a validation seed", help="the report's"
    )

    args = parser.parse_args(argv)
    runs = candidates(args.candidates)
    if args.seed not in VALIDATION_SEEDS:
        raise SystemExit(
            f"--seed {args.seed}: choices are made on the validation seeds {VALIDATION_SEEDS}"
        )
    work = Path(args.work)
    jobs = []
    for name, run in runs.items():
        path = work / f"{name}-seed{args.seed}.json"
        if not path.is_file():
            argv_ = [
                *LCRL, "eval", run, "--sets", *SETS, "--episodes", str(args.episodes),
                "--seed", str(args.seed), "--canonical-reader", "--no-progress",
                "--json", str(path),
            ]  # fmt: skip
            jobs.append((f"eval {name}", argv_, work / f"{name}-seed{args.seed}.log"))
        chained = work / f"{name}-seed{args.seed}-chain{args.chain}.json"
        if args.chain and not chained.is_file():
            argv_ = [
                *LCRL, "eval", run, "--sets", "train", "--chain", str(args.chain),
                "--episodes", str(args.episodes), "--seed", str(args.seed),
                "--canonical-reader", "--no-progress", "--json", str(chained),
            ]  # fmt: skip
            jobs.append((f"chains {name}", argv_, chained.with_suffix(".log")))
    run_jobs(jobs, parallel=args.parallel)

    def read(name: str) -> dict[str, Any]:
        doc = json.loads((work / f"{name}-seed{args.seed}.json").read_text())
        chained = work / f"{name}-seed{args.seed}-chain{args.chain}.json"
        return summary(doc, json.loads(chained.read_text()) if args.chain else None)

    results = {name: read(name) for name in runs}
    chosen = choose(results)
    info = machine()
    headline: dict[str, Any] = {"chosen": chosen, "seed": args.seed}
    for name, r in results.items():
        headline[f"{name}_pooled"] = round(r["pooled"], 3)
        headline[f"{name}_seen"] = round(r.get("train", float("nan")), 3)
        headline[f"{name}_heldout"] = round(r.get("heldout", float("nan")), 3)
        if args.chain:
            headline[f"{name}_chain{args.chain}"] = round(r["chain"], 3)
    payload = {
        "headline": headline,
        "machine": info,
        "candidates": runs,
        "results": results,
        "protocol": f"validation seed {args.seed}: a choice, not a figure to report",
        "tried": [f"{name}={run}" for name, run in runs.items()],
    }
    sets = "seen instructions, held-out word combinations"
    if args.chain:
        sets += f", chains of {args.chain} seen instructions (a whole chain one success)"
    chain_head = f" chain{args.chain} |" if args.chain else ""
    chain_head += " "
    lines = [
        f"Validation seed {args.seed}, {args.episodes} episodes per set ({sets}), free text "
        "through the canonical reader. Chosen: the highest success pooled over "
        f"{'the three' if args.chain else 'both sets'}.",
        "",
        "| candidate | run | pooled (95% CI) | seen | held-out |"
        + chain_head
        + " ".join(f"seen {f} |" for f in FAMILIES),
        "|---|---|---|---:|---:|" + "---:|" * (len(FAMILIES) + bool(args.chain)),
    ]
    for name, r in results.items():
        lo, hi = r["pooled_ci"]
        fams = r.get("train_families", {})
        lines.append(
            f"| {name} | `{runs[name]}` | {r['pooled']:.2f} [{lo:.2f}, {hi:.2f}] | "
            f"{r.get('train', float('nan')):.2f} | {r.get('heldout', float('nan')):.2f} | "
            + (f"{r['chain']:.2f} | " if args.chain else "")
            + " | ".join(f"{fams.get(f, float('nan')):.2f}" for f in FAMILIES)
            + " |"
        )
    if args.chain:
        lines += [
            "",
            f"In the chains of {args.chain}, each family's instructions as the first of a "
            "chain and as a later one (from where the one before left the scene), "
            "successes of attempts:",
            "",
            "| candidate | " + " | ".join(f"{f}: first, later" for f in FAMILIES) + " |",
            "|---|" + "---|" * len(FAMILIES),
        ]
        for name, r in results.items():
            links = r["chain_links"]
            cells = [
                ", ".join("{}/{}".format(*links[k].get(f, [0, 0])) for k in ("first", "later"))
                for f in FAMILIES
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", f"Chosen: **{chosen}**."]
    if args.note:
        lines += ["", args.note]
        payload["note"] = args.note
    fig, ax = new_figure(figsize=(7, 3.6))
    width = 0.8 / len(results)
    for i, (name, r) in enumerate(results.items()):
        fams = r.get("train_families", {})
        xs = [j + i * width for j in range(len(FAMILIES) + 1)]
        ax.bar(xs, [*(fams.get(f, 0.0) for f in FAMILIES), r["pooled"]], width, label=name)
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(FAMILIES) + 1)])
    ax.set_xticklabels([*(f"seen {f}" for f in FAMILIES), "pooled"], fontsize=7)
    ax.set(ylim=(0, 1.02), ylabel=f"success (seed {args.seed})")
    ax.legend(fontsize=7)
    publish(args.name, payload, args.title, "\n".join(lines), fig)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A camera policy through another perception model: how much of its success it owes to
its student network and how much to the perception model it reads.

    python -m benchmarks.perception_swap --perception benchmarks/models/perception-80x3/model

Evaluates ``--model`` (the kept ``robosuite-camera`` policy by default) on ``--seed`` twice,
as ``lcrl eval MODEL`` and as ``lcrl eval MODEL --perception P``: every instruction set and
chains of two (``benchmarks.robosuite_camera.evaluate``, ``--episodes`` each), and push and
lift alone on ``--families-episodes`` episodes, the families whose camera figures fall
furthest below the same policy's on the true state. An evaluation already in ``--work`` is
read, not run again.

The student's network is the same in both arms; only the slots it reads change. The seed
is a validation seed (1, the one the build's choices looked at): the figures tell what to
build next, and no headline of a command is made of them (the swapped policy is no
command's product). Writes ``benchmarks/results/perception-swap.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from benchmarks.common import LCRL, machine, new_figure, publish, run_jobs
from benchmarks.robosuite_camera import FAMILIES, evaluate, summarise

NAME = "perception-swap"
PAIR = ("push", "lift")


def _pair(work: Path, model: str, seed: int, episodes: int, extra: list[str]) -> dict[str, Any]:
    """Push and lift alone, ``episodes`` in all: success per family and pooled."""
    path = work / f"pushlift-seed{seed}.json"
    if not path.is_file():
        argv = [*LCRL, "eval", model, "--seed", str(seed), "--sets", "train"]
        argv += ["--families", *PAIR, "--episodes", str(episodes), "--no-progress", *extra]
        run_jobs([("eval push and lift", [*argv, "--json", str(path)], path.with_suffix(".log"))])
    train = json.loads(path.read_text())["sets"]["train"]
    fams = train["families"]
    return {
        "pooled": train["success"],
        "episodes": train["episodes"],
        **{f: fams[f]["success"] for f in PAIR},
        "intervals": {f: fams[f]["ci"] for f in PAIR},
        "family_episodes": {f: fams[f]["episodes"] for f in PAIR},
    }


def _alone(pair: dict[str, Any], family: str) -> str:
    """A family's success alone, its 95% interval and its episodes."""
    lo, hi = pair["intervals"][family]
    return f"{pair[family]:.2f} [{lo:.2f}, {hi:.2f}] ({pair['family_episodes'][family]})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="benchmarks/models/robosuite-camera")
    parser.add_argument("--perception", required=True, help="the perception model to swap in")
    parser.add_argument("--seed", type=int, default=1, help="a validation seed")
    parser.add_argument("--episodes", type=int, default=100, help="per instruction set")
    parser.add_argument("--families-episodes", type=int, default=200, help="push and lift")
    parser.add_argument("--work", default="runs/bench/perception-swap")
    parser.add_argument("--parallel", type=int, default=2)
    args = parser.parse_args(argv)
    for path in (args.model, args.perception):
        if not Path(path).exists():
            parser.error(f"no such file or folder: {path}")

    arms = {"own": [], "swapped": ["--perception", args.perception]}
    figures: dict[str, dict[str, Any]] = {}
    for arm, extra in arms.items():
        work = Path(args.work) / arm
        ev = evaluate(args.model, args.seed, args.episodes, work, args.parallel, False, extra=extra)
        summary = summarise(ev)
        summary["push_and_lift"] = _pair(work, args.model, args.seed, args.families_episodes, extra)
        figures[arm] = summary
    own, swapped = figures["own"], figures["swapped"]
    headline = {
        "seed": args.seed,
        "perception": args.perception,
        **{f"own_{f}": round(own[f], 3) for f in (*FAMILIES, "chain2")},
        **{f"swapped_{f}": round(swapped[f], 3) for f in (*FAMILIES, "chain2")},
        "own_seen_pooled": round(own["pooled"]["seen"], 3),
        "swapped_seen_pooled": round(swapped["pooled"]["seen"], 3),
        **{f"own_{f}_alone": round(own["push_and_lift"][f], 3) for f in PAIR},
        **{f"swapped_{f}_alone": round(swapped["push_and_lift"][f], 3) for f in PAIR},
    }
    info = machine()
    payload = {
        "headline": headline,
        "machine": info,
        "settings": vars(args),
        "arms": figures,
        "note": "a diagnostic on a validation seed: the swapped policy is no command's "
        "product, and no headline of robosuite-camera.json is made of it",
    }
    rows = [
        "| arm | " + " | ".join(FAMILIES) + " | chain2 | seen, pooled | held-out / seen | "
        "paraphrases / seen | push alone | lift alone |",
        "|---|" + "---:|" * (len(FAMILIES) + 6),
    ]
    for arm, s in figures.items():
        pl = s["push_and_lift"]
        rows.append(
            f"| {arm} | "
            + " | ".join(f"{s[f]:.2f}" for f in FAMILIES)
            + f" | {s['chain2']:.2f} | {s['pooled']['seen']:.2f} | {s['heldout_ratio']:.2f} | "
            f"{s['paraphrase_ratio']:.2f} | " + " | ".join(_alone(pl, f) for f in PAIR) + " |"
        )
    body = (
        f"The policy `{args.model}` evaluated on seed {args.seed} (a validation seed) through "
        f"its own perception model (`own`) and through `{args.perception}` (`swapped`): "
        f"{args.episodes} episodes per instruction set (about a fifth of them per family) and "
        f"{args.episodes} chains of two, then push and lift alone on "
        f"{args.families_episodes} episodes (their episode counts in brackets). The student "
        "network is the same; only the object slots it reads change.\n\n"
        + "\n".join(rows)
        + "\n\n"
        + (
            f"Pooled over the seen set the swapped arm succeeds {swapped['pooled']['seen']:.2f} "
            f"against {own['pooled']['seen']:.2f}; push alone "
            f"{swapped['push_and_lift']['push']:.2f} against {own['push_and_lift']['push']:.2f}, "
            f"lift alone {swapped['push_and_lift']['lift']:.2f} against "
            f"{own['push_and_lift']['lift']:.2f}; chains of two {swapped['chain2']:.2f} against "
            f"{own['chain2']:.2f}. Intervals in brackets (95%).\n\n"
        )
        + "A diagnostic on a validation seed, not a product's figure: the swapped policy "
        "is not what `lcrl train robosuite-camera` builds, and the headline of "
        "[robosuite-camera.md](robosuite-camera.md) stays that build's.\n"
    )
    fig, ax = new_figure(figsize=(8, 3.6))
    names = [*FAMILIES, "chain2", "push alone", "lift alone"]
    for k, (arm, s) in enumerate(figures.items()):
        pl = s["push_and_lift"]
        values = [s[f] for f in FAMILIES] + [s["chain2"], pl["push"], pl["lift"]]
        ax.bar([i + 0.4 * k for i in range(len(names))], values, width=0.4, label=arm)
    ax.set_xticks([i + 0.2 for i in range(len(names))], names)
    ax.set_ylabel(f"success, seed {args.seed}")
    ax.set_ylim(0, 1)
    ax.legend()
    publish(NAME, payload, "A camera policy through another perception model", body, fig)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Perception on the robosuite tabletop: collect labelled camera episodes, train, evaluate
on held-out episodes and on new layouts of another seed.

    python benchmarks/perception.py --episodes 3000 --steps 10000 --work data/bench-perception-3k

Writes ``benchmarks/results/perception-robosuite.{json,md,png}``; the headline is the mean
position error of present objects in cm (target <= 1.0) and the presence accuracy
(target >= 0.99), on held-out episodes. Wall-clock of each phase is recorded, also in
``WORK/times.json`` (what ``benchmarks/image_policy.py`` counts when it reuses the model).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import command, machine, save_figure, save_json, save_markdown

NAME = "perception-robosuite"
TARGETS = {"position_error_cm": 1.0, "presence_accuracy": 0.99}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--episode-steps", type=int, default=20)
    parser.add_argument("--layout-episodes", type=int, default=60, help="new-layout set")
    parser.add_argument("--steps", type=int, default=10000, help="training steps")
    parser.add_argument("--image-size", type=int, default=84)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--work", default="data/bench-perception")
    parser.add_argument(
        "--no-results",
        action="store_true",
        help="only the model and WORK/times.json (a stage of benchmarks/image_policy.py)",
    )
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from captioner.dataset import CollectConfig
    from train.captions import collect
    from train.perception import (
        PerceptionEvalCommand,
        PerceptionTrainConfig,
        train,
    )

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    times = {}
    t0 = time.perf_counter()
    common = dict(
        env="robosuite",
        max_episode_steps=args.episode_steps,
        image_size=args.image_size,
        overwrite=True,
        progress=False,
    )
    collect(CollectConfig(out=str(work / "train.h5"), episodes=args.episodes, seed=0, **common))
    collect(
        CollectConfig(out=str(work / "layouts.h5"), episodes=args.layout_episodes, seed=1, **common)
    )
    times["collect_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cfg = PerceptionTrainConfig(
        data=str(work / "train.h5"),
        out=str(work / "model"),
        steps=args.steps,
        threads=args.threads,
        progress=False,
    )
    heldout = train(cfg)
    times["train_s"] = time.perf_counter() - t0
    (work / "times.json").write_text(json.dumps(times, indent=1))
    if args.no_results:
        return 0
    layouts = PerceptionEvalCommand(str(work / "model"), data=str(work / "layouts.h5")).run()
    history = json.loads((work / "model" / "model" / "history.json").read_text())

    headline = {
        "position_error_cm": round(heldout["position_error_cm"], 3),
        "presence_accuracy": round(heldout["presence_accuracy"], 4),
        "position_error_cm_new_layouts": round(layouts["position_error_cm"], 3),
        "presence_accuracy_new_layouts": round(layouts["presence_accuracy"], 4),
        "within_reach_margin": round(heldout["within_reach_margin"], 3),
        "within_push_distance": round(heldout["within_push_distance"], 3),
        "wall_clock_s": round(times["collect_s"] + times["train_s"], 1),
    }
    reached = {
        "position_error_cm": headline["position_error_cm"] <= TARGETS["position_error_cm"],
        "presence_accuracy": headline["presence_accuracy"] >= TARGETS["presence_accuracy"],
    }
    info = machine()
    save_json(
        NAME,
        {
            "headline": headline,
            "targets": TARGETS,
            "reached": reached,
            "command": command(),
            "machine": info,
            "settings": vars(args),
            "times": times,
            "heldout_episodes": heldout,
            "new_layouts": layouts,
            "history": history,
        },
    )
    rows = [
        ("held-out episodes", heldout),
        ("new layouts (seed 1)", layouts),
    ]
    lines = [
        "| set | position error (cm) | median | 90% | within 2 cm | within 5 cm | presence |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows:
        lines.append(
            f"| {name} | {r['position_error_cm']:.2f} | {r['position_error_cm_median']:.2f} | "
            f"{r['position_error_cm_p90']:.2f} | {r['within_reach_margin']:.2f} | "
            f"{r['within_push_distance']:.2f} | {r['presence_accuracy']:.3f} |"
        )
    verdict = ", ".join(
        f"{k} {'reached' if ok else 'NOT reached'} (target {TARGETS[k]})"
        for k, ok in reached.items()
    )
    body = (
        f"{args.episodes} robosuite episodes of {args.episode_steps} steps (random and "
        f"scripted), {args.image_size} px agentview frames, {args.steps} training steps; "
        f"collection {times['collect_s']:.0f} s, training {times['train_s']:.0f} s.\n\n"
        + "\n".join(lines)
        + f"\n\nTargets: {verdict}.\n"
    )
    save_markdown(NAME, "Perception on the robosuite tabletop", body, info)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    axes[0].plot([h["step"] for h in history], [h["position_loss"] for h in history])
    axes[0].set_yscale("log")
    axes[0].set_xlabel("step")
    axes[0].set_ylabel("position loss (normalised)")
    kinds = sorted(heldout["per_kind"], key=int)
    errs = [heldout["per_kind"][k]["position_error_cm"] or 0 for k in kinds]
    axes[1].bar(kinds, errs)
    axes[1].axhline(TARGETS["position_error_cm"], color="k", ls="--", lw=1, label="target")
    axes[1].set_xlabel("object kind (slot)")
    axes[1].set_ylabel("held-out position error (cm)")
    axes[1].legend()
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    save_figure(NAME, fig, info)
    print(f"wrote benchmarks/results/{NAME}.{{json,md,png}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

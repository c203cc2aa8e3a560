"""Ray rollout workers on ``lang2d``: a run with 2 local workers against the local run at
the same step budget, and the collection rate of 2 workers against one environment.

    python benchmarks/ray_collect.py

Learning: ``lcrl train lang2d`` twice, same seed and step budget, one after the other,
each alone on the machine: ``local`` (one environment in the learner's process) and
``ray`` (``--collect.backend ray --collect.workers 2``, a local Ray). Both are evaluated
with ``lcrl eval`` (100 episodes per set).

Collection rate: steps/s of collection alone (the policy acting, no updates): the local
loop as ``lang2d`` ships it (8 batched environments; the headline's reference), one local
environment, and 2 Ray workers kept busy, ``--collect-seconds`` each.

Writes ``benchmarks/results/ray_collect.{json,md,png}``; headline ``ray_seen``,
``local_seen`` and ``collect_speedup``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.common import (
    LCRL,
    evaluate,
    machine,
    new_figure,
    run_logged,
    save_figure,
    save_json,
    save_markdown,
)

NAME = "ray_collect"
SETS = ("train", "heldout", "paraphrase")


def run_args(args: argparse.Namespace, arm: str) -> list[str]:
    cmd = [*LCRL, "train", "lang2d", "--out", str(Path(args.work) / arm)]
    cmd += ["--total-steps", str(args.steps), "--eval-every", str(args.eval_every)]
    cmd += ["--seed", str(args.seed), "--checkpoint-every", "0"]
    cmd += ["--overwrite", "--no-progress", "--no-tensorboard"]
    if arm == "ray":
        # the workers replace lang2d's batched local environments
        cmd += ["--collect.backend", "ray", "--collect.workers", str(args.workers)]
        cmd += ["--collect.envs", "1"]
    return cmd


def collection_config(seed: int, **collect: Any) -> Any:
    """``lang2d``'s config for timing collection alone (no updates), ``collect`` set."""
    from train.configs.config import CollectionConfig
    from train.configs.presets import PRESETS

    cfg = copy.deepcopy(PRESETS["lang2d"][1])
    return dataclasses.replace(
        cfg,
        out=tempfile.mkdtemp(prefix="lcrl-collect-"),
        learning_starts=0,
        updates_per_step=0.0,
        progress=False,
        tensorboard=False,
        seed=seed,
        collect=CollectionConfig(**collect),
    )


def local_rate(cfg: Any, seconds: float) -> tuple[float, Any, Any]:
    """Steps/s of the local loop collecting alone for ``seconds``, with the policy's
    weights and instruction table (for Ray workers to act the same policy)."""
    from train.training.loop import Trainer

    t = Trainer(cfg)
    t.advance()  # warm up
    t0, s0 = time.perf_counter(), t.step
    while time.perf_counter() - t0 < seconds:
        t.advance()
    rate = (t.step - s0) / (time.perf_counter() - t0)
    weights = t._weights()
    table = (list(t.task.table), t.task.num_train)
    t.close()
    return rate, weights, table


def ray_rate(cfg: Any, table: Any, weights: Any, seconds: float) -> float:
    """Steps/s of ``cfg.collect.workers`` Ray workers kept busy for ``seconds``."""
    from train.training.ray_collect import RayCollector

    remote = RayCollector(cfg, table, weights)
    try:
        index = 0
        for slot in remote.slots:  # warm up: every worker built and acting
            remote.submit(slot, index, False, None)
            index += 1
        for _ in remote.slots:
            remote.next()
        steps, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            for slot in remote.idle():
                remote.submit(slot, index, False, None)
                index += 1
            _, result = remote.next()
            steps += result["steps"] if result else 0
        return steps / (time.perf_counter() - t0)
    finally:
        remote.close()


def collection_rates(workers: int, seconds: float, seed: int) -> dict[str, float]:
    """Steps/s of collection alone: the local loop as ``lang2d`` ships it (its
    ``collect.envs`` environments, batched), one local environment, then ``workers`` Ray
    workers kept busy (the policy acts; nothing is stored or updated)."""
    from train.configs.presets import PRESETS

    envs = PRESETS["lang2d"][1].collect.envs
    shipped, _, _ = local_rate(collection_config(seed, envs=envs), seconds)
    local, weights, table = local_rate(collection_config(seed, envs=1), seconds)
    rcfg = collection_config(seed, backend="ray", workers=workers)
    return {
        "local_envs": envs,
        "local_shipped_steps_per_s": shipped,
        "local_steps_per_s": local,
        "ray_steps_per_s": ray_rate(rcfg, table, weights, seconds),
    }


def without_arms(argv: list[str]) -> list[str]:
    """``argv`` less ``--arms`` and its values."""
    out, skipping = [], False
    for a in argv:
        if a == "--arms":
            skipping = True
        elif skipping and not a.startswith("-"):
            continue
        else:
            skipping = False
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--eval-every", type=int, default=5_000)
    parser.add_argument("--episodes", type=int, default=100, help="final evaluation")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--collect-seconds", type=float, default=60.0)
    parser.add_argument("--work", default="runs/bench/ray-collect")
    parser.add_argument("--arms", nargs="*", default=["local", "ray"])
    args = parser.parse_args(argv)

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rates = collection_rates(args.workers, args.collect_seconds, args.seed)
    print(f"collection: {rates}", flush=True)
    for arm in args.arms:
        seconds = run_logged(run_args(args, arm), work / f"{arm}.log", arm)
        (work / arm / "seconds.txt").write_text(f"{seconds:.1f}")
    final = {
        arm: evaluate(work / arm, args.episodes, SETS, env=dict(os.environ))
        for arm in ("local", "ray")
    }
    seconds = {arm: float((work / arm / "seconds.txt").read_text()) for arm in ("local", "ray")}
    info = machine()
    # the figures are the full command's: --arms only leaves out runs already done
    cmd = " ".join(["python -m benchmarks.ray_collect", *without_arms(argv or sys.argv[1:])])
    headline = {
        "ray_seen": final["ray"]["train"]["success"],
        "local_seen": final["local"]["train"]["success"],
        # against the local loop as shipped (8 batched environments), not one environment
        "collect_speedup": rates["ray_steps_per_s"] / rates["local_shipped_steps_per_s"],
        "collect_speedup_vs_one_env": rates["ray_steps_per_s"] / rates["local_steps_per_s"],
        "workers": args.workers,
        "steps": args.steps,
    }
    save_json(
        NAME,
        {
            "command": cmd,
            "headline": headline,
            "machine": info,
            "settings": vars(args),
            "collection": rates,
            "final": final,
            "seconds": seconds,
        },
    )
    lines = ["| run | seen | held-out | paraphrase | wall-clock |", "|---|---:|---:|---:|---:|"]
    for arm in ("local", "ray"):
        f = final[arm]
        lines.append(
            f"| {arm} | {f['train']['success']:.2f} | {f['heldout']['success']:.2f} | "
            f"{f['paraphrase']['success']:.2f} | {seconds[arm]:.0f} s |"
        )
    body = (
        f"`lang2d`, {args.steps} steps, seed {args.seed}; `ray`: "
        f"`--collect.backend ray --collect.workers {args.workers}` (a local Ray).\n\n"
        + "\n".join(lines)
        + f"\n\nCollection alone (policy acting, no updates): the local loop as `lang2d` "
        f"ships it ({rates['local_envs']} batched environments) "
        f"{rates['local_shipped_steps_per_s']:.0f} steps/s, {args.workers} Ray workers "
        f"{rates['ray_steps_per_s']:.0f} steps/s: **{headline['collect_speedup']:.2f}x**; "
        f"one local environment {rates['local_steps_per_s']:.0f} steps/s "
        f"({headline['collect_speedup_vs_one_env']:.2f}x).\n\n"
        "Changed from the previous file: its speed-up (2.08x) was against one local "
        "environment; the headline is now against the local loop as shipped, measured in "
        "the same run."
    )
    save_markdown(NAME, "Ray rollout workers on lang2d", body, info, cmd)

    fig, axes = new_figure(nrows=1, ncols=2, figsize=(9, 3.5))
    x = range(len(SETS))
    for k, arm in enumerate(("local", "ray")):
        axes[0].bar(
            [i + 0.4 * k - 0.2 for i in x], [final[arm][s]["success"] for s in SETS], 0.4, label=arm
        )
    axes[0].set_xticks(list(x), ["seen", "held-out", "paraphrase"])
    axes[0].set(ylim=(0, 1.02), ylabel="success", title=f"lang2d, {args.steps} steps")
    axes[0].legend()
    axes[1].bar(
        ["1 local env", f"{rates['local_envs']} local envs", f"{args.workers} Ray workers"],
        [rates["local_steps_per_s"], rates["local_shipped_steps_per_s"], rates["ray_steps_per_s"]],
        color="tab:green",
    )
    axes[1].set(ylabel="collection steps/s", title="collection alone")
    save_figure(NAME, fig, info, cmd)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

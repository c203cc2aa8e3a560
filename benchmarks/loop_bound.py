"""How close the training loop runs to its update bound on ``lang2d``.

    python benchmarks/loop_bound.py

One update per environment step (``updates_per_step`` 1), so a loop that did nothing but
update would run at the bare update rate: ``agent.update(buffer.sample(256))`` timed
alone on the same agent and buffer. The loop fraction is the loop's steps/s (acting,
stepping, captioning, storing, sampling and updating, after ``learning_starts``) over
that rate; the rest is what collection costs. Measured for one environment and for
``--envs`` environments stepped at once (``collect.envs``: the policy acts for all in one
forward pass), at 1 and 2 torch threads, synchronous mode. Loop and bare update alternate
(``--rounds`` times) in one process, alone on the machine; medians are reported.

Writes ``benchmarks/results/loop_bound.{json,md,png}``; ``headline.loop_fraction`` is the
lowest fraction of the ``collect.envs`` setting over the thread counts (target >= 0.95).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.common import (
    machine,
    new_figure,
    save_figure,
    save_json,
    save_markdown,
)

NAME = "loop_bound"
TARGET = 0.95


def trainer(envs: int, steps: int, warmup: int, seed: int) -> object:
    """A ``lang2d`` trainer with a filled buffer, at ``learning_starts``."""
    from train.configs.config import CollectionConfig
    from train.configs.presets import PRESETS
    from train.training.loop import Trainer

    cfg = copy.deepcopy(PRESETS["lang2d"][1])
    out = Path(tempfile.mkdtemp(prefix="lcrl-bound-"))
    cfg = dataclasses.replace(
        cfg,
        out=str(out),
        total_steps=10**9,
        learning_starts=warmup,
        updates_per_step=1.0,
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        tensorboard=False,
        seed=seed,
        collect=CollectionConfig(envs=envs),
    )
    t = Trainer(cfg)
    t.open_outputs()
    while t.step < warmup:
        t.advance()
    return t


def discard(t: object) -> None:
    """Close a :func:`trainer` and remove its run folder."""
    out = t.out
    t.close()
    shutil.rmtree(out, ignore_errors=True)


def loop_rate(t: object, steps: int) -> float:
    """Steps/s of the loop over at least ``steps`` steps (whole collection units)."""
    start, t0 = t.step, time.perf_counter()
    while t.step - start < steps:
        t.advance()
    return (t.step - start) / (time.perf_counter() - t0)


def update_rate(t: object, updates: int) -> float:
    """Updates/s of ``agent.update(buffer.sample(batch))`` alone."""
    batch = t.cfg.batch_size
    t0 = time.perf_counter()
    for _ in range(updates):
        t.agent.update(t.buffer.sample(batch))
    return updates / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", type=int, default=8, help="collect.envs of the new setting")
    parser.add_argument("--steps", type=int, default=1500, help="timed steps per round")
    parser.add_argument("--warmup", type=int, default=2000, help="random steps first")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import torch

    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for envs in dict.fromkeys((1, args.envs)):
            t = trainer(envs, args.steps, args.warmup, args.seed)
            t.cfg.torch_threads = threads
            torch.set_num_threads(threads)  # the trainer set its default
            loops, bares = [], []
            for _ in range(args.rounds):
                loops.append(loop_rate(t, args.steps))
                bares.append(update_rate(t, args.steps))
            loop, bare = statistics.median(loops), statistics.median(bares)
            rows.append(
                {
                    "threads": threads,
                    "envs": envs,
                    "loop_steps_per_s": loop,
                    "bare_updates_per_s": bare,
                    "loop_fraction": loop / bare,
                    "loop_rounds": loops,
                    "bare_rounds": bares,
                }
            )
            print(
                f"threads {threads} envs {envs}: loop {loop:.1f} steps/s, bare {bare:.1f} "
                f"updates/s, fraction {loop / bare:.3f}",
                flush=True,
            )
            discard(t)

    info = machine()
    new = [r for r in rows if r["envs"] == args.envs]
    old = [r for r in rows if r["envs"] == 1]
    headline = {"loop_fraction": min(r["loop_fraction"] for r in new)}
    for r in new:
        headline[f"loop_fraction_{r['threads']}_threads"] = r["loop_fraction"]
    headline["loop_fraction_one_env"] = min(r["loop_fraction"] for r in old)
    headline["envs"] = args.envs
    payload = {
        "headline": headline,
        "target": {"loop_fraction": TARGET},
        "reached": {"loop_fraction": headline["loop_fraction"] >= TARGET},
        "machine": info,
        "settings": vars(args),
        "rows": rows,
    }
    save_json(NAME, payload)
    lines = [
        "| torch threads | envs | loop steps/s | bare updates/s | loop fraction |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['threads']} | {r['envs']} | {r['loop_steps_per_s']:.1f} | "
            f"{r['bare_updates_per_s']:.1f} | {r['loop_fraction']:.3f} |"
        )
    reached = "reached" if payload["reached"]["loop_fraction"] else "NOT reached"
    body = (
        f"Target: loop fraction >= {TARGET} with `collect.envs {args.envs}` at every thread "
        f"count: **{reached}** (lowest {headline['loop_fraction']:.3f}).\n\n" + "\n".join(lines)
    )
    save_markdown(NAME, "Loop speed against the update bound (lang2d)", body, info)

    fig, ax = new_figure(figsize=(6, 3.5))
    labels = [f"{r['threads']} thr, {r['envs']} env" for r in rows]
    ax.bar(labels, [r["loop_fraction"] for r in rows], color="tab:blue")
    ax.axhline(TARGET, color="k", ls="--", lw=1, label=f"target {TARGET}")
    ax.set(ylim=(0, 1.05), ylabel="loop steps/s / bare updates/s", title="lang2d loop bound")
    ax.legend(loc="lower right")
    save_figure(NAME, fig, info)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

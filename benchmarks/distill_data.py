"""How a DAgger student's imitation of its teachers on episodes it never saw improves with
its data.

    python -m benchmarks.distill_data runs/robosuite-camera/student

Reads the dataset a ``lcrl distill`` checkpoint keeps (every state the student and its
teachers visited, labelled with the teacher's action) and splits it by instruction segment
(the rows of one instruction in one scene; a chain of instructions gives several):
``--heldout`` of the segments (seeded) are held out, and fresh students with the run's own
networks and settings (``bc``, its batch size, learning rate and precision, a cosine-decayed
learning rate over ``--updates``) are fitted on ``--fractions`` of the rest. Every
``--updates // 8`` updates the action error (squared error summed over the action
dimensions) is measured on the held-out segments, per family and for the gripper, and on
rows the student trained on.

A student that fits the rows it saw but not held-out episodes is short of data rather than
of capacity or updates: its error on held-out segments falls with more segments, and the
figure shows by how much per doubling. The reference is the error of always acting the
training rows' mean action.

``--augment colours mirror+colours ...`` also fits the largest share with every batch's rows
augmented each way (``lcrl distill --augment``: colours renamed in scene and instruction
alike, scenes reflected left to right), to set what each buys beside what more episodes
buy.

Writes ``benchmarks/results/distill-data.{json,md,png}``; ``headline`` holds the best
held-out error per fraction (``heldout_error_<percent>``), the mean-action reference and
the training-row error of the largest fraction.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import time
from typing import Any

import numpy as np

from benchmarks.common import machine, new_figure, publish

NAME = "distill-data"


def segments(initial: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Segment id of every row: a new segment starts where the instruction's first
    observation (``initial``) or the goal changes."""
    change = np.ones(len(goal), bool)
    change[1:] = np.any(initial[1:] != initial[:-1], axis=1) | (goal[1:] != goal[:-1])
    return np.cumsum(change) - 1


def split_rows(
    seg: np.ndarray, heldout: float, fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out row indices: ``heldout`` of the segments held out, ``fraction``
    of the other segments kept for training (the same held-out segments for every
    fraction; a smaller fraction's segments are a subset of a larger one's)."""
    rng = np.random.default_rng(seed)
    n = int(seg.max()) + 1
    draw_held, draw_keep = rng.random(n), rng.random(n)
    held = draw_held < heldout
    keep = (~held) & (draw_keep < fraction)
    return np.flatnonzero(keep[seg]), np.flatnonzero(held[seg])


def action_error(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Squared error summed over action dimensions, per row."""
    return ((pred - target) ** 2).sum(axis=1)


def fit(
    policy: Any,
    data: dict[str, np.ndarray],
    train: np.ndarray,
    probe: np.ndarray,
    families: np.ndarray,
    args: Any,
    augment: Any = None,
) -> list[dict[str, float]]:
    """Fit a fresh student on the ``train`` rows (augmented by ``augment``, a
    :class:`~train.training.augment.Augmentation`, if given); its error on ``probe``
    (held-out rows, as gathered) and on training rows, every ``updates // 8`` updates."""
    import torch

    from train.evaluation.evaluate import build_agent
    from train.training.distill import labelled_batch
    from train.training.loop import attach_grounding

    torch.manual_seed(args.seed)
    cfg = copy.deepcopy(policy.cfg)
    cfg.agent = dataclasses.replace(cfg.agent, seed=args.seed)
    task = policy.task
    agent = build_agent("bc", task.problem(), cfg, task.goal_space.embed)
    keys = list(task.problem().obs_shapes)
    agent.observe({k: data[k][train] for k in keys}, task.embeddings[: task.num_train])
    attach_grounding(agent, task, cfg)
    rng = np.random.default_rng(args.seed)
    seen = rng.choice(train, min(len(train), len(probe)), replace=False)

    def error(rows: np.ndarray) -> np.ndarray:
        pred = np.concatenate(
            [
                agent.act({k: data[k][c] for k in keys}, data["goal"][c], deterministic=True)
                for c in np.array_split(rows, max(1, len(rows) // 2500))
            ]
        )
        return (pred - data["action"][rows]) ** 2

    batch, lr0, points = cfg.batch_size, cfg.bc.lr, []
    every = max(1, args.updates // 8)
    for u in range(args.updates):
        agent.opt.lr = lr0 * 0.5 * (1 + math.cos(math.pi * u / args.updates))
        idx = train[rng.integers(len(train), size=batch)]
        obs, goal = {k: data[k][idx] for k in keys}, data["goal"][idx]
        action = data["action"][idx]
        if augment is not None:
            obs, goal, action = augment.apply(obs, goal, action, rng)
        agent.update(labelled_batch(obs, action, goal, idx))
        if (u + 1) % every == 0 or u + 1 == args.updates:
            e = error(probe)
            point = {
                "updates": u + 1,
                "heldout": float(e.sum(1).mean()),
                "train": float(error(seen).sum(1).mean()),
                "gripper": float(e[:, -1].mean()),
            }
            for f in np.unique(families):
                point[f] = float(e[families[probe] == f].sum(1).mean())
            points.append(point)
            print(
                f"  {u + 1} updates: held-out {point['heldout']:.3f}, "
                f"trained rows {point['train']:.3f}",
                flush=True,
            )
    return points


def augmenter(policy: Any, kinds: str) -> Any:
    """The augmentation ``lcrl distill --augment KINDS`` applies to the policy's rows."""
    from envs.features import slot_layout
    from train.training.augment import augmentation

    size = int(policy.task.problem().obs_shapes["observation"][0])
    table, n = policy.task.table, policy.task.num_train
    return augmentation(kinds, table, n, slot_layout(policy.env), size, policy.task.discrete)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a lcrl distill run or checkpoint folder")
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.25, 0.5, 1.0])
    parser.add_argument("--heldout", type=float, default=0.1)
    parser.add_argument("--updates", type=int, default=8000)
    parser.add_argument("--probe-rows", type=int, default=10_000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--augment",
        nargs="*",
        default=[],
        help="also fit the largest share augmented each of these ways (lcrl distill --augment)",
    )
    args = parser.parse_args(argv)

    import torch

    from captioner.grammar import parse
    from lcrl.errors import LcrlError
    from train.evaluation.evaluate import resolve_checkpoint
    from train.policies.loading import load_policy

    torch.set_num_threads(args.threads)
    if not all(0 < f <= 1 for f in args.fractions) or not 0 < args.heldout < 1:
        raise SystemExit("--fractions must lie in (0, 1] and --heldout in (0, 1)")
    ckpt = resolve_checkpoint(args.run)
    policy = load_policy(ckpt)
    if not policy.checkpoint.has_arrays():
        raise LcrlError(f"{ckpt} keeps no dataset: give a lcrl distill run's own checkpoint")
    data = {k.removeprefix("data_"): v for k, v in policy.checkpoint.arrays().items()}
    if "action" not in data or "goal" not in data:
        raise LcrlError(f"{ckpt} is not a lcrl distill checkpoint (no labelled states)")
    table = policy.task.table
    families = np.array([parse(table[int(g)]).family for g in data["goal"]])
    seg = segments(data["initial"], data["goal"])
    rng = np.random.default_rng(args.seed)
    arms: dict[str, Any] = {}
    start = time.time()
    plans = [(f, "") for f in args.fractions]
    plans += [(max(args.fractions), kinds) for kinds in args.augment]
    for fraction, augmented in plans:
        train, held = split_rows(seg, args.heldout, fraction, args.seed)
        probe = rng.choice(held, min(args.probe_rows, len(held)), replace=False)
        print(
            f"{fraction:.0%} of the training segments: {len(train)} rows, "
            f"{len(np.unique(seg[train]))} segments{f', {augmented}' if augmented else ''}"
        )
        augment = augmenter(policy, augmented) if augmented else None
        points = fit(policy, data, train, probe, families, args, augment)
        best = min(points, key=lambda p: p["heldout"])
        arms[f"{round(fraction * 100)}{f'_{augmented}' if augmented else ''}"] = {
            "fraction": fraction,
            "augment": augmented,
            "rows": len(train),
            "segments": len(np.unique(seg[train])),
            "best": best,
            "final": points[-1],
            "curve": points,
        }
    train, held = split_rows(seg, args.heldout, 1.0, args.seed)
    mean_action = data["action"][train].mean(0)
    reference = float(action_error(data["action"][held], mean_action[None]).mean())
    plain = {k: v for k, v in arms.items() if not v["augment"]}
    largest = plain[max(plain, key=lambda k: plain[k]["fraction"])]
    headline = {
        **{f"heldout_error_{k}": round(v["best"]["heldout"], 3) for k, v in arms.items()},
        "mean_action_error": round(reference, 3),
        "train_error_largest": round(largest["final"]["train"], 3),
        "segments_largest": largest["segments"],
    }
    info = machine()
    payload = {
        "headline": headline,
        "machine": info,
        "run": str(ckpt),
        "rows": len(data["goal"]),
        "segments": int(seg.max()) + 1,
        "heldout_segments": float(args.heldout),
        "updates": args.updates,
        "arms": arms,
        "seconds": round(time.time() - start, 1),
    }
    fams = sorted(set(families.tolist()) - {"reach"})
    lines = [
        f"The DAgger dataset of `{ckpt}`: {payload['rows']:,} labelled states in "
        f"{payload['segments']:,} instruction segments; {args.heldout:.0%} of the segments "
        f"held out. Fresh students (the run's networks and settings, {args.updates:,} updates, "
        "cosine learning rate) fitted on a share of the other segments. Action error: "
        "squared error summed over the action dimensions (best over the run, measured every "
        f"{max(1, args.updates // 8):,} updates).",
        "",
        "| training segments | augmented | rows | held-out error | "
        + " | ".join(fams)
        + " | gripper | trained rows (final) |",
        "|---|---|---:|---:|" + "---:|" * len(fams) + "---:|---:|",
    ]
    for v in arms.values():
        b = v["best"]
        lines.append(
            f"| {v['segments']:,} ({v['fraction']:.0%}) | {v['augment'] or 'no'} | "
            f"{v['rows']:,} | {b['heldout']:.3f} | "
            + " | ".join(f"{b.get(f, float('nan')):.3f}" for f in fams)
            + f" | {b['gripper']:.3f} | {v['final']['train']:.3f} |"
        )
    lines += [
        "",
        f"Always acting the training rows' mean action: {reference:.3f}.",
    ]
    if len(plain) > 1:
        a = sorted(plain.values(), key=lambda v: v["fraction"])
        per_doubling = (a[0]["best"]["heldout"] - a[-1]["best"]["heldout"]) / max(
            math.log2(a[-1]["segments"] / a[0]["segments"]), 1e-9
        )
        payload["headline"]["gain_per_doubling"] = round(per_doubling, 3)
        fits = largest["final"]["train"] < 0.5 * largest["best"]["heldout"]
        if per_doubling <= 0:
            said = f"More segments did not lower the held-out error ({per_doubling:.3f} each time)."
        else:
            said = (
                f"Each doubling of the segments lowers the held-out error by {per_doubling:.3f} "
                f"on average; on rows it trained on the student ends at "
                f"{largest['final']['train']:.3f}"
                + (
                    ": it fits what it saw and is short of episodes, not of updates or capacity."
                    if fits
                    else "."
                )
            )
        lines.append(said)
    fig, axes = new_figure(ncols=2, figsize=(9, 3.6))
    for v in arms.values():
        c = v["curve"]
        name = f"{v['segments']} seg.{' + ' + v['augment'] if v['augment'] else ''}"
        axes[0].plot([p["updates"] for p in c], [p["heldout"] for p in c], label=name)
        axes[0].plot(
            [p["updates"] for p in c], [p["train"] for p in c], ls=":", color="grey", lw=0.8
        )
    axes[0].axhline(reference, color="k", ls="--", lw=0.8, label="mean action")
    axes[0].set(xlabel="updates", ylabel="action error", title="held-out (solid), trained (dotted)")
    axes[0].legend(fontsize=7)
    segs = [v["segments"] for v in plain.values()]
    axes[1].plot(segs, [v["best"]["heldout"] for v in plain.values()], "o-", label="all")
    for f in fams:
        axes[1].plot(segs, [v["best"].get(f, np.nan) for v in plain.values()], ".--", label=f)
    for v, marker in zip([v for v in arms.values() if v["augment"]], "*Pd^", strict=False):
        axes[1].plot(v["segments"], v["best"]["heldout"], marker, ms=9, label=v["augment"])
    axes[1].set(xscale="log", xlabel="training segments", ylabel="best held-out action error")
    axes[1].legend(fontsize=7)
    title = "A DAgger student's error on unseen episodes against its data"
    publish(NAME, payload, title, "\n".join(lines), fig)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

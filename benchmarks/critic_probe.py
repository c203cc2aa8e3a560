"""How fast can a goal-conditioned critic learn the one-step reach reward? (2D tabletop)

The reward of a language goal depends on the one object the instruction names: "reach
the red cube" is satisfied when the pusher ends the step next to the red cube. A critic
must learn to pick that object's slot out of the observation by the goal, then judge a
distance. This probe isolates that from the rest of reinforcement learning: it draws
states of the real 2D tabletop with the pusher 4 to 12 cm from one of the objects, a
reach instruction about that object or another one, and a random action; it steps the
real env and labels the transition with the rule captioner's ``satisfied`` check (about
5% positives). Each network reads the frozen text encoder's embedding of the
instruction (standardised per dimension, as in training) and is trained on the same
batches with binary cross-entropy; recall and false-positive rate on held-out samples
are printed after every 1,000 updates.

Networks (all with the training default 2x256 fused MLP):

* ``concat``: observation and goal features concatenated (the plain UVFA);
* ``film``: FiLM fusion;
* ``attention``: goal-conditioned attention over object slots (``slot_mode="attention"``);
* ``select``: the goal picks slots by position (``slot_mode="select"``);
* ``concat+rel`` / ``select+rel``: the same with each object's position relative to the
  pusher added to its slot (:class:`envs.features.RelativePositions`).

Run from the repository root::

    python benchmarks/critic_probe.py            # all networks, about 10 minutes on a CPU
    python benchmarks/critic_probe.py --updates 2000 select+rel concat

Writes ``benchmarks/results/critic_probe.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F

from benchmarks.common import caption, machine, save_json, save_markdown
from captioner.grammar import Instruction
from envs.features import RelativePositions
from lcrl.nets import GoalConditionedNet, NetConfig, RunningNorm
from lcrl.text_encoder import FrozenTextEncoder
from train.environments.tasks import EnvConfig, make_env, make_task

NETWORKS: dict[str, tuple[bool, dict[str, Any]]] = {
    "concat": (False, {}),
    "film": (False, {"fusion": "film"}),
    "attention": (False, {"slots": (2, 8, 3), "slot_mode": "attention"}),
    "select": (False, {"slots": (2, 8, 3), "slot_mode": "select"}),
    "concat+rel": (True, {}),
    "select+rel": (True, {"slots": (2, 8, 5), "slot_mode": "select"}),
}


def make_data(n: int, seed: int) -> dict[str, Any]:
    """``n`` labelled reach transitions of the real 2D tabletop."""
    cfg = EnvConfig(kind="lang2d", families=("reach",))
    env = make_env(cfg, "train", training=True)
    encoder = FrozenTextEncoder()
    task = make_task(cfg, env, embed=encoder.encode)
    base = env.unwrapped
    rel = RelativePositions(base)
    rng = np.random.default_rng(seed)
    obs, obs_rel, goals, actions, labels = [], [], [], [], []
    while len(labels) < n:
        env.reset(seed=int(rng.integers(2**31)))
        scene = base.scene()
        kinds = list(zip(scene.colours, scene.shapes, strict=True))
        goal_i = int(rng.integers(len(kinds)))
        near_i = goal_i if rng.random() < 0.5 else int(rng.integers(len(kinds)))
        meaning = Instruction("reach", *kinds[goal_i])
        if meaning.text not in task.train_ids:  # held-out combinations are never trained
            continue
        r, angle = rng.uniform(0.04, 0.12), rng.uniform(0.0, 2.0 * np.pi)
        centre = scene.positions[near_i, :2]
        base._px = float(np.clip(centre[0] + r * np.cos(angle), -0.23, 0.23))
        base._py = float(np.clip(centre[1] + r * np.sin(angle), -0.23, 0.23))
        before = base.scene()
        if before.touching is not None and before.touching.any():
            continue
        o = base._observe()[0]["observation"]
        a = rng.uniform(-1.0, 1.0, 2).astype(np.float32)
        base.step(a)
        obs.append(o)
        obs_rel.append(rel.features(o))
        goals.append(task.train_ids[meaning.text])
        actions.append(a)
        labels.append(float(task.captioner.satisfied(meaning, before, base.scene())))
    return {
        "obs": np.array(obs),
        "obs_rel": np.array(obs_rel),
        "goal": np.array(goals),
        "action": np.array(actions),
        "label": np.array(labels, np.float32),
        "embeddings": torch.as_tensor(task.embeddings),
        "num_train": task.num_train,
    }


def probe(
    name: str, data: dict[str, Any], updates: int, every: int, test: int, seed: int
) -> list[dict[str, float]]:
    """Train one network; returns recall / false-positive rate / accuracy per checkpoint."""
    relative, fields = NETWORKS[name]
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    o = data["obs_rel" if relative else "obs"]
    y, g, a = data["label"], data["goal"], data["action"]
    train = slice(0, len(y) - test)
    held = slice(len(y) - test, len(y))
    emb = data["embeddings"]
    net = GoalConditionedNet(
        {"observation": (o.shape[1],)}, "text", (emb.shape[1],), 1, NetConfig(**fields), 2
    )
    obs_norm = RunningNorm(o.shape[1])
    obs_norm.update(torch.as_tensor(o[train]))
    goal_norm = RunningNorm(emb.shape[1], eps=1e-3)
    goal_norm.update(emb[: data["num_train"]])
    opt = torch.optim.Adam(net.parameters(), 1e-3)

    def logits(sl: Any) -> torch.Tensor:
        obs = {"observation": obs_norm(torch.as_tensor(o[sl]))}
        goal = goal_norm(emb[torch.as_tensor(g[sl])])
        return net(obs, goal, torch.as_tensor(a[sl])).squeeze(-1)

    rows = []
    n_train = len(y) - test
    for step in range(1, updates + 1):
        idx = rng.integers(0, n_train, 256)
        loss = F.binary_cross_entropy_with_logits(logits(idx), torch.as_tensor(y[idx]))
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % every == 0:
            with torch.no_grad():
                p = torch.sigmoid(logits(held)).numpy() > 0.5
            pos = y[held] == 1
            rows.append(
                {
                    "updates": step,
                    "recall": float(p[pos].mean()),
                    "false_positive_rate": float(p[~pos].mean()),
                    "accuracy": float((p == pos).mean()),
                }
            )
    return rows


def headline(results: dict[str, list[dict[str, Any]]]) -> dict[str, float]:
    """Each probe's recall and false-positive rate after its last update."""
    head: dict[str, float] = {}
    for name, curve in results.items():
        head[f"{name}_recall"] = round(curve[-1]["recall"], 3)
        head[f"{name}_false_positive_rate"] = round(curve[-1]["false_positive_rate"], 4)
    return head


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("networks", nargs="*", help=f"any of {', '.join(NETWORKS)} (default: all)")
    parser.add_argument("--samples", type=int, default=60_000)
    parser.add_argument("--test", type=int, default=10_000, help="held-out samples")
    parser.add_argument("--updates", type=int, default=4_000)
    parser.add_argument("--every", type=int, default=1_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    names = args.networks or list(NETWORKS)
    unknown = [n for n in names if n not in NETWORKS]
    if unknown:
        parser.error(f"unknown networks {unknown}; choose from {', '.join(NETWORKS)}")
    torch.set_num_threads(1)
    info = machine()
    t0 = time.perf_counter()
    data = make_data(args.samples, args.seed)
    print(
        f"{args.samples} transitions in {time.perf_counter() - t0:.0f} s, "
        f"{data['label'].mean():.1%} positive",
        flush=True,
    )
    results = {}
    for name in names:
        t0 = time.perf_counter()
        results[name] = probe(name, data, args.updates, args.every, args.test, args.seed)
        last = results[name][-1]
        print(
            f"{name:12s} recall {last['recall']:.2f} fpr {last['false_positive_rate']:.3f} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    save_json(
        "critic_probe",
        {
            "headline": headline(results),
            "machine": info,
            "samples": args.samples,
            "positives": float(data["label"].mean()),
            "results": results,
        },
    )
    steps = [r["updates"] for r in results[names[0]]]
    lines = [
        "Recall of the one-step reach reward on held-out transitions (false-positive rate "
        f"in brackets); {data['label'].mean():.1%} of transitions are positive.",
        "",
        "| network | " + " | ".join(f"{s} updates" for s in steps) + " |",
        "|---|" + "---:|" * len(steps),
    ]
    for name, rows in results.items():
        cells = [f"{r['recall']:.2f} ({r['false_positive_rate']:.3f})" for r in rows]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)
    save_markdown("critic_probe", "Critic probe: the one-step reach reward", table, info)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for name, rows in results.items():
        ax.plot(steps, [r["recall"] for r in rows], marker="o", ms=3, label=name)
    ax.set_xlabel("updates (batch 256)")
    ax.set_ylabel("recall of positive transitions")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("How fast a critic learns the one-step reach reward")
    ax.legend(fontsize=7)
    fig.subplots_adjust(bottom=0.22)
    caption(fig, info)
    fig.savefig(Path(__file__).resolve().parent / "results" / "critic_probe.png", dpi=120)
    print("saved benchmarks/results/critic_probe.{json,md,png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

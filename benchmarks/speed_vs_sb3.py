"""Training speed: lcrl's loop against Stable-Baselines3 SAC + HerReplayBuffer, side by side.

Run from the repository root (needs ``pip install -e '.[bench]'``)::

    python benchmarks/speed_vs_sb3.py            # 2 rounds of 1,500 timed steps, 1 and 2 threads

Both train SAC with hindsight relabelling (``future``, k=4) on gymnasium-robotics
``FetchReach-v4`` with the same networks (two hidden layers of 256 for actor and
critics), batch size 256, one gradient update per environment step, and 1,000 steps of
random actions first. What is timed is environment steps per second *after* learning
starts: acting, stepping, storing, sampling with relabelling and updating. The two
libraries alternate (lcrl, SB3, lcrl, SB3, ...) in one process so that both see the same
machine load; the ratio of medians is reported at each torch thread count (``--threads``,
set in the process for both). Target: lcrl at least 1.5x SB3 at 1 and at 2 threads
(``headline.ratio_1thread`` and ``headline.ratio_2threads``).

Writes ``benchmarks/results/speed_vs_sb3.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import matplotlib
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import command, machine, save_figure, save_json, save_markdown
from lcrl.nets import NetConfig
from train.config import PRESETS
from train.loop import Trainer

WARMUP = 1_000
BATCH = 256
HIDDEN = (256, 256)
TARGET = 1.5


def time_lcrl(steps: int, seed: int) -> float:
    """Steps per second of lcrl's loop over ``steps`` steps after learning starts."""
    base = PRESETS["fetch-reach"][1]
    out = Path(tempfile.mkdtemp(prefix="lcrl-speed-"))
    cfg = dataclasses.replace(
        base,
        out=str(out),
        total_steps=WARMUP + steps,
        learning_starts=WARMUP,
        batch_size=BATCH,
        updates_per_step=1.0,
        progress=False,
        tensorboard=False,
        seed=seed,
        torch_threads=torch.get_num_threads(),  # the count main() set, for both libraries
    )
    cfg.agent = dataclasses.replace(cfg.agent, net=NetConfig(hidden=HIDDEN), seed=seed)
    trainer = Trainer(cfg)
    while trainer.step < WARMUP:
        trainer.collect_episode()
    start_step, t0 = trainer.step, time.perf_counter()
    while trainer.step < cfg.total_steps:
        trainer.collect_episode()
    rate = (trainer.step - start_step) / (time.perf_counter() - t0)
    shutil.rmtree(out, ignore_errors=True)
    return rate


def time_sb3(steps: int, seed: int) -> float:
    """Steps per second of SB3 SAC + HerReplayBuffer over ``steps`` steps after learning
    starts."""
    import gymnasium as gym
    import gymnasium_robotics
    from stable_baselines3 import SAC, HerReplayBuffer

    gym.register_envs(gymnasium_robotics)
    env = gym.make("FetchReach-v4")
    model = SAC(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=WARMUP,
        batch_size=BATCH,
        train_freq=1,
        gradient_steps=1,
        policy_kwargs={"net_arch": list(HIDDEN)},
        seed=seed,
        verbose=0,
    )
    model.learn(WARMUP)
    t0 = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    return steps / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=1_500, help="timed steps per round")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args(argv)
    info = machine()
    rates: dict[str, dict[str, list[float]]] = {}
    for n in args.threads:
        torch.set_num_threads(n)
        rates[str(n)] = {"lcrl": [], "sb3": []}
        for r in range(args.rounds):
            for name, fn in (("lcrl", time_lcrl), ("sb3", time_sb3)):
                rate = fn(args.steps, seed=r)
                rates[str(n)][name].append(rate)
                print(f"{n} thread(s), round {r} {name}: {rate:.1f} steps/s", flush=True)
    med = {n: {k: statistics.median(v) for k, v in per.items()} for n, per in rates.items()}
    ratios = {n: m["lcrl"] / m["sb3"] for n, m in med.items()}
    headline = {
        f"ratio_{n}thread{'s' if int(n) > 1 else ''}": round(r, 3) for n, r in ratios.items()
    }
    reached = all(r >= TARGET for r in ratios.values())
    rows = ["| torch threads | library | steps/s per round | median |", "|---:|---|---|---:|"]
    for n, per in rates.items():
        for k, v in per.items():
            rows.append(f"| {n} | {k} | {', '.join(f'{x:.1f}' for x in v)} | {med[n][k]:.1f} |")
    rows += [
        "",
        *(f"Ratio lcrl / SB3 at {n} thread(s): **{r:.2f}x**" for n, r in ratios.items()),
        "",
        f"Target: at least {TARGET}x at every thread count: "
        f"**{'reached' if reached else 'NOT reached'}**.",
        "",
        f"Setting: FetchReach-v4, SAC, HER future k=4, hidden {HIDDEN}, batch {BATCH}, 1 update "
        f"per step, {WARMUP} random steps first, {args.steps} timed steps per round; the two "
        "libraries alternate in one process, alone on the machine.",
    ]
    table = "\n".join(rows)
    print(table)
    save_json(
        "speed_vs_sb3",
        {
            "headline": headline,
            "target": f"every ratio >= {TARGET}",
            "reached": reached,
            "command": command(),
            "machine": info,
            "rates": rates,
            "median": med,
            "steps": args.steps,
            "rounds": args.rounds,
        },
    )
    save_markdown("speed_vs_sb3", "Training speed: lcrl vs Stable-Baselines3", table, info)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    width = 0.38
    for j, lib in enumerate(("lcrl", "sb3")):
        xs = [i + (j - 0.5) * width for i in range(len(rates))]
        ax.bar(xs, [med[n][lib] for n in rates], width, label=lib,
               color="tab:blue" if lib == "lcrl" else "tab:grey")  # fmt: skip
        for x, n in zip(xs, rates, strict=True):
            ax.scatter([x] * len(rates[n][lib]), rates[n][lib], color="black", s=10, zorder=3)
    ax.set_xticks(range(len(rates)), [f"{n} thread(s)\n{ratios[n]:.2f}x" for n in rates])
    ax.set_ylabel("environment steps / s (training)")
    ax.set_title("FetchReach-v4 SAC+HER: lcrl against SB3")
    ax.legend()
    fig.subplots_adjust(bottom=0.3)
    save_figure("speed_vs_sb3", fig, info)
    print("saved benchmarks/results/speed_vs_sb3.{json,md,png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Training speed: lcrl's loop against Stable-Baselines3 SAC + HerReplayBuffer, side by side.

Run from the repository root (needs ``pip install -e '.[bench]'``)::

    python benchmarks/speed_vs_sb3.py            # 5 rounds of 1,500 timed steps, 1 and 2 threads

Both train SAC with hindsight relabelling (``future``, k=4) on gymnasium-robotics
``FetchReach-v4`` from one environment each, with the same networks (two hidden layers of
256 for actor and critics), batch size 256, one gradient update per environment step, and
1,000 steps of random actions first. What is timed is environment steps per second *after* learning
starts: acting, stepping, storing, sampling with relabelling and updating. The two
libraries alternate (lcrl in float32, lcrl with ``--agent.precision bf16``, SB3, ...) in
one process so that all see the same machine load; the ratio of medians is reported at
each torch thread count (``--threads``, set in the process for all). Target: lcrl at least
1.5x SB3 at 1 and at 2 threads (``headline.ratio_1thread`` and ``headline.ratio_2threads``:
lcrl's faster precision, named in ``headline.precision``; the float32 ratios are
``headline.ratio_1thread_fp32`` and ``headline.ratio_2threads_fp32``).

That bf16 updates still learn is checked on the same task: the ``fetch-reach`` preset
(10k steps) is trained in each precision for ``--learn-seeds`` seeds, and the final seen
success of each goes in the file (``headline.success_fp32`` and ``headline.success_bf16``,
means over seeds).

Writes ``benchmarks/results/speed_vs_sb3.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import matplotlib
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks.common import machine, save_figure, save_json, save_markdown
from benchmarks.protocol import check_like_for_like
from lcrl.algos.base import _cpu_bf16
from lcrl.nets import NetConfig
from train.configs.presets import PRESETS
from train.training.loop import Trainer

WARMUP = 1_000
BATCH = 256
HIDDEN = (256, 256)
TARGET = 1.5


#: The headline's ratios, kept per kind of machine (``by_machine``).
RATIO_KEYS = ("ratio_1thread", "ratio_2threads", "ratio_1thread_bf16", "ratio_2threads_bf16")


def machines_rows(table: dict[str, dict]) -> list[str]:
    """The latest ratios on each kind of machine, as Markdown."""
    rows = [
        "",
        "## Each kind of machine (the latest run on it)",
        "",
        "| machine | fp32, 1 thread | fp32, 2 threads | bf16, 1 thread | bf16, 2 threads "
        "| git, date |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for kind, r in table.items():
        cells = [f"{r[k]:.2f}x" if k in r else "-" for k in RATIO_KEYS]
        rows.append(f"| {kind} | {' | '.join(cells)} | {r.get('git')}, {r.get('date')} |")
    return rows


def time_lcrl(steps: int, seed: int, precision: str = "fp32") -> float:
    """Steps per second of lcrl's loop over ``steps`` steps after learning starts, its
    updates in ``precision``."""
    base = PRESETS["fetch-reach"][1]
    out = Path(tempfile.mkdtemp(prefix="lcrl-speed-"))
    cfg = dataclasses.replace(
        base,
        out=str(out),
        total_steps=WARMUP + steps,
        learning_starts=WARMUP,
        batch_size=BATCH,
        collect=dataclasses.replace(base.collect, envs=1),  # one environment, as SB3's
        updates_per_step=1.0,
        progress=False,
        tensorboard=False,
        seed=seed,
        torch_threads=torch.get_num_threads(),  # the count main() set, for both libraries
    )
    cfg.agent = dataclasses.replace(
        cfg.agent, net=NetConfig(hidden=HIDDEN), seed=seed, precision=precision
    )
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


def learn(seed: int, precision: str) -> float:
    """Final seen success of the ``fetch-reach`` preset trained with ``seed`` in
    ``precision`` (its own evaluation, 50 episodes)."""
    base = PRESETS["fetch-reach"][1]
    out = Path(tempfile.mkdtemp(prefix="lcrl-speed-learn-"))
    cfg = dataclasses.replace(
        base,
        out=str(out),
        progress=False,
        tensorboard=False,
        eval_every=0,
        seed=seed,
        torch_threads=torch.get_num_threads(),
    )
    cfg.agent = dataclasses.replace(cfg.agent, seed=seed, precision=precision)
    results = Trainer(cfg).run()
    shutil.rmtree(out, ignore_errors=True)
    return float(results["all"]["success"])


#: The precision each timed library trains in (SB3 has float32 only).
PRECISIONS = {"lcrl": "fp32", "lcrl-bf16": "bf16", "sb3": "fp32"}
LIBRARIES = {
    "lcrl": lambda steps, seed: time_lcrl(steps, seed, PRECISIONS["lcrl"]),
    "lcrl-bf16": lambda steps, seed: time_lcrl(steps, seed, PRECISIONS["lcrl-bf16"]),
    "sb3": lambda steps, seed: time_sb3(steps, seed),
}


def timed_libraries(bf16: bool) -> dict[str, Callable[[int, int], float]]:
    """The libraries timed: lcrl in bfloat16 too where the CPU multiplies bfloat16 natively
    (elsewhere autocast emulates it, slower than float32, and it is left out)."""
    return {k: f for k, f in LIBRARIES.items() if bf16 or PRECISIONS[k] != "bf16"}


def like_for_like_headline(ratios: dict[str, dict[str, float]]) -> dict[str, object]:
    """The headline: lcrl against SB3 at the same precision, float32 (SB3 has no other),
    per thread count (``ratio_1thread``, ``ratio_2threads``); bfloat16 beside it where it
    was timed."""
    check_like_for_like({"precision": PRECISIONS["lcrl"]}, {"precision": PRECISIONS["sb3"]})

    def key(n: str) -> str:
        return f"ratio_{n}thread{'s' if int(n) > 1 else ''}"

    headline: dict[str, object] = {key(n): round(r["lcrl"], 3) for n, r in ratios.items()}
    headline["precision"] = "fp32"
    headline.update(
        {f"{key(n)}_bf16": round(r["lcrl-bf16"], 3) for n, r in ratios.items() if "lcrl-bf16" in r}
    )
    return headline


def paired_ratios(rates: dict[str, dict[str, list[float]]]) -> dict[str, list[float]]:
    """Per thread count, lcrl's float32 rate over SB3's in each round (the two ran next to
    each other in time, so each ratio saw about the same machine load)."""
    return {
        n: [round(a / b, 3) for a, b in zip(per["lcrl"], per["sb3"], strict=True)]
        for n, per in rates.items()
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=1_500, help="timed steps per round")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument(
        "--learn-seeds", type=int, default=3, help="seeds of the learning check per precision"
    )
    parser.add_argument("--note", default="", help="what changed since the file's last figures")
    args = parser.parse_args(argv)
    info = machine()
    bf16 = _cpu_bf16()
    libraries = timed_libraries(bf16)
    if not bf16:
        print("this CPU has no bfloat16 instructions: lcrl-bf16 is not timed", flush=True)
    rates: dict[str, dict[str, list[float]]] = {}
    for n in args.threads:
        torch.set_num_threads(n)
        rates[str(n)] = {name: [] for name in libraries}
        for r in range(args.rounds):
            for name, fn in libraries.items():
                rate = fn(args.steps, r)
                rates[str(n)][name].append(rate)
                print(f"{n} thread(s), round {r} {name}: {rate:.1f} steps/s", flush=True)
    med = {n: {k: statistics.median(v) for k, v in per.items()} for n, per in rates.items()}

    ratios = {
        n: {lib: m[lib] / m["sb3"] for lib in libraries if lib != "sb3"} for n, m in med.items()
    }
    headline = like_for_like_headline(ratios)
    torch.set_num_threads(max(args.threads))
    success: dict[str, list[float]] = {"fp32": [], **({"bf16": []} if bf16 else {})}
    for seed in range(args.learn_seeds):
        for p in success:
            success[p].append(learn(seed, p))
            print(f"fetch-reach seed {seed} {p}: success {success[p][-1]:.2f}", flush=True)
    for p, v in success.items():
        if v:
            headline[f"success_{p}"] = round(statistics.mean(v), 3)
    reached = all(r["lcrl"] >= TARGET for r in ratios.values())
    rows = ["| torch threads | library | steps/s per round | median |", "|---:|---|---|---:|"]
    for n, per in rates.items():
        for k, v in per.items():
            rows.append(f"| {n} | {k} | {', '.join(f'{x:.1f}' for x in v)} | {med[n][k]:.1f} |")
    paired = paired_ratios(rates)
    rows += [
        "",
        "| torch threads | lcrl (fp32) / SB3 | lcrl bf16 / SB3 | fp32 ratio of each round |",
        "|---:|---:|---:|---|",
    ]
    for n, r in ratios.items():
        half = f"{r['lcrl-bf16']:.2f}x" if "lcrl-bf16" in r else "not timed (no bf16 on this CPU)"
        rows.append(
            f"| {n} | {r['lcrl']:.2f}x | {half} | {', '.join(f'{x:.2f}' for x in paired[n])} |"
        )
    rows += [
        "",
        "Headline: lcrl in float32 against SB3 in float32 (like for like); bfloat16 "
        "(`--agent.precision bf16`, which SB3 has no option for) is reported beside it.",
        "",
        f"Target: at least {TARGET}x at every thread count, float32 against float32: "
        f"**{'reached' if reached else 'NOT reached'}**.",
        "",
        f"Setting: FetchReach-v4, SAC, HER future k=4, hidden {HIDDEN}, batch {BATCH}, 1 update "
        f"per step, {WARMUP} random steps first, {args.steps} timed steps per round; the "
        "libraries alternate in one process, alone on the machine. `lcrl-bf16` runs its "
        "updates under bfloat16 autocast (weights, optimiser state and losses in float32); "
        "SB3 has no such option.",
    ]
    if args.learn_seeds:
        rows += [
            "",
            f"Learning check, the `fetch-reach` preset (10k steps), final seen success over "
            f"seeds {list(range(args.learn_seeds))}:",
            "",
            "| precision | success per seed | mean |",
            "|---|---|---:|",
            *(
                f"| {p} | {', '.join(f'{x:.2f}' for x in v)} | {statistics.mean(v):.2f} |"
                for p, v in success.items()
            ),
        ]
    if args.note:
        rows += ["", "## What changed in this measurement", "", args.note]
    path = save_json(
        "speed_vs_sb3",
        {
            "headline": headline,
            "target": f"every ratio >= {TARGET}",
            "reached": reached,
            "machine": info,
            "rates": rates,
            "median": med,
            "ratios": ratios,
            "round_ratios": paired,
            **({"note": args.note} if args.note else {}),
            "learning_check": {"preset": "fetch-reach", "success": success},
            "steps": args.steps,
            "rounds": args.rounds,
        },
        by_machine_keys=RATIO_KEYS,
    )
    rows += machines_rows(json.loads(path.read_text())["by_machine"])
    table = "\n".join(rows)
    print(table)
    save_markdown("speed_vs_sb3", "Training speed: lcrl vs Stable-Baselines3", table, info)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    width = 0.27
    colours = {"lcrl": "tab:blue", "lcrl-bf16": "tab:cyan", "sb3": "tab:grey"}
    for j, lib in enumerate(libraries):
        xs = [i + (j - 1) * width for i in range(len(rates))]
        ax.bar(xs, [med[n][lib] for n in rates], width, label=lib, color=colours[lib])
        for x, n in zip(xs, rates, strict=True):
            ax.scatter([x] * len(rates[n][lib]), rates[n][lib], color="black", s=10, zorder=3)
    ticks = [
        f"{n} thread(s)\n" + " / ".join(f"{r:.2f}x" for r in ratios[n].values()) for n in rates
    ]
    ax.set_xticks(range(len(rates)), ticks)
    ax.set_ylabel("environment steps / s (training)")
    ax.set_title("FetchReach-v4 SAC+HER: lcrl against SB3")
    ax.legend()
    fig.subplots_adjust(bottom=0.3)
    save_figure("speed_vs_sb3", fig, info, rect=None)
    print("saved benchmarks/results/speed_vs_sb3.{json,md,png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

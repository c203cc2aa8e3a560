"""Steps per second of the 2D tabletop on one CPU core.

Run from the repository root::

    python benchmarks/env_speed.py

Measures, pinned to one core, the median over several repeats of environment steps per
second with random actions (a pre-drawn pool from the action space, so that the time of
drawing them is not counted; one row also draws each action with
``action_space.sample()`` to show that cost), resetting at episode ends (every 50
steps: the registered ``TimeLimit``, or by hand for the raw environment). Writes
``benchmarks/results/env_speed.{json,md,png}``.

Targets: 20,000 steps/s without images and 2,000 with images, for
``gymnasium.make("lcrl/Tabletop2D-v0")`` (wrappers included).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the gymnasium ids)
from benchmarks.common import RESULTS_DIR, save_json
from envs.tabletop2d import Tabletop2DEnv

TARGET_STATE = 20_000
TARGET_IMAGE = 2_000
EPISODE_STEPS = 50
ACTION_POOL = 4096


@dataclass
class Config:
    """One benchmarked setting."""

    name: str
    make: Callable[[], gym.Env]
    image: bool
    sample_each_step: bool = False
    manual_reset: bool = False  # raw env: reset every EPISODE_STEPS by hand


@dataclass
class Result:
    """Measured speed of one setting."""

    name: str
    image: bool
    target: int
    median_steps_per_s: float
    min_steps_per_s: float
    max_steps_per_s: float
    repeats: list[float]
    steps_per_repeat: int
    meets_target: bool


def configs() -> list[Config]:
    """The settings to measure, in report order."""
    return [
        Config("raw env, continuous", lambda: Tabletop2DEnv(), False, manual_reset=True),
        Config(
            "raw env, discrete (8 directions)",
            lambda: Tabletop2DEnv(action_type="discrete", num_directions=8),
            False,
            manual_reset=True,
        ),
        Config("gym.make Tabletop2D-v0", lambda: gym.make("lcrl/Tabletop2D-v0"), False),
        Config(
            "gym.make Tabletop2D-v0, disable_env_checker",
            lambda: gym.make("lcrl/Tabletop2D-v0", disable_env_checker=True),
            False,
        ),
        Config(
            "gym.make Tabletop2DDiscrete-v0",
            lambda: gym.make("lcrl/Tabletop2DDiscrete-v0"),
            False,
        ),
        Config(
            "gym.make Tabletop2D-v0 + action_space.sample()",
            lambda: gym.make("lcrl/Tabletop2D-v0"),
            False,
            sample_each_step=True,
        ),
        Config(
            "raw env, image=True (64 px)",
            lambda: Tabletop2DEnv(image=True),
            True,
            manual_reset=True,
        ),
        Config(
            "gym.make Tabletop2D-v0, image=True (64 px)",
            lambda: gym.make("lcrl/Tabletop2D-v0", image=True),
            True,
        ),
        Config(
            "gym.make Tabletop2D-v0, image=True, disable_env_checker",
            lambda: gym.make("lcrl/Tabletop2D-v0", image=True, disable_env_checker=True),
            True,
        ),
    ]


def run_once(config: Config, steps: int, seed: int) -> float:
    """Steps per second of one timed run (after a short warm-up)."""
    env = config.make()
    env.action_space.seed(seed)
    pool = [env.action_space.sample() for _ in range(ACTION_POOL)]
    sample = env.action_space.sample
    env.reset(seed=seed)
    for i in range(200):  # warm-up (also passes the env checker's first-call checks)
        env.step(pool[i])
    env.reset(seed=seed)
    mask = ACTION_POOL - 1
    t = 0
    start = time.perf_counter()
    if config.manual_reset:
        for i in range(steps):
            env.step(pool[i & mask])
            t += 1
            if t == EPISODE_STEPS:
                env.reset()
                t = 0
    elif config.sample_each_step:
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(sample())
            if terminated or truncated:
                env.reset()
    else:
        for i in range(steps):
            _, _, terminated, truncated, _ = env.step(pool[i & mask])
            if terminated or truncated:
                env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed


def pin_to_one_core() -> str:
    """Pin this process to one CPU core (Linux); returns a description."""
    if hasattr(os, "sched_setaffinity"):
        allowed = sorted(os.sched_getaffinity(0))
        core = 0 if 0 in allowed else allowed[0]
        os.sched_setaffinity(0, {core})
        return f"pinned to core {core}"
    return "not pinned (os.sched_setaffinity unavailable)"


def interpreter() -> str:
    """The Python executable as typed (relative to the working directory when inside it)."""
    exe = Path(sys.executable)
    try:
        return str(exe.relative_to(Path.cwd()))
    except ValueError:
        return "python"


def machine_info(pinning: str) -> dict[str, Any]:
    """Platform, CPU and library versions."""
    from train.runtime.machine import cpu_name

    cpu = cpu_name()
    return {
        "platform": platform.platform(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "pinning": pinning,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "gymnasium": gym.__version__,
    }


def write_markdown(path: Path, results: list[Result], meta: dict[str, Any]) -> None:
    """The table plus how it was made."""
    m = meta["machine"]
    lines = [
        "# 2D tabletop environment speed",
        "",
        f"Median of {meta['repeats']} repeats, one CPU core, random actions, "
        f"resets every {EPISODE_STEPS} steps.",
        "",
        "| setting | steps/s (median) | min | max | target | meets |",
        "|---|---:|---:|---:|---:|:---:|",
    ]
    for r in results:
        lines.append(
            f"| {r.name} | {r.median_steps_per_s:,.0f} | {r.min_steps_per_s:,.0f} | "
            f"{r.max_steps_per_s:,.0f} | {r.target:,} | {'yes' if r.meets_target else 'NO'} |"
        )
    lines += [
        "",
        "Actions come from a pool of 4096 drawn beforehand with `action_space.sample()`, "
        "except in the `+ action_space.sample()` row, which draws one per step.",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Date: {meta['date']}",
        "",
        "Machine:",
        "",
    ]
    lines += [f"- {k}: {v}" for k, v in m.items()]
    path.write_text("\n".join(lines) + "\n")


def write_plot(path: Path, results: list[Result], meta: dict[str, Any]) -> None:
    """Bar chart with the two targets as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 6.2))
    ys = np.arange(len(results))[::-1]
    colours = ["#d9822b" if r.image else "#3b75af" for r in results]
    speeds = [r.median_steps_per_s for r in results]
    ax.barh(ys, speeds, color=colours)
    for y, r in zip(ys, results, strict=True):
        ax.text(r.median_steps_per_s * 1.05, y, f"{r.median_steps_per_s:,.0f}", va="center")
        ax.vlines(r.target, y - 0.42, y + 0.42, colors="k", linestyles="--", linewidth=1.2)
    ax.set_yticks(ys, [r.name for r in results])
    ax.set_xscale("log")
    ax.set_xlim(500, max(speeds) * 3)
    ax.set_xlabel("steps per second (log scale; one core; median of repeats)")
    ax.set_title("lcrl 2D tabletop: environment steps per second")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax.legend(
        handles=[
            Patch(color="#3b75af", label="state observations"),
            Patch(color="#d9822b", label="with image observations"),
            Line2D([], [], color="k", linestyle="--", label="target (20k / 2k steps/s)"),
        ],
        loc="upper center",
        bbox_to_anchor=(0.4, -0.12),
        ncol=3,
        frameon=False,
    )
    m = meta["machine"]
    footer = (
        f"$ {meta['command']}    ({meta['date']})\n"
        f"{m['platform']}; {m['cpu']}; {m['cpu_count']} CPUs, {m['pinning']}; "
        f"Python {m['python']}, numpy {m['numpy']}, OpenCV {m['opencv']}, "
        f"gymnasium {m['gymnasium']}"
    )
    fig.text(0.01, 0.01, footer, fontsize=7, family="monospace", va="bottom")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table and write the result files."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=100_000, help="steps per repeat (state)")
    parser.add_argument(
        "--image-steps", type=int, default=20_000, help="steps per repeat (with images)"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)

    pinning = pin_to_one_core()
    command = " ".join([interpreter(), *sys.argv]) if argv is None else "env_speed.main()"
    meta = {
        "command": command,
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "repeats": args.repeats,
        "machine": machine_info(pinning),
    }
    results = []
    print(f"{'setting':58s} {'median steps/s':>15s} {'target':>8s}")
    for config in configs():
        steps = args.image_steps if config.image else args.steps
        target = TARGET_IMAGE if config.image else TARGET_STATE
        speeds = [run_once(config, steps, seed=r) for r in range(args.repeats)]
        median = statistics.median(speeds)
        result = Result(
            name=config.name,
            image=config.image,
            target=target,
            median_steps_per_s=median,
            min_steps_per_s=min(speeds),
            max_steps_per_s=max(speeds),
            repeats=speeds,
            steps_per_repeat=steps,
            meets_target=median >= target,
        )
        results.append(result)
        flag = "" if result.meets_target else "  BELOW TARGET"
        print(f"{config.name:58s} {median:15,.0f} {target:8,}{flag}")

    args.out_dir.mkdir(parents=True, exist_ok=True)
    head = {r.name: round(r.median_steps_per_s) for r in results}
    head["targets_met"] = f"{sum(r.meets_target for r in results)} of {len(results)}"
    payload = {**meta, "headline": head, "results": [asdict(r) for r in results]}
    if args.out_dir.resolve() == RESULTS_DIR.resolve():
        save_json("env_speed", payload)
    else:
        (args.out_dir / "env_speed.json").write_text(json.dumps(payload, indent=2) + "\n")
    write_markdown(args.out_dir / "env_speed.md", results, meta)
    write_plot(args.out_dir / "env_speed.png", results, meta)
    print(f"wrote {args.out_dir}/env_speed.{{json,md,png}}")
    return 0 if all(r.meets_target for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())

"""Robosuite tabletop speed: lcrl's env against robosuite's own Lift task, side by side.

Run from the repository root (needs ``pip install -e '.[robot]'``)::

    python benchmarks/robosuite_speed.py            # 5 alternating rounds, about 3 minutes

Configurations (all a Panda under robosuite's ``OSC_POSITION`` controller at 20 Hz, images
from the ``agentview`` camera at 84 x 84, offscreen through EGL):

(a) robosuite's own path: ``robosuite.make("Lift", robots="Panda", ...,
    has_renderer=False, has_offscreen_renderer=True, use_camera_obs=True,
    camera_names="agentview", camera_heights=84, camera_widths=84, hard_reset=False)``;
    resets are also timed with robosuite's default ``hard_reset=True`` (the model, the
    simulation and the renderer are rebuilt at every reset), and steps without a camera
    (``has_offscreen_renderer=False, use_camera_obs=False``);
(b) ``RobosuiteTabletopEnv(image=True, image_size=84)`` with its defaults (controller
    torques every 5 physics steps, simple arm shapes, no shadows, reflections or skybox),
    and without images (``image=False``);
(c) ``RobosuiteTabletopEnv(image=True, image_size=84, fancy_render=True,
    detailed_robot=True, controller_period=1)``: robosuite's physics and visuals, drawn by
    lcrl's renderer.

Every environment lives in a process of its own, which builds it once and then times what
the main process asks for, so that the environments share no OpenGL state: robosuite's
offscreen renderer makes its context current only when it is created, so in one thread
with other contexts (another env's, or the one a hard reset creates) it draws into
whichever is current, which corrupts frames and makes rendering look faster than it is.
Steps are random actions (the same pre-drawn pool for every configuration) with the clock
stopped while an episode is reset every 100 steps; resets are timed on their own, each
after one step. Python's garbage collector is off while timing. Every camera frame is
checked (not blank; an episode's first frame not identical to the previous episode's).
Every round times every configuration once (the order reversed on odd rounds), so that
all see the same machine load; the table gives the per-round values, their medians, and
the per-round and median ratios. Targets: (b) at least 3x (a) steps/s with 84 x 84 images,
and (b) at least 20 resets/s.

Writes ``benchmarks/results/robosuite_speed.{json,md,png}``.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported (by robosuite)

import argparse
import gc
import multiprocessing as mp
import statistics
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from envs.robosuite_tabletop import RobosuiteTabletopEnv, _quiet_robosuite

SIZE = 84
EPISODE = 100  # steps between two (untimed) resets while timing steps
TARGET_STEP_RATIO = 3.0
TARGET_RESETS = 20.0
POOL = 1024
RS_IMAGE = "agentview_image"


@dataclass
class Measure:
    """One timed quantity: ``what`` (steps or resets) of one environment."""

    key: str
    label: str
    what: str  # "steps" or "resets"
    env: str  # key into the environment table


def _osc_config() -> dict[str, Any]:
    from robosuite.controllers import load_part_controller_config
    from robosuite.controllers.composite.composite_controller_factory import (
        refactor_composite_controller_config,
    )

    part = load_part_controller_config(default_controller="OSC_POSITION")
    return refactor_composite_controller_config(part, "Panda", ["right"])


def make_robosuite(camera: bool, hard_reset: bool) -> Any:
    """robosuite's Lift with the Panda under OSC_POSITION, with or without the camera."""
    with _quiet_robosuite():
        import robosuite

        return robosuite.make(
            "Lift",
            robots="Panda",
            controller_configs=_osc_config(),
            has_renderer=False,
            has_offscreen_renderer=camera,
            use_camera_obs=camera,
            camera_names="agentview",
            camera_heights=SIZE,
            camera_widths=SIZE,
            hard_reset=hard_reset,
        )


class Runner:
    """Steps and resets one environment, hiding the API differences.

    With a camera it also checks the frames: ``blank`` counts frames without contrast and
    ``unchanged`` first frames of an episode identical to the previous episode's (every
    reset draws a new layout), either of which would mean a frame was not rendered. (Frames
    of consecutive steps can be identical: random actions may take the arm out of view.)
    """

    def __init__(self, env: Any, robosuite_api: bool, image_key: str | None) -> None:
        self.env = env
        self.robosuite_api = robosuite_api
        self.image_key = image_key
        self.t = 0
        self.seed = 0
        self.frames = self.blank = self.unchanged = 0
        self._last_reset: np.ndarray | None = None

    def _check(self, obs: dict[str, Any], reset: bool) -> None:
        if self.image_key is None:
            return
        image = obs[self.image_key]
        self.frames += 1
        self.blank += int(image.std() < 2.0)
        if reset:
            last = self._last_reset
            self.unchanged += int(last is not None and np.array_equal(image, last))
            self._last_reset = image

    def reset(self) -> None:
        self.t = 0
        self.seed += 1
        if self.robosuite_api:
            with _quiet_robosuite():
                obs = self.env.reset()
        else:
            obs, _ = self.env.reset(seed=self.seed)
        self._check(obs, reset=True)

    def step(self, action: np.ndarray) -> None:
        obs = self.env.step(action)[0]
        self._check(obs, reset=False)
        self.t += 1

    def close(self) -> None:
        self.env.close()


def time_steps(runner: Runner, pool: np.ndarray, seconds: float, min_steps: int) -> float:
    """Steps per second over at least ``seconds`` and ``min_steps`` (resets not counted)."""
    runner.reset()
    done, elapsed, k = 0, 0.0, 0
    while done < min_steps or elapsed < seconds:
        if runner.t >= EPISODE:
            runner.reset()
        n = min(EPISODE - runner.t, 10)
        start = time.perf_counter()
        for _ in range(n):
            runner.step(pool[k % POOL])
            k += 1
        elapsed += time.perf_counter() - start
        done += n
    return done / elapsed


def time_resets(runner: Runner, pool: np.ndarray, seconds: float, min_resets: int) -> float:
    """Resets per second over at least ``seconds`` and ``min_resets``, each after a step."""
    done, elapsed = 0, 0.0
    while done < min_resets or elapsed < seconds:
        runner.step(pool[done % POOL])  # leave the initial state, as an episode would
        start = time.perf_counter()
        runner.reset()
        elapsed += time.perf_counter() - start
        done += 1
    return done / elapsed


def load_average() -> float:
    """The 1-minute load average (``uptime``)."""
    return float(os.getloadavg()[0])


def uptime() -> str:
    """The output of ``uptime``, or the load averages where it is missing."""
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def gl_renderer(env: RobosuiteTabletopEnv) -> str:
    """The OpenGL renderer string of an env's offscreen context (e.g. llvmpipe)."""
    try:
        from OpenGL import GL

        env._renderer._gl_context.make_current()
        return GL.glGetString(GL.GL_RENDERER).decode()
    except Exception:  # only informative
        return "unknown"


MEASURES = [
    Measure("a_steps", "(a) robosuite Lift, camera 84", "steps", "a"),
    Measure("b_steps", "(b) lcrl default, image 84", "steps", "b"),
    Measure("c_steps", "(c) lcrl robosuite-equivalent, image 84", "steps", "c"),
    Measure("a_steps_nocam", "(a) robosuite Lift, no camera", "steps", "a_nocam"),
    Measure("b_steps_nocam", "(b) lcrl default, no image", "steps", "b_nocam"),
    Measure("a_resets_hard", "(a) robosuite Lift, camera, hard_reset=True", "resets", "a_hard"),
    Measure("a_resets_soft", "(a) robosuite Lift, camera, hard_reset=False", "resets", "a"),
    Measure("b_resets", "(b) lcrl default, image 84", "resets", "b"),
    Measure("c_resets", "(c) lcrl robosuite-equivalent, image 84", "resets", "c"),
]
RATIOS = [
    ("b_steps", "a_steps", "steps/s with 84 px images: (b) / (a)", TARGET_STEP_RATIO),
    ("c_steps", "a_steps", "steps/s with 84 px images: (c) / (a)", None),
    ("b_steps_nocam", "a_steps_nocam", "steps/s without images: (b) / (a)", None),
    ("b_resets", "a_resets_soft", "resets/s: (b) / (a) soft", None),
    ("b_resets", "a_resets_hard", "resets/s: (b) / (a) hard", None),
]


def make_runner(key: str) -> Runner:
    """Build one benchmarked environment (construction is not timed)."""
    makers: dict[str, Callable[[], Runner]] = {
        "a": lambda: Runner(make_robosuite(camera=True, hard_reset=False), True, RS_IMAGE),
        "a_hard": lambda: Runner(make_robosuite(camera=True, hard_reset=True), True, RS_IMAGE),
        "a_nocam": lambda: Runner(make_robosuite(camera=False, hard_reset=False), True, None),
        "b": lambda: Runner(RobosuiteTabletopEnv(image=True, image_size=SIZE), False, "image"),
        "b_nocam": lambda: Runner(RobosuiteTabletopEnv(), False, None),
        "c": lambda: Runner(
            RobosuiteTabletopEnv(
                image=True,
                image_size=SIZE,
                fancy_render=True,
                detailed_robot=True,
                controller_period=1,
            ),
            False,
            "image",
        ),
    }
    return makers[key]()


def worker(key: str, conn: Connection) -> None:
    """Build environment ``key``, warm it up, then time what the main process asks for.

    Messages in: ``(what, seconds, minimum)`` or None to stop. Messages out: first
    ``("ready", gl_renderer)``, then ``(rate, frames, blank, unchanged)`` per request.
    """
    runner = make_runner(key)
    pool = np.random.default_rng(0).uniform(-1.0, 1.0, (POOL, 4))
    runner.reset()  # warm-up: first render, first reset
    for k in range(5):
        runner.step(pool[k])
    renderer = gl_renderer(runner.env) if isinstance(runner.env, RobosuiteTabletopEnv) else ""
    conn.send(("ready", renderer))
    while (request := conn.recv()) is not None:
        what, seconds, minimum = request
        before = (runner.frames, runner.blank, runner.unchanged)
        gc.collect()
        gc.disable()
        try:
            if what == "steps":
                rate = time_steps(runner, pool, seconds, minimum)
            else:
                rate = time_resets(runner, pool, seconds, minimum)
        finally:
            gc.enable()
        now = (runner.frames, runner.blank, runner.unchanged)
        conn.send((rate, *(x - y for x, y in zip(now, before, strict=True))))
    runner.close()
    conn.close()


def start_workers() -> tuple[dict[str, Connection], list[Any], str]:
    """One process per environment; returns their pipes, the processes and the GL renderer."""
    ctx = mp.get_context("spawn")  # fresh interpreters: no OpenGL or simulator state shared
    pipes: dict[str, Connection] = {}
    procs = []
    for key in dict.fromkeys(m.env for m in MEASURES):
        here, there = ctx.Pipe()
        proc = ctx.Process(target=worker, args=(key, there), daemon=True)
        proc.start()
        pipes[key] = here
        procs.append(proc)
    renderer = "unknown"
    for key, pipe in pipes.items():
        tag, gl = pipe.recv()
        assert tag == "ready", tag
        if key == "b":
            renderer = gl
    return pipes, procs, renderer


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the tables and write the result files."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds")
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="minimum timed seconds per steps measure"
    )
    parser.add_argument(
        "--reset-seconds", type=float, default=1.5, help="minimum timed seconds per resets measure"
    )
    parser.add_argument("--min-steps", type=int, default=30, help="minimum steps per measure")
    parser.add_argument("--min-resets", type=int, default=2, help="minimum resets per measure")
    args = parser.parse_args(argv)
    from benchmarks.common import machine, save_json, save_markdown

    info = machine()
    load_before = uptime()
    busy = load_average() > 1.5
    print(f"before timing: {load_before}")
    if busy:
        print("  the machine is busy (load above 1.5): absolute rates are low; ratios stay fair")
    t_start = time.perf_counter()
    pipes, procs, renderer = start_workers()

    rates: dict[str, list[float]] = {m.key: [] for m in MEASURES}
    suspect: list[str] = []  # measures with a frame that looks not rendered
    for r in range(args.rounds):
        order = MEASURES if r % 2 == 0 else MEASURES[::-1]
        for m in order:
            if m.what == "steps":
                request = ("steps", args.seconds, args.min_steps)
            else:
                request = ("resets", args.reset_seconds, args.min_resets)
            pipes[m.env].send(request)
            rate, frames, blank, unchanged = pipes[m.env].recv()
            rates[m.key].append(rate)
            if blank or unchanged:
                suspect.append(
                    f"round {r}, {m.label}, {m.what}: {blank} blank and {unchanged} unchanged "
                    f"frames of {frames}"
                )
            print(f"round {r} {m.label:48s} {rate:8.2f} {m.what}/s", flush=True)
    for pipe in pipes.values():
        pipe.send(None)
    for proc in procs:
        proc.join(timeout=30)
    load_after = uptime()
    wall = time.perf_counter() - t_start

    med = {k: statistics.median(v) for k, v in rates.items()}
    ratios: dict[str, dict[str, Any]] = {}
    for num, den, label, target in RATIOS:
        per_round = [x / y for x, y in zip(rates[num], rates[den], strict=True)]
        ratios[f"{num}/{den}"] = {
            "label": label,
            "per_round": per_round,
            "median": statistics.median(per_round),
            "ratio_of_medians": med[num] / med[den],
            "target": target,
        }
    step_ratio = ratios["b_steps/a_steps"]["median"]
    step_ok = step_ratio >= TARGET_STEP_RATIO
    reset_ok = med["b_resets"] >= TARGET_RESETS

    rows = [
        "| configuration | measure | per round | median |",
        "|---|---|---|---:|",
        *(
            f"| {m.label} | {m.what}/s | {', '.join(f'{x:.1f}' for x in rates[m.key])} | "
            f"{med[m.key]:.1f} |"
            for m in MEASURES
        ),
        "",
        "| ratio | per round | median of per-round | ratio of medians |",
        "|---|---|---:|---:|",
        *(
            f"| {v['label']} | {', '.join(f'{x:.2f}' for x in v['per_round'])} | "
            f"{v['median']:.2f}x | {v['ratio_of_medians']:.2f}x |"
            for v in ratios.values()
        ),
        "",
        f"Target (b) >= {TARGET_STEP_RATIO:g}x (a) steps/s at {SIZE} x {SIZE}: "
        f"**{step_ratio:.2f}x**, {'met' if step_ok else 'NOT met'}.",
        f"Target (b) >= {TARGET_RESETS:g} resets/s: **{med['b_resets']:.1f}/s**, "
        f"{'met' if reset_ok else 'NOT met'}.",
        "",
        f"Load before timing: `{load_before}`; after: `{load_after}`."
        + (
            " The machine was busy (load above 1.5, other processes on the cores): absolute "
            "rates are lower than on an idle machine; the alternating rounds keep the ratios "
            "fair."
            if busy
            else ""
        ),
        f"OpenGL renderer: {renderer}. Steps: random actions, a reset (untimed) every "
        f"{EPISODE} steps, at least {args.seconds:g} s per measure; resets: one step before "
        f"each, at least {args.reset_seconds:g} s per measure; garbage collection off while "
        f"timing. Whole run {wall:.0f} s.",
        "",
        "Each environment ran in a process of its own. Frame check (every camera frame "
        "blank or not, every episode's first frame against the previous episode's): "
        + ("all frames rendered." if not suspect else "SUSPECT: " + "; ".join(suspect)),
    ]
    table = "\n".join(rows)
    print(table)
    save_json(
        "robosuite_speed",
        {
            "headline": {
                "step_ratio": round(step_ratio, 2),
                "resets_per_s": round(med["b_resets"], 1),
            },
            "machine": info,
            "load_before": load_before,
            "load_after": load_after,
            "busy": busy,
            "gl_renderer": renderer,
            "image_size": SIZE,
            "rounds": args.rounds,
            "seconds_per_steps_measure": args.seconds,
            "seconds_per_resets_measure": args.reset_seconds,
            "suspect_frames": suspect,
            "measures": {
                m.key: {"label": m.label, "unit": f"{m.what}/s", "per_round": rates[m.key]}
                for m in MEASURES
            },
            "median": med,
            "ratios": ratios,
            "targets": {
                "step_ratio": TARGET_STEP_RATIO,
                "step_ratio_met": step_ok,
                "resets_per_s": TARGET_RESETS,
                "resets_met": reset_ok,
            },
            "wall_s": wall,
        },
    )
    save_markdown(
        "robosuite_speed", "Robosuite tabletop speed: lcrl env vs robosuite Lift", table, info
    )
    plot(rates, med, step_ratio, info)
    print("saved benchmarks/results/robosuite_speed.{json,md,png}")
    return 0


def plot(
    rates: dict[str, list[float]], med: dict[str, float], step_ratio: float, info: dict[str, Any]
) -> None:
    """Bar chart of the median steps/s and resets/s, with the per-round values as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.common import caption

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), gridspec_kw={"width_ratios": [5, 4]})
    colour = {"a": "tab:grey", "b": "tab:blue", "c": "tab:cyan"}
    for ax, what in zip(axes, ("steps", "resets"), strict=True):
        ms = [m for m in MEASURES if m.what == what]
        ys = np.arange(len(ms))[::-1]
        ax.barh(ys, [med[m.key] for m in ms], color=[colour[m.env[0]] for m in ms])
        for y, m in zip(ys, ms, strict=True):
            ax.scatter(rates[m.key], [y] * len(rates[m.key]), color="black", s=8, zorder=3)
            ax.text(max(rates[m.key]) * 1.15, y, f"{med[m.key]:.1f}", va="center", fontsize=8)
        ax.set_yticks(ys, [m.label for m in ms], fontsize=8)
        ax.set_xscale("log")
        ax.set_xlim(min(min(rates[m.key]) for m in ms) / 2, max(med[m.key] for m in ms) * 4)
        ax.set_xlabel(f"{what} per second (log scale)")
    axes[1].axvline(TARGET_RESETS, color="k", linestyle="--", linewidth=1)
    axes[0].set_title(f"env steps/s, 84 px: (b) = {step_ratio:.2f}x (a)", fontsize=10)
    axes[1].set_title(f"resets/s (target (b) >= {TARGET_RESETS:g})", fontsize=10)
    fig.suptitle("Panda under OSC_POSITION: lcrl RobosuiteTabletopEnv vs robosuite Lift")
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    caption(fig, info)
    fig.savefig(Path(__file__).resolve().parent / "results" / "robosuite_speed.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())

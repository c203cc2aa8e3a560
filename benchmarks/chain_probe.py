"""Where a camera policy's chains of instructions fail: the second instruction, probed apart.

    python -m benchmarks.chain_probe                     # the kept robosuite-camera model
    python -m benchmarks.chain_probe --model RUN --episodes 60 --seed 1

``lcrl eval MODEL --chain 2`` scores a chain as done when both instructions are; a low
figure does not say whether the first or the second fails, nor why. This probe runs each
layout (``--seed``: episode ``i`` starts from layout ``seed * 1000 + i``) three ways, the
policy acting on what it acts on in ``lcrl eval`` (its perception of the camera frames):

``fresh``
    the policy follows the episode's first instruction from the reset scene, as in
    ``lcrl eval``;
``after teacher``
    the env's scripted controller (the one that reads the scene, the chain teacher of
    ``lcrl distill --chain-teacher scripted``) follows the first instruction; where it
    succeeds the episode goes on in the same scene with a second instruction
    (``switch_in_place``, as ``lcrl eval --chain`` does), which the policy follows;
``teacher twice``
    the scripted controller follows both: how often the second instruction is feasible
    for a controller that can do it;
``reset initial``
    as ``after teacher``, but the policy reads the reset's observation as its
    ``initial`` one instead of the observation its instruction started from (what a
    first instruction shows it): whether the start of a later instruction is what it
    fails on. A policy trained without ``initial`` (``lcrl distill --no-initial``) acts
    the same both ways.

At every step the policy acts, the scripted controller's action for the same state is
recorded beside the policy's, and their squared distance (summed over the action's
dimensions, policy units) is averaged per family: the imitation error on the states the
policy meets from a reset and on those it meets after another instruction. Where a family's
training teacher was not the scripted controller (put and stack of ``robosuite-camera``
learned from SAC teachers on their first instruction), its first-instruction error is
against a controller the policy did not imitate there.

Writes ``benchmarks/results/chain-probe.{json,md,png}``. Headline: ``fresh_success``,
``second_success`` (policy's second instruction after the teacher's first),
``teacher_second_success``, ``fresh_action_error``, ``second_action_error``,
``second_success_reset_initial``.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from typing import Any

import numpy as np

from benchmarks.common import machine, new_figure, publish
from lcrl.statistics import wilson_interval

NAME = "chain-probe"
MODEL = "benchmarks/models/robosuite-camera"


class Probe:
    """Episodes of one loaded policy with the scripted controller beside it."""

    def __init__(self, model: str, threads: int) -> None:
        import torch

        from train.environments.tasks import ScriptedActor, find_language_wrapper
        from train.policies.loading import load_policy

        torch.set_num_threads(threads)
        self.policy = load_policy(model)
        self.env, self.task = self.policy.env, self.policy.task
        self.lang = find_language_wrapper(self.env)
        self.scripted = ScriptedActor(self.policy.cfg.env, self.task, 0.0, teacher=True)
        self.rng = np.random.default_rng(0)
        #: (arm, link, family) -> per-step squared action errors; successes
        self.errors: dict[tuple[str, int, str], list[float]] = defaultdict(list)
        self.success: dict[tuple[str, int, str], list[bool]] = defaultdict(list)

    def _instruction(
        self, arm: str, link: int, policy_acts: bool, obs: Any, first: Any = None
    ) -> tuple[Any, bool]:
        """Follow the running instruction to its end; the last observation and success.
        ``first``: the observation the policy reads as its ``initial`` one (default: the
        one the instruction starts from)."""
        env, task = self.env, self.task
        first = obs if first is None else first
        goal = np.asarray([task.goal(obs, env)])
        family = self.lang.meaning.family
        success = False
        while True:
            label = self.scripted.act(env, self.rng)
            if policy_acts:
                mine = task.storage_obs(obs, first)
                batch = {k: v[None] for k, v in mine.items()}
                action = self.policy.agent.act(batch, goal, deterministic=True)[0]
                self.errors[(arm, link, family)].append(float(np.sum((action - label) ** 2)))
            else:
                action = label
            obs, _, terminated, truncated, info = env.step(task.scale_action(action))
            success = success or bool(info.get("is_success", False))
            if terminated or truncated:
                self.success[(arm, link, family)].append(success)
                return obs, success

    def episode(self, seed: int) -> None:
        from train.environments.tasks import switch_in_place

        for arm in ("fresh", "after teacher", "teacher twice", "reset initial"):
            obs, _ = self.env.reset(seed=seed)
            reset = obs
            self.scripted.reset()
            obs, done = self._instruction(arm, 0, arm == "fresh", obs)
            if arm == "fresh" or not done:
                continue
            following = switch_in_place(self.env, obs)
            if following is not None:
                policy_acts = arm in ("after teacher", "reset initial")
                first = reset if arm == "reset initial" else None
                self._instruction(arm, 1, policy_acts, following, first)

    def close(self) -> None:
        self.env.close()


def rate(values: list[bool]) -> dict[str, Any]:
    n, k = len(values), int(sum(values))
    low, high = wilson_interval(k, n) if n else (float("nan"), float("nan"))
    return {"success": k / n if n else float("nan"), "n": n, "ci": [low, high]}


def summary(probe: Probe, families: list[str]) -> dict[str, Any]:
    """Success and action error per (arm, instruction of the chain), pooled and per family."""
    out: dict[str, Any] = {}
    for arm, link in (
        ("fresh", 0),
        ("after teacher", 1),
        ("teacher twice", 1),
        ("reset initial", 1),
    ):
        fam_rows = {}
        for f in families:
            errs = probe.errors.get((arm, link, f), [])
            fam_rows[f] = {
                **rate(probe.success.get((arm, link, f), [])),
                "action_error": float(np.mean(errs)) if errs else None,
            }
        pooled_s = [s for f in families for s in probe.success.get((arm, link, f), [])]
        pooled_e = [e for f in families for e in probe.errors.get((arm, link, f), [])]
        out[f"{arm} {link + 1}"] = {
            **rate(pooled_s),
            "action_error": float(np.mean(pooled_e)) if pooled_e else None,
            "families": fam_rows,
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=MODEL, help="a checkpoint or run (camera policy)")
    parser.add_argument("--episodes", type=int, default=60, help="layouts")
    parser.add_argument("--seed", type=int, default=1, help="layout seeds: seed * 1000 + i")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--name", default=NAME, help="the result's name (benchmarks/results/)")
    args = parser.parse_args(argv)

    from tqdm import tqdm

    probe = Probe(args.model, args.threads)
    try:
        for i in tqdm(range(args.episodes), desc="chain probe", unit="layout"):
            probe.episode(args.seed * 1000 + i)
    finally:
        probe.close()
    families = list(probe.policy.cfg.env.families)
    rows = summary(probe, families)
    fresh, second, teacher = rows["fresh 1"], rows["after teacher 2"], rows["teacher twice 2"]
    reset = rows["reset initial 2"]
    headline = {
        "fresh_success": fresh["success"],
        "second_success": second["success"],
        "teacher_second_success": teacher["success"],
        "fresh_action_error": fresh["action_error"],
        "second_action_error": second["action_error"],
        "second_success_reset_initial": reset["success"],
        "model": args.model,
        "seed": args.seed,
    }
    payload = {"headline": headline, "machine": machine(), "settings": vars(args), "rows": rows}

    def cell(r: dict[str, Any]) -> str:
        if not r["n"]:
            return "-"
        err = "" if r.get("action_error") is None else f", error {r['action_error']:.2f}"
        return f"{r['success']:.2f} [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}] of {r['n']}{err}"

    lines = [
        "| family | policy, first instruction | policy, second (teacher did the first) "
        "| teacher, second | policy, second, reading the reset as `initial` |",
        "|---|---|---|---|---|",
    ]
    for f in [*families, None]:
        pick = (lambda r: r) if f is None else (lambda r, f=f: r["families"][f])
        lines.append(
            f"| {f or '**all**'} | {cell(pick(fresh))} | {cell(pick(second))} "
            f"| {cell(pick(teacher))} | {cell(pick(reset))} |"
        )
    body = (
        f"`{args.model}` on {args.episodes} layouts (seeds {args.seed * 1000} on). Success "
        "with 95% Wilson intervals; error: the mean squared distance between the policy's "
        "action and the scripted controller's for the same state (policy units, summed over "
        "the action's dimensions), over the steps the policy acted; a family whose first "
        "instructions were taught by another teacher (put and stack of robosuite-camera) "
        "imitated another controller there. The last column: the same second instructions "
        "from the same scenes, the policy reading the reset's observation as the one its "
        "instruction started from (`initial`).\n\n" + "\n".join(lines)
    )
    fig, axes = new_figure(ncols=2, figsize=(9, 3.5))
    x = np.arange(len(families))
    for i, (r, label) in enumerate(((fresh, "first, from reset"), (second, "second, mid-scene"))):
        axes[0].bar(x + (i - 0.5) * 0.4, [r["families"][f]["success"] for f in families], 0.4,
                    label=label)  # fmt: skip
        errs = [r["families"][f]["action_error"] or 0.0 for f in families]
        axes[1].bar(x + (i - 0.5) * 0.4, errs, 0.4, label=label)
    for ax, what in zip(axes, ("policy success", "action error vs scripted"), strict=True):
        ax.set_xticks(x, families)
        ax.set(title=what)
    axes[0].legend(fontsize=8)
    publish(args.name, payload, "Chains of two: where the second instruction fails", body, fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

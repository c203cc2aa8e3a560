"""How a policy's failed push episodes fail: how far the named object got.

    python benchmarks/push_misses.py runs/bench/lher60/seed0/rule runs/bench/lher60/seed0/learned

Each run's policy (deterministic) follows its seen push instructions, one after another
from the evaluation's reset seeds (the first feasible layout of each), on the
privileged-state tabletop (``lang2d``). For every episode that fails, the furthest the
named object got along the instruction's direction, as a fraction of the rule captioner's
push distance, puts it in one bin: ``untouched`` (under 0.1: the pusher went to the object,
or not, but did not move it), ``short`` (0.1 to 1), ``drift`` (far enough along, but too
far sideways or pushed back). Also counted: the failures whose pusher came within the
distance of the rule captioner's ``reach`` (``reached``) and those that moved another
object by 2 cm or more (``other_moved``). A policy that goes to its object and stops there
fails ``untouched`` and ``reached``; one whose rewards come a step early fails ``short``.

With ``--captioner DIR`` (learned models over frames), the reward model also scores each
step of every episode against its instruction, at ``--threshold``, and the steps are
sorted by the rule's verdict: ``false_rewards`` are the steps it rewards where the rule does
not, binned like the failures by how far the object had got at that step (``untouched``
then also splits by whether the pusher was at the object); ``missed_rewards`` the steps the
rule rewards and it does not. A false reward in a state that lasts (an object left part of
the way) counts at every step it lasts, so the episodes are counted too: those with a
reward before the rule's first success, and those rewarded at that success.
``--stochastic`` samples the policy's actions, as training episodes do.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

BINS = ("untouched", "short", "drift")
UNTOUCHED = 0.1  # fraction of the push distance under which the object did not move
OTHER_MOVED = 0.02  # metres: another object was disturbed


def miss_bin(along: float) -> str:
    """The bin of a failed episode whose object got ``along`` (fraction of the push
    distance, its furthest along the direction) at best."""
    if along < UNTOUCHED:
        return "untouched"
    return "short" if along < 1.0 else "drift"


def summarise(episodes: Sequence[dict]) -> dict:
    """Success and the failures' bins (fractions of the failures) of ``episodes``, each
    ``{"success", "along", "reached", "other_moved"}``."""
    fails = [e for e in episodes if not e["success"]]
    n = len(fails)
    out = {
        "episodes": len(episodes),
        "success": (len(episodes) - n) / len(episodes) if episodes else float("nan"),
        "failures": n,
    }
    for b in BINS:
        out[b] = sum(miss_bin(e["along"]) == b for e in fails) / n if n else 0.0
    out["reached"] = sum(e["reached"] for e in fails) / n if n else 0.0
    out["other_moved"] = sum(e["other_moved"] for e in fails) / n if n else 0.0
    out["median_along"] = float(np.median([e["along"] for e in fails])) if n else float("nan")
    return out


def summarise_rewards(steps: Sequence[dict]) -> dict:
    """How the reward model's verdicts on ``steps`` (each ``{"rule", "learned", "along",
    "at_object"}``) agree with the rule's: counts, precision and recall, and the false
    rewards' bins (fractions of the false rewards)."""
    tp = sum(s["rule"] and s["learned"] for s in steps)
    fp = [s for s in steps if s["learned"] and not s["rule"]]
    fn = sum(s["rule"] and not s["learned"] for s in steps)
    out = {
        "steps": len(steps),
        "rule_rewards": tp + fn,
        "learned_rewards": tp + len(fp),
        "precision": tp / (tp + len(fp)) if tp + len(fp) else float("nan"),
        "recall": tp / (tp + fn) if tp + fn else float("nan"),
        "false_rewards": len(fp),
        "missed_rewards": fn,
    }
    n = len(fp)
    for b in BINS:
        out[f"false_{b}"] = sum(miss_bin(s["along"]) == b for s in fp) / n if n else 0.0
    out["false_untouched_at_object"] = (
        sum(miss_bin(s["along"]) == "untouched" and s["at_object"] for s in fp) / n if n else 0.0
    )
    return out


def episode_rewards(episodes: Sequence[dict]) -> dict:
    """The reward model's verdicts episode by episode (each episode's ``steps`` carry
    ``rule`` and ``learned``): in how many it rewarded a step before the rule's first
    success (``false_before_success``), and of the episodes that succeed, in how many it
    rewarded the first successful step itself (``hit_at_success``)."""
    false_before = successes = hits = 0
    for e in episodes:
        rule = [s["rule"] for s in e["steps"]]
        learned = [s["learned"] for s in e["steps"]]
        first = rule.index(True) if any(rule) else len(rule)
        false_before += any(learned[:first])
        if first < len(rule):
            successes += 1
            hits += learned[first]
    return {
        "episodes": len(episodes),
        "false_before_success": false_before,
        "successes": successes,
        "hit_at_success": hits,
    }


def episode_probs(
    models, text: str, first: dict, frames: list, proprio: list, start: int
) -> np.ndarray:
    """The reward model's probability that ``text`` is achieved at each recorded step,
    judged from the episode's first observation ``first`` (its image and the robot state,
    the observation's first ``start`` values) to each step's frame and robot state."""
    f0 = np.asarray(first["image"])
    p0 = np.asarray(first["observation"][:start], np.float32)
    n = len(frames)
    return models.score_matrix(
        [text], np.repeat(f0[None], n, 0), np.stack(frames),
        np.repeat(p0[None], n, 0), np.stack(proprio),
    )[:, 0]  # fmt: skip


def family_texts(task: Any, family: str, run: str | Path) -> list[str]:
    """The seen instructions of ``family`` a run was trained on."""
    from lcrl.errors import LcrlError

    texts = [t for t in task.table[: task.num_train] if t.split()[:1] == [family]]
    if not texts:
        raise LcrlError(f"{run} was trained on no {family} instruction")
    return texts


def start_episode(env: Any, wrapper: Any, texts: list[str], seed: int, i: int) -> tuple:
    """Episode ``i`` of an evaluation at ``seed``, on the instructions ``texts`` in turn:
    its instruction, first observation, the scene it starts from, the parsed instruction
    and the index of the object the instruction names."""
    from train.environments.tasks import reset_feasible
    from train.evaluation.eval_suite import episode_seed

    text = texts[i % len(texts)]
    obs, _ = reset_feasible(env, episode_seed(seed, i), text)
    s0 = wrapper.env.unwrapped.scene()
    ins = wrapper.captioner.parse(text)
    return text, obs, s0, ins, s0.index(*ins.obj)


def run_pushes(
    run: str | Path,
    episodes: int,
    seed: int = 0,
    captioner: str | Path | None = None,
    threshold: float = 0.9,
    stochastic: bool = False,
) -> list[dict]:
    """``episodes`` push episodes of ``run``'s policy on its seen push instructions (with
    ``captioner``, each episode's ``steps``: the rule's and the reward model's verdict)."""
    from captioner.rule import DIRECTION_VECTORS
    from train.environments.tasks import find_language_wrapper
    from train.policies.loading import load_policy

    models = None
    overrides = None
    if captioner is not None:
        from captioner.learned import LearnedCaptioner
        from train.environments.tasks import slot_layout_start

        models = LearnedCaptioner.load(captioner)
        overrides = {"extra": {"image": True, "image_size": int(models.frame_shape[0])}}
    policy = load_policy(run, env_overrides=overrides)
    agent, task, env = policy.agent, policy.task, policy.env
    wrapper = find_language_wrapper(env)
    if models is not None:
        start = int(slot_layout_start(wrapper))
    rule = wrapper.captioner
    texts = family_texts(task, "push", run)
    out = []
    for i in range(episodes):
        text, obs, s0, ins, k = start_episode(env, wrapper, texts, seed, i)
        vec = np.asarray(DIRECTION_VECTORS[ins.direction])
        near = float(s0.half_extents[k, :2].max()) + rule.thresholds.reach_margin
        goal = np.asarray([task.goal(obs, env)])
        first, best, reached, other = obs, -np.inf, False, 0.0
        frames, proprio, steps = [], [], []
        while True:
            o = {key: v[None] for key, v in task.storage_obs(obs, first).items()}
            action = agent.act(o, goal, deterministic=not stochastic)[0]
            obs, _, terminated, truncated, info = env.step(task.scale_action(action))
            s = wrapper.env.unwrapped.scene()
            d = s.positions[k, :2] - s0.positions[k, :2]
            along = float(d @ vec)
            best = max(best, along)
            at_object = bool(np.linalg.norm(s.gripper[:2] - s.positions[k, :2]) <= near)
            reached |= at_object
            if models is not None:
                frames.append(np.asarray(obs["image"]))
                proprio.append(np.asarray(obs["observation"][:start], np.float32))
                steps.append(
                    {
                        "rule": bool(rule.satisfied(ins, s0, s)),
                        "along": along / rule.thresholds.push_distance,
                        "at_object": at_object,
                        # the most another object has moved along the same direction
                        "other_along": float(
                            np.delete((s.positions[:, :2] - s0.positions[:, :2]) @ vec, k).max(
                                initial=-np.inf
                            )
                        )
                        / rule.thresholds.push_distance,
                        "lateral": float(abs(d[0] * vec[1] - d[1] * vec[0]))
                        / rule.thresholds.push_distance,
                    }
                )
            moved = np.linalg.norm(s.positions[:, :2] - s0.positions[:, :2], axis=-1)
            other = max(other, float(np.delete(moved, k).max(initial=0.0)))
            if terminated or truncated:
                break
        if models is not None:
            probs = episode_probs(models, text, first, frames, proprio, start)
            for st, p in zip(steps, probs, strict=True):
                st["prob"] = float(p)
                st["learned"] = bool(p >= threshold)
        out.append(
            {
                "instruction": text,
                "success": bool(info.get("is_success", False)),
                "along": best / rule.thresholds.push_distance,
                "reached": reached,
                "other_moved": other >= OTHER_MOVED,
                **({"steps": steps} if models is not None else {}),
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="lang2d run or checkpoint folders")
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed")
    parser.add_argument(
        "--captioner", default=None, help="learned models whose reward model scores each step"
    )
    parser.add_argument("--threshold", type=float, default=0.9, help="the reward model's")
    parser.add_argument(
        "--stochastic", action="store_true", help="sample actions, as training episodes do"
    )
    args = parser.parse_args(argv)
    from lcrl.errors import LcrlError

    for run in args.runs:
        try:
            episodes = run_pushes(
                run, args.episodes, args.seed, args.captioner, args.threshold, args.stochastic
            )
        except (LcrlError, OSError) as e:
            raise SystemExit(f"error: {e}") from None
        print(run, json.dumps(summarise(episodes)))
        if args.captioner is not None:
            steps = [st for e in episodes for st in e["steps"]]
            print(run, "rewards", json.dumps(summarise_rewards(steps)))
            print(run, "episodes", json.dumps(episode_rewards(episodes)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

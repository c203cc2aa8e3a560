"""How the learned reward model judges *reach* on a policy's own episodes, against the rule.

    python benchmarks/reach_rewards.py runs/bench/learned-s0-25k \\
        --captioner runs/bench/captioner-lang2d-sq --family push --episodes 30

A lang2d run's policy follows its seen instructions of one family (``--family``: push or
reach) with sampled actions, as training episodes act, on the frames the learned models
read. At every step the reward model scores "reach the <object>" for the object the
instruction names, and the rule captioner judges the same instruction. Reported per
threshold: the precision and recall of the reward model's reach verdicts against the
rule's, the recall split by whether the object moved that step (the pusher pushing it) or
stood still, and per band of the pusher's distance to the object's edge (centre distance
minus the object's half size): how often the rule and the reward model say reached there,
and the model's mean probability. The rule's reach ends ``reach_margin`` (2 cm) beyond the
object's edge (and holds wherever the pusher touches the object) and the pusher touches it
at its radius (1.5 cm), so a model that reads estimated positions (about 1 cm of error near
the pusher) is unsure whether a pusher in contact reaches; a high threshold then turns most
contact steps of a push into missed reach rewards.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

THRESHOLDS = (0.5, 0.7, 0.9)
#: Bands of the pusher's distance to the object's edge (metres).
BANDS = ((-1.0, 0.02), (0.02, 0.03), (0.03, 0.04), (0.04, 0.05), (0.05, 10.0))
MOVING = 0.002  # metres in one step: the object is being pushed


def summarise(steps: Sequence[dict], thresholds: Sequence[float] = THRESHOLDS) -> dict:
    """Precision / recall of the reward model's reach verdicts against the rule's, per
    threshold, and per band of the pusher's distance to the object's edge; ``steps`` each
    ``{"rule", "prob", "moving", "gap"}``."""
    rule = np.asarray([s["rule"] for s in steps], bool)
    prob = np.asarray([s["prob"] for s in steps], np.float64)
    moving = np.asarray([s["moving"] for s in steps], bool)
    gap = np.asarray([s["gap"] for s in steps], np.float64)

    def frac(a: np.ndarray, b: np.ndarray) -> float:
        return round(float((a & b).sum() / b.sum()), 3) if b.any() else float("nan")

    out: dict = {"steps": len(steps), "rule_reached": int(rule.sum()), "moving": int(moving.sum())}
    out["thresholds"] = {
        str(t): {
            "precision": frac(rule, prob >= t),
            "recall": frac(prob >= t, rule),
            "recall_moving": frac(prob >= t, rule & moving),
            "recall_still": frac(prob >= t, rule & ~moving),
        }
        for t in thresholds
    }
    bands = []
    for lo, hi in BANDS:
        sel = (gap >= lo) & (gap < hi)
        bands.append(
            {
                "gap_cm": [round(100 * max(lo, 0.0), 1), round(100 * min(hi, 1.0), 1)],
                "steps": int(sel.sum()),
                "rule": round(float(rule[sel].mean()), 3) if sel.any() else float("nan"),
                "mean_prob": round(float(prob[sel].mean()), 3) if sel.any() else float("nan"),
                **{
                    f"at_{t}": round(float((prob[sel] >= t).mean()), 3)
                    if sel.any()
                    else float("nan")
                    for t in thresholds
                },
            }
        )
    out["bands"] = bands
    return out


def run_episodes(
    run: str | Path, captioner: str | Path, family: str, episodes: int, seed: int = 7
) -> list[dict]:
    """Every step of ``episodes`` sampled-action episodes of ``run``'s policy on its seen
    ``family`` instructions: the rule's and the reward model's reach verdicts."""
    from benchmarks.push_misses import episode_probs, family_texts, start_episode
    from captioner.learned import LearnedCaptioner
    from lcrl.errors import LcrlError
    from train.environments.tasks import find_language_wrapper, slot_layout_start
    from train.policies.loading import load_policy

    models = LearnedCaptioner.load(captioner)
    if models.reward is None:
        raise LcrlError(f"{captioner} holds no reward model")
    overrides = {"extra": {"image": True, "image_size": int(models.frame_shape[0])}}
    policy = load_policy(run, env_overrides=overrides)
    agent, task, env = policy.agent, policy.task, policy.env
    wrapper = find_language_wrapper(env)
    start = int(slot_layout_start(wrapper))
    rule = wrapper.captioner
    texts = family_texts(task, family, run)
    steps: list[dict] = []
    for i in range(episodes):
        _, obs, s0, ins, k = start_episode(env, wrapper, texts, seed, i)
        reach = f"reach the {ins.obj[0]} {ins.obj[1]}"
        goal = np.asarray([task.goal(obs, env)])
        first, prev = obs, s0.positions[k, :2].copy()
        frames, proprio, ep = [], [], []
        while True:
            o = {key: v[None] for key, v in task.storage_obs(obs, first).items()}
            action = agent.act(o, goal, deterministic=False)[0]
            obs, _, terminated, truncated, _ = env.step(task.scale_action(action))
            s = wrapper.env.unwrapped.scene()
            frames.append(np.asarray(obs["image"]))
            proprio.append(np.asarray(obs["observation"][:start], np.float32))
            dist = float(np.linalg.norm(s.gripper[:2] - s.positions[k, :2]))
            ep.append(
                {
                    "rule": bool(rule.satisfied(reach, s0, s)),
                    "moving": bool(np.linalg.norm(s.positions[k, :2] - prev) > MOVING),
                    "gap": dist - float(s.half_extents[k, :2].max()),
                }
            )
            prev = s.positions[k, :2].copy()
            if terminated or truncated:
                break
        probs = episode_probs(models, reach, first, frames, proprio, start)
        for st, p in zip(ep, probs, strict=True):
            st["prob"] = float(p)
        steps += ep
    return steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="lang2d run or checkpoint folder")
    parser.add_argument("--captioner", required=True, help="learned models (reward model)")
    parser.add_argument("--family", default="push", choices=("push", "reach"))
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=7, help="evaluation seed")
    args = parser.parse_args(argv)
    from lcrl.errors import LcrlError

    try:
        steps = run_episodes(args.run, args.captioner, args.family, args.episodes, args.seed)
    except (LcrlError, OSError) as e:
        raise SystemExit(f"error: {e}") from None
    print(json.dumps(summarise(steps), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Building learners and tasks, evaluating policies, and loading them from checkpoints.

``evaluate`` runs deterministic episodes on every instruction set of a task (seen
instructions ``train``, held-out word combinations ``heldout``, unseen phrasings
``paraphrase``; state-goal tasks have one set) and reports success overall and per family.
It is the periodic evaluation of the training loops and runs on the engine of ``lcrl
eval`` (:func:`train.evaluation.eval_suite.run_evaluation`): the same seed gives the same episodes,
and so the same figures, in both. Evaluation episodes use fixed reset seeds, so two
checkpoints are compared on the same layouts and instructions.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl import algos
from lcrl.algos import Agent, Problem
from lcrl.checkpoint import Checkpoint, find_latest, load_checkpoint
from lcrl.errors import LcrlError
from train.configs.config import TrainConfig
from train.environments.simulators import env_spec
from train.environments.tasks import (
    Task,
    is_language,
    make_env,
    make_task,
    reset_feasible,
    task_texts,
)
from train.evaluation.eval_suite import EVAL_SEED_OFFSET, run_evaluation

__all__ = [
    "EVAL_SEED_OFFSET",
    "LoadedPolicy",
    "build_agent",
    "build_task",
    "describe_problem",
    "evaluate",
    "evaluate_tasks",
    "format_results",
    "load_single",
    "resolve_checkpoint",
    "run_episode",
]
#: Sub-envs stepped together by the training loop's evaluation on a fast simulator (the
#: figures do not depend on it; a slow simulator steps one env).
EVAL_ENVS = 8


def build_task(
    cfg: TrainConfig,
    env: gym.Env,
    ckpt: Checkpoint | None = None,
    table: tuple[list[str], int] | None = None,
    embeddings: np.ndarray | None = None,
) -> Task:
    """The task adapter; language tasks load the frozen text encoder and take the
    checkpoint's instruction table when given (or ``table``: the texts and how many of
    them are training instructions, e.g. a teacher's). With ``table`` and its
    ``embeddings`` (one row per text) no encoder is loaded: what a rollout worker does with
    its learner's table."""
    check_slots(cfg, env)
    if not is_language(cfg.env):
        task = make_task(cfg.env, env)
    elif embeddings is not None and table is not None:
        rows = {t: np.asarray(e, np.float32) for t, e in zip(table[0], embeddings, strict=True)}

        def lookup(texts: list[str]) -> np.ndarray:
            return np.stack([rows[t] for t in texts])

        task = make_task(cfg.env, env, lookup, table=list(table[0]), num_train=int(table[1]))
    else:
        from lcrl.text_encoder import FrozenTextEncoder

        encoder: Any = FrozenTextEncoder(cfg.text_encoder)
        if cfg.env.text_reader or cfg.env.canonical_reader:
            from train.environments.text_reading import reading_encoder

            encoder = reading_encoder(
                encoder, env, ckpt, seed=cfg.seed, canonical=cfg.env.canonical_reader
            )
        kwargs: dict[str, Any] = {}
        if ckpt is not None:
            from train.configs.run_meta import instruction_table

            texts, num_train = instruction_table(ckpt)
            kwargs = {"table": texts, "num_train": num_train}
        elif table is not None:
            kwargs = {"table": list(table[0]), "num_train": int(table[1])}
        task = make_task(cfg.env, env, encoder.encode, **kwargs)
        task.encoder = encoder
    if cfg.agent.perception_lr > 0:
        task.use_perception_frames(env)
    if cfg.agent.privileged_critic:
        task.use_privileged_critic(env)
    return task


def check_slots(cfg: TrainConfig, env: gym.Env) -> None:
    """Refuse ``agent.net.slots`` that do not match the env's object slots (the network
    would read the wrong values silently)."""
    slots = tuple(cfg.agent.net.slots)
    if not slots or cfg.env.image_obs:
        return
    from envs.features import slot_layout

    try:
        layout = slot_layout(env)[:3]
    except LcrlError:
        return  # the env does not describe its slots: the user's layout is taken as given
    if slots != layout:
        raise LcrlError(
            f"agent.net.slots is {slots} but this env's observation slots are {layout} "
            "(relative_positions and displacements widen each slot): pass "
            f"--agent.net.slots {' '.join(map(str, layout))}"
        )


def build_agent(
    algo: str, problem: Problem, cfg: TrainConfig, goal_embed: Any, env: gym.Env | None = None
) -> Agent:
    """The learner named ``algo`` for ``problem`` (:func:`lcrl.algos.build_agent`), with the
    options ``cfg.agent`` and its config from the field of ``cfg`` named after it. A problem
    whose frames go through perception fine-tuned with the losses
    (``agent.perception_lr``) gets the env's perception model attached.

    Raises:
        LcrlError: an unknown algorithm, or one that does not take ``problem``'s actions.
    """
    algo = algos.resolve_algo(algo, problem.discrete)
    algos.check_algo(algo, problem.discrete)
    agent = algos.build_agent(algo, problem, cfg.agent, goal_embed, getattr(cfg, algo))
    if problem.perceived:
        from lcrl.perception import PerceivedSlots
        from train.environments.perception import find_perception

        if algo != "sac":
            raise LcrlError(
                f"fine-tuning perception with the losses (agent.perception_lr) is done by sac, "
                f"not {algo}"
            )
        wrapper = find_perception(env) if env is not None else None
        if wrapper is None:
            raise LcrlError("fine-tuning perception needs the env's perception model")
        module = PerceivedSlots(
            wrapper.model, cfg.env.relative_positions, cfg.env.displacements
        )  # the env's own model: the frames it caches are read with the tuned weights
        agent.attach_perception(module, cfg.agent.perception_lr)
    return agent


def run_episode(
    agent: Agent,
    task: Task,
    env: gym.Env,
    seed: int,
    options: dict[str, Any] | None = None,
    goal_vector: np.ndarray | None = None,
    deterministic: bool = True,
    frames: list[np.ndarray] | None = None,
    feasible_tries: int = 0,
) -> dict[str, Any]:
    """One episode with the policy; returns success, length, return and the instruction.

    ``goal_vector`` replaces the task's goal by an already embedded goal (e.g. the text
    encoder's vector of a free-text instruction). ``frames``, when given, receives
    ``env.render()`` after the reset and after every step (an env made with
    ``render_mode="rgb_array"``). ``feasible_tries`` > 0 with an ``instruction`` option
    resets into the first layout (of ``seed``, then seeds derived from it) where the
    instruction is feasible (:func:`train.environments.tasks.reset_feasible`).
    """
    if feasible_tries > 0 and options and "instruction" in options:
        obs, info = reset_feasible(env, seed, options["instruction"], feasible_tries)
    else:
        obs, info = env.reset(seed=seed, options=options)
    if frames is not None:
        frames.append(env.render())
    first = obs
    goal = None if goal_vector is not None else np.asarray([task.goal(obs, env)])
    steps, ret, success = 0, 0.0, False
    while True:
        o = {k: v[None] for k, v in task.storage_obs(obs, first).items()}
        if goal_vector is not None:
            a = agent.act(o, goal_vector[None], deterministic=deterministic, embedded=True)[0]
        else:
            a = agent.act(o, goal, deterministic=deterministic)[0]
        obs, reward, terminated, truncated, info = env.step(task.scale_action(a))
        if frames is not None:
            frames.append(env.render())
        steps += 1
        ret += float(reward)
        success = success or bool(info.get("is_success", False))
        if terminated or truncated:
            break
    out = {"success": bool(info.get("is_success", False)), "steps": steps, "return": ret}
    out.update(task.outcome(env))
    return out


def evaluate(
    agent: Agent,
    task: Task,
    cfg: TrainConfig,
    episodes: int,
    seed: int = 0,
    sets: tuple[str, ...] | None = None,
) -> dict[str, Any]:
    """Success rates per instruction set (and family) over ``episodes`` episodes per set,
    as the training loops log them.

    The episodes are those of ``lcrl eval`` with the same seed
    (:func:`train.evaluation.eval_suite.run_evaluation`; seeds ``EVAL_SEED_OFFSET + seed * 10_007 +
    i``). With a fixed task set (``env.tasks``, task ids or language goals) there is one
    set, ``train``: episode ``i`` runs task ``i mod K``.

    Returns:
        ``{set: {"success", "ci", "episodes", "families": {family: success}}}`` (plus
        ``"tasks"``, one ``{"id", "instruction", "success", "episodes"}`` per task, for a
        task set; success NaN where a task had no episode). Sets are keyed by name for
        instruction-following tasks, ``all`` otherwise.
    """
    if task_texts(cfg.env):
        sets = ("train",)
    num_envs = 1 if env_spec(cfg.env.kind).step_cost == "slow" else min(EVAL_ENVS, episodes)
    full = run_evaluation(
        agent, task, cfg, episodes, seed=seed, sets=sets, num_envs=num_envs, vector="sync"
    )
    return {name: brief_results(res) for name, res in full.items()}


def evaluate_tasks(
    agent: Agent, task: Task, cfg: TrainConfig, episodes: int, seed: int = 0
) -> dict[str, Any]:
    """The figures of a fixed task set (``env.tasks``): :func:`evaluate`'s ``train`` set,
    episode ``i`` running task ``i mod K``."""
    return evaluate(agent, task, cfg, episodes, seed=seed)["train"]


def _rate(x: float | None) -> float:
    return float("nan") if x is None else float(x)


def brief_results(res: dict[str, Any]) -> dict[str, Any]:
    """The figures of one set of :func:`train.evaluation.eval_suite.run_evaluation` that the
    training
    logs keep: success (NaN when no episode was checked), its interval, episodes, success
    per family and per task."""
    out: dict[str, Any] = {
        "success": _rate(res["success"]),
        "ci": list(res["ci"]),
        "episodes": int(res["episodes"]),
        "families": {f: _rate(st["success"]) for f, st in res["families"].items()},
    }
    if res.get("tasks"):
        out["tasks"] = [
            {
                "id": t["id"],
                "instruction": t["instruction"],
                "success": _rate(t["success"]),
                "episodes": t["episodes"],
            }
            for t in res["tasks"]
        ]
    return out


def format_results(results: dict[str, Any]) -> str:
    """One line per set: overall and per-family success (and per task, for a task set)."""
    lines = []
    for name, res in results.items():
        fams = " ".join(f"{f} {v:.2f}" for f, v in res["families"].items())
        line = f"{name}: success {res['success']:.2f} ({fams}; {res['episodes']} episodes)"
        if res.get("tasks"):
            line += "; tasks " + " ".join(f"{t['id']}:{t['success']:.2f}" for t in res["tasks"])
        lines.append(line)
    return "\n".join(lines)


@dataclass
class LoadedPolicy:
    """A trained agent with its task and environment, ready to run episodes."""

    cfg: TrainConfig
    agent: Agent
    task: Task
    env: gym.Env
    checkpoint: Checkpoint


#: The key of a kept policy's ``meta.json`` that lists the modules it was kept without
#: (``lcrl export``: :func:`train.policies.loading.keep_checkpoint`); loading skips them.
ACTING_ONLY = "acting_only"


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint folder, or a run folder (its latest checkpoint)."""
    p = Path(path)
    if not p.exists():
        raise LcrlError(f"no checkpoint or run folder at {p}")
    if (p / "meta.json").exists():
        return p
    latest = find_latest(p)
    if latest is None:
        raise LcrlError(f"{p} is neither a checkpoint (no meta.json) nor a run with latest.json")
    return latest


def load_single(
    path: str | Path,
    env_overrides: dict[str, Any] | None = None,
    device: str | None = None,
    render: bool = False,
) -> LoadedPolicy:
    """Load one run's checkpoint and rebuild its env, task and agent: a folder made of
    others (an ensemble, a router) as its first member or base alone;
    :func:`train.policies.loading.load_policy` loads any.

    Args:
        path: a checkpoint folder or a run folder.
        env_overrides: env config fields to change (e.g. ``families``); the resulting
            env must match the checkpoint's observation and action shapes.
        device: run the policy here instead of the checkpoint's device.
        render: make the env with ``render_mode="rgb_array"`` (for videos).

    Raises:
        LcrlError: the checkpoint is missing or does not match the environment.
    """
    from train.configs.run_meta import run_meta

    ckpt = load_checkpoint(resolve_checkpoint(path))
    meta = run_meta(ckpt)
    cfg = meta.config
    for key, value in (env_overrides or {}).items():
        if not hasattr(cfg.env, key):
            raise LcrlError(f"unknown env option {key!r}")
        setattr(cfg.env, key, value)
    cfg.env = dataclasses.replace(cfg.env)  # older kind names, as on the command line
    if "perception" in ckpt.meta and "perception" not in (env_overrides or {}):
        cfg.env.perception = str(ckpt.path)  # the copy of the model it acts through
    if device is not None:
        cfg.agent.device = device
    if render:
        cfg.env.extra = {**cfg.env.extra, "render_mode": "rgb_array"}
    env = make_env(cfg.env, "train")
    task = build_task(cfg, env, ckpt)
    problem = task.problem()
    saved = meta.problem
    if problem != saved:
        raise LcrlError(
            f"checkpoint {ckpt.path} does not match the environment: it was trained with "
            f"{describe_problem(saved)}, the environment gives {describe_problem(problem)}"
        )
    agent = build_agent(meta.algo, problem, cfg, task.goal_space.embed, env)
    left_out = set(ckpt.meta.get(ACTING_ONLY, ()))  # kept to act (lcrl export)
    for name, module in agent.modules().items():
        if name not in left_out:
            ckpt.load_module(name, module)
    return LoadedPolicy(cfg, agent, task, env, ckpt)


def describe_problem(p: Problem) -> str:
    """Observation, goal and action shapes of a problem, for messages."""
    obs = ", ".join(f"{k} {tuple(v)}" for k, v in p.obs_shapes.items())
    kind = f"{p.action_dim} discrete actions" if p.discrete else f"{p.action_dim}-d actions"
    return f"observations [{obs}], {p.goal_kind} goals {tuple(p.goal_shape)}, {kind}"

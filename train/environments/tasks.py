"""Environments as training tasks: what is stored, what the goal is, how episodes are labelled.

A :class:`Task` turns an environment's observation dictionaries into the three things the
learning core needs: the stored observation arrays, the goal (a state vector or an
instruction id), and, at the end of an episode, the goal-space fields the replay buffer
writes (achieved goals, or the captioner's labels of what every step achieved).

* :class:`StateTask`: goal environments with ``observation`` / ``achieved_goal`` /
  ``desired_goal`` (gymnasium-robotics Fetch, the 2D tabletop with state goals). Rewards
  are recomputed with the env's own ``compute_reward``.
* :class:`LanguageTask`: environments wrapped by
  :class:`captioner.lang_env.LanguageGoalWrapper`. The policy sees the observation and the
  episode's first observation (push and put are judged relative to the start), the goal is
  an id into the instruction table, and each step is labelled with the training
  instructions the rule captioner says it satisfies.
* :class:`ImageGoalTask`: goal envs that can draw their desired goal (``goal_image()``):
  the goal is that camera frame, relabelled goals are frames of later steps, and rewards
  come from the privileged state behind them.
* :class:`TaskIdTask`: a fixed set of ``K`` instructions (``EnvConfig.tasks``) given to the
  policy as one-hot task ids (``goal_type="task"``): multi-task RL, each task rewarded by
  its own rule-captioner check, nothing relabelled.

With ``image_obs`` the policy sees the camera image and the robot's proprioception (the
first ``proprio_dim`` values of ``observation``) instead of the privileged state.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.errors import LcrlError
from train.environments.language_tasks import LanguageTask, TaskIdTask
from train.environments.simulators import ENVS, EnvConfig, EnvSpec, check_env_config, env_spec
from train.environments.task_base import (
    ImageGoalTask,
    StateTask,
    Task,
    features_wrapper,
    find_language_wrapper,
    slot_attributes,
    slot_layout_start,
    task_texts,
)

__all__ = [
    "ENVS",
    "FEASIBLE_TRIES",
    "GOALS",
    "EnvConfig",
    "GoalModality",
    "ImageGoalTask",
    "LanguageTask",
    "ScriptedActor",
    "StateTask",
    "Task",
    "TaskIdTask",
    "check_tasks",
    "env_spec",
    "features_wrapper",
    "find_language_wrapper",
    "goal_modality",
    "goals_label",
    "has_instructions",
    "is_language",
    "make_env",
    "make_task",
    "reset_feasible",
    "slot_attributes",
    "slot_layout_start",
    "switch_in_place",
    "task_texts",
]

#: Layouts tried per episode for a layout in which the episode's task is feasible.
FEASIBLE_TRIES = 100

#: Names of earlier versions, and what took their place.
RENAMED = {
    "ENV_KINDS": "train.environments.simulators.ENVS (one EnvSpec per simulator; the goal type is "
    "EnvConfig.goal_type)",
    "GOAL_TYPES": "train.environments.tasks.GOALS (one GoalModality per goal type)",
}


class RenamedError(LcrlError, ImportError):
    """A name of an earlier version was asked for; the message gives the new spelling.
    An ``ImportError`` (not an ``AttributeError``, which ``from train.environments.tasks import
    NAME``
    would replace by a message of its own)."""


def __getattr__(name: str) -> Any:
    """Names of earlier versions fail with an error that gives the new spelling."""
    if name in RENAMED:
        raise RenamedError(
            f"train.environments.tasks.{name} was replaced by {RENAMED[name]}: use that "
            "registry instead",
            name=name,
        )
    raise AttributeError(f"module 'train.environments.tasks' has no attribute {name!r}")


def make_env(cfg: EnvConfig, split_set: str = "train", training: bool = False) -> gym.Env:
    """Build the environment of a config: the simulator of ``cfg.kind``
    (:data:`train.environments.simulators.ENVS`), wrapped as its goal type asks
    (:data:`GOALS`; instructions for language goals and task ids), with its time limit.

    Args:
        cfg: the env config.
        split_set: the instruction set an instruction-following env draws from.
        training: apply the training-only options (``train_until_success``).
    """
    check_tasks(cfg)  # the config as a whole, once
    modality, spec = goal_modality(cfg.goal_type), env_spec(cfg.kind)
    env = spec.make(cfg)
    if modality.instructed:
        env = _language_wrapper(env, cfg, spec, split_set, training)
    if spec.time_limit:
        env = gym.wrappers.TimeLimit(env, cfg.max_episode_steps)
    return env


def _language_wrapper(
    env: gym.Env, cfg: EnvConfig, spec: EnvSpec, split_set: str, training: bool
) -> gym.Env:
    """Instructions over a simulator: the compositional split of its families."""
    from captioner.lang_env import LanguageGoalWrapper
    from captioner.splits import make_split

    bad = [f for f in cfg.families if f not in spec.families]
    if bad:
        raise LcrlError(f"the {cfg.kind} env supports the families {spec.families}, not {bad}")
    return LanguageGoalWrapper(
        env,
        split=make_split(cfg.split_seed, spec.families),
        split_set=split_set,
        families=tuple(cfg.families),
        terminate_on_success=cfg.train_until_success or not training,
    )


def is_language(cfg: EnvConfig) -> bool:
    """Whether an env config gives language goals (texts the frozen encoder embeds)."""
    return goal_modality(cfg.goal_type).text


def has_instructions(cfg: EnvConfig) -> bool:
    """Whether an env config's episodes follow instructions (language goals or task ids
    over instructions): the env is wrapped by the language-goal wrapper."""
    return goal_modality(cfg.goal_type).instructed


def check_tasks(cfg: EnvConfig) -> None:
    """Refuse an env config that cannot be built
    (:func:`train.environments.simulators.check_env_config`),
    the instruction reader over goals without text, or a task set that cannot run: task ids
    on an env without instructions, an
    empty task set with task ids, an instruction that does not parse, that is outside the
    env's families, or that repeats another (in any phrasing)."""
    env_spec(cfg.kind)  # an unknown simulator first: its goal type cannot be resolved
    modality = goal_modality(cfg.goal_type)
    spec = check_env_config(cfg)
    if (cfg.text_reader or cfg.canonical_reader) and not modality.text:
        raise LcrlError(
            f"the instruction reader reads language goals; goal type {cfg.goal_type!r} "
            "has none: drop --env.text-reader / --env.canonical-reader"
        )
    tasks = task_texts(cfg)
    if not tasks:
        if modality.needs_tasks:
            raise LcrlError(
                f"goal_type={cfg.goal_type} needs a task set: list the K instructions with "
                "--env.tasks (e.g. --env.tasks 'reach the red cube' 'push the blue cube left'), "
                "or use the lang2d-tasks preset"
            )
        return
    if not modality.instructed or not spec.families:
        raise LcrlError(
            f"env.tasks are instructions: they need language or task goals on a simulator "
            f"with instructions, not goal_type {cfg.goal_type!r} on {cfg.kind!r}"
        )
    from captioner.grammar import parse

    seen: dict[str, str] = {}
    for text in tasks:
        if not text:
            raise LcrlError("env.tasks holds an empty instruction")
        meaning = parse(text)
        if meaning.family not in cfg.families:
            raise LcrlError(
                f"task {text!r} is a {meaning.family} instruction, outside env.families "
                f"{tuple(cfg.families)}: add the family or drop the task"
            )
        if meaning.text in seen:
            raise LcrlError(
                f"tasks {seen[meaning.text]!r} and {text!r} are the same instruction: list "
                "each task once"
            )
        seen[meaning.text] = text


def reset_feasible(
    env: gym.Env, seed: int, instruction: str, tries: int = FEASIBLE_TRIES
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Reset ``env`` with a fixed instruction in the first of ``tries`` layouts where it is
    feasible: the layout of ``seed``, then layouts of seeds derived from it.

    Raises:
        LcrlError: the instruction is feasible in none of them.
    """
    for k in range(tries):
        s = seed if k == 0 else int(np.random.SeedSequence([seed, k]).generate_state(1)[0])
        obs, info = env.reset(seed=s, options={"instruction": instruction})
        if info.get("feasible", True):
            return obs, info
    raise LcrlError(
        f"task {instruction!r} is feasible in none of {tries} random layouts: check that its "
        "objects can appear (env.min_objects, env.max_objects) and that it does not hold "
        "from the start"
    )


class ScriptedActor:
    """The env's scripted controller as a policy-space actor for training episodes.

    Args:
        cfg: the env config (language goals on the 2D tabletop or robosuite).
        task: the run's task (action scaling, discrete moves).
        noise: std of the Gaussian noise added to continuous actions.
        teacher: use the env's controller that reads everything off the scene
            (:attr:`EnvSpec.teacher`, where it has one), to label states it did not lead to.

    Raises:
        LcrlError: the env has no scripted controller.
    """

    def __init__(
        self, cfg: EnvConfig, task: Task, noise: float, teacher: bool = False, funnel: float = 0.0
    ) -> None:
        spec = env_spec(cfg.kind)
        if not has_instructions(cfg) or spec.scripted is None:
            raise LcrlError(
                "scripted episodes need language or task goals on a simulator with a scripted "
                f"controller (env kind {cfg.kind!r}, goal type {cfg.goal_type!r} has none)"
            )
        make = spec.teacher if teacher and spec.teacher is not None else spec.scripted
        if funnel and not (teacher and cfg.kind == "robosuite"):
            raise LcrlError(
                "a drop funnel (distill.scripted_funnel) is a setting of the robosuite "
                f"scripted teacher only (env kind {cfg.kind!r})"
            )
        self.controller: Any = make(funnel=funnel) if funnel else make()
        self.scene = spec.scene or (lambda env: env.unwrapped.scene())
        self.task, self.noise = task, float(noise)

    def reset(self) -> None:
        """Start a new episode."""
        reset = getattr(self.controller, "reset", None)
        if reset is not None:
            reset()

    def act(self, env: gym.Env, rng: np.random.Generator) -> np.ndarray:
        """The controller's action for the env's current scene, in policy space."""
        wrapper = find_language_wrapper(env)
        a = self.controller.act(wrapper.meaning, wrapper.s0, self.scene(env))
        if self.task.discrete:
            from captioner.scripted import to_discrete

            return np.asarray(to_discrete(a))
        a = np.asarray(a, np.float32)
        if self.noise > 0:
            a = a + rng.normal(0.0, self.noise, a.shape).astype(np.float32)
        low, high = self.task.low, self.task.high
        # the controllers speak the env's action units; the buffer stores policy units
        return np.clip(2.0 * (a - low) / (high - low) - 1.0, -1.0, 1.0).astype(np.float32)


def switch_in_place(env: gym.Env, obs: Mapping[str, Any]) -> dict[str, Any] | None:
    """Give a running language episode its next instruction in the same scene (a chain):
    the wrapper draws one among the training instructions feasible there, displacements
    restart and the time limit starts again.

    Args:
        env: the training env, as :func:`make_env` built it.
        obs: the last observation it returned.

    Returns:
        The observation the next instruction starts from, or None when no instruction
        is feasible in the scene (the env then needs a reset).
    """
    wrapper = find_language_wrapper(env)
    if wrapper.switch_instruction() is None:
        return None
    features = features_wrapper(env)
    out = dict(obs) if features is None else features.restarted(obs)
    out["instruction"] = wrapper.instruction
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, gym.wrappers.TimeLimit):
            e._elapsed_steps = 0
        e = e.env
    return out


def make_task(cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any) -> Task:
    """The task adapter of an env config: its goal type's :class:`Task` subclass
    (:data:`GOALS`).

    Args:
        cfg: the env config, checked when :func:`make_env` built ``env`` from it.
        env: the env :func:`make_env` built for it.
        embed: ``texts -> (N, d)`` embeddings (the frozen text encoder), for text goals.
        kwargs: a saved instruction table (``table``, ``num_train``).
    """
    return goal_modality(cfg.goal_type).task.from_config(cfg, env, embed, **kwargs)


@dataclass(frozen=True)
class GoalModality:
    """One goal type of :data:`GOALS`.

    Attributes:
        task: the :class:`Task` subclass: it stores observations, gives the goal of an
            episode, builds the goal space (:mod:`lcrl.goals`: relabelling and rewards)
            and names the network's goal encoder and normaliser (``goal_kind``).
        summary: a few words for help texts.
        instructed: the simulator is wrapped with instructions
            (:class:`captioner.lang_env.LanguageGoalWrapper`): it needs instruction
            families (:attr:`train.environments.simulators.EnvSpec.families`).
        needs_tasks: the goal type needs a fixed task set (``env.tasks``).
        relabel: goals may be relabelled in hindsight (task ids may not).
        label: what its goals are called in reports and messages (``task ids``);
            empty: ``<goal type> goals``.
    """

    task: type[Task]
    summary: str = ""
    instructed: bool = False
    needs_tasks: bool = False
    relabel: bool = True
    label: str = ""

    @property
    def text(self) -> bool:
        """Goals are texts embedded by the frozen text encoder."""
        return bool(self.task.text_goals)

    @property
    def task_ids(self) -> bool:
        """Goals are ids of the fixed task set: a trained policy is asked with a task id
        (its :class:`Task` has ``query = "task_id"``), never with free text."""
        return self.task.query == "task_id"


#: Every goal type, by ``EnvConfig.goal_type``.
GOALS: dict[str, GoalModality] = {
    "state": GoalModality(StateTask, "goal vectors (positions), HER over achieved goals"),
    "image": GoalModality(ImageGoalTask, "goal camera frames, HER over later frames"),
    "language": GoalModality(
        LanguageTask, "instructions, language HER over captions", instructed=True
    ),
    "task": GoalModality(
        TaskIdTask,
        "one-hot ids of a fixed instruction set, no relabelling",
        instructed=True,
        needs_tasks=True,
        relabel=False,
        label="task ids",
    ),
}


def goals_label(goal_type: str) -> str:
    """What a goal type's goals are called in reports (``task ids``, ``state goals``);
    unregistered goal types too."""
    modality = GOALS.get(goal_type)
    return (modality.label if modality is not None else "") or f"{goal_type} goals"


def goal_modality(goal_type: str) -> GoalModality:
    """The registry entry of a goal type.

    Raises:
        LcrlError: no goal type of that name.
    """
    modality = GOALS.get(goal_type)
    if modality is None:
        raise LcrlError(f"unknown goal_type {goal_type!r}; choose one of {tuple(GOALS)}")
    return modality

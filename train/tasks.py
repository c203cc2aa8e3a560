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

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.algos import Problem
from lcrl.errors import LcrlError
from lcrl.goals import ImageGoals, LabelGoals, StateGoals, TaskGoals

ENV_KINDS = ("lang2d", "state2d", "gym", "robosuite")
GOAL_TYPES = ("language", "state", "image", "task")
#: Layouts tried per episode for a layout in which the episode's task is feasible.
FEASIBLE_TRIES = 100


@dataclass
class EnvConfig:
    """Which environment to train on."""

    kind: str = "lang2d"
    """``lang2d`` (2D tabletop, language goals), ``state2d`` (2D tabletop, state goals),
    ``robosuite`` (the Panda tabletop; its goals are ``goal_type``) or ``gym`` (any
    registered goal env, e.g. gymnasium-robotics ``FetchReach-v4``)."""
    goal_type: str = "language"
    """Goals: ``language`` (instructions), ``task`` (one-hot ids of the ``tasks``: the
    policy never sees their text; ``lang2d`` and ``robosuite``), and on the robosuite
    tabletop ``state`` (object or gripper positions, see ``goal``) or ``image`` (a camera
    frame of the goal layout)."""
    tasks: tuple[str, ...] = ()
    """A fixed task set of ``K`` instructions (multi-task RL). Each training episode's task
    is drawn among them (``agent.multitask.sampling``) in a layout where it is feasible,
    and evaluation runs them in turn. With ``goal_type=task`` the policy sees a one-hot
    task id; with ``language`` the instruction table is exactly these instructions (ids
    ``0 .. K-1``, relabelled among them), so the same tasks run either way. Empty: the
    split's instructions (language goals)."""
    image_obs: bool = False
    """The policy sees the camera image and the robot's proprioception instead of the
    privileged object state (robosuite and the 2D tabletop)."""
    image_size: int = 64
    """Camera image side in pixels (robosuite: 64 or 84)."""
    gym_id: str = "FetchReach-v4"
    """Environment id for ``kind=gym``."""
    families: tuple[str, ...] = ("reach", "push")
    """Instruction families to train and evaluate (language goals)."""
    split_seed: int = 0
    """Seed of the compositional instruction split (language goals)."""
    min_objects: int = 2
    """Fewest objects on the table."""
    max_objects: int = 3
    """Most objects on the table."""
    discrete: bool = False
    """Discrete pusher moves (8 directions) instead of continuous ones (2D tabletop)."""
    max_episode_steps: int = 50
    """Time limit of an episode (a truncation: the value bootstraps through it)."""
    goal: str = "object"
    """State goal of ``state2d`` and robosuite state or image goals: ``object`` (all object
    positions), ``pusher`` (2D) or ``gripper`` (robosuite)."""
    relative_positions: bool = False
    """Add each object's position relative to the gripper (pusher) to its observation
    slot (:class:`envs.features.RelativePositions`); pair with ``--agent.net.slots``
    ``(2, 8, 5)`` on the 2D tabletop or ``(4, 8, 7)`` on robosuite."""
    displacements: bool = False
    """Add each object's displacement since the episode's reset to its observation slot
    (:class:`envs.features.SlotFeatures`): push and put are judged on it. Widens each slot
    by 2 values on the 2D tabletop (3 on robosuite); set ``--agent.net.slots`` to match."""
    train_until_success: bool = True
    """Language goals: training episodes end when their instruction is achieved. ``False``
    runs them to the time limit and keeps what happens after the success (an object
    touched, then pushed), which the relabelled goals learn from; the value target still
    ends at the success step. Evaluation episodes always end at success."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the environment constructor."""


def _register_gym_robotics() -> None:
    try:
        import gymnasium_robotics
    except ImportError:
        return
    gym.register_envs(gymnasium_robotics)


def make_env(cfg: EnvConfig, split_set: str = "train", training: bool = False) -> gym.Env:
    """Build the environment of a config (``split_set`` picks the instruction set;
    ``training`` applies the training-only options such as ``train_until_success``)."""
    if cfg.kind not in ENV_KINDS:
        raise LcrlError(f"unknown env kind {cfg.kind!r}; choose one of {ENV_KINDS}")
    if cfg.min_objects > cfg.max_objects:
        raise LcrlError(
            f"min_objects ({cfg.min_objects}) is larger than max_objects ({cfg.max_objects})"
        )
    if cfg.goal_type not in GOAL_TYPES:
        raise LcrlError(f"unknown goal_type {cfg.goal_type!r}; choose one of {GOAL_TYPES}")
    check_tasks(cfg)
    if cfg.kind == "robosuite":
        return _make_robosuite(cfg, split_set, training)
    if cfg.kind == "gym":
        _register_gym_robotics()
        try:
            env = gym.make(
                cfg.gym_id,
                max_episode_steps=cfg.max_episode_steps,
                disable_env_checker=True,
                **cfg.extra,
            )
        except gym.error.Error as e:
            hint = ""
            if "Fetch" in cfg.gym_id:
                hint = " (install gymnasium-robotics and mujoco: pip install -e '.[bench]')"
            raise LcrlError(f"cannot make {cfg.gym_id!r}: {e}{hint}") from None
        return env
    from envs.tabletop2d import Tabletop2DEnv

    kwargs: dict[str, Any] = {
        "num_objects": (cfg.min_objects, cfg.max_objects),
        "action_type": "discrete" if cfg.discrete else "continuous",
        **cfg.extra,
    }
    if cfg.discrete:
        kwargs.setdefault("num_directions", 8)
    if cfg.image_obs:
        kwargs.update(image=True, image_size=cfg.image_size)
    if cfg.kind == "state2d":
        kwargs["goal"] = cfg.goal
        base: gym.Env = _features(Tabletop2DEnv(**kwargs), cfg)
        return gym.wrappers.TimeLimit(base, cfg.max_episode_steps)
    from captioner.grammar import FAMILIES_2D
    from captioner.lang_env import LanguageGoalWrapper
    from captioner.splits import make_split

    bad = [f for f in cfg.families if f not in FAMILIES_2D]
    if bad:
        raise LcrlError(f"the 2D tabletop supports the families {FAMILIES_2D}, not {bad}")
    env = LanguageGoalWrapper(
        _features(Tabletop2DEnv(**kwargs), cfg),
        split=make_split(cfg.split_seed, FAMILIES_2D),
        split_set=split_set,
        families=tuple(cfg.families),
        terminate_on_success=cfg.train_until_success or not training,
    )
    return gym.wrappers.TimeLimit(env, cfg.max_episode_steps)


def _features(env: gym.Env, cfg: EnvConfig) -> gym.Env:
    """The observation feature wrappers a config asks for."""
    if cfg.relative_positions or cfg.displacements:
        from envs.features import SlotFeatures

        return SlotFeatures(env, relative=cfg.relative_positions, displacement=cfg.displacements)
    return env


def _make_robosuite(cfg: EnvConfig, split_set: str, training: bool) -> gym.Env:
    from envs.robosuite_tabletop import RobosuiteTabletopEnv

    kwargs: dict[str, Any] = {"num_objects": (cfg.min_objects, cfg.max_objects), **cfg.extra}
    if cfg.image_obs or cfg.goal_type == "image":
        kwargs.update(image=True, image_size=cfg.image_size)
    instructed = cfg.goal_type in ("language", "task")
    if not instructed:
        goal = {"pusher": "gripper"}.get(cfg.goal, cfg.goal)
        if cfg.goal_type == "image" and goal != "object":
            raise LcrlError("image goals on the robosuite tabletop need goal='object'")
        kwargs["goal"] = goal
    base = _features(RobosuiteTabletopEnv(**kwargs), cfg)
    if not instructed:
        return gym.wrappers.TimeLimit(base, cfg.max_episode_steps)
    from captioner.grammar import FAMILIES
    from captioner.lang_env import LanguageGoalWrapper
    from captioner.splits import make_split

    bad = [f for f in cfg.families if f not in FAMILIES]
    if bad:
        raise LcrlError(f"unknown instruction families {bad}; choose among {FAMILIES}")
    env = LanguageGoalWrapper(
        base,
        split=make_split(cfg.split_seed, FAMILIES),
        split_set=split_set,
        families=tuple(cfg.families),
        terminate_on_success=cfg.train_until_success or not training,
    )
    return gym.wrappers.TimeLimit(env, cfg.max_episode_steps)


def is_language(cfg: EnvConfig) -> bool:
    """Whether an env config gives language goals."""
    if cfg.goal_type == "task":
        return False
    return cfg.kind == "lang2d" or (cfg.kind == "robosuite" and cfg.goal_type == "language")


def has_instructions(cfg: EnvConfig) -> bool:
    """Whether an env config's episodes follow instructions (language goals or task ids
    over instructions): the env is wrapped by the language-goal wrapper."""
    return is_language(cfg) or (cfg.goal_type == "task" and cfg.kind in ("lang2d", "robosuite"))


def task_texts(cfg: EnvConfig) -> tuple[str, ...]:
    """The config's task set with whitespace normalised (what the env's observations say)."""
    return tuple(" ".join(str(t).split()) for t in cfg.tasks)


def check_tasks(cfg: EnvConfig) -> None:
    """Refuse a task set that cannot run: task ids on an env without instructions, an
    empty task set with task ids, an instruction that does not parse, that is outside the
    env's families, or that repeats another (in any phrasing)."""
    if cfg.goal_type == "task" and cfg.kind not in ("lang2d", "robosuite"):
        raise LcrlError(
            f"goal_type=task gives one-hot ids of instructions: it needs env.kind lang2d or "
            f"robosuite, not {cfg.kind!r}"
        )
    tasks = task_texts(cfg)
    if not tasks:
        if cfg.goal_type == "task":
            raise LcrlError(
                "goal_type=task needs a task set: list the K instructions with --env.tasks "
                "(e.g. --env.tasks 'reach the red cube' 'push the blue cube left'), or use "
                "the lang2d-tasks preset"
            )
        return
    if not has_instructions(cfg):
        raise LcrlError(
            f"env.tasks are instructions: they need language or task goals on lang2d or "
            f"robosuite, not goal_type {cfg.goal_type!r} on {cfg.kind!r}"
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


def _proprio_dim(env: gym.Env) -> int:
    dim = getattr(env.unwrapped, "proprio_dim", None)
    if dim is None:
        raise LcrlError(
            f"{type(env.unwrapped).__name__} does not say which observation values are "
            "proprioception (a proprio_dim attribute); image observations need it"
        )
    return int(dim)


def _image_shape(env: gym.Env) -> tuple[int, ...]:
    space = env.observation_space
    if not isinstance(space, gym.spaces.Dict) or "image" not in space.spaces:
        raise LcrlError("image observations or goals need an env with an 'image' observation")
    return tuple(space["image"].shape)


def _action_spec(env: gym.Env) -> tuple[int, bool]:
    space = env.action_space
    if isinstance(space, gym.spaces.Discrete):
        return int(space.n), True
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
        return int(space.shape[0]), False
    raise LcrlError(f"unsupported action space {space}: need Discrete or a 1-D Box")


class Task:
    """Base class: storage layout, goals and episode fields for one environment."""

    goal_kind = "vector"
    sets: tuple[str, ...] = ("train",)
    #: Size of the fixed task set whose ids are the goals (0: none).
    num_tasks: int = 0

    def __init__(self, env: gym.Env) -> None:
        self.action_dim, self.discrete = _action_spec(env)
        space = env.action_space
        if not self.discrete:
            self.low = np.asarray(space.low, np.float32)
            self.high = np.asarray(space.high, np.float32)
            if not (np.all(np.isfinite(self.low)) and np.all(np.isfinite(self.high))):
                raise LcrlError("continuous actions need a bounded Box action space")

    def scale_action(self, a: np.ndarray) -> np.ndarray:
        """Map a policy action in ``[-1, 1]`` to the env's action bounds."""
        if self.discrete:
            return a
        return self.low + (np.clip(a, -1.0, 1.0) + 1.0) * 0.5 * (self.high - self.low)

    def random_action(self, rng: np.random.Generator) -> np.ndarray:
        """A uniformly random policy-space action."""
        if self.discrete:
            return np.asarray(rng.integers(self.action_dim))
        return rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)

    def _setup_image_obs(self, env: gym.Env, image_obs: bool) -> None:
        self.image_obs = image_obs
        if image_obs:
            self.proprio_dim = _proprio_dim(env)
            self.obs_shapes = {"image": _image_shape(env), "proprio": (self.proprio_dim,)}

    def _image_storage(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return {
            "image": np.asarray(obs["image"], np.uint8),
            "proprio": np.asarray(obs["observation"][: self.proprio_dim], np.float32),
        }

    def problem(self) -> Problem:
        """Shapes and goal encoding for the learner."""
        goal_shape = getattr(self.goal_space, "goal_shape", None)
        return Problem(
            obs_shapes=dict(self.obs_shapes),
            goal_kind=self.goal_kind,
            goal_shape=tuple(goal_shape) if goal_shape else (self.goal_space.embed_dim,),
            action_dim=self.action_dim,
            discrete=self.discrete,
            num_tasks=self.num_tasks,
        )


class StateTask(Task):
    """Goal envs with ``observation``, ``achieved_goal`` and ``desired_goal`` vectors."""

    goal_kind = "vector"

    def __init__(self, env: gym.Env, image_obs: bool = False) -> None:
        super().__init__(env)
        space = env.observation_space
        keys = ("observation", "achieved_goal", "desired_goal")
        if not isinstance(space, gym.spaces.Dict) or any(k not in space.spaces for k in keys):
            raise LcrlError(f"a state-goal env needs a Dict observation with {keys}; got {space}")
        self.obs_shapes = {"observation": tuple(space["observation"].shape)}
        dim = int(space["desired_goal"].shape[0])
        unwrapped = env.unwrapped
        if not callable(getattr(unwrapped, "compute_reward", None)):
            raise LcrlError(
                f"{type(unwrapped).__name__} has no compute_reward(achieved, desired, info)"
            )

        def reward_fn(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
            return unwrapped.compute_reward(achieved, desired, None)

        probe = np.zeros((1, dim), np.float32)
        success = float(np.asarray(reward_fn(probe, probe)).reshape(-1)[0])
        self.reward_fn, self.success_reward, self.goal_dim = reward_fn, success, dim
        self.goal_space: StateGoals = StateGoals(dim, reward_fn, success_reward=success)
        self._setup_image_obs(env, image_obs)

    def storage_obs(
        self, obs: Mapping[str, Any], first: Mapping[str, Any]
    ) -> dict[str, np.ndarray]:
        """Observation arrays to store."""
        if self.image_obs:
            return self._image_storage(obs)
        return {"observation": np.asarray(obs["observation"], np.float32)}

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> np.ndarray:
        """The goal the policy is given."""
        return np.asarray(obs["desired_goal"], np.float32)

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """What to remember of each observation for the episode fields."""
        return np.asarray(obs["achieved_goal"], np.float32)

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """Goal-space fields of a finished episode."""
        return {"achieved_goal": np.stack(records), "desired_goal": goal}

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        """Goals in the learner's input space (vectors stay vectors)."""
        return goals


class ImageGoalTask(StateTask):
    """Image goals: the desired goal is the env's ``goal_image()`` (drawn once per episode),
    relabelled goals are later camera frames of the same episode, and rewards come from
    the env's ``compute_reward`` on the privileged state behind each frame."""

    goal_kind = "image"

    def __init__(self, env: gym.Env, image_obs: bool = False) -> None:
        super().__init__(env, image_obs)
        if not callable(getattr(env.unwrapped, "goal_image", None)):
            raise LcrlError(
                f"{type(env.unwrapped).__name__} cannot draw its goal (no goal_image()): "
                "image goals need it"
            )
        shape = _image_shape(env)
        self.goal_space = ImageGoals(
            self.goal_dim, self.reward_fn, shape, success_reward=self.success_reward
        )
        if not image_obs:
            self.obs_shapes = {**self.obs_shapes, "image": shape}

    def storage_obs(
        self, obs: Mapping[str, Any], first: Mapping[str, Any]
    ) -> dict[str, np.ndarray]:
        """The observation arrays, always with the camera image (goal frames live there)."""
        out = super().storage_obs(obs, first)
        out["image"] = np.asarray(obs["image"], np.uint8)
        return out

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> np.ndarray:
        """The frame of the episode's desired goal."""
        return np.asarray(env.unwrapped.goal_image(), np.uint8)

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The achieved and desired state goals of each observation."""
        return (
            np.asarray(obs["achieved_goal"], np.float32),
            np.asarray(obs["desired_goal"], np.float32),
        )

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """Achieved states, the desired state and the desired frame."""
        return {
            "achieved_goal": np.stack([achieved for achieved, _ in records]),
            "desired_goal": records[0][1],
            "desired_image": goal,
        }


class LanguageTask(Task):
    """Language-goal envs (:class:`captioner.lang_env.LanguageGoalWrapper`).

    Args:
        env: the wrapped training env (its split and families define the table).
        embed: ``texts -> (N, d)`` float32 embeddings (the frozen text encoder).
        table: the instruction table to use (e.g. from a checkpoint); default: the
            split's training instructions of the env's families first, then held-out and
            paraphrase ones.
        tasks: a fixed task set: the table is exactly these instructions, all of them
            training instructions (relabelled among themselves), and their ids are task
            ids (:attr:`num_tasks`).
    """

    goal_kind = "text"
    sets = ("train", "heldout", "paraphrase")

    def __init__(
        self,
        env: gym.Env,
        embed: Any,
        table: list[str] | None = None,
        num_train: int | None = None,
        image_obs: bool = False,
        tasks: tuple[str, ...] = (),
    ) -> None:
        super().__init__(env)
        if tasks:
            if table is not None and list(table) != list(tasks):
                raise LcrlError(
                    "the saved instruction table differs from env.tasks: resume with the "
                    "run's own config"
                )
            table, num_train = list(tasks), len(tasks)
            self.num_tasks = len(tasks)
        wrapper = find_language_wrapper(env)
        self.wrapper = wrapper
        self.split = wrapper.split
        self.families = wrapper.families
        self.captioner = wrapper.captioner
        if table is None:
            train = [
                t
                for t, m in zip(self.split.train, self.split.instructions("train"), strict=True)
                if m.family in self.families
            ]
            rest = [
                t
                for name in ("heldout", "paraphrase")
                for t, m in zip(self.split.texts(name), self.split.instructions(name), strict=True)
                if m.family in self.families
            ]
            table = train + [t for t in dict.fromkeys(rest) if t not in set(train)]
            num_train = len(train)
        if num_train is None:
            raise LcrlError("num_train is required with an explicit instruction table")
        self.table = list(table)
        self.num_train = int(num_train)
        self.ids = {t: i for i, t in enumerate(self.table)}
        self.train_ids = {t: i for t, i in self.ids.items() if i < self.num_train}
        # the captioner names achievements in canonical phrasing
        self.label_ids = dict(self.train_ids)
        if tasks:
            self.label_ids = {self.captioner.parse(t).text: i for t, i in self.train_ids.items()}
        self.embed_fn = embed
        self.embeddings = np.asarray(embed(self.table), np.float32)
        space = env.observation_space
        shape = tuple(space["observation"].shape)
        self.obs_shapes = {"observation": shape, "initial": shape}
        self._setup_image_obs(env, image_obs)
        self.goal_space = LabelGoals(
            len(self.table), self.embeddings, num_relabel=self.num_train, terminate_on_success=True
        )

    def storage_obs(
        self, obs: Mapping[str, Any], first: Mapping[str, Any]
    ) -> dict[str, np.ndarray]:
        """The observation and the episode's first observation (or, with image
        observations, the image and the proprioception)."""
        if self.image_obs:
            return self._image_storage(obs)
        return {
            "observation": np.asarray(obs["observation"], np.float32),
            "initial": np.asarray(first["observation"], np.float32),
        }

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> int:
        """The id of the episode's instruction (added to the table if new)."""
        text = obs["instruction"]
        if text not in self.ids:
            raise LcrlError(f"instruction {text!r} is not in the instruction table")
        return self.ids[text]

    #: Learned captioner / reward model (:class:`captioner.learned.LearnedLabeller`) that
    #: labels stored episodes from camera frames; None: the rule captioner does.
    labeller: Any = None

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The scene after each step (captioned at the end of the episode), with the
        camera frame and the robot's state when a learned labeller reads them."""
        scene = self.wrapper.env.unwrapped.scene()
        if self.labeller is None:
            return scene
        if "image" not in obs:
            raise LcrlError("learned relabelling needs camera frames: the env gives no image")
        start = int(slot_layout_start(self.wrapper))
        return scene, np.asarray(obs["image"]), np.asarray(obs["observation"][:start], np.float32)

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """The episode's instruction id and the training instructions each step satisfies
        (rule captioner), or what the learned captioner reads in the frames and what the
        learned reward model judges achieved."""
        lab = self.labeller
        scenes = records if lab is None else [r[0] for r in records]
        s0 = scenes[0]
        labels: list[list[int]] = [[]]
        for s in scenes[1:]:
            texts = (ins.text for ins in self.captioner.caption(s0, s))
            labels.append([self.label_ids[t] for t in texts if t in self.label_ids])
        out: dict[str, Any] = {"goal_id": int(goal), "labels": labels}
        if lab is None:
            return out
        frames = np.stack([r[1] for r in records])
        proprio = np.stack([r[2] for r in records])
        # the rule captioner's labels are kept only to report how far the learned ones agree
        if lab.use_captioner:
            out["labels"] = lab.labels(frames, proprio)
            lab.compare("labels", out["labels"], labels)
        if lab.use_reward:
            cands = sorted({i for ids in out["labels"] for i in ids} | {int(goal)})
            out["achieved"] = lab.achieved(frames, proprio, cands)
            lab.compare("rewards", out["achieved"], labels, among=cands)
        elif lab.use_captioner and not lab.captioner_rewards:
            out["achieved"] = labels  # learned candidates, rule rewards
        # captioner_rewards: no "achieved", so the learned captions are the rewards too
        return out

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        """Instruction ids as text embeddings."""
        return self.embeddings[np.asarray(goals, np.int64)]


class TaskIdTask(Task):
    """A fixed set of ``K`` instructions given to the policy as one-hot task ids.

    Multi-task RL in the same loop: the env is the language-goal env, each episode is
    reset with one task's instruction, the policy sees the observation, the episode's
    first observation and a one-hot id of the task (never its text), and the reward of a
    step is the task's own reward function ``r_i(s0, s)``: the rule captioner's
    ``satisfied`` check of task ``i``'s instruction on the privileged scenes. Nothing is
    relabelled (:class:`lcrl.goals.TaskGoals`).

    Args:
        env: the wrapped env (:class:`captioner.lang_env.LanguageGoalWrapper` inside).
        tasks: the ``K`` instructions; task ``i`` is id ``i``.
        image_obs: the policy sees camera images and proprioception instead.
    """

    goal_kind = "onehot"
    sets = ("train",)

    def __init__(self, env: gym.Env, tasks: tuple[str, ...], image_obs: bool = False) -> None:
        super().__init__(env)
        if not tasks:
            raise LcrlError("task ids need at least one task (env.tasks)")
        wrapper = find_language_wrapper(env)
        self.wrapper = wrapper
        self.families = wrapper.families
        self.captioner = wrapper.captioner
        self.tasks = list(tasks)
        self.num_tasks = len(self.tasks)
        self.meanings = [self.captioner.parse(t) for t in self.tasks]
        #: ``r_i(s0, s) -> bool``: whether the change from ``s0`` to ``s`` achieves task i.
        self.reward_fns = [
            functools.partial(self.captioner.satisfied, meaning) for meaning in self.meanings
        ]
        self.ids = {t: i for i, t in enumerate(self.tasks)}
        self.ids.update({m.text: i for i, m in enumerate(self.meanings)})
        shape = tuple(env.observation_space["observation"].shape)
        self.obs_shapes = {"observation": shape, "initial": shape}
        self._setup_image_obs(env, image_obs)
        self.goal_space = TaskGoals(self.num_tasks, terminate_on_success=True)

    #: the observation and the episode's first one, as language goals store them
    storage_obs = LanguageTask.storage_obs

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> int:
        """The task id of the episode's instruction."""
        text = obs["instruction"]
        task = self.ids.get(text)
        if task is None:
            task = self.ids.get(self.captioner.parse(text).text)
        if task is None:
            raise LcrlError(
                f"instruction {text!r} is not one of the {self.num_tasks} tasks of this task-id "
                "policy (env.tasks): reset the env with options={'instruction': TASK}"
            )
        return task

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The privileged scene after each step."""
        return self.wrapper.env.unwrapped.scene()

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """The task id and, per step, whether the episode achieved its own task."""
        reward = self.reward_fns[int(goal)]
        s0 = records[0]
        return {"goal_id": int(goal), "success": [reward(s0, s) for s in records[1:]]}

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        """Task ids as one-hot vectors."""
        return np.eye(self.num_tasks, dtype=np.float32)[np.asarray(goals, np.int64)]


class ScriptedActor:
    """The env's scripted controller as a policy-space actor for training episodes.

    Args:
        cfg: the env config (language goals on the 2D tabletop or robosuite).
        task: the run's task (action scaling, discrete moves).
        noise: std of the Gaussian noise added to continuous actions.

    Raises:
        LcrlError: the env has no scripted controller.
    """

    def __init__(self, cfg: EnvConfig, task: Task, noise: float) -> None:
        if not has_instructions(cfg):
            raise LcrlError(
                "scripted episodes need language or task goals on the 2D tabletop or robosuite "
                f"(env kind {cfg.kind!r}, goal type {cfg.goal_type!r} has no scripted controller)"
            )
        if cfg.kind == "lang2d":
            from captioner.scripted import ScriptedController2D

            self.controller: Any = ScriptedController2D()
        else:
            from captioner.scripted3d import ScriptedController3D

            self.controller = ScriptedController3D()
        self.task, self.noise = task, float(noise)

    def reset(self) -> None:
        """Start a new episode."""
        reset = getattr(self.controller, "reset", None)
        if reset is not None:
            reset()

    def act(self, env: gym.Env, rng: np.random.Generator) -> np.ndarray:
        """The controller's action for the env's current scene, in policy space."""
        wrapper = find_language_wrapper(env)
        a = self.controller.act(wrapper.meaning, wrapper.s0, env.unwrapped.scene())
        if self.task.discrete:
            from captioner.scripted import to_discrete

            return np.asarray(to_discrete(a))
        a = np.asarray(a, np.float32)
        if self.noise > 0:
            a = a + rng.normal(0.0, self.noise, a.shape).astype(np.float32)
        low, high = self.task.low, self.task.high
        # the controllers speak the env's action units; the buffer stores policy units
        return np.clip(2.0 * (a - low) / (high - low) - 1.0, -1.0, 1.0).astype(np.float32)


def slot_layout_start(env: gym.Env) -> int:
    """How many agent values lead the env's ``observation`` (the robot's own state)."""
    from envs.features import slot_layout

    return slot_layout(env)[0]


def find_language_wrapper(env: gym.Env) -> Any:
    """The :class:`~captioner.lang_env.LanguageGoalWrapper` inside ``env``."""
    from captioner.lang_env import LanguageGoalWrapper

    e = env
    while True:
        if isinstance(e, LanguageGoalWrapper):
            return e
        if not hasattr(e, "env"):
            raise LcrlError("a language task needs an env wrapped by LanguageGoalWrapper")
        e = e.env


def make_task(cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any) -> Task:
    """The task adapter for an env config."""
    check_tasks(cfg)
    if cfg.goal_type == "task":
        return TaskIdTask(env, task_texts(cfg), image_obs=cfg.image_obs)
    if is_language(cfg):
        if embed is None:
            raise LcrlError("language tasks need a text encoder")
        if cfg.tasks:
            kwargs["tasks"] = task_texts(cfg)
        return LanguageTask(env, embed, image_obs=cfg.image_obs, **kwargs)
    if cfg.kind == "robosuite" and cfg.goal_type == "image":
        return ImageGoalTask(env, image_obs=cfg.image_obs)
    return StateTask(env, image_obs=cfg.image_obs)

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
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.algos import Problem
from lcrl.errors import LcrlError
from lcrl.goals import ImageGoals, LabelGoals, StateGoals, TaskGoals
from train.environments.simulators import ENVS, EnvConfig, EnvSpec, check_env_config, env_spec

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


def task_texts(cfg: EnvConfig) -> tuple[str, ...]:
    """The config's task set with whitespace normalised (what the env's observations say)."""
    return tuple(" ".join(str(t).split()) for t in cfg.tasks)


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


def _slot_feature_flags(env: gym.Env) -> tuple[bool, bool]:
    """Whether ``env``'s observation slots carry relative positions and displacements."""
    from envs.features import SlotFeatures

    e: Any = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, SlotFeatures):
            return e.relative, e.displacement
        e = e.env
    return False, False


def _action_spec(env: gym.Env) -> tuple[int, bool]:
    space = env.action_space
    if isinstance(space, gym.spaces.Discrete):
        return int(space.n), True
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
        return int(space.shape[0]), False
    raise LcrlError(f"unsupported action space {space}: need Discrete or a 1-D Box")


class Task:
    """Base class of a goal modality's adapter: storage layout, goals and episode fields
    for one environment (:data:`GOALS` names the subclass of each goal type).

    A subclass sets :attr:`obs_shapes` and :attr:`goal_space` in ``__init__`` and defines
    :meth:`storage_obs`, :meth:`goal`, :meth:`step_record`, :meth:`episode_fields` and
    :meth:`embed_goals`; :meth:`from_config` builds it for a run.
    """

    #: How the networks read the goals: a key of :data:`lcrl.nets.GOAL_ENCODERS`
    #: (``vector``, ``text``, ``onehot``, ``image``), which names the goal encoder; it
    #: also picks the learner's goal normaliser (:data:`lcrl.algos.GOAL_NORMALISERS`).
    goal_kind = "vector"
    #: Evaluation sets (seen instructions first).
    sets: tuple[str, ...] = ("train",)
    #: Size of the fixed task set whose ids are the goals (0: none).
    num_tasks: int = 0
    #: Episodes follow instructions (a language-goal wrapper is inside the env): they
    #: report their instruction and family, and evaluation reports its sets by name.
    instructed = False
    #: Goals are texts that the frozen text encoder embeds (free text can be asked).
    text_goals = False
    #: What a trained policy is asked with (:meth:`train.policies.policy.Policy.act`): ``text``
    #: (an instruction), ``task_id`` (an integer) or ``goal`` (a goal array, by default
    #: the observation's :attr:`goal_key`).
    query = "goal"
    #: The observation entry that holds the goal when none is given (``query="goal"``).
    goal_key: str | None = "desired_goal"

    # What instructions add (language goals; task ids over instructions in part). A task
    # without them keeps these defaults, so no caller has to probe for them.
    #: The instruction table (the training instructions first), or None: no instructions.
    table: list[str] | None = None
    #: How many of :attr:`table`'s instructions are trained on (the rest are held out).
    num_train: int = 0
    #: The frozen text encoder's embedding of every :attr:`table` row, or None.
    embeddings: np.ndarray | None = None
    #: Training instruction -> its row of :attr:`table` (what hindsight labels name), or
    #: None: nothing is relabelled by instruction.
    train_ids: dict[str, int] | None = None
    #: The compositional split the instructions come from (``captioner.splits``), or None.
    split: Any = None
    #: The instruction families its episodes follow (none: goals without instructions).
    families: tuple[str, ...] = ()
    #: What reads the instructions (the frozen encoder, or a reader over it), or None.
    encoder: Any = None
    #: A learned captioner / reward model that labels stored episodes, or None (the rule
    #: captioner does, where there are instructions).
    labeller: Any = None

    def phrasing_embeddings(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Training-only phrasings of the training instructions and how many each has
        (:meth:`LanguageTask.phrasing_embeddings`); None: none."""
        return None

    def grounding_targets(self) -> np.ndarray | None:
        """The object slots each instruction names, for the grounding loss
        (:meth:`LanguageTask.grounding_targets`); None: the goals name no object."""
        return None

    @classmethod
    def from_config(cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any) -> Task:
        """The task of an env config over ``env`` (``embed``: the text encoder, for
        text goals; ``kwargs``: a saved instruction table)."""
        return cls(env, image_obs=cfg.image_obs)  # type: ignore[call-arg]

    @staticmethod
    def start_info(env: gym.Env) -> Any:
        """What evaluation must read from the env when an episode starts, to know its
        goal (image goals: the goal frame); None for most tasks. A static method: it runs
        inside the evaluation's sub-envs, which may be other processes."""
        return None

    def eval_goal(self, obs: Mapping[str, Any], start: Any) -> Any:
        """The goal of an evaluation episode from its observation and :meth:`start_info`."""
        return self.goal(obs, None)  # type: ignore[arg-type]

    def outcome(self, env: gym.Env) -> dict[str, Any]:
        """How a finished episode is filed: its ``family`` (and for instruction-following
        tasks its ``instruction``)."""
        return {"family": "all"}

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

    #: Observation keys only the critics read (:meth:`use_privileged_critic`).
    privileged: tuple[str, ...] = ()

    def use_privileged_critic(self, env: gym.Env) -> None:
        """Store the simulator's true state for critics that read it while the actor reads
        what it acts from (an asymmetric actor-critic): ``privileged`` (and for
        instruction-following tasks ``privileged_initial``, the episode's first one).

        The true state is the env's ``privileged`` entry beside a perception estimate
        (``--env.perception``), or its ``observation`` when the actor reads camera frames
        and proprioception (``--env.image-obs``). Only :meth:`training_obs` writes it:
        acting never needs it.

        Raises:
            LcrlError: the actor reads the true state itself (nothing to keep apart).
        """
        space = env.observation_space
        source = "privileged" if "privileged" in space.spaces else "observation"
        if source == "observation" and not getattr(self, "image_obs", False):
            raise LcrlError(
                "--agent.privileged-critic keeps the true state for the critic apart from what "
                "the actor reads, but this actor reads the true state already: act from "
                "camera frames (--env.perception MODEL, or --env.image-obs)"
            )
        shape = tuple(space[source].shape)
        keys = ("privileged", "privileged_initial") if self.instructed else ("privileged",)
        self._privileged_source = source
        self.privileged = keys
        self.obs_shapes = {**self.obs_shapes, **dict.fromkeys(keys, shape)}

    #: Stored keys that the agent's fine-tuned perception reads (:meth:`use_perception_frames`).
    perceived: tuple[str, ...] = ()
    perceived_dim: int = 0

    def use_perception_frames(self, env: gym.Env) -> None:
        """Store the camera frame, the proprioception and the slot positions perception
        estimated in the episode's first frame instead of the estimate itself, so that the
        agent reads the frames through a perception model it fine-tunes
        (``agent.perception_lr``); the episode's first observation (``initial``) stays the
        estimate computed when it was seen.

        Raises:
            LcrlError: the env acts through no perception model.
        """
        from lcrl.perception import PerceivedSlots
        from train.environments.perception import find_perception

        wrapper = find_perception(env)
        if wrapper is None or getattr(self, "image_obs", False):
            raise LcrlError(
                "agent.perception_lr fine-tunes the perception model the policy acts through: "
                "set --env.perception MODEL (and not --env.image-obs)"
            )
        features = _slot_feature_flags(env)
        reader = PerceivedSlots(wrapper.model, *features)
        space = env.observation_space
        if (reader.out_dim,) != tuple(space["observation"].shape):
            raise LcrlError(
                f"perception's observation has {reader.out_dim} values, the env's "
                f"{tuple(space['observation'].shape)}"
            )
        lay = wrapper.model.layout
        shapes = {k: v for k, v in self.obs_shapes.items() if k != "observation"}
        self.obs_shapes = {
            **shapes,
            "image": tuple(space["image"].shape),
            "proprio": (lay.start,),
            "origin": (lay.count * lay.position_dims,),
        }
        self.perceived = PerceivedSlots.KEYS
        self.perceived_dim = reader.out_dim
        stored = self.storage_obs

        def storage_obs(obs: Mapping[str, Any], first: Mapping[str, Any]) -> dict[str, Any]:
            out = stored(obs, first)
            out.pop("observation", None)
            estimate = np.asarray(obs["observation"], np.float32)
            out["image"] = np.asarray(obs["image"], np.uint8)
            out["proprio"] = estimate[: lay.start].copy()
            out["origin"] = reader.origin(np.asarray(first["observation"], np.float32))
            return out

        self.storage_obs = storage_obs  # type: ignore[method-assign]

    def training_obs(
        self, obs: Mapping[str, Any], first: Mapping[str, Any]
    ) -> dict[str, np.ndarray]:
        """What the replay buffer stores of an observation: :meth:`storage_obs` (what the
        actor reads), and the true state for privileged critics."""
        out = self.storage_obs(obs, first)
        if self.privileged:
            source = self._privileged_source
            out["privileged"] = np.asarray(obs[source], np.float32)
            if "privileged_initial" in self.privileged:
                out["privileged_initial"] = np.asarray(first[source], np.float32)
        return out

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
            privileged=self.privileged,
            perceived=self.perceived,
            perceived_dim=self.perceived_dim,
            reward_range=self.goal_space.reward_range,
            success_ends=self.goal_space.terminate_on_success,
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
        # a goal far from what was achieved: the reward of a miss (sparse rewards)
        miss = float(np.asarray(reward_fn(probe, np.full_like(probe, 1e3))).reshape(-1)[0])
        self.reward_fn, self.success_reward, self.goal_dim = reward_fn, success, dim
        self.reward_range = (min(success, miss), max(success, miss))
        self.goal_space: StateGoals = StateGoals(
            dim, reward_fn, success_reward=success, reward_range=self.reward_range
        )
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
    goal_key = None  # the goal frame is drawn by the env: env.unwrapped.goal_image()

    def __init__(self, env: gym.Env, image_obs: bool = False) -> None:
        super().__init__(env, image_obs)
        if not callable(getattr(env.unwrapped, "goal_image", None)):
            raise LcrlError(
                f"{type(env.unwrapped).__name__} cannot draw its goal (no goal_image()): "
                "image goals need it"
            )
        shape = _image_shape(env)
        self.goal_space = ImageGoals(
            self.goal_dim,
            self.reward_fn,
            shape,
            success_reward=self.success_reward,
            reward_range=self.reward_range,
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

    @staticmethod
    def start_info(env: gym.Env) -> Any:
        """The goal frame, drawn when the episode starts."""
        return np.asarray(env.unwrapped.goal_image(), np.uint8)

    def eval_goal(self, obs: Mapping[str, Any], start: Any) -> Any:
        """The goal frame drawn at the start."""
        return start

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


def slot_attributes() -> tuple[int, ...]:
    """Colour then shape index of each object slot of the tabletops (slot ``k`` holds
    ``OBJECT_KINDS[k]``), the layout of :attr:`lcrl.nets.NetConfig.slot_attributes`."""
    from envs.scene import COLOURS, OBJECT_KINDS, SHAPES

    colours = list(COLOURS)
    return tuple(colours.index(c) for c, _ in OBJECT_KINDS) + tuple(
        SHAPES.index(s) for _, s in OBJECT_KINDS
    )


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
        phrasings: training-only phrasings embedded per training instruction
            (``env.phrasings``), 0: none.
    """

    goal_kind = "text"
    sets = ("train", "heldout", "paraphrase")
    instructed = True
    text_goals = True
    query = "text"

    @classmethod
    def from_config(
        cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any
    ) -> LanguageTask:
        """The language task of a config (``embed`` is required; ``kwargs`` may give a
        saved ``table`` and ``num_train``)."""
        if embed is None:
            raise LcrlError("language tasks need a text encoder")
        if cfg.tasks:
            kwargs["tasks"] = task_texts(cfg)
        return cls(env, embed, image_obs=cfg.image_obs, phrasings=cfg.phrasings, **kwargs)

    def outcome(self, env: gym.Env) -> dict[str, Any]:
        """The episode's instruction and its family (``free`` for unparsed text)."""
        wrapper = find_language_wrapper(env)
        family = wrapper.meaning.family if wrapper.meaning else "free"
        return {"instruction": wrapper.instruction, "family": family}

    def __init__(
        self,
        env: gym.Env,
        embed: Any,
        table: list[str] | None = None,
        num_train: int | None = None,
        image_obs: bool = False,
        tasks: tuple[str, ...] = (),
        phrasings: int = 0,
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
        self.phrasings = int(phrasings)
        self._phrasing_cache: tuple[np.ndarray, np.ndarray] | None = None
        space = env.observation_space
        shape = tuple(space["observation"].shape)
        self.obs_shapes = {"observation": shape, "initial": shape}
        self._setup_image_obs(env, image_obs)
        self.goal_space = LabelGoals(
            len(self.table), self.embeddings, num_relabel=self.num_train, terminate_on_success=True
        )

    def phrasing_embeddings(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Embeddings of up to :attr:`phrasings` training-only phrasings of every training
        instruction (:func:`captioner.phrasings.training_phrasings`), ``(num_train,
        phrasings, d)``, and how many each has; None when :attr:`phrasings` is 0. Embedded
        on the first call (training only)."""
        if self.phrasings <= 0:
            return None
        if self._phrasing_cache is None:
            self._phrasing_cache = self._embed_phrasings()
        return self._phrasing_cache

    def _embed_phrasings(self) -> tuple[np.ndarray, np.ndarray]:
        from captioner.grammar import try_parse
        from captioner.phrasings import training_phrasings

        count = self.phrasings
        counts = np.zeros(self.num_train, np.int64)
        texts: list[list[str]] = []
        for i, text in enumerate(self.table[: self.num_train]):
            meaning = try_parse(text)
            found = training_phrasings(meaning, count, seed=i) if meaning is not None else []
            texts.append(found)
            counts[i] = len(found)
        flat = [t for group in texts for t in group]
        d = self.embeddings.shape[1]
        out = np.zeros((self.num_train, count, d), np.float32)
        if flat:
            vectors = np.asarray(self.embed_fn(flat), np.float32)
            k = 0
            for i, group in enumerate(texts):
                out[i, : len(group)] = vectors[k : k + len(group)]
                k += len(group)
        return out, counts

    def grounding_targets(self) -> np.ndarray:
        """Per instruction id, the object slots it names, as the grammar parses it: the
        kind acted on and the reference object of put and stack, ``(ids, 2)``, -1 where
        there is none (slot ``k`` of both tabletops holds ``OBJECT_KINDS[k]``)."""
        from captioner.grammar import try_parse
        from envs.scene import OBJECT_KINDS

        out = np.full((len(self.table), 2), -1, np.int64)
        for i, text in enumerate(self.table):
            meaning = try_parse(text)
            if meaning is None:
                continue
            out[i, 0] = OBJECT_KINDS.index((meaning.colour, meaning.shape))
            if meaning.target_colour is not None and meaning.target_shape is not None:
                out[i, 1] = OBJECT_KINDS.index((meaning.target_colour, meaning.target_shape))
        return out

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

    # labeller (Task): a learned captioner / reward model
    # (:class:`captioner.learned.LearnedLabeller`) that labels stored episodes from camera
    # frames; None: the rule captioner does.

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The scene after each step (captioned at the end of the episode), with the
        camera frame and the robot's state when a learned labeller reads them."""
        wrapper = find_language_wrapper(env)  # the env that stepped (one of several)
        scene = wrapper.env.unwrapped.scene()
        if self.labeller is None:
            return scene
        if "image" not in obs:
            raise LcrlError("learned relabelling needs camera frames: the env gives no image")
        start = int(slot_layout_start(wrapper))
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
        if lab.use_reward:
            if lab.reward_labels:  # every training instruction is a candidate
                cands = sorted(set(range(lab.num_train)) | {int(goal)})
            else:
                cands = sorted({i for ids in out["labels"] for i in ids} | {int(goal)})
            out["achieved"] = lab.achieved(frames, proprio, cands, out["labels"])
            lab.compare("rewards", out["achieved"], labels, among=cands)
            if lab.reward_labels:  # relabel with what the reward model judges achieved
                out["labels"] = [[i for i in a if i < lab.num_train] for a in out["achieved"]]
            elif lab.use_captioner:  # with confirm: only the labels rewarded where read
                out["labels"] = lab.confirmed(out["labels"], out["achieved"])
        if lab.use_captioner or lab.reward_labels:
            lab.compare("labels", out["labels"], labels)
        if lab.use_captioner and not lab.use_reward and not lab.captioner_rewards:
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
    instructed = True
    query = "task_id"

    @classmethod
    def from_config(
        cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any
    ) -> TaskIdTask:
        """The task-id task of a config's task set."""
        return cls(env, task_texts(cfg), image_obs=cfg.image_obs)

    #: the instruction and family, as language goals report them
    outcome = LanguageTask.outcome

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
        return find_language_wrapper(env).env.unwrapped.scene()

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
        teacher: use the env's controller that reads everything off the scene
            (:attr:`EnvSpec.teacher`, where it has one), to label states it did not lead to.

    Raises:
        LcrlError: the env has no scripted controller.
    """

    def __init__(self, cfg: EnvConfig, task: Task, noise: float, teacher: bool = False) -> None:
        spec = env_spec(cfg.kind)
        if not has_instructions(cfg) or spec.scripted is None:
            raise LcrlError(
                "scripted episodes need language or task goals on a simulator with a scripted "
                f"controller (env kind {cfg.kind!r}, goal type {cfg.goal_type!r} has none)"
            )
        make = spec.teacher if teacher and spec.teacher is not None else spec.scripted
        self.controller: Any = make()
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


def features_wrapper(env: gym.Env) -> Any:
    """The :class:`envs.features.SlotFeatures` with displacements inside ``env``, if any."""
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if getattr(e, "displacement", False) and hasattr(e, "restart_displacements"):
            return e
        e = e.env
    return None


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
    out = dict(obs)
    out["instruction"] = wrapper.instruction
    features = features_wrapper(env)
    if features is not None:
        out["observation"] = features.restart_displacements()
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

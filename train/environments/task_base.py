"""The task base class and the tasks of goal vectors and goal frames, with the helpers that
read an environment's wrappers and observation layout (re-exported by
:mod:`train.environments.tasks`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.algos import Problem
from lcrl.errors import LcrlError
from lcrl.goals import ImageGoals, StateGoals
from train.environments.simulators import EnvConfig


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


def task_texts(cfg: EnvConfig) -> tuple[str, ...]:
    """The config's task set with whitespace normalised (what the env's observations say)."""
    return tuple(" ".join(str(t).split()) for t in cfg.tasks)


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

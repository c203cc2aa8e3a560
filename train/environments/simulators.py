"""The environment registry: one entry per simulator, and the config that picks one.

:data:`ENVS` maps a simulator's name (``EnvConfig.kind``) to an :class:`EnvSpec`: how to
build the bare simulator for a config, the goal types it supports, its instruction
families, its scripted controller, how to read its privileged scene and how evaluation
should vectorise it. The goal type (``EnvConfig.goal_type``) is a separate choice, looked
up in :data:`train.environments.tasks.GOALS`; it decides how the simulator is wrapped
(instructions or
goal vectors) and how its episodes are stored and relabelled.

Adding a simulator is one new module with a factory plus one line here (or, from user
code, ``ENVS["mine"] = EnvSpec(...)``): see ``docs/extending.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym

from lcrl.errors import LcrlError

#: Kinds of earlier versions: ``lang2d`` was the 2D tabletop with instructions (language
#: goals, or task ids of instructions), ``state2d`` the 2D tabletop with state goals.
#: Saved configs and the command line still take them: ``{old: (kind, goal_type or None)}``.
KIND_ALIASES: dict[str, tuple[str, str | None]] = {
    "lang2d": ("tabletop2d", None),
    "state2d": ("tabletop2d", "state"),
}


@dataclass
class EnvConfig:
    """Which environment to train on: a simulator (``kind``) and a goal type."""

    kind: str = "tabletop2d"
    """The simulator (:data:`train.environments.simulators.ENVS`): ``tabletop2d`` (the fast 2D
    tabletop), ``robosuite`` (the Panda tabletop) or ``gym`` (any registered goal env,
    e.g. gymnasium-robotics ``FetchReach-v4``). The older names ``lang2d`` (= tabletop2d)
    and ``state2d`` (= tabletop2d with ``goal_type=state``) are still accepted."""
    goal_type: str = ""
    """Goals (:data:`train.environments.tasks.GOALS`): ``language`` (instructions), ``task``
    (one-hot
    ids of the ``tasks``: the policy never sees their text), ``state`` (object, pusher or
    gripper positions, see ``goal``; the only goal type of ``gym``) or ``image`` (a camera
    frame of the goal layout; robosuite). Empty: the simulator's first goal type
    (``language`` on the tabletops, ``state`` on ``gym``)."""
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
    phrasings: int = 0
    """Instruction augmentation (language goals): up to this many other phrasings of
    every training instruction, with synonyms and templates the grammar does not know
    (:mod:`captioner.phrasings`), are embedded once; in every update half the rows read
    one of them instead of the instruction itself. The grammar's own synonyms stay
    unseen, for the ``paraphrase`` evaluation set. 0: off."""
    text_reader: bool = False
    """Language goals: read instructions at the token level as well. A small reader
    (learned queries over the frozen encoder's token states, :mod:`lcrl.text_reader`) is
    trained before reinforcement learning to predict each training instruction's meaning
    (family, colours, shapes, direction, relation) from it and from 16 training-only
    phrasings of it; the goal vector is then the sentence vector followed by the reader's
    slot-value probabilities. The reader is frozen and saved with the checkpoints."""
    canonical_reader: bool = False
    """Language goals: the same reader, trained the same way, turns every instruction into
    the canonical sentence of the meaning it reads ("nudge the red block left" -> "push the
    red cube left"), and the policy reads that sentence's vector: unseen phrasings of a
    meaning reach the policy as the sentence it trained on. The policy is the one a run
    without a reader trains (canonical captions read as themselves), so ``lcrl eval
    --canonical-reader`` can put a reader in front of any language checkpoint. Every
    instruction becomes some meaning of the grammar, within the values the run's training
    instructions use. Not with ``text_reader``."""
    min_objects: int = 2
    """Fewest objects on the table."""
    max_objects: int = 3
    """Most objects on the table."""
    discrete: bool = False
    """Discrete pusher moves (8 directions) instead of continuous ones (2D tabletop)."""
    max_episode_steps: int = 50
    """Time limit of an episode (a truncation: the value bootstraps through it)."""
    goal: str = "object"
    """State and image goals: ``object`` (all object positions), ``pusher`` (2D) or
    ``gripper`` (robosuite)."""
    relative_positions: bool = False
    """Add each object's position relative to the gripper (pusher) to its observation
    slot (:class:`envs.features.RelativePositions`); pair with ``--agent.net.slots``
    ``(2, 8, 5)`` on the 2D tabletop or ``(4, 8, 7)`` on robosuite."""
    displacements: bool = False
    """Add each object's displacement since the episode's reset to its observation slot
    (:class:`envs.features.SlotFeatures`): push and put are judged on it. Widens each slot
    by 2 values on the 2D tabletop (3 on robosuite); set ``--agent.net.slots`` to match."""
    initial: bool = True
    """Language and task goals: the policy also reads the observation at the start of its
    instruction (``initial``). ``False``: the current observation only, which with
    ``displacements`` still says what moved since the instruction began; the next
    instruction of a chain then looks to the policy like a first one (its gripper
    anywhere), not like a start it rarely saw."""
    perception: str = ""
    """A perception model (``lcrl perception train --out``): the policy's ``observation``
    is its estimate of the object slots from the camera frame and the proprioception
    instead of the privileged state (:class:`train.environments.perception.PerceptionObservation`;
    frozen, computed once per frame). The frames are rendered at the model's size."""
    perception_hold_radius: float | None = None
    """Object permanence of perception's estimate (:class:`lcrl.perception.HeldSlots`): an
    object's estimated position is held while the gripper is farther than this from it
    (metres); 0 takes every frame's own estimate. Default: the perception model's own
    ``hold_radius``. ``lcrl eval --hold-radius`` sets it for a saved policy."""
    train_until_success: bool = True
    """Language goals: training episodes end when their instruction is achieved. ``False``
    runs them to the time limit and keeps what happens after the success (an object
    touched, then pushed), which the relabelled goals learn from; the value target still
    ends at the success step. Evaluation episodes always end at success."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the environment constructor."""

    def __post_init__(self) -> None:
        # the kinds of earlier versions mixed the simulator with the goal type
        alias = KIND_ALIASES.get(self.kind)
        if alias is not None:
            self.kind = alias[0]
            if alias[1] is not None:
                self.goal_type = alias[1]
        if not self.goal_type and self.kind in ENVS:
            self.goal_type = ENVS[self.kind].goal_types[0]


@dataclass(frozen=True)
class EnvSpec:
    """One simulator of :data:`ENVS`.

    Attributes:
        make: ``cfg -> env``: the bare simulator for a config (constructor options, the
            observation feature wrappers it asks for), before the goal type's wrapping and
            time limit.
        goal_types: the goal types (:data:`train.environments.tasks.GOALS` keys) it supports.
        summary: a few words naming it in reports and error messages; a format string
            over the config's fields (``"{gym_id}"``).
        families: instruction families of its rule captioner (language and task goals).
        scripted: ``() -> controller`` with ``act(meaning, s0, scene)`` (and optionally
            ``reset()``): the scripted controller of scripted training episodes and
            demonstrations; None: it has none.
        teacher: ``() -> controller`` like ``scripted``, whose action is a function of the
            scene alone (no phase memory), for labelling the states a student visits
            (``lcrl distill --teacher-for FAMILY=scripted``); None: ``scripted`` does.
        scene: ``env -> SceneState``: the privileged scene of the unwrapped env (what the
            rule captioner reads); None: it has none.
        time_limit: whether :func:`train.environments.tasks.make_env` adds the ``max_episode_steps``
            time limit (False when ``make`` already does, as ``gym.make`` does).
        step_cost: ``fast`` (microseconds a step: evaluation steps sub-envs in one
            process) or ``slow`` (physics and cameras: a process per sub-env).
        caption_name: the name its caption datasets and learned captioners record.
        slot_layout: ``(start, count, width, position_dims)`` of the bare simulator's
            object slots in its ``observation`` (what :func:`envs.features.slot_layout`
            reads from the env class; ``tests/test_tasks.py`` checks the two agree), for
            readers of the registry; None: it has no object slots (``gym``).
    """

    make: Callable[[EnvConfig], gym.Env]
    goal_types: tuple[str, ...]
    summary: str = ""
    families: tuple[str, ...] = ()
    scripted: Callable[[], Any] | None = None
    teacher: Callable[[], Any] | None = None
    scene: Callable[[gym.Env], Any] | None = None
    time_limit: bool = True
    step_cost: str = "fast"
    caption_name: str = ""
    slot_layout: tuple[int, int, int, int] | None = None


def env_spec(kind: str) -> EnvSpec:
    """The registry entry of a simulator (older kind names accepted).

    Raises:
        LcrlError: no simulator of that name.
    """
    kind = KIND_ALIASES.get(kind, (kind, None))[0]
    spec = ENVS.get(kind)
    if spec is None:
        raise LcrlError(f"unknown env kind {kind!r}; choose one of {tuple(ENVS)}")
    return spec


def describe(env: dict[str, Any] | EnvConfig) -> str:
    """The name of a config's simulator in reports (``2D tabletop``, a gym id); a saved
    config's env dict is taken as well as an :class:`EnvConfig`."""
    fields = dict(vars(env)) if isinstance(env, EnvConfig) else dict(env)
    kind = str(fields.get("kind", "?"))
    spec = ENVS.get(KIND_ALIASES.get(kind, (kind, None))[0])
    if spec is None or not spec.summary:
        return kind
    try:
        return spec.summary.format_map(fields)
    except (KeyError, ValueError):
        return spec.summary


def canonical_kind(name: str) -> str:
    """The simulator a kind or caption-dataset name stands for (``lang2d`` ->
    ``tabletop2d``); unknown names are returned as given."""
    name = KIND_ALIASES.get(name, (name, None))[0]
    for kind, spec in ENVS.items():
        if name == spec.caption_name:
            return kind
    return name


def check_env_config(cfg: EnvConfig) -> EnvSpec:
    """Refuse an env config that cannot be built: an unknown simulator, a goal type it
    does not support, instruction families outside its captioner's, or bad object counts.

    Returns:
        The simulator's registry entry.
    """
    spec = env_spec(cfg.kind)
    if cfg.goal_type not in spec.goal_types:
        raise LcrlError(
            f"the {cfg.kind} env supports the goal types {spec.goal_types}, not "
            f"{cfg.goal_type!r}: set env.goal_type (--env.goal-type)"
        )
    if cfg.min_objects > cfg.max_objects:
        raise LcrlError(
            f"min_objects ({cfg.min_objects}) is larger than max_objects ({cfg.max_objects})"
        )
    radius = cfg.perception_hold_radius
    if radius is not None:
        if not cfg.perception:
            raise LcrlError(
                "env.perception_hold_radius holds perception's estimates: set "
                "--env.perception MODEL too"
            )
        if not radius >= 0:
            raise LcrlError(f"env.perception_hold_radius must be >= 0, got {radius}")
    if cfg.text_reader and cfg.canonical_reader:
        raise LcrlError(
            "env.text_reader and env.canonical_reader are two ways to use the reader: "
            "choose one (--env.text-reader or --env.canonical-reader)"
        )
    return spec


def features(env: gym.Env, cfg: EnvConfig) -> gym.Env:
    """The observation wrappers a config asks for: perception's estimate of the object
    slots, then relative positions and displacements since the reset."""
    if cfg.perception:
        from train.environments.perception import PerceptionObservation

        env = PerceptionObservation(env, cfg.perception, cfg.perception_hold_radius)
    if cfg.relative_positions or cfg.displacements:
        from envs.features import SlotFeatures

        return SlotFeatures(env, relative=cfg.relative_positions, displacement=cfg.displacements)
    return env


def frame_size(cfg: EnvConfig) -> int:
    """The camera frame side to render: a perception model's own (it reads frames of the
    size it was trained on), else ``cfg.image_size``."""
    if not cfg.perception:
        return cfg.image_size
    from train.environments.perception import model_meta

    return int(model_meta(cfg.perception)["frame_shape"][0])


def unwrapped_scene(env: gym.Env) -> Any:
    """The privileged scene of a tabletop (``env.unwrapped.scene()``)."""
    return env.unwrapped.scene()


# --- the simulators ---------------------------------------------------------------------------
def make_tabletop2d(cfg: EnvConfig) -> gym.Env:
    """The 2D tabletop (:class:`envs.tabletop2d.Tabletop2DEnv`) for a config."""
    from envs.tabletop2d import Tabletop2DEnv

    kwargs: dict[str, Any] = {
        "num_objects": (cfg.min_objects, cfg.max_objects),
        "action_type": "discrete" if cfg.discrete else "continuous",
        **cfg.extra,
    }
    if cfg.discrete:
        kwargs.setdefault("num_directions", 8)
    if cfg.image_obs or cfg.perception:
        kwargs.update(image=True, image_size=frame_size(cfg))
    if cfg.goal_type in ("state", "image"):
        kwargs["goal"] = cfg.goal
    return features(Tabletop2DEnv(**kwargs), cfg)


def make_robosuite(cfg: EnvConfig) -> gym.Env:
    """The robosuite Panda tabletop (:class:`envs.robosuite_tabletop.RobosuiteTabletopEnv`)
    for a config: state and image goals use ``cfg.goal`` (``pusher`` means the gripper)."""
    from envs.robosuite_tabletop import RobosuiteTabletopEnv

    kwargs: dict[str, Any] = {"num_objects": (cfg.min_objects, cfg.max_objects), **cfg.extra}
    if cfg.image_obs or cfg.goal_type == "image" or cfg.perception:
        kwargs.update(image=True, image_size=frame_size(cfg))
    if cfg.goal_type in ("state", "image"):
        goal = {"pusher": "gripper"}.get(cfg.goal, cfg.goal)
        if cfg.goal_type == "image" and goal != "object":
            raise LcrlError("image goals on the robosuite tabletop need goal='object'")
        kwargs["goal"] = goal
    return features(RobosuiteTabletopEnv(**kwargs), cfg)


def make_gym(cfg: EnvConfig) -> gym.Env:
    """Any registered gymnasium goal env (``cfg.gym_id``), with its time limit."""
    try:
        import gymnasium_robotics
    except ImportError:
        pass
    else:
        gym.register_envs(gymnasium_robotics)
    try:
        return gym.make(
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


def _scripted_2d() -> Any:
    from captioner.scripted import ScriptedController2D

    return ScriptedController2D()


def _scripted_3d() -> Any:
    from captioner.scripted3d import ScriptedController3D

    return ScriptedController3D()


def _teacher_3d(funnel: float = 0.0) -> Any:
    from captioner.scripted3d import MarkovController3D

    return MarkovController3D(funnel=funnel)


def _families(name: str) -> tuple[str, ...]:
    from captioner import grammar

    return tuple(getattr(grammar, name))


#: Every simulator, by ``EnvConfig.kind``.
ENVS: dict[str, EnvSpec] = {
    "tabletop2d": EnvSpec(
        make=make_tabletop2d,
        goal_types=("language", "task", "state"),
        summary="2D tabletop",
        families=_families("FAMILIES_2D"),
        scripted=_scripted_2d,
        scene=unwrapped_scene,
        caption_name="lang2d",
        slot_layout=(2, 8, 3, 2),  # pusher x, y; 8 object kinds of x, y, present
    ),
    "robosuite": EnvSpec(
        make=make_robosuite,
        goal_types=("language", "task", "state", "image"),
        summary="robosuite tabletop",
        families=_families("FAMILIES"),
        scripted=_scripted_3d,
        teacher=_teacher_3d,
        scene=unwrapped_scene,
        step_cost="slow",
        caption_name="robosuite",
        slot_layout=(4, 8, 4, 3),  # gripper x, y, z, opening; 8 kinds of x, y, z, present
    ),
    "gym": EnvSpec(
        make=make_gym,
        goal_types=("state",),
        summary="{gym_id}",
        time_limit=False,
    ),
}

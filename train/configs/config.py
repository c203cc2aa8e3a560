"""Training configuration: typed dataclasses, one docstring per field, validated where a
config is made; read from and written to dicts (:func:`config_from_dict`). The named
presets are in :mod:`train.configs.presets`.

``lcrl train PRESET [--field value ...]`` starts from a preset and overrides any field;
``lcrl train PRESET --help`` lists every field with its documentation and default.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from lcrl.algos import (
    ALGOS,
    AgentOptions,
    BCConfig,
    CRLConfig,
    DQNConfig,
    SACConfig,
    TD3Config,
    check_algo,
    check_multitask,
    resolve_algo,
)
from lcrl.errors import LcrlError
from lcrl.goals import STRATEGIES, TASK_RELABEL_ERROR
from lcrl.nets import check_task_heads
from lcrl.text_encoder import TextEncoderConfig
from train.configs.sections import (
    BUFFER_STORAGE as BUFFER_STORAGE,
    COLLECT_BACKENDS as COLLECT_BACKENDS,
    EPISODE_ENDS as EPISODE_ENDS,
    RELABELLERS as RELABELLERS,
    REWARDERS as REWARDERS,
    BufferConfig as BufferConfig,
    CollectionConfig as CollectionConfig,
    DistillConfig as DistillConfig,
    ExploreConfig as ExploreConfig,
    FinetuneConfig as FinetuneConfig,
    RelabelConfig as RelabelConfig,
    SequentialConfig as SequentialConfig,
    family_teachers as family_teachers,
    family_thresholds as family_thresholds,
)
from train.environments.tasks import (
    EnvConfig,
    check_tasks,
    goal_modality,
    is_language,
)

#: Learners of ``lcrl train --offline FILE``, with what each does there.
OFFLINE_ALGOS = {
    "td3": "TD3+BC",
    "crl": "contrastive RL",
    "bc": "goal-conditioned BC",
}


@dataclass
class TrainConfig:
    """One training run: environment, learner, schedule, evaluation and outputs."""

    out: str = "runs/train"
    """Run folder: config.json, progress.csv, eval.csv, TensorBoard events, checkpoints."""
    env: EnvConfig = field(default_factory=EnvConfig)
    """The environment."""
    algo: str = "auto"
    """``sac``, ``td3``, ``crl`` (contrastive RL), ``dqn``, ``bc`` (behavioural cloning
    from ``--demos``), or ``auto`` (SAC for continuous, DQN for discrete actions)."""
    sac: SACConfig = field(default_factory=SACConfig)
    """SAC hyper-parameters."""
    td3: TD3Config = field(default_factory=TD3Config)
    """TD3 hyper-parameters."""
    crl: CRLConfig = field(default_factory=CRLConfig)
    """Contrastive-RL hyper-parameters."""
    dqn: DQNConfig = field(default_factory=DQNConfig)
    """Double-DQN hyper-parameters."""
    bc: BCConfig = field(default_factory=BCConfig)
    """Behavioural-cloning hyper-parameters (``algo=bc``)."""
    distill: DistillConfig = field(default_factory=DistillConfig)
    """Teacher -> student distillation (``lcrl distill``; the student is a ``bc`` policy
    and ``total_steps``, ``eval_every``, ``checkpoint_every`` and ``log_every`` count DAgger
    rounds)."""
    demos: str = ""
    """Demonstration file (``lcrl demos record``) that ``algo=bc`` learns from. With
    ``bc``, ``total_steps``, ``eval_every``, ``checkpoint_every`` and ``log_every`` count
    gradient updates instead of environment steps."""
    offline: str = ""
    """Learn offline from this HDF5 dataset (``lcrl demos record``, random play with
    ``--actor random``, an import) through the replay buffer and its hindsight
    relabelling, stepping no environment except to evaluate (``--algo td3``: TD3+BC,
    ``--algo crl``: contrastive RL, ``--algo bc``: goal-conditioned BC). ``total_steps``
    and the ``*_every`` settings then count gradient updates."""
    agent: AgentOptions = field(default_factory=AgentOptions)
    """Networks, normalisation, device and seed of the learner."""
    buffer: BufferConfig = field(default_factory=BufferConfig)
    """Replay buffer and relabelling."""
    relabel: RelabelConfig = field(default_factory=RelabelConfig)
    """Rule or learned captioner and reward model (language goals)."""
    text_encoder: TextEncoderConfig = field(default_factory=TextEncoderConfig)
    """Frozen text encoder for language goals."""
    sequential: SequentialConfig = field(default_factory=SequentialConfig)
    """Task groups trained one after another (forgetting, replay, EWC)."""
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    """BC -> RL fine-tuning from a demonstration file (SAC)."""
    collect: CollectionConfig = field(default_factory=CollectionConfig)
    """How training episodes are collected (environments stepped at once)."""
    explore: ExploreConfig = field(default_factory=ExploreConfig)
    """Training on chains of instructions, starts along scripted demonstrations and a
    curriculum over families (language goals)."""
    torch_threads: int = 0
    """Torch threads of the training process; 0: the cores this process may use, divided
    among the training processes lcrl runs at once (``LCRL_PROCESSES``, set by the
    benchmark runners that train configurations side by side), never more busy threads
    than cores."""
    total_steps: int = 100_000
    """Environment steps to train for."""
    learning_starts: int = 1_000
    """Steps of uniformly random actions before learning starts."""
    random_action_repeat: int = 1
    """Hold each random action of the first ``learning_starts`` steps for this many steps
    (1: a fresh action every step). Held actions travel further, so a random pusher
    touches and pushes more objects and the captioner has more to label."""
    scripted_fraction: float = 0.0
    """Fraction of training episodes acted by the env's scripted controller instead of the
    policy (language goals on both tabletops). They are stored, captioned, relabelled and
    counted in ``total_steps`` like any other episode: an exploration aid for families
    whose first success a policy rarely stumbles on (push). 0 is pure reinforcement
    learning. Evaluation always runs the policy."""
    scripted_noise: float = 0.3
    """Standard deviation of the Gaussian noise added to the scripted controller's actions
    (in ``[-1, 1]`` units), so that scripted episodes also show near misses."""
    batch_size: int = 256
    """Transitions per update."""
    updates_per_step: float = 1.0
    """Gradient updates per environment step (fractions update every few steps)."""
    eval_every: int = 10_000
    """Evaluate every this many steps (0: only at the end)."""
    eval_episodes: int = 50
    """Episodes per evaluation set (seen instructions, held-out combinations ...)."""
    eval_sets: tuple[str, ...] = ()
    """Sets of the evaluations every ``eval_every`` (e.g. ``("train",)``: seen
    instructions only); empty: every set of the task. The final evaluation covers every
    set whatever this says."""
    checkpoint_every: int = 25_000
    """Checkpoint every this many steps (0: only at the end and on Ctrl-C)."""
    keep_checkpoints: int = 2
    """How many of the latest checkpoints to keep."""
    save_buffer: bool = True
    """Save the replay buffer with checkpoints so that ``--resume`` continues exactly."""
    resume: bool = False
    """Continue the run in ``out`` from its latest checkpoint, with its saved config (only
    ``total_steps`` is taken from the command line)."""
    overwrite: bool = False
    """Replace a previous run in ``out`` (its checkpoints and logs) instead of refusing."""
    seed: int = 0
    """Seed of the environment resets and the buffer (the learner has ``agent.seed``)."""
    log_every: int = 1_000
    """Write a progress.csv row every this many steps."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files (needs the ``tensorboard`` package)."""

    def resolved_algo(self, discrete: bool) -> str:
        """The algorithm after resolving ``auto`` (``bc`` for behavioural cloning)."""
        return resolve_algo(self.algo, discrete)

    def validate(self, files: bool = True) -> None:
        """Raise :class:`LcrlError` for inconsistent settings; ``files``: also for input
        files that are missing (not for a saved run's config, read to act or evaluate)."""
        check_algo(self.algo)
        # the chosen algorithm's config (for auto: both algorithms it may resolve to)
        for name in dict.fromkeys(resolve_algo(self.algo, d) for d in (False, True)):
            getattr(self, name).validate()
        if self.offline and self.demos:
            raise LcrlError("--offline and --demos are two data sources: give one")
        if self.offline and self.algo not in OFFLINE_ALGOS:
            names = [f"{k} ({v})" for k, v in OFFLINE_ALGOS.items()]
            raise LcrlError(f"--offline trains with --algo {', '.join(names[:-1])} or {names[-1]}")
        if self.demos and (self.algo == "auto" or ALGOS[self.algo].learns_from != "demos"):
            learners = [name for name, spec in ALGOS.items() if spec.learns_from == "demos"]
            raise LcrlError(
                f"--demos is read by behavioural cloning only: add --algo {' or '.join(learners)}"
                " (or train a -bc preset such as lang2d-bc)"
            )
        if self.buffer.strategy not in STRATEGIES:
            raise LcrlError(
                f"unknown relabelling strategy {self.buffer.strategy!r}; choose one of {STRATEGIES}"
            )
        for name in (
            "total_steps",
            "batch_size",
            "eval_episodes",
            "log_every",
            "random_action_repeat",
        ):
            if getattr(self, name) <= 0:
                raise LcrlError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("learning_starts", "eval_every", "checkpoint_every"):
            if getattr(self, name) < 0:
                raise LcrlError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.updates_per_step < 0:
            raise LcrlError("updates_per_step must be >= 0")
        if self.buffer.k < 0:
            raise LcrlError("buffer.k must be >= 0")
        if self.buffer.capacity < 2:
            raise LcrlError(f"buffer.capacity must be at least 2 slots, got {self.buffer.capacity}")
        if self.buffer.storage not in BUFFER_STORAGE:
            raise LcrlError(
                f"buffer.storage must be one of {BUFFER_STORAGE}, got {self.buffer.storage!r}"
            )
        if not 0.0 <= self.scripted_fraction <= 1.0:
            raise LcrlError(f"scripted_fraction must be in [0, 1], got {self.scripted_fraction}")
        if self.scripted_noise < 0:
            raise LcrlError(f"scripted_noise must be >= 0, got {self.scripted_noise}")
        for name, allowed in (("captioner", RELABELLERS), ("reward", REWARDERS)):
            if getattr(self.relabel, name) not in allowed:
                raise LcrlError(
                    f"relabel.{name} must be one of {allowed}, got {getattr(self.relabel, name)!r}"
                )
        if self.relabel.reward == "captioner" and self.relabel.captioner != "learned":
            raise LcrlError(
                "relabel.reward=captioner takes the rewards from the learned captioner's "
                "captions: it needs relabel.captioner=learned"
            )
        both_learned = (self.relabel.captioner, self.relabel.reward) == ("learned", "learned")
        for name, what in (
            ("agree", "asks the learned captioner and reward model to agree"),
            ("confirm", "keeps the learned captions the reward model confirms"),
        ):
            if getattr(self.relabel, name) and not both_learned:
                raise LcrlError(
                    f"relabel.{name} {what}: it needs relabel.captioner=learned and "
                    "relabel.reward=learned"
                )
        if self.relabel.captioner in ("reward", "both") and self.relabel.reward != "learned":
            raise LcrlError(
                f"relabel.captioner={self.relabel.captioner} relabels with what the learned "
                "reward model judges achieved: it needs relabel.reward=learned"
            )
        family_thresholds(self.relabel.family_thresholds)  # raises on a bad entry
        if self.relabel.end not in EPISODE_ENDS:
            raise LcrlError(f"relabel.end must be one of {EPISODE_ENDS}, got {self.relabel.end!r}")
        from captioner.grammar import FAMILIES

        bad = [f for f in self.relabel.end_families if f not in FAMILIES]
        if bad:
            raise LcrlError(f"relabel.end_families must be among {FAMILIES}, got {bad}")
        if self.relabel.end_families and self.relabel.end != "learned":
            raise LcrlError("relabel.end_families needs relabel.end=learned")
        if self.relabel.end == "learned" and self.relabel.reward != "learned":
            raise LcrlError(
                "relabel.end=learned ends training episodes where the learned reward model "
                "says so: it needs relabel.reward=learned"
            )
        if self.relabel.learned and not self.relabel.checkpoint:
            raise LcrlError(
                "learned relabelling needs --relabel.checkpoint (train one with lcrl caption train)"
            )
        self.collect.validate()
        self.explore.validate(tuple(self.env.families))
        if self.explore.active:
            self._validate_explore()
        self.sequential.validate(tuple(self.env.families), self.algo)
        self.finetune.validate(self.algo, files)
        if self.finetune.demos and (self.offline or self.demos):
            raise LcrlError("--finetune.demos trains online: not with --offline or --demos")
        if self.sequential.stages and self.collect.backend != "local":
            raise LcrlError("sequential.stages train with collect.backend local")
        if self.collect.backend == "ray" and self.relabel.learned:
            raise LcrlError(
                "learned relabelling reads camera frames in the learner: use "
                "collect.backend local with relabel.captioner/reward learned"
            )
        if self.torch_threads < 0:
            raise LcrlError(f"torch_threads must be >= 0 (0: automatic), got {self.torch_threads}")
        if self.keep_checkpoints < 1:
            raise LcrlError("keep_checkpoints must be at least 1")
        self.distill.validate()
        if self.agent.perception_lr < 0:
            raise LcrlError(f"agent.perception_lr must be >= 0, got {self.agent.perception_lr}")
        if self.agent.perception_lr > 0:
            if not self.env.perception:
                raise LcrlError(
                    "agent.perception_lr fine-tunes the perception model the policy acts "
                    "through: set --env.perception MODEL"
                )
            mt = self.agent.multitask
            if mt.pcgrad or mt.conflict_every > 0:
                raise LcrlError(
                    "agent.perception_lr cannot be combined with per-task gradients (PCGrad, "
                    "multitask.conflict_every): the frames would be read once per task"
                )
        self._validate_tasks()

    def _validate_explore(self) -> None:
        """Chains, hand-overs and curricula need language goals in the local loop."""
        if not is_language(self.env):
            raise LcrlError(
                "explore.chain, explore.handover and explore.curriculum train language goals "
                f"(this run's goal type is {self.env.goal_type!r})"
            )
        if self.env.tasks:
            raise LcrlError("explore.* draw instructions: not with a fixed task set (env.tasks)")
        if self.collect.backend != "local":
            raise LcrlError("explore.* train with collect.backend local")
        if self.offline or self.demos:
            raise LcrlError("explore.* shape online episodes: not with --offline or --demos")
        if self.explore.curriculum and self.sequential.stages:
            raise LcrlError("explore.curriculum and sequential.stages both order the families")
        if self.explore.chain and self.env.perception:
            raise LcrlError("explore.chain is not supported with env.perception yet")
        if self.explore.prelude:
            from train.environments.simulators import env_spec

            spec = env_spec(self.env.kind)
            if spec.teacher is None and spec.scripted is None:
                raise LcrlError(
                    f"explore.prelude needs the env's scripted teacher; the {self.env.kind} env "
                    "has none"
                )
            bad = [f for f in self.explore.prelude_families if f not in spec.families]
            if bad:
                raise LcrlError(
                    f"explore.prelude_families names {', '.join(bad)}; the {self.env.kind} env "
                    f"has the families {spec.families}"
                )
            if self.env.perception:
                raise LcrlError("explore.prelude is not supported with env.perception yet")

    def _validate_tasks(self) -> None:
        """Multi-task settings: the task set, no relabelling over task ids, per-task heads
        only over task ids, the multitask options (before any env is built)."""
        env = self.env
        check_tasks(env)
        modality = goal_modality(env.goal_type)
        if not modality.relabel and (self.buffer.k > 0 or self.buffer.random_fraction > 0):
            raise LcrlError(TASK_RELABEL_ERROR)
        check_task_heads(self.agent.net, modality.task.goal_kind, (len(env.tasks),))
        mt = self.agent.multitask
        mt.validate(len(env.tasks))
        check_multitask(self.algo, mt)


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A dataclass config as a JSON-able dict."""
    return dataclasses.asdict(cfg)


class ConfigFieldError(LcrlError):
    """A saved config's field holds a value of the wrong type.

    Attributes:
        field: the field's dotted name (``agent.net.hidden``, with the prefix given to
            :func:`config_from_dict`).
    """

    def __init__(self, field: str, expected: str, value: Any) -> None:
        text = repr(value)
        found = f"{type(value).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"
        super().__init__(f"the field {field!r} should be {expected}, not {found}")
        self.field = field


def config_from_dict(d: dict[str, Any], prefix: str = "") -> TrainConfig:
    """Rebuild a :class:`TrainConfig` from :func:`config_to_dict` output (unknown keys are
    an error, missing keys take their defaults).

    Every value is checked against its field's annotation: booleans, integers, numbers
    (integers too), strings, ``None`` where the field allows it, lists for tuples (of
    those), objects for dicts and nested configs. Lists become tuples.

    Args:
        d: the saved config (``config.json``, or ``meta.json``'s ``config``).
        prefix: prepended to field names in errors (``config.`` for a checkpoint's).

    Raises:
        ConfigFieldError: a value of the wrong type, naming the field.
        LcrlError: unknown fields.
    """

    def build(cls: type, values: Any, where: str) -> Any:
        if not isinstance(values, dict):
            raise ConfigFieldError(where.rstrip(".") or "config", "an object", values)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise LcrlError(f"unknown {cls.__name__} fields in a saved config: {unknown}")
        hints = typing.get_type_hints(cls)
        kwargs = {
            name: checked(value, hints[name], f"{where}{name}", build)
            for name, value in values.items()
        }
        return cls(**kwargs)

    env = d.get("env")
    if isinstance(env, dict) and env.get("kind") == "gym" and env.get("goal_type") == "language":
        # Saved when gym envs ignored the goal type: they always had state goals.
        d = {**d, "env": {**env, "goal_type": "state"}}
    agent = d.get("agent")
    if isinstance(agent, dict) and "text_goal_norm" not in agent:
        # Saved before the option existed: those weights read standardised text goals.
        d = {**d, "agent": {**agent, "text_goal_norm": "standardize"}}
    return build(TrainConfig, d, prefix)


#: What a JSON value of each plain annotation is called in errors.
_EXPECTED = {
    bool: "true or false",
    int: "an integer",
    float: "a number",
    str: "a string",
    dict: "an object",
}


def expected_type(hint: Any) -> str:
    """How an annotation's JSON values are named in errors (``a list of integers``)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        names = [expected_type(a) for a in args if a is not type(None)]
        return " or ".join(names + (["null"] if type(None) in args else []))
    if origin is tuple or origin is list:
        inner = args[0] if args else Any
        word = {bool: "booleans", int: "integers", float: "numbers", str: "strings"}
        return f"a list of {word.get(inner, 'values')}"
    if origin is dict or (isinstance(hint, type) and dataclasses.is_dataclass(hint)):
        return "an object"
    return _EXPECTED.get(hint, str(hint))


def checked(value: Any, hint: Any, field: str, build: Any) -> Any:
    """``value`` if it fits the annotation ``hint`` (lists become tuples for tuple fields,
    objects become configs through ``build(cls, values, prefix)``); else
    :class:`ConfigFieldError` naming ``field``. Annotations other than those of the
    configs (bool, int, float, str, None, tuples, dicts, unions, dataclasses) pass."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for option in (a for a in args if a is not type(None)):
            try:
                return checked(value, option, field, build)
            except ConfigFieldError:
                continue
        raise ConfigFieldError(field, expected_type(hint), value)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigFieldError(field, "an object", value)
        return build(hint, value, f"{field}.")
    if origin is tuple or origin is list:
        if not isinstance(value, (list, tuple)):
            raise ConfigFieldError(field, expected_type(hint), value)
        kinds = args[:1] * len(value) if args and args[-1] is Ellipsis else args
        if not args:
            kinds = (Any,) * len(value)
        elif len(kinds) != len(value):
            raise ConfigFieldError(field, f"a list of {len(args)} values", value)
        try:
            items = [checked(v, a, field, build) for v, a in zip(value, kinds, strict=True)]
        except ConfigFieldError:
            raise ConfigFieldError(field, expected_type(hint), value) from None
        return tuple(items) if origin is tuple else items
    if origin is dict or hint is dict:
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise ConfigFieldError(field, "an object", value)
        return value
    ok = {
        bool: lambda v: isinstance(v, bool),
        int: lambda v: isinstance(v, int) and not isinstance(v, bool),
        float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        str: lambda v: isinstance(v, str),
    }.get(hint)
    if ok is not None and not ok(value):
        raise ConfigFieldError(field, expected_type(hint), value)
    return value


def nested_configs(cls: type) -> dict[str, type]:
    """The fields of a dataclass config that hold dataclass configs, with their classes, read
    from the field annotations (strings under ``from __future__ import annotations``,
    resolved in the class's module)."""
    hints = typing.get_type_hints(cls)
    return {
        f.name: hint
        for f in dataclasses.fields(cls)
        if isinstance(hint := hints.get(f.name), type) and dataclasses.is_dataclass(hint)
    }

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
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
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
from train.environments.tasks import (
    EnvConfig,
    check_tasks,
    goal_modality,
    is_language,
)


@dataclass
class BufferConfig:
    """Replay buffer and hindsight relabelling."""

    capacity: int = 1_000_000
    """Observation slots (an episode of T steps takes T + 1)."""
    strategy: str = "future"
    """Relabelling strategy: ``future``, ``final`` or ``episode``."""
    k: int = 4
    """Relabelled goals per original goal: a fraction k / (k + 1) of sampled transitions is
    relabelled. 0 turns hindsight relabelling off."""
    random_fraction: float = 0.0
    """Fraction of sampled transitions given a random goal achieved anywhere (at most
    1 / (k + 1)): the negatives that teach a language-goal critic which object a goal is
    about."""
    n_step: int = 1
    """Rewards summed per sampled transition (multi-step returns, recomputed for relabelled
    goals): values travel back along sparse-reward paths n times faster."""
    storage: str = "host"
    """Where the observation arrays live: ``host`` (numpy in memory) or ``device`` (torch
    tensors on the learner's device, ``agent.device``: on CUDA sampled frames are gathered
    on the GPU and never copied from the host; the relabelling stays on the host)."""


BUFFER_STORAGE = ("host", "device")

RELABELLERS = ("rule", "learned", "reward")
REWARDERS = ("rule", "learned", "captioner")


@dataclass
class RelabelConfig:
    """Who says what a language-goal episode achieved: the rule captioner (privileged
    state) or the learned models of ``lcrl caption train`` (camera frames)."""

    captioner: str = "rule"
    """Relabelling candidates: ``rule``, ``learned`` (the learned captioner's captions of
    each step, read from the camera frames) or ``reward`` (every training instruction the
    learned reward model judges achieved at each step, all of them scored; needs
    ``reward=learned`` and no captioner)."""
    reward: str = "rule"
    """Rewards of stored transitions: ``rule``, ``learned`` (the learned reward model,
    scored once per stored episode for every candidate) or ``captioner`` (the learned
    captioner's captions of each step are what it achieved, as in HIGhER; needs
    ``captioner=learned``). With either learned kind, training episodes run to the time
    limit (``env.train_until_success`` does not apply): the env's own success is the
    privileged rule, and the value target ends where the learned reward says."""
    checkpoint: str = ""
    """The learned models' checkpoint (``lcrl caption train --out``)."""
    min_logprob: float = -1.0
    """Learned captions whose log-likelihood is below this are skipped."""
    beam: int = 3
    """Beam width of the learned captioner (each step keeps every beam caption above
    ``min_logprob``; 0 or 1: one greedy caption)."""
    threshold: float = 0.5
    """Reward-model probability that counts as satisfied."""
    family_thresholds: tuple[str, ...] = ()
    """Per-family overrides of ``threshold``, as ``FAMILY=P`` (``push=0.9``): a family
    whose false rewards cost more (a push rewarded just short of its distance teaches the
    policy to stop there) can ask for more certainty than one whose misses cost more."""
    agree: bool = False
    """With the learned captioner and reward model: an instruction counts as achieved at
    an observation only where both say so (the reward model's probability reaches
    ``threshold`` and the captioner's beam reads the instruction there); fewer false
    rewards, at the cost of the ones the captioner misses."""
    confirm: bool = False
    """With the learned captioner and reward model: a caption is a relabelling candidate at
    an observation only where the reward model also judges it achieved there, so every
    relabelled goal is rewarded where it was read (as the rule captioner's always are),
    and a family the captioner over-reads does not crowd out the others."""
    end: str = "limit"
    """Where a training episode ends, with the learned reward model (``reward=learned``):
    ``limit`` (the time limit) or ``learned`` (also at the first step where the reward
    model judges the episode's own instruction achieved, scored online on the frames, as
    a robot without privileged state would stop). Never at the env's privileged success."""
    end_families: tuple[str, ...] = ()
    """With ``end=learned``: only episodes whose instruction is of these families end where
    the reward model judges it achieved; the others run to the time limit (empty: every
    family). A family whose false rewards come in states that last (an object left part of
    the way) then earns one false reward per episode instead of one per remaining step."""

    @property
    def learned(self) -> bool:
        return "learned" in (self.captioner, self.reward)


def family_thresholds(entries: Sequence[str]) -> dict[str, float]:
    """``("push=0.9", ...)`` as ``{"push": 0.9}``.

    Raises:
        LcrlError: an entry that is not ``FAMILY=P`` with a known family and P in [0, 1].
    """
    from captioner.grammar import FAMILIES

    out: dict[str, float] = {}
    for entry in entries:
        family, sep, value = str(entry).partition("=")
        try:
            p = float(value) if sep else float("nan")
        except ValueError:
            p = float("nan")
        if family not in FAMILIES or not 0.0 <= p <= 1.0:
            raise LcrlError(
                f"relabel.family_thresholds entry {entry!r}: give FAMILY=P with a family of "
                f"{FAMILIES} and P in [0, 1] (e.g. push=0.9)"
            )
        out[family] = p
    return out


#: Where a training episode with learned rewards ends (``relabel.end``).
EPISODE_ENDS = ("limit", "learned")

COLLECT_BACKENDS = ("local", "ray")


@dataclass
class CollectionConfig:
    """How training episodes are collected."""

    envs: int = 1
    """Environments stepped at once in the training process. Each step, the policy acts
    for all of them in one batched forward pass; ``updates_per_step`` counts every
    environment's steps. Each finished episode is captioned and stored whole, in the
    order of its episode number, which also fixes its reset seed. Collection is
    synchronous and deterministic: a seed and a number of environments fix the run (the
    random draws interleave across environments, so 1 and 8 differ in them)."""
    backend: str = "local"
    """Where episodes are collected: ``local`` (this process, synchronous and
    deterministic) or ``ray`` (``workers`` Ray actors, each with an environment, a policy
    copy and the captioner, returning whole captioned episodes while the learner updates:
    asynchronous, so a seed no longer fixes the run; see :mod:`train.training.ray_collect`)."""
    workers: int = 2
    """Ray rollout workers (``backend=ray``)."""
    address: str = ""
    """The Ray cluster to join (``HEAD:6379`` of ``ray start --head``); empty: start a
    local Ray on this machine."""
    sync_every: int = 100
    """Updates between weight syncs to the Ray workers."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot collect."""
        if self.envs < 1:
            raise LcrlError(f"collect.envs must be at least 1, got {self.envs}")
        if self.backend not in COLLECT_BACKENDS:
            raise LcrlError(
                f"collect.backend must be one of {COLLECT_BACKENDS}, got {self.backend!r}"
            )
        if self.backend == "ray":
            if self.workers < 1:
                raise LcrlError(f"collect.workers must be at least 1, got {self.workers}")
            if self.sync_every < 1:
                raise LcrlError(f"collect.sync_every must be at least 1, got {self.sync_every}")
            if self.envs != 1:
                raise LcrlError(
                    "collect.envs steps several environments in this process; with "
                    "collect.backend ray set collect.workers instead"
                )


@dataclass
class SequentialConfig:
    """Task groups trained one after another, with forgetting measured (``stages``)."""

    stages: tuple[str, ...] = ()
    """The stages in order, each a family or families joined by ``+`` (``reach push put``,
    ``reach+push put``); ``total_steps`` is shared equally among them. Training episodes of
    a stage draw instructions of its families only; every family of ``env.families`` is
    evaluated before the first stage and after each, and the success matrix (stage x
    family), the forgetting and the backward and forward transfer are written to
    ``sequential.json`` and ``sequential.png``. Empty: one stage of everything."""
    replay: int = 0
    """Experience replay of earlier stages: transitions kept from them (a fixed memory
    budget, shared equally among the earlier stages, whole episodes drawn at random) and
    put back in the replay buffer at the start of each stage. 0: none. Without replay the
    buffer starts empty at every stage (naive sequential training)."""
    ewc: float = 0.0
    """Weight of the EWC penalty (Kirkpatrick et al. 2017): after each stage the diagonal
    Fisher information of the critic and actor losses is estimated on that stage's data
    and ``ewc / 2 * sum F (theta - theta_stage)^2`` pulls the weights back towards where
    they ended the stage (Fisher summed over stages, anchored at the last). SAC. 0: off."""
    ewc_samples: int = 256
    """Transitions of the Fisher estimate at the end of each stage: the loss gradient of
    each one alone is squared (the empirical Fisher), then averaged. The squared gradient
    of a whole batch's mean loss would average the per-transition gradients away and
    underestimate the Fisher by about the batch size."""

    ewc_fisher: str = "output"
    """What the Fisher information of EWC is the expected squared gradient of: ``output``
    (the networks' outputs: the Q-values as unit-variance Gaussians, the log-likelihood
    of an action drawn from the policy) or ``loss`` (the critic and actor losses on each
    transition, the empirical Fisher), which vanishes on transitions the stage has
    learned well: on lang2d it is about 10^5 times smaller and EWC with it does not lower
    forgetting (benchmarks/results/forgetting.md)."""

    freeze_norm: bool = False
    """Keep the observation normaliser's statistics as the first stage left them: later
    stages' data then cannot move the inputs of earlier stages' states, which weight
    penalties such as EWC do not protect against."""

    def families(self) -> list[tuple[str, ...]]:
        """The families of each stage."""
        return [tuple(f for f in stage.split("+") if f) for stage in self.stages]

    def validate(self, families: tuple[str, ...], algo: str) -> None:
        """Raise :class:`LcrlError` for stages the env cannot train."""
        if not self.stages:
            if self.replay or self.ewc or self.freeze_norm:
                raise LcrlError(
                    "sequential.replay, sequential.ewc and sequential.freeze_norm need "
                    "sequential.stages"
                )
            return
        for stage in self.families():
            bad = [f for f in stage if f not in families]
            if not stage or bad:
                raise LcrlError(
                    f"sequential.stages: {'+'.join(stage) or 'an empty stage'} is not made of "
                    f"env.families {tuple(families)}"
                )
        if self.replay < 0 or self.ewc < 0 or self.ewc_samples < 1:
            raise LcrlError(
                "sequential.replay and sequential.ewc must be >= 0, sequential.ewc_samples >= 1"
            )
        if self.ewc_fisher not in ("loss", "output"):
            raise LcrlError(
                f"sequential.ewc_fisher must be 'loss' or 'output', got {self.ewc_fisher!r}"
            )
        if self.ewc and algo not in ("sac", "auto"):
            raise LcrlError(f"sequential.ewc is implemented for sac, not {algo}")


@dataclass
class ExploreConfig:
    """Where training episodes start and which instructions they get: chains of
    instructions, hand-overs from the scripted controller, a curriculum over families
    (language goals, ``collect.backend local``)."""

    chain: float = 0.0
    """Training on chains: the probability that a training episode which achieved its
    instruction goes on in the same scene with a new instruction (drawn among the
    training instructions feasible there, as ``lcrl eval --chain`` does), instead of a
    reset. The new instruction is judged from the scene at the switch, displacements
    restart there, and the time limit starts again; each instruction is stored as an
    episode of its own. The policy so learns to start from layouts other than reset
    layouts. 0: every episode starts from a reset."""
    chain_length: int = 3
    """Most instructions in a row before the next reset (with ``chain``)."""
    handover: float = 0.0
    """Starts along demonstrations: the fraction of the policy's training episodes in
    which the env's scripted controller acts first, for a number of steps drawn uniformly
    in ``1..handover_steps``, and the policy then takes over from wherever it left the
    robot (holding a cube, next to a target). The controller's steps are stored and count
    in ``total_steps``. 0: off."""
    handover_steps: int = 30
    """Most steps the scripted controller acts before it hands over (with ``handover``)."""
    curriculum: tuple[str, ...] = ()
    """A curriculum over instruction families, in order (``reach push lift put stack``):
    training instructions come from the first family, and the next one opens when the
    policy's live success on the family opened last reaches ``curriculum_threshold`` over
    its last ``curriculum_window`` episodes; opened families stay. Hindsight labels and
    evaluation cover every family of ``env.families`` throughout. Empty: all families
    from the start."""
    curriculum_threshold: float = 0.6
    """Live success that opens the next family of the curriculum."""
    curriculum_window: int = 50
    """Policy episodes of the family opened last that the threshold is judged on; with
    ``family_weights failure``, the episodes of each family its live success is judged
    on."""
    family_weights: str = "uniform"
    """How a training instruction's family is drawn among the open families: ``uniform``,
    or ``failure``: with probability proportional to ``weight_floor`` plus the policy's
    live failure rate on the family (over its last ``curriculum_window`` episodes, neither
    scripted nor handed over; a family not tried yet counts as failed), so that the
    families the policy has mastered give their share to those it has not."""
    weight_floor: float = 0.1
    """The weight a mastered family keeps with ``family_weights failure``."""
    prelude: float = 0.0
    """Starts where another instruction left the scene: the fraction of the policy's
    training episodes (from a reset) in which the env's scripted teacher first follows an
    instruction of ``prelude_families`` (any of the env's families, not only the run's
    ``env.families``), unstored; the run's instruction is then drawn among those feasible
    in the scene it left (a cube displaced, lifted or stacked, the gripper elsewhere), as
    the second instruction of an evaluation chain starts. The teacher's steps are counted
    in progress.csv (``prelude_steps``), not in ``total_steps``. 0: off."""
    prelude_families: tuple[str, ...] = ()
    """Families of the teacher's instructions (with ``prelude``); empty: every family of
    the env."""
    prelude_steps: int = 80
    """Most steps the teacher acts (with ``prelude``); the policy's episode starts where it
    stopped, whether its instruction succeeded or not."""

    @property
    def active(self) -> bool:
        return bool(
            self.chain
            or self.handover
            or self.curriculum
            or self.family_weights != "uniform"
            or self.prelude
        )

    def validate(self, families: tuple[str, ...]) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        for name in ("chain", "handover", "curriculum_threshold", "weight_floor", "prelude"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise LcrlError(f"explore.{name} must be in [0, 1], got {value}")
        if self.family_weights not in ("uniform", "failure"):
            raise LcrlError(
                f"explore.family_weights must be 'uniform' or 'failure', got "
                f"{self.family_weights!r}"
            )
        if self.chain_length < 2 and self.chain:
            raise LcrlError("explore.chain_length must be at least 2 (instructions in a row)")
        if self.handover_steps < 1 or self.curriculum_window < 1 or self.prelude_steps < 1:
            raise LcrlError(
                "explore.handover_steps, explore.curriculum_window and explore.prelude_steps "
                "must be >= 1"
            )
        bad = [f for f in self.curriculum if f not in families]
        if bad:
            raise LcrlError(
                f"explore.curriculum names {', '.join(bad)}, not among env.families "
                f"{tuple(families)}"
            )
        if len(set(self.curriculum)) != len(self.curriculum):
            raise LcrlError("explore.curriculum names a family twice")


@dataclass
class FinetuneConfig:
    """BC -> RL fine-tuning (SAC): a run that starts from a behavioural-cloning actor and a
    critic pretrained offline on a demonstration file, then trains online with language
    HER and a behavioural-cloning term that decays (``demos``)."""

    demos: str = ""
    """Demonstration file (``lcrl demos record``) put into the replay buffer before the
    first episode, labelled and relabelled like the run's own episodes. Empty: off."""
    pretrain_updates: int = 2000
    """Offline updates on the file before the first episode: the critic learns the
    relabelled rewards as online, the actor clones (the hindsight BC term of weight
    ``bc_weight`` plus the entropy term, no Q term)."""
    bc_weight: float = 1.0
    """Weight of the hindsight BC term (squared distance of the policy's mean action to the
    action taken, on rows whose goal was achieved later: demonstrations and the run's own
    episodes) when online training starts; it falls linearly to 0 over ``decay_steps``."""
    decay_steps: int = 20_000
    """Environment steps over which the BC weight falls to 0."""

    def validate(self, algo: str, files: bool = True) -> None:
        """Raise :class:`LcrlError` for settings that cannot train; ``files``: also refuse
        a demonstration file that is not there (a saved policy's config, loaded to act,
        does not need it)."""
        if not self.demos:
            return
        if algo not in ("sac", "auto"):
            raise LcrlError(f"--finetune.demos fine-tunes SAC, not {algo}")
        if self.pretrain_updates < 0 or self.bc_weight < 0 or self.decay_steps < 0:
            raise LcrlError(
                "finetune.pretrain_updates, finetune.bc_weight and finetune.decay_steps must "
                "be >= 0"
            )
        if files and not Path(self.demos).is_file():
            raise LcrlError(f"no demonstration file at {self.demos} (--finetune.demos)")

    def weight(self, step: int) -> float:
        """The BC weight at environment step ``step``."""
        if not self.decay_steps:
            return 0.0
        return self.bc_weight * max(0.0, 1.0 - step / self.decay_steps)


@dataclass
class DistillConfig:
    """Teacher -> student distillation with DAgger (``lcrl distill TEACHER_RUN``): a student
    that acts from what cameras show learns the actions of a privileged-state teacher in
    the states the student itself visits."""

    teacher: str = ""
    """The teacher: a run or checkpoint folder of a policy trained on the privileged state."""
    episodes_per_round: int = 20
    """Episodes collected per DAgger round (``total_steps`` counts rounds)."""
    updates_per_round: int = 500
    """Gradient updates of the student on everything gathered so far, after each round."""
    beta: float = 1.0
    """Probability that the teacher's action is the one executed, in the first round (the
    rest are the student's own, deterministic, actions)."""
    beta_decay: float = 0.5
    """The teacher's share shrinks by this factor each round: ``beta * beta_decay ** r``
    in round ``r`` (0: the student acts alone from the second round on)."""
    teachers: tuple[str, ...] = ()
    """Teachers of some instruction families, as ``FAMILY=RUN`` entries (one policy per
    family, trained apart): the instructions of those families are labelled by them, every
    other family by ``teacher``. Several teachers merge into one student."""
    chain: float = 0.0
    """The probability that an episode whose instruction was achieved goes on in the same
    scene with the next instruction (a chain, as ``lcrl eval --chain`` runs them), so the
    student learns to start from where an instruction left the scene."""
    chain_length: int = 2
    """Most instructions in a row before the next reset (with ``chain``)."""
    chain_teacher: str = ""
    """The teacher of every instruction after the first of a chain: ``scripted`` (the
    env's scripted controller) or a run; empty: the instruction family's teacher."""
    roll_in: float = 0.0
    """The probability that the teacher acts an episode's whole first instruction (its
    states labelled as every other), so that the student acts from where it left the
    scene: more of the states that chains start from (with ``chain``)."""

    init_from_teacher: bool = False
    """The student starts as the teacher: its policy network and observation and goal
    normalisers are copies of the teacher's actor (the mean half of a stochastic actor's
    output layer), so DAgger fine-tunes a policy that already acts, from the first round,
    as the teacher does on the student's input. Needs the teacher's slot mode; a student
    with more or wider hidden layers (``--hidden``, at least the teacher's) starts from
    the teacher's layers grown to them without changing what it computes (Net2Net)."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        if self.episodes_per_round <= 0 or self.updates_per_round < 0:
            raise LcrlError(
                "distill.episodes_per_round must be positive and distill.updates_per_round >= 0"
            )
        for name in ("beta", "beta_decay", "chain", "roll_in"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise LcrlError(f"distill.{name} must be in [0, 1], got {value}")
        if self.chain and self.chain_length < 2:
            raise LcrlError("distill.chain_length must be at least 2 (instructions in a row)")
        family_teachers(self.teachers)


def family_teachers(
    entries: Sequence[str], what: str = "a family's teacher", plural: str = "teachers"
) -> dict[str, str]:
    """``FAMILY=RUN`` entries as ``{family: run}`` (``what``/``plural`` name them in the
    messages: a family's teacher, an expert).

    Raises:
        LcrlError: an entry without ``=``, an empty side, or a family named twice.
    """
    out: dict[str, str] = {}
    for entry in entries:
        family, sep, run = str(entry).partition("=")
        family, run = family.strip(), run.strip()
        if not sep or not family or not run:
            raise LcrlError(f"{what} is FAMILY=RUN (put=runs/put), got {entry!r}")
        if family in out:
            raise LcrlError(f"two {plural} for the family {family!r}: {out[family]} and {run}")
        out[family] = run
    return out


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
        if self.relabel.captioner == "reward" and self.relabel.reward != "learned":
            raise LcrlError(
                "relabel.captioner=reward relabels with what the learned reward model judges "
                "achieved: it needs relabel.reward=learned"
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

"""The sections of a training config other than the environment and the learner: the replay
buffer, relabelling, collection, sequential stages, exploration, fine-tuning from
demonstrations and distillation (fields of :class:`train.configs.config.TrainConfig`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lcrl.errors import LcrlError


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


RELABELLERS = ("rule", "learned", "reward", "both")


REWARDERS = ("rule", "learned", "captioner")


@dataclass
class RelabelConfig:
    """Who says what a language-goal episode achieved: the rule captioner (privileged
    state) or the learned models of ``lcrl caption train`` (camera frames)."""

    captioner: str = "rule"
    """Relabelling candidates: ``rule``, ``learned`` (the learned captioner's captions of
    each step, read from the camera frames), ``reward`` (every training instruction the
    learned reward model judges achieved at each step, all of them scored; needs
    ``reward=learned``, no captioner) or ``both`` (those captions and those instructions
    together; needs ``reward=learned``)."""
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
#: Where Ray rollout workers go (``collect.placement``).
WORKER_PLACEMENTS = ("any", "other-nodes")


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
    placement: str = "any"
    """Where the Ray workers run: ``any`` (where Ray finds a free CPU, the learner's node
    included) or ``other-nodes`` (on the cluster's other nodes, round robin, leaving the
    learner's node to the learner; while no other node is alive, beside the learner)."""

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
            if self.placement not in WORKER_PLACEMENTS:
                raise LcrlError(
                    f"collect.placement must be one of {WORKER_PLACEMENTS}, got {self.placement!r}"
                )
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


#: ``--teacher-for FAMILY=scripted``: the env's scripted controller teaches that family
#: (its memoryless form, :attr:`train.environments.simulators.EnvSpec.teacher`, where it has one: a
#: student that sees only the current state can imitate it).
SCRIPTED = "scripted"


#: Augmentations of a DAgger student's batches (``lcrl distill --augment``, joined by ``+``).
AUGMENTATIONS = ("colours", "mirror")


def augmentation_kinds(text: str) -> tuple[str, ...]:
    """The augmentations ``text`` names (``""``: none; ``colours+mirror``: both).

    Raises:
        LcrlError: an unknown or repeated name.
    """
    kinds = tuple(k.strip() for k in text.split("+")) if text.strip() else ()
    unknown = [k for k in kinds if k not in AUGMENTATIONS]
    if unknown or len(set(kinds)) != len(kinds):
        raise LcrlError(
            f"distill.augment {text!r}: name each of {', '.join(AUGMENTATIONS)} at most once, "
            "joined by '+' (e.g. colours+mirror), or leave it empty"
        )
    return kinds


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
    scripted_funnel: float = 0.0
    """The width (m) of the drop funnel of the scripted teacher's put and stack
    (``scripted``, :class:`captioner.scripted3d.MarkovController3D`): the carried object
    is lowered as it closes the last ``scripted_funnel`` metres to the drop point, so the
    labels change smoothly with the distance left. 0: lowered only once within 8 mm."""
    roll_in: float = 0.0
    """The probability that the teacher acts an episode's whole first instruction (its
    states labelled as every other), so that the student acts from where it left the
    scene: more of the states that chains start from (with ``chain``)."""

    augment: str = ""
    """Augment every update's rows (:mod:`train.training.augment`): ``colours`` renames
    the colours in scene and instruction alike, ``mirror`` reflects half of the rows left
    to right (scene, instruction and action), ``colours+mirror`` both; only into training
    instructions. Empty: the rows as gathered."""

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
        if not 0.0 <= self.scripted_funnel <= 0.2:
            raise LcrlError(
                f"distill.scripted_funnel must be in [0, 0.2] metres, got {self.scripted_funnel}"
            )
        for name in ("beta", "beta_decay", "chain", "roll_in"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise LcrlError(f"distill.{name} must be in [0, 1], got {value}")
        if self.chain and self.chain_length < 2:
            raise LcrlError("distill.chain_length must be at least 2 (instructions in a row)")
        augmentation_kinds(self.augment)
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

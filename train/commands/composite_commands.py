"""The commands that make a policy of others: ``lcrl distill`` (a student of teachers),
``lcrl route`` (experts by instruction family) and ``lcrl ensemble`` (a mean of policies)
(the command line of :mod:`train.commands.cli`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import tyro

from lcrl.errors import LcrlError
from train.commands.policy_commands import checked_hold_radius
from train.training.trainer import check_out_dir


@dataclass
class DistillCommand:
    """Distil a privileged-state teacher into a student that acts from camera frames (or
    teachers of different instruction families into one policy), with DAgger: the
    student acts (the teacher's share of the actions shrinks round by round), the teacher
    labels every state visited, the student is fitted on everything gathered. The student
    is a policy like any other: ``lcrl eval``, ``lcrl act`` and ``lcrl.load`` take its run
    folder."""

    teacher: tyro.conf.Positional[str]
    """The teacher's run (or checkpoint) folder: a policy trained on the privileged state."""
    perception: str = ""
    """The student acts through this perception model (``lcrl perception train --out``):
    object slots estimated from each camera frame."""
    image_obs: bool = False
    """The student reads the camera frames and proprioception through a CNN instead (end
    to end; practical on a GPU)."""
    state: bool = False
    """The student reads the teachers' own privileged state instead: with
    ``--teacher-for``, policies trained apart merge into one."""
    teacher_for: list[str] = field(default_factory=list)
    """Teachers of some instruction families, ``FAMILY=RUN`` (``put=runs/put
    stack=runs/stack``); ``TEACHER`` labels the other families."""
    chain: float = 0.0
    """Probability that an achieved instruction is followed by the next one in the same
    scene (chains, as ``lcrl eval --chain`` runs them)."""
    chain_length: int = 2
    """Most instructions in a row (with ``--chain``)."""
    chain_teacher: str = ""
    """The teacher of the instructions after the first of a chain: ``scripted`` or a
    run (default: each family's teacher)."""
    roll_in: float = 0.0
    """Probability that the teacher acts an episode's whole first instruction, the
    student taking over at the second (with ``--chain``)."""
    scripted_funnel: float = 0.0
    """With a ``scripted`` teacher on robosuite: the width (m) of the drop funnel of its
    put and stack, lowering the carried object as it closes in on the drop point (0: only
    once within 8 mm of it)."""
    hidden: list[int] = field(default_factory=list)
    """The student's hidden layer sizes (default: the teacher's)."""
    init_from_teacher: bool = False
    """Start the student as a copy of the teacher's policy network and normalisers (then
    DAgger fine-tunes it on what the student reads); a wider or deeper ``--hidden`` grows
    the teacher's layers to it, acting the same."""
    slot_mode: str = ""
    """How the student picks object slots: ``attention``, ``select`` or ``attributes``
    (through their colour and shape); default: as the teacher."""
    grounding: float | None = None
    """Weight of the student's auxiliary grounding loss (which slots the instruction
    names; with ``--slot-mode attributes``); default: the teacher's."""
    hold_radius: float | None = None
    """With ``--perception``: hold each object's estimate while the gripper is farther than
    this from it (env units), in place of the model's own ``hold_radius``; saved in the
    student's config, so it acts and is evaluated the same way."""
    families: tuple[str, ...] = ()
    """The student's instruction families (default: the teacher's env's): a student of
    several family teachers (``--teacher-for``) follows all of theirs."""
    initial: bool = True
    """The student also reads the observation at the start of its instruction, as its
    teachers do. ``--no-initial``: the current observation only (its displacements say
    what moved since the instruction began), so the next instruction of a chain looks to
    the student like a first one (``--env.no-initial``)."""
    max_episode_steps: int = 0
    """The student's episode length (default: the teacher's env's; manipulation needs
    100)."""
    augment: str = ""
    """More scenes from the same episodes: ``colours`` renames the colours of every
    update's rows in scene and instruction alike, ``mirror`` reflects half of them left to
    right (scene, instruction and action), ``colours+mirror`` both; only into training
    instructions. With ``--resume`` it applies from the next round on. Empty: the rows as
    gathered (a resumed run keeps its own)."""
    new_perception: str = ""
    """With ``--resume``: the perception model the student acts through from the next
    round on (one fine-tuned on the student's own frames, ``lcrl perception train --init
    ... --extra-data``), in place of the one its checkpoint carries."""
    out: str = "runs/distill"
    """The student's run folder."""
    rounds: int = 10
    """DAgger rounds."""
    episodes_per_round: int = 20
    """Episodes collected per round."""
    updates_per_round: int = 500
    """Student updates after each round, on everything gathered so far."""
    beta: float = 1.0
    """The teacher's share of the executed actions in the first round."""
    beta_decay: float = 0.5
    """That share shrinks by this factor each round."""
    batch_size: int = 256
    """Rows per student update."""
    lr: float = 1e-3
    """The student's learning rate."""
    weight_decay: float = 0.0
    """Decoupled weight decay (as in AdamW) on the student's weights (0: off)."""
    ema: float = 0.0
    """Polyak average of the student's weights, the student that acts, is evaluated and
    checkpointed: ``avg = ema * avg + (1 - ema) * w`` after each update (0: off; e.g.
    0.999)."""
    eval_every: int = 2
    """Evaluate the student every this many rounds (0: only at the end)."""
    eval_episodes: int = 50
    """Episodes per instruction set in evaluations."""
    eval_sets: tuple[str, ...] = ()
    """Instruction sets of the evaluations every ``--eval-every`` rounds (``train``: seen
    instructions only); default: every set. The final evaluation covers every set."""
    seed: int = 0
    """Seed of the episodes, the mixing and the batches."""
    resume: bool = False
    """Continue the run in ``out`` from its latest checkpoint (``--rounds``: the new total)."""
    overwrite: bool = False
    """Replace a previous run in ``out``."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files."""
    torch_threads: int = 0
    """Torch threads of the student's updates and actions (0: automatic, fewer where other
    processes keep cores busy)."""

    def run(self) -> None:
        from lcrl.checkpoint import load_checkpoint
        from train.configs.config import BCConfig, DistillConfig
        from train.configs.presets import SLOT_ATTRIBUTES
        from train.configs.run_meta import run_meta
        from train.evaluation.evaluate import resolve_checkpoint
        from train.runtime.machine import apply_threads
        from train.training.distill import DistillTrainer, student_config

        if self.rounds <= 0:
            raise LcrlError("--rounds must be positive")
        apply_threads(self.torch_threads)
        teacher = run_meta(load_checkpoint(resolve_checkpoint(self.teacher))).config
        distill = DistillConfig(
            teacher=self.teacher,
            episodes_per_round=self.episodes_per_round,
            updates_per_round=self.updates_per_round,
            beta=self.beta,
            beta_decay=self.beta_decay,
            teachers=tuple(self.teacher_for),
            chain=self.chain,
            chain_length=self.chain_length,
            chain_teacher=self.chain_teacher,
            roll_in=self.roll_in,
            scripted_funnel=self.scripted_funnel,
            init_from_teacher=self.init_from_teacher,
            augment=self.augment,
        )
        cfg = student_config(
            teacher,
            perception=self.perception,
            image_obs=self.image_obs,
            state=self.state,
            out=self.out,
            distill=distill,
            total_steps=self.rounds,
            eval_every=self.eval_every,
            eval_episodes=self.eval_episodes,
            eval_sets=tuple(self.eval_sets),
            checkpoint_every=1,
            log_every=1,
            batch_size=self.batch_size,
            seed=self.seed,
            progress=self.progress,
            tensorboard=self.tensorboard,
        )
        cfg.bc = BCConfig(
            lr=self.lr,
            loss="mse",
            hindsight=False,
            ema=self.ema,
            weight_decay=self.weight_decay,
        )
        cfg.env.initial = self.initial
        if self.families:
            cfg.env.families = tuple(self.families)
        if self.max_episode_steps:
            if self.max_episode_steps < 1:
                raise LcrlError("--max-episode-steps must be positive")
            cfg.env.max_episode_steps = self.max_episode_steps
        if self.hidden:
            if min(self.hidden) <= 0:
                raise LcrlError(f"--hidden sizes must be positive, got {self.hidden}")
            cfg.agent.net.hidden = tuple(self.hidden)
        if self.slot_mode:
            cfg.agent.net.slot_mode = self.slot_mode
            if self.slot_mode == "attributes" and not cfg.agent.net.slot_attributes:
                cfg.agent.net.slot_attributes = SLOT_ATTRIBUTES
        if self.grounding is not None:
            cfg.agent.grounding = self.grounding
        if self.hold_radius is not None:
            cfg.env.perception_hold_radius = checked_hold_radius(
                self.hold_radius,
                bool(self.perception),
                "--hold-radius holds perception's estimates: give the student a --perception MODEL",
            )
        cfg.resume, cfg.overwrite = self.resume, self.overwrite
        DistillTrainer(cfg, self.new_perception).run()
        print(f"evaluate again with: lcrl eval {cfg.out}")


@dataclass
class RouteCommand:
    """One policy of runs trained apart: each instruction goes to the expert of its family
    (the family of the base run's nearest training instruction), the other families to
    the base run. Writes a checkpoint folder for ``lcrl eval``, ``lcrl act`` and
    ``lcrl.load``; the experts must read the base's observation features."""

    out: tyro.conf.Positional[str]
    """The routed checkpoint folder to write."""
    base: str
    """The run (or checkpoint) that defines the environment and the routing table, and
    acts for the families without an expert."""
    expert: tuple[str, ...] = ()
    """``FAMILY=RUN``: the run (or checkpoint) that acts for that family."""
    overwrite: bool = False
    """Replace ``out`` if it exists."""

    def run(self) -> None:
        from train.policies.route import expert_entries, write_router

        experts = expert_entries(self.expert)
        check_out_dir(Path(self.out).parent, "the folder of the routed checkpoint")
        out = write_router(self.out, self.base, experts, self.overwrite)
        names = ", ".join(f"{f} <- {r}" for f, r in experts.items())
        print(f"saved {out}: {names}; other families <- {self.base}")


@dataclass
class EnsembleCommand:
    """One policy of runs trained apart (distilled students of other seeds, say) acting as
    the mean of their actions. Writes a checkpoint folder for ``lcrl eval``, ``lcrl act``
    and ``lcrl.load``; the members must read the same observation features, through the
    same perception model held the same way."""

    out: tyro.conf.Positional[str]
    """The ensemble checkpoint folder to write."""
    runs: tyro.conf.Positional[tuple[str, ...]]
    """Two or more runs (or checkpoints); the first one's config is the ensemble's."""
    overwrite: bool = False
    """Replace ``out`` if it exists."""

    def run(self) -> None:
        from train.policies.ensemble import write_ensemble

        check_out_dir(Path(self.out).parent, "the folder of the ensemble checkpoint")
        out = write_ensemble(self.out, self.runs, self.overwrite)
        print(f"saved {out}: the mean of {', '.join(self.runs)}")

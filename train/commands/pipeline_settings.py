"""The settings of a camera pipeline (``lcrl train robosuite-camera --help``): its
teachers' recipes and every stage's sizes; :mod:`train.commands.pipeline` runs them."""

from __future__ import annotations

from dataclasses import dataclass

from train.configs.sections import SCRIPTED


@dataclass
class TeacherRecipe:
    """How one family's privileged-state teacher is trained."""

    family: str
    preset: str
    """The ``lcrl train`` preset, or ``scripted``: the environment's scripted controller in
    its memoryless form teaches the family (nothing to train)."""
    steps: int
    """Environment steps."""
    demos: int = 0
    """Scripted demonstrations recorded first and fine-tuned from (0: none)."""
    extra: tuple[str, ...] = ()
    """More ``lcrl train`` options."""
    demo_preset: str = ""
    """The preset whose families the demonstrations cover (empty: this family alone, with
    ``preset``). Teachers that name the same one share one file, recorded once."""


@dataclass
class CameraPipeline:
    """A camera policy for a whole grammar, built stage by stage (see the module)."""

    env: str
    """The simulator of ``lcrl perception collect`` (``robosuite``, ``lang2d``)."""
    teachers: tuple[TeacherRecipe, ...]
    """One recipe per family; the first trained teacher is the student's base (its
    networks and instruction table)."""
    out: str = "runs/camera"
    """The pipeline's folder."""
    stages: tuple[str, ...] = ()
    """Stages to run (default: every one not done yet)."""
    resume: bool = True
    """Skip finished stages and continue a stopped one (``--no-resume``: refuse a folder
    that holds a pipeline)."""
    keep: str = ""
    """Where the ``keep`` stage copies the final policy (empty: ``OUT/kept``)."""
    perception: str = ""
    """Use this perception model instead of building one (skips ``perception-data`` and
    ``perception``)."""
    state: bool = False
    """The student reads the teachers' privileged state (``lcrl distill --state``) instead
    of the camera: no perception stages, one privileged-state policy for every family
    (``lcrl train robosuite-privileged``)."""
    image_size: int = 84
    """Camera frame side in pixels."""
    perception_episodes: int = 3000
    """Episodes of ``perception-data`` (random and scripted)."""
    perception_episode_steps: int = 20
    """Steps of each such episode (more layouts, not longer episodes, is what helps)."""
    perception_steps: int = 10_000
    """Training steps of ``perception``."""
    state_rounds: int = 0
    """DAgger rounds of ``state-student``: a student of every teacher that reads the
    privileged state (as ``lcrl train robosuite-privileged`` builds), then the camera
    student's one teacher, for every instruction of a chain, the camera student starting
    as a copy of it (``lcrl distill --init-from-teacher``). 0: the teachers teach the
    camera student themselves."""
    state_student: str = ""
    """Take this privileged-state student as the camera student's teacher instead of
    building one (skips ``state-student``)."""
    rounds: int = 30
    """DAgger rounds of ``student``."""
    episodes_per_round: int = 40
    """Episodes the student (with the teachers' share) collects per round."""
    updates_per_round: int = 2000
    """Student updates per round, on everything gathered."""
    student_hidden: tuple[int, ...] = (512, 512, 512)
    """The student's hidden layers."""
    chain: float = 0.5
    """Probability that an achieved instruction is followed by another (chains)."""
    initial: bool = True
    """The student also reads the observation its instruction started from, as the
    teachers do; ``--no-initial``: the current observation only (``lcrl distill
    --no-initial``), so a chain's later instruction looks like a first one (a whole build
    so: chains of two 0.12 against 0.08 on validation seed 1, but pooled 0.31 against
    0.40: ``benchmarks/results/robosuite-camera-no-initial.md``)."""
    student_frames: int = 400
    """Episodes of the student collected for ``perception-ft``."""
    max_episode_steps: int = 100
    """The student's episode length (and that of the episodes of ``student-frames``)."""
    perception_ft_steps: int = 4000
    """Training steps of ``perception-ft``."""
    rounds_ft: int = 10
    """More DAgger rounds through the fine-tuned perception (``student-ft``); 0: no
    fine-tuning (no ``student-frames``, ``perception-ft`` or ``student-ft``)."""
    rounds_aug: int = 0
    """More DAgger rounds after those with every update's rows augmented
    (``student-aug``, ``--augment``); 0: no such stage."""
    augment: str = "colours"
    """The augmentation of ``student-aug`` (``lcrl distill --augment``)."""
    eval_episodes: int = 100
    """Episodes per instruction set of ``eval``."""
    eval_seed: int = 1
    """Evaluation seed of ``eval`` (choose builds on other seeds)."""
    seed: int = 0
    """Seed of every stage's data and training."""
    threads: int = 0
    """Torch threads of each stage (0: automatic)."""
    teacher_steps: int = 0
    """Environment steps of every teacher (0: each recipe's own)."""
    dry_run: bool = False
    """Print the stages, whether each is done, and their commands; run nothing."""
    reader: bool = True
    """Free text through the canonical reader: the evaluation reads instructions through
    it, and the kept policy has it on by default, fitted and kept beside it."""
    extra_student: tuple[str, ...] = ()
    """More ``lcrl distill`` options."""
    parts: str = ""
    """Start from the parts a build kept (``--export-parts``): the stages they hold are
    done, their artefacts copied into ``--out`` (a stage whose data file a later stage
    reads runs again)."""
    export_parts: str = ""
    """Write the finished stages before the student (records, weights and configs; no
    data) to this folder, and stop."""
    jobs: int = 1
    """Stages run at once where one does not need another's output; each gets
    ``cores // jobs`` torch threads unless ``--threads`` is given."""

    @property
    def families(self) -> tuple[str, ...]:
        return tuple(t.family for t in self.teachers)

    @property
    def trained(self) -> tuple[TeacherRecipe, ...]:
        """The recipes with a teacher to train (not ``scripted``)."""
        return tuple(t for t in self.teachers if t.preset != SCRIPTED)


__all__ = ["CameraPipeline", "TeacherRecipe"]

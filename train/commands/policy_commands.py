"""The commands that use a trained policy: ``lcrl eval``, ``lcrl report`` and ``lcrl act``
(the command line of :mod:`train.commands.cli`)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from lcrl.errors import LcrlError
from train.runtime.run_lock import check_output_file, refuse_if_training
from train.training.trainer import check_out_dir


def check_json_path(path: str | None) -> None:
    """Refuse a ``--json`` path that cannot be written (a folder, a path below a file, a
    read-only folder), before any work is done."""
    if path:
        check_output_file(path, "--json")


def canonical_override(saved: Any) -> dict[str, Any]:
    """The env override of ``--canonical-reader`` for a checkpoint whose env config is
    ``saved``; refused in one line where no reader can stand in front of its policy."""
    from train.environments.tasks import is_language

    if saved.text_reader:
        raise LcrlError(
            "this checkpoint reads instructions through its --env.text-reader; "
            "--canonical-reader cannot replace it"
        )
    if not is_language(saved):
        raise LcrlError(
            f"--canonical-reader reads language goals; this checkpoint has {saved.goal_type!r} "
            "goals"
        )
    return {"canonical_reader": True}


@dataclass
class EvalCommand:
    """Evaluate a checkpoint: success with 95% confidence intervals per instruction set
    (seen, held-out combinations, paraphrases, a file of your own), family and slot value;
    optionally chains of instructions; a Markdown report with figures (``--out``). A
    checkpoint trained on a fixed task set (env.tasks) runs its tasks round robin as set
    ``train`` and reports success per task; a task-id checkpoint has that set only."""

    checkpoint: tyro.conf.Positional[str]
    """A checkpoint folder, or a run folder (its latest checkpoint)."""
    episodes: int = 100
    """Episodes per instruction set (chains per set with --chain)."""
    sets: tuple[str, ...] = ()
    """Instruction sets to evaluate (default: every set of the task, plus ``custom`` with
    --instructions)."""
    instructions: str = ""
    """A file of instructions, one per line (blank lines and # comments skipped): the set
    ``custom``; episode i runs line i modulo their number. Lines the rule captioner cannot
    parse still run, their success not checked."""
    chain: int = 0
    """Chained evaluation: up to this many instructions in a row in one episode, each
    drawn among those feasible in the scene after the previous success (0: off)."""
    families: tuple[str, ...] = ()
    """Instruction families to evaluate (default: those it was trained on)."""
    seed: int = 0
    """Seed of the evaluation layouts and instruction draws."""
    num_envs: int = 0
    """Environments stepped together, the policy acting on the batch (0: one per CPU
    core that other busy processes leave free). Results do not depend on it."""
    vector: str = "auto"
    """Vector env: ``sync`` (one process), ``async`` (a process per env) or ``auto``
    (async on robosuite, whose steps are slow, sync otherwise)."""
    device: str | None = None
    """Run the policy on this device (default: the one it was trained on)."""
    canonical_reader: bool = False
    """Put an instruction reader in front of the policy (``--env.canonical-reader``):
    every instruction reaches it as the canonical sentence of the meaning the reader
    reads. A checkpoint trained with one uses its own; for one without, a reader is fitted
    first on the run's training instructions and their training-only phrasings (about a
    minute), the same way training fits it."""
    true_state: bool = False
    """A policy that acts through a perception model acts on the simulator's true object
    slots instead (its camera estimate replaced by what it estimates): the cost of
    perception, side by side with the camera figures."""
    hold_radius: float | None = None
    """A policy acting through perception: hold each object's estimated position while the
    gripper is farther than this from it (metres; ``--env.perception-hold-radius``; 0:
    every frame's own estimate). Default: the radius the policy was trained with."""
    perception: str = ""
    """A policy acting through perception: act through this perception model instead of
    its own (a model folder, or a camera policy's checkpoint that carries one): which of
    a student and its perception model a figure owes to."""
    out: str = ""
    """Write eval.json (every figure), eval.md and PNG figures to this folder; inside a
    run folder (e.g. RUN/evals/NAME) ``lcrl report RUN`` includes them."""
    json: str | None = None
    """Also write every figure to this JSON file."""
    progress: bool = True
    """Show a progress bar over episodes."""
    torch_threads: int = 0
    """Torch threads of the policy's forward passes (0: automatic, fewer where other
    processes keep cores busy)."""

    def run(self) -> None:
        from lcrl.checkpoint import load_checkpoint
        from train.configs.run_meta import run_meta
        from train.environments.tasks import goal_modality
        from train.evaluation.eval_suite import (
            check_task_id_options,
            default_num_envs,
            evaluation_document,
            format_summary,
            read_instruction_file,
            run_evaluation,
        )
        from train.evaluation.evaluate import resolve_checkpoint
        from train.policies.loading import load_policy
        from train.runtime.machine import apply_threads

        apply_threads(self.torch_threads)

        if self.episodes <= 0:
            raise LcrlError("--episodes must be positive")
        if self.num_envs < 0:
            raise LcrlError("--num-envs must be positive (or 0: one per CPU core)")
        if self.chain < 0:
            raise LcrlError("--chain must be 0 (off) or a number of instructions")
        if self.vector not in ("auto", "sync", "async"):
            raise LcrlError(f"--vector must be auto, sync or async, got {self.vector!r}")
        if self.out:  # outputs that cannot be written fail before the evaluation runs
            check_out_dir(Path(self.out), "the evaluation folder")
            refuse_if_training(self.out, "--out")
        check_json_path(self.json)
        if self.instructions:
            read_instruction_file(self.instructions)  # bad lines fail before loading
        # a fixed task set: options that cannot apply fail before the policy is built
        saved = run_meta(load_checkpoint(resolve_checkpoint(self.checkpoint))).config.env
        tasks = tuple(" ".join(str(t).split()) for t in saved.tasks)
        if goal_modality(saved.goal_type).task_ids:
            check_task_id_options(len(tasks), self.sets, bool(self.instructions), self.chain)
        if tasks and self.families:
            raise LcrlError(
                f"--families cannot narrow a checkpoint trained on a fixed task set of "
                f"{len(tasks)} tasks (families {tuple(saved.families)}): drop "
                "it; the figures are broken down per family and per task anyway"
            )
        overrides: dict[str, Any] = {"families": tuple(self.families)} if self.families else {}
        if self.canonical_reader:
            overrides.update(canonical_override(saved))
        if self.hold_radius is not None:
            overrides["perception_hold_radius"] = checked_hold_radius(
                self.hold_radius,
                bool(saved.perception),
                "--hold-radius holds perception's estimates; this checkpoint acts on the "
                "simulator's state, through no perception model",
            )
        if self.true_state:
            if not saved.perception:
                raise LcrlError(
                    "--true-state replaces perception's estimate by the true state; this "
                    "checkpoint acts on the true state already"
                )
            if self.hold_radius is not None:
                raise LcrlError("--true-state reads no estimate: --hold-radius does not apply")
            overrides["perception"] = ""
        if self.perception:
            if not saved.perception or self.true_state:
                raise LcrlError(
                    "--perception replaces the perception model a camera policy acts through; "
                    + ("--true-state replaces it too: use one of them" if self.true_state
                       else "this checkpoint acts on the simulator's state")
                )  # fmt: skip
            if not Path(self.perception).is_dir():
                raise LcrlError(f"--perception {self.perception}: no such folder")
            overrides["perception"] = self.perception
        policy = load_policy(self.checkpoint, overrides or None, self.device)
        extra = self.episodes % len(tasks) if tasks else 0
        if extra and (not self.sets or "train" in self.sets):
            which = "task 0 gets" if extra == 1 else f"tasks 0 to {extra - 1} get"
            print(
                f"note: {self.episodes} episodes over {len(tasks)} tasks: {which} one "
                "episode more than the others (use a multiple of the number of tasks)"
            )
        lines = None
        if self.instructions:
            can_do = getattr(policy.env.unwrapped, "instruction_families", None)
            lines = read_instruction_file(self.instructions, can_do)
            if len(lines) > self.episodes:
                print(
                    f"note: {len(lines)} instructions but --episodes {self.episodes}: only "
                    f"the first {self.episodes} run"
                )
        num_envs = self.num_envs or default_num_envs()
        results = run_evaluation(
            policy.agent,
            policy.task,
            policy.cfg,
            self.episodes,
            seed=self.seed,
            sets=tuple(self.sets) or None,
            instructions=lines,
            chain=self.chain,
            num_envs=num_envs,
            vector=self.vector,
            progress=self.progress,
        )
        step = policy.checkpoint.meta["step"]
        print(f"checkpoint {policy.checkpoint.path} (step {step})")
        print(format_summary(results))
        settings = {
            "episodes": self.episodes,
            "seed": self.seed,
            "chain": self.chain,
            "sets": list(results),
            "instructions_file": self.instructions or None,
            "families": list(policy.cfg.env.families),
            "tasks": list(tasks),
            "num_envs": num_envs,
            "canonical_reader": bool(policy.cfg.env.canonical_reader),
            "hold_radius": self.hold_radius,
            "true_state": self.true_state,
            "perception": self.perception or None,
            "command": self._command(),
        }
        doc = evaluation_document(policy.checkpoint.path, step, policy.cfg, results, settings)
        if self.out:
            from train.evaluation.report import write_evaluation

            paths = write_evaluation(doc, self.out)
            print(f"saved {paths['md']}, {paths['json'].name} and figures in {self.out}")
        if self.json:
            from train.evaluation.report import EVAL_FORMAT, EVAL_VERSION

            Path(self.json).parent.mkdir(parents=True, exist_ok=True)
            with open(self.json, "w") as f:
                json.dump({"format": EVAL_FORMAT, "version": EVAL_VERSION, **doc}, f, indent=1)
            print(f"saved {self.json}")

    def _command(self) -> str:
        """The command line that reproduces these figures."""
        parts = ["lcrl eval", self.checkpoint, f"--episodes {self.episodes}", f"--seed {self.seed}"]
        if self.sets:
            parts.append("--sets " + " ".join(self.sets))
        if self.families:
            parts.append("--families " + " ".join(self.families))
        if self.instructions:
            parts.append(f"--instructions {self.instructions}")
        if self.chain:
            parts.append(f"--chain {self.chain}")
        if self.canonical_reader:
            parts.append("--canonical-reader")
        if self.hold_radius is not None:
            parts.append(f"--hold-radius {self.hold_radius:g}")
        if self.true_state:
            parts.append("--true-state")
        if self.perception:
            parts.append(f"--perception {self.perception}")
        return " ".join(parts)


@dataclass
class ReportCommand:
    """Rebuild a run's report (curves.png, report.md, with the figures of every
    ``lcrl eval --out`` inside the run folder), or compare runs side by side."""

    runs: tyro.conf.Positional[tuple[str, ...]]
    """One run folder (its report is rebuilt), or several (compared; needs --out)."""
    out: str = ""
    """Write here instead of into the run folder; with several runs, the folder that
    receives comparison.md and comparison.png."""

    def run(self) -> None:
        from train.evaluation.report import compare_runs, write_report

        if not self.runs:
            raise LcrlError("give one run folder, or several to compare")
        if len(self.runs) == 1:
            path = write_report(self.runs[0], out=self.out or None)
            print(f"report: {path} (curves: {path.parent / 'curves.png'})")
            return
        if not self.out:
            raise LcrlError("comparing runs needs --out DIR (where comparison.md goes)")
        path = compare_runs(self.runs, self.out)
        print(f"comparison: {path} (curves: {path.parent / 'comparison.png'})")


@dataclass
class ExportCommand:
    """Keep a trained policy: copy a run's latest checkpoint (or a checkpoint folder) with
    its weights, configs and fitted canonical reader, and nothing only resuming reads (no
    replay data, no optimiser state), into a folder for ``lcrl eval``, ``lcrl act`` and
    ``lcrl.load``: a few MB to keep in a repository or move between machines."""

    run_or_checkpoint: Annotated[tyro.conf.Positional[str], tyro.conf.arg(metavar="RUN")]
    """The run folder (its latest checkpoint) or a checkpoint folder."""
    out: Annotated[tyro.conf.Positional[str], tyro.conf.arg(metavar="OUT")]
    """The folder to write."""
    canonical_reader: Literal["as-trained", "on", "off"] = "as-trained"
    """Whether the exported policy reads instructions through the canonical reader by
    default (``lcrl eval`` and ``lcrl act`` can still say otherwise)."""
    acting_only: bool = True
    """Leave out what only learning reads (critics, target networks) as well: the policy
    acts and is evaluated the same, in a fraction of the size."""
    overwrite: bool = False
    """Replace ``out`` if it exists."""

    def run(self) -> None:
        from train.policies.loading import keep_checkpoint

        out = Path(self.out)
        if out.exists() and not self.overwrite:
            raise LcrlError(f"{out} exists: pass --overwrite to replace it")
        check_out_dir(out.parent, "the folder of the exported policy")
        refuse_if_training(out, "the exported folder")
        reader = {"as-trained": None, "on": True, "off": False}[self.canonical_reader]
        kept = keep_checkpoint(self.run_or_checkpoint, out, reader, self.acting_only)
        size = sum(f.stat().st_size for f in kept.rglob("*") if f.is_file())
        print(f"saved {kept} ({size / 1e6:.1f} MB): evaluate it with lcrl eval {kept}")


@dataclass
class ActCommand:
    """Run a checkpoint's policy on free-text instructions and report what happened: how
    the captioner reads each one, the nearest training instructions, success per episode.
    ``--interactive`` reads one instruction per line from the standard input. Policies
    trained on a fixed task set run one of their tasks with ``--task ID`` (task-id
    policies take nothing else)."""

    checkpoint: tyro.conf.Positional[str]
    """A checkpoint folder, or a run folder (its latest checkpoint)."""
    instruction: str = ""
    """Any text; success is reported when the rule captioner can parse and check it.
    Required for language checkpoints (unless --interactive); state- and image-goal
    checkpoints run on the environment's own goals."""
    task: str = ""
    """One task of a checkpoint trained on a fixed task set (env.tasks): its id (0 to
    K-1) or its text. Required for task-id checkpoints (unless --interactive, which then
    reads task ids or texts)."""
    interactive: bool = False
    """Read instructions line by line from the standard input until an empty line,
    ``quit`` or the end of input; run --episodes for each."""
    episodes: int = 10
    """Episodes to run per instruction."""
    seed: int = 0
    """Seed of the layouts: episode i starts from layout seed + i (an instruction the
    captioner checks, from the next layout where it is feasible)."""
    stochastic: bool = False
    """Sample actions instead of taking the policy's mean action."""
    video: str = ""
    """Save the episodes as a video here (``.mp4`` or ``.gif``) with the instruction drawn
    on the frames; with --interactive, one file per instruction (``NAME_001.gif``, ...)."""
    fps: int = 10
    """Frames per second of the video."""
    hold: float = 1.0
    """Seconds each episode's last frame stays in the video, with its outcome."""
    then: tuple[str, ...] = ()
    """Instructions that follow ``--instruction`` in the same scene, each once the one
    before it is achieved (a chain, as ``lcrl eval --chain`` runs them):
    ``--then "lift the blue cylinder"``."""
    canonical_reader: bool = False
    """Read instructions through a canonical reader (as ``lcrl eval --canonical-reader``):
    each instruction reaches the policy as the canonical sentence of the meaning the reader
    reads, printed before its episodes (a checkpoint trained with one always does)."""
    torch_threads: int = 0
    """Torch threads of the policy's forward passes (0: automatic, fewer where other
    processes keep cores busy)."""

    def run(self) -> None:
        from lcrl.checkpoint import load_checkpoint
        from train.commands.act import ActSession, check_video_path, read_lines
        from train.configs.run_meta import run_meta
        from train.evaluation.evaluate import resolve_checkpoint
        from train.policies.policy import load
        from train.runtime.machine import apply_threads

        apply_threads(self.torch_threads)

        video = check_video_path(self.video) if self.video else None
        given = [
            name
            for name, on in (
                ("--instruction", self.instruction.strip()),
                ("--task", self.task.strip()),
                ("--interactive", self.interactive),
            )
            if on
        ]
        if len(given) > 1:
            raise LcrlError(f"give either {given[0]} or {given[1]}, not both")
        if self.then and not self.instruction.strip():
            raise LcrlError("--then continues an --instruction: give the first with --instruction")
        overrides = None
        if self.canonical_reader:
            saved = run_meta(load_checkpoint(resolve_checkpoint(self.checkpoint))).config.env
            overrides = canonical_override(saved)
        policy = load(self.checkpoint, env_overrides=overrides)
        if self.task.strip() and not policy.tasks:
            raise LcrlError(
                "--task runs a task of a checkpoint trained on a fixed task set (env.tasks); "
                "this one has none: "
                + ("give an --instruction" if policy.language else "drop --task")
            )
        if policy.takes_task_ids and not (self.task.strip() or self.interactive):
            what = "it reads no free text (--instruction); " if self.instruction.strip() else ""
            raise LcrlError(
                f"this is a task-id checkpoint: {what}give --task with the id or the text of "
                f"one of its tasks (or --interactive): {policy.describe_tasks()}"
            )
        env = policy.make_env(render=video is not None)
        session = ActSession(
            policy, env, self.episodes, self.seed, not self.stochastic, self.fps, self.hold
        )
        if self.task.strip():
            session.run_task(self.task, video)
        elif policy.takes_task_ids:  # --interactive: task ids or texts, one per line
            session.interactive(read_lines(sys.stdin, "task> "), video)
        elif not policy.language:
            if self.instruction.strip() or self.interactive:
                raise LcrlError(
                    "this checkpoint was not trained with language goals: drop --instruction "
                    "and --interactive to run it on the environment's own goals"
                )
            session.run_goals(video)
        elif self.interactive:
            session.interactive(read_lines(sys.stdin), video)
        elif not self.instruction.strip():
            raise LcrlError(
                "this is a language checkpoint: give an --instruction (or --interactive)"
            )
        elif self.then:
            session.run_chain([self.instruction, *self.then], video)
        else:
            session.run_text(self.instruction, video)
        env.close()


def checked_hold_radius(radius: float, perceives: bool, without: str) -> float:
    """``--hold-radius``: refused (``without``) for a policy that acts through no perception
    model, and below 0."""
    if not perceives:
        raise LcrlError(without)
    if not radius >= 0:
        raise LcrlError(f"--hold-radius must be >= 0, got {radius}")
    return float(radius)

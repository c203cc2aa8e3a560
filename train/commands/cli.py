"""The ``lcrl`` command line.

Subcommands:
    train   train a policy from a named preset (``lcrl train lang2d --total-steps 50000``),
            or clone demonstrations (``lcrl train lang2d-bc --demos FILE``)
    eval    evaluate a checkpoint: instruction sets, families, slot values, chains, report
    report  rebuild a run's report, or compare runs side by side
    act     run a checkpoint on any free-text instruction (or many, --interactive), or on
            one task of a fixed task set (--task ID)
    demo    caption scripted and random episodes on the 2D tabletop, write a report
    split   make a compositional instruction split and save it as JSON
    parse   show how the grammar reads instructions (canonical form and slots)
    caption collect   gather camera episodes labelled by the rule captioner (HDF5)
    caption train     fit the learned captioner and reward model on such a dataset
    caption eval      exact match, slot accuracy, BLEU-4, reward AUC of those models
    demos record      record scripted demonstrations of a language-goal preset (HDF5)
    demos relabel     add hindsight instructions: everything each episode achieved
    demos info        summarise a demonstration dataset (segments per family ...)
    demos import-robomimic   convert a robomimic / LIBERO file into a demonstration dataset
    perception collect | train | eval   learn to read object slots from camera frames
    distill  distil privileged-state teachers into a student (camera frames, or one policy)
    route    one policy of per-family runs: each instruction goes to its family's expert

User mistakes (bad options, unparseable instructions, missing files) print one line
starting with ``lcrl: error:`` and exit with status 2; Ctrl-C exits with status 130.
SIGINT and SIGTERM stop every command the same way from its first instant (the console
script, :mod:`train.commands.entry`, takes them before anything heavy is imported), even where the
shell started ``lcrl`` in the background with SIGINT ignored (:func:`stop_on_signals`).
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro

from lcrl.errors import LcrlError
from train.runtime.run_lock import abandon_locks, check_output_file, refuse_if_training
from train.training.trainer import RunAlreadyDone, RunInterrupted, check_out_dir


@dataclass
class SplitCommand:
    """Make a compositional instruction split (train / held-out combinations / paraphrases)."""

    out: str = "split.json"
    """Where to write the split (JSON)."""
    seed: int = 0
    """The split's seed; the same seed always gives the same split."""
    families: tuple[str, ...] = ("reach", "push", "put", "lift", "stack")
    """Instruction families to include."""
    heldout_per_family: int = 2
    """Object kinds held out of each family."""
    list: bool = False
    """Also print every instruction of every set."""

    def run(self) -> None:
        from captioner.splits import SPLIT_SETS, make_split

        split = make_split(self.seed, self.families, self.heldout_per_family)
        path = split.save(self.out)
        print(split.summary())
        if self.list:
            for name in SPLIT_SETS:
                print(f"\n[{name}]")
                print("\n".join(split.texts(name)))
        print(f"saved {path}")


@dataclass
class ParseCommand:
    """Parse instructions with the grammar and print their canonical form and slots."""

    instructions: tyro.conf.Positional[tuple[str, ...]]
    """One or more instructions (quote each)."""
    json: bool = False
    """Print JSON instead of text."""

    def run(self) -> None:
        from captioner.grammar import parse

        results = []
        for text in self.instructions:
            ins = parse(text)
            results.append({"text": text, "canonical": ins.text, "slots": ins.slots()})
        if self.json:
            print(json.dumps(results, indent=1))
        else:
            for r in results:
                slots = " ".join(f"{k}={v}" for k, v in r["slots"].items())
                print(f"{r['text']!r} -> {r['canonical']!r}  [{slots}]")


@dataclass
class TrainStub:
    """Train a policy from a preset: ``lcrl train PRESET [--field value ...]`` (see
    ``lcrl train --help`` for the presets)."""

    def run(self) -> None:
        _train(["--help"])


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
    core). Results do not depend on it."""
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
    out: str = ""
    """Write eval.json (every figure), eval.md and PNG figures to this folder; inside a
    run folder (e.g. RUN/evals/NAME) ``lcrl report RUN`` includes them."""
    json: str | None = None
    """Also write every figure to this JSON file."""
    progress: bool = True
    """Show a progress bar over episodes."""

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
    canonical_reader: bool = False
    """Read instructions through a canonical reader (as ``lcrl eval --canonical-reader``):
    each instruction reaches the policy as the canonical sentence of the meaning the reader
    reads, printed before its episodes (a checkpoint trained with one always does)."""

    def run(self) -> None:
        from lcrl.checkpoint import load_checkpoint
        from train.commands.act import ActSession, check_video_path, read_lines
        from train.configs.run_meta import run_meta
        from train.evaluation.evaluate import resolve_checkpoint
        from train.policies.policy import load

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
        else:
            session.run_text(self.instruction, video)
        env.close()


def check_preset(argv: Sequence[str], presets: Mapping[str, Any]) -> None:
    """Refuse an unknown preset name in one line naming the closest known ones, before
    tyro would call the flags that follow it misplaced."""
    import difflib

    if not argv or argv[0].startswith("-") or argv[0] in presets:
        return
    close = difflib.get_close_matches(argv[0], list(presets), n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    raise LcrlError(
        f"unknown preset {argv[0]!r}: {hint}lcrl train --help lists all {len(presets)} presets"
    )


def parse_train_args(argv: Sequence[str]) -> Any:
    """The :class:`train.configs.config.TrainConfig` of ``lcrl train ARGV`` (a preset, then
    overrides), as the command builds it."""
    from train.commands.pipeline import PIPELINES
    from train.configs.config import TrainConfig
    from train.configs.presets import PRESETS

    check_preset(argv, {**PRESETS, **PIPELINES})
    presets = {name: cfg for name, (_, cfg) in PRESETS.items()}
    descriptions = {name: desc for name, (desc, _) in PRESETS.items()}
    cfg = tyro.cli(
        tyro.extras.subcommand_type_from_defaults(presets, descriptions),
        prog="lcrl train",
        description="Train a policy. Pick a preset, then override any field. "
        "Policies built in stages (lcrl train NAME --help): "
        + ", ".join(f"{n} ({f.__doc__ or ''})" for n, f in PIPELINES.items()),
        args=list(argv),
    )
    assert isinstance(cfg, TrainConfig)
    return cfg


def _saved_offline(cfg: Any) -> bool:
    """``--resume`` of a run that was trained offline (its saved config says so): its
    dataset and learner are taken into ``cfg`` (the saved config is used from then on)."""
    path = Path(cfg.out) / "config.json"
    if not cfg.resume or not path.is_file():
        return False
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    if not saved.get("offline"):
        return False
    cfg.offline, cfg.algo = saved["offline"], saved.get("algo", cfg.algo)
    return True


#: Options a resumed run takes from the command line (the rest come from its saved config).
RESUME_KEEPS = ("resume", "out", "total_steps", "progress", "torch_threads", "overwrite")


def explore_given(argv: Sequence[str], cfg: Any) -> dict[str, Any]:
    """The ``explore`` fields a ``--resume`` command line gives (``--explore.NAME``), with
    their parsed values: a resumed run takes them (where its next episodes start)."""
    if not getattr(cfg, "resume", False):
        return {}
    out = {}
    for token in argv:
        if token.startswith("--explore."):
            name = token[len("--explore.") :].split("=", 1)[0].replace("-", "_")
            if hasattr(cfg.explore, name):
                out[name] = getattr(cfg.explore, name)
    return out


def ignored_on_resume(argv: Sequence[str], cfg: Any) -> list[str]:
    """The options on a ``--resume`` command line that differ from the run's saved config
    (which the resumed run keeps), as ``--name value (the run has saved)``."""
    path = Path(cfg.out) / "config.json"
    if not cfg.resume or not path.is_file():
        return []
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    out = []
    for token in argv:
        if not token.startswith("--"):
            continue
        name = token[2:].split("=", 1)[0]
        parts = name.replace("-", "_").split(".")
        if parts[-1].startswith("no_"):  # --no-x / --a.no-x of a boolean flag
            parts[-1] = parts[-1][3:]
        if parts[0] in RESUME_KEEPS or parts[0] == "explore":
            continue
        value, old, found = cfg, saved, True
        for part in parts:
            if not hasattr(value, part) or not isinstance(old, dict) or part not in old:
                found = False
                break
            value, old = getattr(value, part), old[part]
        if found and json.loads(json.dumps(value, default=str)) != old:
            out.append(f"--{name} {value} (the run has {old})")
    return out


def _train(argv: Sequence[str]) -> None:
    from lcrl.algos import ALGOS
    from train.commands.pipeline import PIPELINES, pipeline_cli, run_pipeline
    from train.training.loop import Trainer

    if argv and argv[0] in PIPELINES:  # a policy built by stages (train/commands/pipeline.py)
        run_pipeline(pipeline_cli(argv[0], argv[1:]))
        return

    cfg = parse_train_args(argv)
    ignored = ignored_on_resume(argv, cfg)
    if ignored:
        print(
            "lcrl: warning: --resume goes on with the run's saved config; ignored: "
            + "; ".join(ignored),
            file=sys.stderr,
        )
    spec = ALGOS.get(cfg.algo)
    if cfg.offline or _saved_offline(cfg):  # offline RL / GCBC through the replay buffer
        from train.training.offline import OfflineTrainer

        trainer: Trainer | BCTrainer = OfflineTrainer(cfg)
    elif spec is not None and spec.learns_from == "demos":  # behavioural cloning from --demos
        from train.training.bc import BCTrainer

        trainer = BCTrainer(cfg)
    else:
        trainer = Trainer(cfg, explore_given(argv, cfg))
    results = trainer.run()
    out = trainer.out
    tb = ", tb/ (TensorBoard)" if trainer.cfg.tensorboard else ""
    print(
        f"outputs in {out}/: report.md, curves.png, config.json, progress.csv, eval.csv{tb}, "
        "checkpoints/"
    )
    print(f"evaluate again with: lcrl eval {out}")
    del results


@dataclass
class CaptionStub:
    """Learned-captioner data and models: ``lcrl caption collect --help``."""

    def run(self) -> None:
        _caption(["--help"])


@dataclass
class CaptionEvalCommand:
    """Evaluate a learned captioner / reward model on a caption dataset: exact match,
    per-slot accuracy, BLEU-4, reward-model precision / recall / AUC, on seen instructions
    and on held-out word combinations."""

    checkpoint: tyro.conf.Positional[str]
    """The checkpoint folder (``lcrl caption train --out``)."""
    data: str = ""
    """Caption dataset to evaluate on (default: the one it was trained on, its held-out
    episodes)."""
    beam: int = 0
    """Beam width for decoding (0: greedy)."""
    max_pairs: int = 2000
    """Observations per group at most."""
    json: str = ""
    """Also write every figure to this JSON file."""
    thresholds: tuple[float, ...] = ()
    """Also score learned relabelling as a training loop does, on whole episodes, at each
    of these reward thresholds: precision and recall of the rewards and the labels against
    the rule captioner (the figures to choose ``--relabel.threshold`` on)."""
    families: tuple[str, ...] = ()
    """With ``thresholds``: the families the run trains on (default: every training
    instruction of the dataset)."""

    def run(self) -> None:
        check_json_path(self.json)
        from captioner.dataset import CaptionDataset
        from captioner.learned import (
            LearnedCaptioner,
            evaluate_models,
            format_agreement,
            format_results,
            relabel_agreement,
            save_results,
        )

        bad = [t for t in self.thresholds if not 0.0 < t < 1.0]
        if bad:
            raise LcrlError(f"--thresholds are probabilities in (0, 1), got {bad[0]}")
        lc = LearnedCaptioner.load(self.checkpoint)
        path = self.data or lc.meta.get("dataset", "")
        if not path:
            raise LcrlError("pass --data: the checkpoint does not name its dataset")
        with CaptionDataset(path) as data:
            results = evaluate_models(lc, data, max_pairs=self.max_pairs, beam=self.beam)
            if self.thresholds:
                results["relabelling"] = relabel_agreement(
                    lc, data, self.thresholds, self.families, beam=max(self.beam, 3)
                )
        print(format_results(results))
        if self.thresholds:
            print(format_agreement(results["relabelling"]))
        if self.json:
            print(f"saved {save_results(results, self.json)}")


@dataclass
class CaptionMergeCommand:
    """Concatenate caption datasets of one simulator and instruction split into one file
    (say, episodes of a later policy beside the first collection), to train on together."""

    data: tyro.conf.Positional[tuple[str, ...]]
    """The caption datasets (``lcrl caption collect --out``), two or more."""
    out: str = "data/captions-merged.h5"
    """The file to write."""
    overwrite: bool = False
    """Replace an existing file."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> None:
        from captioner.dataset import CaptionDataset, merge

        with CaptionDataset(merge(self.data, self.out, self.overwrite, self.progress)) as d:
            print(d.summary())


def check_json_path(path: str | None) -> None:
    """Refuse a ``--json`` path that cannot be written (a folder, a path below a file, a
    read-only folder), before any work is done."""
    if path:
        check_output_file(path, "--json")


def _collect(cfg: Any) -> None:
    """Collect a caption dataset (``lcrl caption collect``, ``lcrl perception collect``)
    and print its summary."""
    from captioner.dataset import CaptionDataset
    from train.commands.captions import collect

    with CaptionDataset(collect(cfg)) as data:
        print(data.summary())


def _caption(argv: Sequence[str]) -> None:
    from captioner.dataset import CollectConfig
    from captioner.learned import CaptionTrainConfig, train_models

    cfg = tyro.extras.subcommand_cli_from_dict(
        {
            "collect": CollectConfig,
            "merge": CaptionMergeCommand,
            "train": CaptionTrainConfig,
            "eval": CaptionEvalCommand,
        },
        prog="lcrl caption",
        description="Learned captioner and reward model: collect labelled camera episodes, "
        "merge datasets, train, evaluate.",
        args=list(argv),
    )
    if isinstance(cfg, CollectConfig):
        _collect(cfg)
    elif isinstance(cfg, CaptionTrainConfig):
        path = train_models(cfg)
        print(f"saved {path}")
        CaptionEvalCommand(str(path)).run()
    else:
        cfg.run()


@dataclass
class PerceptionStub:
    """Perception (camera frames -> object slots): ``lcrl perception train --help`` (also
    collect, eval)."""

    def run(self) -> None:
        _perception(["--help"])


def _perception(argv: Sequence[str]) -> None:
    from captioner.dataset import CollectConfig
    from train.environments.perception import PerceptionEvalCommand, PerceptionTrainConfig, train

    cfg = tyro.extras.subcommand_cli_from_dict(
        {"collect": CollectConfig, "train": PerceptionTrainConfig, "eval": PerceptionEvalCommand},
        prog="lcrl perception",
        description="Perception: collect camera frames labelled with the privileged state, "
        "train a model that reads the object slots from them, evaluate it.",
        args=list(argv),
    )
    if isinstance(cfg, CollectConfig):
        _collect(cfg)
    elif isinstance(cfg, PerceptionTrainConfig):
        train(cfg)
    else:
        cfg.run()


def checked_hold_radius(radius: float, perceives: bool, without: str) -> float:
    """``--hold-radius``: refused (``without``) for a policy that acts through no perception
    model, and below 0."""
    if not perceives:
        raise LcrlError(without)
    if not radius >= 0:
        raise LcrlError(f"--hold-radius must be >= 0, got {radius}")
    return float(radius)


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
    max_episode_steps: int = 0
    """The student's episode length (default: the teacher's env's; manipulation needs
    100)."""
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

    def run(self) -> None:
        from lcrl.checkpoint import load_checkpoint
        from train.configs.config import BCConfig, DistillConfig
        from train.configs.presets import SLOT_ATTRIBUTES
        from train.configs.run_meta import run_meta
        from train.evaluation.evaluate import resolve_checkpoint
        from train.training.distill import DistillTrainer, student_config

        if self.rounds <= 0:
            raise LcrlError("--rounds must be positive")
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
            init_from_teacher=self.init_from_teacher,
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
        cfg.bc = BCConfig(lr=self.lr, loss="mse", hindsight=False, ema=self.ema)
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


@dataclass
class DemosStub:
    """Demonstration datasets: ``lcrl demos record --help`` (also relabel, info,
    import-robomimic)."""

    def run(self) -> None:
        _demos(["--help"])


def _demos(argv: Sequence[str]) -> None:
    from train.training.demos import COMMANDS

    cfg = tyro.extras.subcommand_cli_from_dict(
        COMMANDS,
        prog="lcrl demos",
        description="Demonstration datasets: record scripted episodes, relabel them in "
        "hindsight, inspect them, import robomimic files.",
        args=list(argv),
    )
    cfg.run()


def stop_on_signals() -> None:
    """SIGINT raises ``KeyboardInterrupt`` and SIGTERM :class:`RunInterrupted` (one too),
    so every command keeps what it finished and stops (130, 143).

    A shell that starts a command in the background (``lcrl train ... &`` in a script)
    leaves SIGINT ignored, and Python keeps it so; the training loop's own handlers then
    took a ``kill -INT`` only once training began, and one sent during start-up was lost.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _terminated)


def _terminated(signum: int, frame: Any) -> None:
    raise RunInterrupted(signum)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the ``lcrl`` console script (through :mod:`train.commands.entry`)."""
    stop_on_signals()
    try:
        _main(argv)
    except KeyboardInterrupt as e:  # a signal before a command had anything to save
        name = e.args[0] if e.args and isinstance(e.args[0], str) else "SIGINT"
        print(f"lcrl: interrupted by {name}", file=sys.stderr)
        sys.exit(getattr(e, "exit_status", 130))
    finally:
        abandon_locks()  # a run refused before it began leaves no folder behind


def _main(argv: Sequence[str] | None) -> None:
    from train.commands.demo import DemoConfig, run_demo

    args = list(sys.argv[1:] if argv is None else argv)
    commands = {
        "train": TrainStub,
        "eval": EvalCommand,
        "act": ActCommand,
        "report": ReportCommand,
        "demo": DemoConfig,
        "split": SplitCommand,
        "parse": ParseCommand,
        "caption": CaptionStub,
        "perception": PerceptionStub,
        "demos": DemosStub,
        "distill": DistillCommand,
        "route": RouteCommand,
        "ensemble": EnsembleCommand,
    }
    try:
        if args and args[0] == "train":
            _train(args[1:])
            return
        if args and args[0] == "perception":
            _perception(args[1:])
            return
        if args and args[0] == "caption":
            _caption(args[1:])
            return
        if args and args[0] == "demos":
            _demos(args[1:])
            return
        cfg = tyro.extras.subcommand_cli_from_dict(
            commands,
            prog="lcrl",
            description="lcrl: language-conditioned reinforcement learning toolkit.",
            args=args,
        )
        if isinstance(cfg, DemoConfig):
            run_demo(cfg)
        else:
            cfg.run()
    except RunAlreadyDone as e:  # --resume of a run already at --total-steps
        print(f"lcrl: {e}", file=sys.stderr)
    except LcrlError as e:
        print(f"lcrl: error: {e}", file=sys.stderr)
        sys.exit(2)
    except OSError as e:  # a file or folder that cannot be read or written
        where = f" {e.filename}" if e.filename else ""
        print(f"lcrl: error: cannot use{where}: {e.strerror or e}", file=sys.stderr)
        sys.exit(2)
    except RunInterrupted as e:  # a training run says what it saved (train/training/trainer.py)
        if not e.reported:
            print(f"lcrl: interrupted by {e.args[0]}", file=sys.stderr)
        sys.exit(e.exit_status)
    except KeyboardInterrupt:
        print("lcrl: interrupted by SIGINT", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()

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
import os
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from lcrl.errors import LcrlError
from train.commands.composite_commands import DistillCommand, EnsembleCommand, RouteCommand
from train.commands.policy_commands import (
    ActCommand,
    EvalCommand,
    ExportCommand,
    ReportCommand,
    check_json_path,
)
from train.runtime.run_lock import abandon_locks
from train.training.trainer import RunAlreadyDone, RunInterrupted


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
    signal.signal(signal.SIGINT, _stopped)
    signal.signal(signal.SIGTERM, _stopped)


def _stopped(signum: int, frame: Any) -> None:
    """Raise ``KeyboardInterrupt`` (SIGINT) or :class:`RunInterrupted` (SIGTERM), unless
    the signal landed where Python swallows an exception (a weakref callback such as the
    import system's module-lock clean-up, or a ``__del__``): there the signal is sent
    again a moment later, so it is raised at the next safe point instead of lost."""
    if _swallows(frame):
        threading.Timer(0.02, os.kill, (os.getpid(), signum)).start()
        return
    if signum == signal.SIGINT:
        signal.default_int_handler(signum, frame)
    raise RunInterrupted(signum)


def _swallows(frame: Any) -> bool:
    """Whether an exception raised in ``frame`` would be printed and dropped."""
    if frame is None:
        return False
    code = frame.f_code
    if code.co_name == "__del__":
        return True
    if code.co_filename.startswith("<frozen importlib") and code.co_name == "cb":
        return True
    return Path(code.co_filename).name in {"weakref.py", "_weakrefset.py"}


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
        "export": ExportCommand,
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

"""The ``lcrl`` command line.

Subcommands:
    train   train a policy from a named preset (``lcrl train lang2d --total-steps 50000``)
    eval    evaluate a checkpoint per instruction set and family
    act     run a checkpoint on any free-text instruction
    demo    caption scripted and random episodes on the 2D tabletop, write a report
    split   make a compositional instruction split and save it as JSON
    parse   show how the grammar reads instructions (canonical form and slots)
    caption collect   gather camera episodes labelled by the rule captioner (HDF5)
    caption train     fit the learned captioner and reward model on such a dataset
    caption eval      exact match, slot accuracy, BLEU-4, reward AUC of those models

User mistakes (bad options, unparseable instructions, missing files) print one line
starting with ``lcrl: error:`` and exit with status 2; Ctrl-C exits with status 130.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from lcrl.errors import LcrlError


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


@dataclass
class EvalCommand:
    """Evaluate a checkpoint: success per instruction set (seen, held-out, paraphrase) and
    family."""

    checkpoint: tyro.conf.Positional[str]
    """A checkpoint folder, or a run folder (its latest checkpoint)."""
    episodes: int = 100
    """Episodes per instruction set."""
    sets: tuple[str, ...] = ()
    """Instruction sets to evaluate (default: every set of the task)."""
    families: tuple[str, ...] = ()
    """Instruction families to evaluate (default: those it was trained on)."""
    seed: int = 0
    """Seed of the evaluation layouts."""
    device: str | None = None
    """Run the policy on this device (default: the one it was trained on)."""
    json: str | None = None
    """Also write the results to this JSON file."""

    def run(self) -> None:
        from train.evaluate import evaluate, format_results, load_policy

        if self.episodes <= 0:
            raise LcrlError("--episodes must be positive")
        overrides = {"families": tuple(self.families)} if self.families else None
        policy = load_policy(self.checkpoint, overrides, self.device)
        sets = tuple(self.sets) or policy.task.sets
        bad = [s for s in sets if s not in policy.task.sets]
        if bad:
            raise LcrlError(f"unknown sets {bad}; this task has {policy.task.sets}")
        results = evaluate(
            policy.agent, policy.task, policy.cfg, self.episodes, seed=self.seed, sets=sets
        )
        print(f"checkpoint {policy.checkpoint.path} (step {policy.checkpoint.meta['step']})")
        print(format_results(results))
        if self.json:
            with open(self.json, "w") as f:
                json.dump(results, f, indent=1)
            print(f"saved {self.json}")


@dataclass
class ActCommand:
    """Run a checkpoint's policy on a free-text instruction and report what happened."""

    checkpoint: tyro.conf.Positional[str]
    """A checkpoint folder, or a run folder (its latest checkpoint)."""
    instruction: str = ""
    """Any text; success is reported when the rule captioner can parse and check it.
    Required for language checkpoints; state- and image-goal checkpoints run on the
    environment's own goals."""
    episodes: int = 10
    """Episodes to run."""
    seed: int = 0
    """Seed of the layouts."""
    stochastic: bool = False
    """Sample actions instead of taking the policy's mean action."""
    video: str = ""
    """Save the episodes as a video here (``.mp4``), one after the other."""
    fps: int = 10
    """Frames per second of the video."""

    def run(self) -> None:
        from captioner.grammar import try_parse
        from train.evaluate import load_policy, run_episode
        from train.tasks import LanguageTask

        if self.episodes <= 0:
            raise LcrlError("--episodes must be positive")
        if self.video and not self.video.lower().endswith(".mp4"):
            raise LcrlError(f"--video must name an .mp4 file, got {self.video!r}")
        if self.fps <= 0:
            raise LcrlError("--fps must be positive")
        policy = load_policy(self.checkpoint, render=bool(self.video))
        task = policy.task
        frames: list[np.ndarray] | None = [] if self.video else None
        if not isinstance(task, LanguageTask):
            if self.instruction.strip():
                raise LcrlError(
                    "this checkpoint was not trained with language goals: drop --instruction "
                    "to run it on the environment's own goals"
                )
            self._run_goals(policy, frames)
            return
        text = " ".join(self.instruction.split())
        if not text:
            raise LcrlError("this is a language checkpoint: give an --instruction")
        meaning = try_parse(text)
        vector = np.asarray(task.encoder.encode([text])[0], np.float32)
        if meaning is None:
            print(f"{text!r}: the captioner cannot parse it, so success is not checked")
        else:
            print(f"{text!r} -> {meaning.text!r}")
        successes, checked = [], 0
        for i in range(self.episodes):
            options = {"instruction": text} if meaning is not None else None
            try:
                r = run_episode(
                    policy.agent,
                    task,
                    policy.env,
                    seed=self.seed + i,
                    options=options,
                    goal_vector=vector,
                    deterministic=not self.stochastic,
                    frames=frames,
                )
            except LcrlError as e:
                print(f"episode {i}: {e}")
                continue
            if meaning is not None:
                checked += 1
                successes.append(r["success"])
                status = "success" if r["success"] else "failure"
            else:
                status = "not checked"
            print(f"episode {i}: {r['steps']} steps, {status}")
        if checked:
            print(f"success {np.mean(successes):.2f} over {checked} episodes")
        self._save_video(frames)

    def _run_goals(self, policy: Any, frames: list[np.ndarray] | None) -> None:
        from train.evaluate import run_episode

        successes = []
        for i in range(self.episodes):
            r = run_episode(
                policy.agent,
                policy.task,
                policy.env,
                seed=self.seed + i,
                deterministic=not self.stochastic,
                frames=frames,
            )
            successes.append(r["success"])
            print(f"episode {i}: {r['steps']} steps, {'success' if r['success'] else 'failure'}")
        print(f"success {np.mean(successes):.2f} over {self.episodes} episodes")
        self._save_video(frames)

    def _save_video(self, frames: list[np.ndarray] | None) -> None:
        if not frames:
            return
        path = save_video(self.video, frames, self.fps)
        print(f"video: {path} ({len(frames)} frames at {self.fps} fps)")


def save_video(path: str | Path, frames: Sequence[np.ndarray], fps: int = 10) -> Path:
    """Write RGB uint8 frames ``(H, W, 3)`` to an ``.mp4`` file (OpenCV's mp4v codec)."""
    import cv2

    frames = [f for f in frames if f is not None]
    if not frames:
        raise LcrlError("no frames to save: the environment did not render")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        raise LcrlError(f"cannot write a video to {path} (OpenCV has no mp4v encoder here)")
    try:
        for frame in frames:
            writer.write(cv2.cvtColor(np.ascontiguousarray(frame, np.uint8), cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return path


def _train(argv: Sequence[str]) -> None:
    from train.config import PRESETS, TrainConfig
    from train.loop import Trainer

    presets = {name: cfg for name, (_, cfg) in PRESETS.items()}
    descriptions = {name: desc for name, (desc, _) in PRESETS.items()}
    cfg = tyro.cli(
        tyro.extras.subcommand_type_from_defaults(presets, descriptions),
        prog="lcrl train",
        description="Train a policy. Pick a preset, then override any field.",
        args=list(argv),
    )
    assert isinstance(cfg, TrainConfig)
    trainer = Trainer(cfg)
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

    def run(self) -> None:
        from captioner.dataset import CaptionDataset
        from captioner.learned import (
            LearnedCaptioner,
            evaluate_models,
            format_results,
            save_results,
        )

        lc = LearnedCaptioner.load(self.checkpoint)
        path = self.data or lc.meta.get("dataset", "")
        if not path:
            raise LcrlError("pass --data: the checkpoint does not name its dataset")
        with CaptionDataset(path) as data:
            results = evaluate_models(lc, data, max_pairs=self.max_pairs, beam=self.beam)
        print(format_results(results))
        if self.json:
            print(f"saved {save_results(results, self.json)}")


def _caption(argv: Sequence[str]) -> None:
    from captioner.dataset import CaptionDataset, CollectConfig, collect
    from captioner.learned import CaptionTrainConfig, train_models

    cfg = tyro.extras.subcommand_cli_from_dict(
        {"collect": CollectConfig, "train": CaptionTrainConfig, "eval": CaptionEvalCommand},
        prog="lcrl caption",
        description="Learned captioner and reward model: collect labelled camera episodes, "
        "train, evaluate.",
        args=list(argv),
    )
    if isinstance(cfg, CollectConfig):
        path = collect(cfg)
        with CaptionDataset(path) as data:
            print(data.summary())
    elif isinstance(cfg, CaptionTrainConfig):
        path = train_models(cfg)
        print(f"saved {path}")
        CaptionEvalCommand(str(path)).run()
    else:
        cfg.run()


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the ``lcrl`` console script."""
    from train.demo import DemoConfig, run_demo

    args = list(sys.argv[1:] if argv is None else argv)
    commands = {
        "train": TrainStub,
        "eval": EvalCommand,
        "act": ActCommand,
        "demo": DemoConfig,
        "split": SplitCommand,
        "parse": ParseCommand,
        "caption": CaptionStub,
    }
    try:
        if args and args[0] == "train":
            _train(args[1:])
            return
        if args and args[0] == "caption":
            _caption(args[1:])
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
    except LcrlError as e:
        print(f"lcrl: error: {e}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("lcrl: interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()

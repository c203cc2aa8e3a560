"""Helpers shared by the test modules (imported as ``helpers``: pytest puts this folder on
the import path)."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

from lcrl.nets import NetConfig
from train.cli import main
from train.config import PRESETS, TrainConfig

#: Options that shrink an ``lcrl train`` command line to a few seconds.
TINY_CLI = [
    "--eval-episodes", "3",
    "--checkpoint-every", "0",
    "--log-every", "100",
    "--batch-size", "32",
    "--agent.net.hidden", "32", "32",
    "--agent.net.text-dim", "8",
    "--no-progress",
    "--no-tensorboard",
]  # fmt: skip


def tiny(preset: str, out: Path, **overrides) -> TrainConfig:
    """A preset shrunk to a few hundred steps and 32-unit networks."""
    base = copy.deepcopy(PRESETS[preset][1])
    cfg = dataclasses.replace(
        base,
        out=str(out),
        total_steps=300,
        learning_starts=100,
        batch_size=32,
        eval_every=0,
        eval_episodes=3,
        checkpoint_every=0,
        log_every=100,
        progress=False,
        tensorboard=False,
        buffer=dataclasses.replace(base.buffer, capacity=2000),
        agent=dataclasses.replace(
            base.agent, net=NetConfig(hidden=(32, 32), text_dim=8), grounding=0.0
        ),
    )
    return dataclasses.replace(cfg, **overrides)


def cli(*args: str) -> int:
    """Run ``lcrl ARGS``; the exit status (0 when main returns)."""
    try:
        main(list(args))
    except SystemExit as e:
        return 0 if e.code is None else e.code if isinstance(e.code, int) else 1
    return 0


def error_line(stderr: str) -> str:
    """The last line of stderr (the transformers loading bar may precede it)."""
    return stderr.strip().splitlines()[-1]


def interrupt_update(monkeypatch, agent, at: int) -> None:
    """Make ``agent.update`` raise ``KeyboardInterrupt`` on its ``at``-th call: a Ctrl-C in
    the middle of a block of updates."""
    update, calls = agent.update, {"n": 0}

    def interrupted(batch):
        calls["n"] += 1
        if calls["n"] == at:
            raise KeyboardInterrupt
        return update(batch)

    monkeypatch.setattr(agent, "update", interrupted)

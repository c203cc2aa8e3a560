"""Helpers shared by the test modules (imported as ``helpers``: pytest puts this folder on
the import path)."""

from __future__ import annotations

import copy
import dataclasses
import subprocess
import sys
from pathlib import Path

from lcrl.nets import NetConfig
from train.commands.cli import main
from train.configs.config import TrainConfig
from train.configs.presets import PRESETS

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
        collect=dataclasses.replace(base.collect, envs=1),  # one env: runs step by step
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


def untrained_perception(out: Path, seed: int = 0) -> Path:
    """A perception model for the 2D tabletop's 64 px frames with untrained weights (seeded):
    enough for whatever only needs something that reads frames."""
    import numpy as np
    import torch

    from lcrl.perception import Perception, SlotLayout
    from train.environments.perception import PerceptionTrainConfig, save_model

    torch.manual_seed(seed)
    layout = SlotLayout(2, 8, 3, 2)
    stats = {
        "pos_mean": np.zeros((8, 2), np.float32),
        "pos_std": np.full((8, 2), 0.3, np.float32),
        "proprio_mean": np.zeros(2, np.float32),
        "proprio_std": np.full(2, 0.3, np.float32),
    }
    model = Perception((64, 64, 3), layout, stats=stats)
    meta = {"env": "lang2d", "slot_layout": layout.to_list(), "image_size": 64}
    save_model(out, model, PerceptionTrainConfig(), meta, 0, [], np.zeros(0, int))
    return out


def train_tiny(out: Path, preset: str, seed: int = 0, steps: int = 200, **env) -> Path:
    """A tiny run of ``preset`` trained for ``steps`` (half of them before learning), with
    ``env`` options replaced; its run folder."""
    from train.training.loop import Trainer

    cfg = tiny(preset, out, total_steps=steps, learning_starts=steps // 2, seed=seed)
    if env:
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, **env))
    Trainer(cfg).run()
    return out


#: Holds a run folder's lock until its standard input closes: ``python -c HOLD FOLDER``.
HOLD = """
import sys
from train.runtime.run_lock import lock_run
print(lock_run(sys.argv[1]) or "held", flush=True)
sys.stdin.read()
"""


def hold(folder: Path) -> subprocess.Popen:
    """A real process holding ``folder`` (until its stdin closes or it is killed)."""
    folder.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)],
        cwd=Path(__file__).resolve().parent.parent,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


def oracle_perception(dataset):
    """Perception that reads the simulator's own state of each frame of a caption dataset
    (what a perfect model would estimate)."""
    import numpy as np

    from captioner.dataset import CaptionDataset
    from lcrl.perception import Perception, SlotLayout

    with CaptionDataset(dataset) as data:
        lookup = {f.tobytes(): s for f, s in zip(data.frames[:], data.state[:], strict=True)}
        layout = SlotLayout.of(data.meta["slot_layout"])
        shape = data.frame_shape

    class Oracle(Perception):
        def observation(self, frames, proprio, present=None):
            out = np.stack([lookup[f.tobytes()] for f in np.asarray(frames, np.uint8)])
            if present is not None:  # given flags replace the read ones, as the model's do
                lay = self.layout
                slots = out[:, lay.start : lay.dim].reshape(len(out), lay.count, lay.width)
                flags = np.asarray(present, np.float32)
                slots = np.concatenate([slots[..., :-1] * flags[..., None], flags[..., None]], -1)
                out = np.concatenate([out[:, : lay.start], slots.reshape(len(out), -1)], 1)
            return out

    return Oracle(shape, layout)

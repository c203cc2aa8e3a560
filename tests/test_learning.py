"""Learning tests: hindsight relabelling must learn where the same run without it does not.

The CI test trains SAC on the fast 2D tabletop with state goals (move the pusher to a goal
position; reward 1 within 2 cm, else 0) for 6,000 steps, with HER (``future``, k=4) and
without (k=0), from the same seeds, and compares deterministic success over 50 evaluation
episodes. About half a minute per run on two CPU cores.

Language goals take longer than a CI budget (reach and push: 0.55 success on seen
instructions after 30k steps, reach 1.00, against 0.10 without relabelling); that
comparison is ``benchmarks/learning_curves.py lang2d``.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import pytest
import torch

from lcrl.nets import NetConfig
from train.config import PRESETS, BufferConfig, TrainConfig
from train.loop import Trainer


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _train(preset: str, out: Path, k: int, **changes: object) -> float:
    cfg: TrainConfig = copy.deepcopy(PRESETS[preset][1])
    cfg = dataclasses.replace(
        cfg,
        out=str(out),
        buffer=BufferConfig(
            capacity=50_000, k=k, random_fraction=cfg.buffer.random_fraction if k else 0.0
        ),
        eval_every=0,
        checkpoint_every=0,
        save_buffer=False,
        progress=False,
        tensorboard=False,
        **changes,
    )
    results = Trainer(cfg).run()
    return next(iter(results.values()))["success"]


def test_her_learns_to_reach_state_goals_and_no_relabelling_does_not(tmp_path: Path) -> None:
    common = dict(
        total_steps=6_000,
        learning_starts=500,
        batch_size=128,
        eval_episodes=50,
        agent=dataclasses.replace(
            PRESETS["state2d"][1].agent, net=NetConfig(hidden=(64, 64)), seed=0
        ),
    )
    her = _train("state2d", tmp_path / "her", k=4, **common)
    no_her = _train("state2d", tmp_path / "no-her", k=0, **common)
    assert her >= 0.6, f"SAC + HER reached only {her:.2f} success"
    assert no_her <= 0.2, f"SAC without relabelling reached {no_her:.2f}: the task is too easy"
    assert her - no_her >= 0.4

"""Learning tests: hindsight relabelling must learn where the same run without it does not.

The CI test trains SAC on the fast 2D tabletop with state goals (move the pusher to a goal
position; reward 1 within 2 cm, else 0) for 6,000 steps, with HER (``future``, k=4) and
without (k=0), from the same seeds, and compares deterministic success over 50 evaluation
episodes. About half a minute per run on two CPU cores.

Language goals take longer than a CI budget (reach and push: 0.55 success on seen
instructions after 30k steps, reach 1.00, against 0.10 without relabelling); that
comparison is ``benchmarks/learning_curves.py lang2d``. One language test fits: reach
instructions with two held-out colour x shape combinations, 4,000 steps, where slots
picked through their colour and shape with the grounding loss reach the held-out
objects and slots picked by position do not (``benchmarks/compositional.py`` measures
it over seeds at full length).
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import pytest
import torch

from lcrl.nets import NetConfig
from train.configs.config import BufferConfig, TrainConfig
from train.configs.presets import PRESETS
from train.training.loop import Trainer


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _train(preset: str, out: Path, k: int, **changes: object) -> float:
    return next(iter(_run(preset, out, k, **changes).values()))["success"]


def _run(preset: str, out: Path, k: int, **changes: object) -> dict:
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
    return Trainer(cfg).run()


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


def test_attribute_slots_with_grounding_reach_held_out_combinations(tmp_path: Path) -> None:
    from train.configs.presets import SLOT_ATTRIBUTES

    base = PRESETS["lang2d-quick"][1]
    pooled_net = dataclasses.replace(base.agent.net, slot_mode="select")
    grounded_net = dataclasses.replace(
        base.agent.net, slot_mode="attributes", slot_attributes=SLOT_ATTRIBUTES
    )
    common = dict(total_steps=4_000, eval_episodes=50)
    pooled = _run(
        "lang2d-quick",
        tmp_path / "pooled",
        k=4,
        agent=dataclasses.replace(base.agent, net=pooled_net, grounding=0.0, seed=0),
        **common,
    )
    grounded = _run(
        "lang2d-quick",
        tmp_path / "grounded",
        k=4,
        agent=dataclasses.replace(base.agent, net=grounded_net, grounding=1.0, seed=0),
        **common,
    )
    held = grounded["heldout"]["success"]
    assert held >= 0.4, f"held-out combinations: {held:.2f} success with attribute slots"
    assert held - pooled["heldout"]["success"] >= 0.25, (
        f"attribute slots {held:.2f} vs position-wise {pooled['heldout']['success']:.2f}"
    )
    assert grounded["train"]["success"] >= pooled["train"]["success"] - 0.15

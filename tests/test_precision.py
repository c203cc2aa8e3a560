"""``--agent.precision bf16``: updates under bfloat16 autocast, float32 everywhere else."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch
from helpers import cli, error_line, tiny
from torch import nn

from lcrl.errors import LcrlError
from train.training.loop import Trainer


def filled(tmp_path, preset: str = "lang2d-quick", precision: str = "fp32") -> Trainer:
    """A tiny trainer at ``learning_starts`` with its agent in ``precision``."""
    cfg = tiny(preset, tmp_path / "run")
    cfg.agent = dataclasses.replace(cfg.agent, precision=precision)
    trainer = Trainer(cfg)
    while trainer.step < cfg.learning_starts:
        trainer.advance()
    return trainer


def linear_output_dtypes(agent, run) -> set[torch.dtype]:
    """The dtypes the networks' linear layers produce during ``run()``."""
    seen: set[torch.dtype] = set()
    hooks = [
        m.register_forward_hook(lambda _m, _i, out: seen.add(out.dtype))
        for net in (agent.actor, agent.critic)
        for m in net.modules()
        if isinstance(m, nn.Linear)
    ]
    try:
        run()
    finally:
        for h in hooks:
            h.remove()
    return seen


@pytest.mark.parametrize("preset", ["lang2d-quick", "lang2d-td3"])
def test_bf16_updates_multiply_in_bf16_and_keep_float32_state(tmp_path, preset):
    trainer = filled(tmp_path, preset, "bf16")
    try:
        agent = trainer.agent
        batch = trainer.buffer.sample(32)
        assert linear_output_dtypes(agent, lambda: agent.update(batch)) == {torch.bfloat16}
        for _ in range(3):
            metrics = agent.update(trainer.buffer.sample(32))
        assert all(v == v for v in metrics.values() if isinstance(v, float))  # no NaN
        for module in agent.modules().values():
            assert {p.dtype for p in module.parameters()} <= {torch.float32}
        assert agent.critic_opt.flat.dtype == torch.float32
        # acting (outside updates) stays float32
        batch = trainer.buffer.sample(4)
        dtypes = linear_output_dtypes(agent, lambda: agent.act(batch.obs, batch.goal))
        assert dtypes == {torch.float32}
    finally:
        trainer.close()


def test_fp32_updates_stay_float32(tmp_path):
    trainer = filled(tmp_path)
    try:
        agent, batch = trainer.agent, trainer.buffer.sample(32)
        assert linear_output_dtypes(agent, lambda: agent.update(batch)) == {torch.float32}
    finally:
        trainer.close()


def test_bf16_update_steps_as_fp32_does(tmp_path):
    """The same agent, batch and noise: a bf16 update's gradients are float32's, up to
    rounding."""
    trainer = filled(tmp_path)
    try:
        agent32 = trainer.agent
        agent16 = copy.deepcopy(agent32)
        agent16.options = dataclasses.replace(agent16.options, precision="bf16")
        batch = trainer.buffer.sample(32)
        agent32.update(batch)
        agent16.update(batch)
        for name in ("critic_opt", "actor_opt"):
            g32, g16 = getattr(agent32, name).grad, getattr(agent16, name).grad
            assert g32.norm() > 0
            cos = torch.nn.functional.cosine_similarity(g32, g16, dim=0)
            assert cos > 0.95, (name, float(cos))
            assert 0.8 < float(g16.norm() / g32.norm()) < 1.25
    finally:
        trainer.close()


def test_unknown_precision_is_one_line_error(tmp_path, capsys):
    cfg = tiny("lang2d-quick", tmp_path / "run")
    cfg.agent = dataclasses.replace(cfg.agent, precision="fp16")
    with pytest.raises(LcrlError, match="unknown precision 'fp16'; choose one of"):
        Trainer(cfg)
    code = cli("train", "lang2d-quick", "--out", str(tmp_path / "cli"), "--agent.precision", "x")
    assert code != 0
    assert "unknown precision 'x'" in error_line(capsys.readouterr().err)

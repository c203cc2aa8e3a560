"""``--agent.compile``: compiled networks keep their parameter names and learn as eager."""

from __future__ import annotations

import pytest
import torch
from helpers import tiny

from train.loop import Trainer


@pytest.mark.slow  # compiling takes a minute or more on a CPU
def test_compiled_networks_keep_checkpoint_names_and_update(tmp_path):
    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=200, learning_starts=100)
    trainer = Trainer(cfg)
    try:
        while trainer.step < 150:
            trainer.advance()
        agent = trainer.agent
        names = {k: list(m.state_dict()) for k, m in agent.modules().items()}
        before = [p.detach().clone() for p in agent.critic.parameters()]
        agent.compile_networks()
        assert {k: list(m.state_dict()) for k, m in agent.modules().items()} == names
        metrics = agent.update(trainer.buffer.sample(32))
        assert all(v == v for v in metrics.values() if isinstance(v, float))  # no NaN
        after = list(agent.critic.parameters())
        assert any(not torch.equal(a, b) for a, b in zip(after, before, strict=True))
    finally:
        trainer.close()

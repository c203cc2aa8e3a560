"""``--agent.compile``: compiled networks keep their parameter names and learn as eager."""

from __future__ import annotations

import pytest
import torch
from helpers import tiny

from train.training.loop import Trainer


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


def test_compile_mode_records_cuda_graphs_on_cuda_only():
    from lcrl.algos.base import compile_mode

    assert compile_mode(torch.device("cuda")) == "reduce-overhead"
    assert compile_mode(torch.device("cuda:1")) == "reduce-overhead"
    assert compile_mode(torch.device("cpu")) == "default"


def test_compiling_on_cuda_is_refused_with_the_reason():
    """On CUDA the CUDA-graph replay overwrote outputs still in use (measured on an H100):
    a clear error before training, not a traceback at the first update."""
    from types import SimpleNamespace

    from lcrl.algos.base import Agent
    from lcrl.errors import LcrlError

    with pytest.raises(LcrlError, match="does not work on CUDA yet"):
        Agent.compile_networks(SimpleNamespace(device=torch.device("cuda")))


def test_to_device_on_cpu_converts_without_pinning(monkeypatch):
    import numpy as np

    from lcrl.algos.base import to_device

    def no_pin(self):
        raise AssertionError("pinned memory on a CPU transfer")

    monkeypatch.setattr(torch.Tensor, "pin_memory", no_pin)
    a = np.arange(6, dtype=np.float64).reshape(2, 3)
    t = to_device(a, torch.device("cpu"), torch.float32)
    assert t.dtype == torch.float32 and t.shape == (2, 3)
    assert torch.equal(t, torch.arange(6.0).reshape(2, 3))
    same = np.ones(4, np.float32)
    assert to_device(same, torch.device("cpu")).data_ptr() == same.ctypes.data  # no copy
    assert torch.equal(to_device(torch.ones(2), torch.device("cpu")), torch.ones(2))


def test_to_device_on_cuda_goes_through_pinned_memory(monkeypatch):
    """The CUDA path, observed on a CPU build: the host tensor is pinned, then copied with
    ``non_blocking=True``."""
    import numpy as np

    from lcrl.algos.base import to_device

    calls = []
    real_to = torch.Tensor.to

    def fake_pin(self):
        calls.append("pin")
        return self

    def fake_to(self, *args, **kwargs):
        if args and isinstance(args[0], torch.device) and args[0].type == "cuda":
            calls.append(("to", args[0].type, kwargs.get("non_blocking")))
            return self
        return real_to(self, *args, **kwargs)

    monkeypatch.setattr(torch.Tensor, "pin_memory", fake_pin)
    monkeypatch.setattr(torch.Tensor, "to", fake_to)
    t = to_device(np.zeros((2, 2), np.float64), torch.device("cuda"), torch.float32)
    assert t.dtype == torch.float32
    assert calls == ["pin", ("to", "cuda", True)]

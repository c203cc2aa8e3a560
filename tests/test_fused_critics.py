"""The critics' hand-written backward pass (:mod:`lcrl.nets.fused`): the same values and
gradients as autograd through the layers, the actor's ``min_k Q_k`` through the smallest
member only, and the layer path wherever the fused one does not apply."""

from __future__ import annotations

import pytest
import torch

from lcrl.nets.heads import GoalConditionedEnsemble
from lcrl.nets.layers import NetConfig

OBS, GOAL, ACT, ROWS = 6, 3, 2, 40


def _ensemble(hidden: tuple[int, ...], members: int = 2) -> GoalConditionedEnsemble:
    torch.manual_seed(0)
    return GoalConditionedEnsemble(
        members, {"observation": (OBS,)}, "vector", (GOAL,), 1, NetConfig(hidden=hidden), ACT
    )


def _inputs(seed: int = 1) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    obs = {"observation": torch.randn(ROWS, OBS, generator=gen)}
    goal = torch.randn(ROWS, GOAL, generator=gen)
    action = torch.randn(ROWS, ACT, generator=gen).requires_grad_(True)
    return obs, goal, action


def _layer_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(GoalConditionedEnsemble, "_fusable", lambda self, h: False)


def _grads(net: torch.nn.Module, action: torch.Tensor, loss: torch.Tensor) -> list[torch.Tensor]:
    net.zero_grad()
    action.grad = None
    loss.backward()
    grads = [p.grad.clone() for p in net.parameters() if p.requires_grad]
    return [*grads, action.grad.clone()]


@pytest.mark.parametrize("hidden", [(16, 16), (8,)])
def test_the_fused_critic_step_matches_autograd_through_the_layers(hidden, monkeypatch) -> None:
    net = _ensemble(hidden)
    obs, goal, action = _inputs()
    target = torch.randn(2, ROWS, 1, generator=torch.Generator().manual_seed(2))

    out = net(obs, goal, action)
    assert out.grad_fn is not None and type(out.grad_fn).__name__ == "EnsembleMLPBackward"
    fused = _grads(net, action, (out - target).pow(2).sum())
    with monkeypatch.context() as m:
        _layer_path(m)
        ref_out = net(obs, goal, action)
        assert type(ref_out.grad_fn).__name__ != "EnsembleMLPBackward"
        ref = _grads(net, action, (ref_out - target).pow(2).sum())
    torch.testing.assert_close(out, ref_out)
    assert len(fused) == len(ref) == 2 * (len(hidden) + 1) + 1
    for a, b in zip(fused, ref, strict=True):
        assert b.abs().max() > 0  # every parameter and the action get a gradient
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_the_actor_reads_frozen_critics_through_the_smallest_member_only(monkeypatch) -> None:
    net = _ensemble((16, 16), members=3)
    net.requires_grad_(False)
    obs, goal, action = _inputs(seed=4)
    weights = torch.linspace(-1.0, 2.0, ROWS).unsqueeze(-1)

    value = net.min_value(obs, goal, action)
    assert type(value.grad_fn).__name__ == "EnsembleMinBackward"
    (value * weights).sum().backward()
    fused = action.grad.clone()
    action.grad = None
    with monkeypatch.context() as m:
        _layer_path(m)
        ref_value = net(obs, goal, action).min(0).values
        (ref_value * weights).sum().backward()
    torch.testing.assert_close(value, ref_value)
    torch.testing.assert_close(fused, action.grad, rtol=1e-5, atol=1e-6)
    chosen = net(obs, goal, action).argmin(0).squeeze(-1)
    assert len(set(chosen.tolist())) == 3  # every member is the smallest somewhere


def test_critics_that_learn_take_the_minimum_with_every_member_s_gradient() -> None:
    net = _ensemble((16,))
    obs, goal, action = _inputs()
    value = net.min_value(obs, goal, action)
    assert type(value.grad_fn).__name__ != "EnsembleMinBackward"
    value.sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_bf16_autocast_keeps_the_layer_path() -> None:
    net = _ensemble((16,))
    obs, goal, action = _inputs()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(obs, goal, action)
    assert type(out.grad_fn).__name__ != "EnsembleMLPBackward"
    assert out.dtype == torch.float32

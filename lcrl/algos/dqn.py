"""Double DQN (discrete actions) with a Polyak-averaged target network and epsilon-greedy
exploration."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lcrl.algos.base import (
    Agent,
    AgentOptions,
    AlgoSpec,
    GoalEmbedder,
    Problem,
    check_fields,
    flat_target,
)
from lcrl.buffer import Batch
from lcrl.nets import FlatAdam


@dataclass
class DQNConfig:
    """Double DQN (discrete actions)."""

    gamma: float = 0.98
    """Discount factor."""
    lr: float = 1e-3
    """Learning rate."""
    tau: float = 0.01
    """Polyak rate of the target network."""
    eps_start: float = 1.0
    """Initial epsilon of epsilon-greedy exploration."""
    eps_end: float = 0.05
    """Final epsilon."""
    eps_decay_steps: int = 20_000
    """Acting steps over which epsilon decays linearly."""
    max_grad_norm: float | None = 10.0
    """Clip gradient norms to this (``None``: no clipping)."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        check_fields(
            self,
            "dqn",
            unit=("gamma", "tau"),
            probability=("eps_start", "eps_end"),
            positive=("lr",),
            non_negative=("eps_decay_steps",),
            positive_or_none=("max_grad_norm",),
        )


class DQN(Agent):
    """Double DQN with a Polyak-averaged target network and epsilon-greedy exploration.

    Args:
        problem: observation shapes, goal encoding, discrete action space.
        options: networks, normalisation, augmentation, device and seed.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: DQN's hyper-parameters (defaults when ``None``).
    """

    LEARNING_ONLY = ("q_target",)

    name = "dqn"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: DQNConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = cfg = config or DQNConfig()
        self.q = self._net(problem.action_dim)
        self.q_target, self._target_flat = flat_target(self.q)
        self.opt = FlatAdam(self.q.parameters(), cfg.lr, max_grad_norm=cfg.max_grad_norm)

    @property
    def epsilon(self) -> float:
        """Current exploration rate (linear decay over acting steps)."""
        cfg = self.cfg
        frac = min(1.0, self.acts / max(1, cfg.eps_decay_steps))
        return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Greedy actions, epsilon-greedy when not ``deterministic``."""
        with torch.inference_mode():
            q = self.q(self.obs_tensors(obs), self.goal_tensor(goal, embedded))
            a = q.argmax(-1).cpu().numpy()
        if not deterministic:
            explore = self.np_rng.random(a.shape) < self.epsilon
            a = np.where(explore, self.np_rng.integers(0, self.problem.action_dim, a.shape), a)
            self.acts += 1
        return a.astype(np.int64)

    def update(self, batch: Batch) -> dict[str, float]:
        """One double-DQN step (Huber loss) and a target update."""
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        cfg = self.cfg
        with torch.no_grad():
            best = self.q(nobs, goal).argmax(-1, keepdim=True)
            target_q = self.q_target(nobs, goal).gather(-1, best).squeeze(-1)
            y = self.bound_targets(rew + boot * target_q)
        q = self.q(obs, goal).gather(-1, act.reshape(-1, 1)).squeeze(-1)
        loss = F.smooth_l1_loss(q, y)
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        with torch.no_grad():
            self._target_flat.lerp_(self.opt.flat, cfg.tau)
        self.updates += 1
        return {"loss": loss.item(), "q": q.detach().mean().item(), "epsilon": self.epsilon}

    def modules(self) -> dict[str, nn.Module]:
        """Q network, its target and normalisers."""
        return {**super().modules(), "q": self.q, "q_target": self.q_target}

    def states(self) -> dict[str, Any]:
        """Optimiser state, generator and counters."""
        return {**super().states(), "opt": self.opt.state_dict()}

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        self.opt.load_state_dict(states["opt"])


SPEC = AlgoSpec(
    name="dqn",
    agent=DQN,
    config=DQNConfig,
    actions="discrete",
    multitask=False,
    learns_from="env",
    summary="double DQN: epsilon-greedy exploration, Huber loss, Polyak target network",
)

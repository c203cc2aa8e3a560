"""Twin delayed DDPG (TD3, continuous actions): twin critics, target policy smoothing and
delayed actor and target updates."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
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
from lcrl.nets import FlatAdam, grounding_loss


@dataclass
class TD3Config:
    """Twin delayed DDPG (continuous actions)."""

    gamma: float = 0.98
    """Discount factor."""
    tau: float = 0.005
    """Polyak rate of the target networks."""
    actor_lr: float = 1e-3
    """Actor learning rate."""
    critic_lr: float = 1e-3
    """Critic learning rate."""
    policy_noise: float = 0.2
    """Std of the target policy smoothing noise."""
    noise_clip: float = 0.5
    """Clip of the target policy smoothing noise."""
    policy_delay: int = 2
    """Critic updates per actor update."""
    exploration_noise: float = 0.2
    """Std of the Gaussian noise added to actions while collecting data."""
    max_grad_norm: float | None = None
    """Clip gradient norms to this (``None``: no clipping)."""
    bc_alpha: float = 2.5
    """Offline training only (``lcrl train --offline FILE``): TD3+BC (Fujimoto & Gu 2021).
    The actor minimises ``-alpha / mean|Q| * Q(s, pi(s)) + (pi(s) - a)^2`` with ``a`` the
    dataset's action, so it stays near the data where the critic is trusted; larger alpha
    is more RL, 0 is plain behavioural cloning of the relabelled data. Online runs ignore it."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        check_fields(
            self,
            "td3",
            unit=("gamma", "tau"),
            positive=("actor_lr", "critic_lr", "policy_delay"),
            non_negative=("policy_noise", "noise_clip", "exploration_noise", "bc_alpha"),
            positive_or_none=("max_grad_norm",),
        )


def deterministic_act(
    agent: Agent,
    obs: Mapping[str, np.ndarray],
    goal: np.ndarray | torch.Tensor,
    deterministic: bool,
    embedded: bool,
) -> np.ndarray:
    """``tanh(actor(obs, goal))``, plus Gaussian noise of std
    ``agent.cfg.exploration_noise`` (clipped to the action box) unless ``deterministic``:
    how deterministic actors (TD3, CRL) act."""
    with torch.inference_mode():
        a = torch.tanh(agent.actor(agent.obs_tensors(obs), agent.goal_tensor(goal, embedded)))
        if not deterministic:
            noise = torch.randn(a.shape, generator=agent.gen, device=agent.device)
            a = (a + agent.cfg.exploration_noise * noise).clamp(-1.0, 1.0)
    agent.acts += 1
    return a.cpu().numpy()


class TD3(Agent):
    """Twin delayed deep deterministic policy gradient.

    Args:
        problem: observation shapes, goal encoding, continuous action space.
        options: networks, normalisation, augmentation, device and seed.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: TD3's hyper-parameters (defaults when ``None``).
    """

    LEARNING_ONLY = ("critic", "actor_target", "critic_target")

    name = "td3"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: TD3Config | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = cfg = config or TD3Config()
        n = problem.action_dim
        self.actor = self._net(n)
        self.critic = self._critics(n)
        self.actor_target, self._actor_target_flat = flat_target(self.actor)
        self.critic_target, self._critic_target_flat = flat_target(self.critic)
        self.actor_opt = FlatAdam(
            self.actor.parameters(), cfg.actor_lr, max_grad_norm=cfg.max_grad_norm
        )
        self.critic_opt = FlatAdam(
            self.critic.parameters(), cfg.critic_lr, max_grad_norm=cfg.max_grad_norm
        )
        self._last_actor_loss = 0.0
        #: Learning from a fixed dataset (TD3+BC's actor loss, :attr:`TD3Config.bc_alpha`).
        self.offline = False

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Deterministic actions, plus clipped Gaussian exploration noise when not
        ``deterministic``."""
        return deterministic_act(self, obs, goal, deterministic, embedded)

    def update(self, batch: Batch) -> dict[str, float]:
        """One critic step, and an actor and target step every ``policy_delay`` calls."""
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        cfg = self.cfg
        with torch.no_grad():
            noise = torch.randn(act.shape, generator=self.gen, device=self.device)
            noise = (cfg.policy_noise * noise).clamp(-cfg.noise_clip, cfg.noise_clip)
            next_a = (torch.tanh(self.actor_target(nobs, goal)) + noise).clamp(-1.0, 1.0)
            target_q = self.critic_target.min_value(nobs, goal, next_a).squeeze(-1)
            y = self.bound_targets(rew + boot * target_q)
        q = self.critic(obs, goal, act).squeeze(-1)
        critic_loss = 0.5 * (q - y).pow(2).mean(-1).sum()
        named = self.grounding_rows(batch.goal)
        grounding = {}
        if named is not None:  # the auxiliary grounding loss (AgentOptions.grounding)
            ground = grounding_loss(self.critic.selection_logits(obs, goal), named)
            grounding["grounding_critic"] = ground.item()
            critic_loss = critic_loss + self.options.grounding * ground
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        if self.updates % cfg.policy_delay == 0:
            self.critic.requires_grad_(False)
            pi = torch.tanh(self.actor(obs, goal))
            q_pi = self.critic(obs, goal, pi)[0]
            if self.offline:  # TD3+BC: stay near the dataset's actions
                lam = cfg.bc_alpha / q_pi.abs().mean().detach().clamp_min(1e-6)
                actor_loss = -lam * q_pi.mean() + (pi - act).pow(2).mean()
            else:
                actor_loss = -q_pi.mean()
            if named is not None:
                ground = grounding_loss(self.actor.selection_logits(obs, goal), named)
                grounding["grounding_actor"] = ground.item()
                actor_loss = actor_loss + self.options.grounding * ground
            self.actor_opt.zero_grad()
            actor_loss.backward()
            self.actor_opt.step()
            self.critic.requires_grad_(True)
            with torch.no_grad():
                self._actor_target_flat.lerp_(self.actor_opt.flat, cfg.tau)
                self._critic_target_flat.lerp_(self.critic_opt.flat, cfg.tau)
            self._last_actor_loss = actor_loss.item()
        return {
            "critic_loss": critic_loss.item(),
            "actor_loss": self._last_actor_loss,
            "q": q.detach().mean().item(),
            **grounding,
        }

    def modules(self) -> dict[str, nn.Module]:
        """Actor, critics, their targets and normalisers."""
        return {
            **super().modules(),
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
        }

    def states(self) -> dict[str, Any]:
        """Optimiser states, generator and counters."""
        return {
            **super().states(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "last_actor_loss": self._last_actor_loss,
        }

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        self.actor_opt.load_state_dict(states["actor_opt"])
        self.critic_opt.load_state_dict(states["critic_opt"])
        self._last_actor_loss = float(states.get("last_actor_loss", 0.0))


SPEC = AlgoSpec(
    name="td3",
    agent=TD3,
    config=TD3Config,
    actions="continuous",
    multitask=False,
    privileged_critic=True,
    learns_from="env",
    summary="twin delayed DDPG: deterministic actor with Gaussian exploration noise",
)

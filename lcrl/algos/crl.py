"""Contrastive RL (CRL, Eysenbach et al. 2022; OGBench's ``crl``): the critic is a
classifier of which goal a state-action pair goes on to achieve, learned by InfoNCE on the
buffer's hindsight-relabelled rows, and the actor climbs it.

A row whose goal was relabelled to one its episode achieved later (``Batch.relabelled``)
is a positive pair ``(s, a, g+)``. Its negatives are the goals of ``negatives`` other rows
of the same batch, so they follow the goals' marginal distribution; for goals given as ids
(instructions, task ids), a negative equal to the positive is masked out. The critic
``f(s, a, g)`` is the run's goal-conditioned network (it reads object slots through the
goal like the other learners), evaluated on the positive and the negatives of each row;
its softmax cross-entropy on the positive is the loss, and at its optimum ``f`` is the log
ratio ``p(g | s, a) / p(g)`` up to a per-row constant. Rows that keep their recorded goal
are not used: nothing says their episode reached it.

The actor maximises ``f(s, pi(s), g) / mean|f|`` minus ``bc_alpha`` times the squared
distance to the dataset's action (the offline regulariser of OGBench's CRL; 0 online).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lcrl.algos.base import Agent, AgentOptions, AlgoSpec, GoalEmbedder, Problem, check_fields
from lcrl.algos.td3 import deterministic_act
from lcrl.buffer import Batch
from lcrl.nets import FlatAdam, grounding_loss


@dataclass
class CRLConfig:
    """Contrastive RL (continuous actions)."""

    actor_lr: float = 3e-4
    """Actor learning rate."""
    critic_lr: float = 3e-4
    """Critic (contrastive classifier) learning rate."""
    negatives: int = 15
    """Negative goals per positive row, taken from other rows of the batch."""
    bc_alpha: float = 0.1
    """Weight of the behavioural-cloning term of the actor loss (offline regulariser;
    ``(pi(s) - a)^2`` with ``a`` the stored action). 0: pure critic ascent."""
    exploration_noise: float = 0.2
    """Std of the Gaussian noise added to actions while collecting data."""
    max_grad_norm: float | None = None
    """Clip gradient norms to this (``None``: no clipping)."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        check_fields(
            self,
            "crl",
            positive=("actor_lr", "critic_lr", "negatives"),
            non_negative=("bc_alpha", "exploration_noise"),
            positive_or_none=("max_grad_norm",),
        )


class CRL(Agent):
    """Contrastive RL with a goal-conditioned critic ensemble and a deterministic actor.

    Args:
        problem: observation shapes, goal encoding, continuous action space.
        options: networks, normalisation, augmentation, device and seed.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: CRL's hyper-parameters (defaults when ``None``).
    """

    LEARNING_ONLY = ("critic",)

    name = "crl"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: CRLConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = cfg = config or CRLConfig()
        n = problem.action_dim
        self.actor = self._net(n)
        self.critic = self._critics(n)
        self.actor_opt = FlatAdam(
            self.actor.parameters(), cfg.actor_lr, max_grad_norm=cfg.max_grad_norm
        )
        self.critic_opt = FlatAdam(
            self.critic.parameters(), cfg.critic_lr, max_grad_norm=cfg.max_grad_norm
        )

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Deterministic actions, plus Gaussian exploration noise when not
        ``deterministic``."""
        return deterministic_act(self, obs, goal, deterministic, embedded)

    def contrastive_logits(
        self,
        obs: Mapping[str, torch.Tensor],
        act: torch.Tensor,
        goal: torch.Tensor,
        negatives: torch.Tensor,
    ) -> torch.Tensor:
        """Critic logits ``(ensemble, B, 1 + M)``: column 0 for each row's own goal, the
        others for the goals of rows ``negatives[:, m]`` (``(B, M)`` indices)."""
        b, m = negatives.shape
        goals = torch.cat([goal.unsqueeze(1), goal[negatives]], 1)  # (B, 1 + M, ...)
        goals = goals.reshape(b * (1 + m), *goal.shape[1:])
        rep = {k: v.repeat_interleave(1 + m, 0) for k, v in obs.items()}
        out = self.critic(rep, goals, act.repeat_interleave(1 + m, 0))
        return out.reshape(out.shape[0], b, 1 + m)

    def update(self, batch: Batch) -> dict[str, float]:
        """One contrastive critic step and one actor step on the batch's relabelled rows
        (a batch without any changes nothing)."""
        rows = np.flatnonzero(batch.relabelled)
        if rows.size < 2:
            return {}
        cfg = self.cfg
        obs = self.obs_tensors({k: v[rows] for k, v in batch.obs.items()})
        ids = np.asarray(batch.goal)[rows]
        goal = self.goal_tensor(ids)
        act = torch.as_tensor(batch.action[rows], device=self.device).float()
        b = rows.size
        m = min(cfg.negatives, b - 1)
        # M distinct other rows for each row: shifts 1..B-1 drawn without replacement
        shifts = torch.randperm(b - 1, generator=self.gen, device=self.device)[:m] + 1
        negatives = (torch.arange(b, device=self.device)[:, None] + shifts[None, :]) % b
        logits = self.contrastive_logits(obs, act, goal, negatives)
        if ids.dtype.kind in "iu":  # the same goal drawn as a negative is no negative
            same = torch.as_tensor(ids, device=self.device)
            clash = same[negatives] == same[:, None]
            logits = logits.masked_fill(
                torch.cat([torch.zeros_like(clash[:, :1]), clash], 1).unsqueeze(0), -1e9
            )
        target = torch.zeros(b, dtype=torch.long, device=self.device)
        critic_loss = sum(F.cross_entropy(lg, target) for lg in logits)
        named = self.grounding_rows(ids) if ids.dtype.kind in "iu" else None
        metrics: dict[str, float] = {}
        if named is not None:  # the auxiliary grounding loss (AgentOptions.grounding)
            ground = grounding_loss(self.critic.selection_logits(obs, goal), named)
            metrics["grounding_critic"] = ground.item()
            critic_loss = critic_loss + self.options.grounding * ground
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()

        self.critic.requires_grad_(False)
        pi = torch.tanh(self.actor(obs, goal))
        q = self.critic.min_value(obs, goal, pi).squeeze(-1)
        actor_loss = -(q / q.abs().mean().detach().clamp_min(1e-6)).mean()
        if cfg.bc_alpha:
            actor_loss = actor_loss + cfg.bc_alpha * (pi - act).pow(2).mean()
        if named is not None:
            ground = grounding_loss(self.actor.selection_logits(obs, goal), named)
            metrics["grounding_actor"] = ground.item()
            actor_loss = actor_loss + self.options.grounding * ground
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        self.critic.requires_grad_(True)
        self.updates += 1
        with torch.no_grad():
            accuracy = (logits[0].argmax(-1) == 0).float().mean()
        return {
            "critic_loss": float(critic_loss.item()),
            "actor_loss": actor_loss.item(),
            "q": q.detach().mean().item(),
            "contrastive_accuracy": accuracy.item(),
            **metrics,
        }

    def modules(self) -> dict[str, nn.Module]:
        """Actor, critics and normalisers."""
        return {**super().modules(), "actor": self.actor, "critic": self.critic}

    def states(self) -> dict[str, Any]:
        """Optimiser states, generator and counters."""
        return {
            **super().states(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
        }

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        self.actor_opt.load_state_dict(states["actor_opt"])
        self.critic_opt.load_state_dict(states["critic_opt"])


SPEC = AlgoSpec(
    name="crl",
    agent=CRL,
    config=CRLConfig,
    actions="continuous",
    multitask=False,
    privileged_critic=False,
    learns_from="env",
    summary="contrastive RL: an InfoNCE critic over hindsight goals, a deterministic actor",
)

"""Multi-task behavioural cloning conditioned on goals (frozen text embeddings, ids, vectors).

:class:`BC` regresses the demonstrated action from the observation and the goal with the
same networks as the reinforcement-learning actor (:class:`lcrl.nets.GoalConditionedNet`:
one encoder per observation key, CNNs for camera images, a learned projection of the
frozen text embedding), so one policy follows many instructions, and a checkpoint of it
loads and acts exactly like an RL policy.

Losses (:attr:`BCConfig.loss`):

* ``mse``: deterministic regression of the tanh-squashed mean onto the demonstrated
  action (squared error summed over action dimensions, averaged over the batch);
* ``gaussian``: negative log-likelihood of the demonstrated action under a tanh-squashed
  Gaussian (mean and log-std per dimension, the SAC actor's distribution); acting
  deterministically takes the tanh of the mean;
* discrete actions always use the cross-entropy of the action logits; acting takes the
  argmax (or samples the softmax when not deterministic).

A batch is anything with ``obs`` (``{key: (B, ...)}``), ``action`` and ``goal`` (goal ids
embedded by the goal space, or goal vectors): :class:`lcrl.demos.DemoBatch` and
:class:`lcrl.buffer.Batch` both are.

Normalisation: vector observations go through the running normalisers of
:class:`lcrl.algos.base.Agent`; fit them on the data before training with
:meth:`Agent.observe` (and text goals on the training instructions' embeddings), then
they stay fixed, since :meth:`BC.update` never updates them.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lcrl.algos.base import Agent, AgentOptions, AlgoSpec, GoalEmbedder, Problem, check_fields
from lcrl.errors import LcrlError
from lcrl.nets import FlatAdam, gaussian_log_prob_tanh, grounding_loss, random_shift

#: Losses of continuous-action behavioural cloning (:attr:`BCConfig.loss`).
BC_LOSSES = ("mse", "gaussian")
#: Demonstrated actions are clipped to this magnitude before ``atanh`` (gaussian loss).
ACTION_CLIP = 1.0 - 1e-3
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


@dataclass
class BCConfig:
    """Behavioural cloning from demonstrations (``lcrl train lang2d-bc --demos FILE``)."""

    lr: float = 1e-3
    """Learning rate (Adam)."""
    loss: str = "mse"
    """Continuous actions: ``mse`` (regress the tanh-squashed mean onto the demonstrated
    action) or ``gaussian`` (log-likelihood under a tanh-squashed Gaussian, the SAC
    actor's distribution). Discrete actions always use cross-entropy."""
    weight_decay: float = 0.0
    """Decoupled weight decay (as in AdamW) on every network weight; 0 turns it off."""
    max_grad_norm: float | None = 10.0
    """Clip the gradient norm to this (``None``: no clipping, and no grad_norm logged)."""
    hindsight: bool = True
    """Also train on the dataset's hindsight segments (instructions a demonstration
    achieved on the way, added by ``lcrl demos relabel``); ``--bc.no-hindsight`` trains on
    the given instructions only."""
    cache_steps: int = 200_000
    """Observations of the dataset held in memory at a time (blocks of episodes are read
    and shuffled within; larger mixes better, smaller saves memory on image datasets)."""
    norm_rows: int = 50_000
    """Dataset rows the observation normalisers are fitted on before training (at most
    the dataset's size, drawn at random)."""
    ema: float = 0.0
    """Polyak average of the policy's weights, the policy that acts (and is evaluated and
    checkpointed as ``actor_ema``): after each update ``avg = ema * avg + (1 - ema) * w``;
    0 turns it off and the trained weights act. Typical: 0.999."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        if self.loss not in BC_LOSSES:
            raise LcrlError(f"unknown bc.loss {self.loss!r}; choose one of {BC_LOSSES}")
        check_fields(
            self,
            "bc",
            positive=("lr", "cache_steps", "norm_rows"),
            non_negative=("weight_decay",),
            positive_or_none=("max_grad_norm",),
        )
        if not 0.0 <= self.ema < 1.0:
            raise LcrlError(f"bc.ema must be in [0, 1) (0: off), got {self.ema}")


def tanh_gaussian_log_prob(
    mean: torch.Tensor, log_std: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """Log-density (``(B,)``) of actions in ``[-1, 1]`` under ``tanh(N(mean, exp(log_std)))``
    (actions are clipped to :data:`ACTION_CLIP` first, where ``atanh`` is finite)."""
    a = action.clamp(-ACTION_CLIP, ACTION_CLIP)
    z = (torch.atanh(a) - mean) * torch.exp(-log_std)
    logp = (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    return logp - torch.log1p(-a.pow(2)).sum(-1)


class BC(Agent):
    """Goal-conditioned behavioural cloning: one policy network, trained by regression.

    Args:
        problem: observation shapes, goal encoding, action space.
        options: networks, normalisation, augmentation, device and seed.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: learning rate, loss, regularisation.
    """

    name = "bc"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: BCConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = cfg = config or BCConfig()
        cfg.validate()
        n = problem.action_dim
        self.gaussian = not problem.discrete and cfg.loss == "gaussian"
        self.actor = self._net(2 * n if self.gaussian else n)
        self.opt = FlatAdam(self.actor.parameters(), cfg.lr, max_grad_norm=cfg.max_grad_norm)
        #: The averaged policy that acts (:attr:`BCConfig.ema`); None: the trained one acts.
        self.actor_ema: nn.Module | None = None
        if cfg.ema:
            self.actor_ema = copy.deepcopy(self.actor).requires_grad_(False)
            self.reset_average()

    def reset_average(self) -> None:
        """Make the averaged policy equal the trained one (after its weights were set
        from elsewhere, e.g. a teacher's); nothing without :attr:`BCConfig.ema`."""
        if self.actor_ema is None:
            return
        pairs = [
            *zip(self.actor_ema.parameters(), self.actor.parameters(), strict=True),
            *zip(self.actor_ema.buffers(), self.actor.buffers(), strict=True),
        ]
        with torch.no_grad():
            for avg, w in pairs:
                avg.grad = None
                avg.copy_(w)

    def _average(self) -> None:
        """Move the averaged policy towards the trained one by ``1 - ema``."""
        if self.actor_ema is None:
            return
        with torch.no_grad():
            avg = list(self.actor_ema.parameters())
            torch._foreach_lerp_(avg, list(self.actor.parameters()), 1.0 - self.cfg.ema)
            for b, w in zip(self.actor_ema.buffers(), self.actor.buffers(), strict=True):
                b.copy_(w)

    # --- acting ----------------------------------------------------------------------
    def _outputs(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor, acting: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Action mean (pre-tanh) or logits, and the log-std of the gaussian loss, of the
        trained policy, or with ``acting`` of the one that acts (the average, if any)."""
        net = self.actor_ema if acting and self.actor_ema is not None else self.actor
        out = net(obs, goal)
        if not self.gaussian:
            return out, None
        mean, log_std = out.chunk(2, -1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Actions for a batch of observations and goals.

        Continuous actions lie in ``[-1, 1]``: the tanh of the mean, or with the gaussian
        loss and not ``deterministic`` a sample of the tanh-Gaussian (the mse loss has no
        spread to sample: it always acts with the mean). Discrete actions are the argmax of
        the logits, or a sample of their softmax when not ``deterministic``.
        """
        with torch.inference_mode():
            mean, log_std = self._outputs(
                self.obs_tensors(obs), self.goal_tensor(goal, embedded), acting=True
            )
            if self.problem.discrete:
                if deterministic:
                    a = mean.argmax(-1)
                else:
                    a = torch.multinomial(mean.softmax(-1), 1, generator=self.gen).squeeze(-1)
                out = a.cpu().numpy().astype(np.int64)
            elif log_std is not None and not deterministic:
                noise = torch.randn(mean.shape, generator=self.gen, device=self.device)
                out = gaussian_log_prob_tanh(mean, log_std, noise)[0].cpu().numpy()
            else:
                out = torch.tanh(mean).cpu().numpy()
        self.acts += 1
        return out

    # --- learning --------------------------------------------------------------------
    def log_prob(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor, action: torch.Tensor
    ) -> torch.Tensor:
        """Log-likelihood of actions (``(B,)``): the categorical of discrete actions, the
        tanh-Gaussian of continuous ones (gaussian loss only)."""
        mean, log_std = self._outputs(obs, goal)
        if self.problem.discrete:
            return -F.cross_entropy(mean, action.long(), reduction="none")
        if log_std is None:
            raise LcrlError("the mse loss has no likelihood: use bc.loss=gaussian")
        return tanh_gaussian_log_prob(mean, log_std, action)

    def update(self, batch: Any) -> dict[str, float]:
        """One gradient step on a batch with ``obs``, ``action`` and ``goal``.

        Returns:
            ``loss`` (the optimised loss), ``action_mse`` (squared error of the
            deterministic action, summed over dimensions) or ``accuracy`` (discrete),
            ``grad_norm`` (with clipping), and ``log_std`` (gaussian loss).
        """
        obs = self.obs_tensors(batch.obs)
        goal = self.batch_goal(batch.goal)
        pad = self.options.augment_pad
        if pad:
            for key, t in obs.items():
                if t.dim() == 4:
                    obs[key] = random_shift(t, pad, self.gen)
            if goal.dim() == 4:
                goal = random_shift(goal, pad, self.gen)
        action = torch.as_tensor(np.asarray(batch.action), device=self.device)
        if self.problem.discrete:
            action = action.long().reshape(-1)
        else:
            action = action.float().reshape(action.shape[0], -1)
        mean, log_std = self._outputs(obs, goal)
        metrics: dict[str, float] = {}
        named = self.grounding_rows(batch.goal)
        if self.problem.discrete:
            loss = F.cross_entropy(mean, action)
            metrics["accuracy"] = (mean.argmax(-1) == action).float().mean().item()
        else:
            err = (torch.tanh(mean) - action).pow(2).sum(-1).mean()
            if log_std is None:
                loss = err
            else:
                loss = -tanh_gaussian_log_prob(mean, log_std, action).mean()
                metrics["log_std"] = log_std.detach().mean().item()
            metrics["action_mse"] = err.item()
        if named is not None:  # the auxiliary grounding loss (AgentOptions.grounding)
            ground = grounding_loss(self.actor.selection_logits(obs, goal), named)
            metrics["grounding_actor"] = ground.item()
            loss = loss + self.options.grounding * ground
        self.opt.zero_grad()
        loss.backward()
        if self.cfg.weight_decay:
            with torch.no_grad():
                self.opt.flat.mul_(1.0 - self.cfg.lr * self.cfg.weight_decay)
        norm = self.opt.step()
        self._average()
        self.updates += 1
        metrics["loss"] = loss.item()
        if self.cfg.max_grad_norm is not None:
            metrics["grad_norm"] = norm
        return metrics

    # --- saving ----------------------------------------------------------------------
    def modules(self) -> dict[str, nn.Module]:
        """The policy network (and its average) and the normalisers."""
        out = {**super().modules(), "actor": self.actor}
        if self.actor_ema is not None:
            out["actor_ema"] = self.actor_ema
        return out

    def states(self) -> dict[str, Any]:
        """Optimiser state, generator and counters."""
        return {**super().states(), "opt": self.opt.state_dict()}

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        self.opt.load_state_dict(states["opt"])


SPEC = AlgoSpec(
    name="bc",
    agent=BC,
    config=BCConfig,
    actions="any",
    multitask=False,
    learns_from="demos",
    summary="behavioural cloning from instruction-labelled demonstrations (--demos)",
    title="behavioural cloning",
)

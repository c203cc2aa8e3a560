"""Soft actor-critic (continuous actions), with the multi-task objective ``sum_i w_i L_i``:
task weights, PCGrad and gradient-conflict measurement over a fixed task set."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
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
from lcrl.multitask import GradNorm, TaskGradients, rows_by_task, task_weights
from lcrl.nets import FlatAdam, gaussian_log_prob_tanh, grounding_loss


@dataclass
class SACConfig:
    """Soft actor-critic (continuous actions)."""

    gamma: float = 0.98
    """Discount factor."""
    tau: float = 0.005
    """Polyak rate of the target critics."""
    actor_lr: float = 1e-3
    """Actor learning rate."""
    critic_lr: float = 1e-3
    """Critic learning rate."""
    alpha_lr: float = 1e-3
    """Entropy temperature learning rate."""
    init_alpha: float = 0.1
    """Initial entropy temperature."""
    autotune_alpha: bool = True
    """Tune the temperature towards the target entropy."""
    target_entropy: float | None = None
    """Target entropy; default ``-action_dim``."""
    max_grad_norm: float | None = None
    """Clip gradient norms to this (``None``: no clipping)."""
    hindsight_bc: float = 0.0
    """Weight of a hindsight behaviour-cloning term in the actor loss: on relabelled rows
    (whose goal the episode did achieve later), the squared distance between the policy's
    mean action and the action taken, as in goal-conditioned supervised learning. 0 turns
    it off."""
    demo_bc: float = 0.0
    """Weight of a behaviour-cloning term on demonstration rows (transitions the scripted
    controller or a demonstration file acted, with their recorded or relabelled goals):
    the squared distance between the policy's mean action and the demonstrator's, as in
    Nair et al. 2018. 0 turns it off."""
    q_filter: bool = True
    """Clone a demonstration row only where the critic values the demonstrator's action
    above the policy's (the Q-filter of Nair et al. 2018), so a policy that has learned
    to do better is not pulled back."""
    target_clip: float | None = None
    """Clip the critic's TD targets to ``[-target_clip, target_clip]``. Success rewards of
    0 or 1 that end the episode bound every value by 1, so 1.0 is exact there; a critic
    whose values climb past the bound (overestimation feeding on itself) is then held
    back. ``None``: no clipping."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings that cannot train."""
        check_fields(
            self,
            "sac",
            unit=("gamma", "tau"),
            positive=("actor_lr", "critic_lr", "alpha_lr", "init_alpha"),
            non_negative=("hindsight_bc", "demo_bc"),
            positive_or_none=("max_grad_norm", "target_clip"),
            finite_or_none=("target_entropy",),
        )


@dataclass
class _Update:
    """What one SAC update's critic and actor steps share."""

    obs: dict[str, torch.Tensor]
    #: the observations the actor reads (detached where perception learned from the critic)
    actor_obs: dict[str, torch.Tensor]
    goal: torch.Tensor
    act: torch.Tensor
    y: torch.Tensor  # TD targets
    weights: torch.Tensor | None  # per-row weights (task weights), None: equal
    alpha: torch.Tensor
    measure: bool  # this update compares task gradients
    parts: list[np.ndarray | None]  # each task's rows, or [None]: the whole batch
    coefs: np.ndarray
    n: int
    relabelled: np.ndarray
    n_rel: int
    demo: np.ndarray
    n_demo: int
    named: torch.Tensor | None  # the slots each row's instruction names (grounding)
    grounding: dict[str, list[float]] = field(default_factory=lambda: {"critic": [], "actor": []})
    demo_rows: int = 0
    demo_cloned: int = 0


def _weighted_mean(x: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``x`` over its last dimension (batch rows), each row weighted (``None``: a
    plain mean)."""
    return x.mean(-1) if weights is None else (x * weights).mean(-1)


def _weighted(coefs: np.ndarray, losses: list[torch.Tensor | None]) -> float:
    """``sum_i c_i L_i`` over the parts that have a loss."""
    return float(
        sum(c * float(x.detach()) for c, x in zip(coefs, losses, strict=True) if x is not None)
    )


class SAC(Agent):
    """Soft actor-critic with twin critics, target critics and a tuned temperature.

    With active multi-task options (:class:`lcrl.multitask.MultiTaskOptions`) a batch
    row's task is its goal id, and :meth:`update` optimises ``sum_i w_i L_i``.

    Args:
        problem: observation shapes, goal encoding, continuous action space.
        options: networks, normalisation, augmentation, device, seed, multi-task options.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: SAC's hyper-parameters (defaults when ``None``).
    """

    LEARNING_ONLY = ("critic", "critic_target")

    name = "sac"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: SACConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = cfg = config or SACConfig()
        n = problem.action_dim
        self.actor = self._net(2 * n)
        self.critic = self._critics(n)
        self.critic_target, self._target_flat = flat_target(self.critic)
        #: Set by a trainer between updates (BC -> RL fine-tuning): the weight of the Q term
        #: in the actor loss (0: the actor clones, with its entropy term) and a hindsight BC
        #: weight added to ``hindsight_bc``.
        self.q_weight = 1.0
        self.extra_bc = 0.0
        self.actor_opt = FlatAdam(
            self.actor.parameters(), cfg.actor_lr, max_grad_norm=cfg.max_grad_norm
        )
        self.critic_opt = FlatAdam(
            self.critic.parameters(), cfg.critic_lr, max_grad_norm=cfg.max_grad_norm
        )
        self.log_alpha = torch.tensor(
            float(np.log(cfg.init_alpha)), device=self.device, requires_grad=True
        )
        self.alpha_opt = FlatAdam([self.log_alpha], cfg.alpha_lr)
        self.target_entropy = float(-n if cfg.target_entropy is None else cfg.target_entropy)
        mt = options.multitask
        self.multitask = mt if mt.active else None
        self._task_w: torch.Tensor | None = None  # w_i / mean(w) per task; None: all equal
        if self.multitask is not None:
            w = task_weights(mt.task_weights, problem.num_tasks)
            if not np.allclose(w, 1.0):
                self._task_w = torch.as_tensor(w, dtype=torch.float32, device=self.device)
            self._critic_tasks = TaskGradients(self.critic_opt, pcgrad=mt.pcgrad)
            self._actor_tasks = TaskGradients(self.actor_opt, pcgrad=mt.pcgrad)
        #: GradNorm's weights, learned from the critic's task gradients (multitask.weighting
        #: gradnorm); they weigh the critic and actor losses alike.
        self._gradnorm = (
            GradNorm(problem.num_tasks, mt.gradnorm_alpha, mt.gradnorm_lr)
            if self.multitask is not None and mt.gradnorm
            else None
        )
        self._task_norms: np.ndarray | None = None

    def _gaussian(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The policy's mean, clamped log standard deviation and a draw of its noise."""
        mean, log_std = self.actor(obs, goal).chunk(2, -1)
        noise = torch.randn(mean.shape, generator=self.gen, device=self.device)
        return mean, log_std.clamp(-20.0, 2.0), noise

    def _policy(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor, with_mean: bool = False
    ) -> Any:
        mean, log_std, noise = self._gaussian(obs, goal)
        a, logp = gaussian_log_prob_tanh(mean, log_std, noise)
        return (a, logp, torch.tanh(mean)) if with_mean else (a, logp)

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Sampled (or mean, when ``deterministic``) tanh-squashed actions."""
        with torch.inference_mode():
            o = self.obs_tensors(obs)
            g = self.goal_tensor(goal, embedded)
            if deterministic:
                a = torch.tanh(self.actor(o, g).chunk(2, -1)[0])
            else:  # the sample of _policy, without its log-probability
                mean, log_std, noise = self._gaussian(o, g)
                a = torch.tanh(mean + log_std.exp() * noise)
        self.acts += 1
        return a.cpu().numpy()

    def update(self, batch: Batch) -> dict[str, float]:
        """One critic, actor and temperature step and a target step; returns losses and
        diagnostics.

        The critic and actor losses are per-row losses averaged over the batch with per-row
        weights: ``w_i / mean(w)`` of the row's task under multi-task task weights, all
        equal otherwise (the usual mean). The hindsight behaviour-cloning term averages over
        the relabelled rows with the same weights.

        On updates that measure gradient conflict between tasks (every update with PCGrad,
        every ``conflict_every``-th otherwise) the batch is split by task instead: each
        task's rows go through the networks on their own (so that the task gradients cost
        about one backward pass together), the mean of their per-row losses is the task's
        loss, and :class:`lcrl.multitask.TaskGradients` combines the task gradients
        (projected first with PCGrad) with coefficients ``n_i / n * w_i`` and reports
        their conflict (``grad/*`` metrics); without projection that is the gradient of
        the same weighted loss. The targets, the temperature (tuned on the whole batch) and
        the target critics' step are the same on every update.
        """
        if self.perceiver_opt is not None:
            self.perceiver_opt.zero_grad()
        u = self._prepare(batch)
        metrics, critic_value, qs = self._critic_step(u)
        # a fine-tuned perception module learns from the critic loss; from the actor loss
        # where the critics read privileged state instead
        critic_perceives = self.perceiver is not None and not self.problem.privileged
        if critic_perceives:
            self.perceiver_opt.step()
            u.actor_obs = {k: v.detach() for k, v in u.obs.items()}
        self.critic.requires_grad_(False)
        actor_metrics, actor_value, bc_value, logp = self._actor_step(u)
        metrics.update(actor_metrics)
        if self.perceiver_opt is not None and not critic_perceives:
            self.perceiver_opt.step()
        self.critic.requires_grad_(True)
        if self.cfg.autotune_alpha:
            # the gradient of -(log_alpha * (logp + target_entropy)).mean() in closed form
            # (one autograd pass fewer per update)
            with torch.no_grad():
                self.alpha_opt.grad.copy_(-(logp.detach().float() + self.target_entropy).mean())
            self.alpha_opt.step()
        with torch.no_grad():
            self._target_flat.lerp_(self.critic_opt.flat, self.cfg.tau)
        self.updates += 1
        out = {
            "critic_loss": critic_value,
            "actor_loss": actor_value,
            "alpha": float(u.alpha),
            "q": (q_all := torch.cat(qs)).mean().item(),
            "q_max": q_all.max().item(),
            "entropy": -logp.detach().mean().item(),
        }
        if bc_value is not None:
            out["bc_loss"] = bc_value
        if u.n_demo:  # share of the batch from demonstrations, share of those cloned
            out["demo_rows"] = u.n_demo / u.n
            out["demo_cloned"] = u.demo_cloned / max(u.demo_rows, 1)
        for name, values in u.grounding.items():
            if values:  # cross-entropy of the slots picked against the slots named
                out[f"grounding_{name}"] = float(np.mean(values))
        return {**out, **metrics}

    def _prepare(self, batch: Batch) -> _Update:
        """The tensors, targets, task parts and row masks one update shares."""
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        alpha = self.log_alpha.detach().exp()
        y = self.td_target(nobs, goal, rew, boot, alpha)
        measure = self._measures()
        parts, coefs, weights = self._parts(batch, measure)
        n = len(batch.reward)
        relabelled = np.asarray(batch.relabelled, bool)
        demo = np.zeros(n, bool) if batch.demo is None else np.asarray(batch.demo, bool)
        return _Update(
            obs=obs,
            actor_obs=obs,
            goal=goal,
            act=act,
            y=y,
            weights=weights,
            alpha=alpha,
            measure=measure,
            parts=parts,
            coefs=coefs,
            n=n,
            relabelled=relabelled,
            n_rel=int(relabelled.sum()),
            demo=demo,
            n_demo=int(demo.sum()) if self.cfg.demo_bc > 0.0 else 0,
            named=self.grounding_rows(batch.goal),  # the slots each instruction names
        )

    def _take(self, u: _Update, rows: np.ndarray | None, o: Any) -> tuple[Any, ...]:
        """Observations, goals, actions, targets and row weights of a part."""
        if rows is None:
            return o, u.goal, u.act, u.y, u.weights
        idx = torch.as_tensor(rows, device=self.device)
        return {k: v[idx] for k, v in o.items()}, u.goal[idx], u.act[idx], u.y[idx], None

    def _ground(
        self, u: _Update, net: Any, o: Any, g: torch.Tensor, rows: np.ndarray | None, name: str
    ) -> Any:
        """The weighted grounding loss of a part (0 when grounding is off)."""
        if u.named is None:
            return 0.0
        t = u.named if rows is None else u.named[torch.as_tensor(rows, device=self.device)]
        loss = grounding_loss(net.selection_logits(o, g), t)
        u.grounding[name].append(float(loss.detach()))
        return self.options.grounding * loss

    def _critic_step(self, u: _Update) -> tuple[dict[str, float], float, list[torch.Tensor]]:
        """The critics' step on 0.5 (Q_k - y)^2 per critic and row: its metrics, the
        weighted loss and each part's Q values."""
        losses: list[torch.Tensor | None] = []
        qs = []
        for rows in u.parts:
            if rows is not None and len(rows) == 0:
                losses.append(None)
                continue
            o, g, a, target, w = self._take(u, rows, u.obs)
            q = self.critic(o, g, a).squeeze(-1)
            loss = 0.5 * _weighted_mean((q - target).pow(2), w).sum()
            losses.append(loss + self._ground(u, self.critic, o, g, rows, "critic"))
            qs.append(q.detach().reshape(-1))
        metrics = self._step("critic", u.measure, losses, u.coefs)
        if self._gradnorm is not None and self._task_norms is not None:
            values = [np.nan if loss is None else float(loss.detach()) for loss in losses]
            w = self._gradnorm.update(self._task_norms, np.asarray(values))
            self._task_w = torch.as_tensor(w / w.mean(), dtype=torch.float32, device=self.device)
        return metrics, _weighted(u.coefs, losses), qs

    def _actor_step(self, u: _Update) -> tuple[dict[str, float], float, float | None, torch.Tensor]:
        """The actor's step on alpha log pi - min_k Q_k per row, plus hindsight BC on
        relabelled rows and BC on demonstration rows: its metrics, the weighted loss, the
        weighted hindsight-BC loss (None without one) and the log-probabilities."""
        losses: list[torch.Tensor | None] = []
        bc_losses: list[torch.Tensor | None] = []
        logps = []
        bc_weight = self.cfg.hindsight_bc + self.extra_bc
        for rows in u.parts:
            if rows is not None and len(rows) == 0:
                losses.append(None)
                bc_losses.append(None)
                continue
            o, g, a_taken, _, w = self._take(u, rows, u.actor_obs)
            a, logp, mean_action = self._policy(o, g, with_mean=True)
            q_pi = self.critic.min_value(o, g, a).squeeze(-1)
            loss = _weighted_mean(u.alpha * logp - self.q_weight * q_pi, w)
            rel = u.relabelled if rows is None else u.relabelled[rows]
            bc_loss = None
            if bc_weight > 0.0 and rel.any():
                mask = torch.as_tensor(rel, device=self.device)
                bc_rows = (mean_action[mask] - a_taken[mask]).pow(2).sum(-1)
                bc_loss = _weighted_mean(bc_rows, None if w is None else w[mask])
                if rows is not None:  # the task's share of the mean over relabelled rows
                    bc_loss = bc_loss * (int(rel.sum()) / u.n_rel * u.n / len(rows))
                loss = loss + bc_weight * bc_loss
            dem = (u.demo if rows is None else u.demo[rows]) if u.n_demo else None
            if dem is not None and dem.any():
                loss = loss + self.cfg.demo_bc * self._demo_loss(
                    u, rows, dem, o, g, a_taken, mean_action, q_pi
                )
            losses.append(loss + self._ground(u, self.actor, o, g, rows, "actor"))
            bc_losses.append(bc_loss)
            logps.append(logp)
        metrics = self._step("actor", u.measure, losses, u.coefs)
        bc_value = _weighted(u.coefs, bc_losses) if any(x is not None for x in bc_losses) else None
        return metrics, _weighted(u.coefs, losses), bc_value, torch.cat(logps)

    def _demo_loss(
        self,
        u: _Update,
        rows: np.ndarray | None,
        dem: np.ndarray,
        o: Any,
        g: torch.Tensor,
        a_taken: torch.Tensor,
        mean_action: torch.Tensor,
        q_pi: torch.Tensor,
    ) -> torch.Tensor:
        """Behavioural cloning on a part's demonstration rows (``dem``), with the Q filter
        (clone where the demonstrator's action is valued higher) when it is on."""
        mask = torch.as_tensor(dem, device=self.device)
        if self.cfg.q_filter:
            with torch.no_grad():
                q_demo = (
                    self.critic({k: v[mask] for k, v in o.items()}, g[mask], a_taken[mask])
                    .min(0)
                    .values.squeeze(-1)
                )
            keep = q_demo > q_pi.detach()[mask]
        else:
            keep = torch.ones(int(mask.sum()), dtype=torch.bool, device=self.device)
        demo_loss = ((mean_action[mask] - a_taken[mask]).pow(2).sum(-1) * keep).mean()
        if rows is not None:  # the task's share of the mean over demonstration rows
            demo_loss = demo_loss * (int(dem.sum()) / u.n_demo * u.n / len(rows))
        u.demo_rows += int(dem.sum())
        u.demo_cloned += int(keep.sum())
        return demo_loss

    def _measures(self) -> bool:
        """Whether this update compares task gradients."""
        mt = self.multitask
        if mt is None:
            return False
        every = mt.conflict_every > 0 and self.updates % mt.conflict_every == 0
        return mt.pcgrad or mt.gradnorm or every

    def _parts(
        self, batch: Batch, measure: bool
    ) -> tuple[list[np.ndarray | None], np.ndarray, torch.Tensor | None]:
        """How an update splits the batch.

        Returns:
            ``(parts, coefs, weights)``: the rows of each part (``[None]``: the whole batch;
            per task when ``measure``), the coefficient of each part's loss in the objective
            (``n_i / n * w_i`` per task; ``[1]``), and the per-row weights of the whole
            batch (``None`` for equal weights).
        """
        tasks = np.asarray(batch.goal)
        if measure:
            parts: list[np.ndarray | None] = list(rows_by_task(tasks, self.problem.num_tasks))
            w = np.ones(len(parts)) if self._task_w is None else self._task_w.tolist()
            n = len(tasks)
            coefs = np.array([len(r) / n * wi for r, wi in zip(parts, w, strict=True)])
            return parts, coefs, None
        weights = None
        if self._task_w is not None:
            weights = self._task_w[torch.as_tensor(tasks.astype(np.int64), device=self.device)]
        return [None], np.ones(1), weights

    def _step(
        self, net: str, measure: bool, losses: list[torch.Tensor | None], coefs: np.ndarray
    ) -> dict[str, float]:
        """The gradient step of the ``critic`` or the ``actor``: its one loss
        back-propagated, or, when ``measure``, its per-task losses combined by
        :class:`lcrl.multitask.TaskGradients`.

        Returns:
            ``grad/{net}_cos_mean``, ``grad/{net}_cos_min`` and ``grad/{net}_conflict``
            when ``measure``; nothing otherwise.
        """
        opt = self.critic_opt if net == "critic" else self.actor_opt
        if not measure:
            (loss,) = losses
            assert loss is not None
            opt.zero_grad()
            loss.backward()
            self._add_penalty(net, opt)
            opt.step()
            return {}
        tasks = self._critic_tasks if net == "critic" else self._actor_tasks
        stats = tasks.backward(losses, coefs, self.np_rng)
        self._add_penalty(net, opt)
        opt.step()
        if net == "critic":
            self._task_norms = stats["norms"]
        return {
            f"grad/{net}_cos_mean": stats["cos_mean"],
            f"grad/{net}_cos_min": stats["cos_min"],
            f"grad/{net}_conflict": stats["conflict_fraction"],
        }

    #: The EWC penalty of sequential training (:class:`lcrl.continual.EWC`); None: off.
    ewc: Any = None

    def _add_penalty(self, net: str, opt: FlatAdam) -> None:
        """Add the EWC penalty's gradient to a network's flat gradient (when EWC is on)."""
        if self.ewc is not None:
            g = self.ewc.grad(net, opt.flat)
            if g is not None:
                opt.grad.add_(g)

    def flat_parameters(self) -> dict[str, torch.Tensor]:
        """The critic's and the actor's flat parameter vectors (what EWC anchors)."""
        return {"critic": self.critic_opt.flat, "actor": self.actor_opt.flat}

    def loss_gradients(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The gradients of the critic loss and of the actor loss on ``batch`` (flat, the
        layout of :meth:`flat_parameters`), without any step: what the Fisher information
        of EWC is estimated from. Plain SAC losses (no task split, no grounding term)."""
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        alpha = self.log_alpha.detach().exp()
        y = self.td_target(nobs, goal, rew, boot, alpha)
        out = {}
        self.critic_opt.zero_grad()
        q = self.critic(obs, goal, act).squeeze(-1)
        (0.5 * (q - y).pow(2).mean(-1).sum()).backward()
        out["critic"] = self.critic_opt.grad.clone()
        self.critic_opt.zero_grad()
        self.actor_opt.zero_grad()
        self.critic.requires_grad_(False)
        try:
            a, logp = self._policy(obs, goal)
            q_pi = self.critic.min_value(obs, goal, a).squeeze(-1)
            (alpha * logp - q_pi).mean().backward()
        finally:
            self.critic.requires_grad_(True)
        out["actor"] = self.actor_opt.grad.clone()
        self.actor_opt.zero_grad()
        return out

    def td_target(
        self,
        nobs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        rew: torch.Tensor,
        boot: torch.Tensor,
        alpha: torch.Tensor,
    ) -> torch.Tensor:
        """The soft TD target ``r + boot * (min Q_target(s', a') - alpha log pi(a'|s'))``
        with ``a'`` drawn from the policy, clipped to the return's bounds
        (:meth:`Agent.bound_targets`) and to ``sac.target_clip`` when set."""
        with torch.no_grad():
            next_a, next_logp = self._policy(nobs, goal)
            target_q = self.critic_target.min_value(nobs, goal, next_a).squeeze(-1)
            y = rew + boot * (target_q - alpha * next_logp)
            y = self.bound_targets(y)
            clip = self.cfg.target_clip
            return y if clip is None else y.clamp(-clip, clip)

    def output_gradients(self, batch: Batch) -> dict[str, torch.Tensor]:
        """Per network, the gradient whose square is the Fisher information of the
        network's output distribution at ``batch`` (one transition): for the critic, the
        gradient of its Q-values (a unit-variance Gaussian around each); for the actor,
        the score ``d log pi(u | s, g) / d theta`` of a pre-squash action ``u`` drawn from
        the policy itself. Unlike the gradient of the losses, it does not vanish where the
        losses are small, that is, on what a stage has learned well."""
        obs, _, goal, act, _, _ = self.batch_tensors(batch)
        out = {}
        self.critic_opt.zero_grad()
        self.critic(obs, goal, act).sum().backward()
        out["critic"] = self.critic_opt.grad.clone()
        self.critic_opt.zero_grad()
        self.actor_opt.zero_grad()
        mean, log_std = self.actor(obs, goal).chunk(2, -1)
        log_std = log_std.clamp(-20.0, 2.0)
        noise = torch.randn(mean.shape, generator=self.gen, device=self.device)
        # d/d(mean) log N(u) = noise / std and d/d(log std) = noise^2 - 1 at u = mean + std noise
        score = (noise / log_std.exp()).detach() * mean + (noise.pow(2) - 1.0) * log_std
        score.sum().backward()
        out["actor"] = self.actor_opt.grad.clone()
        self.actor_opt.zero_grad()
        return out

    def learned_task_weights(self) -> np.ndarray | None:
        """GradNorm's current task weights (summing to the number of tasks); None when
        task weights are not learned."""
        return None if self._gradnorm is None else self._gradnorm.weights.copy()

    def modules(self) -> dict[str, nn.Module]:
        """Actor, critics, target critics and normalisers."""
        return {
            **super().modules(),
            "actor": self.actor,
            "critic": self.critic,
            "critic_target": self.critic_target,
        }

    def states(self) -> dict[str, Any]:
        """Optimiser states, temperature, generator and counters."""
        return {
            **super().states(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "log_alpha": self.log_alpha.detach().cpu(),
            **({"gradnorm": self._gradnorm.state_dict()} if self._gradnorm is not None else {}),
        }

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        if self._gradnorm is not None and "gradnorm" in states:
            self._gradnorm.load_state_dict(states["gradnorm"])
            w = self._gradnorm.weights
            self._task_w = torch.as_tensor(w / w.mean(), dtype=torch.float32, device=self.device)
        self.actor_opt.load_state_dict(states["actor_opt"])
        self.critic_opt.load_state_dict(states["critic_opt"])
        self.alpha_opt.load_state_dict(states["alpha_opt"])
        with torch.no_grad():
            self.log_alpha.copy_(torch.as_tensor(states["log_alpha"]))


SPEC = AlgoSpec(
    name="sac",
    agent=SAC,
    config=SACConfig,
    actions="continuous",
    multitask=True,
    privileged_critic=True,
    learns_from="env",
    summary="soft actor-critic: twin critics, tuned entropy temperature; multi-task options",
)

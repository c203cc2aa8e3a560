"""Off-policy learners for goal-conditioned RL: SAC, TD3 and double DQN.

Every learner takes a :class:`Problem` (observation shapes, goal encoding, action space),
acts with :meth:`Agent.act`, and learns with ``update(batch) -> dict[str, float]`` on a
:class:`lcrl.buffer.Batch`. Targets bootstrap through time limits: only ``terminated``
transitions (goal reached, failure) stop the bootstrap, truncations do not (the buffer
never marks a truncation as terminated).

Runs are deterministic on the CPU under a seed: each agent draws its noise from its own
``torch.Generator``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from lcrl.multitask import MultiTaskOptions, TaskGradients, rows_by_task, task_weights
from lcrl.nets import (
    FlatAdam,
    GoalConditionedEnsemble,
    GoalConditionedNet,
    NetConfig,
    RunningNorm,
    WhiteningNorm,
    flatten_parameters,
    gaussian_log_prob_tanh,
    random_shift,
)

GoalEmbedder = Callable[[np.ndarray, torch.device], torch.Tensor]
#: Normalisations of text goals (:attr:`AgentOptions.text_goal_norm`).
TEXT_GOAL_NORMS = ("whiten", "standardize")


@dataclass
class Problem:
    """What a learner must know about the task.

    Attributes:
        obs_shapes: ``{key: shape}`` of the stored observation (vectors ``(d,)``, uint8
            images ``(H, W, C)``).
        goal_kind: ``vector``, ``text``, ``onehot`` or ``image`` (see :mod:`lcrl.nets`).
        goal_shape: shape of one embedded goal.
        action_dim: continuous action width (actions in ``[-1, 1]``), or the number of
            discrete actions.
        discrete: whether actions are discrete.
        num_tasks: the size of a fixed task set whose goal ids are batch goals (one-hot
            task ids, or instruction ids of a table of exactly those tasks); 0 for none.
    """

    obs_shapes: dict[str, tuple[int, ...]]
    goal_kind: str
    goal_shape: tuple[int, ...]
    action_dim: int
    discrete: bool = False
    num_tasks: int = 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return {
            "obs_shapes": {k: list(v) for k, v in self.obs_shapes.items()},
            "goal_kind": self.goal_kind,
            "goal_shape": list(self.goal_shape),
            "action_dim": self.action_dim,
            "discrete": self.discrete,
            "num_tasks": self.num_tasks,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Problem:
        """Inverse of :meth:`to_dict`."""
        return cls(
            obs_shapes={k: tuple(v) for k, v in d["obs_shapes"].items()},
            goal_kind=d["goal_kind"],
            goal_shape=tuple(d["goal_shape"]),
            action_dim=int(d["action_dim"]),
            discrete=bool(d["discrete"]),
            num_tasks=int(d.get("num_tasks", 0)),
        )


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


@dataclass
class AgentOptions:
    """Options shared by every learner."""

    net: NetConfig = field(default_factory=NetConfig)
    """Network sizes and fusion."""
    normalize_obs: bool = True
    """Normalise vector observations with running statistics."""
    normalize_goal: bool = True
    """Normalise goals: state goals with running statistics of achieved goals, text goals
    with the statistics of the training instructions' embeddings (see
    ``text_goal_norm``)."""
    text_goal_norm: str = "standardize"
    """How text goals are normalised: ``standardize`` (each dimension on its own) or
    ``whiten`` (regularised PCA whitening over the training instructions, so that the one
    word telling two instructions apart, such as left and right, is as visible as the
    rest: cosine 0.61 instead of 0.91 between those two). Whitening did not learn faster
    in the runs measured so far (see the README), so it is not the default."""
    text_whiten_eps: float = 0.01
    """Ridge of the whitening, as a fraction of the embeddings' total variance (smaller
    whitens harder)."""
    reward_shift: float = 0.0
    """Added to every reward the learner sees. -1 turns 0/1 success rewards into -1/0 ones
    (as in gymnasium-robotics): every step that does not reach the goal then costs
    something, which pins down the value of goals the policy does not reach far faster
    than discounting alone."""
    augment_pad: int = 0
    """Random-shift augmentation of image inputs in updates (DrQ): each image (observation,
    next observation, image goal) is padded by this many edge pixels and cropped back at a
    random offset. 0 turns it off; 4 is DrQ's value for 84x84 images."""
    device: str = "cpu"
    """``cpu``, ``cuda`` or ``cuda:N``."""
    seed: int = 0
    """Seed of the network initialisation and of the agent's noise."""
    multitask: MultiTaskOptions = field(default_factory=MultiTaskOptions)
    """Multi-task training over a fixed task set (``env.tasks``): PCGrad, task weights,
    gradient-conflict measurement (SAC) and how training tasks are drawn."""


def resolve_device(name: str) -> torch.device:
    """The torch device for a config string, with a clear error when it is unavailable."""
    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise LcrlError(f"unknown device {name!r}: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise LcrlError(f"device {name!r} requested but CUDA is not available on this machine")
    return device


class Agent:
    """Shared machinery: device, normalisers, tensors from batches, saving."""

    name = "agent"

    def __init__(self, problem: Problem, options: AgentOptions, goal_embed: GoalEmbedder) -> None:
        self.problem = problem
        self.options = options
        self.device = resolve_device(options.device)
        self.goal_embed = goal_embed
        torch.manual_seed(options.seed)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(options.seed)
        self.np_rng = np.random.default_rng(options.seed)
        self.norms = nn.ModuleDict()
        if options.normalize_obs:
            for key, shape in problem.obs_shapes.items():
                if len(shape) == 1:
                    self.norms[f"obs_{key}"] = RunningNorm(shape[0])
        if options.text_goal_norm not in TEXT_GOAL_NORMS:
            raise LcrlError(
                f"unknown text_goal_norm {options.text_goal_norm!r}; choose one of "
                f"{TEXT_GOAL_NORMS}"
            )
        if options.text_whiten_eps <= 0:
            raise LcrlError(f"text_whiten_eps must be positive, got {options.text_whiten_eps}")
        if options.normalize_goal and problem.goal_kind == "text":
            # Frozen sentence embeddings of instructions are close to each other (cosine
            # 0.98 between "push the red cube left" and "... right"); whitening over the
            # instruction table spreads them apart (cosine 0.61), standardising each
            # dimension much less (0.91).
            if options.text_goal_norm == "whiten":
                self.norms["goal"] = WhiteningNorm(
                    problem.goal_shape[0], eps=options.text_whiten_eps
                )
            else:
                self.norms["goal"] = RunningNorm(problem.goal_shape[0], eps=1e-3)
        elif options.normalize_goal and problem.goal_kind == "vector":
            self.norms["goal"] = RunningNorm(problem.goal_shape[0], eps=1e-2)
        self.norms.to(self.device)
        self.updates = 0
        self.acts = 0
        options.multitask.validate(problem.num_tasks)
        if options.multitask.active and self.name != "sac":
            raise LcrlError(
                f"PCGrad, task weights and gradient-conflict measurement are implemented for "
                f"SAC, not {self.name}: use --algo sac or turn the multitask options off"
            )

    # --- inputs ----------------------------------------------------------------------
    def observe(self, obs: Mapping[str, np.ndarray], goals: np.ndarray | None = None) -> None:
        """Update the running normalisers with observations and goal vectors (achieved state
        goals, or the embeddings of the training instructions)."""
        for key, arr in obs.items():
            if f"obs_{key}" in self.norms:
                self.norms[f"obs_{key}"].update(torch.as_tensor(np.asarray(arr, np.float32)))
        if goals is not None and "goal" in self.norms:
            g = np.asarray(goals)
            if g.dtype.kind in "iu":  # ids: embed them first
                t = self.goal_embed(g, self.device)
            else:
                t = torch.as_tensor(g, dtype=torch.float32)
            self.norms["goal"].update(t)

    def obs_tensors(self, obs: Mapping[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """Observation arrays as (normalised) tensors on the device."""
        out = {}
        for key, arr in obs.items():
            t = torch.as_tensor(arr, device=self.device)
            if t.dtype != torch.uint8:
                t = t.float()
                if f"obs_{key}" in self.norms:
                    t = self.norms[f"obs_{key}"](t)
            out[key] = t
        return out

    def goal_tensor(self, goal: np.ndarray | torch.Tensor, embedded: bool = False) -> torch.Tensor:
        """Goals as network input: embedded by the goal space (unless already) and normalised."""
        if embedded:
            g = torch.as_tensor(goal, device=self.device)
            g = g.float() if g.dtype != torch.uint8 else g
        else:
            g = self.goal_embed(np.asarray(goal), self.device)
        if "goal" in self.norms:
            g = self.norms["goal"](g)
        return g

    def batch_tensors(self, batch: Batch) -> tuple[Any, ...]:
        """``obs, next_obs, goal, action, reward, bootstrap`` tensors of a batch.

        ``bootstrap`` multiplies the next state's value in the target: the discount
        (``gamma``, or :attr:`Batch.discount` for multi-step rows) where the row did not
        terminate, 0 where it did.
        """
        obs = self.obs_tensors(batch.obs)
        nobs = self.obs_tensors(batch.next_obs)
        goal = self.goal_tensor(batch.goal)
        pad = self.options.augment_pad
        if pad:
            for d in (obs, nobs):
                for key, t in d.items():
                    if t.dim() == 4:
                        d[key] = random_shift(t, pad, self.gen)
            if goal.dim() == 4:
                goal = random_shift(goal, pad, self.gen)
        act = torch.as_tensor(batch.action, device=self.device)
        act = act.long() if self.problem.discrete else act.float()
        rew = torch.as_tensor(batch.reward, device=self.device, dtype=torch.float32)
        gamma = float(self.cfg.gamma)
        if batch.discount is None:
            disc = torch.full_like(rew, gamma)
        else:
            disc = torch.as_tensor(batch.discount, device=self.device, dtype=torch.float32)
        if self.options.reward_shift:
            # a shift per step: sum_j gamma**j over the row's m rewards, gamma**m = disc
            per_row = 1.0 if batch.discount is None else (1.0 - disc) / (1.0 - gamma)
            rew = rew + self.options.reward_shift * per_row
        term = torch.as_tensor(batch.terminated, device=self.device, dtype=torch.float32)
        return obs, nobs, goal, act, rew, (1.0 - term) * disc

    def _critics(self, action_dim: int, n: int = 2) -> GoalConditionedEnsemble:
        p = self.problem
        return GoalConditionedEnsemble(
            n, p.obs_shapes, p.goal_kind, p.goal_shape, 1, self.options.net, action_dim
        ).to(self.device)

    def _net(self, out_dim: int, action_dim: int = 0) -> GoalConditionedNet:
        p = self.problem
        return GoalConditionedNet(
            p.obs_shapes, p.goal_kind, p.goal_shape, out_dim, self.options.net, action_dim
        ).to(self.device)

    # --- acting ----------------------------------------------------------------------
    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Actions for a batch of observations and goals (continuous in ``[-1, 1]``)."""
        raise NotImplementedError

    # --- saving ----------------------------------------------------------------------
    def modules(self) -> dict[str, nn.Module]:
        """Weights to checkpoint, by name."""
        return {"norms": self.norms}

    def states(self) -> dict[str, Any]:
        """Optimiser moments, noise generator and counters to checkpoint."""
        return {
            "generator": self.gen.get_state(),
            "np_rng": self.np_rng.bit_generator.state,
            "counters": {"updates": self.updates, "acts": self.acts},
        }

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        self.gen.set_state(torch.as_tensor(states["generator"], dtype=torch.uint8).cpu())
        self.np_rng.bit_generator.state = states["np_rng"]
        self.updates = int(states["counters"]["updates"])
        self.acts = int(states["counters"]["acts"])


def _weighted(coefs: np.ndarray, losses: list[torch.Tensor | None]) -> float:
    """``sum_i c_i L_i`` over the tasks that have a loss."""
    return float(
        sum(c * float(x.detach()) for c, x in zip(coefs, losses, strict=True) if x is not None)
    )


def _flat_target(module: nn.Module) -> tuple[nn.Module, torch.Tensor]:
    target = copy.deepcopy(module)
    for p in target.parameters():
        p.requires_grad_(False)
    flat, _ = flatten_parameters(list(target.parameters()))
    return target, flat


class SAC(Agent):
    """Soft actor-critic with twin critics, target critics and a tuned temperature."""

    name = "sac"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: SACConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        if problem.discrete:
            raise LcrlError("SAC needs continuous actions; use DQN for discrete action spaces")
        self.cfg = cfg = config or SACConfig()
        n = problem.action_dim
        self.actor = self._net(2 * n)
        self.critic = self._critics(n)
        self.critic_target, self._target_flat = _flat_target(self.critic)
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
        if self.multitask is not None:
            self._task_w = torch.as_tensor(
                task_weights(mt.task_weights, problem.num_tasks),
                dtype=torch.float32,
                device=self.device,
            )
            self._critic_tasks = TaskGradients(self.critic_opt, pcgrad=mt.pcgrad)
            self._actor_tasks = TaskGradients(self.actor_opt, pcgrad=mt.pcgrad)

    def _policy(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor, with_mean: bool = False
    ) -> Any:
        mean, log_std = self.actor(obs, goal).chunk(2, -1)
        log_std = log_std.clamp(-20.0, 2.0)
        noise = torch.randn(mean.shape, generator=self.gen, device=self.device)
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
            else:
                a = self._policy(o, g)[0]
        self.acts += 1
        return a.cpu().numpy()

    def update(self, batch: Batch) -> dict[str, float]:
        """One critic, actor and temperature step; returns losses and diagnostics."""
        if self.multitask is not None:
            return self._update_multitask(batch)
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        cfg = self.cfg
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            next_a, next_logp = self._policy(nobs, goal)
            target_q = self.critic_target(nobs, goal, next_a).min(0).values.squeeze(-1)
            y = rew + boot * (target_q - alpha * next_logp)
        q = self.critic(obs, goal, act).squeeze(-1)
        critic_loss = 0.5 * (q - y).pow(2).mean(-1).sum()
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()

        self.critic.requires_grad_(False)
        a, logp, mean_action = self._policy(obs, goal, with_mean=True)
        q_pi = self.critic(obs, goal, a).min(0).values.squeeze(-1)
        actor_loss = (alpha * logp - q_pi).mean()
        bc_loss = None
        if cfg.hindsight_bc > 0.0 and batch.relabelled.any():
            rel = torch.as_tensor(batch.relabelled, device=self.device)
            bc_loss = (mean_action[rel] - act[rel]).pow(2).sum(-1).mean()
            actor_loss = actor_loss + cfg.hindsight_bc * bc_loss
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        self.critic.requires_grad_(True)

        if cfg.autotune_alpha:
            alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self.alpha_opt.zero_grad()
            alpha_loss.backward()
            self.alpha_opt.step()
        with torch.no_grad():
            self._target_flat.lerp_(self.critic_opt.flat, cfg.tau)
        self.updates += 1
        metrics = {
            "critic_loss": critic_loss.item(),
            "actor_loss": actor_loss.item(),
            "alpha": float(alpha),
            "q": q.detach().mean().item(),
            "entropy": -logp.detach().mean().item(),
        }
        if bc_loss is not None:
            metrics["bc_loss"] = bc_loss.item()
        return metrics

    def _update_multitask(self, batch: Batch) -> dict[str, float]:
        """The update of :meth:`update` for the multi-task objective ``sum_i w_i L_i``.

        A batch row's task is its goal id. Rows of task ``i`` weigh ``w_i / mean(w)`` in the
        critic and actor losses (the usual losses for equal weights). On updates that
        measure gradient conflict (every update with PCGrad, every ``conflict_every``-th
        otherwise) each task's rows go through the networks on their own, the per-task
        gradients of the critic and the actor are compared (``grad/*`` metrics) and, with
        PCGrad, projected before their weighted sum is applied. The temperature is tuned
        on the whole batch as usual.
        """
        mt = self.multitask
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        cfg = self.cfg
        alpha = self.log_alpha.detach().exp()
        tasks = np.asarray(batch.goal, np.int64)
        groups = rows_by_task(tasks, self.problem.num_tasks)
        w = self._task_w[torch.as_tensor(tasks, device=self.device)]
        n = len(tasks)
        with torch.no_grad():
            next_a, next_logp = self._policy(nobs, goal)
            target_q = self.critic_target(nobs, goal, next_a).min(0).values.squeeze(-1)
            y = rew + boot * (target_q - alpha * next_logp)
        rel = torch.as_tensor(batch.relabelled, device=self.device)
        use_bc = cfg.hindsight_bc > 0.0 and bool(batch.relabelled.any())
        measure = mt.pcgrad or (mt.conflict_every > 0 and self.updates % mt.conflict_every == 0)
        metrics: dict[str, float] = {}

        def sub(d: Mapping[str, torch.Tensor], rows: torch.Tensor) -> dict[str, torch.Tensor]:
            return {k: v[rows] for k, v in d.items()}

        def actor_rows(o: Any, g: torch.Tensor, a_taken: torch.Tensor, rows: Any) -> Any:
            a, logp, mean_action = self._policy(o, g, with_mean=True)
            q_pi = self.critic(o, g, a).min(0).values.squeeze(-1)
            per_row = alpha * logp - q_pi
            if use_bc:
                bc = (mean_action - a_taken).pow(2).sum(-1)
                per_row = per_row + cfg.hindsight_bc * rel[rows] * bc * (n / int(rel.sum()))
            return per_row, logp

        if not measure:
            q = self.critic(obs, goal, act).squeeze(-1)
            critic_loss = (0.5 * (q - y).pow(2).sum(0) * w).mean()
            self.critic_opt.zero_grad()
            critic_loss.backward()
            self.critic_opt.step()
            self.critic.requires_grad_(False)
            per_row, logp = actor_rows(obs, goal, act, slice(None))
            actor_loss = (per_row * w).mean()
            self.actor_opt.zero_grad()
            actor_loss.backward()
            self.actor_opt.step()
            self.critic.requires_grad_(True)
            q_mean, actor_value = q.detach().mean().item(), actor_loss.item()
            critic_value = critic_loss.item()
        else:
            idx = [torch.as_tensor(r, device=self.device) for r in groups]
            coefs = np.array(
                [len(r) / n * float(self._task_w[i]) for i, r in enumerate(groups)], np.float64
            )
            losses: list[torch.Tensor | None] = []
            q_sum = 0.0
            for rows in idx:
                if rows.numel() == 0:
                    losses.append(None)
                    continue
                q = self.critic(sub(obs, rows), goal[rows], act[rows]).squeeze(-1)
                losses.append((0.5 * (q - y[rows]).pow(2).sum(0)).mean())
                q_sum += float(q.detach().sum())
            stats = self._critic_tasks.step(losses, coefs, self.np_rng)
            critic_value = _weighted(coefs, losses)
            metrics.update({f"grad/critic_{k}": stats[k] for k in ("cos_mean", "cos_min")})
            metrics["grad/critic_conflict"] = stats["conflict_fraction"]
            self.critic.requires_grad_(False)
            losses, logps = [], []
            for rows in idx:
                if rows.numel() == 0:
                    losses.append(None)
                    continue
                per_row, logp_i = actor_rows(sub(obs, rows), goal[rows], act[rows], rows)
                losses.append(per_row.mean())
                logps.append(logp_i)
            stats = self._actor_tasks.step(losses, coefs, self.np_rng)
            self.critic.requires_grad_(True)
            logp = torch.cat(logps)
            actor_value = _weighted(coefs, losses)
            metrics.update({f"grad/actor_{k}": stats[k] for k in ("cos_mean", "cos_min")})
            metrics["grad/actor_conflict"] = stats["conflict_fraction"]
            q_mean = q_sum / (n * self.critic.n)

        if cfg.autotune_alpha:
            alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self.alpha_opt.zero_grad()
            alpha_loss.backward()
            self.alpha_opt.step()
        with torch.no_grad():
            self._target_flat.lerp_(self.critic_opt.flat, cfg.tau)
        self.updates += 1
        return {
            "critic_loss": critic_value,
            "actor_loss": actor_value,
            "alpha": float(alpha),
            "q": q_mean,
            "entropy": -logp.detach().mean().item(),
            **metrics,
        }

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
        }

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        super().load_states(states)
        self.actor_opt.load_state_dict(states["actor_opt"])
        self.critic_opt.load_state_dict(states["critic_opt"])
        self.alpha_opt.load_state_dict(states["alpha_opt"])
        with torch.no_grad():
            self.log_alpha.copy_(torch.as_tensor(states["log_alpha"]))


class TD3(Agent):
    """Twin delayed deep deterministic policy gradient."""

    name = "td3"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: TD3Config | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        if problem.discrete:
            raise LcrlError("TD3 needs continuous actions; use DQN for discrete action spaces")
        self.cfg = cfg = config or TD3Config()
        n = problem.action_dim
        self.actor = self._net(n)
        self.critic = self._critics(n)
        self.actor_target, self._actor_target_flat = _flat_target(self.actor)
        self.critic_target, self._critic_target_flat = _flat_target(self.critic)
        self.actor_opt = FlatAdam(
            self.actor.parameters(), cfg.actor_lr, max_grad_norm=cfg.max_grad_norm
        )
        self.critic_opt = FlatAdam(
            self.critic.parameters(), cfg.critic_lr, max_grad_norm=cfg.max_grad_norm
        )
        self._last_actor_loss = 0.0

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Deterministic actions, plus clipped Gaussian exploration noise when not
        ``deterministic``."""
        with torch.inference_mode():
            a = torch.tanh(self.actor(self.obs_tensors(obs), self.goal_tensor(goal, embedded)))
            if not deterministic:
                noise = torch.randn(a.shape, generator=self.gen, device=self.device)
                a = (a + self.cfg.exploration_noise * noise).clamp(-1.0, 1.0)
        self.acts += 1
        return a.cpu().numpy()

    def update(self, batch: Batch) -> dict[str, float]:
        """One critic step, and an actor and target step every ``policy_delay`` calls."""
        obs, nobs, goal, act, rew, boot = self.batch_tensors(batch)
        cfg = self.cfg
        with torch.no_grad():
            noise = torch.randn(act.shape, generator=self.gen, device=self.device)
            noise = (cfg.policy_noise * noise).clamp(-cfg.noise_clip, cfg.noise_clip)
            next_a = (torch.tanh(self.actor_target(nobs, goal)) + noise).clamp(-1.0, 1.0)
            target_q = self.critic_target(nobs, goal, next_a).min(0).values.squeeze(-1)
            y = rew + boot * target_q
        q = self.critic(obs, goal, act).squeeze(-1)
        critic_loss = 0.5 * (q - y).pow(2).mean(-1).sum()
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        if self.updates % cfg.policy_delay == 0:
            self.critic.requires_grad_(False)
            q_pi = self.critic(obs, goal, torch.tanh(self.actor(obs, goal)))[0]
            actor_loss = -q_pi.mean()
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


class DQN(Agent):
    """Double DQN with a Polyak-averaged target network and epsilon-greedy exploration."""

    name = "dqn"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: GoalEmbedder,
        config: DQNConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        if not problem.discrete:
            raise LcrlError("DQN needs a discrete action space; use SAC or TD3 for continuous")
        self.cfg = cfg = config or DQNConfig()
        self.q = self._net(problem.action_dim)
        self.q_target, self._target_flat = _flat_target(self.q)
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
            y = rew + boot * target_q
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


ALGOS: dict[str, type[Agent]] = {"sac": SAC, "td3": TD3, "dqn": DQN}

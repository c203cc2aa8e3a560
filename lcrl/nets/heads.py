"""Goal-conditioned networks: the fused MLP, per-task output heads, one network and an
ensemble of critics evaluated in one batched pass."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from lcrl.errors import LcrlError
from lcrl.nets.encoders import build_encoders, goal_encoder_spec
from lcrl.nets.fused import EnsembleMin, EnsembleMLP
from lcrl.nets.layers import FUSIONS, BatchedLinear, NetConfig, mlp


class TaskHeads(nn.Module):
    """One linear layer per task; row ``b`` of the input goes through head ``task[b]``.

    Each head is initialised like :class:`torch.nn.Linear`. With ``members`` > 0 the heads
    belong to an ensemble: inputs ``(members, B, in)`` (or ``(B, in)``, shared), outputs
    ``(members, B, out)``.

    Args:
        num_tasks: heads.
        in_dim: input width (the trunk's last hidden layer).
        out_dim: output width.
        members: ensemble members (0: a single network).
    """

    def __init__(self, num_tasks: int, in_dim: int, out_dim: int, members: int = 0) -> None:
        super().__init__()
        self.members = members
        lead = (members,) if members else ()
        self.weight = nn.Parameter(torch.empty(*lead, num_tasks, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(*lead, num_tasks, out_dim))
        bound = 1.0 / math.sqrt(in_dim)
        with torch.no_grad():
            w = self.weight.view(-1, in_dim, out_dim)
            for i in range(w.shape[0]):
                layer = torch.empty(out_dim, in_dim)
                nn.init.kaiming_uniform_(layer, a=math.sqrt(5))
                w[i].copy_(layer.T)
            self.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
        rows = torch.arange(task.shape[0], device=task.device)
        if not self.members:
            out = torch.einsum("bi,kio->bko", x, self.weight) + self.bias
            return out[rows, task]
        if x.dim() == 2:
            x = x.expand(self.members, *x.shape)
        out = torch.einsum("nbi,nkio->nbko", x, self.weight) + self.bias[:, None]
        return out[:, rows, task]


def check_task_heads(cfg: NetConfig, goal_kind: str, goal_shape: Sequence[int]) -> int:
    """The number of per-task heads of a network (0 for none).

    Raises:
        LcrlError: heads asked for with goals that are not one-hot task ids, or a number of
            heads other than the number of tasks.
    """
    heads = int(cfg.task_heads)
    if heads < 0:
        raise LcrlError(f"net.task_heads must be >= 0, got {heads}")
    if not heads:
        return 0
    if not goal_encoder_spec(goal_kind).task_ids:
        raise LcrlError(
            f"net.task_heads picks a head by one-hot task id, but this network's goals are "
            f"{goal_kind!r}: use --env.goal-type task, or set net.task_heads=0"
        )
    if heads != int(goal_shape[0]):
        raise LcrlError(
            f"net.task_heads is {heads} but there are {goal_shape[0]} tasks: set "
            f"--agent.net.task-heads {goal_shape[0]}"
        )
    return heads


class FusedMLP(nn.Module):
    """MLP over (features, goal features [, extra input]) with concat or FiLM fusion.

    ``concat``: ``MLP([x, g, extra])``. ``film``: ``h_l = relu(W_l h_{l-1}) * (1 + gamma_l(g))
    + beta_l(g)`` for every hidden layer, the first reading ``[x, extra]``. With
    ``task_heads`` the output layer is a :class:`TaskHeads` picked by ``task``.
    """

    def __init__(
        self,
        in_dim: int,
        goal_dim: int,
        out_dim: int,
        hidden: Sequence[int],
        fusion: str,
        task_heads: int = 0,
    ) -> None:
        super().__init__()
        if fusion not in FUSIONS:
            raise LcrlError(f"unknown fusion {fusion!r}; choose one of {FUSIONS}")
        if not hidden:
            raise LcrlError("the fused MLP needs at least one hidden layer")
        self.fusion = fusion
        self.task_heads = task_heads
        if fusion == "concat" and task_heads:
            self.net = mlp([in_dim + goal_dim, *hidden], out_act=True)
            self.heads = TaskHeads(task_heads, hidden[-1], out_dim)
        elif fusion == "concat":
            self.net = mlp([in_dim + goal_dim, *hidden, out_dim])
        else:
            sizes = [in_dim, *hidden]
            self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(sizes))
            self.film = nn.Linear(goal_dim, 2 * sum(hidden))
            nn.init.zeros_(self.film.weight)
            nn.init.zeros_(self.film.bias)
            self.out: nn.Module = (
                TaskHeads(task_heads, hidden[-1], out_dim)
                if task_heads
                else nn.Linear(hidden[-1], out_dim)
            )
            self.hidden = tuple(hidden)

    def forward(
        self, x: torch.Tensor, g: torch.Tensor, task: torch.Tensor | None = None
    ) -> torch.Tensor:
        if self.fusion == "concat":
            h = self.net(torch.cat([x, g], -1))
            return self.heads(h, task) if self.task_heads else h
        params = self.film(g).split([h for h in self.hidden for _ in range(2)], -1)
        h = x
        for i, layer in enumerate(self.layers):
            h = F.relu(layer(h)) * (1 + params[2 * i]) + params[2 * i + 1]
        return self.out(h, task) if self.task_heads else self.out(h)


class GoalConditionedNet(nn.Module):
    """Observation encoder + goal encoder + fused MLP: ``f(obs, goal[, action])``.

    Args:
        obs_shapes: ``{key: shape}`` of the observation.
        goal_kind: goal encoder kind (see :class:`GoalEncoder`).
        goal_shape: shape of one embedded goal.
        out_dim: output width.
        cfg: network config.
        action_dim: width of an action input (critics), 0 for none.
    """

    def __init__(
        self,
        obs_shapes: Mapping[str, Sequence[int]],
        goal_kind: str,
        goal_shape: Sequence[int],
        out_dim: int,
        cfg: NetConfig,
        action_dim: int = 0,
    ) -> None:
        super().__init__()
        obs_encoder, goal_encoder = build_encoders(obs_shapes, goal_kind, goal_shape, cfg)
        self.goal_encoder = goal_encoder  # registered first: parameter order as before
        self.obs_encoder = obs_encoder
        self.task_heads = check_task_heads(cfg, goal_kind, goal_shape)
        self.head = FusedMLP(
            self.obs_encoder.out_dim + action_dim,
            self.goal_encoder.out_dim,
            out_dim,
            cfg.hidden,
            cfg.fusion,
            self.task_heads,
        )

    def forward(
        self,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        g = self.goal_encoder(goal)
        x = self.obs_encoder(obs, g)
        if action is not None:
            x = torch.cat([x, action], -1)
        # float32 out, also where the update runs under bf16 autocast (agent precision)
        if self.task_heads:
            return self.head(x, g, goal.argmax(-1)).float()
        return self.head(x, g).float()

    def selection_logits(self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Logits of the object slots the goal picks, ``(1, B, heads, count)``."""
        return self.obs_encoder.selection_logits(obs, self.goal_encoder(goal)).unsqueeze(0).float()


class GoalConditionedEnsemble(nn.Module):
    """``n`` independent :class:`GoalConditionedNet` s evaluated together: ``(n, B, out)``.

    With concatenation fusion the members' MLPs run as batched matrix products (one call
    per layer for all members), and members whose encoders have no parameters (vector
    inputs) share the encoding work; FiLM heads and learned encoders run per member.

    Args:
        n: number of members (2 for twin critics).
        obs_shapes, goal_kind, goal_shape, out_dim, cfg, action_dim: as for
            :class:`GoalConditionedNet`.
    """

    def __init__(
        self,
        n: int,
        obs_shapes: Mapping[str, Sequence[int]],
        goal_kind: str,
        goal_shape: Sequence[int],
        out_dim: int,
        cfg: NetConfig,
        action_dim: int = 0,
    ) -> None:
        super().__init__()
        self.n = n
        pairs = [build_encoders(obs_shapes, goal_kind, goal_shape, cfg) for _ in range(n)]
        self.goal_encoders = nn.ModuleList(goal for _, goal in pairs)
        self.obs_encoders = nn.ModuleList(obs for obs, _ in pairs)
        self.shared = not any(
            p.numel()
            for enc in (self.obs_encoders[0], self.goal_encoders[0])
            for p in enc.parameters()
        )
        in_dim = self.obs_encoders[0].out_dim + action_dim
        goal_dim = self.goal_encoders[0].out_dim
        self.batched = cfg.fusion == "concat"
        self.task_heads = check_task_heads(cfg, goal_kind, goal_shape)
        if self.batched:
            sizes = [in_dim + goal_dim, *cfg.hidden, out_dim]
            if self.task_heads:
                sizes = sizes[:-1]
            self.layers = nn.ModuleList(
                BatchedLinear(n, a, b) for a, b in itertools.pairwise(sizes)
            )
            if self.task_heads:
                self.out_heads = TaskHeads(self.task_heads, cfg.hidden[-1], out_dim, members=n)
        else:
            self.heads = nn.ModuleList(
                FusedMLP(in_dim, goal_dim, out_dim, cfg.hidden, cfg.fusion, self.task_heads)
                for _ in range(n)
            )

    def _features(
        self,
        i: int,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.goal_encoders[i](goal)
        x = self.obs_encoders[i](obs, g)
        if action is not None:
            x = torch.cat([x, action], -1)
        return x, g

    def _inputs(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor, action: torch.Tensor | None
    ) -> torch.Tensor:
        """The batched layers' input: ``(B, in)`` shared by the members, else ``(n, B, in)``."""
        if self.shared:
            return torch.cat(self._features(0, obs, goal, action), -1)
        return torch.stack(
            [torch.cat(self._features(i, obs, goal, action), -1) for i in range(self.n)]
        )

    def _params(self) -> list[torch.Tensor]:
        return [p for layer in self.layers for p in (layer.weight, layer.bias)]

    def _fusable(self, h: torch.Tensor) -> bool:
        """Whether the batched layers run as one :mod:`lcrl.nets.fused` function: float32
        outside autocast and compilation, without task heads."""
        return (
            not self.task_heads
            and h.dtype == torch.float32
            and self.layers[0].weight.dtype == torch.float32
            and not torch.is_autocast_enabled(h.device.type)
            and not torch.compiler.is_compiling()
        )

    def min_value(
        self,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``min_k Q_k`` per row, ``(B, out)``. With frozen parameters (an actor's loss)
        and one output its backward pass runs each row through the smallest member only
        (:class:`lcrl.nets.fused.EnsembleMin`); the same gradient as ``self(...).min(0)``."""
        if not self.batched:
            return self(obs, goal, action).min(0).values
        h = self._inputs(obs, goal, action)
        params = self._params()
        one_output = params[-2].shape[2] == 1
        if self._fusable(h) and one_output and not any(p.requires_grad for p in params):
            return EnsembleMin.apply(h, *params)
        return self._batched(h, goal).min(0).values

    def selection_logits(self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each member's logits of the object slots the goal picks, ``(n, B, heads,
        count)``."""
        return torch.stack(
            [
                enc.selection_logits(obs, goal_enc(goal))
                for enc, goal_enc in zip(self.obs_encoders, self.goal_encoders, strict=True)
            ]
        ).float()

    def forward(
        self,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if not self.batched:
            task = goal.argmax(-1) if self.task_heads else None
            outs = []
            for i in range(self.n):
                x, g = self._features(i, obs, goal, action)
                outs.append(self.heads[i](x, g, task))
            return torch.stack(outs).float()
        return self._batched(self._inputs(obs, goal, action), goal)

    def _batched(self, h: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """The batched layers (and task heads) on their input ``h``: ``(n, B, out)``."""
        if self._fusable(h):
            return EnsembleMLP.apply(h, *self._params())
        last = len(self.layers) - (0 if self.task_heads else 1)
        for k, layer in enumerate(self.layers):
            h = layer(h)
            if k < last:
                h = F.relu(h)
        if self.task_heads:
            return self.out_heads(h, goal.argmax(-1)).float()
        return h.float()

"""Reading object slots by the goal: attention, selection by position or by attributes, and
the grounding loss."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from lcrl.errors import LcrlError
from lcrl.nets.layers import NetConfig, mlp


class _SlotReader(nn.Module):
    """Shared part of the slot readers: the ``(start, count, width)`` layout and the
    slots of every key side by side, ``(B, count, keys * width)``."""

    def __init__(self, layout: Sequence[int]) -> None:
        super().__init__()
        start, count, width = (int(v) for v in layout)
        self.start, self.count, self.width = start, count, width
        self.end = start + count * width

    def _slots(self, xs: Sequence[torch.Tensor]) -> torch.Tensor:
        b = xs[0].shape[0]
        return torch.cat(
            [x[:, self.start : self.end].reshape(b, self.count, self.width) for x in xs], -1
        )


class SlotAttention(_SlotReader):
    """Goal-conditioned attention over object slots of vector observations.

    Every key's vector is ``[global (start values), count slots of width values,
    rest]``. Slot ``i`` is encoded by a shared MLP from its values in every key, the
    global and rest values, and a learned embedding of ``i`` (which object kind the slot
    holds); each head's query comes from the goal features. Output: the attended slot
    features of every head, then the global and rest values.

    Args:
        dims: vector width of each key (all keys share the slot layout).
        layout: ``(start, count, width)``.
        goal_dim: width of the goal features.
        cfg: network config (``slot_dim``, ``slot_heads``).
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(layout)
        count, width = self.count, self.width
        self.extra = sum(d - count * width for d in dims)  # global + rest values, all keys
        d, heads = cfg.slot_dim, cfg.slot_heads
        self.identity = nn.Parameter(torch.randn(count, d) * 0.1)
        self.slot_mlp = mlp([len(dims) * width + self.extra + d, d, d], out_act=True)
        self.query = nn.Linear(goal_dim, heads * d)
        self.key = nn.Linear(d, heads * d)
        self.heads, self.d = heads, d
        self.out_dim = heads * d + self.extra

    def _encode(self, xs: Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-slot features ``(B, count, d)`` and the global and rest values."""
        b = xs[0].shape[0]
        slots = self._slots(xs)
        extra = torch.cat([torch.cat([x[:, : self.start], x[:, self.end :]], -1) for x in xs], -1)
        per_slot = torch.cat(
            [
                slots,
                extra.unsqueeze(1).expand(b, self.count, self.extra),
                self.identity.expand(b, -1, -1),
            ],
            -1,
        )
        return self.slot_mlp(per_slot), extra

    def _scores(self, h: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        b = h.shape[0]
        q = self.query(goal).view(b, self.heads, 1, self.d)
        k = self.key(h).view(b, self.count, self.heads, self.d).transpose(1, 2)
        return (q * k).sum(-1) / math.sqrt(self.d)  # (B, heads, count)

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each head's attention logits over the slots, ``(B, heads, count)``."""
        return self._scores(self._encode(xs)[0], goal)

    def forward(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = xs[0].shape[0]
        h, extra = self._encode(xs)
        w = torch.softmax(self._scores(h, goal), -1)  # (B, heads, count)
        picked = torch.einsum("bhc,bcd->bhd", w, h).reshape(b, self.heads * self.d)
        return torch.cat([picked, extra], -1)


class SlotSelect(_SlotReader):
    """Goal-conditioned selection of object slots by position.

    Every key's vector is ``[global (start values), count slots of width values,
    rest]``, and slot ``i`` always holds the same object kind. Each head turns the goal
    features into softmax weights over the ``count`` slot positions and picks the
    weighted sum of the slots' raw values (from every key); the output is the picked
    values of every head followed by every key's full vector, so that nothing is lost.

    Args:
        dims: vector width of each key (all keys share the slot layout).
        layout: ``(start, count, width)``.
        goal_dim: width of the goal features.
        cfg: network config (``slot_heads``).
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(layout)
        self.heads = cfg.slot_heads
        self.logits = nn.Linear(goal_dim, self.heads * self.count)
        self.out_dim = self.heads * len(dims) * self.width + sum(dims)

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each head's logits over the slot positions, ``(B, heads, count)``."""
        return self.logits(goal).view(goal.shape[0], self.heads, self.count)

    def forward(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = xs[0].shape[0]
        slots = self._slots(xs)
        w = torch.softmax(self.selection_logits(xs, goal), -1)
        picked = torch.bmm(w, slots).reshape(b, -1)  # (B, heads * keys * width)
        return torch.cat([picked, *xs], -1)


def grounding_loss(logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of slot selection against the slots an instruction names.

    Args:
        logits: ``(n, B, heads, count)`` selection logits of ``n`` networks.
        targets: ``(B, T)`` slot index named for head ``t`` (the object acted on, then
            the reference object of two-object families), -1 where none is.

    Returns:
        The mean over networks of the summed per-head cross-entropies (each averaged over
        its rows with a target); 0 where no row has one.
    """
    n, b, heads, count = logits.shape
    total = logits.new_zeros(())
    for t in range(min(heads, targets.shape[1])):
        y = targets[:, t]
        if not bool((y >= 0).any()):
            continue
        flat = logits[:, :, t].reshape(n * b, count)
        total = total + F.cross_entropy(flat, y.repeat(n), ignore_index=-1)
    return total


class SlotAttributes(SlotSelect):
    """:class:`SlotSelect` whose logits go through the slots' attributes: per head and
    attribute the goal features score every value of the attribute, and a slot's logit
    is the sum of the scores of its values (``cfg.slot_attributes``).

    Raises:
        LcrlError: ``slot_attributes`` is not ``count`` non-negative values per attribute.
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(dims, layout, goal_dim, cfg)
        del self.logits
        values = [int(v) for v in cfg.slot_attributes]
        if not values or len(values) % self.count or min(values) < 0:
            raise LcrlError(
                f"slot_mode attributes needs slot_attributes: {self.count} values (one per "
                f"slot) for each attribute, got {tuple(values)}"
            )
        table = torch.tensor(values).view(-1, self.count)  # (attributes, count)
        self.scores = nn.ModuleList()
        for a, row in enumerate(table):
            onehot = F.one_hot(row, int(row.max()) + 1).float()  # (count, values)
            self.register_buffer(f"onehot{a}", onehot, persistent=False)
            self.scores.append(nn.Linear(goal_dim, self.heads * onehot.shape[1]))

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = goal.shape[0]
        out = goal.new_zeros(b, self.heads, self.count)
        for a, score in enumerate(self.scores):
            onehot = getattr(self, f"onehot{a}")
            out = out + score(goal).view(b, self.heads, -1) @ onehot.T
        return out

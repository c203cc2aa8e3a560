"""Continual learning: the elastic weight consolidation penalty (Kirkpatrick et al. 2017).

After a stage, :meth:`EWC.consolidate` records where each network's weights ended
(``theta*``) and their diagonal Fisher information ``F`` (the mean squared gradient of the
loss on that stage's data, summed over stages). The penalty
``weight / 2 * sum_j F_j (theta_j - theta*_j)^2`` then pulls the weights back along the
directions that mattered for earlier stages; its gradient is added to the network's flat
gradient before each optimiser step (:meth:`EWC.grad`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch


class EWC:
    """The EWC penalty over the flat parameter vectors of named networks.

    Args:
        weight: ``lambda``, the penalty's weight.
    """

    def __init__(self, weight: float) -> None:
        self.weight = float(weight)
        self.fisher: dict[str, torch.Tensor] = {}
        self.anchor: dict[str, torch.Tensor] = {}

    def consolidate(self, name: str, params: torch.Tensor, fisher: torch.Tensor) -> None:
        """End of a stage for network ``name``: anchor at ``params`` and add ``fisher``."""
        params, fisher = params.detach().clone(), fisher.detach().clone()
        if name in self.fisher:
            fisher = fisher + self.fisher[name]
        self.fisher[name], self.anchor[name] = fisher, params

    def penalty(self, name: str, params: torch.Tensor) -> torch.Tensor:
        """``weight / 2 * sum F (params - anchor)^2`` (0 before any stage ended)."""
        if name not in self.anchor:
            return params.new_zeros(())
        diff = params - self.anchor[name]
        return 0.5 * self.weight * (self.fisher[name] * diff * diff).sum()

    def grad(self, name: str, params: torch.Tensor) -> torch.Tensor | None:
        """The penalty's gradient ``weight * F (params - anchor)`` (None before any stage
        ended)."""
        if name not in self.anchor:
            return None
        return self.weight * self.fisher[name] * (params.detach() - self.anchor[name])

    def state_dict(self) -> dict[str, Any]:
        """Fisher and anchors as tensors, by network."""
        return {
            **{f"fisher/{k}": v for k, v in self.fisher.items()},
            **{f"anchor/{k}": v for k, v in self.anchor.items()},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        tables: dict[str, dict[str, torch.Tensor]] = {"fisher": {}, "anchor": {}}
        for key, value in state.items():
            kind, _, name = key.partition("/")
            tables[kind][name] = torch.as_tensor(value)
        self.fisher, self.anchor = tables["fisher"], tables["anchor"]

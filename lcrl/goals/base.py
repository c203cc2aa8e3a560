"""What every goal space shares: the relabelling strategies, the reward function's signature,
the :class:`GoalSpace` interface and the pick of a relabelling step."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np
import torch

from lcrl.errors import LcrlError

STRATEGIES = ("future", "final", "episode")


RewardFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class GoalSpace(Protocol):
    """What the replay buffer needs from a goal space (see the module docstring)."""

    kind: str
    terminate_on_success: bool
    #: The lowest and highest reward of one transition (``None``: unknown).
    reward_range: tuple[float, float] | None

    def allocate(self, capacity: int) -> None: ...

    def nbytes(self, capacity: int) -> int: ...

    def write(self, start: int, episode: Mapping[str, Any]) -> None: ...

    def desired(self, idx: np.ndarray) -> np.ndarray: ...

    def relabel(
        self,
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def relabelable(
        self, idx: np.ndarray, ep_start: np.ndarray, ep_end: np.ndarray, strategy: str
    ) -> np.ndarray: ...

    def random_goals(self, slots: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...

    def reward(self, idx: np.ndarray, goals: np.ndarray) -> np.ndarray: ...

    def embed(self, goals: np.ndarray, device: torch.device | str) -> torch.Tensor: ...

    def arrays(self) -> dict[str, np.ndarray]: ...

    def load_arrays(self, arrays: Mapping[str, np.ndarray]) -> None: ...


def pick_step(
    first: np.ndarray, last: np.ndarray, strategy: str, rng: np.random.Generator
) -> np.ndarray:
    """Pick one index per row in ``[first, last]`` (inclusive) for a relabelling strategy.

    ``future`` picks uniformly in ``[first, last]``, ``final`` picks ``last`` and
    ``episode`` is the caller's business (it passes the episode's own first index).
    """
    if strategy == "final":
        return last.copy()
    return first + (rng.random(first.shape) * (last - first + 1)).astype(np.int64)


def _check_strategy(strategy: str) -> None:
    if strategy not in STRATEGIES:
        raise LcrlError(f"unknown relabelling strategy {strategy!r}; choose one of {STRATEGIES}")

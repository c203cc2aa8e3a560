"""Goal vectors (:class:`StateGoals`): achieved goals relabelled, rewards by the env's own
``compute_reward``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from lcrl.errors import LcrlError
from lcrl.goals.base import RewardFn, _check_strategy, pick_step


class StateGoals:
    """Vector goals with a vectorised reward function (classic HER).

    The episode passed to :meth:`write` needs ``achieved_goal`` of shape ``(T + 1, d)``
    (what each observation achieved) and ``desired_goal`` of shape ``(d,)`` or
    ``(T + 1, d)``.

    Args:
        dim: goal dimension.
        reward_fn: ``reward_fn(achieved (B, d), desired (B, d)) -> (B,)`` rewards; e.g.
            ``lambda a, d: env.unwrapped.compute_reward(a, d, None)``.
        success_reward: the reward value that means "goal reached" (0.0 for
            gymnasium-robotics' -1/0 rewards, 1.0 for 0/1 rewards); used for
            termination when ``terminate_on_success``.
        terminate_on_success: whether reaching the goal ends the episode (a terminal
            transition, no bootstrap). Goal envs that run to a time limit use ``False``.
        reward_range: the lowest and highest reward ``reward_fn`` gives (the bounds of
            the critic's targets); ``None``: unknown.
    """

    kind = "state"

    def __init__(
        self,
        dim: int,
        reward_fn: RewardFn,
        success_reward: float = 1.0,
        terminate_on_success: bool = False,
        reward_range: tuple[float, float] | None = None,
    ) -> None:
        self.dim = int(dim)
        self.reward_fn = reward_fn
        self.success_reward = float(success_reward)
        self.terminate_on_success = terminate_on_success
        self.reward_range = reward_range
        self._achieved = np.zeros((0, self.dim), np.float32)
        self._desired = np.zeros((0, self.dim), np.float32)

    def allocate(self, capacity: int) -> None:
        """Preallocate ``capacity`` slots."""
        self._achieved = np.zeros((capacity, self.dim), np.float32)
        self._desired = np.zeros((capacity, self.dim), np.float32)

    def nbytes(self, capacity: int) -> int:
        """The bytes :meth:`allocate` takes for ``capacity`` slots."""
        return 2 * capacity * self.dim * 4

    def write(self, start: int, episode: Mapping[str, Any]) -> None:
        """Store an episode's achieved and desired goals at ``start .. start + T``."""
        achieved = np.asarray(episode["achieved_goal"], np.float32)
        n = len(episode["action"]) + 1
        if achieved.shape != (n, self.dim):
            raise LcrlError(
                f"achieved_goal has shape {achieved.shape}; expected (T + 1, {self.dim}) = "
                f"{(n, self.dim)}"
            )
        desired = np.asarray(episode["desired_goal"], np.float32)
        if desired.shape not in ((self.dim,), (n, self.dim)):
            raise LcrlError(
                f"desired_goal has shape {desired.shape}; expected ({self.dim},) or "
                f"({n}, {self.dim})"
            )
        self._achieved[start : start + n] = achieved
        self._desired[start : start + n] = desired

    def desired(self, idx: np.ndarray) -> np.ndarray:
        """Desired goals of the transitions at ``idx``."""
        return self._desired[idx]

    def relabel(
        self,
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Goals achieved by the same episode: the achieved goal after a chosen step.

        ``future`` takes the next observation of a step ``t' >= t`` (uniform), ``final``
        the episode's last observation, ``episode`` the next observation of any step.
        """
        slots = self._achieved_slots(idx, ep_start, ep_end, strategy, rng)
        return self._achieved[slots], np.ones(idx.shape, bool)

    @staticmethod
    def _achieved_slots(
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Observation slots whose achieved goals relabel the transitions at ``idx``."""
        _check_strategy(strategy)
        last = ep_end - 1  # last transition slot
        first = ep_start if strategy == "episode" else idx
        return pick_step(first, last, strategy, rng) + 1

    def relabelable(
        self, idx: np.ndarray, ep_start: np.ndarray, ep_end: np.ndarray, strategy: str
    ) -> np.ndarray:
        """Every transition has an achieved goal after it."""
        return np.ones(idx.shape, bool)

    def random_goals(self, slots: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The goals achieved after the transitions at ``slots``."""
        return self._achieved[slots + 1]

    def reward(self, idx: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """``reward_fn`` of the achieved goal after each transition and ``goals``."""
        return np.asarray(self.reward_fn(self._achieved[idx + 1], goals), np.float32)

    def success(self, rewards: np.ndarray) -> np.ndarray:
        """Which rewards mean success."""
        return rewards >= self.success_reward

    def embed(self, goals: np.ndarray, device: torch.device | str) -> torch.Tensor:
        """Goals as a float tensor."""
        return torch.as_tensor(goals, dtype=torch.float32, device=device)

    @property
    def embed_dim(self) -> int:
        """Width of :meth:`embed`'s output."""
        return self.dim

    def arrays(self) -> dict[str, np.ndarray]:
        """Storage to save with the buffer."""
        return {"achieved": self._achieved, "desired": self._desired}

    def load_arrays(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore storage saved by :meth:`arrays`."""
        self._achieved = np.array(arrays["achieved"], np.float32)
        self._desired = np.array(arrays["desired"], np.float32)

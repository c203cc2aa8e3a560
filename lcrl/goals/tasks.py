"""One-hot ids of a fixed task set (:class:`TaskGoals`), each with its own reward, never
relabelled."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from lcrl.errors import LcrlError
from lcrl.goals.labels import LabelGoals

#: Why a buffer over :class:`TaskGoals` refuses hindsight relabelling.
TASK_RELABEL_ERROR = (
    "one-hot task ids cannot be relabelled (each task has its own reward function, so what "
    "an episode of one task achieved says nothing about another task's reward): set "
    "buffer.k=0 and buffer.random_fraction=0"
)


TaskRewardFn = Callable[[np.ndarray], np.ndarray]


class TaskGoals(LabelGoals):
    """One-hot task ids over a fixed set of ``K`` tasks, each with its own reward function.

    The goal of an episode is its task id, embedded as a one-hot vector; the reward of a
    step is whether it achieved *that* task, stored once per step when the episode is
    written. Nothing is relabelled: :meth:`relabel` and :meth:`random_goals` raise, and
    :class:`lcrl.buffer.HindsightReplayBuffer` refuses ``k > 0`` or
    ``random_fraction > 0`` over this goal space.

    The episode passed to :meth:`write` needs ``goal_id`` (an int in ``[0, K)``) and one of

    * ``success``: ``(T,)`` bools, whether step ``t`` achieved the episode's task (its next
      observation, ``t + 1``, satisfies it), or ``(T + 1,)`` bools for every observation;
    * ``achieved_goal``: ``(T + 1, ...)`` what each observation achieved, judged by
      ``reward_fns[goal_id](achieved_goal) -> (T + 1,)`` bools (vectorised over the
      episode; row 0 is the first observation, so a reward relative to the start can be
      computed).

    Args:
        num_tasks: ``K``.
        reward_fns: ``K`` vectorised reward functions (see above); ``None`` when episodes
            carry ``success`` flags.
        terminate_on_success: whether achieving the task ends the episode (no bootstrap).
    """

    kind = "task"
    can_relabel = False

    def __init__(
        self,
        num_tasks: int,
        reward_fns: Sequence[TaskRewardFn] | None = None,
        terminate_on_success: bool = True,
    ) -> None:
        super().__init__(num_tasks, None, max_labels=1, terminate_on_success=terminate_on_success)
        if reward_fns is not None and len(reward_fns) != self.num_goals:
            raise LcrlError(
                f"{len(reward_fns)} reward functions for {self.num_goals} tasks: give one per task"
            )
        self.reward_fns = None if reward_fns is None else list(reward_fns)

    @property
    def num_tasks(self) -> int:
        """``K``."""
        return self.num_goals

    def write(self, start: int, episode: Mapping[str, Any]) -> None:
        """Store an episode's task id and whether each step achieved that task."""
        n = len(episode["action"]) + 1
        goal = int(episode["goal_id"])
        if not 0 <= goal < self.num_goals:
            raise LcrlError(f"task id {goal} is outside the {self.num_goals} tasks")
        if "success" in episode:
            hit = np.asarray(episode["success"], bool).reshape(-1)
            if hit.shape == (n - 1,):
                hit = np.concatenate([[False], hit])
        elif self.reward_fns is not None and "achieved_goal" in episode:
            hit = np.asarray(self.reward_fns[goal](np.asarray(episode["achieved_goal"])), bool)
            hit = hit.reshape(-1)
        else:
            raise LcrlError(
                "a task-id episode needs per-step 'success' flags, or 'achieved_goal' with "
                "reward functions given to TaskGoals"
            )
        if hit.shape != (n,):
            raise LcrlError(
                f"task success has {hit.size} entries; expected T = {n - 1} (per step) or "
                f"T + 1 = {n} (per observation)"
            )
        labels = [[goal] if h else [] for h in hit]
        super().write(start, {"goal_id": goal, "labels": labels, "action": episode["action"]})

    def relabel(
        self,
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Refused: task ids are never relabelled."""
        raise LcrlError(TASK_RELABEL_ERROR)

    def relabelable(
        self, idx: np.ndarray, ep_start: np.ndarray, ep_end: np.ndarray, strategy: str
    ) -> np.ndarray:
        """No transition can be relabelled."""
        return np.zeros(np.shape(idx), bool)

    def random_goals(self, slots: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Refused: task ids are never relabelled."""
        raise LcrlError(TASK_RELABEL_ERROR)

    def reward(self, idx: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """1.0 where the transition achieved its episode's task (``goals`` must be the
        transitions' own task ids)."""
        goals = np.asarray(goals, np.int64)
        if np.any(goals != self._goal[idx]):
            raise LcrlError(TASK_RELABEL_ERROR)
        return super().reward(idx, goals)

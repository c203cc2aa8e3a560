"""Goal spaces: what a goal is, how it is relabelled, how its reward is recomputed.

The replay buffer (:mod:`lcrl.buffer`) stores episodes and picks which transitions to
relabel; a goal space owns everything goal-specific behind one small interface:

``allocate(capacity)``
    preallocate per-slot storage for a buffer of ``capacity`` observation slots.
``write(start, episode)``
    store one episode's goal data at slots ``start .. start + T`` (``T + 1`` observation
    slots for ``T`` transitions; slot ``start + t + 1`` is what step ``t`` achieved).
``desired(idx)``
    the goals the transitions at slots ``idx`` were collected with.
``relabel(idx, ep_start, ep_end, strategy, rng)``
    goals achieved in the same episode at or after each transition (``future``), at its
    end (``final``) or anywhere in it (``episode``), plus a mask of the transitions for
    which such a goal exists.
``relabelable(idx, ep_start, ep_end, strategy)``
    which transitions have such a goal (all of them for state goals).
``random_goals(slots, rng)``
    goals achieved anywhere in the buffer (HER's ``random`` strategy), given random slots.
``reward(idx, goals)``
    the sparse reward of the transitions at ``idx`` under ``goals``, from what they
    achieved (vectorised).
``embed(goals, device)``
    the goals as a float tensor for the networks.

Two goal spaces are provided:

:class:`StateGoals`
    goals are vectors (``achieved_goal`` / ``desired_goal``); the reward is any
    vectorised ``reward_fn(achieved, desired) -> reward``, e.g. a gymnasium-robotics
    env's ``compute_reward`` with ``info=None``.
:class:`LabelGoals`
    goals are integer ids into a table: instructions (embedded by the frozen text encoder,
    looked up by id when a batch is made) or one-hot task ids. What each step achieved is
    a set of ids written at insertion (the captioner's labels); relabelled goals are drawn
    from labels achieved later in the same episode, and the reward is whether the goal is
    among the labels of the step's next observation, i.e. the captioner's ``satisfied``
    check on ``(s0, s_{t+1})``, evaluated once at insertion and stored as a bitset.

Image goals (a frame of an achieved step, judged on the underlying state) fit the same
interface: the goal is a slot index into the buffer's image storage and the reward is a
:class:`StateGoals` reward on that slot's achieved state.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
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

    def allocate(self, capacity: int) -> None: ...

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
    """

    kind = "state"

    def __init__(
        self,
        dim: int,
        reward_fn: RewardFn,
        success_reward: float = 1.0,
        terminate_on_success: bool = False,
    ) -> None:
        self.dim = int(dim)
        self.reward_fn = reward_fn
        self.success_reward = float(success_reward)
        self.terminate_on_success = terminate_on_success
        self._achieved = np.zeros((0, self.dim), np.float32)
        self._desired = np.zeros((0, self.dim), np.float32)

    def allocate(self, capacity: int) -> None:
        """Preallocate ``capacity`` slots."""
        self._achieved = np.zeros((capacity, self.dim), np.float32)
        self._desired = np.zeros((capacity, self.dim), np.float32)

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
        _check_strategy(strategy)
        last = ep_end - 1  # last transition slot
        first = ep_start if strategy == "episode" else idx
        step = pick_step(first, last, strategy, rng)
        return self._achieved[step + 1], np.ones(idx.shape, bool)

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


class LabelGoals:
    """Goals that are ids into a table: instructions (language HER) or task ids.

    The episode passed to :meth:`write` needs ``goal_id`` (an int, the episode's
    instruction) and ``labels``: ``T + 1`` sequences of ids, ``labels[j]`` being what the
    episode had achieved at observation ``j`` (``labels[0]`` is normally empty). Ids at or
    above ``num_relabel`` are recorded for rewards but never used as relabelled goals: put
    the training instructions first in the table so that held-out instructions can be
    recognised without ever being trained on.

    Relabelling strategies, over the labelled observations of the episode:

    * ``future``: a label of an observation at or after the transition's next one,
      uniformly among such labelled observations, then uniformly among its labels;
    * ``final``: a label of the last labelled observation, if it is at or after the
      transition's next observation;
    * ``episode``: a label of any labelled observation of the episode.

    A transition with no such labelled observation cannot be relabelled
    (:meth:`relabelable`); the buffer draws the transitions it relabels among those that
    can be, so the relabelled fraction stays ``k / (k + 1)`` even when most steps achieve
    nothing (a random arm rarely touches anything).

    Args:
        num_goals: size of the id table.
        embeddings: ``(num_goals, d)`` float array of goal embeddings (the frozen text
            encoder's vectors), looked up by id when a batch is embedded; ``None`` gives
            one-hot task ids.
        num_relabel: ids ``< num_relabel`` may become relabelled goals (default all).
        max_labels: labels kept per observation for relabelling (the reward check uses
            all of them); extras are subsampled at random.
        terminate_on_success: whether achieving the goal ends the episode.
        seed: seed for subsampling labels.
    """

    kind = "label"

    def __init__(
        self,
        num_goals: int,
        embeddings: np.ndarray | torch.Tensor | None = None,
        num_relabel: int | None = None,
        max_labels: int = 32,
        terminate_on_success: bool = True,
        seed: int = 0,
    ) -> None:
        if num_goals < 1:
            raise LcrlError("a label goal space needs at least one goal id")
        if num_goals >= 2**15:
            raise LcrlError(f"at most {2**15 - 1} goal ids are supported, got {num_goals}")
        self.num_goals = int(num_goals)
        self.num_relabel = self.num_goals if num_relabel is None else int(num_relabel)
        self.max_labels = int(max_labels)
        self.terminate_on_success = terminate_on_success
        self._rng = np.random.default_rng(seed)
        self._nbytes = (self.num_goals + 7) // 8
        self._table: torch.Tensor | None = None
        self._embeddings = None
        if embeddings is not None:
            emb = torch.as_tensor(np.asarray(embeddings, np.float32))
            if emb.ndim != 2 or emb.shape[0] != self.num_goals:
                raise LcrlError(
                    f"embeddings must have shape ({self.num_goals}, d), got {tuple(emb.shape)}"
                )
            self._embeddings = emb
        self.allocate(0)

    @property
    def embed_dim(self) -> int:
        """Width of :meth:`embed`'s output."""
        return self.num_goals if self._embeddings is None else int(self._embeddings.shape[1])

    def allocate(self, capacity: int) -> None:
        """Preallocate ``capacity`` slots."""
        self._goal = np.zeros(capacity, np.int16)
        self._labels = np.full((capacity, self.max_labels), -1, np.int16)
        self._nlab = np.zeros(capacity, np.int16)
        self._bits = np.zeros((capacity, self._nbytes), np.uint8)
        # rank[j]: labelled observations of j's episode before slot j; pos[start + r]: the
        # slot of the episode's r-th labelled observation; total[j]: labelled observations
        # in j's episode.
        self._rank = np.zeros(capacity, np.int32)
        self._pos = np.zeros(capacity, np.int64)
        self._total = np.zeros(capacity, np.int32)

    def write(self, start: int, episode: Mapping[str, Any]) -> None:
        """Store an episode's goal id and per-observation labels."""
        labels = episode["labels"]
        n = len(labels)
        expected = len(episode["action"]) + 1
        if n != expected:
            raise LcrlError(f"labels has {n} entries; expected T + 1 = {expected}")
        goal = int(episode["goal_id"])
        if not 0 <= goal < self.num_goals:
            raise LcrlError(f"goal id {goal} is outside the table of {self.num_goals} goals")
        sl = slice(start, start + n)
        self._goal[sl] = goal
        self._labels[sl] = -1
        self._nlab[sl] = 0
        self._bits[sl] = 0
        rank = np.zeros(n, np.int32)
        count = 0
        for j, lab in enumerate(labels):
            rank[j] = count
            ids = np.unique(np.asarray(lab, np.int64))
            if ids.size and (ids.min() < 0 or ids.max() >= self.num_goals):
                raise LcrlError(f"label ids must be in [0, {self.num_goals}), got {ids}")
            np.bitwise_or.at(self._bits[start + j], ids >> 3, (1 << (ids & 7)).astype(np.uint8))
            usable = ids[ids < self.num_relabel]
            if usable.size > self.max_labels:
                usable = self._rng.choice(usable, self.max_labels, replace=False)
            if usable.size:
                self._labels[start + j, : usable.size] = usable
                self._nlab[start + j] = usable.size
                self._pos[start + count] = start + j
                count += 1
        self._rank[sl] = rank
        self._total[sl] = count

    def desired(self, idx: np.ndarray) -> np.ndarray:
        """Goal ids the transitions at ``idx`` were collected with."""
        return self._goal[idx].astype(np.int64)

    def relabel(
        self,
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Labels achieved in the same episode (see the class docstring)."""
        _check_strategy(strategy)
        nxt = idx + 1
        total = self._total[idx].astype(np.int64)
        if strategy == "episode":
            lo = np.zeros_like(total)
        elif strategy == "future":
            lo = self._rank[nxt].astype(np.int64)
        else:  # final: the last labelled observation, when it comes after t
            lo = np.maximum(total - 1, self._rank[nxt])
        ok = lo < total
        r = lo + (rng.random(idx.shape) * np.maximum(total - lo, 0)).astype(np.int64)
        r = np.minimum(r, np.maximum(total - 1, 0))
        slot = self._pos[ep_start + r]
        k = (rng.random(idx.shape) * np.maximum(self._nlab[slot], 1)).astype(np.int64)
        goals = self._labels[slot, k].astype(np.int64)
        goals = np.where(ok, goals, self.desired(idx))
        return goals, ok

    def relabelable(
        self, idx: np.ndarray, ep_start: np.ndarray, ep_end: np.ndarray, strategy: str
    ) -> np.ndarray:
        """Transitions with a labelled observation for the strategy (see :meth:`relabel`)."""
        _check_strategy(strategy)
        total = self._total[idx]
        if strategy == "episode":
            return total > 0
        return self._rank[idx + 1] < total

    def random_goals(self, slots: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Uniformly random relabelling ids (``< num_relabel``); ``slots`` is unused."""
        return rng.integers(0, self.num_relabel, slots.shape[0]).astype(np.int64)

    def achieved(self, slots: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Whether the observations at ``slots`` carry the labels ``goals``."""
        byte = self._bits[slots, goals >> 3]
        return ((byte >> (goals & 7)) & 1).astype(bool)

    def reward(self, idx: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """1.0 where the transition's next observation carries the goal's label."""
        return self.achieved(idx + 1, goals).astype(np.float32)

    def success(self, rewards: np.ndarray) -> np.ndarray:
        """Which rewards mean success."""
        return rewards >= 1.0

    def embed(self, goals: np.ndarray, device: torch.device | str) -> torch.Tensor:
        """Goal ids as vectors: their embeddings, or one-hot task ids."""
        device = torch.device(device)
        if self._table is None or self._table.device != device:
            if self._embeddings is None:
                self._table = torch.eye(self.num_goals, device=device)
            else:
                self._table = self._embeddings.to(device)
        ids = torch.as_tensor(np.asarray(goals, np.int64), device=device)
        return self._table[ids]

    def arrays(self) -> dict[str, np.ndarray]:
        """Storage to save with the buffer."""
        return {
            "goal": self._goal,
            "labels": self._labels,
            "nlab": self._nlab,
            "bits": self._bits,
            "rank": self._rank,
            "pos": self._pos,
            "total": self._total,
        }

    def load_arrays(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore storage saved by :meth:`arrays`."""
        for name, value in arrays.items():
            current = getattr(self, f"_{name}")
            if value.shape[1:] != current.shape[1:]:
                raise LcrlError(
                    f"saved goal array {name!r} has shape {value.shape}; this goal space "
                    f"expects (*, {', '.join(map(str, current.shape[1:]))})"
                )
            setattr(self, f"_{name}", np.array(value, current.dtype))


def label_ids(labels: Sequence[Sequence[str]], table: Mapping[str, int]) -> list[list[int]]:
    """Map per-observation label texts to table ids, dropping texts not in the table."""
    return [[table[t] for t in lab if t in table] for lab in labels]

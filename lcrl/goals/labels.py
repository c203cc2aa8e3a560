"""Instruction labels (:class:`LabelGoals`): ids of an instruction table, relabelled with
what the captioner says each step achieved."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from lcrl.errors import LcrlError
from lcrl.goals.base import _check_strategy


class LabelGoals:
    """Goals that are ids into a table: instructions (language HER) or task ids.

    The episode passed to :meth:`write` needs ``goal_id`` (an int, the episode's
    instruction) and ``labels``: ``T + 1`` sequences of ids, ``labels[j]`` being what the
    episode had achieved at observation ``j`` (``labels[0]`` is normally empty). An
    optional ``achieved`` (same form) gives the ids that earn reward at each observation
    when that judge differs from the one proposing relabelling goals (a learned reward
    model next to a learned captioner); by default the labels are the rewards. Ids at or
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
    #: Rewards are 1 where the goal is achieved, 0 elsewhere.
    reward_range: tuple[float, float] | None = (0.0, 1.0)

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

    def nbytes(self, capacity: int) -> int:
        """The bytes :meth:`allocate` takes for ``capacity`` slots."""
        return capacity * (2 + 2 * self.max_labels + 2 + self._nbytes + 4 + 8 + 4)

    def write(self, start: int, episode: Mapping[str, Any]) -> None:
        """Store an episode's goal id and per-observation labels."""
        labels = episode["labels"]
        achieved = episode.get("achieved", labels)
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
        if len(achieved) != n:
            raise LcrlError(f"achieved has {len(achieved)} entries; expected T + 1 = {n}")
        rank = np.zeros(n, np.int32)
        count = 0
        for j, lab in enumerate(labels):
            rank[j] = count
            ids = np.unique(np.asarray(lab, np.int64))
            hit = np.unique(np.asarray(achieved[j], np.int64)) if achieved is not labels else ids
            for arr in (ids, hit):
                if arr.size and (arr.min() < 0 or arr.max() >= self.num_goals):
                    raise LcrlError(f"label ids must be in [0, {self.num_goals}), got {arr}")
            np.bitwise_or.at(self._bits[start + j], hit >> 3, (1 << (hit & 7)).astype(np.uint8))
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

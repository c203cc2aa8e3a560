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

:class:`ImageGoals`
    the policy sees a camera frame as its goal; the frame is what the policy is shown,
    the privileged state behind it is what judges success. A relabelled goal is a slot
    index into the buffer's own image storage (the frame of a later step of the same
    episode), so frames are stored once; the reward is a :class:`StateGoals` reward on
    that slot's achieved state.

:class:`TaskGoals`
    one-hot task ids of a fixed task set, each task with its own reward function
    (multi-task RL). Whether an episode achieved its own task is stored per step; a goal
    achieved by one task's episode says nothing about another task's reward, so these
    goals are never relabelled (``can_relabel = False``: the buffer refuses ``k > 0``).

A goal space with an ``attach(obs_arrays)`` method is handed the buffer's observation
arrays after :meth:`allocate` (image goals read their frames there). One with
``can_relabel = False`` cannot be relabelled in hindsight.
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


class ImageGoals(StateGoals):
    """Image goals: a camera frame to reach, judged on the privileged state behind it.

    Goals are int64 codes in batches: a code ``c >= 0`` is a buffer slot whose image
    observation is the goal frame and whose achieved state judges it (relabelled and
    random goals are achieved frames, stored once with the observations); ``c < 0`` is
    the desired goal of the episode stored at slot ``-c - 1``, whose frame is kept here.
    :meth:`embed` turns codes into uint8 frames; it also accepts frames directly (the
    environment's goal image when acting).

    The episode passed to :meth:`write` needs what :class:`StateGoals` needs plus
    ``desired_image``, the ``(H, W, C)`` uint8 frame of the desired goal.

    Desired frames live in a ring of ``capacity // (min_episode_steps + 1) + 1`` entries,
    enough for every episode the buffer can hold when episodes have at least
    ``min_episode_steps`` steps. If shorter episodes make the ring wrap first, an episode
    whose desired frame was overwritten uses its final achieved frame (and state) as its
    original goal instead.

    Args:
        dim: state goal dimension (the privileged achieved / desired goal).
        reward_fn: vectorised ``reward_fn(achieved, desired)`` on state goals.
        image_shape: ``(H, W, C)`` of a goal frame.
        image_key: the observation key whose frames are goals.
        success_reward, terminate_on_success, reward_range: as for :class:`StateGoals`.
        min_episode_steps: sizes the ring of desired frames (see above).
    """

    kind = "image"

    def __init__(
        self,
        dim: int,
        reward_fn: RewardFn,
        image_shape: Sequence[int],
        image_key: str = "image",
        success_reward: float = 1.0,
        terminate_on_success: bool = False,
        min_episode_steps: int = 20,
        reward_range: tuple[float, float] | None = None,
    ) -> None:
        super().__init__(dim, reward_fn, success_reward, terminate_on_success, reward_range)
        self.image_shape = tuple(int(x) for x in image_shape)
        if len(self.image_shape) != 3:
            raise LcrlError(f"image_shape must be (H, W, C), got {self.image_shape}")
        self.image_key = image_key
        self.min_episode_steps = max(1, int(min_episode_steps))
        self._frames: np.ndarray | None = None
        self.allocate(0)

    @property
    def embed_dim(self) -> int:
        """Not a vector: see :attr:`goal_shape`."""
        raise LcrlError("image goals are frames; use goal_shape")

    @property
    def goal_shape(self) -> tuple[int, ...]:
        """Shape of one embedded goal: the frame."""
        return self.image_shape

    @property
    def host_obs_keys(self) -> tuple[str, ...]:
        """Observation keys a buffer must keep in host memory: the goal frames are read
        from them with numpy (:meth:`attach`)."""
        return (self.image_key,)

    def allocate(self, capacity: int) -> None:
        """Preallocate ``capacity`` slots and the ring of desired frames."""
        super().allocate(capacity)
        ring = capacity // (self.min_episode_steps + 1) + 1 if capacity else 0
        self._ring = np.zeros((ring, *self.image_shape), np.uint8)
        self._ring_owner = np.full(ring, -1, np.int64)  # episode start slot of each entry
        self._ring_next = 0
        self._ring_ref = np.zeros(capacity, np.int64)  # ring entry of a slot's episode
        self._ep_first = np.zeros(capacity, np.int64)  # first observation slot of the episode
        self._ep_last = np.zeros(capacity, np.int64)  # last observation slot of the episode

    def nbytes(self, capacity: int) -> int:
        """The bytes :meth:`allocate` takes for ``capacity`` slots (the ring of desired
        frames included)."""
        ring = capacity // (self.min_episode_steps + 1) + 1 if capacity else 0
        frame = int(np.prod(self.image_shape))
        return super().nbytes(capacity) + ring * (frame + 8) + capacity * 3 * 8

    def attach(self, obs_arrays: Mapping[str, np.ndarray]) -> None:
        """Read goal frames from the buffer's observation arrays."""
        if self.image_key not in obs_arrays:
            raise LcrlError(
                f"image goals read the observation {self.image_key!r}, which the buffer does "
                f"not store (it stores {sorted(obs_arrays)})"
            )
        frames = obs_arrays[self.image_key]
        if frames.shape[1:] != self.image_shape or frames.dtype != np.uint8:
            raise LcrlError(
                f"observation {self.image_key!r} holds {frames.dtype} {frames.shape[1:]} "
                f"frames; image goals need uint8 {self.image_shape}"
            )
        self._frames = frames

    def write(self, start: int, episode: Mapping[str, Any]) -> None:
        """Store the episode's states and its desired frame."""
        image = np.asarray(episode["desired_image"])
        if image.shape != self.image_shape or image.dtype != np.uint8:
            raise LcrlError(
                f"desired_image must be uint8 {self.image_shape}, got {image.dtype} {image.shape}"
            )
        super().write(start, episode)
        n = len(episode["action"]) + 1
        r = self._ring_next
        self._ring[r] = image
        self._ring_owner[r] = start
        self._ring_next = (r + 1) % len(self._ring)
        self._ring_ref[start : start + n] = r
        self._ep_first[start : start + n] = start
        self._ep_last[start : start + n] = start + n - 1

    def desired(self, idx: np.ndarray) -> np.ndarray:
        """Codes of the goals the transitions at ``idx`` were collected with: their
        episode's desired frame, or its final frame if the ring has overwritten it."""
        first = self._ep_first[idx]
        alive = self._ring_owner[self._ring_ref[idx]] == first
        return np.where(alive, -first - 1, self._ep_last[idx]).astype(np.int64)

    def relabel(
        self,
        idx: np.ndarray,
        ep_start: np.ndarray,
        ep_end: np.ndarray,
        strategy: str,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frames achieved by the same episode (slots of later observations)."""
        slots = self._achieved_slots(idx, ep_start, ep_end, strategy, rng)
        return slots.astype(np.int64), np.ones(idx.shape, bool)

    def random_goals(self, slots: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frames observed after the transitions at ``slots``."""
        return (slots + 1).astype(np.int64)

    def goal_states(self, goals: np.ndarray) -> np.ndarray:
        """The privileged state goal behind each code."""
        goals = np.asarray(goals, np.int64)
        achieved = self._achieved[np.maximum(goals, 0)]
        desired = self._desired[np.maximum(-goals - 1, 0)]
        return np.where((goals >= 0)[:, None], achieved, desired)

    def reward(self, idx: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """``reward_fn`` of the achieved state after each transition and the goal's state."""
        return np.asarray(
            self.reward_fn(self._achieved[idx + 1], self.goal_states(goals)), np.float32
        )

    def frames(self, goals: np.ndarray) -> np.ndarray:
        """uint8 goal frames of codes."""
        if self._frames is None:
            raise LcrlError("image goals are not attached to a buffer's frames")
        goals = np.asarray(goals, np.int64)
        out = self._frames[np.maximum(goals, 0)]
        neg = goals < 0
        if neg.any():
            out[neg] = self._ring[self._ring_ref[-goals[neg] - 1]]
        return out

    def embed(self, goals: np.ndarray, device: torch.device | str) -> torch.Tensor:
        """Goal frames as a uint8 tensor: codes are looked up, frames pass through."""
        goals = np.asarray(goals)
        if goals.ndim == 1 + len(self.image_shape):
            return torch.as_tensor(goals, dtype=torch.uint8, device=device)
        return torch.as_tensor(self.frames(goals), device=device)

    def arrays(self) -> dict[str, np.ndarray]:
        """Storage to save with the buffer (frames of achieved goals are the buffer's)."""
        out = super().arrays()
        out.update(
            ring=self._ring,
            ring_owner=self._ring_owner,
            ring_ref=self._ring_ref,
            ep_first=self._ep_first,
            ep_last=self._ep_last,
            ring_next=np.array([self._ring_next], np.int64),
        )
        return out

    def load_arrays(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore storage saved by :meth:`arrays`."""
        super().load_arrays(arrays)
        ring = np.asarray(arrays["ring"])
        if ring.shape[1:] != self.image_shape:
            raise LcrlError(
                f"saved goal frames have shape {ring.shape[1:]}, not {self.image_shape}"
            )
        self._ring = np.array(ring, np.uint8)
        self._ring_owner = np.array(arrays["ring_owner"], np.int64)
        self._ring_ref = np.array(arrays["ring_ref"], np.int64)
        self._ep_first = np.array(arrays["ep_first"], np.int64)
        self._ep_last = np.array(arrays["ep_last"], np.int64)
        self._ring_next = int(np.asarray(arrays["ring_next"])[0])


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


def label_ids(labels: Sequence[Sequence[str]], table: Mapping[str, int]) -> list[list[int]]:
    """Map per-observation label texts to table ids, dropping texts not in the table."""
    return [[table[t] for t in lab if t in table] for lab in labels]

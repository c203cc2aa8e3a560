"""Goal camera frames (:class:`ImageGoals`): later frames of the same episode, judged on the
privileged state behind them."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from lcrl.errors import LcrlError
from lcrl.goals.base import RewardFn
from lcrl.goals.state import StateGoals


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

"""Observation features computed from the tabletops' object slots.

Both tabletops lay out ``"observation"`` as ``[agent values, 8 object slots, ...]``: the
agent's own values first (pusher ``x, y``; gripper ``x, y, z``, opening), then one slot
per object kind in :data:`~envs.scene.OBJECT_KINDS` order, each ``[position, present]``.
The env class says where: ``slot_layout = (start, count, width)`` and ``position_dims``
(the position values at the front of the agent values and of each slot).

:class:`RelativePositions` adds each object's position relative to the agent to its slot.
A goal-conditioned network then reads "how far is the red cube from the gripper" from
one slot instead of computing a difference between two inputs that it must first learn
to pick by the goal; with :class:`lcrl.nets.SlotSelect` the one-step reach reward is
learned several times faster (see the README).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lcrl.errors import LcrlError

__all__ = ["RelativePositions", "slot_layout"]


def slot_layout(env: gym.Env) -> tuple[int, int, int, int]:
    """``(start, count, width, position_dims)`` of ``env``'s observation slots: from the
    outermost :class:`RelativePositions` if any, else from the unwrapped env's class."""
    e: Any = env
    while True:
        if "slot_layout" in vars(e):
            start, count, width = e.slot_layout
            return int(start), int(count), int(width), int(e.position_dims)
        if not isinstance(e, gym.Wrapper):
            break
        e = e.env
    base = env.unwrapped
    layout = getattr(base, "slot_layout", None)
    if layout is None:
        raise LcrlError(
            f"{type(base).__name__} does not describe its observation slots (no slot_layout)"
        )
    start, count, width = layout
    return int(start), int(count), int(width), int(base.position_dims)


class RelativePositions(gym.ObservationWrapper):
    """Append to every object slot its position minus the agent's position.

    Slot ``k`` becomes ``[original values, rel_1 .. rel_d]`` with ``d = position_dims``;
    absent kinds (present flag, the slot's last value, is 0) get zeros. The agent values
    and anything after the slots are unchanged, so ``slot_layout`` becomes
    ``(start, count, width + d)``.

    Args:
        env: a tabletop (or a wrapper of one) whose class defines ``slot_layout`` and
            ``position_dims``.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        start, count, width, dims = slot_layout(env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "observation" not in space.spaces:
            raise LcrlError("RelativePositions needs a Dict observation with 'observation'")
        box = space["observation"]
        if start < dims or start + count * width > box.shape[0]:
            raise LcrlError(f"slot layout {(start, count, width)} does not fit {box.shape}")
        self._start, self._count, self._width, self._dims = start, count, width, dims
        self._end = start + count * width
        self.slot_layout = (start, count, width + dims)
        self.position_dims = dims
        low, high = box.low.astype(np.float64), box.high.astype(np.float64)
        slots_lo = low[start : self._end].reshape(count, width)
        slots_hi = high[start : self._end].reshape(count, width)
        rel_lo = np.minimum(slots_lo[:, :dims] - high[:dims], 0.0)
        rel_hi = np.maximum(slots_hi[:, :dims] - low[:dims], 0.0)
        new_low = np.concatenate(
            [low[:start], np.concatenate([slots_lo, rel_lo], 1).ravel(), low[self._end :]]
        )
        new_high = np.concatenate(
            [high[:start], np.concatenate([slots_hi, rel_hi], 1).ravel(), high[self._end :]]
        )
        self.observation_space = spaces.Dict(
            {
                **space.spaces,
                "observation": spaces.Box(
                    new_low.astype(np.float32), new_high.astype(np.float32), dtype=np.float32
                ),
            }
        )

    def features(self, observation: np.ndarray) -> np.ndarray:
        """The extended ``"observation"`` vector(s) (any leading batch shape)."""
        x = np.asarray(observation, np.float32)
        lead = x.shape[:-1]
        slots = x[..., self._start : self._end].reshape(*lead, self._count, self._width)
        present = slots[..., -1:] > 0.5
        rel = np.where(present, slots[..., : self._dims] - x[..., None, : self._dims], 0.0)
        body = np.concatenate([slots, rel.astype(np.float32)], -1).reshape(*lead, -1)
        return np.concatenate([x[..., : self._start], body, x[..., self._end :]], -1)

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        out = dict(observation)
        out["observation"] = self.features(observation["observation"])
        return out

"""Observation features computed from the tabletops' object slots.

Both tabletops lay out ``"observation"`` as ``[agent values, 8 object slots, ...]``: the
agent's own values first (pusher ``x, y``; gripper ``x, y, z``, opening), then one slot
per object kind in :data:`~envs.scene.OBJECT_KINDS` order, each ``[position, present]``.
The env class says where: ``slot_layout = (start, count, width)`` and ``position_dims``
(the position values at the front of the agent values and of each slot).

:class:`SlotFeatures` adds to each slot the object's position relative to the agent
(:class:`RelativePositions`) and, optionally, how far it moved since the episode began.
A goal-conditioned network then reads "how far is the red cube from the gripper" from
one slot instead of computing a difference between two inputs that it must first learn
to pick by the goal; with :class:`lcrl.nets.SlotSelect` the one-step reach reward is
learned several times faster (see the README).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lcrl.errors import LcrlError

__all__ = ["FEATURE_KEYS", "RelativePositions", "SlotFeatures", "slot_layout"]

#: Observation entries laid out in object slots: the observation the policy reads and,
#: where that is an estimate (perception from camera frames), the true state beside it.
FEATURE_KEYS = ("observation", "privileged")


def slot_layout(env: gym.Env) -> tuple[int, int, int, int]:
    """``(start, count, width, position_dims)`` of ``env``'s observation slots: from the
    outermost :class:`SlotFeatures` if any, else from the unwrapped env's class."""
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


class SlotFeatures(gym.ObservationWrapper):
    """Append per-object features to every object slot.

    Slot ``k`` becomes ``[original values, rel_1 .. rel_d, disp_1 .. disp_d]`` with
    ``d = position_dims``, each part present when its option is on:

    * ``relative``: the object's position minus the agent's position (how far the red
      cube is from the gripper);
    * ``displacement``: the object's position minus its position at the episode's reset
      (how far the red cube has been pushed). Push and put instructions are judged on
      that change; as an explicit feature it is normalised on its own scale (most objects
      never move, so a 5 cm push stands out) instead of being a small difference of two
      large position inputs.

    Absent kinds (present flag, the slot's last value, is 0) get zeros. The agent values
    and anything after the slots are unchanged, so ``slot_layout`` becomes
    ``(start, count, width + d * parts)``.

    An env whose ``"observation"`` is an estimate (perception from camera frames) also
    gives the true state as ``"privileged"`` (same layout), for a critic that reads it in
    training: that entry gets the same features, from its own values.

    Args:
        env: a tabletop (or a wrapper of one) whose class defines ``slot_layout`` and
            ``position_dims``; not already wrapped by :class:`SlotFeatures`.
        relative: add positions relative to the agent.
        displacement: add displacements since the reset.
    """

    def __init__(self, env: gym.Env, relative: bool = True, displacement: bool = False) -> None:
        super().__init__(env)
        if not (relative or displacement):
            raise LcrlError("SlotFeatures needs relative=True or displacement=True")
        e: Any = env
        while isinstance(e, gym.Wrapper):
            if isinstance(e, SlotFeatures):
                raise LcrlError(
                    "the env already has slot features: use one SlotFeatures with both options"
                )
            e = e.env
        start, count, width, dims = slot_layout(env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "observation" not in space.spaces:
            raise LcrlError("SlotFeatures needs a Dict observation with 'observation'")
        box = space["observation"]
        if start < dims or start + count * width > box.shape[0]:
            raise LcrlError(f"slot layout {(start, count, width)} does not fit {box.shape}")
        self.relative, self.displacement = bool(relative), bool(displacement)
        self._start, self._count, self._width, self._dims = start, count, width, dims
        self._end = start + count * width
        parts = int(self.relative) + int(self.displacement)
        self.slot_layout = (start, count, width + dims * parts)
        self.position_dims = dims
        self._origin: np.ndarray | None = None  # slot positions at the last reset
        self._raw: np.ndarray | None = None  # the last raw observation vector
        low, high = box.low.astype(np.float64), box.high.astype(np.float64)
        slots_lo = low[start : self._end].reshape(count, width)
        slots_hi = high[start : self._end].reshape(count, width)
        los, his = [slots_lo], [slots_hi]
        if self.relative:
            los.append(np.minimum(slots_lo[:, :dims] - high[:dims], 0.0))
            his.append(np.maximum(slots_hi[:, :dims] - low[:dims], 0.0))
        if self.displacement:
            span = slots_hi[:, :dims] - slots_lo[:, :dims]
            los.append(np.minimum(-span, 0.0))
            his.append(np.maximum(span, 0.0))
        new_low = np.concatenate([low[:start], np.concatenate(los, 1).ravel(), low[self._end :]])
        new_high = np.concatenate([high[:start], np.concatenate(his, 1).ravel(), high[self._end :]])
        box = spaces.Box(new_low.astype(np.float32), new_high.astype(np.float32), dtype=np.float32)
        #: the entries that get features: the observation, and the true state beside an
        #: estimated one
        self.keys = tuple(k for k in FEATURE_KEYS if k in space.spaces)
        self._origins: dict[str, np.ndarray] = {}  # slot positions at the last reset, by key
        self._raws: dict[str, np.ndarray] = {}  # the last raw values of the other keys
        self.observation_space = spaces.Dict({**space.spaces, **dict.fromkeys(self.keys, box)})

    def _slots(self, x: np.ndarray) -> np.ndarray:
        return x[..., self._start : self._end].reshape(*x.shape[:-1], self._count, self._width)

    def features(self, observation: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
        """The extended ``"observation"`` vector(s) (any leading batch shape).

        Args:
            observation: raw observation vector(s) of the wrapped env.
            origin: with ``displacement``, the raw observation(s) at the episode's reset
                (default: the one this wrapper saw at its last reset).
        """
        x = np.asarray(observation, np.float32)
        lead = x.shape[:-1]
        slots = self._slots(x)
        present = slots[..., -1:] > 0.5
        parts = [slots]
        if self.relative:
            rel = slots[..., : self._dims] - x[..., None, : self._dims]
            parts.append(np.where(present, rel, 0.0).astype(np.float32))
        if self.displacement:
            if origin is None:
                if self._origin is None:
                    raise LcrlError("SlotFeatures: reset the env before asking for displacements")
                start = self._origin
            else:
                start = self._slots(np.asarray(origin, np.float32))[..., : self._dims]
            disp = slots[..., : self._dims] - start
            parts.append(np.where(present, disp, 0.0).astype(np.float32))
        body = np.concatenate(parts, -1).reshape(*lead, -1)
        return np.concatenate([x[..., : self._start], body, x[..., self._end :]], -1)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        for key in self.keys:
            raw = np.asarray(obs[key], np.float32)
            self._origins[key] = self._slots(raw)[..., : self._dims].copy()
        self._origin = self._origins["observation"]
        return self.observation(obs), info

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        out = dict(observation)
        self._raw = np.asarray(observation["observation"], np.float32)
        out["observation"] = self.features(self._raw)
        for key in self.keys[1:]:
            raw = self._raws[key] = np.asarray(observation[key], np.float32)
            origin = self._origins.get(key)
            out[key] = self.features(raw, None if origin is None else self._with_slots(origin))
        return out

    def _with_slots(self, positions: np.ndarray) -> np.ndarray:
        """An observation vector whose slot positions are ``positions`` (for
        :meth:`features`' ``origin``, which reads only those)."""
        x = np.zeros(self._end, np.float32)
        self._slots(x)[..., : self._dims] = positions
        return x

    def restart_displacements(self) -> np.ndarray:
        """Measure displacements from the objects' current positions from now on.

        For a new task that begins mid-episode (the next instruction of a chain): push
        and put are then judged from here, and so are the displacement features.

        Returns:
            The current ``"observation"`` vector recomputed (its displacements are 0).

        Raises:
            LcrlError: the env has not been reset.
        """
        if self._raw is None:
            raise LcrlError("SlotFeatures: reset the env before restarting displacements")
        self._origin = self._slots(self._raw)[..., : self._dims].copy()
        self._origins["observation"] = self._origin
        for key, raw in self._raws.items():
            self._origins[key] = self._slots(raw)[..., : self._dims].copy()
        return self.features(self._raw)

    def restarted(self, obs: Mapping[str, Any]) -> dict[str, Any]:
        """``obs`` (the last observation this wrapper returned) with displacements
        restarted from now (:meth:`restart_displacements`) in every entry that has them:
        the observation and, beside an estimated one, the true state (``"privileged"``),
        so that a teacher or critic reading the true state sees the same restart."""
        out = dict(obs)
        out["observation"] = self.restart_displacements()
        for key in self.keys[1:]:
            if key in self._raws:
                out[key] = self.features(self._raws[key], self._with_slots(self._origins[key]))
        return out


class RelativePositions(SlotFeatures):
    """:class:`SlotFeatures` with positions relative to the agent only."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env, relative=True, displacement=False)

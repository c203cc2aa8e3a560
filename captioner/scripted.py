"""Scripted (non-learned) controllers for the 2D tabletop families.

They read the privileged scene and return a pusher action, which makes them a test that
every 2D instruction family is achievable and recognised by the captioner, and a source of
demonstrations. Stateless: each action depends only on the instruction, ``s0`` and ``s``.

Pushing an object towards a point: go round the object to the side opposite the goal
(staying clear of it), line up behind it, then push through its centre, correcting
sideways drift.
"""

from __future__ import annotations

import math

import numpy as np

from captioner.grammar import DIRECTION_VECTORS, RELATION_VECTORS, Instruction, parse
from captioner.rule import Thresholds
from envs.scene import SceneState


class ScriptedController2D:
    """Scripted pusher policy for ``reach``, ``push`` and ``put``.

    Args:
        max_step: metres the pusher moves for an action of norm 1 (the env's ``max_step``).
        pusher_radius: radius of the pusher disc.
        thresholds: the captioner thresholds to aim beyond.
    """

    def __init__(
        self,
        max_step: float = 0.02,
        pusher_radius: float = 0.015,
        thresholds: Thresholds | None = None,
    ) -> None:
        self.max_step = max_step
        self.pusher_radius = pusher_radius
        self.thresholds = thresholds or Thresholds()

    def _toward(self, g: np.ndarray, target: np.ndarray) -> np.ndarray:
        return np.clip((target - g) / self.max_step, -1.0, 1.0)

    def _push_to(
        self, g: np.ndarray, o: np.ndarray, half: float, goal: np.ndarray, limit: float
    ) -> np.ndarray:
        d = goal - o
        dist = float(np.linalg.norm(d))
        if dist < 1e-3:
            return np.zeros(2)
        u = d / dist
        perp = np.array([-u[1], u[0]])
        rel = g - o
        along, lat = float(rel @ u), float(rel @ perp)
        contact = half + self.pusher_radius
        if along <= -contact + 0.004 and abs(lat) <= 0.5 * half:
            # lined up behind: push through the centre, correcting sideways drift
            a = u - perp * np.clip(lat / half, -1.0, 1.0)
            speed = min(1.0, (dist + 0.01) / self.max_step)
            return np.clip(a * speed, -1.0, 1.0)
        behind = o - u * (contact + 0.006)
        if along <= -0.5 * contact:  # on the back half: slide round to the push point
            return self._toward(g, behind)
        side = 1.0 if lat >= 0 else -1.0
        clear = contact + 0.02
        waypoint = o + perp * side * clear - u * (contact + 0.01)
        if np.any(np.abs(waypoint) > limit):  # no room on this side: go round the other
            side = -side
            waypoint = o + perp * side * clear - u * (contact + 0.01)
        if abs(lat) < clear and lat * side >= 0:  # in the object's corridor: step out
            return np.clip(perp * side, -1.0, 1.0)
        return self._toward(g, np.clip(waypoint, -limit, limit))

    def act(self, instruction: str | Instruction, s0: SceneState, s: SceneState) -> np.ndarray:
        """Action in [-1, 1]^2 for the current scene; zeros when the object is missing."""
        ins = parse(instruction) if isinstance(instruction, str) else instruction
        i = s.index(*ins.obj)
        g = s.gripper[:2]
        if i < 0:
            return np.zeros(2, dtype=np.float32)
        o = s.positions[i, :2]
        half = float(s.half_extents[i, :2].max())
        limit = min(-s.table_bounds[0], s.table_bounds[1], -s.table_bounds[2], s.table_bounds[3])
        limit -= self.pusher_radius
        th = self.thresholds
        if ins.family == "reach":
            a = self._toward(g, o)
        elif ins.family == "push":
            vec = np.asarray(DIRECTION_VECTORS[ins.direction])
            goal = s0.positions[i, :2] + vec * (th.push_distance + 0.02)
            a = self._push_to(g, o, half, goal, limit)
        elif ins.family == "put":
            j = s.index(*ins.target)
            if j < 0:
                return np.zeros(2, dtype=np.float32)
            vec = np.asarray(RELATION_VECTORS[ins.relation])
            b = s.positions[j, :2]
            gap = th.relation_gap + half + float(s.half_extents[j, :2].max())
            # keep to A's side of B (within the captioner's lateral tolerance) so that the
            # straight push from A to the goal does not run into B
            perp = np.array([-vec[1], vec[0]])
            lat = float((o - b) @ perp)
            clearance = half + float(s.half_extents[j, :2].max()) + 0.012
            if float((o - b) @ vec) < gap and abs(lat) < clearance:
                lat = clearance if lat >= 0 else -clearance
            lat = float(np.clip(lat, -0.6 * th.relation_lateral, 0.6 * th.relation_lateral))
            goal = b + vec * (gap + 0.005) + perp * lat
            goal = np.clip(goal, -limit + half, limit - half)
            a = self._push_to(g, o, half, goal, limit)
        else:
            raise ValueError(f"no 2D scripted controller for family {ins.family!r}")
        return np.asarray(a, dtype=np.float32)


def to_discrete(action: np.ndarray, num_directions: int = 8, dead_zone: float = 0.3) -> int:
    """Map a continuous pusher action to the 2D tabletop's discrete action.

    0 is stay; ``1 + k`` moves along angle ``2*pi*k/num_directions`` counter-clockwise from +x.
    """
    x, y = float(action[0]), float(action[1])
    if math.hypot(x, y) < dead_zone:
        return 0
    k = round(math.atan2(y, x) / (2 * math.pi / num_directions)) % num_directions
    return 1 + int(k)

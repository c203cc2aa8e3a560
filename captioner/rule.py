"""Rule captioner: what did the change from s0 to s achieve, in words.

The captioner reads privileged :class:`envs.scene.SceneState` snapshots. ``caption(s0, s)``
returns every canonical instruction (of its families, over the objects in the scene) that
the change from ``s0`` to ``s`` satisfies; ``satisfied(instruction, s0, s)`` checks one
instruction in any phrasing the grammar parses. Both evaluate the same vectorised
predicates, so an instruction is in the caption exactly when it is satisfied.

Predicates and thresholds (all in metres, viewer frame; see :class:`Thresholds`):

reach X
    The gripper's xy distance to X's centre is at most X's xy half size + ``reach_margin``
    and the gripper is no higher than X's top + ``reach_height``; or the environment
    reports contact between gripper and X.
push X <dir>
    X moved at least ``push_distance`` along the direction, and its sideways drift is at
    most ``push_lateral_ratio`` times that (within 45 degrees for ratio 1); X is not
    held and was not raised by ``lift_height`` or more.
put X <rel> Y
    In s, X - Y points along the relation (left of: X.x < Y.x, in front of: X.y < Y.y,
    ...) by at least ``relation_gap`` with at most ``relation_lateral`` offset on the other
    axis; the relation did not hold in s0; X moved at least ``move_distance``; and X is
    not held (when the environment reports grasping): carried over the spot is not put.
lift X
    X's centre rose at least ``lift_height`` since s0, and X is held when the environment
    reports grasping.
stack X on Y
    X's centre is within ``stack_xy`` of Y's in xy, its height above Y's centre is the sum of
    their half heights within ``stack_z_tolerance``, X is not held (when grasping is
    reported), and X was not already on Y in s0.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from captioner.grammar import (
    DIRECTION_VECTORS,
    DIRECTIONS,
    FAMILIES,
    RELATION_VECTORS,
    RELATIONS,
    Instruction,
    InstructionParseError,
    parse,
)
from envs.scene import SceneState


@dataclass(frozen=True)
class Thresholds:
    """Success thresholds of the rule captioner, in metres (see the module docstring)."""

    reach_margin: float = 0.02
    """reach: extra xy distance beyond the object's half size."""
    reach_height: float = 0.03
    """reach: how far above the object's top the gripper may be."""
    push_distance: float = 0.05
    """push: minimum displacement along the direction."""
    push_lateral_ratio: float = 1.0
    """push: maximum sideways drift as a fraction of the displacement along the direction."""
    relation_gap: float = 0.05
    """put: minimum separation of the two centres along the relation's axis."""
    relation_lateral: float = 0.10
    """put: maximum offset of the two centres on the other axis."""
    move_distance: float = 0.02
    """put: the moved object must have moved at least this far."""
    lift_height: float = 0.04
    """lift: minimum rise of the object's centre."""
    stack_xy: float = 0.02
    """stack: maximum xy offset between the two centres."""
    stack_z_tolerance: float = 0.01
    """stack: tolerance on the vertical distance between the centres."""
    feasibility_margin: float = 0.01
    """sampling: room to keep from the table edge when judging an instruction feasible."""


def _pair(family: str, s: SceneState, a: int, b: int, **slots: str) -> Instruction:
    """The instruction of a two-object family acting on object ``a`` relative to ``b``."""
    return Instruction(
        family,
        s.colours[a],
        s.shapes[a],
        target_colour=s.colours[b],
        target_shape=s.shapes[b],
        **slots,
    )


def _as_index(x: int | np.ndarray) -> np.ndarray:
    return np.atleast_1d(np.asarray(x, dtype=np.intp))


class RuleCaptioner:
    """Captions scene changes and checks instructions against them.

    Args:
        families: the families :meth:`caption` enumerates (``satisfied`` accepts any).
        thresholds: success thresholds.
    """

    def __init__(
        self, families: Iterable[str] = FAMILIES, thresholds: Thresholds | None = None
    ) -> None:
        self.families = tuple(families)
        unknown = [f for f in self.families if f not in FAMILIES]
        if unknown:
            raise InstructionParseError(f"unknown families {unknown}; known: {FAMILIES}")
        self.thresholds = thresholds or Thresholds()
        self._parse_cache: dict[str, Instruction] = {}

    # --- vectorised predicates over object index arrays -------------------------------
    def _reach(self, s: SceneState, i: np.ndarray) -> np.ndarray:
        th = self.thresholds
        d_xy = np.linalg.norm(s.positions[i, :2] - s.gripper[:2], axis=-1)
        radius = s.half_extents[i, :2].max(axis=-1) + th.reach_margin
        top = s.positions[i, 2] + s.half_extents[i, 2]
        near = (d_xy <= radius) & (s.gripper[2] <= top + th.reach_height)
        if s.touching is not None:
            near |= s.touching[i]
        return near

    def _raised(self, s0: SceneState, s: SceneState, i: np.ndarray) -> np.ndarray:
        return s.positions[i, 2] - s0.positions[i, 2] >= self.thresholds.lift_height

    def _push(
        self, s0: SceneState, s: SceneState, i: np.ndarray, direction: np.ndarray
    ) -> np.ndarray:
        th = self.thresholds
        disp = s.positions[i, :2] - s0.positions[i, :2]
        along = np.sum(disp * direction, axis=-1)
        lateral = np.abs(disp[..., 0] * direction[..., 1] - disp[..., 1] * direction[..., 0])
        ok = (along >= th.push_distance) & (lateral <= th.push_lateral_ratio * along)
        ok &= ~self._raised(s0, s, i)
        if s.grasped is not None:
            ok &= ~s.grasped[i]
        return ok

    def _relation(self, s: SceneState, i: np.ndarray, j: np.ndarray, vec: np.ndarray) -> np.ndarray:
        th = self.thresholds
        diff = s.positions[i, :2] - s.positions[j, :2]
        along = np.sum(diff * vec, axis=-1)
        lateral = np.abs(diff[..., 0] * vec[..., 1] - diff[..., 1] * vec[..., 0])
        return (along >= th.relation_gap) & (lateral <= th.relation_lateral)

    def _put(
        self, s0: SceneState, s: SceneState, i: np.ndarray, j: np.ndarray, vec: np.ndarray
    ) -> np.ndarray:
        moved = (
            np.linalg.norm(s.positions[i, :2] - s0.positions[i, :2], axis=-1)
            >= self.thresholds.move_distance
        )
        ok = self._relation(s, i, j, vec) & ~self._relation(s0, i, j, vec) & moved
        if s.grasped is not None:
            ok &= ~s.grasped[i]
        return ok

    def _lift(self, s0: SceneState, s: SceneState, i: np.ndarray) -> np.ndarray:
        ok = self._raised(s0, s, i)
        if s.grasped is not None:
            ok &= s.grasped[i]
        return ok

    def _on(self, s: SceneState, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        th = self.thresholds
        d_xy = np.linalg.norm(s.positions[i, :2] - s.positions[j, :2], axis=-1)
        dz = s.positions[i, 2] - s.positions[j, 2]
        expected = s.half_extents[i, 2] + s.half_extents[j, 2]
        ok = (d_xy <= th.stack_xy) & (np.abs(dz - expected) <= th.stack_z_tolerance)
        if s.grasped is not None:
            ok &= ~s.grasped[i]
        return ok

    def _stack(self, s0: SceneState, s: SceneState, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return self._on(s, i, j) & ~self._on(s0, i, j)

    def _evaluate(
        self,
        family: str,
        s0: SceneState,
        s: SceneState,
        i: np.ndarray,
        j: np.ndarray | None,
        vec: np.ndarray | None,
    ) -> np.ndarray:
        if family == "reach":
            return self._reach(s, i)
        if family == "push":
            return self._push(s0, s, i, vec)
        if family == "put":
            return self._put(s0, s, i, j, vec)
        if family == "lift":
            return self._lift(s0, s, i)
        return self._stack(s0, s, i, j)

    # --- public API --------------------------------------------------------------------
    def parse(self, instruction: str | Instruction) -> Instruction:
        """Parse (cached) a sentence, or pass an :class:`Instruction` through."""
        if isinstance(instruction, Instruction):
            return instruction
        ins = self._parse_cache.get(instruction)
        if ins is None:
            ins = parse(instruction)
            self._parse_cache[instruction] = ins
        return ins

    def satisfied(self, instruction: str | Instruction, s0: SceneState, s: SceneState) -> bool:
        """Whether the change from ``s0`` to ``s`` satisfies the instruction.

        Args:
            instruction: an :class:`Instruction` or any sentence the grammar parses.
            s0: the scene at the start of the episode (or segment).
            s: the scene now.

        Returns:
            ``False`` when an object it names is not in the scene.

        Raises:
            InstructionParseError: the sentence cannot be parsed.
        """
        ins = self.parse(instruction)
        i = s.index(*ins.obj)
        if i < 0:
            return False
        j = None
        if ins.target is not None:
            j = s.index(*ins.target)
            if j < 0:
                return False
            j = _as_index(j)
        vec = None
        if ins.direction is not None:
            vec = np.asarray(DIRECTION_VECTORS[ins.direction])
        elif ins.relation is not None:
            vec = np.asarray(RELATION_VECTORS[ins.relation])
        return bool(self._evaluate(ins.family, s0, s, _as_index(i), j, vec)[0])

    def caption(self, s0: SceneState, s: SceneState) -> set[Instruction]:
        """Every canonical instruction of this captioner's families that s0 -> s satisfies.

        Args:
            s0: the scene at the start of the episode (or segment).
            s: the scene now; it must hold the same objects in the same order.

        Returns:
            A set of :class:`Instruction`; ``{i.text for i in ...}`` gives sentences.
        """
        if s0.names != s.names:
            raise ValueError("s0 and s must describe the same objects in the same order")
        n = len(s)
        idx = np.arange(n)
        pi, pj = np.nonzero(~np.eye(n, dtype=bool))  # ordered pairs of distinct objects
        out: set[Instruction] = set()
        for fam in self.families:
            if fam in ("reach", "lift"):
                for k in np.flatnonzero(self._evaluate(fam, s0, s, idx, None, None)):
                    out.add(Instruction(fam, s.colours[k], s.shapes[k]))
            elif fam == "push":
                for d in DIRECTIONS:
                    vec = np.asarray(DIRECTION_VECTORS[d])
                    for k in np.flatnonzero(self._push(s0, s, idx, vec)):
                        out.add(Instruction(fam, s.colours[k], s.shapes[k], direction=d))
            elif fam == "put":
                for r in RELATIONS:
                    vec = np.asarray(RELATION_VECTORS[r])
                    hits = np.flatnonzero(self._put(s0, s, pi, pj, vec))
                    out.update(_pair(fam, s, pi[k], pj[k], relation=r) for k in hits)
            else:  # stack
                hits = np.flatnonzero(self._stack(s0, s, pi, pj))
                out.update(_pair(fam, s, pi[k], pj[k]) for k in hits)
        return out

    def feasible(self, instruction: str | Instruction, s0: SceneState) -> bool:
        """Whether an episode starting in ``s0`` can reasonably achieve the instruction.

        The objects must be in the scene, the instruction must not already hold, and for
        push and put there must be room on the table for the move.
        """
        ins = self.parse(instruction)
        i = s0.index(*ins.obj)
        if i < 0 or (ins.target is not None and s0.index(*ins.target) < 0):
            return False
        if self.satisfied(ins, s0, s0):
            return False
        th = self.thresholds
        xmin, xmax, ymin, ymax = s0.table_bounds
        half = s0.half_extents[i, :2]
        lo = np.array([xmin, ymin]) + half + th.feasibility_margin
        hi = np.array([xmax, ymax]) - half - th.feasibility_margin
        if ins.family == "push":
            goal = s0.positions[i, :2] + th.push_distance * np.asarray(
                DIRECTION_VECTORS[ins.direction]
            )
            return bool(np.all(goal >= lo) and np.all(goal <= hi))
        if ins.family == "put":
            j = s0.index(*ins.target)
            vec = np.asarray(RELATION_VECTORS[ins.relation])
            if self._relation(s0, _as_index(i), _as_index(j), vec)[0]:
                return False  # already true: the change could never make it true
            gap = th.relation_gap + s0.half_extents[j, :2].max() + half.max()
            goal = s0.positions[j, :2] + gap * vec
            return bool(np.all(goal >= lo) and np.all(goal <= hi))
        if ins.family == "stack":
            j = _as_index(s0.index(*ins.target))
            return not bool(self._on(s0, _as_index(i), j)[0])
        return True  # reach, lift (whether an env can lift is its family list's business)

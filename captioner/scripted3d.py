"""Scripted (non-learned) controllers for the robosuite tabletop families.

They read the privileged scene (:meth:`envs.robosuite_tabletop.RobosuiteTabletopEnv.scene`)
and return the env's 4-D action (``dx, dy, dz`` in the viewer frame, gripper ``-1`` open /
``+1`` close), which makes them a test that every instruction family is achievable on the
Panda and recognised by the rule captioner, and a source of demonstrations.

Strategies (every target lies beyond the captioner's thresholds, by the margins of
:class:`ScriptedController3D`):

reach X
    Fly above X, then come down with closed fingers to just above its top (centred on it).
push X <dir>
    Line up behind X on the side opposite the direction, high enough to pass over the other
    objects; lower the closed fingers to mid-height of X; push through X's centre towards a
    goal ``push_distance + push_margin`` beyond X's start, steering sideways so that the push
    line keeps running through the centre (drift correction). The closed fingers' footprint
    (``finger_half_width``: about 5.6 cm along ``x``, 3.2 cm along ``y``) sets how far
    behind X they come down; where that spot is taken by another object the push runs up
    to 40 degrees off the direction (the captioner accepts up to 45).
put X <rel> Y
    Pick X up (as for lift) and carry it, above the other objects, to a point
    ``relation_gap + put_margin`` from Y along the relation and at most ``put_lateral`` off
    its axis (keeping X's present offset where it is small enough); lower it onto the table,
    release it and back off upwards. (The relation only reads xy positions, so it already
    holds while X is carried over the point.)
lift X
    Open, fly above X, come down around it, close until the env reports a grasp, raise X's
    centre ``lift_height + lift_margin`` above where it started and hold it there.
stack X on Y
    Grasp X as for lift, raise it above every object, carry it until its centre (not the
    gripper's) is over Y's, lower it until it rests on Y, release and back off upwards.

State: the controller keeps a small phase machine per episode (``approach``, ``descend``,
``close``, ``carry``, ``lower``, ``release``, ``retreat`` for the grasping families;
``approach``, ``descend``, ``push``, ``done`` for push; reach needs none) with a step
counter per phase, a lost-contact counter, the push's goal and the gripper's last motion.
Grasping and pushing are sequences whose stage cannot be read reliably from the scene alone
(it does not report how far the fingers are open), so each stage ends on what the scene
shows (a grasp reported, X over Y, ...) or after a time limit, and every failure (grasp not
made, object dropped, object lost by the pusher, object not where it should be after
release) goes back to the approach. The arm under the operational-space controller keeps
some momentum and lags small requests, so moves are proportional with gain ``gain`` and
damped by the last step's motion.

The phase machine restarts by itself when the instruction changes or ``s0`` is another
object than at the previous call (a new episode); :meth:`ScriptedController3D.reset`
restarts it explicitly.

``python -m captioner.scripted3d --episodes 20`` prints the success rate per family on
language-goal episodes (:func:`evaluate`; needs robosuite).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from captioner.grammar import (
    DIRECTION_VECTORS,
    FAMILIES,
    RELATION_VECTORS,
    Instruction,
    parse,
)
from captioner.rule import RuleCaptioner, Thresholds
from envs.scene import SceneState

OPEN, CLOSE = -1.0, 1.0


@dataclass
class _Memory:
    """Per-episode state of the phase machine."""

    phase: str = "approach"
    steps: int = 0  # steps spent in the current phase
    lost: int = 0  # consecutive steps without the expected grasp or push contact (negative:
    # consecutive steps with the grasp, while closing)
    previous: np.ndarray | None = None  # gripper position at the previous step
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its last motion
    goal: np.ndarray | None = None  # push: where the object is being pushed to (xy)

    def goto(self, phase: str) -> None:
        """Enter ``phase`` (resets the counters, keeps ``previous``)."""
        self.phase, self.steps, self.lost = phase, 0, 0


class ScriptedController3D:
    """Scripted Panda policy for ``reach``, ``push``, ``put``, ``lift`` and ``stack``.

    Args:
        thresholds: the captioner thresholds to aim beyond.
        step_size: metres of requested end-effector displacement per unit of action (the
            env's operational-space scale, 0.05).
        finger_half_width: half extent of the closed fingers along ``x`` and along ``y``
            in the viewer frame (m).
        standoff: gap (m) between the closed fingers and the object where a push starts.
        push_margin: how far beyond ``push_distance`` a push aims (m).
        put_margin: how far beyond ``relation_gap`` a put aims (m).
        put_lateral: the largest offset across the relation's axis a put aims for (m).
        lift_margin: how far beyond ``lift_height`` a lift raises the object (m).
        clearance: height (m) of the fingertips above the other objects when flying over
            them.
        damping: how many steps' worth of the gripper's last motion to subtract from the
            distance to a target (stops the arm overshooting).
        gain: proportional gain of moves (the arm covers only part of a small requested
            displacement in one step).

    The controller keeps per-episode state (see the module docstring): call :meth:`reset`
    at every environment reset, or let it restart by itself on a new ``s0``.
    """

    def __init__(
        self,
        thresholds: Thresholds | None = None,
        step_size: float = 0.05,
        finger_half_width: tuple[float, float] = (0.028, 0.016),
        standoff: float = 0.01,
        push_margin: float = 0.035,
        put_margin: float = 0.04,
        put_lateral: float = 0.05,
        lift_margin: float = 0.04,
        clearance: float = 0.035,
        damping: float = 1.0,
        gain: float = 2.0,
    ) -> None:
        self.thresholds = thresholds or Thresholds()
        self.step_size = step_size
        self.finger_half_width = np.asarray(finger_half_width, dtype=np.float64)
        self.standoff = standoff
        self.push_margin = push_margin
        self.put_margin = put_margin
        self.put_lateral = put_lateral
        self.lift_margin = lift_margin
        self.clearance = clearance
        self.damping = damping
        self.gain = gain
        self._captioner = RuleCaptioner(thresholds=self.thresholds)
        self._memory = _Memory()
        self._instruction: Instruction | None = None
        self._s0: SceneState | None = None  # held, so that a new episode's s0 is a new object

    # ------------------------------------------------------------------ public API

    def reset(self) -> None:
        """Forget the episode's phase (call at every env reset; also automatic on a new
        instruction or ``s0``)."""
        self._memory = _Memory()
        self._instruction = None
        self._s0 = None

    @property
    def phase(self) -> str:
        """The current phase of the phase machine (for logs and tests)."""
        return self._memory.phase

    def act(self, instruction: str | Instruction, s0: SceneState, s: SceneState) -> np.ndarray:
        """Action for the current scene.

        Args:
            instruction: an :class:`Instruction` or any sentence the grammar parses.
            s0: the scene at the start of the episode.
            s: the scene now.

        Returns:
            A float32 ``(4,)`` action in ``[-1, 1]``: ``dx, dy, dz`` and the gripper
            command. Zero motion with an open gripper when an object it names is missing.
        """
        ins = parse(instruction) if isinstance(instruction, str) else instruction
        if ins != self._instruction or s0 is not self._s0:
            self.reset()
            self._instruction, self._s0 = ins, s0
        i = s.index(*ins.obj)
        j = s.index(*ins.target) if ins.target is not None else 0
        if i < 0 or j < 0 or s0.index(*ins.obj) < 0:
            return np.array([0.0, 0.0, 0.0, OPEN], dtype=np.float32)
        mem = self._memory
        g = s.gripper
        mem.velocity = np.zeros(3) if mem.previous is None else g - mem.previous
        mem.previous = g.copy()
        if ins.family == "reach":
            a = self._reach(s, i)
        elif ins.family == "push":
            a = self._push(ins, s0, s, i, mem)
        else:
            a = self._grasp_family(ins, s0, s, i, j, mem)
        mem.steps += 1
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ helpers

    def _move(
        self, g: np.ndarray, target: np.ndarray, grip: float, speed: float = 1.0
    ) -> np.ndarray:
        """Damped proportional step towards ``target``, each axis limited to ``speed``.

        The arm keeps some momentum from one control step to the next; subtracting
        ``damping`` times the last step's motion stops it overshooting the target.
        """
        err = np.asarray(target) - g - self.damping * self._memory.velocity
        d = np.clip(self.gain * err / self.step_size, -speed, speed)
        return np.array([d[0], d[1], d[2], grip])

    def _hover_z(self, s: SceneState, skip: int = -1) -> float:
        """Grip-site height at which the fingertips clear every object (but ``skip``) by
        ``clearance``."""
        tops = s.positions[:, 2] + s.half_extents[:, 2]
        if skip >= 0:
            tops = np.delete(tops, skip)
        return float(tops.max(initial=s.table_height)) + self.clearance + 0.01

    def _fly(
        self, s: SceneState, target: np.ndarray, grip: float, hover: float | None = None
    ) -> np.ndarray:
        """Go to ``target`` via the hover height: up first, across, then down."""
        g = s.gripper
        hover = self._hover_z(s) if hover is None else hover
        xy_err = float(np.linalg.norm(target[:2] - g[:2]))
        if xy_err > 0.015:
            if g[2] < hover - 0.02:  # too low to cross: rise on the spot (slight drift ok)
                return self._move(g, np.array([g[0], g[1], hover]), grip)
            return self._move(g, np.array([target[0], target[1], max(hover, target[2])]), grip)
        return self._move(g, target, grip)

    # ------------------------------------------------------------------ reach

    def _reach(self, s: SceneState, i: int) -> np.ndarray:
        o = s.positions[i]
        top = o[2] + s.half_extents[i, 2]
        target = np.array([o[0], o[1], top + 0.012])
        return self._fly(s, target, CLOSE, hover=top + 0.05)

    # ------------------------------------------------------------------ push

    def _push_plan(
        self, ins: Instruction, s0: SceneState, s: SceneState, i: int
    ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, float, float, float]:
        """A push's geometry: the direction, X's half size, the bounds of X's centre on
        the table, the aimed progress, the progress so far and the fingers' height."""
        th = self.thresholds
        half = float(s.half_extents[i, :2].max())
        vec = np.asarray(DIRECTION_VECTORS[ins.direction], dtype=np.float64)
        start = s0.positions[i, :2]
        xmin, xmax, ymin, ymax = s.table_bounds
        lo = np.array([xmin, ymin]) + half
        hi = np.array([xmax, ymax]) - half
        # the farthest the table allows along the direction, capped at the aimed distance
        room = min(
            (hi - start)[k] / vec[k] if vec[k] > 0 else (lo - start)[k] / vec[k]
            for k in range(2)
            if vec[k] != 0
        )
        aim = min(th.push_distance + self.push_margin, max(room, th.push_distance + 0.005))
        progress = float((s.positions[i, :2] - start) @ vec)
        return vec, half, lo, hi, aim, progress, s.table_height + 0.018

    def _push(
        self, ins: Instruction, s0: SceneState, s: SceneState, i: int, mem: _Memory
    ) -> np.ndarray:
        th = self.thresholds
        g, o = s.gripper, s.positions[i]
        vec, half, lo, hi, aim, progress, push_z = self._push_plan(ins, s0, s, i)
        if progress >= aim - 0.003 and mem.phase != "done":
            mem.goto("done")
        if mem.phase == "done":
            if progress < th.push_distance + 0.005:  # slid back or was knocked: push again
                mem.goto("approach")
            else:
                return self._move(g, np.array([g[0], g[1], push_z + 0.06]), CLOSE, 0.5)
        if mem.phase == "approach" or mem.goal is None:
            # push along the direction, or up to 35 degrees off it where the fingers would
            # otherwise come down on another object; the goal keeps the aimed progress
            axis = self._push_axis(s, i, vec)
            remaining = max(aim - progress, 0.01) / float(axis @ vec)
            mem.goal = np.clip(o[:2] + axis * remaining, lo, hi)
        goal = mem.goal
        d = goal - o[:2]
        dist = float(np.linalg.norm(d))
        u = d / dist if dist > 1e-6 else vec
        perp = np.array([-u[1], u[0]])
        reach = float(np.abs(u) @ self.finger_half_width)  # fingers' half depth along u
        behind = o[:2] - u * (half + reach + self.standoff)
        rel = g[:2] - o[:2]
        along, lat = float(rel @ u), float(rel @ perp)
        if mem.phase == "approach":
            target = np.array([behind[0], behind[1], self._hover_z(s)])
            if float(np.linalg.norm(g[:2] - behind)) < 0.008:
                mem.goto("descend")
            else:
                return self._fly(s, target, CLOSE)
        if mem.phase == "descend":
            target = np.array([behind[0], behind[1], push_z])
            if abs(g[2] - push_z) < 0.006 or mem.steps > 20:
                mem.goto("push")
            else:
                return self._move(g, target, CLOSE)
        # push: move along u through the centre, steering the fingers back onto the line
        in_line = along < -(half + reach) + 0.02 and abs(lat) < 0.7 * half
        if not in_line or g[2] > push_z + 0.02:
            mem.lost += 1
            if mem.lost > 3:
                mem.goto("approach")
                return self._move(g, np.array([g[0], g[1], self._hover_z(s)]), CLOSE)
        else:
            mem.lost = 0
        speed = float(np.clip((dist + 0.02) / self.step_size, 0.2, 0.6))
        a_xy = u * speed - perp * np.clip(lat / self.step_size, -0.5, 0.5)
        a_z = np.clip((push_z - g[2]) / self.step_size, -1.0, 1.0)
        return np.array([a_xy[0], a_xy[1], a_z, CLOSE])

    def _push_axis(self, s: SceneState, i: int, vec: np.ndarray) -> np.ndarray:
        """The push direction nearest ``vec`` whose start spot is clear of other objects.

        The closed fingers come down ``standoff`` behind object ``i``; candidates are
        ``vec`` turned by 0, +-20, +-32 and +-40 degrees (a push within 45 degrees of the
        direction still counts). The first whose spot leaves 3 mm between the fingers and
        every other object wins; when none does, the one leaving the most room.
        """
        o = s.positions[i, :2]
        half = float(s.half_extents[i, :2].max())
        others = [k for k in range(len(s)) if k != i]
        best, best_room = vec, -np.inf
        for deg in (0.0, 20.0, -20.0, 32.0, -32.0, 40.0, -40.0):
            c, sn = np.cos(np.radians(deg)), np.sin(np.radians(deg))
            axis = np.array([c * vec[0] - sn * vec[1], sn * vec[0] + c * vec[1]])
            reach = float(np.abs(axis) @ self.finger_half_width)
            spot = o - axis * (half + reach + self.standoff)
            room = np.inf  # the fingers' box against each object's: the widest gap on x or y
            for k in others:
                gap = np.abs(spot - s.positions[k, :2]) - s.half_extents[k, :2]
                room = min(room, float(np.max(gap - self.finger_half_width)))
            if room >= 0.003:
                return axis
            if room > best_room + 1e-9:
                best, best_room = axis, room
        return best

    # ------------------------------------------------------------------ grasping families

    def _put_goal(
        self, ins: Instruction, s0: SceneState, s: SceneState, i: int, j: int
    ) -> np.ndarray:
        """Where a put leaves X's centre (xy): beside Y as it is now, on X's side of Y's
        axis as X was at the start."""
        th = self.thresholds
        vec = np.asarray(RELATION_VECTORS[ins.relation], dtype=np.float64)
        perp = np.array([-vec[1], vec[0]])
        b = s.positions[j, :2]
        lat0 = (s0.positions[i, :2] - s0.positions[j, :2]) @ perp
        lat = float(np.clip(lat0, -self.put_lateral, self.put_lateral))
        goal = b + vec * (th.relation_gap + self.put_margin) + perp * lat
        half = float(s.half_extents[i, :2].max())
        xmin, xmax, ymin, ymax = s.table_bounds
        return np.clip(goal, [xmin + half, ymin + half], [xmax - half, ymax - half])

    def _grasp_family(
        self,
        ins: Instruction,
        s0: SceneState,
        s: SceneState,
        i: int,
        j: int,
        mem: _Memory,
    ) -> np.ndarray:
        g, o = s.gripper, s.positions[i]
        held = bool(s.grasped[i]) if s.grasped is not None else False
        hover = self._hover_z(s, skip=i)
        if mem.phase == "approach":
            target = np.array([o[0], o[1], o[2] + 0.06])
            if float(np.linalg.norm(g[:2] - o[:2])) < 0.006 and g[2] < hover + 0.03:
                mem.goto("descend")
            else:
                return self._fly(s, target, OPEN, hover=max(hover, o[2] + 0.06))
        if mem.phase == "descend":
            target = o.copy()
            if abs(g[2] - o[2]) < 0.004 or mem.steps > 20:
                mem.goto("close")
            elif float(np.linalg.norm(g[:2] - o[:2])) > 0.02:
                mem.goto("approach")  # the object moved away (knocked): line up again
                return self._move(g, np.array([g[0], g[1], hover]), OPEN)
            else:
                return self._move(g, target, OPEN)
        if mem.phase == "close":
            if held:
                mem.lost -= 1
                if mem.lost <= -2:  # held for two steps in a row
                    mem.goto("carry")
            elif mem.steps > 12:  # the fingers closed on nothing: start over
                mem.goto("approach")
                return self._move(g, np.array([g[0], g[1], hover]), OPEN)
            else:
                mem.lost = 0
            if mem.phase == "close":
                return self._move(g, o, CLOSE, 0.3)
        if mem.phase in ("carry", "lower"):
            if not held:
                mem.lost += 1
                if mem.lost > 3:  # dropped: start over
                    mem.goto("approach")
                    return self._move(g, np.array([g[0], g[1], hover]), OPEN)
            else:
                mem.lost = 0
        if ins.family == "lift":
            rise = self.thresholds.lift_height + self.lift_margin
            target_o = np.array([s0.positions[i, 0], s0.positions[i, 1], s0.positions[i, 2] + rise])
            target_o[:2] = o[:2]  # straight up from where it is held
            return self._move(g, g + (target_o - o), CLOSE)
        # put / stack: carry above everything, then lower at the drop point
        if ins.family == "stack":
            dest = s.positions[j].copy()
            dest[2] += s.half_extents[j, 2] + s.half_extents[i, 2] + 0.004
        else:
            dest = np.append(self._put_goal(ins, s0, s, i, j), s.table_height)
            dest[2] += s.half_extents[i, 2] + 0.004
        carry_z = hover + (o[2] - g[2]) + s.half_extents[i, 2]  # X's bottom at the hover level
        if mem.phase == "carry":
            xy_err = float(np.linalg.norm(dest[:2] - o[:2]))
            if o[2] < carry_z - 0.015 and xy_err > 0.01:
                target_o = np.array([o[0], o[1], carry_z])  # up first
            else:
                target_o = np.array([dest[0], dest[1], carry_z])
            if xy_err < 0.004:
                mem.goto("lower")
            else:
                return self._move(g, g + (target_o - o), CLOSE)
        if mem.phase == "lower":
            xy_err = float(np.linalg.norm(dest[:2] - o[:2]))
            if o[2] - dest[2] < 0.003 or mem.steps > 25:
                if xy_err < 0.008:
                    mem.goto("release")
                elif mem.steps > 25:
                    mem.goto("carry")
            if mem.phase == "lower":
                target_o = dest if xy_err < 0.01 else np.array([dest[0], dest[1], o[2]])
                return self._move(g, g + (target_o - o), CLOSE, 0.5)
        if mem.phase == "release":
            if mem.steps >= 5:
                mem.goto("retreat")
            else:
                return np.array([0.0, 0.0, 0.0, OPEN])
        # retreat: back off upwards; start over if the object is not where it should be
        if mem.steps > 10 and not self._captioner.satisfied(ins, s0, s):
            mem.goto("approach")
        return self._move(g, np.array([g[0], g[1], hover + 0.03]), OPEN)


class MarkovController3D(ScriptedController3D):
    """The scripted strategies as a function of the scene alone: no phase machine, no
    counters, no damping by the last motion.

    :class:`ScriptedController3D` decides when to close, carry, lower or release from its
    phase and step counters, and damps moves by the gripper's last motion; a policy that
    sees only the current state cannot imitate those decisions. This controller reads the
    phase off the scene each step (what is held, where the gripper is against the object
    and the drop point), so it labels any state the same way whatever led there: the
    teacher for DAgger (``lcrl distill --teacher-for FAMILY=scripted``).

    Rules per family (the geometry of :class:`ScriptedController3D`):

    * reach: as there (already a function of the scene);
    * push: with an object in the fingers, open and rise; otherwise approach behind X at
      hover height, come down there, then push through X's centre while the fingers are
      in line with it, and approach again when they are not;
    * lift / put / stack, X not held: approach above X with open fingers, come down when
      lined up, close when at X's height; when X rests at the drop point (put, stack),
      open and rise instead of grasping it again;
    * X held: lift raises it; put and stack carry it above the others to the drop point,
      lower it there, and open when it rests there.

    Failures need no counters: a knocked or dropped object is no longer lined up, and the
    approach starts again.
    """

    def __init__(self, *args: Any, funnel: float = 0.0, **kwargs: Any) -> None:
        kwargs["damping"] = 0.0
        super().__init__(*args, **kwargs)
        self.funnel = float(funnel)

    def act(self, instruction: str | Instruction, s0: SceneState, s: SceneState) -> np.ndarray:
        """Action for the current scene (see :meth:`ScriptedController3D.act`), from the
        scene alone."""
        ins = parse(instruction) if isinstance(instruction, str) else instruction
        self._memory = _Memory()  # nothing carries over from one step to the next
        i = s.index(*ins.obj)
        j = s.index(*ins.target) if ins.target is not None else 0
        if i < 0 or j < 0 or s0.index(*ins.obj) < 0:
            return np.array([0.0, 0.0, 0.0, OPEN], dtype=np.float32)
        if ins.family == "reach":
            a = self._reach(s, i)
        elif ins.family == "push":
            a = self._push_now(ins, s0, s, i)
        else:
            a = self._grasp_now(ins, s0, s, i, j)
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def _push_now(self, ins: Instruction, s0: SceneState, s: SceneState, i: int) -> np.ndarray:
        g, o = s.gripper, s.positions[i]
        if s.grasped is not None and bool(np.any(s.grasped)):  # let go of what is held
            return np.array([0.0, 0.0, 0.5, OPEN])
        vec, half, lo, hi, aim, progress, push_z = self._push_plan(ins, s0, s, i)
        axis = self._push_axis(s, i, vec)
        remaining = max(aim - progress, 0.01) / float(axis @ vec)
        goal = np.clip(o[:2] + axis * remaining, lo, hi)
        d = goal - o[:2]
        dist = float(np.linalg.norm(d))
        u = d / dist if dist > 1e-6 else vec
        perp = np.array([-u[1], u[0]])
        reach = float(np.abs(u) @ self.finger_half_width)
        behind = o[:2] - u * (half + reach + self.standoff)
        rel = g[:2] - o[:2]
        along, lat = float(rel @ u), float(rel @ perp)
        in_line = along < -(half + reach) + 0.02 and abs(lat) < 0.7 * half
        if in_line and g[2] <= push_z + 0.02 and along > -(half + reach + 0.04):
            speed = float(np.clip((dist + 0.02) / self.step_size, 0.2, 0.6))
            a_xy = u * speed - perp * np.clip(lat / self.step_size, -0.5, 0.5)
            a_z = np.clip((push_z - g[2]) / self.step_size, -1.0, 1.0)
            return np.array([a_xy[0], a_xy[1], a_z, CLOSE])
        if float(np.linalg.norm(g[:2] - behind)) < 0.012:  # lined up behind X: come down
            return self._move(g, np.array([behind[0], behind[1], push_z]), CLOSE)
        return self._fly(s, np.array([behind[0], behind[1], self._hover_z(s)]), CLOSE)

    def _drop_point(
        self, ins: Instruction, s0: SceneState, s: SceneState, i: int, j: int
    ) -> np.ndarray:
        """Where put and stack leave X's centre."""
        if ins.family == "stack":
            dest = s.positions[j].copy()
            dest[2] += s.half_extents[j, 2] + s.half_extents[i, 2] + 0.004
            return dest
        dest = np.append(self._put_goal(ins, s0, s, i, j), s.table_height)
        dest[2] += s.half_extents[i, 2] + 0.004
        return dest

    def _grasp_now(
        self, ins: Instruction, s0: SceneState, s: SceneState, i: int, j: int
    ) -> np.ndarray:
        g, o = s.gripper, s.positions[i]
        held = bool(s.grasped[i]) if s.grasped is not None else False
        hover = self._hover_z(s, skip=i)
        dest = self._drop_point(ins, s0, s, i, j) if ins.family != "lift" else None
        xy_err = float(np.linalg.norm(dest[:2] - o[:2])) if dest is not None else np.inf
        release = 0.012 if self.funnel > 0 else 0.008  # how near the drop point X is let go
        if not held:
            if dest is not None and xy_err < release + 0.002 and o[2] - dest[2] < 0.006:
                return self._move(g, np.array([g[0], g[1], hover + 0.03]), OPEN)  # let go
            xy = float(np.linalg.norm(g[:2] - o[:2]))
            if xy < 0.008 and abs(g[2] - o[2]) < 0.006:
                return self._move(g, o, CLOSE, 0.3)  # at X: close
            if xy < 0.012 and g[2] < o[2] + 0.07:
                return self._move(g, o, OPEN)  # lined up above X: come down
            return self._fly(s, np.array([o[0], o[1], o[2] + 0.06]), OPEN, max(hover, o[2] + 0.06))
        if dest is None:  # lift: straight up from where it is held
            rise = self.thresholds.lift_height + self.lift_margin
            target_o = np.array([o[0], o[1], s0.positions[i, 2] + rise])
            return self._move(g, g + (target_o - o), CLOSE)
        carry_z = hover + (o[2] - g[2]) + s.half_extents[i, 2]
        if self.funnel > 0:
            return self._funnel(g, o, dest, xy_err, carry_z, release)
        if xy_err < 0.008:
            if o[2] - dest[2] < 0.003:
                return np.array([0.0, 0.0, 0.0, OPEN])  # resting at the drop point: release
            target_o = dest if xy_err < 0.006 else np.array([dest[0], dest[1], o[2]])
            return self._move(g, g + (target_o - o), CLOSE, 0.5)  # lower
        if o[2] < carry_z - 0.015 and xy_err > 0.01:
            target_o = np.array([o[0], o[1], carry_z])  # up first
        else:
            target_o = np.array([dest[0], dest[1], carry_z])
        return self._move(g, g + (target_o - o), CLOSE)

    def _funnel(
        self,
        g: np.ndarray,
        o: np.ndarray,
        dest: np.ndarray,
        xy_err: float,
        carry_z: float,
        release: float,
    ) -> np.ndarray:
        """Carry X to the drop point along a funnel: the height aimed for falls from the
        carry height to the drop height as X's centre closes the last ``funnel`` metres,
        so every label is a smooth function of the distance left (no threshold to cross
        before X is lowered); X is let go once it rests within ``release`` of the point."""
        if xy_err < release and o[2] - dest[2] < 0.004:
            return np.array([0.0, 0.0, 0.0, OPEN])  # resting at the drop point: release
        if o[2] < carry_z - 0.015 and xy_err > self.funnel + release:
            return self._move(g, g + (np.array([o[0], o[1], carry_z]) - o), CLOSE)  # up first
        frac = float(np.clip((xy_err - 0.5 * release) / self.funnel, 0.0, 1.0))
        z = dest[2] + frac * max(carry_z - dest[2], 0.0)
        target_o = np.array([dest[0], dest[1], z])
        return self._move(g, g + (target_o - o), CLOSE, 0.5 + 0.5 * frac)


def evaluate(
    families: Sequence[str] = FAMILIES,
    seeds: Iterable[int] = range(20),
    max_steps: int = 100,
    markov: bool = False,
    funnel: float = 0.0,
    **env_kwargs: Any,
) -> dict[str, dict[int, int | None]]:
    """Run the scripted controller (``markov``: :class:`MarkovController3D`) on
    language-goal episodes of the robosuite tabletop.

    Each family gets its own :class:`~captioner.lang_env.LanguageGoalWrapper` (instructions
    of that family only, sampled by the wrapper from the train set of split 0) around one
    shared :class:`~envs.robosuite_tabletop.RobosuiteTabletopEnv`.

    Args:
        families: the instruction families to run.
        seeds: the reset seeds (one episode each, per family).
        max_steps: steps before an episode counts as failed.
        markov: run the controller that reads everything off the scene.
        **env_kwargs: passed to the environment.

    Returns:
        ``{family: {seed: steps to success, or None on failure}}``.
    """
    from captioner.lang_env import LanguageGoalWrapper
    from envs.robosuite_tabletop import RobosuiteTabletopEnv

    env = RobosuiteTabletopEnv(**env_kwargs)
    controller = MarkovController3D(funnel=funnel) if markov else ScriptedController3D()
    out: dict[str, dict[int, int | None]] = {}
    try:
        for family in families:
            wrapped = LanguageGoalWrapper(env, families=(family,))
            out[family] = {}
            for seed in seeds:
                wrapped.reset(seed=seed)
                controller.reset()
                steps = None
                for t in range(max_steps):
                    action = controller.act(wrapped.meaning, wrapped.s0, env.scene())
                    _, _, _, truncated, info = wrapped.step(action)
                    if info["is_success"]:
                        steps = t + 1
                        break
                    if truncated:
                        break
                out[family][seed] = steps
    finally:
        env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the scripted controller's success rate per family (``python -m
    captioner.scripted3d``)."""
    parser = argparse.ArgumentParser(description=main.__doc__.split("(")[0].strip())
    parser.add_argument("--episodes", type=int, default=20, help="seeds 0 .. N-1 per family")
    parser.add_argument("--max-steps", type=int, default=100)
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    parser.add_argument("--num-objects", type=int, default=None, help="default: 2 to 4")
    parser.add_argument("--controller-period", type=int, default=5)
    parser.add_argument(
        "--markov", action="store_true", help="the controller without memory (a DAgger teacher)"
    )
    parser.add_argument(
        "--funnel", type=float, default=0.0, help="with --markov: the drop funnel's width (m)"
    )
    args = parser.parse_args(argv)
    env_kwargs: dict[str, Any] = {"controller_period": args.controller_period}
    if args.num_objects is not None:
        env_kwargs["num_objects"] = args.num_objects
    print(f"{'family':8s} {'success':>9s} {'steps: median':>14s} {'max':>5s}")
    for family in args.families:
        steps = evaluate(
            [family], range(args.episodes), args.max_steps, args.markov, args.funnel, **env_kwargs
        )[family]
        done = [n for n in steps.values() if n is not None]
        rate = len(done) / max(len(steps), 1)
        median = f"{float(np.median(done)):.0f}" if done else "-"
        print(
            f"{family:8s} {rate:9.0%} {median:>14s} {max(done, default=0):5d}"
            + (
                ""
                if rate == 1
                else f"   failed seeds: {[k for k, n in steps.items() if n is None]}"
            ),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

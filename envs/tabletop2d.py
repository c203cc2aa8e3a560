"""A fast, pure-numpy tabletop pushing environment in the spirit of Language Table.

A circular pusher and 2 to 4 objects share a square table. Everything is in the
*viewer frame* of :mod:`envs.scene`: metres, ``x`` to the viewer's right, ``y`` away from
the viewer ("forward"), ``z`` up, table surface at ``z = 0``.

Geometry:
    * table: ``x, y`` in ``[-0.25, 0.25]``;
    * pusher: disc of radius ``0.015``;
    * ``"cube"``: axis-aligned square of half size ``0.025`` (it never rotates);
    * ``"cylinder"``: disc of radius ``0.025``.

Within one scene every (colour, shape) kind of :data:`envs.scene.OBJECT_KINDS` appears at
most once, so "the red cube" always names one object.

Physics (position based, deterministic, no noise). One step:
    1. The pusher moves by the action (``max_step = 0.02`` m per unit of action) and is
       clamped so that it stays entirely on the table.
    2. For each object the pusher penetrates, the object is pushed out along the
       separating direction (pusher vs cube: circle vs axis-aligned box using the closest
       point of the box, or the axis of least penetration when the pusher's centre is
       inside the box; pusher vs cylinder: circle vs circle).
    3. Object-object overlaps are relaxed pairwise (cube vs cube: least-penetration axis;
       cube vs cylinder: circle vs box; cylinder vs cylinder: circle vs circle), splitting
       the correction between the two objects; an object that a table edge stops passes
       the rest of the correction to the other one. Objects are clamped to stay entirely on
       the table. Up to 4 relaxation passes are made, stopping early when nothing overlaps.
    4. Whatever the pusher still penetrates (an object blocked by an edge or by other
       objects) pushes the pusher back out: the pusher cannot move through objects. If
       that moves the pusher into another object, steps 2 to 4 repeat (at most 4 times).

A step moves the pusher by at most ``0.02 * sqrt(2)`` m, below the pusher + object
contact distance (0.04 m), so nothing tunnels.

Observation (a :class:`gymnasium.spaces.Dict`):
    * ``"observation"``: float32, 26 values: pusher ``x, y``, then for each of the 8 kinds
      in :data:`~envs.scene.OBJECT_KINDS` order a slot ``[x, y, present]``; absent kinds
      are all zeros. Slot ``k`` (kind ``OBJECT_KINDS[k]``) is at ``2 + 3 k``.
    * ``"achieved_goal"`` / ``"desired_goal"``: float32.

      - ``goal="object"`` (default): 16 values, the ``x, y`` of every kind slot (absent
        kinds are 0). The desired goal is the reset layout with one randomly chosen object
        moved to a random free spot at least 0.08 m from where it started. Success: every
        slot within ``distance_threshold = 0.03`` m of its target.
      - ``goal="pusher"``: 2 values, the pusher's ``x, y``; the desired goal is a random
        point of the table. Success: within 0.03 m of it.
    * ``"image"`` (only with ``image=True``): uint8 ``(image_size, image_size, 3)``
      top-down RGB render; image up is ``+y`` (away from the viewer), image right is ``+x``.

Reward is 1.0 on success and 0.0 otherwise (see :meth:`Tabletop2DEnv.compute_reward`);
``terminated`` is always False; the registered ids truncate after 50 steps.

Speed: the physics uses plain Python floats (at most 4 objects, so a loop of float
arithmetic is much cheaper than many small numpy calls), observations are built from
Python lists in one ``np.array`` call each, and :class:`~envs.scene.SceneState` is only
built when :meth:`Tabletop2DEnv.scene` is called.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs.layout import check_num_objects, check_objects, sample_points
from envs.scene import COLOURS, OBJECT_KINDS, SceneState
from lcrl.errors import LcrlError

__all__ = [
    "DISTANCE_THRESHOLD",
    "MAX_STEP",
    "OBJECT_HALF_SIZE",
    "PUSHER_RADIUS",
    "TABLE_HALF_SIZE",
    "Tabletop2DConfigError",
    "Tabletop2DEnv",
]

#: Half the side of the square table (m); the table spans ``[-0.25, 0.25]`` in x and y.
TABLE_HALF_SIZE = 0.25
#: Pusher radius (m).
PUSHER_RADIUS = 0.015
#: Half size of a cube and radius of a cylinder (m); also the objects' half height.
OBJECT_HALF_SIZE = 0.025
#: Pusher displacement (m) per unit of action.
MAX_STEP = 0.02
#: Distance (m) under which a goal slot counts as reached.
DISTANCE_THRESHOLD = 0.03
#: Height (m) of the pusher's centre reported by :meth:`Tabletop2DEnv.scene`.
PUSHER_HEIGHT = 0.01

_NUM_KINDS = len(OBJECT_KINDS)
_OBS_DIM = 2 + 3 * _NUM_KINDS
_GOAL_DIM_OBJECT = 2 * _NUM_KINDS
_MIN_OBJECTS, _MAX_OBJECTS = 2, 4

_R = PUSHER_RADIUS
_H = OBJECT_HALF_SIZE
_PUSHER_LIMIT = TABLE_HALF_SIZE - PUSHER_RADIUS  # pusher centre stays in [-lim, lim]
_OBJECT_LIMIT = TABLE_HALF_SIZE - OBJECT_HALF_SIZE  # object centre stays in [-lim, lim]
_CONTACT = _R + _H  # pusher-object centre distance at contact along an axis
_TOUCH_TOLERANCE = 1e-3

# Sampling of layouts and goals.
# Object centres and object goals are drawn in [-0.18, 0.18]^2: far enough from the edge
# for the pusher (limit 0.235) to get behind an object (0.18 + 0.04 + margin) and push it
# in any direction.
_SPAWN_LIMIT = 0.18
_PUSHER_SPAWN_LIMIT = 0.22
_MIN_OBJECT_GAP = 0.08  # centre distance: > 2 * 0.025 * sqrt(2) (cube corners) + margin
_MIN_PUSHER_GAP = 0.06  # centre distance: > 0.015 + 0.025 * sqrt(2) + margin
_MIN_GOAL_MOVE = 0.08

_THRESHOLD_SQ = DISTANCE_THRESHOLD * DISTANCE_THRESHOLD
_CONTACT_ITERATIONS = 4  # push objects / relax / push the pusher back
_RELAXATION_PASSES = 4  # object-object passes per iteration (stop early when clear)

_TABLE_RGB = (214, 204, 186)
_PUSHER_RGB = (64, 64, 64)
_RENDER_SHIFT = 4  # cv2 fixed-point bits: 1/16 pixel accuracy
_RENDER_SCALE = 1 << _RENDER_SHIFT

_ACTION_TYPES = ("continuous", "discrete")
_GOALS = ("object", "pusher")
_NUM_DIRECTIONS = (4, 8)
_IMAGE_SIZE_RANGE = (16, 1024)


class Tabletop2DConfigError(LcrlError, ValueError):
    """A bad :class:`Tabletop2DEnv` constructor argument (also a :class:`ValueError`)."""


class _UnitBox(spaces.Box):
    """``Box(-1, 1, (2,), float32)`` whose :meth:`sample` is about 15 times faster.

    ``gymnasium.spaces.Box.sample`` spends ~35 microseconds on masks for unbounded
    coordinates, longer than a whole environment step. This draws the same numbers from
    the same generator (``uniform(-1, 1)`` cast to float32), so seeded samples are
    identical to a plain ``Box``'s.
    """

    def __init__(self) -> None:
        super().__init__(-1.0, 1.0, (2,), np.float32)

    def sample(self, mask: None = None, probability: None = None) -> np.ndarray:
        """A uniform sample of the box (``mask`` / ``probability`` are unsupported)."""
        if mask is not None or probability is not None:
            return super().sample(mask, probability)  # raises gymnasium's error
        return self.np_random.uniform(-1.0, 1.0, (2,)).astype(np.float32)


def _bad(name: str, value: Any, allowed: str) -> Tabletop2DConfigError:
    return Tabletop2DConfigError(f"Tabletop2DEnv: bad {name}={value!r}; {allowed}")


def _points(
    count: int,
    existing: list[tuple[float, float]],
    min_gap: float,
    limit: float,
    rng: np.random.Generator,
) -> list[tuple[float, float]]:
    """Non-overlapping points of ``[-limit, limit]^2`` (see :func:`envs.layout.sample_points`)."""
    return sample_points(count, existing, min_gap, limit, limit, rng, "Tabletop2DEnv")


def _clamp(v: float, lim: float) -> float:
    return -lim if v < -lim else (lim if v > lim else v)


def _circle_box(dx: float, dy: float, r: float) -> tuple[float, float]:
    """Separation of a circle and an axis-aligned square of half size ``_H``.

    Args:
        dx: box centre minus circle centre, x.
        dy: box centre minus circle centre, y.
        r: circle radius.

    Returns:
        The displacement to apply to the box (or minus it to the circle) so that they no
        longer overlap; ``(0.0, 0.0)`` when they do not overlap.
    """
    ax = dx if dx >= 0.0 else -dx
    ay = dy if dy >= 0.0 else -dy
    reach = _H + r
    if ax >= reach or ay >= reach:
        return 0.0, 0.0
    if ax > _H:
        if ay > _H:  # corner region: closest point is a corner
            cx = ax - _H
            cy = ay - _H
            d2 = cx * cx + cy * cy
            if d2 >= r * r:
                return 0.0, 0.0
            d = math.sqrt(d2)
            pen = (r - d) / d
            return math.copysign(cx * pen, dx), math.copysign(cy * pen, dy)
        return math.copysign(reach - ax, dx), 0.0  # x face
    if ay > _H:
        return 0.0, math.copysign(reach - ay, dy)  # y face
    # Circle centre inside the box: leave along the axis of least penetration.
    px = reach - ax
    py = reach - ay
    if px <= py:
        return math.copysign(px, dx), 0.0
    return 0.0, math.copysign(py, dy)


def _circle_circle(dx: float, dy: float, reach: float) -> tuple[float, float]:
    """Displacement of circle 2 (``dx, dy`` from circle 1) so the circles stop overlapping."""
    d2 = dx * dx + dy * dy
    if d2 >= reach * reach:
        return 0.0, 0.0
    if d2 <= 1e-24:
        return reach, 0.0
    d = math.sqrt(d2)
    pen = (reach - d) / d
    return dx * pen, dy * pen


def _box_box(dx: float, dy: float) -> tuple[float, float]:
    """Displacement of square 2 (``dx, dy`` from square 1) along the least-overlap axis."""
    reach = 2.0 * _H
    ax = dx if dx >= 0.0 else -dx
    ay = dy if dy >= 0.0 else -dy
    if ax >= reach or ay >= reach:
        return 0.0, 0.0
    px = reach - ax
    py = reach - ay
    if px <= py:
        return math.copysign(px, dx), 0.0
    return 0.0, math.copysign(py, dy)


def _pusher_overlap(dx: float, dy: float, cube: bool) -> tuple[float, float]:
    """Displacement of an object (``dx, dy`` from the pusher) that takes it out of the pusher."""
    if cube:
        return _circle_box(dx, dy, _R)
    return _circle_circle(dx, dy, _CONTACT)


def _object_separation(dx: float, dy: float, a_cube: bool, b_cube: bool) -> tuple[float, float]:
    """Displacement of object b (``dx, dy`` from object a) that removes their overlap."""
    if a_cube:
        if b_cube:
            return _box_box(dx, dy)
        mx, my = _circle_box(-dx, -dy, _H)  # moves box a away from disc b
        return -mx, -my
    if b_cube:
        return _circle_box(dx, dy, _H)
    return _circle_circle(dx, dy, 2.0 * _H)


class Tabletop2DEnv(gym.Env):
    """Pusher-and-objects tabletop with a goal-conditioned dict observation.

    See the module docstring for the physics and the observation layout.

    Args:
        num_objects: number of objects, or an inclusive ``(low, high)`` range sampled at
            every reset; between 2 and 4.
        objects: the ``(colour, shape)`` kinds that may appear (default: all 8 of
            :data:`~envs.scene.OBJECT_KINDS`); at least as many as the largest object count.
        action_type: ``"continuous"`` (``Box(-1, 1, (2,))``, a displacement of
            ``max_step * action`` metres) or ``"discrete"`` (``Discrete(1 + num_directions)``:
            0 stays, ``k >= 1`` moves ``max_step`` metres at angle
            ``2 pi (k - 1) / num_directions`` counter-clockwise from ``+x``).
        num_directions: 4 or 8; only used by the discrete action type.
        goal: ``"object"`` (rearrange one object) or ``"pusher"`` (reach a point).
        image: add an ``"image"`` entry (top-down RGB render) to the observation.
        image_size: side of rendered images in pixels (16 to 1024).
        render_mode: ``None`` or ``"rgb_array"``.

    Raises:
        ValueError: (a :class:`Tabletop2DConfigError`) for any bad argument, naming it.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    #: Pusher displacement (m) per unit of action.
    max_step: float = MAX_STEP
    #: Goal distance threshold (m).
    distance_threshold: float = DISTANCE_THRESHOLD
    #: Pusher radius (m).
    pusher_radius: float = PUSHER_RADIUS
    #: Half size of a cube / radius of a cylinder (m).
    object_half_size: float = OBJECT_HALF_SIZE
    #: ``(xmin, xmax, ymin, ymax)`` of the table (m).
    table_bounds: tuple[float, float, float, float] = (
        -TABLE_HALF_SIZE,
        TABLE_HALF_SIZE,
        -TABLE_HALF_SIZE,
        TABLE_HALF_SIZE,
    )

    #: Instruction families this env can achieve (a pusher cannot lift or stack).
    instruction_families: tuple[str, ...] = ("reach", "push", "put")
    #: The first values of ``"observation"`` that describe the agent itself (pusher x, y).
    proprio_dim: int = 2
    #: ``(start, count, width)`` of the object slots in ``"observation"``.
    slot_layout: tuple[int, int, int] = (2, 8, 3)
    #: Position values at the front of the agent's values and of every slot.
    position_dims: int = 2

    def __init__(
        self,
        num_objects: int | tuple[int, int] = (2, 4),
        objects: Sequence[tuple[str, str]] | None = None,
        action_type: str = "continuous",
        num_directions: int = 4,
        goal: str = "object",
        image: bool = False,
        image_size: int = 64,
        render_mode: str | None = None,
    ) -> None:
        self._count_range = check_num_objects(num_objects, _MIN_OBJECTS, _MAX_OBJECTS, _bad)
        self._allowed_slots = check_objects(objects, self._count_range[1], _bad)
        if action_type not in _ACTION_TYPES:
            raise _bad("action_type", action_type, f"expected one of {list(_ACTION_TYPES)}")
        if isinstance(num_directions, bool) or num_directions not in _NUM_DIRECTIONS:
            raise _bad("num_directions", num_directions, f"expected one of {_NUM_DIRECTIONS}")
        if goal not in _GOALS:
            raise _bad("goal", goal, f"expected one of {list(_GOALS)}")
        if not isinstance(image, (bool, np.bool_)):
            raise _bad("image", image, "expected a bool")
        lo, hi = _IMAGE_SIZE_RANGE
        if (
            isinstance(image_size, bool)
            or not isinstance(image_size, (int, np.integer))
            or not lo <= image_size <= hi
        ):
            raise _bad("image_size", image_size, f"expected an int in [{lo}, {hi}]")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise _bad(
                "render_mode",
                render_mode,
                f"expected None or one of {self.metadata['render_modes']}",
            )

        self.num_objects = num_objects
        self.objects = tuple(OBJECT_KINDS[k] for k in self._allowed_slots)
        self.action_type = action_type
        self.num_directions = int(num_directions)
        self.goal = goal
        self.image = bool(image)
        self.image_size = int(image_size)
        self.render_mode = render_mode

        self._discrete = action_type == "discrete"
        self._object_goal = goal == "object"
        if self._discrete:
            self.action_space: spaces.Space[Any] = spaces.Discrete(1 + self.num_directions)
            self._moves = [(0.0, 0.0)]
            for k in range(self.num_directions):
                angle = 2.0 * math.pi * k / self.num_directions
                # Snap cos/sin to exact 0 / +-1 where they should be.
                self._moves.append(
                    (MAX_STEP * round(math.cos(angle), 12), MAX_STEP * round(math.sin(angle), 12))
                )
        else:
            self.action_space = _UnitBox()
            self._moves = []

        t = np.float32(TABLE_HALF_SIZE)
        obs_low = np.zeros(_OBS_DIM, np.float32)
        obs_high = np.zeros(_OBS_DIM, np.float32)
        obs_low[:2], obs_high[:2] = -t, t
        for k in range(_NUM_KINDS):
            s = 2 + 3 * k
            obs_low[s : s + 2], obs_high[s : s + 2] = -t, t
            obs_high[s + 2] = 1.0
        goal_dim = _GOAL_DIM_OBJECT if self._object_goal else 2
        goal_space = spaces.Box(-t, t, (goal_dim,), np.float32)
        obs_spaces: dict[str, spaces.Space[Any]] = {
            "observation": spaces.Box(obs_low, obs_high, dtype=np.float32),
            "achieved_goal": goal_space,
            "desired_goal": goal_space,
        }
        if self.image:
            obs_spaces["image"] = spaces.Box(
                0, 255, (self.image_size, self.image_size, 3), np.uint8
            )
        self.observation_space: spaces.Space[Any] = spaces.Dict(obs_spaces)

        # Rendering: preallocated table background and fixed-point coordinate transform.
        self._background = np.empty((self.image_size, self.image_size, 3), np.uint8)
        self._background[:] = _TABLE_RGB
        self._px_per_m = self.image_size / (2.0 * TABLE_HALF_SIZE)
        self._colour_of_slot = [COLOURS[c] for c, _ in OBJECT_KINDS]

        # State (filled in by reset). Plain Python floats / lists for speed.
        self._px = 0.0
        self._py = 0.0
        self._ox: list[float] = []
        self._oy: list[float] = []
        self._cube: list[bool] = []
        self._slots: list[int] = []
        self._n = 0
        self._obs_template: list[float] = [0.0] * _OBS_DIM
        self._goal_template: list[float] = [0.0] * _GOAL_DIM_OBJECT
        self._desired = np.zeros(goal_dim, np.float32)
        self._desired_list: list[float] = [0.0] * goal_dim
        self._has_reset = False

    # ------------------------------------------------------------------ gym API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Sample a new layout (and goal) from ``self.np_random``.

        Args:
            seed: seed for the environment's random generator.
            options: unused.

        Returns:
            ``(observation, info)`` with ``info = {"is_success": bool}``.
        """
        super().reset(seed=seed)
        rng = self.np_random
        lo, hi = self._count_range
        n = lo if lo == hi else int(rng.integers(lo, hi + 1))
        order = rng.permutation(len(self._allowed_slots))[:n].tolist()
        slots = sorted(self._allowed_slots[i] for i in order)

        points = _points(n, [], _MIN_OBJECT_GAP, _SPAWN_LIMIT, rng)
        self._n = n
        self._slots = slots
        self._cube = [OBJECT_KINDS[s][1] == "cube" for s in slots]
        self._ox = [p[0] for p in points]
        self._oy = [p[1] for p in points]
        (pusher,) = _points(1, points, _MIN_PUSHER_GAP, _PUSHER_SPAWN_LIMIT, rng)
        self._px, self._py = pusher

        template = [0.0] * _OBS_DIM
        for s in slots:
            template[4 + 3 * s] = 1.0
        self._obs_template = template

        if self._object_goal:
            mover = int(rng.integers(n))
            # Keeping the target away from every current centre, the mover's included,
            # leaves room for the mover and makes it move at least _MIN_GOAL_MOVE.
            (target,) = _points(1, points, max(_MIN_OBJECT_GAP, _MIN_GOAL_MOVE), _SPAWN_LIMIT, rng)
            desired = [0.0] * _GOAL_DIM_OBJECT
            for i, s in enumerate(slots):
                x, y = target if i == mover else points[i]
                desired[2 * s] = x
                desired[2 * s + 1] = y
        else:
            # Any point of the table the pusher can reach, not already (nearly) reached.
            desired = list(_points(1, [pusher], 2.0 * DISTANCE_THRESHOLD, _PUSHER_LIMIT, rng)[0])
        self._desired = np.array(desired, np.float32)
        self._desired_list = self._desired.tolist()  # float32-exact, as compute_reward sees it
        self._has_reset = True
        obs, success = self._observe()
        return obs, {"is_success": success}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Move the pusher, resolve contacts, and observe.

        Args:
            action: a ``(2,)`` array in ``[-1, 1]`` (continuous; values outside are
                clipped) or an int in ``[0, num_directions]`` (discrete).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; reward is 1.0 on success
            and 0.0 otherwise, ``terminated`` and ``truncated`` are False, and
            ``info = {"is_success": bool}``.
        """
        if not self._has_reset:
            raise RuntimeError("Tabletop2DEnv.step() called before reset()")
        if self._discrete:
            a = _discrete_action(action)
            if not 0 <= a <= self.num_directions:
                raise ValueError(
                    f"discrete action {action!r} is outside [0, {self.num_directions}]"
                )
            dx, dy = self._moves[a]
        else:
            try:
                ax, ay = action.tolist()
            except (AttributeError, ValueError, TypeError):
                ax, ay = np.asarray(action, dtype=np.float64).reshape(2).tolist()
            if not (-1.0 <= ax <= 1.0):
                ax = _clip_action(ax)
            if not (-1.0 <= ay <= 1.0):
                ay = _clip_action(ay)
            dx = ax * MAX_STEP
            dy = ay * MAX_STEP
        self._physics(dx, dy)
        obs, success = self._observe()
        return obs, 1.0 if success else 0.0, False, False, {"is_success": success}

    def compute_reward(
        self, achieved_goal: Any, desired_goal: Any, info: Any = None
    ) -> float | np.ndarray:
        """Goal reward, vectorised over any leading batch dimensions.

        Args:
            achieved_goal: ``(..., goal_dim)`` achieved goals.
            desired_goal: ``(..., goal_dim)`` desired goals.
            info: ignored (kept for the gymnasium-robotics ``GoalEnv`` signature).

        Returns:
            1.0 where every goal slot is within ``distance_threshold`` and 0.0 elsewhere:
            a float for single goals, a float32 array of the batch shape otherwise.
        """
        diff = np.asarray(achieved_goal, dtype=np.float64) - np.asarray(
            desired_goal, dtype=np.float64
        )
        if diff.shape[-1:] != self._desired.shape:
            raise ValueError(
                f"goals must have a last dimension of {self._desired.shape[0]}, got {diff.shape}"
            )
        pairs = diff.reshape(*diff.shape[:-1], -1, 2)
        dist_sq = pairs[..., 0] * pairs[..., 0] + pairs[..., 1] * pairs[..., 1]
        success = np.all(dist_sq <= _THRESHOLD_SQ, axis=-1)
        if success.ndim == 0:
            return 1.0 if success else 0.0
        return success.astype(np.float32)

    def render(self) -> np.ndarray | None:
        """Top-down RGB image ``(image_size, image_size, 3)`` for ``render_mode="rgb_array"``.

        Returns:
            The image, or None when ``render_mode`` is None.
        """
        if self.render_mode is None:
            gym.logger.warn(
                "Tabletop2DEnv.render() called without a render_mode; "
                'pass render_mode="rgb_array" to the constructor.'
            )
            return None
        return self._render_image()

    def scene(self) -> SceneState:
        """Privileged description of the current scene in the viewer frame.

        Returns:
            A :class:`~envs.scene.SceneState`; objects are listed in
            :data:`~envs.scene.OBJECT_KINDS` order, rest on the table (``z = 0.025``),
            are never grasped, and ``touching`` says whether the pusher is within 1 mm of
            each object's surface.
        """
        if not self._has_reset:
            raise RuntimeError("Tabletop2DEnv.scene() called before reset()")
        n = self._n
        kinds = [OBJECT_KINDS[s] for s in self._slots]
        positions = np.array([(self._ox[i], self._oy[i], _H) for i in range(n)], np.float64)
        touching = np.array(
            [self._gap_to_object(i) <= _TOUCH_TOLERANCE for i in range(n)], dtype=bool
        )
        return SceneState(
            colours=tuple(c for c, _ in kinds),
            shapes=tuple(s for _, s in kinds),
            positions=positions.reshape(n, 3),
            half_extents=np.full((n, 3), _H),
            gripper=np.array((self._px, self._py, PUSHER_HEIGHT)),
            table_bounds=self.table_bounds,
            table_height=0.0,
            grasped=np.zeros(n, dtype=bool),
            touching=touching,
        )

    # ------------------------------------------------------------------ internals

    def _physics(self, dx: float, dy: float) -> None:
        """Advance the pusher by ``(dx, dy)`` metres and resolve every contact."""
        lim = _PUSHER_LIMIT
        px = self._px + dx
        py = self._py + dy
        px = -lim if px < -lim else (lim if px > lim else px)
        py = -lim if py < -lim else (lim if py > lim else py)
        ox = self._ox
        oy = self._oy
        cube = self._cube
        n = self._n
        olim = _OBJECT_LIMIT
        reach = _CONTACT

        both = 2.0 * _H
        for _ in range(_CONTACT_ITERATIONS):
            # 1. The pusher pushes objects out of itself.
            moved = False
            for i in range(n):
                ex = ox[i] - px
                ey = oy[i] - py
                if -reach < ex < reach and -reach < ey < reach:
                    mx, my = _pusher_overlap(ex, ey, cube[i])
                    if mx or my:
                        x = ox[i] + mx
                        y = oy[i] + my
                        ox[i] = -olim if x < -olim else (olim if x > olim else x)
                        oy[i] = -olim if y < -olim else (olim if y > olim else y)
                        moved = True
            if not moved:
                break

            # 2. Relax object-object overlaps.
            for _ in range(_RELAXATION_PASSES):
                overlap = False
                for i in range(n - 1):
                    for j in range(i + 1, n):
                        ex = ox[j] - ox[i]
                        ey = oy[j] - oy[i]
                        if not (-both < ex < both and -both < ey < both):
                            continue
                        mx, my = _object_separation(ex, ey, cube[i], cube[j])
                        if not (mx or my):
                            continue
                        overlap = True
                        # i takes half (clamped); j takes whatever i could not.
                        xi = ox[i]
                        yi = oy[i]
                        x = xi - 0.5 * mx
                        y = yi - 0.5 * my
                        x = -olim if x < -olim else (olim if x > olim else x)
                        y = -olim if y < -olim else (olim if y > olim else y)
                        ox[i] = x
                        oy[i] = y
                        x = ox[j] + mx + (x - xi)
                        y = oy[j] + my + (y - yi)
                        ox[j] = -olim if x < -olim else (olim if x > olim else x)
                        oy[j] = -olim if y < -olim else (olim if y > olim else y)
                if not overlap:
                    break

            # 3. Objects that could not get out of the way push the pusher back (all
            # corrections computed from the same pusher position, then summed). If that
            # moves the pusher into another object, the next iteration pushes that one.
            cx = cy = 0.0
            for i in range(n):
                ex = ox[i] - px
                ey = oy[i] - py
                if -reach < ex < reach and -reach < ey < reach:
                    mx, my = _pusher_overlap(ex, ey, cube[i])
                    cx += mx
                    cy += my
            if not (cx or cy):
                break
            px -= cx
            py -= cy
            px = -lim if px < -lim else (lim if px > lim else px)
            py = -lim if py < -lim else (lim if py > lim else py)
        self._px = px
        self._py = py

    def _observe(self) -> tuple[dict[str, np.ndarray], bool]:
        """Build a fresh observation dict and the success flag for the current state."""
        ox = self._ox
        oy = self._oy
        obs = self._obs_template[:]
        obs[0] = self._px
        obs[1] = self._py
        if self._object_goal:
            goal = self._goal_template[:]
            for i, s in enumerate(self._slots):
                x = ox[i]
                y = oy[i]
                obs[2 + 3 * s] = x
                obs[3 + 3 * s] = y
                goal[2 * s] = x
                goal[2 * s + 1] = y
            achieved = np.array(goal, np.float32)
            # Success from the float32 values, exactly as compute_reward computes it.
            ag = achieved.tolist()
            dg = self._desired_list
            success = True
            for s in self._slots:
                ex = ag[2 * s] - dg[2 * s]
                ey = ag[2 * s + 1] - dg[2 * s + 1]
                if ex * ex + ey * ey > _THRESHOLD_SQ:
                    success = False
                    break
        else:
            for i, s in enumerate(self._slots):
                obs[2 + 3 * s] = ox[i]
                obs[3 + 3 * s] = oy[i]
            achieved = np.array(obs[:2], np.float32)
            ax, ay = achieved.tolist()
            dx, dy = self._desired_list
            ex = ax - dx
            ey = ay - dy
            success = ex * ex + ey * ey <= _THRESHOLD_SQ
        out = {
            "observation": np.array(obs, np.float32),
            "achieved_goal": achieved,
            "desired_goal": self._desired.copy(),
        }
        if self.image:
            out["image"] = self._render_image()
        return out, success

    def _render_image(self) -> np.ndarray:
        """Draw the current state with OpenCV (fixed-point coordinates for sub-pixel accuracy)."""
        img = self._background.copy()
        k = self._px_per_m * _RENDER_SCALE
        # Pixel centres are at integer coordinates: the table edge x = -0.25 is at -0.5 px.
        off_x = (TABLE_HALF_SIZE * self._px_per_m - 0.5) * _RENDER_SCALE
        half = _H * k
        shift = _RENDER_SHIFT
        line = cv2.LINE_AA
        colours = self._colour_of_slot
        for i, s in enumerate(self._slots):
            cx = off_x + self._ox[i] * k
            cy = off_x - self._oy[i] * k  # image rows grow towards the viewer (-y)
            if self._cube[i]:
                # cv2.rectangle includes both corners: shrink by half a pixel each side.
                h = half - 0.5 * _RENDER_SCALE
                cv2.rectangle(
                    img,
                    (round(cx - h), round(cy - h)),
                    (round(cx + h), round(cy + h)),
                    colours[s],
                    -1,
                    line,
                    shift,
                )
            else:
                cv2.circle(img, (round(cx), round(cy)), round(half), colours[s], -1, line, shift)
        cv2.circle(
            img,
            (round(off_x + self._px * k), round(off_x - self._py * k)),
            round(_R * k),
            _PUSHER_RGB,
            -1,
            line,
            shift,
        )
        return img

    def _gap_to_object(self, i: int) -> float:
        """Distance between the pusher's edge and object ``i``'s surface (<= 0: overlap)."""
        ex = abs(self._ox[i] - self._px)
        ey = abs(self._oy[i] - self._py)
        if self._cube[i]:
            cx = max(ex - _H, 0.0)
            cy = max(ey - _H, 0.0)
            return math.hypot(cx, cy) - _R
        return math.hypot(ex, ey) - _R - _H


def _discrete_action(action: Any) -> int:
    """One whole number: an int, a numpy integer or a whole-valued float (``3.0``), alone
    or in a one-element array. A fraction such as 2.5 names no move and is refused, as NaN
    is, instead of being truncated to one."""
    value = np.asarray(action)
    if value.size != 1 or value.dtype.kind not in "iuf":
        raise ValueError(f"discrete action {action!r} must be one integer (a move index)")
    v = value.reshape(()).item()
    if isinstance(v, float) and not (math.isfinite(v) and v == int(v)):
        raise ValueError(
            f"discrete action {action!r} is not a whole number: pass a move index (an integer)"
        )
    return int(v)


def _clip_action(v: float) -> float:
    if v != v:  # NaN
        raise ValueError("Tabletop2DEnv.step: action contains NaN")
    return -1.0 if v < -1.0 else (1.0 if v > 1.0 else v)

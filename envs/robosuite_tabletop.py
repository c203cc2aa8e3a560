"""A robosuite Panda tabletop with coloured cubes and cylinders, for language goals.

A Franka Panda arm (robosuite 1.5, ``OSC_POSITION`` controller plus its parallel gripper)
stands behind a table. Every episode shows 2 to 4 of the 8 object kinds of
:data:`envs.scene.OBJECT_KINDS` (4 colours x cube / cylinder, colours from
:data:`envs.scene.COLOURS`) at random, non-overlapping spots drawn from the reset seed.

Frame: everything the environment reports is in the *viewer frame* of :mod:`envs.scene`,
seen from the ``agentview`` camera: metres, ``x`` to the camera's right, ``y`` away from
the camera (towards the robot), ``z`` up. Its origin is the table centre on the floor, so
the table surface is at ``z = TABLE_HEIGHT = 0.8``. In robosuite's world frame the
camera looks along ``-x``, so ``viewer = (world_y, -world_x, world_z)``.

Geometry:
    * usable table area (``table_bounds``): ``x`` in ``[-0.25, 0.25]``, ``y`` in
      ``[-0.2, 0.2]``, all within the arm's reach and the agentview image;
    * objects: cubes of half size ``0.022`` and cylinders of radius and half height
      ``0.022`` (about 85 g and 67 g); they start upright and axis-aligned, their centres
      in ``x`` in ``[-0.16, 0.16]``, ``y`` in ``[-0.12, 0.12]`` and at least 0.08 m apart;
    * the gripper starts about 0.2 m above the table near ``(0, 0.1)``; its joints get
      gaussian noise (``init_noise`` radians) at every reset.

Kinds not in the episode are parked below the floor, out of every camera's view, with
collisions and gravity switched off for them, so they take no part in the physics. A
reset only writes the state (robosuite's soft reset, ``hard_reset=False``); the MuJoCo
model is built once, in the constructor.

Action: ``Box(-1, 1, (4,))``: ``dx, dy, dz`` in the viewer frame and the gripper command
(``-1`` opens, ``+1`` closes). The arm moves under robosuite's operational-space position
controller: one unit of action asks for 0.05 m of end-effector displacement per control
step, and the hand moves at most about 1.5 cm per step. The control rate is
``control_freq = 20`` Hz (0.05 s, 25 physics steps of 2 ms): a reach or a push takes 10 to
30 steps, a scripted pick-and-lift 50 to 70, a stack about 100. The controller's joint
torques are recomputed every ``controller_period = 5`` physics steps (100 Hz) rather than
at every physics step as robosuite does: a step costs 2.4 times less, and scripted
reaches, pushes, grasps, lifts and stacks behave the same (``controller_period=1``
restores robosuite's behaviour).

Observation (a :class:`gymnasium.spaces.Dict`):
    * ``"observation"``: float32, 36 values: the gripper (grip site, between the
      fingertips) ``x, y, z``; the gripper opening (finger joint 1 minus finger joint 2:
      about 0.014 m closed on nothing, 0.044 m holding an object, 0.078 m open); then for
      each of the 8 kinds in :data:`~envs.scene.OBJECT_KINDS` order a slot
      ``[x, y, z, present]`` (all zeros when the kind is absent). Slot ``k`` (kind
      ``OBJECT_KINDS[k]``) starts at ``4 + 4 k``.
    * ``"achieved_goal"`` / ``"desired_goal"``: float32.

      - ``goal="object"`` (default): 24 values, the ``x, y, z`` of every kind slot (0 for
        absent kinds). The desired goal is the reset layout with one randomly chosen object
        moved to a random free spot of the table (resting on it) at least 0.08 m from where
        it started. Success: every slot within ``distance_threshold = 0.05`` m of its
        target.
      - ``goal="gripper"``: 3 values, the gripper's ``x, y, z``; the desired goal is a
        random point above the table (``z`` from 0.03 to 0.25 m above the surface) at least
        0.1 m from the start. Success: within 0.05 m of it.
    * ``"image"`` (only with ``image=True``): uint8 ``(image_size, image_size, 3)`` RGB from
      the ``agentview`` camera, image up is up; image right is ``+x``.
    * ``"eye_image"`` (only with ``eye_in_hand=True``): the same from the camera in the hand.

Reward is 1.0 on success and 0.0 otherwise (:meth:`RobosuiteTabletopEnv.compute_reward`);
``terminated`` is always False; ``lcrl/RobosuiteTabletop-v0`` truncates after 100 steps
(5 s of simulated time).

Rendering does not go through robosuite's camera observations: one ``mujoco.Renderer``
draws the camera(s) once per control step. By default shadows, reflections and the skybox
are off (``fancy_render=True`` keeps them) and the arm is drawn with its simple collision
shapes instead of its detailed meshes (``detailed_robot=True`` draws the meshes), which
makes a frame 3 to 4 times cheaper on a software OpenGL renderer.

Simulation errors (NaN or inf in the state, MuJoCo's instability warnings, an exception
inside the simulator) never escape :meth:`RobosuiteTabletopEnv.step`: the step returns the
last good observation with ``truncated=True`` and ``info["sim_error"]``, counts the error
in ``sim_errors`` and issues a :class:`RuntimeWarning`; the next reset starts afresh.

robosuite and mujoco are optional dependencies (``pip install -e ".[robot]"``): this module
imports them only when an environment is created.
"""

from __future__ import annotations

import atexit
import warnings
from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs._gl import use_headless_gl
from envs.layout import check_num_objects, check_objects, is_int, sample_points
from envs.robosuite_backend import (
    _ARM_RGBA,
    _CONTROL_FREQS,
    _EXIT_HOOK,
    _GOAL_DIM_OBJECT,
    _GOALS,
    _GRIPPER_GOAL_XY,
    _GRIPPER_GOAL_Z,
    _H,
    _HAND_RGBA,
    _HIDDEN_GROUP,
    _IMAGE_SIZES,
    _LIVE_RENDERERS,
    _MAX_OPENING,
    _MAX_SAMPLE_TRIES,
    _MIN_GOAL_MOVE,
    _MIN_GRIPPER_GOAL_MOVE,
    _MIN_OBJECT_GAP,
    _MODEL_TIMESTEP,
    _MOUNT_RGBA,
    _NUM_KINDS,
    _OBS_DIM,
    _PARK_Z,
    _POS_LIMIT,
    _SIMPLE_ROBOT_GROUP,
    _SLOT0,
    _SPAWN_X,
    _SPAWN_Y,
    _WHO,
    CONTROL_FREQ as CONTROL_FREQ,
    DISTANCE_THRESHOLD as DISTANCE_THRESHOLD,
    MAX_EPISODE_STEPS as MAX_EPISODE_STEPS,
    OBJECT_HALF_SIZE as OBJECT_HALF_SIZE,
    TABLE_BOUNDS as TABLE_BOUNDS,
    TABLE_HEIGHT as TABLE_HEIGHT,
    RobosuiteMissingError as RobosuiteMissingError,
    RobosuiteTabletopConfigError as RobosuiteTabletopConfigError,
    _backend,
    _bad,
    _close_live_renderers,
    _make_renderer as _make_renderer,
    _quiet_robosuite as _quiet_robosuite,
)
from envs.scene import OBJECT_KINDS, SceneState
from lcrl.errors import LcrlError

__all__ = [
    "CONTROL_FREQ",
    "DISTANCE_THRESHOLD",
    "MAX_EPISODE_STEPS",
    "OBJECT_HALF_SIZE",
    "TABLE_BOUNDS",
    "TABLE_HEIGHT",
    "RobosuiteMissingError",
    "RobosuiteTabletopConfigError",
    "RobosuiteTabletopEnv",
]


_MIN_OBJECTS, _MAX_OBJECTS = 2, 4


_TOUCH, _LEFT_PAD, _RIGHT_PAD = 1, 2, 4


def _reraise_interrupt(exc: BaseException) -> None:
    """Raise the interrupt behind ``exc``, if a signal handler's exception is in its chain.

    A KeyboardInterrupt (or a run's SIGTERM) raised inside compiled simulator code, such as
    numba's controller functions, comes back as a SystemError whose cause or context is the
    interrupt. That is the user stopping the run, not a simulation error.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if not isinstance(e, Exception):
            raise e
        e = e.__cause__ or e.__context__


class RobosuiteTabletopEnv(gym.Env):
    """Panda arm and coloured objects on a table, with a goal-conditioned dict observation.

    See the module docstring for the scene, the frame and the observation layout.

    Args:
        num_objects: number of objects, or an inclusive ``(low, high)`` range sampled at
            every reset; between 2 and 4.
        objects: the ``(colour, shape)`` kinds that may appear (default: all 8 of
            :data:`~envs.scene.OBJECT_KINDS`); at least as many as the largest object count.
            Observation slots always cover all 8 kinds.
        goal: ``"object"`` (move one object) or ``"gripper"`` (reach a point).
        image: add an ``"image"`` entry (agentview camera) to the observation.
        image_size: side of rendered images in pixels, 64 or 84.
        eye_in_hand: add an ``"eye_image"`` entry (camera in the hand).
        fancy_render: keep shadows, reflections and the skybox.
        detailed_robot: draw the arm's detailed meshes instead of its collision shapes.
        control_freq: control steps per second: 10, 20, 25 or 50.
        controller_period: physics steps (2 ms) between two updates of the controller's
            torques, from 1 (every step, robosuite's default) to the number of physics
            steps in one control step.
        init_noise: standard deviation (radians) of the gaussian noise on the arm's initial
            joint angles; 0 starts every episode from the same pose.
        render_mode: ``None`` or ``"rgb_array"`` (the agentview camera at ``image_size``).

    Raises:
        ValueError: (a :class:`RobosuiteTabletopConfigError`) for any bad argument.
        ImportError: (a :class:`RobosuiteMissingError`) when robosuite or mujoco is not
            installed, or no OpenGL context can be made for rendering.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 20}

    #: Goal distance threshold (m).
    distance_threshold: float = DISTANCE_THRESHOLD
    #: Half size of a cube / radius and half height of a cylinder (m).
    object_half_size: float = OBJECT_HALF_SIZE
    #: ``(xmin, xmax, ymin, ymax)`` of the usable table area (m, viewer frame).
    table_bounds: tuple[float, float, float, float] = TABLE_BOUNDS
    #: z of the table surface (m).
    table_height: float = TABLE_HEIGHT

    #: Instruction families this env can achieve.
    instruction_families: tuple[str, ...] = ("reach", "push", "put", "lift", "stack")
    #: The first values of ``"observation"`` that describe the robot itself (gripper
    #: x, y, z and opening).
    proprio_dim: int = 4
    #: ``(start, count, width)`` of the object slots in ``"observation"``.
    slot_layout: tuple[int, int, int] = (_SLOT0, _NUM_KINDS, 4)
    #: Position values at the front of the agent's values and of every slot.
    position_dims: int = 3

    def __init__(
        self,
        num_objects: int | tuple[int, int] = (2, 4),
        objects: Sequence[tuple[str, str]] | None = None,
        goal: str = "object",
        image: bool = False,
        image_size: int = 84,
        eye_in_hand: bool = False,
        fancy_render: bool = False,
        detailed_robot: bool = False,
        control_freq: int = CONTROL_FREQ,
        controller_period: int = 5,
        init_noise: float = 0.02,
        render_mode: str | None = None,
    ) -> None:
        self._count_range = check_num_objects(num_objects, _MIN_OBJECTS, _MAX_OBJECTS, _bad)
        self._allowed_slots = check_objects(objects, self._count_range[1], _bad)
        if goal not in _GOALS:
            raise _bad("goal", goal, f"expected one of {list(_GOALS)}")
        for name, value in (
            ("image", image),
            ("eye_in_hand", eye_in_hand),
            ("fancy_render", fancy_render),
            ("detailed_robot", detailed_robot),
        ):
            if not isinstance(value, (bool, np.bool_)):
                raise _bad(name, value, "expected a bool")
        if not is_int(image_size) or image_size not in _IMAGE_SIZES:
            raise _bad("image_size", image_size, f"expected one of {list(_IMAGE_SIZES)}")
        if not is_int(control_freq) or control_freq not in _CONTROL_FREQS:
            raise _bad("control_freq", control_freq, f"expected one of {list(_CONTROL_FREQS)}")
        substeps = round(1.0 / (control_freq * _MODEL_TIMESTEP))
        if not is_int(controller_period) or not 1 <= controller_period <= substeps:
            raise _bad(
                "controller_period",
                controller_period,
                f"expected an int in [1, {substeps}] (physics steps per control step)",
            )
        if (
            isinstance(init_noise, (bool, np.bool_))
            or not isinstance(init_noise, (int, float, np.floating, np.integer))
            or not 0.0 <= float(init_noise) <= 0.2
        ):
            raise _bad("init_noise", init_noise, "expected a number in [0, 0.2] (radians)")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise _bad(
                "render_mode",
                render_mode,
                f"expected None or one of {self.metadata['render_modes']}",
            )

        self.num_objects = num_objects
        self.objects = tuple(OBJECT_KINDS[k] for k in self._allowed_slots)
        self.goal = goal
        self.image = bool(image)
        self.image_size = int(image_size)
        self.eye_in_hand = bool(eye_in_hand)
        self.fancy_render = bool(fancy_render)
        self.detailed_robot = bool(detailed_robot)
        self.control_freq = int(control_freq)
        self.controller_period = int(controller_period)
        self.init_noise = float(init_noise)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.control_freq}
        #: Number of simulation errors met so far (each truncated an episode).
        self.sim_errors = 0

        backend = _backend()
        self._mujoco = backend["mujoco"]
        with _quiet_robosuite():
            part = backend["load_part_controller_config"](default_controller="OSC_POSITION")
            controller = backend["refactor_config"](part, "Panda", ["right"])
            self._task = backend["task_class"](
                controller_period=self.controller_period,
                robots="Panda",
                controller_configs=controller,
                initialization_noise={"magnitude": self.init_noise, "type": "gaussian"},
                use_camera_obs=False,
                has_renderer=False,
                has_offscreen_renderer=False,
                render_camera=None,
                control_freq=self.control_freq,
                lite_physics=True,
                horizon=2**62,
                ignore_done=True,
                hard_reset=False,
                renderer="mujoco",
            )
        self._setup_ids()
        self._object_goal = goal == "object"

        # Spaces.
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)
        lim = np.float32(_POS_LIMIT)
        obs_low = np.full(_OBS_DIM, -lim, np.float32)
        obs_high = np.full(_OBS_DIM, lim, np.float32)
        obs_low[3], obs_high[3] = 0.0, _MAX_OPENING
        for k in range(_NUM_KINDS):
            obs_low[_SLOT0 + 4 * k + 3], obs_high[_SLOT0 + 4 * k + 3] = 0.0, 1.0
        self._obs_low, self._obs_high = obs_low, obs_high
        goal_dim = _GOAL_DIM_OBJECT if self._object_goal else 3
        goal_space = spaces.Box(-lim, lim, (goal_dim,), np.float32)
        obs_spaces: dict[str, spaces.Space[Any]] = {
            "observation": spaces.Box(obs_low, obs_high, dtype=np.float32),
            "achieved_goal": goal_space,
            "desired_goal": goal_space,
        }
        shape = (self.image_size, self.image_size, 3)
        if self.image:
            obs_spaces["image"] = spaces.Box(0, 255, shape, np.uint8)
        if self.eye_in_hand:
            obs_spaces["eye_image"] = spaces.Box(0, 255, shape, np.uint8)
        self.observation_space: spaces.Space[Any] = spaces.Dict(obs_spaces)

        self._renderer: Any = None
        if self.image or self.eye_in_hand or self.render_mode is not None:
            self._setup_renderer()

        # Episode state (filled in by reset).
        self._slots: list[int] = []
        self._present = np.zeros(_NUM_KINDS, bool)
        self._desired = np.zeros(goal_dim, np.float32)
        self._last_obs: dict[str, np.ndarray] | None = None
        self._sim_error: str | None = None
        self._has_reset = False

    # ------------------------------------------------------------------ set-up

    def _setup_ids(self) -> None:
        """Look up the MuJoCo ids and addresses the env reads and writes."""
        mj = self._mujoco
        task = self._task
        #: The underlying ``mujoco.MjModel`` (built once; resets never replace it).
        self.model = task.sim.model._model
        #: The underlying ``mujoco.MjData``.
        self.data = task.sim.data._data
        m = self.model
        robot = task.robots[0]
        gripper = robot.gripper["right"]
        self._eef_site = int(robot.eef_site_id["right"])
        self._finger_qpos = [int(m.jnt_qposadr[m.joint(j).id]) for j in gripper.joints]

        self._body = np.array([m.body(o.root_body).id for o in task.kind_objects])
        self._qpos_adr = [int(m.jnt_qposadr[m.joint(o.joints[0]).id]) for o in task.kind_objects]
        self._collision_geoms = [[m.geom(g).id for g in o.contact_geoms] for o in task.kind_objects]
        self._visual_geoms = [[m.geom(g).id for g in o.visual_geoms] for o in task.kind_objects]
        self._contype = {
            g: (int(m.geom_contype[g]), int(m.geom_conaffinity[g]))
            for gs in self._collision_geoms
            for g in gs
        }
        self._geom_slot = np.full(m.ngeom, -1, np.int64)
        for k, gs in enumerate(self._collision_geoms):
            self._geom_slot[gs] = k
        self._geom_grip = np.zeros(m.ngeom, np.int64)
        for name in gripper.contact_geoms:
            self._geom_grip[m.geom(name).id] = _TOUCH
        left = [m.geom(name).id for name in gripper.important_geoms["left_fingerpad"]]
        right = [m.geom(name).id for name in gripper.important_geoms["right_fingerpad"]]
        self._geom_grip[left] |= _LEFT_PAD
        self._geom_grip[right] |= _RIGHT_PAD
        self._pads = (left[0], right[0])  # their centres give the fingers' closing axis

        bad = mj.mjtWarning
        self._bad_warnings = [
            int(bad.mjWARN_BADQPOS),
            int(bad.mjWARN_BADQVEL),
            int(bad.mjWARN_BADQACC),
        ]
        self._agentview = m.camera("agentview").id
        self._eye_camera = m.camera("robot0_eye_in_hand").id

    def _setup_renderer(self) -> None:
        """Create the offscreen renderer and its (fast by default) visual options."""
        mj = self._mujoco
        m = self.model
        if not self.detailed_robot:
            # Draw the arm, hand and mount with their collision shapes (a few hundred
            # triangles each) instead of their visual meshes (up to 33 000 each).
            root = m.body_rootid[m.body(self._task.robots[0].robot_model.root_body).id]
            hand = {m.geom(g).id for g in self._task.robots[0].gripper["right"].contact_geoms}
            for g in range(m.ngeom):
                if m.body_rootid[m.geom_bodyid[g]] != root:
                    continue
                if m.geom_group[g] == 1:
                    m.geom_group[g] = _HIDDEN_GROUP
                elif m.geom_group[g] == 0:
                    name = m.geom(g).name
                    m.geom_group[g] = _SIMPLE_ROBOT_GROUP
                    if g in hand:
                        m.geom_rgba[g] = _HAND_RGBA
                    elif name.startswith("robot0_"):
                        m.geom_rgba[g] = _ARM_RGBA
                    else:
                        m.geom_rgba[g] = _MOUNT_RGBA
        try:
            renderer = _make_renderer(mj, m, self.image_size)
        except Exception as exc:
            raise RobosuiteMissingError(
                f"RobosuiteTabletopEnv could not create an offscreen OpenGL context "
                f"(MUJOCO_GL={use_headless_gl()!r}): {exc}. On a machine without a display "
                "set MUJOCO_GL=egl (or osmesa) before starting Python."
            ) from exc
        if not self.fancy_render:
            flags = renderer.scene.flags
            flags[mj.mjtRndFlag.mjRND_SHADOW] = False
            flags[mj.mjtRndFlag.mjRND_REFLECTION] = False
            flags[mj.mjtRndFlag.mjRND_SKYBOX] = False
        if not _EXIT_HOOK:
            # Registered after the first context exists, so that it runs before the EGL
            # backend's own exit hook (exit hooks run last registered, first called).
            atexit.register(_close_live_renderers)
            _EXIT_HOOK.append(True)
        _LIVE_RENDERERS.add(renderer)
        opt = mj.MjvOption()
        opt.geomgroup[:] = 0
        opt.geomgroup[1] = 1  # visual geoms (robosuite's convention; 0 is collision)
        opt.geomgroup[_SIMPLE_ROBOT_GROUP] = 1
        opt.sitegroup[:] = 0
        self._vopt = opt
        self._renderer = renderer

    # ------------------------------------------------------------------ gym API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Sample a new layout (and goal) from ``self.np_random`` and reset the simulation.

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
        points = sample_points(n, [], _MIN_OBJECT_GAP, _SPAWN_X, _SPAWN_Y, rng, _WHO)
        self._slots = slots
        self._present = np.zeros(_NUM_KINDS, bool)
        self._present[slots] = True

        rest_z = TABLE_HEIGHT + _H
        layout = []
        for k in range(_NUM_KINDS):
            if self._present[k]:
                x, y = points[slots.index(k)]
                pos = (-y, x, rest_z)  # viewer -> world
            else:
                pos = (-0.35 + 0.1 * k, 0.0, _PARK_Z)
            layout.append(np.array([*pos, 1.0, 0.0, 0.0, 0.0]))
        self._apply_presence()
        task = self._task
        task.layout = layout
        task.rng = np.random.default_rng(int(rng.integers(2**63)))  # arm's initial noise
        with _quiet_robosuite():
            task.reset()
        self._sim_error = None
        self._has_reset = True

        if self._object_goal:
            mover = int(rng.integers(n))
            (target,) = sample_points(
                1, points, max(_MIN_OBJECT_GAP, _MIN_GOAL_MOVE), _SPAWN_X, _SPAWN_Y, rng, _WHO
            )
            desired = np.zeros(_GOAL_DIM_OBJECT, np.float32)
            for i, k in enumerate(slots):
                x, y = target if i == mover else points[i]
                desired[3 * k : 3 * k + 3] = (x, y, rest_z)
        else:
            start = self._viewer(self.data.site_xpos[self._eef_site])
            gx, gy = _GRIPPER_GOAL_XY
            zlo, zhi = _GRIPPER_GOAL_Z
            for _ in range(_MAX_SAMPLE_TRIES):
                p = rng.uniform((-gx, -gy, TABLE_HEIGHT + zlo), (gx, gy, TABLE_HEIGHT + zhi))
                if np.linalg.norm(p - start) >= _MIN_GRIPPER_GOAL_MOVE:
                    break
            desired = p.astype(np.float32)
        self._desired = desired
        obs, success = self._observe()
        return obs, {"is_success": success}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Apply one control step of the arm and gripper, and observe.

        Args:
            action: a ``(4,)`` array: ``dx, dy, dz`` (viewer frame) and the gripper
                command, each in ``[-1, 1]`` (values outside are clipped).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; reward is 1.0 on success
            and 0.0 otherwise, ``terminated`` is False, ``info = {"is_success": bool}``. After
            a simulation error ``truncated`` is True, ``info["sim_error"]`` says what went
            wrong and the observation is the last good one (also on every further step until
            the next reset).
        """
        if not self._has_reset:
            raise RuntimeError("RobosuiteTabletopEnv.step() called before reset()")
        a = np.asarray(action, dtype=np.float64)
        if a.size != 4:
            raise ValueError(f"action must have 4 values (dx, dy, dz, gripper), got {a.shape}")
        a = a.reshape(4)
        if np.isnan(a).any():
            raise ValueError("RobosuiteTabletopEnv.step: action contains NaN")
        a = np.clip(a, -1.0, 1.0)
        if self._sim_error is None:
            self._sim_error = self._advance(np.array([-a[1], a[0], a[2], a[3]]))
            if self._sim_error is None:
                obs, success = self._observe()
                return obs, 1.0 if success else 0.0, False, False, {"is_success": success}
            self.sim_errors += 1
            warnings.warn(
                f"RobosuiteTabletopEnv: simulation error, episode truncated: {self._sim_error}",
                RuntimeWarning,
                stacklevel=2,
            )
        assert self._last_obs is not None
        obs = {k: v.copy() for k, v in self._last_obs.items()}
        return obs, 0.0, False, True, {"is_success": False, "sim_error": self._sim_error}

    def compute_reward(
        self, achieved_goal: Any, desired_goal: Any, info: Any = None
    ) -> float | np.ndarray:
        """Goal reward, vectorised over any leading batch dimensions.

        Args:
            achieved_goal: ``(..., goal_dim)`` achieved goals.
            desired_goal: ``(..., goal_dim)`` desired goals.
            info: ignored (kept for the gymnasium-robotics ``GoalEnv`` signature).

        Returns:
            1.0 where every ``x, y, z`` goal slot is within ``distance_threshold`` and 0.0
            elsewhere: a float for single goals, a float32 array of the batch shape otherwise.
        """
        diff = np.asarray(achieved_goal, dtype=np.float64) - np.asarray(
            desired_goal, dtype=np.float64
        )
        if diff.shape[-1:] != self._desired.shape:
            raise ValueError(
                f"goals must have a last dimension of {self._desired.shape[0]}, got {diff.shape}"
            )
        triples = diff.reshape(*diff.shape[:-1], -1, 3)
        dist_sq = np.sum(triples * triples, axis=-1)
        success = np.all(dist_sq <= DISTANCE_THRESHOLD * DISTANCE_THRESHOLD, axis=-1)
        if success.ndim == 0:
            return 1.0 if success else 0.0
        return success.astype(np.float32)

    def goal_image(self, camera: str = "agentview") -> np.ndarray:
        """The camera frame of the desired goal: objects at their goal positions (upright),
        the arm where it is now. The simulation state is restored afterwards.

        Raises:
            LcrlError: with ``goal="gripper"`` (moving the arm to a point needs a plan) or
                before the first reset.
        """
        if not self._object_goal:
            raise LcrlError(
                "goal images need goal='object'; a gripper goal cannot be drawn without "
                "moving the arm"
            )
        if not self._has_reset:
            raise LcrlError("call reset() before goal_image()")
        if camera not in ("agentview", "eye_in_hand"):
            raise RobosuiteTabletopConfigError(
                f"unknown camera {camera!r}; choose 'agentview' or 'eye_in_hand'"
            )
        mj, m, d = self._mujoco, self.model, self.data
        qpos, qvel = d.qpos.copy(), d.qvel.copy()
        try:
            for k in self._slots:
                x, y, z = (float(v) for v in self._desired[3 * k : 3 * k + 3])
                a = self._qpos_adr[k]
                d.qpos[a : a + 7] = (-y, x, z, 1.0, 0.0, 0.0, 0.0)  # viewer -> world
            mj.mj_forward(m, d)
            cam = self._agentview if camera == "agentview" else self._eye_camera
            if self._renderer is None:
                self._setup_renderer()
            return self._render(cam).copy()
        finally:
            d.qpos[:] = qpos
            d.qvel[:] = qvel
            mj.mj_forward(m, d)

    def render(self) -> np.ndarray | None:
        """The agentview image ``(image_size, image_size, 3)`` for ``render_mode="rgb_array"``.

        Returns:
            The image, or None when ``render_mode`` is None.
        """
        if self.render_mode is None:
            gym.logger.warn(
                "RobosuiteTabletopEnv.render() called without a render_mode; "
                'pass render_mode="rgb_array" to the constructor.'
            )
            return None
        return self._render(self._agentview)

    def close(self) -> None:
        """Free the renderer (the simulation itself needs no closing; calling twice is fine)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def scene(self) -> SceneState:
        """Privileged description of the current scene in the viewer frame.

        Returns:
            A :class:`~envs.scene.SceneState` of the present objects in
            :data:`~envs.scene.OBJECT_KINDS` order. ``gripper`` is the grip site between
            the fingertips; ``grasped`` says whether both finger pads squeeze the object
            (robosuite's grasp test, both pads in contact, plus contact normals along the
            closing axis); ``touching`` whether any gripper geom (hand, fingers, pads)
            touches it. Half extents are those of the upright object.
        """
        if not self._has_reset:
            raise RuntimeError("RobosuiteTabletopEnv.scene() called before reset()")
        slots = self._slots
        n = len(slots)
        d = self.data
        positions = self._viewer(d.xpos[self._body[slots]]).reshape(n, 3)
        flags = self._contact_flags()[slots]
        return SceneState(
            colours=tuple(OBJECT_KINDS[k][0] for k in slots),
            shapes=tuple(OBJECT_KINDS[k][1] for k in slots),
            positions=positions,
            half_extents=np.full((n, 3), _H),
            gripper=self._viewer(d.site_xpos[self._eef_site]),
            table_bounds=TABLE_BOUNDS,
            table_height=TABLE_HEIGHT,
            grasped=(flags & (_LEFT_PAD | _RIGHT_PAD)) == (_LEFT_PAD | _RIGHT_PAD),
            touching=(flags & _TOUCH) != 0,
        )

    # ------------------------------------------------------------------ internals

    @staticmethod
    def _viewer(world: np.ndarray) -> np.ndarray:
        """World positions ``(..., 3)`` to the viewer frame (``(y, -x, z)``)."""
        w = np.asarray(world, dtype=np.float64)
        return np.stack([w[..., 1], -w[..., 0], w[..., 2]], axis=-1)

    def _apply_presence(self) -> None:
        """Switch gravity, collisions and drawing on for present kinds, off for parked ones."""
        m = self.model
        for k in range(_NUM_KINDS):
            on = bool(self._present[k])
            m.body_gravcomp[self._body[k]] = 0.0 if on else 1.0
            for g in self._collision_geoms[k]:
                contype, conaffinity = self._contype[g] if on else (0, 0)
                m.geom_contype[g] = contype
                m.geom_conaffinity[g] = conaffinity
            for g in self._visual_geoms[k]:
                m.geom_group[g] = 1 if on else _HIDDEN_GROUP

    def _advance(self, rs_action: np.ndarray) -> str | None:
        """Run one robosuite step; a description of what went wrong, or None."""
        d = self.data
        before = d.warning.number[self._bad_warnings].copy()
        try:
            self._task.step(rs_action)
        except Exception as exc:  # any simulator failure ends the episode, never the caller
            _reraise_interrupt(exc)
            return f"{type(exc).__name__}: {exc}"
        new = d.warning.number[self._bad_warnings] != before
        if new.any():
            bad = [name for name, hit in zip(("qpos", "qvel", "qacc"), new, strict=True) if hit]
            return f"MuJoCo found NaN, inf or huge values in {'/'.join(bad)} (unstable simulation)"
        if not (
            np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all() and np.isfinite(d.qacc).all()
        ):
            return "NaN or inf in the simulation state"
        return None

    def _contact_flags(self) -> np.ndarray:
        """Per kind slot: bit 1 any gripper contact, bits 2 / 4 left / right finger pad.

        A pad contact only sets its bit when the contact normal lies along the fingers'
        closing axis (within 60 degrees): the pad squeezes the object's side. Pads resting
        on top of an object (closed fingers pressed down on it) touch it but do not grasp it.
        """
        d = self.data
        flags = np.zeros(_NUM_KINDS, np.int64)
        ncon = d.ncon
        if ncon == 0:
            return flags
        contact = d.contact
        geoms = contact.geom
        slot = self._geom_slot[geoms]
        grip = self._geom_grip[geoms]
        axis = d.geom_xpos[self._pads[0]] - d.geom_xpos[self._pads[1]]
        axis /= max(float(np.linalg.norm(axis)), 1e-9)
        squeeze = np.abs(contact.frame[:, :3] @ axis) >= 0.5
        for a, b in ((0, 1), (1, 0)):
            hit = (slot[:, a] >= 0) & (grip[:, b] > 0)
            if hit.any():
                bits = np.where(squeeze[hit], grip[hit, b], grip[hit, b] & _TOUCH)
                np.bitwise_or.at(flags, slot[hit, a], bits)
        return flags

    def _render(self, camera: int) -> np.ndarray:
        renderer = self._renderer
        renderer.update_scene(self.data, camera=camera, scene_option=self._vopt)
        return renderer.render()

    def _observe(self) -> tuple[dict[str, np.ndarray], bool]:
        """Build a fresh observation dict and the success flag for the current state."""
        d = self.data
        obs = np.zeros(_OBS_DIM, np.float64)
        grip = self._viewer(d.site_xpos[self._eef_site])
        obs[:3] = grip
        f1, f2 = self._finger_qpos
        obs[3] = d.qpos[f1] - d.qpos[f2]
        slots = self._slots
        positions = self._viewer(d.xpos[self._body[slots]])
        for i, k in enumerate(slots):
            s = _SLOT0 + 4 * k
            obs[s : s + 3] = positions[i]
            obs[s + 3] = 1.0
        obs = np.clip(obs, self._obs_low, self._obs_high).astype(np.float32)
        if self._object_goal:
            achieved = np.zeros(_GOAL_DIM_OBJECT, np.float32)
            for k in slots:
                s = _SLOT0 + 4 * k
                achieved[3 * k : 3 * k + 3] = obs[s : s + 3]
        else:
            achieved = obs[:3].copy()
        success = bool(self.compute_reward(achieved, self._desired) > 0.0)
        out = {
            "observation": obs,
            "achieved_goal": achieved,
            "desired_goal": self._desired.copy(),
        }
        if self.image:
            out["image"] = self._render(self._agentview)
        if self.eye_in_hand:
            out["eye_image"] = self._render(self._eye_camera)
        self._last_obs = out
        return {k: v.copy() for k, v in out.items()}, success


# ---------------------------------------------------------------------- helpers

"""What the robosuite tabletop stands on: its dimensions and limits, robosuite and MuJoCo
imported once (with a clear error where they are missing), quiet logs, and offscreen
renderers closed at exit."""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

import numpy as np

from envs._gl import use_headless_gl
from envs.scene import COLOURS, OBJECT_KINDS
from lcrl.errors import LcrlError

#: Half size of a cube, radius and half height of a cylinder (m).
OBJECT_HALF_SIZE = 0.022


#: z of the table surface (m).
TABLE_HEIGHT = 0.8


#: ``(xmin, xmax, ymin, ymax)`` of the usable table area in the viewer frame (m).
TABLE_BOUNDS: tuple[float, float, float, float] = (-0.25, 0.25, -0.2, 0.2)


#: Distance (m) under which a goal slot counts as reached.
DISTANCE_THRESHOLD = 0.05


#: Default control rate (Hz).
CONTROL_FREQ = 20


#: Episode length of the registered id (steps).
MAX_EPISODE_STEPS = 100


_H = OBJECT_HALF_SIZE


_NUM_KINDS = len(OBJECT_KINDS)


_SLOT0 = 4  # first object slot in "observation"


_OBS_DIM = _SLOT0 + 4 * _NUM_KINDS


_GOAL_DIM_OBJECT = 3 * _NUM_KINDS


_TABLE_FULL_SIZE = (0.8, 0.8, 0.05)


_SPAWN_X = 0.16  # object centres: |x| <= 0.16, |y| <= 0.12 (viewer frame)


_SPAWN_Y = 0.12


_MIN_OBJECT_GAP = 0.08  # centre distance: > cube diagonal 2 * 0.022 * sqrt(2) + margin


_MIN_GOAL_MOVE = 0.08


_GRIPPER_GOAL_XY = (0.2, 0.15)  # gripper goals: |x| <= 0.2, |y| <= 0.15


_GRIPPER_GOAL_Z = (0.03, 0.25)  # above the table surface


_MIN_GRIPPER_GOAL_MOVE = 0.1


_MAX_SAMPLE_TRIES = 200


_PARK_Z = -0.5  # world z of parked objects: under the floor


_POS_LIMIT = 3.0  # observation bounds (the floor is 6 m x 6 m)


_MAX_OPENING = 0.1


_MODEL_TIMESTEP = 0.002  # robosuite's physics step (s)


_HIDDEN_GROUP = 5  # geom group never drawn


_SIMPLE_ROBOT_GROUP = 4  # geom group of the arm's collision shapes in simple rendering


_ARM_RGBA = (0.88, 0.88, 0.88, 1.0)


_HAND_RGBA = (0.22, 0.22, 0.22, 1.0)


_MOUNT_RGBA = (0.15, 0.15, 0.15, 1.0)


_GOALS = ("object", "gripper")


_IMAGE_SIZES = (64, 84)


_CONTROL_FREQS = (10, 20, 25, 50)


_ROBOSUITE_LOGGER = "robosuite_logs"


class RobosuiteTabletopConfigError(LcrlError, ValueError):
    """A bad :class:`RobosuiteTabletopEnv` constructor argument (also a :class:`ValueError`)."""


class RobosuiteMissingError(LcrlError, ImportError):
    """robosuite (or mujoco, or an OpenGL context for rendering) is not available."""


def _bad(name: str, value: Any, allowed: str) -> RobosuiteTabletopConfigError:
    return RobosuiteTabletopConfigError(f"RobosuiteTabletopEnv: bad {name}={value!r}; {allowed}")


_WHO = "RobosuiteTabletopEnv"


@contextlib.contextmanager
def _quiet_robosuite() -> Iterator[None]:
    """Silence robosuite's logger (import-time warnings about optional extras, set-up lines)."""
    logger = logging.getLogger(_ROBOSUITE_LOGGER)
    was_disabled = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = was_disabled


_BACKEND: dict[str, Any] = {}


_LIVE_RENDERERS: weakref.WeakSet[Any] = weakref.WeakSet()


_EXIT_HOOK: list[bool] = []  # non-empty once _close_live_renderers is registered


def _close_live_renderers() -> None:
    """Free every open renderer at exit, before EGL shuts down.

    MuJoCo's EGL backend terminates the display in an exit hook of its own; contexts freed
    after that raise errors during interpreter shutdown.
    """
    for renderer in list(_LIVE_RENDERERS):
        with contextlib.suppress(Exception):
            renderer.close()


def _backend() -> dict[str, Any]:
    """Import mujoco and robosuite (once), quietly, and define the robosuite task class."""
    if _BACKEND:
        return _BACKEND
    use_headless_gl()
    with _quiet_robosuite():
        try:
            import mujoco
            from robosuite.controllers import load_part_controller_config
            from robosuite.controllers.composite.composite_controller_factory import (
                refactor_composite_controller_config,
            )
            from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
            from robosuite.models.arenas import TableArena
            from robosuite.models.objects import BoxObject, CylinderObject
            from robosuite.models.tasks import ManipulationTask
        except ImportError as exc:
            raise RobosuiteMissingError(
                f"RobosuiteTabletopEnv needs robosuite and mujoco ({exc}); install them with "
                '`pip install -e ".[robot]"`'
            ) from exc

    class TabletopTask(ManipulationEnv):
        """The robosuite side: Panda, table, one object of every kind; no observables.

        ``layout`` (one free-joint qpos per kind) is written at every reset; the OSC torques
        are recomputed every ``controller_period`` physics steps.
        """

        def __init__(self, controller_period: int, **kwargs: Any) -> None:
            self.table_full_size = _TABLE_FULL_SIZE
            self.table_offset = np.array((0.0, 0.0, TABLE_HEIGHT))
            self.controller_period = controller_period
            self.layout: list[np.ndarray] | None = None
            self.kind_objects: list[Any] = []
            self._substep = 0
            super().__init__(**kwargs)

        def _load_model(self) -> None:
            super()._load_model()
            robot_model = self.robots[0].robot_model
            robot_model.set_base_xpos(
                robot_model.base_xpos_offset["table"](self.table_full_size[0])
            )
            arena = TableArena(
                table_full_size=self.table_full_size,
                table_friction=(1.0, 5e-3, 1e-4),
                table_offset=self.table_offset,
            )
            arena.set_origin([0, 0, 0])
            self.kind_objects = []
            for colour, shape in OBJECT_KINDS:
                rgba = [c / 255.0 for c in COLOURS[colour]] + [1.0]
                name = f"{colour}_{shape}"
                if shape == "cube":
                    obj = BoxObject(name=name, size=[_H, _H, _H], rgba=rgba)
                else:
                    obj = CylinderObject(name=name, size=[_H, _H], rgba=rgba)
                # Compiled with gravity compensation so that the env can switch it on for
                # parked objects (MuJoCo skips it entirely when no body has it at compile).
                obj.get_obj().set("gravcomp", "1")
                self.kind_objects.append(obj)
            self.model = ManipulationTask(
                mujoco_arena=arena,
                mujoco_robots=[robot_model],
                mujoco_objects=self.kind_objects,
            )

        def _setup_observables(self) -> OrderedDict:
            return OrderedDict()

        def reward(self, action: Any = None) -> float:
            return 0.0

        def _reset_internal(self) -> None:
            super()._reset_internal()
            if self.layout is not None:
                for obj, qpos in zip(self.kind_objects, self.layout, strict=True):
                    self.sim.data.set_joint_qpos(obj.joints[0], qpos)

        def _pre_action(self, action: Any, policy_step: bool = False) -> None:
            if policy_step:
                self._substep = 0
            if self._substep % self.controller_period == 0:
                super()._pre_action(action, policy_step)
            self._substep += 1

    _BACKEND.update(
        mujoco=mujoco,
        task_class=TabletopTask,
        load_part_controller_config=load_part_controller_config,
        refactor_config=refactor_composite_controller_config,
    )
    return _BACKEND


def _make_renderer(mj: Any, model: Any, size: int) -> Any:
    """A ``mujoco.Renderer`` whose OpenGL context follows ``MUJOCO_GL`` as set now.

    MuJoCo picks its context class when it is first imported. robosuite imports mujoco
    *before* it sets ``MUJOCO_GL=egl`` on Linux, so after ``import robosuite`` on a
    headless machine mujoco still holds the windowed (GLFW) class. In that case the
    headless class asked for is used for this renderer only.
    """
    from mujoco import gl_context

    for name in ("_gl_context", "_mjr_context"):
        # A renderer whose __init__ is cut short (Ctrl-C while a scene is built) lacks
        # these, and its __del__ then prints a traceback; as class defaults it frees none.
        if not hasattr(mj.Renderer, name):
            setattr(mj.Renderer, name, None)
    wanted = os.environ.get("MUJOCO_GL", "").lower().strip()
    current = getattr(gl_context, "GLContext", None)
    if (
        wanted in ("egl", "osmesa")
        and current is not None
        and current.__module__ != f"mujoco.{wanted}"
    ):
        gl_context.GLContext = importlib.import_module(f"mujoco.{wanted}").GLContext
        try:
            return mj.Renderer(model, size, size)
        finally:
            gl_context.GLContext = current
    return mj.Renderer(model, size, size)

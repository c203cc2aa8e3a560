"""Headless OpenGL selection for MuJoCo rendering.

MuJoCo picks its OpenGL backend from the ``MUJOCO_GL`` environment variable when
``mujoco`` (or robosuite) is first imported. On a machine without a display the default
(GLFW) backend cannot open a window, so environments that render call
:func:`use_headless_gl` *before* importing mujoco or robosuite: it selects EGL, the
offscreen backend that works on headless Linux machines (with or without a GPU).
"""

from __future__ import annotations

import os
import sys

__all__ = ["use_headless_gl"]


def use_headless_gl() -> str | None:
    """Select EGL rendering when ``MUJOCO_GL`` is unset and there is no display.

    A ``MUJOCO_GL`` the user has set is always kept, and so is the default when a display
    (X11 or Wayland) is available or the platform is not Linux.

    Returns:
        The ``MUJOCO_GL`` value in effect afterwards (``None`` when it stays unset).
    """
    if (
        "MUJOCO_GL" not in os.environ
        and sys.platform.startswith("linux")
        and not os.environ.get("DISPLAY")
        and not os.environ.get("WAYLAND_DISPLAY")
    ):
        os.environ["MUJOCO_GL"] = "egl"
    return os.environ.get("MUJOCO_GL")

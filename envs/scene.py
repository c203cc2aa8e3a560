"""Privileged scene description shared by every lcrl environment.

An environment exposes ``scene()``, returning a :class:`SceneState`: what is on the table
and where the gripper is. The rule captioner reads nothing else, so any environment that
fills this in (the 2D tabletop, the robosuite tabletop, a user's own) gets instruction
captioning and language rewards for free.

Frame convention (the *viewer frame*): metres; ``x`` points to the viewer's right, ``y``
points away from the viewer (``forward``), ``z`` points up and the table surface is
``z = table_height``. Environments whose simulator uses another frame convert to this one
when they build the scene, so that "left", "behind" and "forward" mean the same thing
everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Object colours every environment can render, with their RGB values (0-255).
COLOURS: dict[str, tuple[int, int, int]] = {
    "red": (220, 40, 40),
    "green": (40, 170, 60),
    "blue": (40, 80, 220),
    "yellow": (235, 200, 30),
}

#: Object shapes every environment can build.
SHAPES: tuple[str, ...] = ("cube", "cylinder")


def object_name(colour: str, shape: str) -> str:
    """Canonical name of an object kind, e.g. ``"red cube"``."""
    return f"{colour} {shape}"


#: Every object kind, in a fixed order (colour-major). Environments use this order for
#: per-kind observation slots.
OBJECT_KINDS: tuple[tuple[str, str], ...] = tuple((c, s) for c in COLOURS for s in SHAPES)


@dataclass(frozen=True, eq=False)
class SceneState:
    """A snapshot of the scene in the viewer frame.

    Attributes:
        colours: colour name of each object, length N.
        shapes: shape name of each object, length N. Each (colour, shape) pair is unique
            within a scene, so ``"the red cube"`` always names one object.
        positions: (N, 3) object centres in metres.
        half_extents: (N, 3) half sizes along x, y, z (a cylinder's x/y half size is its
            radius).
        gripper: (3,) gripper (or pusher) position.
        table_bounds: ``(xmin, xmax, ymin, ymax)`` of the usable table area.
        table_height: z of the table surface.
        grasped: (N,) whether the gripper holds each object, or ``None`` when the
            environment cannot tell (a pusher never grasps).
        touching: (N,) whether the gripper touches each object, or ``None`` when unknown.
    """

    colours: tuple[str, ...]
    shapes: tuple[str, ...]
    positions: np.ndarray
    half_extents: np.ndarray
    gripper: np.ndarray
    table_bounds: tuple[float, float, float, float]
    table_height: float = 0.0
    grasped: np.ndarray | None = None
    touching: np.ndarray | None = None
    names: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        n = len(self.colours)
        if len(self.shapes) != n:
            raise ValueError(f"{n} colours but {len(self.shapes)} shapes")
        for attr in ("positions", "half_extents"):
            arr = np.asarray(getattr(self, attr), dtype=np.float64)
            if arr.shape != (n, 3):
                raise ValueError(f"SceneState.{attr} must have shape ({n}, 3), got {arr.shape}")
            object.__setattr__(self, attr, arr)
        gripper = np.asarray(self.gripper, dtype=np.float64)
        if gripper.shape != (3,):
            raise ValueError(f"SceneState.gripper must have shape (3,), got {gripper.shape}")
        object.__setattr__(self, "gripper", gripper)
        for attr in ("grasped", "touching"):
            value = getattr(self, attr)
            if value is not None:
                arr = np.asarray(value, dtype=bool)
                if arr.shape != (n,):
                    raise ValueError(f"SceneState.{attr} must have shape ({n},), got {arr.shape}")
                object.__setattr__(self, attr, arr)
        names = tuple(object_name(c, s) for c, s in zip(self.colours, self.shapes, strict=True))
        if len(set(names)) != n:
            raise ValueError(f"object kinds must be unique within a scene, got {names}")
        object.__setattr__(self, "names", names)

    def __len__(self) -> int:
        return len(self.colours)

    def index(self, colour: str, shape: str) -> int:
        """Index of the object with this colour and shape; ``-1`` if it is not in the scene."""
        try:
            return self.names.index(object_name(colour, shape))
        except ValueError:
            return -1

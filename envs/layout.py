"""Scene layout helpers shared by the tabletop environments: argument checks for the
object set and rejection sampling of non-overlapping positions."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from envs.scene import COLOURS, OBJECT_KINDS, SHAPES, object_name

#: ``bad(name, value, allowed) -> Exception``: an env's own configuration error.
BadArgument = Callable[[str, Any, str], Exception]

_SAMPLE_BATCH = 32
_MAX_SAMPLE_TRIES = 200


def is_int(v: Any) -> bool:
    """An integer that is not a bool."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def check_num_objects(num_objects: Any, low: int, high: int, bad: BadArgument) -> tuple[int, int]:
    """``num_objects`` (an int or an inclusive ``(lo, hi)`` pair within ``[low, high]``)."""
    allowed = f"expected an int in [{low}, {high}] or an inclusive (low, high) range within it"
    if is_int(num_objects):
        lo = hi = int(num_objects)
    elif (
        isinstance(num_objects, (tuple, list))
        and len(num_objects) == 2
        and all(is_int(v) for v in num_objects)
    ):
        lo, hi = int(num_objects[0]), int(num_objects[1])
    else:
        raise bad("num_objects", num_objects, allowed)
    if not low <= lo <= hi <= high:
        raise bad("num_objects", num_objects, allowed)
    return lo, hi


def check_objects(objects: Any, max_count: int, bad: BadArgument) -> list[int]:
    """Kind slots (indices into ``OBJECT_KINDS``) allowed in a scene; ``None``: all."""
    if objects is None:
        return list(range(len(OBJECT_KINDS)))
    if isinstance(objects, str) or not isinstance(objects, Sequence):
        raise bad("objects", objects, "expected a sequence of (colour, shape) pairs")
    slots: list[int] = []
    for item in objects:
        if (
            isinstance(item, str)
            or not isinstance(item, Sequence)
            or len(item) != 2
            or not all(isinstance(v, str) for v in item)
        ):
            raise bad("objects", objects, f"entry {item!r} is not a (colour, shape) pair")
        colour, shape = item
        if colour not in COLOURS:
            raise bad(
                "objects", objects, f"unknown colour {colour!r}; expected one of {list(COLOURS)}"
            )
        if shape not in SHAPES:
            raise bad(
                "objects", objects, f"unknown shape {shape!r}; expected one of {list(SHAPES)}"
            )
        slot = OBJECT_KINDS.index((colour, shape))
        if slot in slots:
            raise bad("objects", objects, f"{object_name(colour, shape)!r} is listed twice")
        slots.append(slot)
    if len(slots) < max_count:
        raise bad(
            "objects",
            objects,
            f"needs at least {max_count} distinct kinds for num_objects up to {max_count}",
        )
    return sorted(slots)


def sample_points(
    count: int,
    existing: list[tuple[float, float]],
    min_gap: float,
    limit_x: float,
    limit_y: float,
    rng: np.random.Generator,
    who: str = "the environment",
) -> list[tuple[float, float]]:
    """Rejection-sample ``count`` points of ``[-limit_x, limit_x] x [-limit_y, limit_y]``.

    New points keep ``min_gap`` from each other and from ``existing``; candidates are drawn
    in batches to keep the number of generator calls small.
    """
    placed = list(existing)
    new: list[tuple[float, float]] = []
    gap_sq = min_gap * min_gap
    for _ in range(_MAX_SAMPLE_TRIES):
        batch = rng.uniform((-limit_x, -limit_y), (limit_x, limit_y), (_SAMPLE_BATCH, 2))
        for x, y in batch.tolist():
            for qx, qy in placed:
                if (x - qx) * (x - qx) + (y - qy) * (y - qy) < gap_sq:
                    break
            else:
                placed.append((x, y))
                new.append((x, y))
                if len(new) == count:
                    return new
    raise RuntimeError(f"{who}: could not place objects without overlap")

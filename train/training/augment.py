"""Augmentations of labelled states: more scenes for a student from the same episodes.

A tabletop observation is laid out in object slots, one per object kind of
:data:`envs.scene.OBJECT_KINDS` (4 colours x 2 shapes). Renaming the colours (red -> blue,
blue -> yellow, ...) in both the scene and the instruction gives another scene whose
correct action is the same: the red cube the gripper is carrying becomes a blue cube
carried the same way, and "put the red cube on the green cylinder" becomes "put the blue
cube on the yellow cylinder". :class:`ColourPermutations` applies such renamings to a
batch of rows (observation slots moved, instruction id replaced), keeping only those whose
renamed instruction is itself a training instruction: held-out word combinations stay
unseen.

A DAgger student fits the states it was shown and generalises little to new scenes
(``benchmarks/distill_data.py``: its action error on held-out episodes falls with every
doubling of the episodes); the permutations multiply the scenes it learns from by up to 24
(18 on average over the robosuite split's training instructions).

:class:`MirrorLeftRight` reflects a scene through the table's centre line (``x`` to
``-x``: every ``x`` of the agent and the object slots, and the action's first value, the
motion along ``x``): "push the red cube left" becomes "push the red cube right" and "left
of" becomes "right of", again only into training instructions. Both tabletops are
symmetric that way (their tables are centred on ``x = 0`` and their arm or pusher starts
on that line).

:func:`augmentation` builds what ``lcrl distill --augment`` names: ``colours``,
``mirror`` or both (``colours+mirror``).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from lcrl.errors import LcrlError
from train.configs.sections import AUGMENTATIONS, augmentation_kinds

__all__ = [
    "AUGMENTATIONS",
    "Augmentation",
    "ColourPermutations",
    "MirrorLeftRight",
    "augmentation",
    "augmentation_kinds",
]

#: Directions and relations a reflection through ``x = 0`` swaps.
MIRRORED = {"left": "right", "right": "left", "left of": "right of", "right of": "left of"}


def _on_slot_entries(
    obs: Mapping[str, np.ndarray], size: int, fn: Callable[[np.ndarray], np.ndarray]
) -> dict[str, np.ndarray]:
    """``obs`` with ``fn`` applied to every entry laid out in the slots (a batch of
    ``size`` values a row: the observation and the instruction's first one)."""
    return {k: fn(v) if v.ndim == 2 and v.shape[1] == size else v for k, v in obs.items()}


def _training_ids(table: Sequence[str], num_train: int) -> tuple[list[Any], dict[str, int]]:
    from captioner.grammar import InstructionParseError, parse

    try:
        meanings = [parse(text) for text in table[:num_train]]
    except InstructionParseError as e:
        raise LcrlError(f"augmentations rename the grammar's instructions: {e}") from None
    return meanings, {text: i for i, text in enumerate(table[:num_train])}


class ColourPermutations:
    """Renamings of the colours of a batch's scenes and instructions.

    Args:
        table: the task's instruction table (canonical texts; the first ``num_train`` are
            the training instructions).
        num_train: how many of ``table`` are training instructions.
        layout: ``(start, count, width)`` of the observation's object slots
            (:func:`envs.features.slot_layout`).
        size: the observation's length (the values after the slots stay in place).

    Raises:
        LcrlError: slots that are not one per object kind, or a training instruction that
            is not a sentence of the grammar.
    """

    def __init__(
        self, table: Sequence[str], num_train: int, layout: tuple[int, int, int], size: int
    ) -> None:
        from envs.scene import COLOURS, OBJECT_KINDS

        start, count, width = layout
        if count != len(OBJECT_KINDS) or start + count * width > size:
            raise LcrlError(
                f"colour permutations need one observation slot per object kind "
                f"({len(OBJECT_KINDS)}); this observation has {count} slots of {width} from "
                f"{start} in {size} values"
            )
        meanings, ids = _training_ids(table, num_train)
        colours = list(COLOURS)
        columns, goals = [], []
        for perm in itertools.permutations(range(len(colours))):
            rename = {colours[i]: colours[j] for i, j in enumerate(perm)}
            cols = np.arange(size)
            for k, (colour, shape) in enumerate(OBJECT_KINDS):
                new = OBJECT_KINDS.index((rename[colour], shape))
                cols[start + new * width : start + (new + 1) * width] = np.arange(
                    start + k * width, start + (k + 1) * width
                )
            goal = np.full(len(table), -1, np.int64)
            for g, m in enumerate(meanings):
                renamed = {"colour": rename[m.colour]}
                if m.target_colour is not None:
                    renamed["target_colour"] = rename[m.target_colour]
                goal[g] = ids.get(dataclasses.replace(m, **renamed).text, -1)
            columns.append(cols)
            goals.append(goal)
        #: ``(permutations, size)``: row ``p`` reads the observation's values in this order.
        self.columns = np.stack(columns)
        #: ``(permutations, len(table))``: the renamed instruction's id, -1 where it is not
        #: a training instruction (permutation 0 is the identity).
        self.goals = np.stack(goals)
        self.size = size

    def per_instruction(self) -> float:
        """Mean number of renamings (the identity included) that keep a training
        instruction a training instruction."""
        trained = self.goals[:, self.goals[0] >= 0]
        return float((trained >= 0).sum(0).mean())

    def apply(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray,
        action: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """A random renaming per row (one that keeps its instruction a training
        instruction; the identity is one of them), applied to every observation entry of
        the slot layout's length and to the goal ids; the actions stay."""
        goal = np.asarray(goal)
        n = len(goal)
        perm = rng.integers(len(self.columns), size=n)
        renamed = self.goals[perm, goal]
        keep = renamed < 0
        perm[keep] = 0
        renamed[keep] = goal[keep]
        rows = np.arange(n)[:, None]
        cols = self.columns[perm]
        return _on_slot_entries(obs, self.size, lambda v: v[rows, cols]), renamed, action


class MirrorLeftRight:
    """Reflections of a batch's scenes through ``x = 0``, instructions and actions alike.

    Args:
        table, num_train: as :class:`ColourPermutations`.
        layout: ``(start, count, width, position_dims)`` of the observation's object slots
            (:func:`envs.features.slot_layout`): the agent's values before ``start`` and
            each slot begin with a position whose first value is ``x``; a slot's relative
            position and displacement (:class:`envs.features.SlotFeatures`) follow its
            ``position_dims + 1`` own values.
        size: the observation's length.
        share: the share of rows reflected (of those whose reflected instruction is a
            training instruction).
    """

    def __init__(
        self,
        table: Sequence[str],
        num_train: int,
        layout: tuple[int, int, int, int],
        size: int,
        share: float = 0.5,
    ) -> None:
        start, count, width, dims = layout
        if start < 1 or width < dims + 1 or start + count * width > size:
            raise LcrlError(
                f"a reflection needs the agent's position and slots that begin with one; this "
                f"observation has {count} slots of {width} from {start} in {size} values"
            )
        meanings, ids = _training_ids(table, num_train)
        goal = np.full(len(table), -1, np.int64)
        for g, m in enumerate(meanings):
            swapped = {
                k: MIRRORED[v]
                for k, v in (("direction", m.direction), ("relation", m.relation))
                if v in MIRRORED
            }
            goal[g] = ids.get(dataclasses.replace(m, **swapped).text, -1)
        own = dims + 1  # position and present flag; then relative position, displacement
        offsets = [0, *range(own, width, dims)]
        #: Observation columns holding an ``x``: negated by a reflection.
        self.columns = np.asarray(
            [0, *(start + k * width + o for k in range(count) for o in offsets)], np.int64
        )
        #: The reflected instruction's id (-1: not a training instruction).
        self.goals = goal
        self.size, self.share = size, float(share)
        #: -1 at :attr:`columns`, 1 elsewhere: a reflected observation is ``obs * sign``.
        self.sign = np.ones(size, np.float32)
        self.sign[self.columns] = -1.0

    def apply(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray,
        action: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """``share`` of the rows reflected (those whose reflected instruction is a training
        instruction): their ``x`` values and the action's first value negated, their
        instruction reflected."""
        goal = np.asarray(goal)
        flip = (rng.random(len(goal)) < self.share) & (self.goals[goal] >= 0)
        rows = flip[:, None]
        out = _on_slot_entries(obs, self.size, lambda v: np.where(rows, v * self.sign, v))
        action = np.asarray(action).copy()
        action[flip, 0] *= -1.0
        return out, np.where(flip, self.goals[goal], goal), action


class Augmentation:
    """Several augmentations applied in turn (:func:`augmentation`)."""

    def __init__(self, kinds: tuple[str, ...], parts: list[Any]) -> None:
        self.kinds, self.parts = kinds, parts

    def apply(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray,
        action: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        out = dict(obs)
        for part in self.parts:
            out, goal, action = part.apply(out, goal, action, rng)
        return out, goal, action

    def describe(self) -> str:
        """What the rows get, in words."""
        said = []
        for kind, part in zip(self.kinds, self.parts, strict=True):
            if kind == "colours":
                said.append(
                    f"colours renamed ({part.per_instruction():.1f} renamings per training "
                    "instruction)"
                )
            else:
                said.append(f"{part.share:.0%} reflected left to right")
        return " and ".join(said)


def augmentation(
    text: str,
    table: Sequence[str],
    num_train: int,
    layout: tuple[int, int, int, int],
    size: int,
    discrete: bool = False,
) -> Augmentation | None:
    """The augmentations ``text`` names (:func:`augmentation_kinds`) for an observation of
    ``size`` values in ``layout`` (:func:`envs.features.slot_layout`); None for none.

    Raises:
        LcrlError: a name that is not known, a reflection of discrete moves, or an
            observation or table the augmentation cannot read.
    """
    kinds = augmentation_kinds(text)
    if not kinds:
        return None
    if "mirror" in kinds and discrete:
        raise LcrlError("--augment mirror reflects continuous actions; these are discrete moves")
    start, count, width, _ = layout
    parts: list[Any] = []
    for kind in kinds:
        if kind == "colours":
            parts.append(ColourPermutations(table, num_train, (start, count, width), size))
        else:
            parts.append(MirrorLeftRight(table, num_train, layout, size))
    return Augmentation(kinds, parts)

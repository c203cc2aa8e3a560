"""Colour permutations of labelled states: more scenes for a student from the same episodes.

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
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence

import numpy as np

from lcrl.errors import LcrlError

__all__ = ["AUGMENTATIONS", "ColourPermutations"]

#: Augmentations of a DAgger student's batches (``lcrl distill --augment``).
AUGMENTATIONS = ("", "colours")


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
        from captioner.grammar import InstructionParseError, parse
        from envs.scene import COLOURS, OBJECT_KINDS

        start, count, width = layout
        if count != len(OBJECT_KINDS) or start + count * width > size:
            raise LcrlError(
                f"colour permutations need one observation slot per object kind "
                f"({len(OBJECT_KINDS)}); this observation has {count} slots of {width} from "
                f"{start} in {size} values"
            )
        try:
            meanings = [parse(text) for text in table[:num_train]]
        except InstructionParseError as e:
            raise LcrlError(f"colour permutations rename the grammar's instructions: {e}") from None
        ids = {text: i for i, text in enumerate(table[:num_train])}
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
        self, obs: Mapping[str, np.ndarray], goal: np.ndarray, rng: np.random.Generator
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """A random renaming per row (one that keeps its instruction a training
        instruction; the identity is one of them), applied to every observation entry of
        the slot layout's length and to the goal ids."""
        goal = np.asarray(goal)
        n = len(goal)
        perm = rng.integers(len(self.columns), size=n)
        renamed = self.goals[perm, goal]
        keep = renamed < 0
        perm[keep] = 0
        renamed[keep] = goal[keep]
        rows = np.arange(n)[:, None]
        cols = self.columns[perm]
        out = {
            k: (v[rows, cols] if v.ndim == 2 and v.shape[1] == self.size else v)
            for k, v in obs.items()
        }
        return out, renamed

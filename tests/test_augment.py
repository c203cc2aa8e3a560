"""Colour permutations of a DAgger student's rows (``lcrl distill --augment colours``): the
scene's object slots and the instruction are renamed alike, and only into training
instructions."""

from __future__ import annotations

import numpy as np
import pytest

from captioner.grammar import parse
from envs.scene import OBJECT_KINDS
from lcrl.errors import LcrlError
from train.training.augment import ColourPermutations

# 2 agent values, 8 slots of 3 (x, y, present), 1 value after the slots
START, COUNT, WIDTH, SIZE = 2, 8, 3, 2 + 8 * 3 + 1
TRAIN = [
    "reach the red cube",
    "reach the green cube",
    "reach the blue cube",
    "put the red cube left of the green cylinder",
    "put the blue cube left of the yellow cylinder",
    "reach the yellow cylinder",  # no other colour's cylinder is a training instruction
]
HELD_OUT = ["reach the yellow cube", "put the green cube left of the red cylinder"]


def _scene(rows: list[tuple[str, str, float, float]]) -> np.ndarray:
    """An observation with the given (colour, shape, x, y) objects present."""
    obs = np.zeros(SIZE, np.float32)
    obs[:START] = (0.1, -0.2)
    obs[-1] = 7.0
    for colour, shape, x, y in rows:
        k = OBJECT_KINDS.index((colour, shape))
        obs[START + k * WIDTH : START + (k + 1) * WIDTH] = (x, y, 1.0)
    return obs


def _objects(obs: np.ndarray) -> dict[tuple[str, str], tuple[float, float]]:
    out = {}
    for k, kind in enumerate(OBJECT_KINDS):
        x, y, present = obs[START + k * WIDTH : START + (k + 1) * WIDTH]
        if present:
            out[kind] = (round(float(x), 3), round(float(y), 3))
    return out


def test_a_renamed_row_moves_its_objects_and_renames_its_instruction_alike():
    perms = ColourPermutations(TRAIN + HELD_OUT, len(TRAIN), (START, COUNT, WIDTH), SIZE)
    scene = _scene([("red", "cube", 0.3, 0.1), ("green", "cylinder", -0.2, 0.4)])
    goal = TRAIN.index("put the red cube left of the green cylinder")
    obs = {"observation": np.tile(scene, (400, 1)), "initial": np.tile(scene, (400, 1))}
    out, goals = perms.apply(obs, np.full(400, goal), np.random.default_rng(0))
    renamed = {TRAIN[g] for g in goals}
    # the only renaming into a training instruction: red -> blue, green -> yellow
    assert renamed == {TRAIN[goal], "put the blue cube left of the yellow cylinder"}
    for row, g in enumerate(goals):
        meaning = parse(TRAIN[g])
        for key in ("observation", "initial"):
            seen = _objects(out[key][row])
            # the object the instruction names sits where the red cube was, its reference
            # where the green cylinder was: the same scene under other names
            assert seen == {meaning.obj: (0.3, 0.1), meaning.target: (-0.2, 0.4)}
            assert out[key][row][:START].tolist() == pytest.approx([0.1, -0.2])
            assert out[key][row][-1] == 7.0


def test_no_row_is_renamed_into_a_held_out_instruction():
    perms = ColourPermutations(TRAIN + HELD_OUT, len(TRAIN), (START, COUNT, WIDTH), SIZE)
    goals = np.repeat(np.arange(len(TRAIN)), 200)
    obs = {"observation": np.zeros((len(goals), SIZE), np.float32)}
    _, renamed = perms.apply(obs, goals, np.random.default_rng(1))
    assert renamed.min() >= 0 and renamed.max() < len(TRAIN)
    # the reaches of cubes rename among themselves; the yellow cylinder has no partner
    cubes = [TRAIN.index(f"reach the {c} cube") for c in ("red", "green", "blue")]
    assert set(renamed[np.isin(goals, cubes)]) == set(cubes)
    alone = TRAIN.index("reach the yellow cylinder")
    assert set(renamed[goals == alone]) == {alone}
    # of the 24 renamings: 18 keep a cube's reach a training one (its colour to red, green
    # or blue, the other three free), 4 each put (itself, or its one partner), 6 the
    # yellow cylinder's (yellow stays)
    assert perms.per_instruction() == pytest.approx((18 * 3 + 4 + 4 + 6) / 6)


def test_layouts_and_tables_that_cannot_be_renamed_are_refused():
    with pytest.raises(LcrlError, match="one observation slot per object kind"):
        ColourPermutations(TRAIN, len(TRAIN), (START, 4, WIDTH), SIZE)
    with pytest.raises(LcrlError, match="rename the grammar's instructions"):
        ColourPermutations(["task 3"], 1, (START, COUNT, WIDTH), SIZE)

"""Augmentations of a DAgger student's rows (``lcrl distill --augment``): colours renamed
and scenes reflected left to right, scene, instruction and action alike, and only into
training instructions."""

from __future__ import annotations

import numpy as np
import pytest

from captioner.grammar import parse
from envs.scene import OBJECT_KINDS
from lcrl.errors import LcrlError
from train.training.augment import ColourPermutations, MirrorLeftRight, augmentation

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
    action = np.tile(np.float32([0.5, -0.5, 0.1, 1.0]), (400, 1))
    out, goals, acted = perms.apply(obs, np.full(400, goal), action, np.random.default_rng(0))
    np.testing.assert_array_equal(acted, action)  # the same motion in the renamed scene
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
    _, renamed, _ = perms.apply(obs, goals, np.zeros((len(goals), 4)), np.random.default_rng(1))
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
    with pytest.raises(LcrlError, match="reflects continuous actions"):
        augmentation("mirror", TRAIN, len(TRAIN), (START, COUNT, WIDTH, 2), SIZE, discrete=True)
    with pytest.raises(LcrlError, match="at most once, joined by"):
        augmentation("colours+shapes", TRAIN, len(TRAIN), (START, COUNT, WIDTH, 2), SIZE)
    assert augmentation("", TRAIN, len(TRAIN), (START, COUNT, WIDTH, 2), SIZE) is None


# 2 agent values (x, y), 8 slots of 7 (x, y, present, relative x, y, displacement x, y)
M_WIDTH, M_SIZE = 7, 2 + 8 * 7
MIRROR_TRAIN = [
    "push the red cube left",
    "push the red cube right",
    "push the blue cube forward",
    "put the red cube left of the green cylinder",
    "put the red cube right of the green cylinder",
    "push the green cube left",  # its reflection is held out
]
MIRROR_HELD = ["push the green cube right"]


def test_a_reflected_row_negates_every_x_the_motion_along_x_and_swaps_left_and_right():
    mirror = MirrorLeftRight(
        MIRROR_TRAIN + MIRROR_HELD, len(MIRROR_TRAIN), (2, 8, M_WIDTH, 2), M_SIZE, share=1.0
    )
    row = np.arange(M_SIZE, dtype=np.float32) + 1.0
    obs = {"observation": np.tile(row, (len(MIRROR_TRAIN), 1))}
    goals = np.arange(len(MIRROR_TRAIN))
    action = np.tile(np.float32([0.5, -0.3]), (len(goals), 1))
    out, reflected, acted = mirror.apply(obs, goals, action, np.random.default_rng(0))
    names = [MIRROR_TRAIN[g] for g in reflected]
    assert names == [
        "push the red cube right",
        "push the red cube left",
        "push the blue cube forward",  # forward stays forward, but the scene is reflected
        "put the red cube right of the green cylinder",
        "put the red cube left of the green cylinder",
        "push the green cube left",  # not reflected: that would be a held-out instruction
    ]
    x_columns = {0} | {2 + k * M_WIDTH + o for k in range(8) for o in (0, 3, 5)}
    for r in range(5):
        for c in range(M_SIZE):
            assert out["observation"][r, c] == (-row[c] if c in x_columns else row[c])
        assert acted[r].tolist() == pytest.approx([-0.5, -0.3])
    np.testing.assert_array_equal(out["observation"][5], row)
    assert acted[5].tolist() == pytest.approx([0.5, -0.3])


def test_a_share_of_the_rows_is_reflected_and_both_augmentations_compose():
    mirror = MirrorLeftRight(MIRROR_TRAIN, len(MIRROR_TRAIN), (2, 8, M_WIDTH, 2), M_SIZE)
    goals = np.zeros(4000, np.int64)
    obs = {"observation": np.ones((4000, M_SIZE), np.float32)}
    _, reflected, _ = mirror.apply(obs, goals, np.ones((4000, 2)), np.random.default_rng(2))
    assert 0.45 < (reflected == 1).mean() < 0.55
    both = augmentation(
        "colours+mirror", MIRROR_TRAIN, len(MIRROR_TRAIN), (2, 8, M_WIDTH, 2), M_SIZE
    )
    assert both.kinds == ("colours", "mirror")
    assert "reflected left to right" in both.describe() and "colours renamed" in both.describe()
    _, g, a = both.apply(obs, goals, np.ones((4000, 2)), np.random.default_rng(3))
    assert set(g) <= set(range(len(MIRROR_TRAIN)))
    # a reflected row's motion along x is negated, the others' kept
    assert set(np.unique(a[:, 0])) == {-1.0, 1.0}

"""Tests for the pure-numpy 2D tabletop (envs/tabletop2d.py)."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs  # registers the gymnasium ids
from envs.scene import COLOURS, OBJECT_KINDS, SceneState
from envs.tabletop2d import (
    DISTANCE_THRESHOLD,
    MAX_STEP,
    OBJECT_HALF_SIZE,
    PUSHER_RADIUS,
    Tabletop2DConfigError,
    Tabletop2DEnv,
)

H = OBJECT_HALF_SIZE
SLOT = {kind: k for k, kind in enumerate(OBJECT_KINDS)}


def place(
    env: Tabletop2DEnv,
    objects: dict[tuple[str, str], tuple[float, float]],
    pusher: tuple[float, float],
) -> None:
    """Overwrite the layout of a reset env (objects must be the scene's kinds)."""
    env._slots = sorted(SLOT[k] for k in objects)
    env._n = len(objects)
    env._cube = [OBJECT_KINDS[s][1] == "cube" for s in env._slots]
    env._ox = [float(objects[OBJECT_KINDS[s]][0]) for s in env._slots]
    env._oy = [float(objects[OBJECT_KINDS[s]][1]) for s in env._slots]
    env._px, env._py = map(float, pusher)
    template = [0.0] * 26
    for s in env._slots:
        template[4 + 3 * s] = 1.0
    env._obs_template = template


def object_xy(obs: dict[str, np.ndarray], kind: tuple[str, str]) -> np.ndarray:
    s = 2 + 3 * SLOT[kind]
    return obs["observation"][s : s + 2].astype(np.float64)


def assert_obs_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


# --------------------------------------------------------------------------- API


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"action_type": "discrete", "num_directions": 4},
        {"action_type": "discrete", "num_directions": 8},
        {"image": True, "render_mode": "rgb_array"},
        {"goal": "pusher"},
        {"num_objects": 2, "objects": [("red", "cube"), ("blue", "cylinder")]},
    ],
    ids=["continuous", "discrete4", "discrete8", "image", "pusher-goal", "restricted"],
)
def test_check_env_passes(kwargs: dict) -> None:
    env = Tabletop2DEnv(**kwargs)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not having a spec.*")
        check_env(env)
    obs, info = env.reset(seed=0)
    assert obs in env.observation_space
    assert info == {"is_success": False}


@pytest.mark.parametrize(
    ("env_id", "action_space"),
    [
        ("lcrl/Tabletop2D-v0", gym.spaces.Box(-1.0, 1.0, (2,), np.float32)),
        ("lcrl/Tabletop2DDiscrete-v0", gym.spaces.Discrete(9)),
    ],
)
def test_registered_ids(env_id: str, action_space: gym.Space) -> None:
    env = gym.make(env_id)
    assert env.action_space == action_space
    assert env.spec is not None and env.spec.max_episode_steps == 50
    check_env(env.unwrapped)  # with a spec, this also exercises render modes and close
    env.reset(seed=1)
    env.action_space.seed(1)
    truncated = False
    steps = 0
    while not truncated:
        _, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert terminated is False
        assert reward in (0.0, 1.0) and isinstance(info["is_success"], bool)
        steps += 1
    assert steps == 50


def test_action_space_sample_matches_plain_box() -> None:
    space = Tabletop2DEnv().action_space
    plain = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    assert space == plain and plain == space
    space.seed(5)
    plain.seed(5)
    for _ in range(200):
        sample = space.sample()
        assert sample.dtype == np.float32 and sample in plain
        np.testing.assert_array_equal(sample, plain.sample())
    with pytest.raises(gym.error.Error, match="mask"):
        space.sample(mask=np.ones(2))


def test_make_passes_kwargs_through() -> None:
    env = gym.make("lcrl/Tabletop2D-v0", image=True, image_size=32, goal="pusher", num_objects=3)
    obs, _ = env.reset(seed=0)
    assert obs["image"].shape == (32, 32, 3)
    assert obs["desired_goal"].shape == (2,)
    assert len(env.unwrapped.scene()) == 3
    # Re-registering (re-import) must not fail or warn about overriding.
    envs._register()
    assert "lcrl/Tabletop2D-v0" in gym.registry


def test_observation_layout() -> None:
    env = Tabletop2DEnv(num_objects=(2, 4))
    counts = set()
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        o = obs["observation"]
        assert o.dtype == np.float32 and o.shape == (26,)
        slots = o[2:].reshape(8, 3)
        present = slots[:, 2]
        assert set(np.unique(present)) <= {0.0, 1.0}
        counts.add(int(present.sum()))
        assert np.all(slots[present == 0] == 0.0)  # absent kinds are all zeros
        ag = obs["achieved_goal"].reshape(8, 2)
        np.testing.assert_array_equal(ag, slots[:, :2])
        dg = obs["desired_goal"].reshape(8, 2)
        assert np.all(dg[present == 0] == 0.0)
        moved = np.linalg.norm(dg - ag, axis=1)
        assert (moved > 0).sum() == 1 and moved.max() >= 0.08 - 1e-6  # exactly one object moves
        assert np.all(np.abs(dg) <= 0.2 + 1e-6)
    assert counts == {2, 3, 4}


def test_restricted_kinds_and_fixed_count() -> None:
    kinds = [("red", "cube"), ("green", "cylinder"), ("yellow", "cube")]
    env = Tabletop2DEnv(num_objects=3, objects=kinds)
    for seed in range(5):
        env.reset(seed=seed)
        scene = env.scene()
        assert sorted(zip(scene.colours, scene.shapes, strict=True)) == sorted(kinds)


# --------------------------------------------------------------------------- determinism


def test_determinism_same_seed_same_actions() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (60, 2)).astype(np.float32)
    runs = []
    for _ in range(2):
        env = Tabletop2DEnv(image=True)
        trajectory = [env.reset(seed=42)[0]]
        trajectory += [env.step(a)[0] for a in actions]
        runs.append(trajectory)
    for a, b in zip(*runs, strict=True):
        assert_obs_equal(a, b)


def test_different_seeds_give_different_layouts() -> None:
    env = Tabletop2DEnv()
    layouts = {env.reset(seed=seed)[0]["observation"].tobytes() for seed in range(10)}
    assert len(layouts) == 10


def test_reset_layout_has_no_overlap() -> None:
    env = Tabletop2DEnv(num_objects=4)
    for seed in range(50):
        env.reset(seed=seed)
        scene = env.scene()
        xy = scene.positions[:, :2]
        assert np.all(np.abs(xy) <= 0.2)
        dist = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        assert dist[~np.eye(4, dtype=bool)].min() >= 0.08
        assert np.linalg.norm(xy - scene.gripper[:2], axis=1).min() >= 0.06
        assert not scene.touching.any()


# --------------------------------------------------------------------------- physics


@pytest.mark.parametrize("shape", ["cube", "cylinder"])
@pytest.mark.parametrize("direction", [(1, 0), (0, 1), (-1, 0), (0, -1)])
def test_scripted_push_moves_object(shape: str, direction: tuple[int, int]) -> None:
    env = Tabletop2DEnv(num_objects=2)
    env.reset(seed=0)
    target, other = ("red", shape), ("blue", "cube")
    d = np.array(direction, dtype=np.float64)
    start = np.zeros(2)
    pusher = start - d * (H + PUSHER_RADIUS + 0.01)  # 1 cm behind the object
    # Keep the other object well away from the push path.
    place(env, {target: (0.0, 0.0), other: tuple(-0.15 * d + 0.15 * d[::-1])}, pusher)
    steps = 6
    for _ in range(steps):
        obs, *_ = env.step(d.astype(np.float32))
    travel = steps * MAX_STEP
    moved = object_xy(obs, target) - start
    # It moves along the push by the pusher's travel minus the initial 1 cm gap.
    assert moved @ d == pytest.approx(travel - 0.01, abs=1e-4)
    assert abs(moved @ d[::-1]) < 1e-6  # and not sideways
    np.testing.assert_allclose(obs["observation"][:2], pusher + travel * d, atol=1e-6)
    assert env.scene().touching[env.scene().index(*target)]
    np.testing.assert_allclose(object_xy(obs, other), -0.15 * d + 0.15 * d[::-1], atol=1e-6)


def test_push_against_edge_blocks_pusher() -> None:
    env = Tabletop2DEnv(num_objects=2)
    env.reset(seed=0)
    place(env, {("red", "cube"): (0.2, 0.0), ("blue", "cube"): (-0.1, -0.1)}, (0.14, 0.0))
    for _ in range(10):
        obs, *_ = env.step(np.array([1.0, 0.0], np.float32))
    # The cube stops at the table edge; the pusher stops against it.
    assert object_xy(obs, ("red", "cube"))[0] == pytest.approx(0.25 - H, abs=1e-6)
    assert obs["observation"][0] == pytest.approx(0.25 - 2 * H - PUSHER_RADIUS, abs=1e-6)


def test_push_one_object_into_another() -> None:
    env = Tabletop2DEnv(num_objects=2)
    env.reset(seed=0)
    a, b = ("red", "cylinder"), ("green", "cylinder")
    place(env, {a: (-0.05, 0.0), b: (0.01, 0.0)}, (-0.1, 0.0))
    for _ in range(10):
        obs, *_ = env.step(np.array([1.0, 0.0], np.float32))
    xa, xb = object_xy(obs, a)[0], object_xy(obs, b)[0]
    assert xb > 0.05  # the second object was pushed along too
    assert xb - xa == pytest.approx(2 * H, abs=2e-3)  # in contact, not overlapping
    assert obs["observation"][0] < xa - H  # the pusher stays behind the first object


def penetration(gap: np.ndarray, a_cube: bool, ra: float, b_cube: bool, rb: float) -> float:
    """Penetration depth of two shapes whose centres differ by ``gap`` (<= 0: apart)."""
    g = np.abs(gap)
    if a_cube and b_cube:  # two axis-aligned squares
        return float(min(ra + rb - g[0], ra + rb - g[1]))
    if not a_cube and not b_cube:  # two discs
        return float(ra + rb - np.linalg.norm(g))
    h, r = (ra, rb) if a_cube else (rb, ra)  # square of half size h, disc of radius r
    if g[0] <= h and g[1] <= h:  # disc centre inside the square
        return float(r + min(h - g[0], h - g[1]))
    return float(r - np.linalg.norm(np.maximum(g - h, 0.0)))


def overlaps(env: Tabletop2DEnv) -> tuple[float, float]:
    """Largest object-object and pusher-object penetration depth (m), from the scene."""
    scene = env.scene()
    xy = scene.positions[:, :2]
    cubes = [shape == "cube" for shape in scene.shapes]
    worst_objects = worst_pusher = 0.0
    for i in range(len(scene)):
        gap = xy[i] - scene.gripper[:2]
        worst_pusher = max(worst_pusher, penetration(gap, False, PUSHER_RADIUS, cubes[i], H))
        for j in range(i + 1, len(scene)):
            pen = penetration(xy[j] - xy[i], cubes[i], H, cubes[j], H)
            worst_objects = max(worst_objects, pen)
    return worst_objects, worst_pusher


def test_random_pushing_keeps_objects_in_bounds_and_apart() -> None:
    env = Tabletop2DEnv(num_objects=4)
    rng = np.random.default_rng(0)
    worst_objects = worst_pusher = 0.0
    pushes = 0
    for episode in range(20):
        obs, _ = env.reset(seed=episode)
        start = obs["observation"].copy()
        for t in range(60):
            # Chase a random object so that many contacts (and wedges) happen.
            if t % 20 == 0:
                target = int(rng.integers(env._n))
            to = np.array([env._ox[target] - env._px, env._oy[target] - env._py])
            action = to / (np.linalg.norm(to) + 1e-9) + rng.normal(0.0, 0.3, 2)
            obs, *_ = env.step(np.clip(action, -1, 1).astype(np.float32))
            o = obs["observation"]
            assert np.all(np.abs(o[:2]) <= 0.25 - PUSHER_RADIUS + 1e-6)
            xy = o[2:].reshape(8, 3)[:, :2]
            assert np.all(np.abs(xy) <= 0.25 - H + 1e-6)
            worst = overlaps(env)
            worst_objects = max(worst_objects, worst[0])
            worst_pusher = max(worst_pusher, worst[1])
        pushes += int(np.any(o[2:] != start[2:]))
    assert pushes >= 15  # the chasing policy really moved objects
    assert worst_objects < 3e-3
    assert worst_pusher < 1e-3


@pytest.mark.parametrize("num_directions", [4, 8])
def test_discrete_directions(num_directions: int) -> None:
    env = Tabletop2DEnv(action_type="discrete", num_directions=num_directions, num_objects=2)
    env.reset(seed=0)
    assert env.action_space == gym.spaces.Discrete(1 + num_directions)
    for k in range(1 + num_directions):
        # Objects far in a corner, pusher in the middle: free motion.
        place(env, {("red", "cube"): (-0.2, -0.2), ("blue", "cube"): (-0.2, 0.2)}, (0.05, 0.0))
        obs, *_ = env.step(k)
        delta = obs["observation"][:2].astype(np.float64) - (0.05, 0.0)
        if k == 0:
            np.testing.assert_allclose(delta, 0.0, atol=1e-7)
            continue
        angle = 2 * math.pi * (k - 1) / num_directions
        expected = MAX_STEP * np.array([math.cos(angle), math.sin(angle)])
        np.testing.assert_allclose(delta, expected, atol=1e-6)
    with pytest.raises(ValueError, match="discrete action"):
        env.step(num_directions + 1)


def test_continuous_action_is_clipped() -> None:
    env = Tabletop2DEnv(num_objects=2)
    env.reset(seed=0)
    place(env, {("red", "cube"): (-0.2, -0.2), ("blue", "cube"): (-0.2, 0.2)}, (0.0, 0.0))
    obs, *_ = env.step(np.array([5.0, -0.5], np.float32))
    np.testing.assert_allclose(obs["observation"][:2], (MAX_STEP, -0.5 * MAX_STEP), atol=1e-7)
    obs, *_ = env.step([0.0, 1.0])  # lists work too
    np.testing.assert_allclose(obs["observation"][:2], (MAX_STEP, 0.5 * MAX_STEP), atol=1e-7)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0.0], np.float32))


# --------------------------------------------------------------------------- goals and rewards


@pytest.mark.parametrize("goal", ["object", "pusher"])
def test_compute_reward_batched_matches_single(goal: str) -> None:
    env = Tabletop2DEnv(goal=goal)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    dim = obs["desired_goal"].shape[0]
    achieved = np.repeat(obs["achieved_goal"][None], 64, axis=0)
    desired = np.repeat(obs["desired_goal"][None], 64, axis=0)
    # Half the batch: achieved == desired (success); the rest perturbed around the threshold.
    achieved[:32] = desired[:32]
    achieved[32:] = desired[32:] + rng.normal(0.0, DISTANCE_THRESHOLD / 2, (32, dim))
    batch = env.compute_reward(achieved, desired, {})
    assert batch.dtype == np.float32 and batch.shape == (64,)
    single = [env.compute_reward(a, d, {}) for a, d in zip(achieved, desired, strict=True)]
    assert all(isinstance(r, float) for r in single)
    np.testing.assert_array_equal(batch, np.array(single, np.float32))
    assert np.all(batch[:32] == 1.0)
    assert 0 < batch[32:].sum() < 32  # both outcomes occur in the perturbed half
    # Extra leading dimensions work too.
    assert env.compute_reward(
        achieved.reshape(8, 8, dim), desired.reshape(8, 8, dim), None
    ).shape == (
        8,
        8,
    )
    with pytest.raises(ValueError, match="last dimension"):
        env.compute_reward(np.zeros(dim + 1), np.zeros(dim + 1), None)


def test_object_goal_success_when_object_reaches_target() -> None:
    env = Tabletop2DEnv(num_objects=2)
    obs, _ = env.reset(seed=3)
    assert env.compute_reward(obs["achieved_goal"], obs["desired_goal"], None) == 0.0
    # Teleport the moved object onto its target: success, and step/compute_reward agree.
    diff = (obs["desired_goal"] - obs["achieved_goal"]).reshape(8, 2)
    slot = int(np.flatnonzero(np.linalg.norm(diff, axis=1))[0])
    i = env._slots.index(slot)
    env._ox[i], env._oy[i] = map(float, obs["desired_goal"][2 * slot : 2 * slot + 2])
    env._px, env._py = 0.24, 0.24
    place_free = env._ox[1 - i], env._oy[1 - i]
    assert math.dist(place_free, (0.24, 0.24)) > 0.06
    obs, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))
    assert reward == 1.0 and info == {"is_success": True}
    assert env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info) == 1.0
    assert not terminated and not truncated


def test_pusher_goal_reward() -> None:
    env = Tabletop2DEnv(goal="pusher", num_objects=2)
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs["achieved_goal"], obs["observation"][:2])
    assert not info["is_success"]
    place(env, {("red", "cube"): (-0.2, -0.2), ("blue", "cube"): (-0.2, 0.2)}, (0.0, 0.0))
    goal = obs["desired_goal"].astype(np.float64)
    env._px, env._py = goal[0] - 0.02, goal[1]
    obs, reward, *_, info = env.step(np.zeros(2, np.float32))
    assert reward == 1.0 and info["is_success"]
    env._px, env._py = goal[0] - 0.04, goal[1]
    obs, reward, *_, info = env.step(np.zeros(2, np.float32))
    assert reward == 0.0 and not info["is_success"]


def test_step_reward_always_matches_compute_reward() -> None:
    env = Tabletop2DEnv(goal="pusher", num_objects=2)
    rng = np.random.default_rng(1)
    successes = 0
    for episode in range(10):
        obs, _ = env.reset(seed=episode)
        for _ in range(50):
            to_goal = obs["desired_goal"] - obs["achieved_goal"]
            action = np.clip(to_goal / MAX_STEP + rng.normal(0, 0.5, 2), -1, 1)
            obs, reward, _, _, info = env.step(action.astype(np.float32))
            assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
            assert info["is_success"] == (reward == 1.0)
            successes += int(reward)
    assert successes > 0


# --------------------------------------------------------------------------- scene and image


def test_scene_matches_observation() -> None:
    env = Tabletop2DEnv(num_objects=(2, 4))
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        scene = env.scene()
        assert isinstance(scene, SceneState)
        o = obs["observation"]
        np.testing.assert_allclose(scene.gripper, (o[0], o[1], 0.01), atol=1e-7)
        slots = o[2:].reshape(8, 3)
        assert len(scene) == int(slots[:, 2].sum())
        for i, (colour, shape) in enumerate(zip(scene.colours, scene.shapes, strict=True)):
            s = SLOT[(colour, shape)]
            assert slots[s, 2] == 1.0
            np.testing.assert_allclose(scene.positions[i], (*slots[s, :2], H), atol=1e-7)
        np.testing.assert_array_equal(scene.half_extents, np.full((len(scene), 3), H))
        assert scene.table_bounds == (-0.25, 0.25, -0.25, 0.25)
        assert scene.table_height == 0.0
        assert not scene.grasped.any()


def test_scene_touching() -> None:
    env = Tabletop2DEnv(num_objects=2)
    env.reset(seed=0)
    kinds = {("red", "cube"): (0.0, 0.0), ("blue", "cylinder"): (0.15, 0.15)}
    # Cube face at x = 0.025: pusher edge 0.5 mm away touches, 2 mm away does not.
    place(env, kinds, (H + PUSHER_RADIUS + 5e-4, 0.0))
    assert env.scene().touching.tolist() == [True, False]
    place(env, kinds, (H + PUSHER_RADIUS + 2e-3, 0.0))
    assert env.scene().touching.tolist() == [False, False]
    place(env, kinds, (0.15, 0.15 - 2 * H - PUSHER_RADIUS - 5e-4 + H))
    assert env.scene().touching.tolist() == [False, True]


def test_image_observation_and_render() -> None:
    size = 64
    env = Tabletop2DEnv(image=True, image_size=size, render_mode="rgb_array", num_objects=2)
    obs, _ = env.reset(seed=0)
    img = obs["image"]
    assert img.shape == (size, size, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(env.render(), img)
    red = np.array(COLOURS["red"])
    for pos in [(0.12, 0.15), (-0.17, -0.05)]:  # right/away, then left/near
        place(env, {("red", "cube"): pos, ("blue", "cylinder"): (0.0, -0.2)}, (-0.2, 0.2))
        img = env.step(np.zeros(2, np.float32))[0]["image"]
        mask = np.all(np.abs(img.astype(int) - red) <= 10, axis=-1)
        rows, cols = np.nonzero(mask)
        # x right -> column, y away from the viewer -> up (smaller row).
        px_per_m = size / 0.5
        expected_col = (pos[0] + 0.25) * px_per_m - 0.5
        expected_row = (0.25 - pos[1]) * px_per_m - 0.5
        assert cols.mean() == pytest.approx(expected_col, abs=0.5)
        assert rows.mean() == pytest.approx(expected_row, abs=0.5)
        side = 2 * H * px_per_m  # 6.4 px: a filled square of about that side
        assert 0.6 * side**2 <= mask.sum() <= 1.2 * side**2
    no_render = Tabletop2DEnv(num_objects=2)
    no_render.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert no_render.render() is None


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_objects": 5}, "num_objects"),
        ({"num_objects": 1}, "num_objects"),
        ({"num_objects": (3, 2)}, "num_objects"),
        ({"num_objects": (2, 5)}, "num_objects"),
        ({"num_objects": "3"}, "num_objects"),
        ({"num_objects": True}, "num_objects"),
        ({"objects": [("purple", "cube"), ("red", "cube")]}, "objects"),
        ({"objects": [("red", "sphere"), ("red", "cube")]}, "objects"),
        ({"objects": [("red", "cube"), ("red", "cube")]}, "objects"),
        ({"objects": [("red", "cube")], "num_objects": 2}, "objects"),
        ({"objects": "red cube"}, "objects"),
        ({"action_type": "joint"}, "action_type"),
        ({"num_directions": 6}, "num_directions"),
        ({"goal": "gripper"}, "goal"),
        ({"image": "yes"}, "image"),
        ({"image_size": 8}, "image_size"),
        ({"image_size": 64.0}, "image_size"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_bad_kwargs_raise_value_error(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name) as excinfo:
        Tabletop2DEnv(**kwargs)
    assert isinstance(excinfo.value, Tabletop2DConfigError)
    message = str(excinfo.value)
    assert repr(kwargs[name]) in message  # names the bad value
    assert "expected" in message or "needs" in message or "twice" in message


def test_bad_kwargs_through_make() -> None:
    with pytest.raises(ValueError, match="num_objects=5"):
        gym.make("lcrl/Tabletop2D-v0", num_objects=5)


def test_step_before_reset_raises() -> None:
    with pytest.raises(RuntimeError, match="reset"):
        Tabletop2DEnv().step(np.zeros(2, np.float32))

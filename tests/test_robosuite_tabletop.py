"""Tests for the robosuite Panda tabletop (envs/robosuite_tabletop.py).

Environments are built once per module (building one takes a second or two); every test
resets them with its own seed.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import warnings
from collections.abc import Iterator

import pytest

import envs.robosuite_tabletop as rt  # imports neither robosuite nor mujoco

with rt._quiet_robosuite():  # robosuite logs warnings about optional extras on import
    pytest.importorskip("robosuite")

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env

import envs  # registers the gymnasium ids
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner
from envs.robosuite_tabletop import (
    OBJECT_HALF_SIZE,
    TABLE_HEIGHT,
    RobosuiteMissingError,
    RobosuiteTabletopConfigError,
    RobosuiteTabletopEnv,
)
from envs.scene import OBJECT_KINDS, SceneState
from lcrl.errors import LcrlError

SIZE = 64


@pytest.fixture(scope="module")
def env() -> Iterator[RobosuiteTabletopEnv]:
    e = RobosuiteTabletopEnv(image=True, eye_in_hand=True, image_size=SIZE)
    yield e
    e.close()


@pytest.fixture(scope="module")
def gripper_env() -> Iterator[gym.Env]:
    e = gym.make(
        "lcrl/RobosuiteTabletop-v0", goal="gripper", num_objects=3, render_mode="rgb_array"
    )
    yield e
    e.close()


def up(dz: float) -> np.ndarray:
    """A vertical offset."""
    return np.array([0.0, 0.0, dz])


def move_to(
    env: RobosuiteTabletopEnv, target: np.ndarray, grip: float, steps: int, tol: float = 0.005
) -> dict[str, np.ndarray]:
    """Drive the gripper towards a viewer-frame point with a proportional controller."""
    obs: dict[str, np.ndarray] = {}
    for _ in range(steps):
        delta = np.asarray(target) - env.scene().gripper
        obs, *_ = env.step(np.array([*np.clip(delta / 0.05, -1.0, 1.0), grip]))
        if np.linalg.norm(delta) < tol:
            break
    return obs


def gripper_column(env: RobosuiteTabletopEnv) -> float:
    """Mean image column of the gripper's pixels in the agentview camera (segmentation)."""
    import mujoco

    with rt._make_renderer(mujoco, env.model, SIZE) as renderer:
        renderer.enable_segmentation_rendering()
        renderer.update_scene(env.data, camera="agentview", scene_option=env._vopt)
        seg = renderer.render()
    gripper_geoms = np.flatnonzero(env._geom_grip > 0)
    mask = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], gripper_geoms)
    assert mask.sum() > 5, "the gripper is not visible in the agentview image"
    return float(np.nonzero(mask)[1].mean())


# --------------------------------------------------------------------------- API


def test_spaces_and_check_env(env: RobosuiteTabletopEnv) -> None:
    spaces = env.observation_space.spaces
    assert env.action_space.shape == (4,)
    assert spaces["observation"].shape == (36,)
    assert spaces["achieved_goal"].shape == spaces["desired_goal"].shape == (24,)
    assert spaces["image"].shape == spaces["eye_image"].shape == (SIZE, SIZE, 3)
    assert env.instruction_families == ("reach", "push", "put", "lift", "stack")
    check_env(env, skip_render_check=True)


def test_registered_gripper_goal(gripper_env: gym.Env) -> None:
    assert gripper_env.spec is not None and gripper_env.spec.max_episode_steps == 100
    unwrapped = gripper_env.unwrapped
    assert isinstance(unwrapped, RobosuiteTabletopEnv)
    check_env(unwrapped, skip_render_check=True, skip_close_check=True)
    obs, info = gripper_env.reset(seed=3)
    assert "image" not in obs
    frame = gripper_env.render()
    assert frame.shape == (84, 84, 3) and frame.dtype == np.uint8
    assert obs["achieved_goal"].shape == obs["desired_goal"].shape == (3,)
    np.testing.assert_allclose(obs["achieved_goal"], obs["observation"][:3])
    target = obs["desired_goal"].astype(np.float64)
    assert target[2] > TABLE_HEIGHT
    assert unwrapped.compute_reward(obs["achieved_goal"], target) == 0.0
    obs = move_to(unwrapped, target, -1.0, 40)
    _, reward, _, _, info = gripper_env.step(np.array([0.0, 0.0, 0.0, -1.0]))
    assert reward == 1.0 and info["is_success"]


def test_compute_reward_vectorised(env: RobosuiteTabletopEnv) -> None:
    obs, _ = env.reset(seed=0)
    ag = np.stack([obs["achieved_goal"], obs["desired_goal"]])
    dg = np.stack([obs["desired_goal"], obs["desired_goal"]])
    np.testing.assert_array_equal(env.compute_reward(ag, dg, None), [0.0, 1.0])
    assert env.compute_reward(obs["desired_goal"], obs["desired_goal"]) == 1.0


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_objects": 5}, "num_objects"),
        ({"num_objects": (3, 2)}, "num_objects"),
        ({"objects": [("red", "cube")], "num_objects": 2}, "objects"),
        ({"objects": [("pink", "cube"), ("red", "cube")]}, "objects"),
        ({"goal": "pusher"}, "goal"),
        ({"image": 1}, "image"),
        ({"image_size": 100}, "image_size"),
        ({"control_freq": 30}, "control_freq"),
        ({"controller_period": 0}, "controller_period"),
        ({"controller_period": 26}, "controller_period"),
        ({"init_noise": -0.1}, "init_noise"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_bad_arguments(kwargs: dict, name: str) -> None:
    with pytest.raises(RobosuiteTabletopConfigError, match=name) as info:
        RobosuiteTabletopEnv(**kwargs)
    assert isinstance(info.value, ValueError) and isinstance(info.value, LcrlError)


def test_missing_robosuite_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import envs.robosuite_backend as backend

    monkeypatch.setattr(backend, "_BACKEND", {})  # robosuite not imported yet
    monkeypatch.setitem(sys.modules, "robosuite.controllers", None)
    with pytest.raises(RobosuiteMissingError, match=r"pip install -e \"\.\[robot\]\"") as info:
        RobosuiteTabletopEnv()
    assert isinstance(info.value, LcrlError)


def test_importing_envs_does_not_import_robosuite() -> None:
    code = (
        "import sys, gymnasium, envs\n"
        "assert 'lcrl/RobosuiteTabletop-v0' in gymnasium.registry\n"
        "assert 'robosuite' not in sys.modules and 'mujoco' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=envs.__path__[0] + "/..")


# --------------------------------------------------------------------------- layouts


def test_object_count_and_no_overlap(env: RobosuiteTabletopEnv) -> None:
    counts = set()
    xmin, xmax, ymin, ymax = env.table_bounds
    for seed in range(12):
        env.reset(seed=seed)
        s = env.scene()
        assert isinstance(s, SceneState)
        assert 2 <= len(s) <= 4
        counts.add(len(s))
        xy = s.positions[:, :2]
        gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + 10 * np.eye(len(s))
        assert gaps.min() >= 0.08 - 1e-3
        assert np.all((xy[:, 0] > xmin) & (xy[:, 0] < xmax) & (xy[:, 1] > ymin))
        assert np.all(xy[:, 1] < ymax)
        np.testing.assert_allclose(s.positions[:, 2], TABLE_HEIGHT + OBJECT_HALF_SIZE, atol=2e-3)
        assert s.table_height == TABLE_HEIGHT
        assert not s.grasped.any() and not s.touching.any()
    assert counts == {2, 3, 4}


def test_seeded_layouts(env: RobosuiteTabletopEnv) -> None:
    a, _ = env.reset(seed=7)
    b, _ = env.reset(seed=7)
    c, _ = env.reset(seed=8)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert not np.array_equal(a["observation"], c["observation"])


def test_absent_kinds_are_zero(env: RobosuiteTabletopEnv) -> None:
    obs, _ = env.reset(seed=5)
    s = env.scene()
    o = obs["observation"]
    for k, kind in enumerate(OBJECT_KINDS):
        slot = o[4 + 4 * k : 8 + 4 * k]
        if s.index(*kind) < 0:
            np.testing.assert_array_equal(slot, 0.0)
            np.testing.assert_array_equal(obs["achieved_goal"][3 * k : 3 * k + 3], 0.0)
        else:
            assert slot[3] == 1.0
            np.testing.assert_allclose(slot[:3], s.positions[s.index(*kind)], atol=1e-5)
    # Exactly one present object has a different target.
    moved = (
        np.linalg.norm((obs["desired_goal"] - obs["achieved_goal"]).reshape(8, 3), axis=-1) > 0.05
    )
    assert moved.sum() == 1 and o[4 + 4 * int(np.argmax(moved)) + 3] == 1.0


def test_relative_positions_in_3d(env: RobosuiteTabletopEnv) -> None:
    from envs.features import RelativePositions, slot_layout

    wrapped = RelativePositions(env)
    assert slot_layout(wrapped) == (4, 8, 7, 3)
    obs, _ = wrapped.reset(seed=5)
    x = obs["observation"]
    assert x.shape == (4 + 8 * 7,) and wrapped.observation_space["observation"].contains(x)
    s = env.scene()
    for k, kind in enumerate(OBJECT_KINDS):
        slot = x[4 + 7 * k : 11 + 7 * k]
        if s.index(*kind) < 0:
            np.testing.assert_array_equal(slot, 0.0)
        else:
            np.testing.assert_allclose(slot[4:], s.positions[s.index(*kind)] - s.gripper, atol=1e-5)


def test_displacements_in_3d(env: RobosuiteTabletopEnv) -> None:
    from envs.features import SlotFeatures, slot_layout

    wrapped = SlotFeatures(env, relative=False, displacement=True)
    assert slot_layout(wrapped) == (4, 8, 7, 3)
    obs, _ = wrapped.reset(seed=6)
    start = env.scene()
    np.testing.assert_array_equal(obs["observation"][4:].reshape(8, 7)[:, 4:], 0.0)
    for _ in range(5):  # objects settle and may shift a little; the features follow them
        obs, *_ = wrapped.step(np.array([0.0, 0.0, -1.0, -1.0]))
    slots, now = obs["observation"][4:].reshape(8, 7), env.scene()
    for k, kind in enumerate(OBJECT_KINDS):
        i = now.index(*kind)
        if i < 0:
            np.testing.assert_array_equal(slots[k], 0.0)
        else:
            moved = now.positions[i] - start.positions[i]
            np.testing.assert_allclose(slots[k, 4:], moved, atol=1e-5)


def test_reset_keeps_the_model(env: RobosuiteTabletopEnv) -> None:
    model, data = env.model, env.data
    for seed in range(5):
        env.reset(seed=seed)
    assert env.model is model and env.data is data
    assert env._task.sim.model._model is model


# --------------------------------------------------------------------------- images, frame


def test_images_and_viewer_frame(env: RobosuiteTabletopEnv) -> None:
    obs, _ = env.reset(seed=2)
    for key in ("image", "eye_image"):
        assert obs[key].shape == (SIZE, SIZE, 3) and obs[key].dtype == np.uint8
    # Bring the gripper down into the picture, left of the centre.
    start = env.scene().gripper
    obs = move_to(env, np.array([-0.08, start[1] - 0.05, TABLE_HEIGHT + 0.1]), -1.0, 30)
    before_image, before_eye = obs["image"], obs["eye_image"]
    x0 = env.scene().gripper[0]
    col0 = gripper_column(env)
    for _ in range(8):
        obs, *_ = env.step(np.array([1.0, 0.0, 0.0, -1.0]))
    assert env.scene().gripper[0] > x0 + 0.04
    assert gripper_column(env) > col0 + 3  # further right in the image
    assert np.abs(obs["image"].astype(int) - before_image).sum() > 0
    assert np.abs(obs["eye_image"].astype(int) - before_eye).sum() > 0
    # Image up is up: the (white) table fills the bottom rows.
    assert obs["image"][-4:].mean() > 180


# --------------------------------------------------------------------------- scripted skills


def test_reach_touches_object(env: RobosuiteTabletopEnv) -> None:
    env.reset(seed=4)
    s0 = env.scene()
    target = s0.positions[0]
    # Closed fingers come down on top of the object.
    move_to(env, target + up(0.08), 1.0, 40)
    assert not env.scene().touching[0]
    move_to(env, target + up(0.02), 1.0, 30)
    for _ in range(3):
        env.step(np.array([0.0, 0.0, -0.5, 1.0]))
    s = env.scene()
    assert s.touching[0] and not s.grasped[0]
    assert RuleCaptioner().satisfied(f"reach the {s0.names[0]}", s0, s)


def test_grasp_and_lift_cube(env: RobosuiteTabletopEnv) -> None:
    env.reset(seed=1)
    s0 = env.scene()
    k = next(i for i, shape in enumerate(s0.shapes) if shape == "cube")
    cube = s0.positions[k]
    move_to(env, cube + up(0.08), -1.0, 40)
    move_to(env, cube, -1.0, 30)
    for _ in range(8):
        env.step(np.array([0.0, 0.0, 0.0, 1.0]))
    assert env.scene().grasped[k]
    move_to(env, cube + up(0.12), 1.0, 30)
    s = env.scene()
    assert s.grasped[k]
    assert s.positions[k, 2] > cube[2] + 0.08
    assert RuleCaptioner().satisfied(f"lift the {s0.names[k]}", s0, s)


# --------------------------------------------------------------------------- robustness


def test_nan_state_truncates_cleanly(
    env: RobosuiteTabletopEnv, monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo appends its warning to ./MUJOCO_LOG.TXT
    env.reset(seed=0)
    errors = env.sim_errors
    env.data.qvel[:] = np.nan
    with pytest.warns(RuntimeWarning, match="simulation error"):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4))
    assert truncated and not terminated and reward == 0.0
    assert "qvel" in info["sim_error"]
    assert env.sim_errors == errors + 1
    assert all(np.isfinite(v).all() for v in obs.values())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, _, _, truncated, info = env.step(np.zeros(4))  # no new error, still truncated
    assert truncated and "sim_error" in info and env.sim_errors == errors + 1
    env.reset(seed=0)
    _, _, _, truncated, info = env.step(np.zeros(4))
    assert not truncated and "sim_error" not in info


def test_simulator_exception_truncates_cleanly(
    env: RobosuiteTabletopEnv, monkeypatch: pytest.MonkeyPatch
) -> None:
    env.reset(seed=0)
    errors = env.sim_errors

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(env._task, "step", boom)
    with pytest.warns(RuntimeWarning, match="solver exploded"):
        _, _, _, truncated, info = env.step(np.zeros(4))
    assert truncated and info["sim_error"] == "RuntimeError: solver exploded"
    assert env.sim_errors == errors + 1
    monkeypatch.undo()
    env.reset(seed=1)
    _, _, _, truncated, _ = env.step(np.zeros(4))
    assert not truncated


@pytest.mark.parametrize("how", ["direct", "cause", "context"])
def test_a_signal_inside_the_simulator_stops_the_run_instead_of_truncating(
    env: RobosuiteTabletopEnv, monkeypatch: pytest.MonkeyPatch, how: str
) -> None:
    """A SIGTERM handler's exception raised inside numba code comes back as a SystemError."""
    from train.training.trainer import RunInterrupted

    env.reset(seed=0)
    errors = env.sim_errors
    stop = RunInterrupted(signal.SIGTERM)

    def interrupted(*args: object, **kwargs: object) -> None:
        if how == "direct":
            raise stop
        if how == "cause":
            raise SystemError("CPUDispatcher(opspace_matrices) returned a result") from stop
        try:
            raise stop
        except RunInterrupted:  # numba's wrapper: the interrupt is only the context
            raise SystemError("returned a result with an exception set") from None

    monkeypatch.setattr(env._task, "step", interrupted)
    with pytest.raises(RunInterrupted) as info:
        env.step(np.zeros(4))
    assert info.value is stop and env.sim_errors == errors


def test_bad_actions(env: RobosuiteTabletopEnv) -> None:
    env.reset(seed=0)
    with pytest.raises(ValueError, match="4 values"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([0.0, np.nan, 0.0, 0.0]))
    env.step(np.array([5.0, -5.0, 0.0, 1.0]))  # clipped


# --------------------------------------------------------------------------- language


def test_language_wrapper(env: RobosuiteTabletopEnv) -> None:
    wrapped = LanguageGoalWrapper(env)
    assert wrapped.families == env.instruction_families
    obs, info = wrapped.reset(seed=0)
    assert isinstance(obs["instruction"], str) and obs["instruction"] == info["instruction"]
    for _ in range(3):
        obs, reward, _, _, info = wrapped.step(wrapped.action_space.sample())
        assert reward in (0.0, 1.0) and obs["instruction"] == info["instruction"]
    obs, _ = wrapped.reset(seed=1, options={"instruction": "lift the  red cube"})
    assert obs["instruction"] == "lift the red cube"
    _, reward, *_ = wrapped.step(np.zeros(4))
    assert reward == 0.0


def test_goal_image_draws_the_goal_layout_and_restores_the_state(
    env: RobosuiteTabletopEnv, gripper_env: gym.Env
) -> None:
    obs, _ = env.reset(seed=11)
    before = {k: v.copy() for k, v in obs.items()}
    qpos = env.data.qpos.copy()
    goal = env.goal_image()
    assert goal.shape == obs["image"].shape and goal.dtype == np.uint8
    assert np.abs(goal.astype(int) - obs["image"].astype(int)).sum() > 0  # an object moved
    np.testing.assert_array_equal(env.data.qpos, qpos)
    np.testing.assert_array_equal(env._render(env._agentview), before["image"])
    np.testing.assert_array_equal(env.goal_image(), goal)  # the same frame again
    with pytest.raises(LcrlError, match="goal='object'"):
        gripper_env.unwrapped.goal_image()

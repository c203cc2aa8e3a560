"""Slot features: object positions relative to the agent and displacements since the reset."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.features import RelativePositions, SlotFeatures, slot_layout
from envs.tabletop2d import Tabletop2DEnv
from lcrl.errors import LcrlError
from train.environments.tasks import EnvConfig, make_env


def test_relative_slots_match_the_scene() -> None:
    env = RelativePositions(Tabletop2DEnv(num_objects=3))
    assert slot_layout(env) == (2, 8, 5, 2)
    assert slot_layout(env.unwrapped) == (2, 8, 3, 2)
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(30):
        x = obs["observation"]
        assert x.shape == (42,) and env.observation_space["observation"].contains(x)
        scene = env.unwrapped.scene()
        np.testing.assert_array_equal(x[:2], scene.gripper[:2].astype(np.float32))
        slots = x[2:].reshape(8, 5)
        present = slots[:, 2] > 0.5
        assert present.sum() == 3
        np.testing.assert_allclose(
            slots[present, 3:], slots[present, :2] - x[:2], rtol=0, atol=1e-6
        )
        np.testing.assert_array_equal(slots[~present], 0.0)
        obs, *_ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
    # Batches of observations get the same features.
    base = Tabletop2DEnv(num_objects=2)
    raw = np.stack([base.reset(seed=s)[0]["observation"] for s in range(4)])
    feats = RelativePositions(base).features(raw)
    assert feats.shape == (4, 42)
    np.testing.assert_array_equal(feats[1], RelativePositions(base).features(raw[1]))


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped")
def test_wrapped_env_passes_the_env_checker() -> None:
    check_env(RelativePositions(Tabletop2DEnv()), skip_render_check=True)


def test_env_config_option_and_errors() -> None:
    env = make_env(EnvConfig(kind="lang2d", relative_positions=True))
    assert env.observation_space["observation"].shape == (42,)
    obs, _ = env.reset(seed=0)
    assert obs["observation"].shape == (42,) and "instruction" in obs
    state = make_env(EnvConfig(kind="state2d", relative_positions=True))
    assert state.observation_space["observation"].shape == (42,)
    with pytest.raises(LcrlError, match="slot_layout"):
        RelativePositions(gym.make("CartPole-v1"))


def test_displacements_since_reset() -> None:
    env = SlotFeatures(Tabletop2DEnv(num_objects=2), relative=True, displacement=True)
    assert slot_layout(env) == (2, 8, 7, 2)
    obs, _ = env.reset(seed=1)
    slots = obs["observation"][2:].reshape(8, 7)
    np.testing.assert_array_equal(slots[:, 5:], 0.0)  # nothing has moved at the reset
    start = env.unwrapped.scene()
    target = int(np.flatnonzero(slots[:, 2] > 0.5)[0])
    for _ in range(50):  # steer the pusher into one object and through it
        slots = obs["observation"][2:].reshape(8, 7)
        obs, *_ = env.step(np.clip(slots[target, 3:5] * 20, -1, 1).astype(np.float32))
        assert env.observation_space["observation"].contains(obs["observation"])
    slots = obs["observation"][2:].reshape(8, 7)
    now = env.unwrapped.scene()
    moved = now.positions[:, :2] - start.positions[:, :2]
    assert np.abs(moved).max() > 0.05  # the object was pushed
    present = np.flatnonzero(slots[:, 2] > 0.5)
    np.testing.assert_allclose(slots[present, 5:], moved, rtol=0, atol=1e-6)
    np.testing.assert_allclose(slots[present, 3:5], slots[present, :2] - obs["observation"][:2])
    np.testing.assert_array_equal(slots[slots[:, 2] < 0.5], 0.0)
    # A new episode starts from zero again; batches take an explicit origin.
    obs2, _ = env.reset(seed=2)
    np.testing.assert_array_equal(obs2["observation"][2:].reshape(8, 7)[:, 5:], 0.0)
    raw = env.unwrapped._observe()[0]["observation"]
    feats = env.features(np.stack([raw, raw]), origin=np.stack([raw, raw]))
    np.testing.assert_array_equal(feats.reshape(2, -1)[:, 2:].reshape(2, 8, 7)[..., 5:], 0.0)


def test_displacement_only_and_errors() -> None:
    env = SlotFeatures(Tabletop2DEnv(num_objects=3), relative=False, displacement=True)
    assert slot_layout(env) == (2, 8, 5, 2)
    with pytest.raises(LcrlError, match="reset the env"):
        env.features(np.zeros(26, np.float32))
    obs, _ = env.reset(seed=0)
    assert obs["observation"].shape == (42,)
    with pytest.raises(LcrlError, match="already has slot features"):
        SlotFeatures(env, relative=True)
    with pytest.raises(LcrlError, match="relative=True or displacement=True"):
        SlotFeatures(Tabletop2DEnv(), relative=False, displacement=False)
    lang = make_env(EnvConfig(kind="lang2d", relative_positions=True, displacements=True))
    assert lang.observation_space["observation"].shape == (58,)


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped")
def test_displacement_env_passes_the_env_checker() -> None:
    check_env(SlotFeatures(Tabletop2DEnv(), displacement=True), skip_render_check=True)


def test_slots_that_do_not_match_the_env_are_refused() -> None:
    from train.configs.presets import PRESETS
    from train.evaluation.evaluate import check_slots

    cfg = PRESETS["lang2d"][1]
    check_slots(cfg, make_env(cfg.env))  # the preset matches its env
    env = make_env(EnvConfig(kind="lang2d", relative_positions=True))
    with pytest.raises(LcrlError, match=r"--agent\.net\.slots 2 8 5"):
        check_slots(cfg, env)

"""RelativePositions: object positions relative to the agent, added to each slot."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.features import RelativePositions, slot_layout
from envs.tabletop2d import Tabletop2DEnv
from lcrl.errors import LcrlError
from train.tasks import EnvConfig, make_env


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

"""Training on the robosuite tabletop: language, state and image goals through one loop.

Tiny runs (tens of steps, small networks); the learning result itself is a benchmark.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytest.importorskip("robosuite")

from lcrl.errors import LcrlError
from lcrl.goals import ImageGoals, LabelGoals, StateGoals
from lcrl.nets import NetConfig
from train.configs.config import BufferConfig, TrainConfig
from train.configs.presets import PRESETS
from train.environments.tasks import (
    EnvConfig,
    ImageGoalTask,
    LanguageTask,
    StateTask,
    make_env,
    make_task,
)
from train.evaluation.evaluate import run_episode
from train.policies.loading import load_policy
from train.training.loop import Trainer

SIZE = 64


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny(preset: str, out, **env) -> TrainConfig:
    cfg = PRESETS[preset][1]
    agent = dataclasses.replace(
        cfg.agent, net=dataclasses.replace(cfg.agent.net, hidden=(32,), cnn_channels=(8, 8))
    )
    return dataclasses.replace(
        cfg,
        out=str(out),
        env=dataclasses.replace(cfg.env, max_episode_steps=15, **env),
        agent=agent,
        buffer=dataclasses.replace(cfg.buffer, capacity=500),
        total_steps=60,
        learning_starts=30,
        batch_size=8,
        eval_every=0,
        eval_episodes=1,
        checkpoint_every=0,
        progress=False,
        tensorboard=False,
    )


@pytest.mark.parametrize(
    ("goal_type", "image_obs", "task_cls", "space_cls", "obs_keys"),
    [
        ("language", False, LanguageTask, LabelGoals, {"observation", "initial"}),
        ("language", True, LanguageTask, LabelGoals, {"image", "proprio"}),
        ("state", False, StateTask, StateGoals, {"observation"}),
        ("image", False, ImageGoalTask, ImageGoals, {"observation", "image"}),
        ("image", True, ImageGoalTask, ImageGoals, {"image", "proprio"}),
    ],
)
def test_one_option_picks_the_goal_modality(
    goal_type, image_obs, task_cls, space_cls, obs_keys
) -> None:
    cfg = EnvConfig(kind="robosuite", goal_type=goal_type, image_obs=image_obs, image_size=SIZE)
    env = make_env(cfg)
    try:
        embed = (
            (lambda texts: np.zeros((len(texts), 8), np.float32))
            if goal_type == "language"
            else None
        )
        task = make_task(cfg, env, embed)
        assert type(task) is task_cls and isinstance(task.goal_space, space_cls)
        assert set(task.obs_shapes) == obs_keys
        obs, _ = env.reset(seed=0)
        stored = task.storage_obs(obs, obs)
        assert set(stored) == obs_keys
        for key, shape in task.obs_shapes.items():
            assert stored[key].shape == tuple(shape)
            assert stored[key].dtype == (np.uint8 if len(shape) == 3 else np.float32)
        if image_obs:
            np.testing.assert_array_equal(stored["proprio"], obs["observation"][:4])
        problem = task.problem()
        if goal_type == "image":
            assert problem.goal_kind == "image" and problem.goal_shape == (SIZE, SIZE, 3)
            goal = task.goal(obs, env)
            assert goal.shape == (SIZE, SIZE, 3) and goal.dtype == np.uint8
    finally:
        env.close()


def test_bad_robosuite_options_are_clear_errors() -> None:
    with pytest.raises(LcrlError, match="goal_type"):
        make_env(EnvConfig(kind="robosuite", goal_type="smell"))
    with pytest.raises(LcrlError, match="goal='object'"):
        make_env(EnvConfig(kind="robosuite", goal_type="image", goal="gripper"))
    with pytest.raises(LcrlError, match="families"):
        make_env(EnvConfig(kind="robosuite", families=("dance",)))


def test_image_goal_run_stores_frames_once_and_reloads(tmp_path) -> None:
    trainer = Trainer(tiny("robosuite-image-goal", tmp_path / "img"))
    final = trainer.run()
    assert trainer.step == 60
    buf = trainer.buffer
    assert buf.obs["image"].dtype == np.uint8 and "image" in buf.obs
    batch = buf.sample(64)
    frames = buf.goal_space.frames(batch.goal)
    assert frames.dtype == np.uint8 and frames.shape == (64, SIZE, SIZE, 3)
    rel = batch.relabelled
    # relabelled goals are frames the buffer holds: slot >= 0, no copy in the goal space
    assert (batch.goal[rel] >= 0).all() and (batch.goal[~rel] < 0).any()
    np.testing.assert_array_equal(frames[rel], buf.obs["image"][batch.goal[rel]])
    assert np.isfinite(final["all"]["success"])
    trainer.close()
    policy = load_policy(tmp_path / "img")
    r = run_episode(policy.agent, policy.task, policy.env, seed=3)
    assert r["steps"] >= 1
    policy.env.close()


def test_language_run_on_image_observations(tmp_path) -> None:
    cfg = tiny("robosuite-image", tmp_path / "lang")
    cfg = dataclasses.replace(
        cfg,
        agent=dataclasses.replace(
            cfg.agent, net=NetConfig(hidden=(32,), cnn_channels=(8, 8), text_dim=8)
        ),
        buffer=BufferConfig(capacity=500, k=4, random_fraction=0.1),
    )
    trainer = Trainer(cfg)
    final = trainer.run()
    assert trainer.step == 60 and set(final) >= {"train", "heldout", "paraphrase"}
    assert trainer.agent.updates > 0
    trainer.close()


def test_simulator_errors_end_episodes_not_the_run(tmp_path, monkeypatch) -> None:
    import csv

    import envs.robosuite_tabletop as rt

    original = rt.RobosuiteTabletopEnv._advance
    calls = {"n": 0}

    def flaky(self, action):
        calls["n"] += 1
        if calls["n"] % 7 == 0:
            return "injected instability"
        return original(self, action)

    monkeypatch.setattr(rt.RobosuiteTabletopEnv, "_advance", flaky)
    cfg = dataclasses.replace(tiny("robosuite-state", tmp_path / "flaky"), log_every=20)
    trainer = Trainer(cfg)
    with pytest.warns(RuntimeWarning, match="injected"):
        trainer.run()
    assert trainer.step == 60 and trainer.sim_errors >= 5
    with (tmp_path / "flaky" / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert int(rows[-1]["sim_errors"]) == trainer.sim_errors
    trainer.close()

"""Task adapters: gymnasium-robotics goal envs as state-goal tasks, env errors, run reports."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lcrl.buffer import HindsightReplayBuffer
from lcrl.errors import LcrlError
from train.environments.tasks import EnvConfig, StateTask, make_env
from train.evaluation.report import write_report


def test_fetch_reach_rewards_come_from_its_compute_reward() -> None:
    pytest.importorskip("gymnasium_robotics")
    env = make_env(EnvConfig(kind="gym", gym_id="FetchReach-v4", max_episode_steps=20))
    task = StateTask(env)
    assert task.goal_space.success_reward == 0.0  # Fetch rewards are -1 / 0
    assert task.obs_shapes == {"observation": (10,)}
    p = task.problem()
    assert (p.goal_kind, p.goal_shape, p.action_dim, p.discrete) == ("vector", (3,), 4, False)

    buf = HindsightReplayBuffer(
        200, {"observation": ((10,), np.float32)}, (4,), np.float32, task.goal_space, k=4
    )
    rng = np.random.default_rng(0)
    for ep in range(3):
        obs, _ = env.reset(seed=ep)
        first = obs
        stored, records, actions = [task.storage_obs(obs, first)], [], []
        records.append(task.step_record(obs, env))
        goal = task.goal(obs, env)
        for _ in range(20):
            a = task.random_action(rng)
            obs, _, terminated, truncated, _ = env.step(task.scale_action(a))
            stored.append(task.storage_obs(obs, first))
            records.append(task.step_record(obs, env))
            actions.append(a)
            if terminated or truncated:
                break
        buf.add_episode(
            {
                "obs": {"observation": np.stack([s["observation"] for s in stored])},
                "action": np.asarray(actions),
                "reward": np.zeros(len(actions), np.float32),
                "terminated": np.zeros(len(actions), bool),
                **task.episode_fields(records, goal, env),
            }
        )
    batch = buf.sample(512)
    achieved = buf.goal_space._achieved[batch.index + 1]
    expected = env.unwrapped.compute_reward(achieved, batch.goal, None)
    np.testing.assert_array_equal(batch.reward, expected.astype(np.float32))
    assert (batch.reward[batch.relabelled] == 0.0).any()  # some relabelled goals are reached
    assert not batch.terminated.any()  # Fetch episodes only end at the time limit


def test_unknown_gym_env_and_bad_object_counts_are_clear_errors() -> None:
    with pytest.raises(LcrlError, match="cannot make"):
        make_env(EnvConfig(kind="gym", gym_id="NoSuchEnv-v9"))
    with pytest.raises(LcrlError, match="min_objects"):
        make_env(EnvConfig(kind="lang2d", min_objects=4, max_objects=2))
    with pytest.raises(LcrlError, match="unknown env kind"):
        make_env(EnvConfig(kind="robot"))
    with pytest.raises(LcrlError, match="families"):
        make_env(EnvConfig(kind="lang2d", families=("stack",)))


def test_report_has_curves_and_final_table(tmp_path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    config = {
        "env": {"kind": "lang2d", "families": ["reach"], "gym_id": ""},
        "buffer": {"strategy": "future", "k": 4},
        "algo": "auto",
        "resolved_algo": "sac",
        "total_steps": 200,
        "seed": 0,
    }
    (run / "config.json").write_text(json.dumps(config))
    (run / "progress.csv").write_text(
        "step,episodes,success,steps_per_s,updates\n100,2,0.0,50,0\n200,4,0.5,60,100\n"
    )
    (run / "eval.csv").write_text(
        "step,episodes,train/success,train/reach,heldout/success,heldout/reach\n"
        "200,4,0.5,0.5,0.25,0.25\n"
    )
    final = {
        "train": {"success": 0.5, "episodes": 4, "families": {"reach": 0.5}},
        "heldout": {"success": 0.25, "episodes": 4, "families": {"reach": 0.25}},
    }
    path = write_report(run, final)
    text = path.read_text()
    assert "| heldout | 0.25 | 0.25 |" in text
    assert "curves.png" in text
    assert (run / "curves.png").stat().st_size > 1000
    with pytest.raises(LcrlError, match="not a run folder"):
        write_report(tmp_path / "nothing")


@pytest.mark.parametrize("kind", ["tabletop2d", "robosuite", "gym"])
def test_registered_slot_layouts_match_the_simulators(kind) -> None:
    """The slot layout an ENVS entry documents is the one its simulator reports."""
    from envs.features import slot_layout
    from train.environments.simulators import ENVS, EnvConfig

    spec = ENVS[kind]
    if spec.slot_layout is None:
        assert kind == "gym"  # goal envs of gymnasium-robotics have no object slots
        return
    if kind == "robosuite":
        pytest.importorskip("robosuite")
    env = spec.make(EnvConfig(kind=kind))
    try:
        assert slot_layout(env) == spec.slot_layout
    finally:
        env.close()

"""The extension points, used from test code only (as ``docs/extending.md`` shows): a new
simulator enters :data:`train.environments.simulators.ENVS`, a new goal modality enters
:data:`train.environments.tasks.GOALS`, and the unchanged training loop, evaluation engine,
checkpoints
and ``lcrl eval`` run them.

* The simulator, ``point``: a point on a plane moved by 2-D velocity actions towards a goal
  position (a gymnasium goal env with ``compute_reward``).
* The goal modality, ``offset``: the goal is where to go *relative to where the episode
  started* (``desired - start``); hindsight relabelling replaces it by offsets achieved
  later in the episode (``achieved(t') - start``), with the same reward function.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from helpers import cli

from lcrl.goals import StateGoals
from lcrl.nets import NetConfig
from train.configs.config import BufferConfig, TrainConfig
from train.environments.simulators import ENVS, EnvConfig, EnvSpec
from train.environments.tasks import GOALS, GoalModality, Task
from train.evaluation.evaluate import run_episode
from train.policies.loading import load_policy
from train.training.loop import Trainer

REACHED = 0.1


class PointEnv(gym.Env):
    """A point in ``[-1, 1]^2``; actions are velocities of at most 0.1 a step."""

    def __init__(self) -> None:
        box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = gym.spaces.Dict(
            {"observation": box, "achieved_goal": box, "desired_goal": box}
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            "observation": self.pos.copy(),
            "achieved_goal": self.pos.copy(),
            "desired_goal": self.goal.copy(),
        }

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-0.5, 0.5, 2).astype(np.float32)
        self.goal = self.np_random.uniform(-0.5, 0.5, 2).astype(np.float32)
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        self.pos = np.clip(self.pos + 0.1 * np.asarray(action, np.float32), -1.0, 1.0)
        reward = float(self.compute_reward(self.pos, self.goal, None))
        return self._obs(), reward, False, False, {"is_success": reward == 0.0}

    def compute_reward(self, achieved: np.ndarray, desired: np.ndarray, info: Any) -> Any:
        d = np.linalg.norm(np.asarray(achieved) - np.asarray(desired), axis=-1)
        return -(d > REACHED).astype(np.float32)


class OffsetTask(Task):
    """Goals are displacements from the episode's start position."""

    goal_kind = "vector"  # the network's goal encoder (and goal normaliser)

    def __init__(self, env: gym.Env, image_obs: bool = False) -> None:
        super().__init__(env)  # action space: scaling, random actions
        unwrapped = env.unwrapped
        self.obs_shapes = {"observation": (2,), "initial": (2,)}

        def reward_fn(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
            return unwrapped.compute_reward(achieved, desired, None)

        self.goal_space = StateGoals(2, reward_fn, success_reward=0.0)

    @classmethod
    def from_config(cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kw: Any) -> Task:
        return cls(env)

    def storage_obs(self, obs: Mapping[str, Any], first: Mapping[str, Any]) -> dict:
        # arrays the buffer stores per step
        return {
            "observation": np.asarray(obs["observation"], np.float32),
            "initial": np.asarray(first["observation"], np.float32),
        }

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> np.ndarray:
        # the goal of the episode, from its first observation: where to go, from here
        return np.asarray(obs["desired_goal"] - obs["achieved_goal"], np.float32)

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        return np.asarray(obs["achieved_goal"], np.float32)  # what to remember of a step

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        # the goal-space fields of the episode
        achieved = np.stack(records)
        return {"achieved_goal": achieved - achieved[0], "desired_goal": goal}

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        return goals  # goals as the learner's input

    def eval_goal(self, obs: Mapping[str, Any], start: Any) -> Any:
        # the goal in evaluation's vector envs, from the first observation alone
        return self.goal(obs, None)  # type: ignore[arg-type]


@pytest.fixture
def registries():
    """The registries as they were before the test, whatever it registered."""
    saved = dict(ENVS), dict(GOALS)
    yield
    for registry, before in zip((ENVS, GOALS), saved, strict=True):
        registry.clear()
        registry.update(before)


@pytest.fixture
def registered(registries):
    """``point`` and ``offset`` in the registries for one test, as docs/extending.md
    registers them."""
    GOALS["offset"] = GoalModality(OffsetTask, "offsets from the start")
    ENVS["point"] = EnvSpec(make=lambda cfg: PointEnv(), goal_types=("offset", "state"))


def test_a_simulator_takes_the_goal_types_it_lists(registries):
    ENVS["point"] = EnvSpec(make=lambda cfg: PointEnv(), goal_types=("state",))
    TrainConfig(env=EnvConfig(kind="point", goal_type="state")).validate()
    from lcrl.errors import LcrlError

    with pytest.raises(LcrlError, match=r"supports the goal types \('state',\), not 'image'"):
        TrainConfig(env=EnvConfig(kind="point", goal_type="image")).validate()


def config(out, k: int, steps: int) -> TrainConfig:
    return TrainConfig(
        out=str(out),
        env=EnvConfig(kind="point", goal_type="offset", max_episode_steps=20),
        buffer=BufferConfig(capacity=20_000, k=k),
        total_steps=steps,
        learning_starts=200,
        batch_size=64,
        eval_every=0,
        eval_episodes=40,
        checkpoint_every=0,
        log_every=500,
        progress=False,
        tensorboard=False,
    )


def test_a_new_simulator_and_goal_modality_train_through_the_registries(
    registered, tmp_path, one_thread
):
    cfg = config(tmp_path / "her", k=4, steps=2000)
    cfg.agent.net = NetConfig(hidden=(64, 64))
    her = Trainer(cfg).run()["all"]["success"]
    cfg = config(tmp_path / "none", k=0, steps=2000)
    cfg.agent.net = NetConfig(hidden=(64, 64))
    without = Trainer(cfg).run()["all"]["success"]
    # hindsight offsets teach the point to go where it is told; sparse rewards alone
    # rarely do in 2,000 steps
    print(f"offset goals after 2,000 steps: HER {her:.2f}, no relabelling {without:.2f}")
    assert her >= 0.6 and her >= without + 0.2, (her, without)

    # the run is an ordinary run: saved config, checkpoint, lcrl eval, load_policy
    saved = json.loads((tmp_path / "her" / "config.json").read_text())["env"]
    assert (saved["kind"], saved["goal_type"]) == ("point", "offset")
    out = tmp_path / "eval"
    assert cli("eval", str(tmp_path / "her"), "--episodes", "40", "--out", str(out)) == 0
    doc = json.loads((out / "eval.json").read_text())
    assert doc["sets"]["all"]["success"] == pytest.approx(her)  # one engine, one seed
    # a policy that mostly fails: the same few successes, episode for episode
    out = tmp_path / "eval-none"
    assert cli("eval", str(tmp_path / "none"), "--episodes", "40", "--num-envs", "3",
               "--out", str(out)) == 0  # fmt: skip
    doc = json.loads((out / "eval.json").read_text())
    assert doc["sets"]["all"]["success"] == pytest.approx(without)
    last = (tmp_path / "none" / "eval.csv").read_text().splitlines()[-1].split(",")
    assert float(last[2]) == pytest.approx(without, abs=1e-6)  # step, episodes, all/success
    loaded = load_policy(tmp_path / "her")
    assert isinstance(loaded.task, OffsetTask)
    assert run_episode(loaded.agent, loaded.task, loaded.env, seed=1)["family"] == "all"


def test_unregistered_names_are_clear_errors(registered):
    from lcrl.errors import LcrlError

    with pytest.raises(LcrlError, match="unknown env kind 'nowhere'"):
        TrainConfig(env=EnvConfig(kind="nowhere")).validate()
    with pytest.raises(LcrlError, match="supports the goal types"):
        TrainConfig(env=EnvConfig(kind="point", goal_type="language")).validate()
    with pytest.raises(LcrlError, match="unknown goal_type 'telepathy'"):
        TrainConfig(env=EnvConfig(kind="point", goal_type="telepathy")).validate()


def test_a_new_goal_kind_is_one_registry_line(monkeypatch):
    """A goal kind of the test's own: its encoder and normaliser come from the two
    registries of the learning core, and the agent saves them under the usual names."""
    import torch
    from torch import nn

    from lcrl.algos import GOAL_NORMALISERS, AgentOptions, Problem, SACConfig, build_agent
    from lcrl.algos.base import vector_goal_normaliser
    from lcrl.errors import LcrlError
    from lcrl.nets import GOAL_ENCODERS, GoalEncoderSpec

    def scaled_goal_encoder(shape, cfg, shared=None):
        return nn.Linear(shape[0], 5), 5

    monkeypatch.setitem(GOAL_ENCODERS, "scaled", GoalEncoderSpec(scaled_goal_encoder))
    monkeypatch.setitem(GOAL_NORMALISERS, "scaled", vector_goal_normaliser)
    problem = Problem({"observation": (4,)}, "scaled", (3,), 2)

    def embed(goals, device):
        return torch.as_tensor(np.asarray(goals), dtype=torch.float32, device=device)

    options = AgentOptions(net=NetConfig(hidden=(8, 8)))
    agent = build_agent("sac", problem, options, embed, SACConfig())
    assert agent.act({"observation": np.zeros((2, 4), np.float32)}, np.ones((2, 3))).shape == (2, 2)
    assert {"goal_encoder.net.weight", "goal_encoder.net.bias"} <= set(
        agent.modules()["actor"].state_dict()
    )
    assert "goal.mean" in agent.modules()["norms"].state_dict()
    monkeypatch.delitem(GOAL_NORMALISERS, "scaled")  # no entry: goals are not normalised
    agent = build_agent("sac", problem, options, embed, SACConfig())
    assert not any(k.startswith("goal.") for k in agent.modules()["norms"].state_dict())
    # per-task heads pick by one-hot task ids only
    heads = AgentOptions(net=NetConfig(hidden=(8, 8), task_heads=3))
    with pytest.raises(LcrlError, match="picks a head by one-hot task id"):
        build_agent("sac", problem, heads, embed, SACConfig())
    with pytest.raises(LcrlError, match="unknown goal kind 'nowhere'"):
        build_agent("sac", Problem({"observation": (4,)}, "nowhere", (3,), 2), options, embed)


def test_reports_and_messages_read_the_goal_modality_not_its_name(monkeypatch):
    """A second task-id goal type, under a name of its own: reports, the policy's
    description and the presets' checks treat it as task ids from its registry entry."""
    from train.configs.presets import TASKS_2D
    from train.environments.tasks import TaskIdTask
    from train.evaluation.report import learning_summary, task_name
    from train.policies.policy import describe_env

    numbered = GoalModality(
        TaskIdTask, "numbered tasks", instructed=True, needs_tasks=True, relabel=False,
        label="numbered tasks",
    )  # fmt: skip
    monkeypatch.setitem(GOALS, "numbered", numbered)
    env = {"kind": "tabletop2d", "goal_type": "numbered", "tasks": list(TASKS_2D[:2])}
    assert task_name(env) == "2D tabletop, 2 tasks as numbered tasks"
    assert learning_summary({"algo": "sac", "env": env}) == "numbered tasks, no relabelling"
    assert numbered.task_ids and not numbered.text
    cfg = TrainConfig(env=EnvConfig(kind="tabletop2d", goal_type="numbered", tasks=TASKS_2D[:2]))
    assert describe_env(cfg).endswith("(numbered goals), 2 task ids")
    # a language-goal type under another name reads its families, as language goals do
    monkeypatch.setitem(GOALS, "words", GOALS["language"])
    words = {"kind": "tabletop2d", "goal_type": "words", "families": ["reach"]}
    assert task_name(words) == "2D tabletop reach"
    assert task_name({"kind": "tabletop2d", "goal_type": "mystery"}) == (
        "2D tabletop (mystery goals)"
    )

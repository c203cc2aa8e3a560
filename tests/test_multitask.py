"""Multi-task RL: PCGrad, gradient conflict, task sampling, task-id goals without
relabelling, per-task heads, and tiny ``lcrl train lang2d-tasks`` runs end to end."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import cli, error_line, tiny
from torch import nn

from lcrl.algos import SAC, AgentOptions, Problem
from lcrl.buffer import HindsightReplayBuffer
from lcrl.checkpoint import load_checkpoint, save_checkpoint
from lcrl.errors import LcrlError
from lcrl.goals import TASK_RELABEL_ERROR, TaskGoals
from lcrl.multitask import (
    MultiTaskOptions,
    TaskGradients,
    TaskSampler,
    conflict_stats,
    project_conflicting,
    rows_by_task,
    task_weights,
)
from lcrl.nets import FlatAdam, GoalConditionedEnsemble, GoalConditionedNet, NetConfig, TaskHeads
from train.configs.config import BufferConfig, TrainConfig
from train.configs.presets import PRESETS, TASKS_2D
from train.environments.tasks import (
    EnvConfig,
    LanguageTask,
    ScriptedActor,
    TaskIdTask,
    make_env,
    make_task,
    reset_feasible,
)
from train.training.loop import Trainer


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


def t(rows: list[list[float]]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


# --- PCGrad -------------------------------------------------------------------------------------
def test_pcgrad_two_tasks_2d_by_hand():
    # g1 . g2 = -1: g1 - (-1 / 2) g2 = (0.5, 0.5); g2 - (-1 / 1) g1 = (0, 1)
    out = project_conflicting(t([[1, 0], [-1, 1]]))
    assert torch.equal(out, t([[0.5, 0.5], [0.0, 1.0]]))


def test_pcgrad_two_tasks_3d_by_hand_and_orthogonal():
    g = t([[1, 2, -1], [0, -1, 1]])  # dot -3, |g1|^2 = 6, |g2|^2 = 2
    out = project_conflicting(g)
    assert torch.allclose(out, t([[1, 0.5, 0.5], [0.5, 0, 0.5]]), atol=1e-12)
    # with two tasks each projected gradient is orthogonal to the other original one
    assert abs(float(out[0] @ g[1])) < 1e-12
    assert abs(float(out[1] @ g[0])) < 1e-12


def test_pcgrad_orthogonal_in_high_dimension():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(500, generator=gen, dtype=torch.float64)
    b = -a + 0.3 * torch.randn(500, generator=gen, dtype=torch.float64)
    g = torch.stack([a, b])
    assert float(a @ b) < 0
    out = project_conflicting(g)
    assert abs(float(out[0] @ b)) < 1e-9 * float(a.norm() * b.norm())
    assert abs(float(out[1] @ a)) < 1e-9 * float(a.norm() * b.norm())


def test_pcgrad_leaves_agreeing_gradients_alone():
    g = t([[1, 1, 0], [1, 2, 3], [0, 1, 1]])  # every pairwise dot product >= 0
    assert torch.equal(project_conflicting(g, rng=np.random.default_rng(0)), g)
    g32 = g.float()
    assert torch.equal(project_conflicting(g32), g32)  # dtype kept, values untouched


def test_pcgrad_three_tasks_order_matters():
    g = t([[1, 0, 0], [-1, 1, 0], [-1, 0, 1]])
    # task 0 visiting 1 then 2: (0.5, 0.5, 0), then dot with g2 = -0.5 -> + 0.25 g2
    first = project_conflicting(g, order=[[1, 2], [0, 2], [0, 1]])
    # task 0 visiting 2 then 1: (0.5, 0, 0.5), then dot with g1 = -0.5 -> + 0.25 g1
    second = project_conflicting(g, order=[[2, 1], [2, 0], [1, 0]])
    assert torch.allclose(first, t([[0.25, 0.5, 0.25], [0, 1, 0], [0, 0, 1]]), atol=1e-12)
    assert torch.allclose(second, t([[0.25, 0.25, 0.5], [0, 1, 0], [0, 0, 1]]), atol=1e-12)
    # the projection uses the original g_j: task 1 sees g0 = (1, 0, 0), not a projected one
    assert not torch.allclose(first[0], second[0])


def test_pcgrad_random_order_is_seeded_and_zero_rows_stay_zero():
    gen = torch.Generator().manual_seed(1)
    g = torch.randn(5, 40, generator=gen)
    g[3] = 0.0
    a = project_conflicting(g, rng=np.random.default_rng(7))
    b = project_conflicting(g, rng=np.random.default_rng(7))
    assert torch.equal(a, b)
    assert torch.equal(a[3], torch.zeros(40))
    with pytest.raises(LcrlError, match="order"):
        project_conflicting(g[:3], order=[[1, 1], [0, 2], [0, 1]])


def test_conflict_stats_by_hand():
    g = t([[1, 0], [-1, 1], [1, 1], [0, 0]])  # the zero row (a task without rows) is left out
    stats = conflict_stats(g)
    # cos(0, 1) = -1/sqrt(2), cos(0, 2) = 1/sqrt(2), cos(1, 2) = 0
    assert stats["cos_mean"] == pytest.approx(0.0, abs=1e-12)
    assert stats["cos_min"] == pytest.approx(-1 / math.sqrt(2))
    assert stats["conflict_fraction"] == pytest.approx(1 / 3)
    assert stats["pairs"] == 3
    assert math.isnan(conflict_stats(t([[1, 0], [0, 0]]))["cos_mean"])


def _linear_losses(model: nn.Linear, directions: list[list[float]]) -> list[torch.Tensor]:
    """Losses a_i . theta: their gradients are exactly the a_i."""
    theta = model.weight.reshape(-1)
    return [torch.tensor(a, dtype=torch.float32) @ theta for a in directions]


def test_task_gradients_plain_sum_without_conflict():
    model = nn.Linear(3, 1, bias=False)
    opt = FlatAdam(model.parameters(), lr=0.1)
    dirs, coefs = [[1.0, 0.0, 2.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.2, 0.5, 0.3]
    stats = TaskGradients(opt, pcgrad=True).backward(_linear_losses(model, dirs), coefs)
    got = opt.grad.clone()
    opt.zero_grad()
    sum(c * loss for c, loss in zip(coefs, _linear_losses(model, dirs), strict=True)).backward()
    assert torch.allclose(got, opt.grad, atol=1e-7)
    assert stats["conflict_fraction"] == 0.0


def test_task_gradients_project_conflicts_and_step():
    model = nn.Linear(2, 1, bias=False)
    opt = FlatAdam(model.parameters(), lr=0.1)
    before = opt.flat.clone()
    dirs, coefs = [[1.0, 0.0], [-1.0, 1.0]], [0.25, 0.75]
    tg = TaskGradients(opt, pcgrad=True)
    stats = tg.step(_linear_losses(model, dirs), coefs)
    # projected: (0.5, 0.5) and (0, 1)
    assert torch.allclose(opt.grad, torch.tensor([0.25 * 0.5, 0.25 * 0.5 + 0.75]))
    assert stats["conflict_fraction"] == 1.0
    assert not torch.equal(opt.flat, before)  # the optimiser stepped
    plain = TaskGradients(opt, pcgrad=False)
    plain.backward([*_linear_losses(model, dirs), None], [*coefs, 1.0])
    assert torch.allclose(opt.grad, torch.tensor([0.25 - 0.75, 0.75]))


def test_rows_by_task_and_weights():
    groups = rows_by_task(np.array([2, 0, 2, 1, 0]), 4)
    assert [g.tolist() for g in groups] == [[1, 4], [3], [0, 2], []]
    with pytest.raises(LcrlError):
        rows_by_task(np.array([4]), 4)
    assert task_weights((), 3).tolist() == [1.0, 1.0, 1.0]
    assert task_weights((1, 2, 3), 3).tolist() == pytest.approx([0.5, 1.0, 1.5])
    for bad in ((1, 2), (1, -1, 1), (0, 0, 0)):
        with pytest.raises(LcrlError, match="task_weights"):
            task_weights(bad, 3)


# --- task sampling ------------------------------------------------------------------------------
def test_uniform_sampler_is_uniform_and_seeded():
    s = TaskSampler(4)
    assert s.probs().tolist() == [0.25] * 4
    rng, again = np.random.default_rng(5), np.random.default_rng(5)
    draws = [s.sample(rng) for _ in range(4000)]
    assert draws == [s.sample(again) for _ in range(4000)]
    counts = np.bincount(draws, minlength=4) / 4000
    assert np.all(np.abs(counts - 0.25) < 0.03)


def test_success_sampler_favours_failing_tasks_without_starving_any():
    s = TaskSampler(3, "success", window=10, eps=0.05, uniform_mix=0.2)
    for _ in range(20):
        s.update(0, True)
        s.update(1, False)
    rates = s.success_rates()
    assert rates[0] == 1.0 and rates[1] == 0.0 and math.isnan(rates[2])
    p = s.probs()
    # scores 0.05, 1.05, 1.05 (a task never run counts as failing)
    raw = np.array([0.05, 1.05, 1.05]) / 2.15
    assert p == pytest.approx(0.8 * raw + 0.2 / 3)
    assert p[0] < p[1] == p[2]
    assert p.min() >= 0.2 / 3 - 1e-12 and p.sum() == pytest.approx(1.0)
    # the window forgets: task 0 failing for a window brings it back up
    for _ in range(10):
        s.update(0, False)
    assert s.success_rates()[0] == 0.0
    assert s.probs()[0] == pytest.approx(s.probs()[1])


def test_progress_sampler_favours_changing_tasks():
    s = TaskSampler(3, "progress", fast_rate=0.2, slow_rate=0.02)
    for _ in range(50):
        s.update(0, True)  # always succeeds: no progress (bias-corrected averages agree)
        s.update(1, False)  # never succeeds: no progress
    for k in range(50):
        s.update(2, k >= 40)  # just started to succeed
    lp = s.progress()
    assert lp[0] == pytest.approx(0.0, abs=1e-12) and lp[1] == 0.0
    assert lp[2] > 0.5
    p = s.probs()
    assert p[2] > p[0] and p[0] == pytest.approx(p[1])
    assert p.min() >= 0.2 / 3 - 1e-12


def test_sampler_state_round_trip_and_checks():
    s = TaskSampler(4, "success", window=5)
    rng = np.random.default_rng(0)
    for _ in range(30):
        k = s.sample(rng)
        s.update(k, rng.random() < 0.3 * k)
    copy = TaskSampler(4, "success", window=5)
    copy.load_state_dict(s.state_dict())
    assert np.array_equal(copy.probs(), s.probs())
    assert np.array_equal(copy.episodes, s.episodes)
    r1, r2 = np.random.default_rng(9), np.random.default_rng(9)
    assert [s.sample(r1) for _ in range(50)] == [copy.sample(r2) for _ in range(50)]
    with pytest.raises(LcrlError, match="saved task sampler"):
        TaskSampler(3, "success", window=5).load_state_dict(s.state_dict())
    with pytest.raises(LcrlError, match="unknown task sampling"):
        TaskSampler(2, "greedy")
    with pytest.raises(LcrlError):
        s.update(4, True)


# --- task-id goals: no relabelling, per-task rewards -------------------------------------------
def _buffer(goal_space, k=0, random_fraction=0.0):
    return HindsightReplayBuffer(
        200, {"x": ((2,), np.float32)}, (1,), np.float32, goal_space, k=k,
        random_fraction=random_fraction,
    )  # fmt: skip


def test_buffer_refuses_relabelling_task_ids():
    for k, frac in ((4, 0.0), (0, 0.1), (1, 0.2)):
        with pytest.raises(LcrlError) as e:
            _buffer(TaskGoals(3), k=k, random_fraction=frac)
        assert str(e.value) == TASK_RELABEL_ERROR
        assert "set buffer.k=0 and buffer.random_fraction=0" in str(e.value)
    g = TaskGoals(3)
    with pytest.raises(LcrlError, match="cannot be relabelled"):
        g.relabel(np.zeros(1, np.int64), np.zeros(1, np.int64), np.ones(1, np.int64), "future",
                  np.random.default_rng(0))  # fmt: skip
    with pytest.raises(LcrlError, match="cannot be relabelled"):
        g.random_goals(np.zeros(1, np.int64), np.random.default_rng(0))


def test_task_rewards_match_the_per_task_reward_functions():
    # task i is achieved where the first achieved value exceeds i (vectorised over steps)
    fns = [lambda a, i=i: a[:, 0] > i for i in range(3)]
    goals = TaskGoals(3, reward_fns=fns)
    buf = _buffer(goals)
    rng = np.random.default_rng(0)
    episodes = {}  # start slot -> (achieved, task)
    for e in range(12):
        n = int(rng.integers(3, 9))
        achieved = rng.uniform(0, 3, (n + 1, 2)).astype(np.float32)
        episodes[buf.ptr] = (achieved, e % 3)
        buf.add_episode({
            "obs": {"x": achieved}, "action": np.zeros((n, 1), np.float32),
            "reward": np.zeros(n), "terminated": np.zeros(n, bool), "goal_id": e % 3,
            "achieved_goal": achieved,
        })  # fmt: skip
    batch = buf.sample(500)
    assert not batch.relabelled.any()
    assert 0 < batch.reward.mean() < 1
    for i, g, r in zip(batch.index, batch.goal, batch.reward, strict=True):
        start = int(buf.ep_start[i])
        achieved, task = episodes[start]
        assert g == task
        assert r == float(fns[task](achieved)[i - start + 1])
    # terminate_on_success: the value target ends where the task is achieved
    assert np.array_equal(batch.terminated, batch.reward)
    with pytest.raises(LcrlError, match="cannot be relabelled"):
        goals.reward(batch.index[:1], (batch.goal[:1] + 1) % 3)


def test_task_goals_take_per_step_success_flags():
    buf = _buffer(TaskGoals(2))
    flags = [False, True, False]  # step 1 achieved the episode's task
    buf.add_episode({
        "obs": {"x": np.zeros((4, 2), np.float32)}, "action": np.zeros((3, 1), np.float32),
        "reward": np.zeros(3), "terminated": np.zeros(3, bool), "goal_id": 1, "success": flags,
    })  # fmt: skip
    batch = buf.sample(200)
    assert np.array_equal(batch.reward, np.asarray(flags, np.float32)[batch.index])
    assert (batch.goal == 1).all()
    emb = buf.goal_space.embed(batch.goal[:2], "cpu")
    assert torch.equal(emb, torch.tensor([[0.0, 1.0], [0.0, 1.0]]))
    with pytest.raises(LcrlError, match="per-step 'success'"):
        buf.add_episode({
            "obs": {"x": np.zeros((2, 2), np.float32)}, "action": np.zeros((1, 1), np.float32),
            "reward": np.zeros(1), "terminated": np.zeros(1, bool), "goal_id": 0,
        })  # fmt: skip


def _env_cfg(**kw) -> EnvConfig:
    return EnvConfig(kind="lang2d", goal_type="task", tasks=TASKS_2D, **kw)


def test_task_id_task_rewards_are_the_rule_captioner_checks():
    cfg = _env_cfg()
    env = make_env(cfg, "train", training=True)
    task = make_task(cfg, env)
    assert isinstance(task, TaskIdTask)
    assert task.problem().goal_kind == "onehot" and task.problem().goal_shape == (8,)
    assert task.problem().num_tasks == 8
    actor = ScriptedActor(cfg, task, noise=0.0)
    rng = np.random.default_rng(0)
    buf = HindsightReplayBuffer(
        2000, {k: (s, np.float32) for k, s in task.obs_shapes.items()}, (2,), np.float32,
        task.goal_space, k=0,
    )  # fmt: skip
    hits, flags = 0, {}
    for e, k in enumerate([0, 1, 4, 5]):
        obs, info = reset_feasible(env, 100 + e, TASKS_2D[k])
        assert info["feasible"] and task.goal(obs, env) == k
        first, records, stored, actions = obs, [task.step_record(obs, env)], [], []
        stored.append(task.storage_obs(obs, first))
        actor.reset()
        for _ in range(50):
            a = actor.act(env, rng)
            obs, _, term, trunc, info = env.step(task.scale_action(a))
            records.append(task.step_record(obs, env))
            stored.append(task.storage_obs(obs, first))
            actions.append(a)
            if term or trunc:
                break
        fields = task.episode_fields(records, k, env)
        expected = [task.captioner.satisfied(TASKS_2D[k], records[0], s) for s in records[1:]]
        assert fields["success"] == expected
        assert fields["success"][-1] == bool(info["is_success"])
        hits += int(any(expected))
        flags[buf.ptr] = expected
        buf.add_episode({
            "obs": {key: np.stack([s[key] for s in stored]) for key in stored[0]},
            "action": np.asarray(actions), "reward": np.zeros(len(actions)),
            "terminated": np.zeros(len(actions), bool), **fields,
        })  # fmt: skip
    assert hits >= 3  # the scripted controller does these tasks
    batch = buf.sample(1000)
    assert batch.reward.sum() > 0
    for i, r in zip(batch.index, batch.reward, strict=True):
        start = int(buf.ep_start[i])
        assert r == float(flags[start][i - start])  # step i - start achieved the task
    env.close()


def test_reset_feasible_gives_up_with_a_clear_error():
    env = make_env(_env_cfg(), "train")
    for seed in range(50):  # a layout without the red cube
        _, info = env.reset(seed=seed, options={"instruction": "reach the red cube"})
        if not info["feasible"]:
            break
    with pytest.raises(LcrlError, match="feasible in none of 1 random layouts"):
        reset_feasible(env, seed, "reach the red cube", tries=1)
    obs, info = reset_feasible(env, seed, "reach the red cube")
    assert info["feasible"] and obs["instruction"] == "reach the red cube"


def test_language_goals_over_the_task_set():
    cfg = EnvConfig(kind="lang2d", tasks=("touch the red cube", "push the blue cube left"))
    env = make_env(cfg, "train")
    task = make_task(cfg, env, embed=lambda texts: np.ones((len(texts), 4), np.float32))
    assert isinstance(task, LanguageTask)
    assert task.table == ["touch the red cube", "push the blue cube left"]
    assert task.num_train == 2 and task.problem().num_tasks == 2
    # the captioner's canonical phrasing labels the paraphrased task
    assert task.label_ids == {"reach the red cube": 0, "push the blue cube left": 1}
    env.close()


# --- configuration ------------------------------------------------------------------------------
def _cfg(**env) -> TrainConfig:
    return TrainConfig(env=EnvConfig(kind="lang2d", **env), buffer=BufferConfig(k=0))


@pytest.mark.parametrize(
    ("cfg", "match"),
    [
        (_cfg(goal_type="task"), "goal_type=task needs a task set"),
        (_cfg(goal_type="task", tasks=("reach the red cube", "touch the red cube")), "same"),
        (_cfg(goal_type="task", tasks=("put the red cube left of the blue cube",)), "outside"),
        (_cfg(goal_type="task", tasks=("dance",)), "cannot parse 'dance'"),
        (
            TrainConfig(env=EnvConfig(kind="state2d", goal_type="task", tasks=TASKS_2D)),
            "env.tasks are instructions",
        ),
        (
            TrainConfig(env=EnvConfig(kind="lang2d", goal_type="task", tasks=TASKS_2D)),
            "cannot be relabelled",
        ),
    ],
)
def test_validate_refuses_bad_task_sets(cfg, match):
    with pytest.raises(LcrlError, match=match):
        cfg.validate()


def test_validate_refuses_bad_multitask_options():
    base = _cfg(goal_type="task", tasks=TASKS_2D)
    base.validate()
    bad = [
        (dataclasses.replace(base, algo="td3"), "pcgrad", "implemented for SAC"),
        (_cfg(), "pcgrad", "needs a task set"),
        (base, "weights", "task_weights has 2 values for 8 tasks"),
        (base, "heads_text", "one-hot task id"),
        (base, "heads_count", "set --agent.net.task-heads 8"),
    ]
    for cfg, what, match in bad:
        cfg = dataclasses.replace(cfg, agent=AgentOptions())
        if what == "pcgrad":
            cfg.agent.multitask = MultiTaskOptions(pcgrad=True)
        elif what == "weights":
            cfg.agent.multitask = MultiTaskOptions(task_weights=(1.0, 2.0))
        elif what == "heads_text":
            cfg.env = dataclasses.replace(cfg.env, goal_type="language")
            cfg.buffer = BufferConfig(k=4)
            cfg.agent.net = NetConfig(task_heads=8)
        else:
            cfg.agent.net = NetConfig(task_heads=3)
        with pytest.raises(LcrlError, match=match):
            cfg.validate()


def test_cli_refuses_relabelling_task_ids(capsys):
    assert cli("train", "lang2d-tasks", "--buffer.k", "4", "--no-progress") == 2
    assert "one-hot task ids cannot be relabelled" in error_line(capsys.readouterr().err)


# --- per-task heads -----------------------------------------------------------------------------
@pytest.mark.parametrize("fusion", ["concat", "film"])
def test_task_heads_pick_the_task_head(fusion):
    torch.manual_seed(0)
    cfg = NetConfig(hidden=(16, 16), text_dim=8, fusion=fusion, task_heads=3)
    obs_shapes = {"observation": (5,)}
    nets = [
        GoalConditionedNet(obs_shapes, "onehot", (3,), 2, cfg),
        GoalConditionedEnsemble(2, obs_shapes, "onehot", (3,), 1, cfg, action_dim=2),
    ]
    obs = {"observation": torch.randn(6, 5)}
    goal = torch.eye(3)[[0, 1, 2, 0, 1, 2]]
    act = torch.randn(6, 2)
    rows1 = goal.argmax(-1) == 1
    for net in nets:
        ensemble = isinstance(net, GoalConditionedEnsemble)
        args = (obs, goal, act) if ensemble else (obs, goal)
        before = net(*args).detach()
        heads = [m for m in net.modules() if isinstance(m, TaskHeads)]
        assert heads
        with torch.no_grad():  # change head 1 only: rows of tasks 0 and 2 keep their output
            for h in heads:
                h.weight[..., 1, :, :] += 1.0
        diff = (net(*args).detach() - before).abs()
        if ensemble:
            assert diff.shape == (2, 6, 1)
            diff = diff.amax(0)
        assert torch.all(diff[~rows1] == 0) and torch.all(diff[rows1] > 0)


def test_task_heads_refuse_other_goals():
    with pytest.raises(LcrlError, match="one-hot task id"):
        GoalConditionedNet({"o": (3,)}, "text", (8,), 2, NetConfig(task_heads=8))
    with pytest.raises(LcrlError, match="task-heads 4"):
        GoalConditionedNet({"o": (3,)}, "onehot", (4,), 2, NetConfig(task_heads=3))


def test_sac_with_task_heads_round_trips_a_checkpoint(tmp_path):
    problem = Problem({"observation": (4,)}, "onehot", (3,), 2, num_tasks=3)
    opts = AgentOptions(net=NetConfig(hidden=(16, 16), text_dim=8, task_heads=3))
    embed = TaskGoals(3).embed
    agent = SAC(problem, opts, embed)
    path = save_checkpoint(tmp_path / "ck", modules=agent.modules(), states=agent.states(),
                           meta={"problem": problem.to_dict()})  # fmt: skip
    ckpt = load_checkpoint(path)
    assert Problem.from_dict(ckpt.meta["problem"]) == problem
    other = SAC(problem, dataclasses.replace(opts, seed=5), embed)
    obs = {"observation": np.random.default_rng(0).normal(size=(3, 4)).astype(np.float32)}
    goals = np.array([0, 1, 2])
    assert not np.allclose(other.act(obs, goals, True), agent.act(obs, goals, True))
    for name, module in other.modules().items():
        ckpt.load_module(name, module)
    assert np.array_equal(other.act(obs, goals, True), agent.act(obs, goals, True))


# --- the SAC update ----------------------------------------------------------------------------
def _batch(num_tasks: int, tasks: np.ndarray, seed: int = 0):
    from lcrl.buffer import Batch

    rng = np.random.default_rng(seed)
    n = len(tasks)
    return Batch(
        obs={"observation": rng.normal(size=(n, 4)).astype(np.float32)},
        action=rng.uniform(-1, 1, (n, 2)).astype(np.float32),
        reward=rng.integers(0, 2, n).astype(np.float32),
        next_obs={"observation": rng.normal(size=(n, 4)).astype(np.float32)},
        terminated=np.zeros(n, np.float32),
        goal=np.asarray(tasks, np.int64),
        relabelled=np.zeros(n, bool),
        index=np.arange(n),
    )


def _sac(multitask: MultiTaskOptions, seed: int = 0) -> SAC:
    problem = Problem({"observation": (4,)}, "onehot", (3,), 2, num_tasks=3)
    opts = AgentOptions(net=NetConfig(hidden=(16, 16), text_dim=8), multitask=multitask, seed=seed)
    return SAC(problem, opts, TaskGoals(3).embed)


def test_sac_multitask_update_matches_the_single_task_update():
    batch = _batch(3, np.arange(32) % 3)
    plain = _sac(MultiTaskOptions())
    assert plain.multitask is None
    plain.update(batch)
    # measured (per-task forward passes), no PCGrad, equal weights: the same critic gradient
    measured = _sac(MultiTaskOptions(conflict_every=1))
    metrics = measured.update(batch)
    assert torch.allclose(measured.critic_opt.grad, plain.critic_opt.grad, atol=1e-6)
    assert -1.0 <= metrics["grad/critic_cos_mean"] <= 1.0
    assert 0.0 <= metrics["grad/actor_conflict"] <= 1.0
    # not measured on this update: the single-task computation, same random draws
    skipped = _sac(MultiTaskOptions(conflict_every=5))
    skipped.updates = 1
    before = _sac(MultiTaskOptions())
    m1, m2 = skipped.update(batch), before.update(batch)
    assert not any(k.startswith("grad/") for k in m1)
    for opt in ("critic_opt", "actor_opt"):
        a, b = getattr(skipped, opt).grad, getattr(before, opt).grad
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6), opt
    assert m1["critic_loss"] == pytest.approx(m2["critic_loss"], rel=1e-5)


@pytest.mark.parametrize("pcgrad", [False, True])
def test_sac_zero_task_weight_ignores_that_task(pcgrad):
    agent = _sac(MultiTaskOptions(task_weights=(1.0, 0.0, 1.0), pcgrad=pcgrad))
    critic, actor = agent.critic_opt.flat.clone(), agent.actor_opt.flat.clone()
    agent.update(_batch(3, np.ones(16, np.int64)))  # only rows of the weight-0 task
    assert torch.equal(agent.critic_opt.flat, critic)
    assert torch.equal(agent.actor_opt.flat, actor)
    agent.update(_batch(3, np.arange(16) % 3))
    assert not torch.equal(agent.critic_opt.flat, critic)


def test_pcgrad_needs_sac():
    from lcrl.algos import TD3

    problem = Problem({"observation": (4,)}, "onehot", (3,), 2, num_tasks=3)
    opts = AgentOptions(multitask=MultiTaskOptions(pcgrad=True))
    with pytest.raises(LcrlError, match="implemented for SAC, not td3"):
        TD3(problem, opts, TaskGoals(3).embed)


# --- lcrl train lang2d-tasks end to end --------------------------------------------------------
def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


TASK_COLUMNS = [f"tasks/{i}/{c}" for i in range(8) for c in ("success", "prob")]
GRAD_COLUMNS = [
    f"grad/{net}_{k}" for net in ("critic", "actor") for k in ("cos_mean", "cos_min", "conflict")
]


@pytest.mark.parametrize("pcgrad", [False, True])
def test_train_lang2d_tasks_writes_per_task_and_conflict_columns(tmp_path, pcgrad):
    cfg = tiny("lang2d-tasks", tmp_path / "run", eval_episodes=8)
    cfg.agent.multitask = MultiTaskOptions(pcgrad=pcgrad, conflict_every=3)
    results = Trainer(cfg).run()
    fields, rows = read_csv(tmp_path / "run" / "progress.csv")
    assert set(TASK_COLUMNS) <= set(fields) and set(GRAD_COLUMNS) <= set(fields)
    probs = [sum(float(r[f"tasks/{i}/prob"]) for i in range(8)) for r in rows]
    assert probs == pytest.approx([1.0] * len(rows))
    last = rows[-1]
    assert all(math.isfinite(float(last[c])) for c in GRAD_COLUMNS)
    assert -1.0 <= float(last["grad/critic_cos_mean"]) <= 1.0
    played = [i for i in range(8) if last[f"tasks/{i}/success"] != "nan"]
    assert len(played) >= 4
    fields, _ = read_csv(tmp_path / "run" / "eval.csv")
    assert [f"tasks/{i}" for i in range(8)] == [f for f in fields if f.startswith("tasks/")]
    tasks = results["train"]["tasks"]
    assert [x["instruction"] for x in tasks] == list(TASKS_2D)
    assert [x["episodes"] for x in tasks] == [1] * 8  # round robin over the tasks
    report = (tmp_path / "run" / "report.md").read_text()
    assert "Success per task" in report and "push the yellow cube backward" in report


def test_cli_train_lang2d_tasks_with_pcgrad(tmp_path, capsys):
    out = tmp_path / "cli"
    args = [
        "train", "lang2d-tasks", "--out", str(out), "--total-steps", "200",
        "--learning-starts", "100", "--batch-size", "16", "--eval-episodes", "8",
        "--log-every", "100", "--buffer.capacity", "2000", "--agent.net.hidden", "16", "16",
        "--agent.net.text-dim", "8", "--agent.net.task-heads", "8",
        "--agent.multitask.pcgrad", "--agent.multitask.sampling", "success",
        "--no-progress", "--no-tensorboard",
    ]  # fmt: skip
    assert cli(*args) == 0
    fields, rows = read_csv(out / "progress.csv")
    assert set(GRAD_COLUMNS) <= set(fields)
    assert math.isfinite(float(rows[-1]["grad/actor_cos_mean"]))  # PCGrad measures every update
    ckpt = load_checkpoint(out / "checkpoints" / "step_000000200")
    assert ckpt.meta["config"]["agent"]["multitask"]["pcgrad"] is True
    assert ckpt.meta["problem"]["num_tasks"] == 8
    # the report rebuilt from eval.csv keeps the per-task table
    (out / "report.md").unlink()
    assert cli("report", str(out)) == 0
    assert "| 7 | push the yellow cube backward |" in (out / "report.md").read_text()
    capsys.readouterr()
    assert cli("eval", str(out), "--episodes", "8", "--no-progress") == 0
    assert "task 7 'push the yellow cube backward'" in capsys.readouterr().out


def test_resume_keeps_the_task_sampler_state(tmp_path):
    cfg = tiny("lang2d-tasks", tmp_path / "run", total_steps=10_000, learning_starts=60)
    cfg.agent.multitask = MultiTaskOptions(sampling="success", window=3, pcgrad=True)
    straight = Trainer(cfg)
    for _ in range(5):
        straight.collect_episode()
    straight.save()  # at an episode boundary: the resumed run continues exactly
    saved = straight.sampler.state_dict()
    # the sampler learns from the policy's episodes, not the scripted ones
    assert sum(saved["count"]) == 5 - straight.scripted_episodes > 0
    assert saved["strategy"] == "success"
    for _ in range(3):
        straight.collect_episode()
    resumed = Trainer(dataclasses.replace(cfg, resume=True))
    assert resumed.sampler.state_dict() == saved
    for _ in range(3):
        resumed.collect_episode()
    assert resumed.step == straight.step and resumed.agent.updates == straight.agent.updates > 0
    assert resumed.sampler.state_dict() == straight.sampler.state_dict()
    assert resumed.task_rng.bit_generator.state == straight.task_rng.bit_generator.state
    assert torch.equal(resumed.agent.actor_opt.flat, straight.agent.actor_opt.flat)


def test_train_lang2d_tasks_as_language_goals(tmp_path):
    """The same tasks as language goals: the table is the task set, relabelled among them,
    evaluated round robin like task ids."""
    cfg = tiny("lang2d-tasks-lang", tmp_path / "lang", total_steps=200, eval_episodes=8)
    trainer = Trainer(cfg)
    assert trainer.task.table == list(TASKS_2D) and trainer.problem.num_tasks == 8
    assert trainer.buffer.k == 4
    results = trainer.run()
    assert [t["episodes"] for t in results["train"]["tasks"]] == [1] * 8
    batch = trainer.buffer.sample(256)
    assert batch.goal.max() < 8  # relabelled goals are task ids too
    fields, _ = read_csv(tmp_path / "lang" / "progress.csv")
    assert set(TASK_COLUMNS) <= set(fields) and set(GRAD_COLUMNS) <= set(fields)


@pytest.mark.slow
def test_task_ids_on_robosuite():
    pytest.importorskip("robosuite")
    tasks = ("reach the red cube", "push the blue cube left")
    cfg = EnvConfig(kind="robosuite", goal_type="task", tasks=tasks, max_episode_steps=10)
    env = make_env(cfg, "train", training=True)
    try:
        task = make_task(cfg, env)
        assert isinstance(task, TaskIdTask) and task.problem().goal_shape == (2,)
        obs, info = reset_feasible(env, 0, tasks[1])
        assert info["feasible"] and task.goal(obs, env) == 1
        records = [task.step_record(obs, env)]
        for _ in range(3):
            obs, *_ = env.step(env.action_space.sample())
            records.append(task.step_record(obs, env))
        fields = task.episode_fields(records, 1, env)
        assert fields["success"] == [
            task.captioner.satisfied(tasks[1], records[0], s) for s in records[1:]
        ]
    finally:
        env.close()


def test_benchmark_configs():
    from benchmarks.multitask import RUNS, per_task_counts, run_config

    assert per_task_counts(20, 8) == [3, 3, 3, 3, 2, 2, 2, 2]
    for name, (preset, pcgrad, weighting) in RUNS.items():
        cfg = run_config(name, 1000, 0, 16, "cpu")
        cfg.validate()
        assert cfg.agent.multitask.pcgrad is pcgrad and cfg.env.tasks == TASKS_2D
        assert cfg.agent.multitask.weighting == weighting
        assert cfg.learning_starts == 250 and cfg.eval_every == 500
        assert (cfg.env.goal_type == "task") is (preset == "lang2d-tasks")
        assert cfg.buffer.k == (0 if preset == "lang2d-tasks" else 4)
        # every arm collects alike, whatever its preset ships
        assert (cfg.collect.envs, cfg.batch_size) == (1, 256)
    assert PRESETS["lang2d-tasks-lang"][1].collect.envs == 8


def test_benchmark_runs_stopped_midway_go_on_from_their_checkpoint(tmp_path):
    import dataclasses

    from benchmarks.learning_curves import resumable
    from benchmarks.multitask import run_config, summarise, train_one

    cfg = dataclasses.replace(run_config("ids", 600, 0, 8, "cpu"), out=str(tmp_path / "ids"))
    assert cfg.checkpoint_every == cfg.eval_every == 300 and cfg.save_buffer
    assert not resumable(cfg, tmp_path / "ids")  # nothing there yet
    train_one(dataclasses.replace(cfg, total_steps=300))  # a session ends at step 300
    assert resumable(cfg, tmp_path / "ids")
    assert not resumable(dataclasses.replace(cfg, total_steps=300), tmp_path / "ids")
    pcgrad = run_config("ids-pcgrad", 600, 0, 8, "cpu")
    assert not resumable(dataclasses.replace(pcgrad, out=cfg.out), tmp_path / "ids")
    first = read_csv(tmp_path / "ids" / "eval.csv")[1]
    train_one(cfg)  # goes on from 300: the first evaluation is kept
    rows = read_csv(tmp_path / "ids" / "eval.csv")[1]
    assert rows[0] == first[0] and int(rows[-1]["step"]) >= 600
    assert not resumable(cfg, tmp_path / "ids")
    summary = summarise("ids", cfg, None)
    assert summary["seconds"] == float(rows[-1]["train_s"]) > float(first[-1]["train_s"])

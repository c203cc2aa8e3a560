"""Evaluating and querying policies trained on a fixed task set: ``lcrl eval`` per task,
``lcrl act --task``, ``lcrl.load(...).act(obs, task_id)``, their errors, and the summary
lines of ``lcrl report`` for task-id and behavioural-cloning runs.

Policies come from tiny training runs (200 steps, 32-unit networks) of the
``lang2d-tasks`` (one-hot task ids) and ``lang2d-tasks-lang`` (the same tasks as language
goals) presets, and from an oracle that drives the pusher straight at the object of its
task, so that the per-task figures are not all zero.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from helpers import cli, error_line, tiny

import lcrl
from captioner.grammar import parse
from envs.features import slot_layout
from envs.scene import OBJECT_KINDS
from lcrl.errors import LcrlError
from train.commands.act import ActSession
from train.configs.config import config_to_dict
from train.configs.presets import PRESETS, TASKS_2D
from train.evaluation.eval_suite import episode_seed, run_evaluation
from train.evaluation.evaluate import evaluate, run_episode
from train.evaluation.report import learning_summary, write_report
from train.policies.loading import load_policy
from train.policies.policy import Policy
from train.training.loop import Trainer

K = len(TASKS_2D)


# --- fixtures and helpers ----------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def task_run(tmp_path_factory) -> Path:
    """A finished 200-step lang2d-tasks run (8 tasks as one-hot task ids)."""
    out = tmp_path_factory.mktemp("tasks") / "run"
    Trainer(tiny("lang2d-tasks", out, total_steps=200, eval_episodes=8)).run()
    return out


@pytest.fixture(scope="module")
def lang_run(tmp_path_factory) -> Path:
    """A finished 150-step lang2d-tasks-lang run (the same tasks as language goals)."""
    out = tmp_path_factory.mktemp("tasks-lang") / "run"
    Trainer(
        tiny("lang2d-tasks-lang", out, total_steps=150, learning_starts=100, eval_episodes=8)
    ).run()
    return out


@pytest.fixture(scope="module")
def loaded(task_run):
    return load_policy(task_run)


class TaskOracle:
    """Moves the pusher straight at the object of its task (read from the one-hot task
    id's instruction): reach tasks succeed, push tasks mostly do not. Row by row numpy, so
    its actions never depend on how many rows a call holds."""

    def __init__(self, task, env) -> None:
        self.objects = [OBJECT_KINDS.index(m.obj) for m in task.meanings]
        self.start, _, self.width, _ = slot_layout(env)

    def act(self, obs, goal, deterministic=True, embedded=False):
        assert deterministic and not embedded
        out = []
        for row, g in zip(obs["observation"], np.asarray(goal), strict=True):
            k = self.objects[int(g)]
            rel = row[self.start + k * self.width :][3:5]  # [x, y, present, rel x, rel y, ..]
            out.append(np.clip(rel / max(float(np.abs(rel).max()), 1e-6), -1.0, 1.0))
        return np.asarray(out, np.float32)


class RecordActions(gym.Wrapper):
    """Keeps every action passed to ``step``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.actions: list[np.ndarray] = []

    def step(self, action):
        self.actions.append(np.array(action, copy=True))
        return self.env.step(action)


def _without_results(res: dict) -> dict:
    return {k: v for k, v in res.items() if k != "episode_results"}


# --- lcrl eval on task ids ---------------------------------------------------------------
def test_task_ids_round_robin_and_independent_of_num_envs(loaded):
    one = run_evaluation(loaded.agent, loaded.task, loaded.cfg, 2 * K, num_envs=1)
    two = run_evaluation(loaded.agent, loaded.task, loaded.cfg, 2 * K, num_envs=2)
    assert list(one) == ["train"]
    assert one == two
    res = one["train"]
    episodes = res["episode_results"]
    assert [e["seed"] for e in episodes] == [episode_seed(0, i) for i in range(2 * K)]
    assert [e["attempts"][0]["instruction"] for e in episodes] == [*TASKS_2D, *TASKS_2D]
    tasks = res["tasks"]
    assert [t["id"] for t in tasks] == list(range(K))
    assert [t["instruction"] for t in tasks] == list(TASKS_2D)
    assert [t["family"] for t in tasks] == [parse(t).family for t in TASKS_2D]
    assert [t["episodes"] for t in tasks] == [2] * K  # split evenly over the tasks
    assert sum(t["successes"] for t in tasks) == res["successes"]
    for t in tasks:
        low, high = t["ci"]
        assert 0.0 <= low <= t["success"] <= high <= 1.0
    assert set(res["families"]) == {"reach", "push"}
    assert res["families"]["reach"]["episodes"] == res["families"]["push"]["episodes"] == K


def test_task_layouts_are_those_of_the_training_evaluation(loaded):
    """An oracle that reaches its task's object: per-task success of lcrl eval (vector
    envs) equals that of the training loop's round-robin evaluation, layout for layout."""
    oracle = TaskOracle(loaded.task, loaded.env)
    n = 2 * K
    loop = evaluate(oracle, loaded.task, loaded.cfg, n, seed=3)["train"]
    suite = run_evaluation(oracle, loaded.task, loaded.cfg, n, seed=3, num_envs=3)["train"]
    assert [t["success"] for t in suite["tasks"]] == pytest.approx(
        [t["success"] for t in loop["tasks"]]
    )
    assert suite["success"] == pytest.approx(loop["success"])
    reach = [t["success"] for t in suite["tasks"] if t["family"] == "reach"]
    assert min(reach) == 1.0  # the oracle reaches every object: the figures are not all 0
    steps = suite["tasks"][0]["mean_steps_to_success"]
    assert steps is not None and 0 < steps < loaded.cfg.env.max_episode_steps


def test_cli_eval_task_ids_writes_the_report_format(task_run, capsys):
    out = task_run / "evals" / "final"
    args = ["eval", str(task_run), "--episodes", "12", "--num-envs", "2", "--no-progress"]
    assert cli(*args, "--out", str(out)) == 0
    printed = capsys.readouterr().out
    assert "note: 12 episodes over 8 tasks: tasks 0 to 3 get one episode more" in printed
    assert "task 7 'push the yellow cube backward'" in printed
    doc = json.loads((out / "eval.json").read_text())
    assert doc["format"] == "lcrl-eval" and list(doc["sets"]) == ["train"]
    assert doc["task"] == "2D tabletop, 8 tasks as task ids"
    assert doc["settings"]["tasks"] == list(TASKS_2D)
    assert [t["episodes"] for t in doc["sets"]["train"]["tasks"]] == [2] * 4 + [1] * 4
    for name in ("sets.png", "tasks.png", "heatmap.png", "curves.png", "eval.md"):
        assert (out / name).is_file(), name
    md = (out / "eval.md").read_text()
    assert "## Success per task" in md and "![success per task](tasks.png)" in md
    assert "| 7 | push the yellow cube backward | push |" in md
    assert cli("report", str(task_run)) == 0
    report = (task_run / "report.md").read_text()
    assert "2D tabletop, 8 tasks as task ids, sac, task ids, no relabelling, 200 steps" in report
    assert "### final (checkpoint step 200)" in report
    assert "![final: success per task](evals/final/tasks.png)" in report


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--sets", "heldout"), "a task-id policy has one set, 'train' (its 8 tasks)"),
        (("--chain", "2"), "a task-id policy cannot follow: drop --chain"),
        (("--instructions", "FILE"), "reads no text, only the ids of its 8 tasks"),
        (("--families", "reach"), "cannot narrow a checkpoint trained on a fixed task set"),
    ],
)
def test_cli_eval_task_id_errors(task_run, tmp_path, capsys, extra, message):
    path = tmp_path / "instructions.txt"
    path.write_text("reach the red cube\n")
    extra = tuple(str(path) if x == "FILE" else x for x in extra)
    assert cli("eval", str(task_run), "--episodes", "8", *extra) == 2
    err = capsys.readouterr().err
    assert message in error_line(err) and "Traceback" not in err


def test_eval_language_goals_over_a_task_set(lang_run):
    policy = load_policy(lang_run)
    one = run_evaluation(policy.agent, policy.task, policy.cfg, K, num_envs=1)
    assert list(one) == ["train", "heldout", "paraphrase"]
    train = one["train"]
    assert [t["episodes"] for t in train["tasks"]] == [1] * K
    assert [e["attempts"][0]["instruction"] for e in train["episode_results"]] == list(TASKS_2D)
    assert "tasks" not in one["heldout"] and "tasks" not in one["paraphrase"]
    heldout = {e["attempts"][0]["instruction"] for e in one["heldout"]["episode_results"]}
    assert not heldout & set(TASKS_2D)
    two = run_evaluation(policy.agent, policy.task, policy.cfg, K, sets=["train"], num_envs=2)
    assert two["train"] == train


# --- lcrl act --task ----------------------------------------------------------------------
def test_cli_act_runs_a_task_by_id_or_text(task_run, tmp_path, capsys):
    video = tmp_path / "task.gif"
    args = ["act", str(task_run), "--episodes", "2"]
    assert cli(*args, "--task", "2", "--video", str(video)) == 0
    out = capsys.readouterr().out
    assert "task 2: 'reach the blue cube' (task id 2 of 8)" in out
    assert out.count("episode ") == 2 and "over 2 episodes" in out
    from PIL import Image

    with Image.open(video) as gif:
        assert gif.n_frames >= 2
    assert cli(*args, "--task", "touch the blue block") == 0  # any phrasing of the task
    assert "task 2: 'reach the blue cube'" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (("--task", "dance a jig"), "is none of this policy's tasks: 0 'reach the red cube'"),
        (("--task", "8"), "task id 8 is out of range: this policy has 8 tasks, ids 0 to 7"),
        (("--instruction", "reach the red cube"), "it reads no free text (--instruction)"),
        ((), "this is a task-id checkpoint: give --task"),
        (("--task", "1", "--instruction", "x"), "give either --instruction or --task, not both"),
    ],
)
def test_cli_act_task_errors(task_run, capsys, extra, message):
    assert cli("act", str(task_run), "--episodes", "1", *extra) == 2
    err = capsys.readouterr().err
    assert message in error_line(err) and "Traceback" not in err
    if "is none of" in message or "out of range" in message:
        assert "7 'push the yellow cube backward'" in err  # the tasks are listed


def test_interactive_reads_task_ids_and_texts(task_run):
    policy = lcrl.load(task_run, device="cpu")
    printed = io.StringIO()
    session = ActSession(policy, policy.make_env(), episodes=1, out=printed)
    lines = ["3", "dance a jig", "shove the red cube to the left", "quit", "1"]
    results = session.interactive(lines)
    assert [r.text for r in results] == [TASKS_2D[3], TASKS_2D[4]]
    assert all(len(r.steps) == 1 for r in results)
    assert "error: 'dance a jig' is none of this policy's tasks" in printed.getvalue()
    with pytest.raises(LcrlError, match="trained with task ids: it reads no text"):
        session.run_text("reach the red cube")


def test_cli_act_task_on_language_goals(lang_run, capsys):
    assert cli("act", str(lang_run), "--task", "3", "--episodes", "1") == 0
    out = capsys.readouterr().out
    assert "task 3 of 8:" in out and "1.000  reach the yellow cube" in out


# --- lcrl.load(...).act(obs, task_id) -----------------------------------------------------
def test_load_acts_on_task_ids_exactly_like_the_episode_runner(task_run):
    policy = lcrl.load(task_run, device="cpu")
    assert policy.takes_task_ids and not policy.language
    assert policy.tasks == list(TASKS_2D)
    assert "8 task ids" in repr(policy)
    env = RecordActions(policy.make_env())
    run_episode(policy.agent, policy.task, env, seed=5, options={"instruction": TASKS_2D[3]})
    obs, _ = env.reset(seed=5, options={"instruction": TASKS_2D[3]})
    policy.reset()
    for recorded in env.actions:
        action = policy.act(obs, 3)
        np.testing.assert_array_equal(action, recorded)
        assert np.array_equal(policy.act(obs, np.int64(3)), action)
        assert np.array_equal(policy.act(obs, np.asarray(3)), action)
        assert np.array_equal(policy.act(obs), action)  # the observation's instruction
        obs, *_ = env.env.step(action)


def test_task_id_batches_and_lookup(task_run):
    policy = lcrl.load(task_run, device="cpu")
    env = policy.make_env()
    obs = [env.reset(seed=s, options={"instruction": TASKS_2D[s]})[0] for s in range(3)]
    batch = {"observation": np.stack([o["observation"] for o in obs])}
    ids = [0, 3, 7]
    rows = []
    for o, i in zip(obs, ids, strict=True):
        policy.reset()
        rows.append(policy.act(o, i))
    policy.reset()
    np.testing.assert_allclose(policy.act(batch, ids), np.stack(rows), atol=1e-6)
    policy.reset()
    np.testing.assert_allclose(policy.act(batch, np.asarray(ids)), np.stack(rows), atol=1e-6)
    policy.reset()
    same = policy.act(batch, 4)
    assert same.shape == (3, 2)
    policy.reset()
    np.testing.assert_allclose(same, policy.act(batch, [4, 4, 4]), atol=1e-6)
    assert policy.task_id("touch the blue block") == 2
    assert policy.task_id(" push  the red cube left ") == 4
    assert policy.task_id(np.int32(6)) == 6


@pytest.mark.parametrize(
    "task, message",
    [
        ("reach the red cube", "reads no text; pass a task id"),
        (["reach the red cube"], "reads no text; pass a task id"),
        (8, "task id 8 is out of range: this policy has 8 tasks"),
        (-1, "task id -1 is out of range"),
        (True, "a task id must be an integer, got bool"),
        (1.0, "a task id must be an integer, got float"),
        ([0, 1], "2 task ids for one observation"),
        ([[0]], "one id or a list of ids"),
    ],
)
def test_task_id_act_errors(task_run, task, message):
    policy = lcrl.load(task_run, device="cpu")
    obs, _ = policy.make_env().reset(seed=0, options={"instruction": TASKS_2D[0]})
    with pytest.raises(LcrlError, match=message.replace("(", r"\(")):
        policy.act(obs, task)
    assert policy._initial is None  # nothing remembered from a refused call


def test_task_id_policy_other_errors(task_run):
    policy = lcrl.load(task_run, device="cpu")
    env = policy.make_env()
    obs, _ = env.reset(seed=0, options={"instruction": "reach the red cylinder"})
    with pytest.raises(LcrlError, match="instruction 'reach the red cylinder' is none"):
        policy.act(obs)
    with pytest.raises(LcrlError, match="goal= is for state- and image-goal policies"):
        policy.act(obs, 0, goal=np.zeros(2))
    with pytest.raises(LcrlError, match="'dance' is none of this policy's tasks: 0 'reach"):
        policy.task_id("dance")
    with pytest.raises(LcrlError, match="not trained with language goals"):
        policy.nearest("reach the red cube")
    cfg = copy.deepcopy(policy.cfg)
    cfg.env.tasks = ()
    plain = Policy(cfg, policy.agent, policy.task, policy.env, policy.checkpoint)
    assert plain.tasks == []
    with pytest.raises(LcrlError, match="not trained on a fixed task set"):
        plain.task_id(0)


# --- report summary lines ------------------------------------------------------------------
def _run_with(tmp_path: Path, name: str, config: dict) -> str:
    run = tmp_path / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps(config))
    return write_report(run).read_text().splitlines()[2]


def test_report_summary_lines(tmp_path):
    bc = copy.deepcopy(PRESETS["lang2d-bc"][1])
    bc = dataclasses.replace(bc, demos="data/demos.h5")
    line = _run_with(tmp_path, "bc", {**config_to_dict(bc), "resolved_algo": "bc"})
    assert "bc, behavioural cloning from data/demos.h5 (hindsight segments on)" in line
    assert "20,000 updates" in line and "relabelling" not in line
    bc.bc.hindsight = False
    assert "(hindsight segments off)" in learning_summary(config_to_dict(bc))
    tasks = config_to_dict(PRESETS["lang2d-tasks"][1])
    line = _run_with(tmp_path, "tasks", {**tasks, "resolved_algo": "sac"})
    assert line.startswith("2D tabletop, 8 tasks as task ids, sac, task ids, no relabelling,")
    lang = config_to_dict(PRESETS["lang2d-tasks-lang"][1])
    assert learning_summary({**lang, "resolved_algo": "sac"}) == "relabelling future k=4"

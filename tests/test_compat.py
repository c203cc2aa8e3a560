"""Runs, checkpoints and configs written before ``EnvConfig`` split the simulator from the
goal type still load, evaluate and resume.

``tests/fixtures/v0`` holds tiny runs made by that version: ``lang2d`` (the 2D tabletop
with language goals, kind ``lang2d``), ``state2d`` (kind ``state2d``, which saved
``goal_type="language"`` and meant state goals), ``tasks`` (task ids, kind ``lang2d``)
and the saved config of the ``fetch-reach`` preset (kind ``gym``, ``goal_type="language"``,
meaning state goals). Each run has 120 steps, 16-unit networks and no replay buffer.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers import cli

from train.configs.config import config_from_dict
from train.evaluation.evaluate import run_episode
from train.policies.loading import load_policy
from train.training.loop import Trainer

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "v0"


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


def saved_config(name: str) -> dict:
    path = FIXTURES / name / "config.json"
    if not path.exists():
        path = FIXTURES / f"{name}-config.json"
    data = json.loads(path.read_text())
    data.pop("resolved_algo", None)
    return data


@pytest.mark.parametrize(
    ("name", "kind", "goal_type"),
    [
        ("lang2d", "tabletop2d", "language"),
        ("state2d", "tabletop2d", "state"),
        ("tasks", "tabletop2d", "task"),
        ("fetch-reach", "gym", "state"),
    ],
)
def test_old_configs_load_with_simulator_and_goal_type_apart(name, kind, goal_type):
    saved = saved_config(name)
    assert saved["env"]["kind"] in ("lang2d", "state2d", "gym")  # the old spelling
    cfg = config_from_dict(saved)
    assert (cfg.env.kind, cfg.env.goal_type) == (kind, goal_type)
    cfg.validate()


@pytest.mark.parametrize("name", ["lang2d", "state2d", "tasks"])
def test_old_checkpoints_load_and_act(name):
    loaded = load_policy(FIXTURES / name)
    options = None
    if loaded.task.query == "task_id":
        options = {"instruction": loaded.cfg.env.tasks[0]}
    r = run_episode(loaded.agent, loaded.task, loaded.env, seed=0, options=options)
    assert r["steps"] > 0 and isinstance(r["success"], bool)
    loaded.env.close()


def test_old_run_evaluates_and_resumes(tmp_path, capsys):
    run = tmp_path / "lang2d"
    shutil.copytree(FIXTURES / "lang2d", run)
    assert (
        cli("eval", str(run), "--episodes", "2", "--no-progress", "--out", str(tmp_path / "e")) == 0
    )
    doc = json.loads((tmp_path / "e" / "eval.json").read_text())
    assert set(doc["sets"]) == {"train", "heldout", "paraphrase"}
    assert doc["task"] == "2D tabletop reach"

    cfg = config_from_dict(saved_config("lang2d"))
    cfg.out, cfg.resume, cfg.total_steps, cfg.progress = str(run), True, 150, False
    trainer = Trainer(cfg)
    assert trainer.step == 120 and trainer.cfg.env.kind == "tabletop2d"
    trainer.run()
    assert trainer.step == 150
    assert "holds no replay buffer" in capsys.readouterr().out
    assert json.loads((run / "config.json").read_text())["env"]["kind"] == "tabletop2d"


def test_old_kind_names_work_on_the_command_line(tmp_path):
    out = tmp_path / "run"
    args = ["train", "lang2d-quick", "--env.kind", "state2d", "--env.goal", "pusher"]
    args += ["--scripted-fraction", "0"]
    tiny = ["--total-steps", "40", "--learning-starts", "20", "--eval-every", "0"]
    tiny += ["--eval-episodes", "1", "--batch-size", "8", "--no-progress", "--no-tensorboard"]
    assert cli(*args, *tiny, "--out", str(out)) == 0
    env = json.loads((out / "config.json").read_text())["env"]
    assert (env["kind"], env["goal_type"]) == ("tabletop2d", "state")


def test_removed_registry_names_give_the_new_spelling():
    import train.environments.tasks
    from lcrl.errors import LcrlError

    with pytest.raises(
        ImportError, match=r"ENV_KINDS was replaced by train\.environments\.simulators\.ENVS"
    ):
        from train.environments.tasks import ENV_KINDS  # noqa: F401
    with pytest.raises(
        LcrlError, match=r"GOAL_TYPES was replaced by train\.environments\.tasks\.GOALS"
    ):
        _ = train.environments.tasks.GOAL_TYPES
    assert not hasattr(
        train.environments.tasks, "NO_SUCH_NAME"
    )  # other names: a plain AttributeError

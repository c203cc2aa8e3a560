"""Teacher -> student distillation with DAgger (``lcrl distill``), at a tiny size: the
student's loss on the teacher's labels falls, the teacher's share of the actions shrinks,
the student acts through ``lcrl.load`` from camera frames, resuming is exact, and
teachers or students that cannot work are refused in one line."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import cli, error_line, hold, tiny, untrained_perception

from lcrl.perception import Perception, SlotLayout
from train.environments.perception import PerceptionTrainConfig, save_model


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def teacher(tmp_path_factory) -> Path:
    """A privileged-state lang2d-quick policy (a few hundred steps: DAgger clones whatever
    it does)."""
    from train.training.loop import Trainer

    out = tmp_path_factory.mktemp("distill") / "teacher"
    Trainer(tiny("lang2d-quick", out, total_steps=400, learning_starts=100)).run()
    return out


@pytest.fixture(scope="module")
def perception(tmp_path_factory) -> Path:
    """A perception model for the 2D tabletop's 64 px frames (untrained weights: DAgger
    only needs something that reads frames)."""
    return untrained_perception(tmp_path_factory.mktemp("distill") / "perception")


def _rows(path: Path) -> list[dict[str, float]]:
    with open(path) as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def test_dagger_hands_over_control_and_its_loss_falls(teacher, perception, tmp_path):
    out = tmp_path / "student"
    args = ["distill", str(teacher), "--perception", str(perception), "--out", str(out)]
    args += ["--rounds", "3", "--episodes-per-round", "4", "--updates-per-round", "150"]
    args += ["--batch-size", "64", "--eval-every", "0", "--eval-episodes", "2"]
    assert cli(*args, "--no-progress", "--no-tensorboard") == 0
    rows = _rows(out / "progress.csv")
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert [r["beta"] for r in rows] == [1.0, 0.5, 0.25]
    assert rows[0]["teacher_share"] == 1.0 and rows[2]["teacher_share"] < 0.6
    assert rows[0]["rows"] < rows[1]["rows"] < rows[2]["rows"]  # the dataset aggregates
    # the student's loss on the teacher's labels falls within a round and over the run
    assert all(r["loss"] < 0.5 * r["loss_first"] for r in rows)
    assert rows[2]["loss"] < 0.5 * rows[0]["loss_first"]

    import lcrl

    policy = lcrl.load(out)
    assert policy.perceives and policy.checkpoint.meta["algo"] == "bc"
    assert policy.checkpoint.meta["distill"]["rows"] == rows[2]["rows"]
    env = policy.make_env()
    obs, _ = env.reset(seed=0)
    frames = {"image": obs["image"], "proprio": obs["privileged"][:2]}
    action = policy.act(frames, "reach the red cube")
    policy.reset()
    np.testing.assert_array_equal(action, policy.act(obs, "reach the red cube"))


def test_a_resumed_distillation_continues_exactly(teacher, perception, tmp_path):
    common = ["--perception", str(perception), "--episodes-per-round", "2"]
    common += ["--updates-per-round", "20", "--batch-size", "16", "--eval-every", "0"]
    common += ["--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    assert cli("distill", str(teacher), "--out", str(whole), "--rounds", "3", *common) == 0
    assert cli("distill", str(teacher), "--out", str(parts), "--rounds", "2", *common) == 0
    from lcrl.checkpoint import load_checkpoint
    from train.evaluation.evaluate import resolve_checkpoint

    before = load_checkpoint(resolve_checkpoint(parts)).state("trainer")["train_s"]
    args = ["distill", str(teacher), "--out", str(parts), "--rounds", "3", "--resume", *common]
    assert cli(*args) == 0
    # the seconds of training count both sessions
    after = load_checkpoint(resolve_checkpoint(parts)).state("trainer")["train_s"]
    assert after > before > 0
    last = (parts / "eval.csv").read_text().strip().splitlines()[-1].split(",")[-1]
    assert float(last) >= before

    a, b = (load_checkpoint(resolve_checkpoint(p)).weights("actor") for p in (whole, parts))
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)


def test_a_resumed_student_evaluates_after_its_first_checkpoint_is_pruned(
    teacher, perception, tmp_path
):
    """A resumed perception student acts through the perception model its checkpoint
    carries; evaluations after that checkpoint is pruned (two are kept) still find it."""
    out = tmp_path / "student"
    args = ["distill", str(teacher), "--perception", str(perception), "--out", str(out)]
    args += ["--episodes-per-round", "1", "--updates-per-round", "2", "--batch-size", "8"]
    args += ["--eval-every", "3", "--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    assert cli(*args, "--rounds", "1") == 0
    assert cli(*args, "--rounds", "4", "--resume") == 0
    steps = [line.split(",")[0] for line in (out / "eval.csv").read_text().splitlines()[1:]]
    assert steps == ["1", "3", "4"]
    assert not (out / "checkpoints" / "step_000000001").exists()
    kept = json.loads((out / "config.json").read_text())["env"]["perception"]
    assert Path(kept) == out / "perception" and (out / "perception" / "meta.json").is_file()
    assert cli(*args, "--rounds", "1", "--overwrite") == 0  # a new run drops the copy
    assert not (out / "perception").exists()


def test_students_and_teachers_that_cannot_work_are_refused(teacher, perception, tmp_path, capsys):
    out = ["--out", str(tmp_path / "s")]
    assert cli("distill", str(teacher), *out) == 2
    assert "one of: --perception MODEL" in error_line(capsys.readouterr().err)
    assert cli("distill", str(tmp_path / "nothing"), "--perception", str(perception), *out) == 2
    assert "no checkpoint or run folder" in error_line(capsys.readouterr().err)
    # a student of another camera: a perception model for robosuite's slots
    other = tmp_path / "other"
    layout = SlotLayout(4, 8, 4, 3)
    save_model(other, Perception((64, 64, 3), layout), PerceptionTrainConfig(), {}, 0, [], [])
    assert cli("distill", str(teacher), "--perception", str(other), *out) == 2
    line = error_line(capsys.readouterr().err)
    assert "the perception model reads [4, 8, 4, 3]" in line and "[2, 8, 3, 2]" in line


def test_a_student_distilled_with_a_hold_radius_acts_with_it(teacher, perception, tmp_path, capsys):
    """``lcrl distill --hold-radius R`` collects, checkpoints and acts with objects held at
    ``R`` (in place of the perception model's own radius); it needs a perception student
    and a radius >= 0."""
    from lcrl.perception import load_model

    out = tmp_path / "held"
    args = ["distill", str(teacher), "--perception", str(perception), "--out", str(out)]
    args += ["--rounds", "1", "--episodes-per-round", "2", "--updates-per-round", "5"]
    args += ["--batch-size", "16", "--eval-every", "0", "--eval-episodes", "1"]
    assert cli(*args, "--hold-radius", "0.02", "--no-progress", "--no-tensorboard") == 0
    saved = json.loads((out / "config.json").read_text())["env"]
    assert saved["perception_hold_radius"] == 0.02
    assert load_model(perception)[0].cfg.hold_radius != 0.02

    import lcrl

    policy = lcrl.load(out)
    env = policy.make_env()
    assert env.get_wrapper_attr("held").radius == 0.02
    obs, _ = env.reset(seed=0)
    policy.act({"image": obs["image"], "proprio": obs["privileged"][:2]}, "reach the red cube")
    assert policy._held.radius == 0.02

    refused = ["distill", str(teacher), "--out", str(tmp_path / "refused")]
    assert cli(*refused, "--state", "--hold-radius", "0.02") == 2
    assert "give the student a --perception MODEL" in error_line(capsys.readouterr().err)
    assert cli(*refused, "--perception", str(perception), "--hold-radius", "-1") == 2
    assert "--hold-radius must be >= 0, got -1.0" in error_line(capsys.readouterr().err)
    assert not (tmp_path / "refused").exists()


def test_eval_sets_limit_the_periodic_evaluations_not_the_final_one(
    teacher, perception, tmp_path, capsys
):
    out = tmp_path / "student"
    args = ["distill", str(teacher), "--perception", str(perception)]
    args += ["--rounds", "2", "--episodes-per-round", "2", "--updates-per-round", "5"]
    args += ["--batch-size", "16", "--eval-every", "1", "--eval-episodes", "2"]
    args += ["--no-progress", "--no-tensorboard"]
    assert cli(*args, "--out", str(out), "--eval-sets", "train") == 0
    with open(out / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["step"] for r in rows] == ["1", "2"]
    assert rows[0]["train/success"] != "" and rows[0]["heldout/success"] == ""
    assert rows[1]["heldout/success"] != "" and rows[1]["paraphrase/success"] != ""
    # a set the task does not have is refused before the first round
    assert cli(*args, "--out", str(tmp_path / "bad"), "--eval-sets", "train", "unseen") == 2
    line = error_line(capsys.readouterr().err)
    assert "eval_sets ['unseen']" in line and "'heldout'" in line
    assert not (tmp_path / "bad" / "progress.csv").exists()


def test_a_student_started_from_the_teacher_acts_as_the_teacher(teacher, perception, tmp_path):
    """``--init-from-teacher``: before any update the student's action is the teacher's
    deterministic one on the same state, also for a student with more and wider hidden
    layers (the teacher's grown to them); a student from nothing acts otherwise."""
    from lcrl.checkpoint import load_checkpoint
    from train.configs.config import DistillConfig
    from train.configs.run_meta import run_meta
    from train.evaluation.evaluate import resolve_checkpoint
    from train.training.distill import DistillTrainer, student_config

    teacher_cfg = run_meta(load_checkpoint(resolve_checkpoint(teacher))).config
    had = tuple(teacher_cfg.agent.net.hidden)
    grown = (2 * had[0], *[h + 8 for h in had[1:]], had[-1] + 8)
    actions, widths = {}, {}
    cases = [("warm", True, had, 0.0), ("grown", True, grown, 0.0), ("cold", False, had, 0.0)]
    cases.append(("averaged", True, grown, 0.99))  # the average acts, and starts as the teacher
    for name, init, hidden, ema in cases:
        distill = DistillConfig(teacher=str(teacher), init_from_teacher=init)
        cfg = student_config(
            teacher_cfg, state=True, out=str(tmp_path / name), distill=distill, total_steps=1
        )
        cfg.agent.net.hidden = hidden
        cfg.bc = dataclasses.replace(cfg.bc, ema=ema)
        trainer = DistillTrainer(cfg)
        try:
            widths[name] = [
                m.out_features
                for m in trainer.agent.actor.head.net
                if isinstance(m, torch.nn.Linear)
            ][:-1]
            obs, _ = trainer.env.reset(seed=3)
            goal = np.asarray([trainer.task.goal(obs, trainer.env)])
            mine = {k: v[None] for k, v in trainer.task.storage_obs(obs, obs).items()}
            actions[name] = trainer.agent.act(mine, goal, deterministic=True)[0]
            theirs = trainer.teacher.agent.act(mine, goal, deterministic=True)[0]
        finally:
            trainer.close()
    assert widths["grown"] == list(grown) and widths["warm"] == list(had)
    np.testing.assert_allclose(actions["warm"], theirs, atol=1e-5)
    np.testing.assert_allclose(actions["grown"], theirs, atol=1e-5)
    np.testing.assert_allclose(actions["averaged"], theirs, atol=1e-5)
    assert np.abs(actions["cold"] - theirs).max() > 1e-2


def test_an_averaged_student_is_checkpointed_and_acts_through_load(teacher, perception, tmp_path):
    """``--ema``: the student's weight average is saved beside the trained weights, and the
    policy ``lcrl.load`` gives acts with the average; ``--ema 1`` is refused in one line."""
    import lcrl
    from lcrl.checkpoint import load_checkpoint
    from train.evaluation.evaluate import resolve_checkpoint

    out = tmp_path / "averaged"
    args = ["distill", str(teacher), "--perception", str(perception), "--ema", "0.9"]
    args += ["--weight-decay", "0.01"]
    args += ["--rounds", "1", "--episodes-per-round", "2", "--updates-per-round", "20"]
    args += ["--batch-size", "32", "--eval-every", "0", "--eval-episodes", "1"]
    args += ["--no-progress", "--no-tensorboard"]
    assert cli(*args, "--out", str(out)) == 0
    ckpt = load_checkpoint(resolve_checkpoint(out))
    averaged, trained = ckpt.weights("actor_ema"), ckpt.weights("actor")
    assert averaged.keys() == trained.keys()
    assert any(not torch.equal(averaged[k], trained[k]) for k in averaged)
    policy = lcrl.load(out)
    agent = policy.agent
    for k, w in agent.actor_ema.state_dict().items():
        torch.testing.assert_close(w, averaged[k])
    assert agent.cfg.ema == 0.9 and agent.cfg.weight_decay == 0.01
    bad = ["distill", str(teacher), "--perception", str(perception), "--ema", "1.0"]
    assert cli(*bad, "--out", str(tmp_path / "bad"), "--no-progress") == 2
    bad = ["distill", str(teacher), "--perception", str(perception), "--weight-decay", "-1"]
    assert cli(*bad, "--out", str(tmp_path / "bad"), "--no-progress") == 2


def test_grown_layers_compute_the_same_function_and_learn_apart():
    """Net2Net growth: deeper and wider ReLU layers give the same outputs, copied units
    get different outgoing weights, and a narrower or shallower target is refused."""
    from lcrl.errors import LcrlError
    from train.training.distill import grown_layers

    gen = torch.Generator().manual_seed(0)
    layers = [
        (torch.randn(8, 5, generator=gen), torch.randn(8, generator=gen)),
        (torch.randn(8, 8, generator=gen), torch.randn(8, generator=gen)),
        (torch.randn(3, 8, generator=gen), torch.randn(3, generator=gen)),
    ]

    def forward(stack, x):
        for i, (w, b) in enumerate(stack):
            x = x @ w.T + b
            x = torch.relu(x) if i < len(stack) - 1 else x
        return x

    x = torch.randn(64, 5, generator=gen)
    grown = grown_layers(layers, (16, 12, 20))
    assert [tuple(w.shape) for w, _ in grown] == [(16, 5), (12, 16), (20, 12), (3, 20)]
    torch.testing.assert_close(forward(grown, x), forward(layers, x), atol=1e-4, rtol=1e-4)
    w_in, w_out = grown[0][0], grown[1][0]
    for j in range(8, 16):  # each new unit copies one of the first 8 ...
        (source,) = [i for i in range(8) if torch.equal(w_in[j], w_in[i])]
        # ... and takes another share of its outgoing weights
        assert not torch.allclose(w_out[:, j], w_out[:, source])
    for bad in ((4, 8), (8,), (8, 8, 4)):
        with pytest.raises(LcrlError, match="cannot grow"):
            grown_layers(layers, bad)


def test_init_from_teacher_over_perception_and_its_refusals(teacher, perception, tmp_path, capsys):
    """A student through perception starts from the teacher and fine-tunes (the checkpoint
    says so); from the teacher's own state its first loss is far below a fresh student's;
    another network size is refused in one line."""
    common = ["--rounds", "1", "--episodes-per-round", "3", "--updates-per-round", "5"]
    common += ["--batch-size", "32", "--eval-every", "0", "--eval-episodes", "1"]
    common += ["--no-progress", "--no-tensorboard"]
    out = tmp_path / "perceived"
    args = ["distill", str(teacher), "--perception", str(perception), "--init-from-teacher"]
    assert cli(*args, "--out", str(out), *common) == 0
    from lcrl.checkpoint import load_checkpoint
    from train.evaluation.evaluate import resolve_checkpoint

    assert load_checkpoint(resolve_checkpoint(out)).meta["distill"]["init_from_teacher"] is True
    first = {}
    for name, extra in (("warm", ["--init-from-teacher"]), ("cold", [])):
        run = tmp_path / name
        assert cli("distill", str(teacher), "--state", *extra, "--out", str(run), *common) == 0
        first[name] = _rows(run / "progress.csv")[0]["loss_first"]
    assert first["warm"] < 0.1 * first["cold"]
    bad = [*args, "--hidden", "32", "--out", str(tmp_path / "bad"), *common]
    assert cli(*bad) == 2
    line = error_line(capsys.readouterr().err)
    assert "--init-from-teacher" in line and "the teacher's" in line and "(32," in line


def test_the_student_does_not_inherit_how_the_teacher_explored(tmp_path):
    """A teacher trained with chains, hand-overs and demonstrations (robosuite-push from
    demos) gives a student config without them: DAgger collects its own episodes, and
    chains are not available through perception."""
    import dataclasses

    from train.configs.config import ExploreConfig, FinetuneConfig
    from train.training.distill import student_config

    base = tiny("lang2d-quick", tmp_path / "teacher")
    teacher_cfg = dataclasses.replace(
        base,
        explore=ExploreConfig(chain=0.5, handover=0.3),
        finetune=FinetuneConfig(demos=str(tmp_path / "demos.h5")),
    )
    cfg = student_config(teacher_cfg, perception=str(tmp_path / "p"), out=str(tmp_path / "s"))
    assert cfg.explore == ExploreConfig() and cfg.finetune == FinetuneConfig()
    assert cfg.env.perception == str(tmp_path / "p") and cfg.algo == "bc"
    assert cfg.env.families == teacher_cfg.env.families
    cfg.validate()  # chains with perception would be refused


@pytest.fixture(scope="module")
def two_families(tmp_path_factory) -> Path:
    """A privileged-state lang2d policy over reach and push (a few hundred steps)."""
    from train.training.loop import Trainer

    out = tmp_path_factory.mktemp("distill") / "two"
    Trainer(tiny("lang2d", out, total_steps=300, learning_starts=100)).run()
    return out


def test_family_teachers_merge_into_one_state_student_over_chains(two_families, teacher, tmp_path):
    """``--state --teacher-for``: every family is labelled by its own teacher (here the
    scripted controller, which succeeds where a 300-step policy cannot), achieved
    instructions go on in the same scene, and the student is one policy over both."""
    out = tmp_path / "merged"
    args = ["distill", str(two_families), "--state", "--out", str(out), "--chain", "1"]
    args += ["--teacher-for", "reach=scripted", "push=scripted", "--rounds", "2"]
    args += ["--episodes-per-round", "6", "--updates-per-round", "100", "--batch-size", "64"]
    args += ["--eval-every", "0", "--eval-episodes", "2", "--no-progress", "--no-tensorboard"]
    assert cli(*args) == 0
    rows = _rows(out / "progress.csv")
    first = rows[0]  # the teachers act alone in the first round
    assert first["teacher_share"] == 1.0 and first["success"] >= 5 / 6
    assert first["chained"] >= 5 and first["chained_success"] >= 0.8
    assert rows[1]["rows"] > first["rows"] and rows[1]["loss"] < first["loss_first"]

    import lcrl

    policy = lcrl.load(out)
    meta = policy.checkpoint.meta["distill"]
    assert meta["teachers"] == {"reach": {"path": "scripted"}, "push": {"path": "scripted"}}
    assert not policy.perceives
    obs, _ = policy.make_env().reset(seed=0)
    assert policy.act(obs, "push the red cube left").shape == (2,)

    # the chain's teacher labels every instruction after the first: the 300-step policy
    # labels first push instructions (and fails them), the scripted controller the rest
    out = tmp_path / "chained"
    args = ["distill", str(two_families), "--state", "--out", str(out), "--chain", "1"]
    args += ["--teacher-for", "reach=scripted", "--chain-teacher", "scripted", "--rounds", "1"]
    args += ["--episodes-per-round", "8", "--updates-per-round", "5", "--batch-size", "16"]
    args += ["--eval-every", "0", "--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    assert cli(*args) == 0
    row = _rows(out / "progress.csv")[0]
    assert row["success"] < 1.0 and row["chained"] >= 1 and row["chained_success"] == 1.0
    assert lcrl.load(out).checkpoint.meta["distill"]["chain_teacher"] == {"path": "scripted"}
    # resumed without naming them, the run keeps the teachers it started with
    resume = ["distill", str(two_families), "--state", "--out", str(out), "--resume"]
    assert cli(*resume, "--rounds", "2", "--no-progress", "--no-tensorboard") == 0
    meta = lcrl.load(out).checkpoint.meta["distill"]
    assert meta["chain_teacher"] == {"path": "scripted"}
    assert meta["teachers"] == {"reach": {"path": "scripted"}}
    # roll-in: the teacher acts the first instruction whole, the student (beta 0) the rest
    rolled = tmp_path / "rolled"
    args[args.index(str(out))] = str(rolled)
    assert cli(*args, "--roll-in", "1", "--beta", "0") == 0
    row = _rows(rolled / "progress.csv")[0]
    assert row["chained"] >= 1 and 0.0 < row["teacher_share"] < 1.0

    # a family's teacher run: the instruction's id is looked up in that teacher's table
    from lcrl.checkpoint import load_checkpoint
    from train.configs.config import DistillConfig
    from train.configs.run_meta import run_meta
    from train.evaluation.evaluate import resolve_checkpoint
    from train.training.distill import DistillTrainer, student_config

    base = run_meta(load_checkpoint(resolve_checkpoint(two_families))).config
    cfg = student_config(
        base,
        state=True,
        out=str(tmp_path / "reach-teacher"),
        distill=DistillConfig(teacher=str(two_families), teachers=(f"reach={teacher}",)),
        progress=False,
        tensorboard=False,
    )
    trainer = DistillTrainer(cfg)
    try:
        reach_teacher = trainer.family_teachers["reach"]
        text = next(t for t in trainer.task.table[: trainer.task.num_train] if "reach" in t)
        goal = trainer.task.ids[text]
        trainer.env.reset(seed=0, options={"instruction": text})
        chosen, ids = trainer._teacher(goal)
        assert chosen is reach_teacher and ids.tolist() == [reach_teacher.task.ids[text]]
        push = next(t for t in trainer.task.table[: trainer.task.num_train] if "push" in t)
        trainer.env.reset(seed=0, options={"instruction": push})
        chosen, ids = trainer._teacher(trainer.task.ids[push])
        assert chosen is trainer.teacher and ids.tolist() == [trainer.task.ids[push]]
    finally:
        trainer.close()


def test_a_student_without_initial_reads_the_current_observation_only(two_families, tmp_path):
    """``--no-initial``: the student's rows and network hold the current observation only
    (the teachers still read theirs with ``initial``); the saved config says so, and the
    policy acts, over chains too, through ``lcrl.load`` and ``lcrl eval``."""
    import lcrl
    from lcrl.checkpoint import load_checkpoint
    from train.evaluation.evaluate import resolve_checkpoint

    out = tmp_path / "current"
    args = ["distill", str(two_families), "--state", "--out", str(out), "--chain", "1"]
    args += ["--teacher-for", "reach=scripted", "push=scripted", "--rounds", "1"]
    args += ["--episodes-per-round", "4", "--updates-per-round", "20", "--batch-size", "32"]
    args += ["--eval-every", "0", "--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    assert cli(*args, "--no-initial") == 0
    ckpt = load_checkpoint(resolve_checkpoint(out))
    assert ckpt.meta["config"]["env"]["initial"] is False
    assert {k for k in ckpt.arrays() if k.startswith("data_")} == {
        "data_observation",
        "data_action",
        "data_goal",
    }
    policy = lcrl.load(out)
    assert set(policy.task.obs_shapes) == {"observation"}
    teacher = lcrl.load(two_families)
    assert set(teacher.task.obs_shapes) == {"observation", "initial"}
    obs, _ = policy.make_env().reset(seed=0)
    assert policy.act(obs, "push the red cube left").shape == (2,)
    report = tmp_path / "chain.json"
    eval_args = ["eval", str(out), "--episodes", "3", "--chain", "2", "--sets", "train"]
    assert cli(*eval_args, "--no-progress", "--json", str(report)) == 0
    chain = json.loads(report.read_text())["sets"]["train"]["chain"]
    assert chain["length"] == 2 and chain["chains"] == 3


def test_family_teachers_that_cannot_teach_are_refused(two_families, teacher, tmp_path, capsys):
    out = ["--out", str(tmp_path / "s"), "--no-progress", "--no-tensorboard"]
    base = ["distill", str(two_families), "--state", *out]
    assert cli(*base, "--teacher-for", "reach") == 2
    assert "FAMILY=RUN (put=runs/put), got 'reach'" in error_line(capsys.readouterr().err)
    assert cli(*base, "--teacher-for", "lift=scripted") == 2
    assert "the student's env has the families reach, push" in error_line(capsys.readouterr().err)
    assert cli(*base, "--teacher-for", "reach=scripted", "reach=scripted") == 2
    assert "two teachers for the family 'reach'" in error_line(capsys.readouterr().err)
    # the reach-only policy never saw a push instruction
    assert cli(*base, "--teacher-for", f"push={teacher}") == 2
    line = error_line(capsys.readouterr().err)
    assert "was not trained on" in line and "push instructions" in line
    assert cli(*base, "--perception", str(tmp_path / "p")) == 2
    assert "one of: --perception MODEL" in error_line(capsys.readouterr().err)
    assert cli(*base, "--chain", "1.5") == 2
    assert "distill.chain must be in [0, 1]" in error_line(capsys.readouterr().err)
    assert cli(*base, "--roll-in", "-0.5") == 2
    assert "distill.roll_in must be in [0, 1]" in error_line(capsys.readouterr().err)
    assert cli(*base, "--scripted-funnel", "0.5") == 2
    assert "distill.scripted_funnel must be in [0, 0.2]" in error_line(capsys.readouterr().err)
    # a funnel for the 2D tabletop's scripted teacher, which has none
    assert cli(*base, "--teacher-for", "push=scripted", "--scripted-funnel", "0.05") == 2
    assert "setting of the robosuite scripted teacher only" in error_line(capsys.readouterr().err)


def test_the_teacher_acting_on_perceptions_estimate(teacher, perception):
    """benchmarks/distill.py's check of how much of a teacher's skill survives perception's
    errors: the same episodes acted on the true state and on the estimate; an untrained
    perception model reads the state wrongly, so the teacher's actions on the two differ."""
    from benchmarks.distill import teacher_on_estimates

    out = teacher_on_estimates(teacher, str(perception), 2)
    assert out["episodes"] == 2 and out["action_gap"] > 0.01
    assert out["hold_radius"] == 0.06  # the model's own
    held = teacher_on_estimates(teacher, str(perception), 1, hold_radius=0.02)
    assert held["hold_radius"] == 0.02 and held["episodes"] == 1
    for way in ("true_state", "estimate"):
        low, high = out[way]["ci"]
        assert out[way]["success"] in (0.0, 0.5, 1.0) and low <= out[way]["success"] <= high
    # perception's error by the object's distance from the agent, every object-step once
    bands = out["error_by_gripper_distance"]
    assert [(b["from_cm"], b["to_cm"]) for b in bands] == [(0, 6), (6, 10), (10, 20), (20, 1000)]
    counted = [b for b in bands if b["object_steps"]]
    assert sum(b["object_steps"] for b in bands) >= 2 * 2  # two episodes, 2+ objects each
    assert all(b["p90_cm"] >= b["mean_cm"] * 0.5 > 0 for b in counted)
    assert all(b["mean_cm"] is None for b in bands if not b["object_steps"])


def test_a_distillation_into_a_folder_another_process_holds_is_refused(
    teacher, perception, tmp_path, capsys
):
    out = tmp_path / "student"
    proc = hold(out)
    try:
        args = ["distill", str(teacher), "--perception", str(perception), "--out", str(out)]
        assert cli(*args, "--rounds", "1", "--no-progress", "--no-tensorboard") == 2
        assert f"in use by process {proc.pid}" in error_line(capsys.readouterr().err)
        assert not (out / "progress.csv").exists()
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)


def test_a_student_of_more_families_than_its_base_teacher_has_their_table(teacher, tmp_path):
    """The base teacher follows reach only; a student of reach and push (``--families``)
    gets the instruction table of its own families, the base labelling reach through its
    own ids and the scripted controller push."""
    out = tmp_path / "wider"
    args = ["distill", str(teacher), "--state", "--out", str(out), "--families", "reach", "push"]
    args += ["--teacher-for", "push=scripted", "--rounds", "1", "--episodes-per-round", "6"]
    args += ["--updates-per-round", "5", "--batch-size", "16", "--eval-every", "0"]
    args += ["--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    assert cli(*args) == 0
    import lcrl

    table = lcrl.load(out).task.table
    assert any(t.startswith("push ") for t in table) and any(t.startswith("reach ") for t in table)
    assert _rows(out / "progress.csv")[0]["rows"] > 0


def test_colour_renaming_switched_on_at_a_resume_is_recorded_from_its_round(
    teacher, perception, tmp_path, capsys
):
    out = tmp_path / "student"
    args = ["distill", str(teacher), "--perception", str(perception), "--out", str(out)]
    args += ["--episodes-per-round", "1", "--updates-per-round", "3", "--batch-size", "8"]
    args += ["--eval-every", "0", "--eval-episodes", "1", "--no-progress", "--no-tensorboard"]
    assert cli(*args, "--rounds", "1") == 0
    assert cli(*args, "--rounds", "2", "--resume", "--augment", "colours") == 0
    said = capsys.readouterr().out
    assert "every update's rows augmented from round 2 on: colours renamed" in said
    from lcrl.checkpoint import load_checkpoint
    from train.evaluation.evaluate import resolve_checkpoint

    ckpt = load_checkpoint(resolve_checkpoint(out))
    assert ckpt.meta["distill"]["augment"] == {"kind": "colours", "from_round": 1}
    # a later resumption keeps it on, from the same round
    assert cli(*args, "--rounds", "3", "--resume") == 0
    ckpt = load_checkpoint(resolve_checkpoint(out))
    assert ckpt.meta["distill"]["augment"] == {"kind": "colours", "from_round": 1}
    assert ckpt.state("trainer")["augment_from"] == 1
    assert cli(*args, "--rounds", "1", "--overwrite", "--augment", "shapes") == 2
    assert "distill.augment 'shapes': name each of" in error_line(capsys.readouterr().err)

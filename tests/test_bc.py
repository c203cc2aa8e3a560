"""Behavioural cloning: fitting and goal conditioning of :class:`lcrl.bc.BC`, the trainer
on recorded demonstrations (outputs, checkpoints, exact resume, the hindsight switch), the
command line, and the errors users meet (no demonstrations, mismatched shapes or action
spaces, instructions that would leak the evaluation).

The trainer runs are tiny (200-300 updates, 32-unit networks, one torch thread, a few
evaluation episodes) on 24 scripted lang2d demonstrations.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import safetensors.torch
import torch
from helpers import TINY_CLI, cli, error_line, interrupt_update

from lcrl.algos import AgentOptions, Problem
from lcrl.bc import BC, BCConfig
from lcrl.buffer import Batch
from lcrl.checkpoint import find_latest, load_checkpoint
from lcrl.demos import DemoDataset, DemoWriter
from lcrl.errors import LcrlError
from lcrl.nets import NetConfig
from train.configs.config import TrainConfig
from train.configs.presets import PRESETS
from train.evaluation.evaluate import evaluate, run_episode
from train.policies.loading import load_policy
from train.training.bc import BCTrainer
from train.training.demos import RecordConfig, record, relabel

SETS = ("train", "heldout", "paraphrase")
OBS_DIM = 58  # the lang2d preset's observation: pusher x, y + 8 slots of 7 values


class Rows(NamedTuple):
    """A hand-made batch: what :meth:`BC.update` reads."""

    obs: dict[str, np.ndarray]
    action: np.ndarray
    goal: np.ndarray


# --- fixtures ----------------------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def encoder(one_thread):
    """The frozen text encoder, warm (trainers build their own, faster once warm)."""
    from lcrl.text_encoder import FrozenTextEncoder

    return FrozenTextEncoder()


@pytest.fixture(scope="module")
def demos(encoder, tmp_path_factory) -> Path:
    """24 scripted lang2d episodes (reach and push) recorded like ``lcrl demos record``,
    relabelled in hindsight with the rule captioner."""
    folder = tmp_path_factory.mktemp("demos")
    given = record(
        RecordConfig(
            out=str(folder / "given.h5"), preset="lang2d", episodes=24, noise=0.1, progress=False
        )
    )
    relabel(given, folder / "demos.h5", progress=False)
    return folder / "demos.h5"


def tiny_bc(out: Path, demos: Path, **overrides) -> TrainConfig:
    """The lang2d-bc preset shrunk to 300 updates, 32-unit networks, 3 evaluation episodes."""
    base = PRESETS["lang2d-bc"][1]
    cfg = dataclasses.replace(
        base,
        out=str(out),
        demos=str(demos),
        total_steps=300,
        batch_size=32,
        eval_every=0,
        eval_episodes=3,
        checkpoint_every=0,
        log_every=100,
        progress=False,
        tensorboard=False,
        agent=dataclasses.replace(base.agent, net=NetConfig(hidden=(32, 32), text_dim=8)),
        bc=dataclasses.replace(base.bc),
        env=dataclasses.replace(base.env),
    )
    return dataclasses.replace(cfg, **overrides)


@pytest.fixture(scope="module")
def bc_run(demos, tmp_path_factory):
    """A finished 200-update run with an evaluation at update 100: (trainer, results)."""
    out = tmp_path_factory.mktemp("bc") / "run"
    trainer = BCTrainer(tiny_bc(out, demos, total_steps=200, eval_every=100, log_every=50))
    return trainer, trainer.run()


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def write_demos(path: Path, obs_dim: int, actions: np.ndarray, texts: list[str], meta=None) -> Path:
    """A dataset of one random episode per instruction (shapes are what matters)."""
    rng = np.random.default_rng(0)
    with DemoWriter(path, meta or {}) as w:
        for text in texts:
            obs = rng.normal(size=(len(actions) + 1, obs_dim)).astype(np.float32)
            w.add_episode({"observation": obs}, actions, instruction=text, success=True)
    return path


def preset_split():
    """The instruction split of the lang2d-bc preset's env (and its families)."""
    from train.environments.tasks import find_language_wrapper, make_env

    cfg = PRESETS["lang2d-bc"][1].env
    env = make_env(cfg)
    split = find_language_wrapper(env).split
    env.close()
    return split, cfg.families


def train_texts(n: int = 2) -> list[str]:
    """The first training instructions of the lang2d-bc preset's table."""
    split, families = preset_split()
    return [
        t
        for t, m in zip(split.train, split.instructions("train"), strict=True)
        if m.family in families
    ][:n]


def fake_embed(table: np.ndarray):
    def embed(ids: np.ndarray, device: torch.device) -> torch.Tensor:
        return torch.as_tensor(table[np.asarray(ids, np.int64)], device=device)

    return embed


def fit(agent: BC, rows: Rows, updates: int) -> list[float]:
    agent.observe(rows.obs)
    return [agent.update(rows)["loss"] for _ in range(updates)]


# --- 1. the learner ----------------------------------------------------------------------
@pytest.mark.parametrize("loss", ["mse", "gaussian"])
def test_bc_fits_a_fixed_dataset(loss):
    rng = np.random.default_rng(0)
    goals = rng.normal(size=(3, 16)).astype(np.float32)
    weights = rng.normal(size=(3, 6, 2)).astype(np.float32)
    obs = rng.normal(size=(48, 6)).astype(np.float32)
    goal = np.arange(48) % 3
    action = (0.9 * np.tanh(np.einsum("bi,bij->bj", obs, weights[goal]))).astype(np.float32)
    problem = Problem({"observation": (6,)}, "vector", (16,), 2)
    options = AgentOptions(net=NetConfig(hidden=(64, 64)), normalize_goal=False)
    agent = BC(problem, options, fake_embed(goals), BCConfig(loss=loss, lr=3e-3))
    rows = Rows({"observation": obs}, action, goal)
    losses = fit(agent, rows, 1000)
    assert agent.updates == 1000
    if loss == "mse":
        assert np.mean(losses[-10:]) < 0.02 * np.mean(losses[:10])
    else:  # a log-likelihood: it falls by a margin, not by a factor
        assert np.mean(losses[-10:]) < np.mean(losses[:10]) - 3.0
    acted = agent.act({"observation": obs}, goal, deterministic=True)
    assert acted.shape == action.shape and np.abs(acted).max() <= 1.0
    assert np.abs(acted - action).max() < 0.1
    if loss == "gaussian":  # samples spread around the mean, inside the action bounds
        sampled = agent.act({"observation": obs}, goal)
        assert np.abs(sampled).max() <= 1.0 and not np.allclose(sampled, acted)


def test_bc_averaged_policy_moves_by_one_minus_ema_and_acts():
    """``BCConfig.ema``: after each update the averaged weights move ``1 - ema`` of the way
    to the trained ones, the average is what acts and what ``modules()`` checkpoints; a
    bad value is refused."""
    rng = np.random.default_rng(2)
    goals = rng.normal(size=(2, 8)).astype(np.float32)
    obs = rng.normal(size=(32, 4)).astype(np.float32)
    goal = np.arange(32) % 2
    action = np.tanh(obs[:, :2]).astype(np.float32)
    problem = Problem({"observation": (4,)}, "vector", (8,), 2)
    options = AgentOptions(net=NetConfig(hidden=(32, 32)), normalize_goal=False)
    agent = BC(problem, options, fake_embed(goals), BCConfig(lr=1e-2, ema=0.9))
    plain = BC(problem, options, fake_embed(goals), BCConfig(lr=1e-2))
    assert "actor_ema" in agent.modules() and "actor_ema" not in plain.modules()
    rows = Rows({"observation": obs}, action, goal)
    agent.observe(rows.obs)
    start = [p.detach().clone() for p in agent.actor_ema.parameters()]
    for before, w in zip(start, agent.actor.parameters(), strict=True):
        torch.testing.assert_close(before, w.detach())  # the average starts as the policy
    agent.update(rows)
    for before, avg, w in zip(
        start, agent.actor_ema.parameters(), agent.actor.parameters(), strict=True
    ):
        torch.testing.assert_close(avg, 0.9 * before + 0.1 * w.detach())
    for _ in range(50):
        agent.update(rows)
    acted = agent.act({"observation": obs}, goal, deterministic=True)
    with torch.no_grad():
        o, g = agent.obs_tensors({"observation": obs}), agent.goal_tensor(goal)
        averaged = torch.tanh(agent.actor_ema(o, g)).numpy()
        trained = torch.tanh(agent.actor(o, g)).numpy()
    np.testing.assert_allclose(acted, averaged, atol=1e-6)
    assert np.abs(acted - trained).max() > 1e-4
    for bad in (1.0, -0.1):
        with pytest.raises(LcrlError, match=r"bc\.ema"):
            BCConfig(ema=bad).validate()


def test_bc_discrete_actions_use_cross_entropy():
    rng = np.random.default_rng(1)
    goals = np.eye(2, dtype=np.float32)
    obs = rng.normal(size=(40, 4)).astype(np.float32)
    goal = np.arange(40) % 2
    # goal 0: the sign pattern of two inputs picks one of 4 moves; goal 1 shifts it by 2
    action = ((obs[:, 0] > 0) * 1 + (obs[:, 1] > 0) * 2 + 2 * goal) % 4
    problem = Problem({"observation": (4,)}, "vector", (2,), 4, discrete=True)
    options = AgentOptions(net=NetConfig(hidden=(64, 64)), normalize_goal=False)
    agent = BC(problem, options, fake_embed(goals), BCConfig(lr=3e-3))
    rows = Rows({"observation": obs}, action.astype(np.int64), goal)
    losses = fit(agent, rows, 400)
    assert losses[-1] < 0.1 * losses[0]
    acted = agent.act({"observation": obs}, goal, deterministic=True)
    assert acted.dtype == np.int64 and acted.shape == (40,)
    np.testing.assert_array_equal(acted, action)
    assert agent.update(rows)["accuracy"] == 1.0


def test_bc_tells_apart_two_instructions_with_opposite_actions(encoder):
    texts = ["push the red cube left", "push the red cube right"]
    table = encoder.encode(texts)
    assert float(table[0] @ table[1]) > 0.95  # nearly parallel: the norm must separate them
    rng = np.random.default_rng(2)
    obs = np.repeat(rng.normal(size=(16, 8)).astype(np.float32), 2, axis=0)
    goal = np.tile([0, 1], 16)
    targets = np.asarray([[0.8, -0.3], [-0.8, 0.3]], np.float32)
    problem = Problem({"observation": (8,)}, "text", (table.shape[1],), 2)
    agent = BC(problem, AgentOptions(net=NetConfig(hidden=(64, 64))), fake_embed(table))
    agent.observe({}, table)  # text-goal norm from the training instructions' embeddings
    fit(agent, Rows({"observation": obs}, targets[goal], goal), 300)
    same = obs[:1].repeat(2, 0)  # one observation, both instructions
    acted = agent.act({"observation": same}, np.asarray([0, 1]), deterministic=True)
    np.testing.assert_allclose(acted, targets, atol=0.1)
    # with an already embedded goal, the same actions
    embedded = agent.act({"observation": same}, table, deterministic=True, embedded=True)
    np.testing.assert_allclose(embedded, acted, atol=1e-6)


def test_bc_learns_from_camera_images_with_augmentation():
    rng = np.random.default_rng(4)
    images = rng.integers(0, 255, size=(16, 16, 16, 3), dtype=np.uint8)
    proprio = rng.normal(size=(16, 3)).astype(np.float32)
    goal = np.arange(16) % 2
    action = np.where(images[:, :, :, 0].mean((1, 2))[:, None] > 127, 0.5, -0.5) * [1, -1]
    action = action.astype(np.float32) * (1 - 2 * goal[:, None])
    problem = Problem({"image": (16, 16, 3), "proprio": (3,)}, "vector", (2,), 2)
    net = NetConfig(hidden=(64,), cnn_channels=(8, 8), cnn_features=16)
    options = AgentOptions(net=net, augment_pad=1, normalize_goal=False)
    agent = BC(problem, options, fake_embed(np.eye(2, dtype=np.float32)), BCConfig(lr=3e-3))
    rows = Rows({"image": images, "proprio": proprio}, action, goal)
    losses = fit(agent, rows, 150)
    assert np.mean(losses[-5:]) < 0.3 * np.mean(losses[:5])
    acted = agent.act({"image": images, "proprio": proprio}, goal, deterministic=True)
    assert acted.shape == (16, 2) and np.abs(acted).max() <= 1.0
    assert agent.modules().keys() == {"norms", "actor"}
    assert any(p.dim() == 4 for p in agent.actor.parameters()), "a CNN reads the image"


def test_bc_updates_on_replay_buffer_batches():
    rng = np.random.default_rng(3)
    obs = {"observation": rng.normal(size=(8, 5)).astype(np.float32)}
    batch = Batch(
        obs=obs,
        action=rng.uniform(-1, 1, size=(8, 2)).astype(np.float32),
        reward=np.zeros(8, np.float32),
        next_obs=obs,
        terminated=np.zeros(8, np.float32),
        goal=rng.normal(size=(8, 3)).astype(np.float32),
        relabelled=np.zeros(8, bool),
        index=np.arange(8),
        discount=None,
    )
    problem = Problem({"observation": (5,)}, "vector", (3,), 2)
    agent = BC(problem, AgentOptions(net=NetConfig(hidden=(16,))), lambda g, d: torch.as_tensor(g))
    first = agent.update(batch)
    assert {"loss", "action_mse", "grad_norm"} <= set(first)
    for _ in range(50):
        last = agent.update(batch)
    assert last["loss"] < first["loss"]


def test_bc_config_errors():
    problem = Problem({"observation": (3,)}, "vector", (2,), 2)
    for bad, match in (
        (BCConfig(loss="huber"), "unknown bc.loss"),
        (BCConfig(lr=0.0), "bc.lr"),
        (BCConfig(weight_decay=-1.0), "weight_decay"),
        (BCConfig(cache_steps=0), "cache_steps"),
    ):
        with pytest.raises(LcrlError, match=match):
            BC(problem, AgentOptions(), lambda g, d: torch.as_tensor(g), bad)


# --- 2. the trainer ----------------------------------------------------------------------
def test_bc_run_writes_logs_checkpoint_and_report(bc_run, demos):
    trainer, results = bc_run
    out = trainer.out
    assert trainer.step == 200 and trainer.agent.updates == 200
    config = json.loads((out / "config.json").read_text())
    assert config["resolved_algo"] == "bc" and config["demos"] == str(demos)

    fields, rows = read_csv(out / "progress.csv")
    assert {"step", "updates", "epochs", "loss", "action_mse", "steps_per_s"} <= set(fields)
    assert [int(r["step"]) for r in rows] == [50, 100, 150, 200]
    losses = [float(r["loss"]) for r in rows]
    assert losses[-1] < losses[0]

    fields, rows = read_csv(out / "eval.csv")
    assert [int(r["step"]) for r in rows] == [100, 200]
    for name in SETS:
        assert f"{name}/success" in fields and f"{name}/reach" in fields
    assert set(results) == set(SETS)

    ckpt = load_checkpoint(find_latest(out))
    assert ckpt.path.name == "step_000000200"
    assert ckpt.meta["algo"] == "bc" and ckpt.meta["step"] == 200
    assert ckpt.meta["demos"]["hindsight"] is True and ckpt.meta["demos"]["episodes"] == 24
    table = ckpt.json("instructions")
    assert table["texts"] == trainer.task.table and table["num_train"] == trainer.task.num_train
    assert (out / "report.md").is_file() and "| train |" in (out / "report.md").read_text()


def test_dataset_instructions_map_to_the_table_by_text(bc_run):
    trainer, _ = bc_run
    data, task = trainer.data, trainer.task
    used = np.unique(trainer.segments[:, 3])
    assert (trainer.goal_map[used] >= 0).all()
    for i in used:
        tid = trainer.goal_map[i]
        assert task.table[tid] == data.instructions[i] and tid < task.num_train
    with DemoDataset(trainer.cfg.demos) as fresh:  # batches carry table ids
        trainer.data = fresh
        trainer._stream = None
        batch = trainer._batch()
        assert set(batch.goal.tolist()) <= set(trainer.goal_map[used].tolist())
        assert batch.obs.keys() == {"observation", "initial"}
        trainer._stream.close()


def test_checkpoint_round_trip_gives_identical_actions(bc_run):
    trainer, _ = bc_run
    loaded = load_policy(trainer.out)
    assert isinstance(loaded.agent, BC) and loaded.task.table == trainer.task.table
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(5, OBS_DIM)).astype(np.float32)
    batch_obs = {"observation": obs, "initial": obs[::-1].copy()}
    goals = np.arange(5) % trainer.task.num_train
    a = trainer.agent.act(batch_obs, goals, deterministic=True)
    b = loaded.agent.act(batch_obs, goals, deterministic=True)
    np.testing.assert_array_equal(a, b)
    episodes = [run_episode(p.agent, p.task, p.env, seed=3) for p in (loaded, loaded)]
    assert episodes[0] == episodes[1]

    import lcrl

    policy = lcrl.load(trainer.out)
    env = policy.make_env()
    o, _ = env.reset(seed=1)
    text = trainer.task.table[0]
    policy.reset()
    first = {k: np.asarray(v)[None] for k, v in loaded.task.storage_obs(o, o).items()}
    expected = loaded.agent.act(first, np.asarray([0]), deterministic=True)[0]
    expected = loaded.task.scale_action(expected)
    np.testing.assert_allclose(policy.act(o, text), expected, atol=1e-6)
    env.close()


def test_hindsight_switch_chooses_the_segments(demos, tmp_path):
    with DemoDataset(demos) as data:
        all_segments = data.segments()
    assert (all_segments[:, 4] == 1).any(), "the relabelled demos hold hindsight segments"
    on = BCTrainer(tiny_bc(tmp_path / "on", demos))
    off = BCTrainer(tiny_bc(tmp_path / "off", demos, bc=BCConfig(hindsight=False)))
    try:
        assert len(on.segments) == len(all_segments)
        assert (off.segments[:, 4] == 0).all() and len(off.segments) < len(on.segments)
        given = {(int(e), int(s)) for e, s, end, *_ in off.segments for s in range(s, end)}
        for _ in range(5):  # every row drawn comes from a given segment
            b = off._batch()
            assert {(int(e), int(s)) for e, s in zip(b.episode, b.step, strict=True)} <= given
    finally:
        on.close()
        off.close()


def test_ctrl_c_saves_and_resume_continues_exactly(demos, tmp_path, monkeypatch, capsys):
    full = BCTrainer(tiny_bc(tmp_path / "full", demos, checkpoint_every=100))
    full.run()

    out = tmp_path / "part"
    trainer = BCTrainer(tiny_bc(out, demos, checkpoint_every=100))
    interrupt_update(monkeypatch, trainer.agent, 151)
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    assert "interrupted at update 150" in capsys.readouterr().out
    ckpt = load_checkpoint(find_latest(out))
    assert ckpt.meta["step"] == 150 and ckpt.state("trainer")["step"] == 150

    resumed = BCTrainer(tiny_bc(out, demos, total_steps=300, checkpoint_every=7, resume=True))
    assert resumed.step == 150 and resumed.cfg.checkpoint_every == 100  # the saved config
    resumed.run()
    assert resumed.step == 300
    for name in ("weights.safetensors", "state.safetensors"):
        a = safetensors.torch.load_file(str(out / "checkpoints" / "step_000000300" / name))
        b = safetensors.torch.load_file(str(full.out / "checkpoints" / "step_000000300" / name))
        assert a.keys() == b.keys()
        assert [k for k in a if not torch.equal(a[k], b[k])] == [], name


def test_a_grammar_paraphrase_joins_the_training_instructions(encoder, tmp_path):
    from captioner.grammar import parse, random_paraphrase

    texts = train_texts(2)
    split, _ = preset_split()
    known = {*split.train, *split.heldout, *split.paraphrase}
    rng = np.random.default_rng(0)
    paraphrase = texts[0]
    while paraphrase in known:  # a phrasing of a training meaning that no set holds
        paraphrase = random_paraphrase(parse(texts[0]), rng)
    actions = np.zeros((4, 2), np.float32)
    path = write_demos(tmp_path / "d.h5", OBS_DIM, actions, [texts[1], paraphrase])
    base = BCTrainer(
        tiny_bc(tmp_path / "ref", write_demos(tmp_path / "r.h5", OBS_DIM, actions, texts))
    )
    trainer = BCTrainer(tiny_bc(tmp_path / "run", path))
    try:
        task = trainer.task
        assert task.num_train == base.task.num_train + 1
        assert paraphrase in task.table[: task.num_train]
        assert task.table[task.num_train :] == base.task.table[base.task.num_train :]
        assert trainer.goal_map.tolist() == [task.ids[texts[1]], task.ids[paraphrase]]
    finally:
        base.close()
        trainer.close()


# --- 3. the command line -----------------------------------------------------------------
def test_cli_train_bc_then_eval(demos, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    out = tmp_path / "run"
    args = ["train", "lang2d-bc", "--demos", str(demos), "--out", str(out)]
    assert cli(*args, "--total-steps", "200", "--bc.no-hindsight", *TINY_CLI) == 0
    captured = capsys.readouterr().out
    assert "behavioural cloning on" in captured and "final checkpoint" in captured
    assert f"lcrl eval {out}" in captured
    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "bc" and config["total_steps"] == 200
    assert config["bc"]["hindsight"] is False
    assert config["agent"]["net"]["hidden"] == [32, 32]
    assert find_latest(out) == out / "checkpoints" / "step_000000200"

    assert cli("eval", str(out), "--episodes", "3", "--num-envs", "1", "--no-progress") == 0
    captured = capsys.readouterr().out
    assert "(step 200)" in captured
    for name in SETS:
        assert f"{name}: success" in captured
    assert cli("report", str(out)) == 0


def test_cli_errors_name_the_fix(demos, tmp_path, capsys):
    out = str(tmp_path / "run")
    assert cli("train", "lang2d-bc", "--out", out, *TINY_CLI) == 2
    assert error_line(capsys.readouterr().err) == (
        "lcrl: error: behavioural cloning needs demonstrations: pass --demos FILE (record one "
        "with lcrl demos record)"
    )
    missing = str(tmp_path / "missing.h5")
    assert cli("train", "lang2d-bc", "--out", out, "--demos", missing, *TINY_CLI) == 2
    line = error_line(capsys.readouterr().err)
    assert f"no demonstration file at {missing}" in line and "pass --demos FILE" in line
    assert cli("train", "lang2d", "--out", out, "--demos", str(demos), *TINY_CLI) == 2
    assert "--demos is read by behavioural cloning only" in error_line(capsys.readouterr().err)
    assert not Path(out).exists()


def test_shape_mismatch_names_the_matching_preset(demos, tmp_path):
    # demonstrations of the lang2d preset, a run whose env has no displacement features
    cfg = tiny_bc(tmp_path / "run", demos)
    cfg.env = dataclasses.replace(cfg.env, displacements=False)
    cfg.agent = dataclasses.replace(cfg.agent, net=NetConfig(hidden=(32, 32)))
    with pytest.raises(LcrlError) as e:
        BCTrainer(cfg)
    msg = str(e.value)
    assert "does not fit this run's env" in msg
    assert f"observation ({OBS_DIM},)" in msg and "initial (42,)" in msg
    assert f"train with lcrl train lang2d-bc --demos {demos}" in msg

    # demonstrations of an env no preset has: the differing env options are named
    env = dataclasses.asdict(dataclasses.replace(PRESETS["lang2d-bc"][1].env, max_objects=2))
    env["relative_positions"] = False
    actions = np.zeros((3, 2), np.float32)
    path = write_demos(tmp_path / "d.h5", 42, actions, train_texts(1), meta={"env": env})
    with pytest.raises(LcrlError) as e:
        BCTrainer(tiny_bc(tmp_path / "run2", path))
    msg = str(e.value)
    assert "observation (42,)" in msg
    assert "--env.max-objects 2" in msg and "--env.no-relative-positions" in msg


def test_other_env_options_with_fitting_shapes_train_with_a_note(tmp_path, capsys):
    env = dataclasses.asdict(dataclasses.replace(PRESETS["lang2d-bc"][1].env, max_objects=2))
    actions = np.zeros((3, 2), np.float32)
    path = write_demos(tmp_path / "d.h5", OBS_DIM, actions, train_texts(1), meta={"env": env})
    trainer = BCTrainer(tiny_bc(tmp_path / "run", path))
    trainer.close()
    out = capsys.readouterr().out
    assert "recorded with other env options than this run's (--env.max-objects 2)" in out


def test_discrete_and_continuous_actions_must_agree(tmp_path):
    texts = train_texts(1)
    moves = np.asarray([0, 3, 5], np.int64)
    path = write_demos(tmp_path / "d.h5", OBS_DIM, moves, texts)
    with pytest.raises(LcrlError, match="holds discrete actions but this run's env has continuous"):
        BCTrainer(tiny_bc(tmp_path / "run", path))
    continuous = write_demos(tmp_path / "c.h5", OBS_DIM, np.zeros((3, 2), np.float32), texts)
    cfg = tiny_bc(tmp_path / "run2", continuous)
    cfg.env = dataclasses.replace(cfg.env, discrete=True)
    with pytest.raises(LcrlError, match="holds continuous actions but this run's env has discrete"):
        BCTrainer(cfg)
    wide = write_demos(tmp_path / "w.h5", OBS_DIM, np.zeros((3, 3), np.float32), texts)
    with pytest.raises(LcrlError, match="3-d actions"):
        BCTrainer(tiny_bc(tmp_path / "run3", wide))


def test_instructions_that_leak_the_evaluation_or_do_not_parse_are_refused(encoder, tmp_path):
    split, families = preset_split()

    def first(name: str) -> str:
        return next(
            t
            for t, m in zip(split.texts(name), split.instructions(name), strict=True)
            if m.family in families
        )

    from captioner.grammar import parse, random_paraphrase

    rng = np.random.default_rng(0)
    known = {*split.train, *split.heldout, *split.paraphrase}
    new_phrasing = first("heldout")
    while new_phrasing in known:  # a held-out combination in a phrasing no set holds
        new_phrasing = random_paraphrase(parse(first("heldout")), rng)
    actions = np.zeros((3, 2), np.float32)
    cases = (
        ([first("heldout")], "would leak the evaluation"),
        ([new_phrasing], "would leak the evaluation"),
        ([first("paraphrase")], "would leak the evaluation"),
        (["open the drawer"], "the grammar cannot parse them, e.g. 'open the drawer'"),
        (["lift the red cube"], "families ['lift'] that this run does not train"),
    )
    for i, (texts, match) in enumerate(cases):
        path = write_demos(tmp_path / f"d{i}.h5", OBS_DIM, actions, train_texts(1) + texts)
        with pytest.raises(LcrlError, match=match.replace("[", r"\[").replace("]", r"\]")):
            BCTrainer(tiny_bc(tmp_path / f"run{i}", path))


# --- 4. learning -------------------------------------------------------------------------
@pytest.mark.slow
def test_bc_on_scripted_reach_demos_beats_the_untrained_policy(encoder, tmp_path):
    path = record(
        RecordConfig(
            out=str(tmp_path / "reach.h5"),
            preset="lang2d",
            families=("reach",),
            episodes=200,
            noise=0.1,
            seed=1,
            progress=False,
        )
    )
    base = PRESETS["lang2d-bc"][1]
    cfg = dataclasses.replace(
        base,
        out=str(tmp_path / "run"),
        demos=str(path),
        env=dataclasses.replace(base.env, families=("reach",)),
        agent=dataclasses.replace(
            base.agent, net=dataclasses.replace(base.agent.net, hidden=(128, 128))
        ),
        total_steps=2000,
        batch_size=128,
        eval_every=0,
        eval_episodes=50,
        checkpoint_every=0,
        log_every=500,
        progress=False,
        tensorboard=False,
    )
    trainer = BCTrainer(cfg)
    before = evaluate(trainer.agent, trainer.task, cfg, episodes=50, sets=("train",))
    after = trainer.run()
    assert before["train"]["success"] <= 0.3
    assert after["train"]["success"] >= 0.8
    assert after["train"]["success"] >= before["train"]["success"] + 0.5


@pytest.mark.slow
def test_bc_on_robosuite_demonstrations_end_to_end(encoder, tmp_path, capsys):
    path = record(
        RecordConfig(out=str(tmp_path / "robo.h5"), preset="robosuite", episodes=2, progress=False)
    )
    out = tmp_path / "run"
    args = ["train", "robosuite-bc", "--demos", str(path), "--out", str(out)]
    assert cli(*args, "--total-steps", "50", "--eval-episodes", "1", *TINY_CLI[2:]) == 0
    assert find_latest(out) == out / "checkpoints" / "step_000000050"
    assert load_checkpoint(find_latest(out)).meta["algo"] == "bc"
    capsys.readouterr()
    assert cli("eval", str(out), "--episodes", "1", "--num-envs", "1", "--no-progress") == 0
    assert "(step 50)" in capsys.readouterr().out

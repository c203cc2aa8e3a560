"""Training runs end to end: outputs, checkpoints, exact resume, Ctrl-C, loading, the CLI.

Every run is tiny (a few hundred steps, 32-unit networks, one torch thread) so the whole
file takes well under a minute on a small CPU.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import safetensors.torch
import torch
from helpers import cli, error_line, tiny

from lcrl.checkpoint import find_latest, load_checkpoint
from lcrl.errors import LcrlError
from train.configs.presets import PRESETS
from train.evaluation.evaluate import evaluate, run_episode
from train.policies.loading import load_policy
from train.training.loop import Trainer

EPISODE = 50  # state2d's max_episode_steps; goal="pusher" episodes never terminate early
SETS = ("train", "heldout", "paraphrase")
CKPT_FILES = ("meta.json", "weights.safetensors", "instructions.json", "split.json")
TINY_CLI = [
    "--learning-starts", "100",
    "--batch-size", "32",
    "--eval-every", "0",
    "--eval-episodes", "3",
    "--checkpoint-every", "0",
    "--log-every", "100",
    "--buffer.capacity", "2000",
    "--agent.net.hidden", "32", "32",
    "--agent.net.text-dim", "8",
    "--no-progress",
    "--no-tensorboard",
]  # fmt: skip


# --- fixtures and helpers ----------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def text_encoder(one_thread):
    """Warm the frozen text encoder once (trainers build their own, faster once warm)."""
    from lcrl.text_encoder import FrozenTextEncoder

    return FrozenTextEncoder()


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def assert_same_tensors(a: Path, b: Path) -> None:
    """Two checkpoints hold bit-identical weights and optimiser/RNG tensors."""
    for name in ("weights.safetensors", "state.safetensors"):
        ta = safetensors.torch.load_file(str(a / name))
        tb = safetensors.torch.load_file(str(b / name))
        assert ta.keys() == tb.keys(), name
        different = [k for k in ta if not torch.equal(ta[k], tb[k])]
        assert not different, f"{name}: {different[:5]}"


@pytest.fixture(scope="module")
def lang_run(text_encoder, tmp_path_factory):
    """A finished 300-step lang2d-quick run: (trainer, results)."""
    out = tmp_path_factory.mktemp("lang") / "run"
    trainer = Trainer(tiny("lang2d-quick", out))
    results = trainer.run()
    return trainer, results


@pytest.fixture(scope="module")
def state_full(one_thread, tmp_path_factory):
    """An uninterrupted 300-step state2d run (pusher goals): the reference for resumes."""
    out = tmp_path_factory.mktemp("state") / "full"
    trainer = Trainer(tiny("state2d", out))
    trainer.run()
    return trainer


# --- 1. outputs of a run -----------------------------------------------------------------
def test_lang2d_run_writes_all_outputs(lang_run):
    trainer, results = lang_run
    out = trainer.out
    assert trainer.step == 300

    config = json.loads((out / "config.json").read_text())
    assert config["resolved_algo"] == "sac"
    assert config["total_steps"] == 300 and config["env"]["kind"] == "tabletop2d"

    fields, rows = read_csv(out / "progress.csv")
    assert {"step", "episodes", "success", "buffer", "updates"} <= set(fields)
    assert [int(r["step"]) for r in rows][-1] == 300
    assert all(float(r["updates"]) >= 0 for r in rows)

    fields, rows = read_csv(out / "eval.csv")
    assert len(rows) == 1 and int(rows[0]["step"]) == 300
    for name in SETS:
        assert f"{name}/success" in fields
        assert any(f"{name}/{fam}" in fields for fam in ("reach", "push"))
        assert 0.0 <= float(rows[0][f"{name}/success"]) <= 1.0

    ckpt = out / "checkpoints" / "step_000000300"
    for name in CKPT_FILES:
        assert (ckpt / name).is_file(), name
    assert (out / "latest.json").is_file()
    assert find_latest(out) == ckpt
    meta = json.loads((ckpt / "meta.json").read_text())
    assert meta["step"] == 300 and meta["algo"] == "sac"
    instructions = json.loads((ckpt / "instructions.json").read_text())
    assert 0 < instructions["num_train"] < len(instructions["texts"])

    assert set(results) == set(SETS)
    for res in results.values():
        assert 0.0 <= res["success"] <= 1.0
        assert res["episodes"] == 3
        assert res["families"] and set(res["families"]) <= {"reach"}
        assert all(0.0 <= v <= 1.0 for v in res["families"].values())


def test_short_run_still_writes_a_final_progress_row(one_thread, tmp_path):
    cfg = tiny("state2d", tmp_path / "run", total_steps=150, log_every=1000)
    Trainer(cfg).run()
    _, rows = read_csv(tmp_path / "run" / "progress.csv")
    assert int(rows[-1]["step"]) == 150


def test_periodic_checkpoints_keep_the_latest(one_thread, tmp_path):
    out = tmp_path / "run"
    Trainer(tiny("state2d", out, checkpoint_every=100, keep_checkpoints=2)).run()
    kept = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert kept == ["step_000000200", "step_000000300"]
    assert find_latest(out) == out / "checkpoints" / "step_000000300"


# --- 2. exact resume ---------------------------------------------------------------------
def test_resume_without_a_saved_buffer_says_so(tmp_path, capsys):
    out = tmp_path / "nobuf"
    Trainer(tiny("state2d", out, total_steps=100, save_buffer=False)).run()
    resumed = Trainer(tiny("state2d", out, total_steps=200, resume=True))
    printed = capsys.readouterr().out
    assert resumed.step == 100 and resumed.buffer.size == 0
    assert "holds no replay buffer" in printed and "does not continue the run exactly" in printed


def test_resume_at_episode_boundary_is_bit_identical(state_full, tmp_path, capsys):
    full = state_full
    # the assumption that makes 150 an episode boundary: no episode ends early
    assert full.cfg.env.goal == "pusher" and full.cfg.env.max_episode_steps == EPISODE
    assert full.episodes == 300 // EPISODE
    assert not full.buffer.terminated.any()

    out = tmp_path / "part"
    first = Trainer(tiny("state2d", out, total_steps=150))
    first.run()
    assert first.step == 150 and first.episodes == 150 // EPISODE
    saved_arrays = first.buffer.arrays()

    # everything but total_steps comes from the saved config
    resumed = Trainer(tiny("state2d", out, total_steps=300, batch_size=64, resume=True))
    assert resumed.step == 150 and resumed.episodes == 3
    assert resumed.cfg.batch_size == 32 and resumed.cfg.total_steps == 300
    assert resumed.buffer.size == first.buffer.size > 0
    assert resumed.agent.updates == first.agent.updates
    restored = resumed.buffer.arrays()
    assert restored.keys() == saved_arrays.keys()
    for key, value in saved_arrays.items():
        np.testing.assert_array_equal(restored[key], value, err_msg=key)
    assert "resumed" in capsys.readouterr().out

    resumed.run()
    assert resumed.step == 300 and resumed.episodes == full.episodes
    assert resumed.agent.updates == full.agent.updates
    assert_same_tensors(
        out / "checkpoints" / "step_000000300", full.out / "checkpoints" / "step_000000300"
    )
    # progress.csv continues under one header
    lines = (out / "progress.csv").read_text().splitlines()
    assert sum(line.startswith("step,") for line in lines) == 1
    steps = [int(line.split(",")[0]) for line in lines[1:]]
    assert steps == sorted(set(steps)) and {100, 200, 300} <= set(steps)


def test_buffer_storage_on_the_device_learns_and_resumes_as_on_the_host(state_full, tmp_path):
    """Observations stored as tensors on the learner's device (the CPU here) give the same
    run as host storage, bit for bit, and so does a resume of such a run."""
    out = tmp_path / "dev"
    device = dict(buffer=dataclasses.replace(state_full.cfg.buffer, storage="device"))
    first = Trainer(tiny("state2d", out, total_steps=150, **device))
    assert first.buffer.device_keys and isinstance(first.buffer.obs["observation"], torch.Tensor)
    first.run()
    resumed = Trainer(tiny("state2d", out, total_steps=300, resume=True))
    assert resumed.cfg.buffer.storage == "device" and resumed.buffer.size == first.buffer.size
    resumed.run()
    assert_same_tensors(
        out / "checkpoints" / "step_000000300", state_full.out / "checkpoints" / "step_000000300"
    )


def test_bad_buffer_storage_is_one_line(tmp_path):
    cfg = tiny("state2d", tmp_path / "bad", buffer=dataclasses.replace(
        PRESETS["state2d"][1].buffer, storage="gpu"))  # fmt: skip
    with pytest.raises(
        LcrlError, match=r"buffer.storage must be one of \('host', 'device'\), got 'gpu'"
    ):
        cfg.validate()


# --- 3. Ctrl-C ---------------------------------------------------------------------------
def test_ctrl_c_saves_a_checkpoint_and_resumes_exactly(state_full, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    calls = {"n": 0}
    original = Trainer.collect_episode

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        original(self)

    monkeypatch.setattr(Trainer, "collect_episode", interrupted)
    trainer = Trainer(tiny("state2d", out))
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    assert "interrupted at step 100" in capsys.readouterr().out
    assert (out / "latest.json").is_file()
    ckpt = load_checkpoint(find_latest(out))
    assert ckpt.meta["step"] == 2 * EPISODE and ckpt.meta["episodes"] == 2
    assert ckpt.state("trainer")["step"] == 2 * EPISODE
    assert ckpt.has_arrays()
    monkeypatch.undo()

    resumed = Trainer(tiny("state2d", out, resume=True))
    assert resumed.step == 100 and resumed.buffer.size == trainer.buffer.size
    resumed.run()
    assert resumed.step == 300
    assert_same_tensors(
        out / "checkpoints" / "step_000000300",
        state_full.out / "checkpoints" / "step_000000300",
    )


def test_ctrl_c_mid_episode_rolls_back_and_resumes_exactly(state_full, tmp_path):
    """Stopped 20 steps into the third episode, after 20 of its gradient updates: the
    checkpoint is the state at the episode's start, and the resumed run ends with the
    weights of the uninterrupted one."""
    out = tmp_path / "run"
    trainer = Trainer(tiny("state2d", out))
    env_step, calls = trainer.env.step, {"n": 0}

    def step(action):
        calls["n"] += 1
        if calls["n"] == 2 * EPISODE + 20:  # 20 steps into the third episode
            raise KeyboardInterrupt
        return env_step(action)

    trainer.env.step = step
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    ckpt = load_checkpoint(find_latest(out))
    assert ckpt.meta["episodes"] == 2
    assert ckpt.meta["step"] == 2 * EPISODE
    assert ckpt.state("counters")["updates"] == 2 * EPISODE - 100 + 1  # updates to step 100

    resumed = Trainer(tiny("state2d", out, resume=True))
    resumed.run()
    assert resumed.step == 300
    assert_same_tensors(
        out / "checkpoints" / "step_000000300",
        state_full.out / "checkpoints" / "step_000000300",
    )


# --- 4. refusing to clobber or to resume nothing -----------------------------------------
def test_new_run_over_existing_run_or_resume_without_checkpoint_fails(state_full, tmp_path):
    out = state_full.out
    before = sorted(p.name for p in (out / "checkpoints").iterdir())
    with pytest.raises(LcrlError, match="already holds a run"):
        Trainer(tiny("state2d", out))
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == before

    with pytest.raises(LcrlError, match="no checkpoint"):
        Trainer(tiny("state2d", tmp_path / "empty", resume=True))
    dangling = tmp_path / "dangling"
    dangling.mkdir()
    (dangling / "latest.json").write_text(json.dumps({"checkpoint": "checkpoints/step_1"}))
    with pytest.raises(LcrlError):
        Trainer(tiny("state2d", dangling, resume=True))


# --- 5. loading policies -----------------------------------------------------------------
def test_load_policy_from_run_or_checkpoint_and_evaluate(lang_run):
    trainer, _ = lang_run
    ckpt_dir = trainer.out / "checkpoints" / "step_000000300"
    from_run = load_policy(trainer.out)
    from_ckpt = load_policy(ckpt_dir)
    assert from_run.checkpoint.path == from_ckpt.checkpoint.path == ckpt_dir
    assert from_run.task.table == trainer.task.table

    episodes = [run_episode(p.agent, p.task, p.env, seed=5) for p in (from_run, from_ckpt)] + [
        run_episode(trainer.agent, trainer.task, trainer.env, seed=5)
    ]
    assert episodes[0] == episodes[1] == episodes[2]

    results = evaluate(from_ckpt.agent, from_ckpt.task, from_ckpt.cfg, episodes=3)
    assert set(results) == set(SETS)
    for res in results.values():
        assert set(res["families"]) <= {"reach"} and res["families"]
        assert 0.0 <= res["success"] <= 1.0
    only = evaluate(from_ckpt.agent, from_ckpt.task, from_ckpt.cfg, 3, sets=("heldout",))
    assert set(only) == {"heldout"}


def test_load_policy_rejects_mismatched_env_and_missing_path(lang_run, tmp_path):
    trainer, _ = lang_run
    with pytest.raises(LcrlError) as e:
        load_policy(trainer.out, env_overrides={"kind": "state2d"})
    msg = str(e.value)
    assert "does not match" in msg
    assert "text goals (384,)" in msg and "vector goals (16,)" in msg
    assert "initial (58,)" in msg

    with pytest.raises(LcrlError) as e:
        load_policy(trainer.out, env_overrides={"discrete": True})
    assert "2-d actions" in str(e.value)
    assert re.search(r"gives .*\d+ discrete actions", str(e.value))

    with pytest.raises(LcrlError, match="unknown env option"):
        load_policy(trainer.out, env_overrides={"colour": "red"})
    with pytest.raises(LcrlError):
        load_policy(tmp_path / "missing")
    with pytest.raises(LcrlError):
        load_policy(tmp_path)  # exists, but neither a checkpoint nor a run


# --- 6. the command line -----------------------------------------------------------------
def test_cli_train_eval_act(text_encoder, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    out = tmp_path / "run"
    assert cli("train", "lang2d-quick", "--out", str(out), "--total-steps", "200", *TINY_CLI) == 0
    captured = capsys.readouterr().out
    assert "final checkpoint" in captured and f"lcrl eval {out}" in captured
    config = json.loads((out / "config.json").read_text())
    assert config["agent"]["net"]["hidden"] == [32, 32]
    assert config["agent"]["net"]["text_dim"] == 8
    assert config["total_steps"] == 200 and config["buffer"]["capacity"] == 2000
    assert find_latest(out) == out / "checkpoints" / "step_000000200"

    assert cli("eval", str(out), "--episodes", "3") == 0
    captured = capsys.readouterr().out
    assert "(step 200)" in captured
    for name in SETS:
        line = rf"^{name}: success \d\.\d\d \(reach \d\.\d\d; 3 episodes\)"
        assert re.search(line, captured, re.M)

    assert cli("act", str(out), "--instruction", "touch the red block", "--episodes", "2") == 0
    captured = capsys.readouterr().out
    assert "-> 'reach the red cube'" in captured
    assert re.search(r"^success \d\.\d\d over 2 episodes$", captured, re.M)

    assert cli("act", str(out), "--instruction", "dance a little jig", "--episodes", "1") == 0
    captured = capsys.readouterr().out
    assert "cannot parse" in captured and "not checked" in captured
    assert "over 1 episodes" not in captured

    # a second train into the same folder needs --resume; with it, the run continues
    assert cli("train", "lang2d-quick", "--out", str(out), "--total-steps", "260", *TINY_CLI) == 2
    assert "already holds a run" in error_line(capsys.readouterr().err)
    args = ("train", "lang2d-quick", "--out", str(out), "--total-steps", "260", "--resume")
    assert cli(*args, "--no-progress") == 0
    assert "resumed" in capsys.readouterr().out
    assert find_latest(out) == out / "checkpoints" / "step_000000260"


def test_cli_errors_and_help(text_encoder, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    assert cli("eval", str(tmp_path / "nonexistent")) == 2
    err = capsys.readouterr().err
    assert err.startswith("lcrl: error:") and "Traceback" not in err
    assert "nonexistent" in err

    assert cli("train", "lang2d-quick", "--help") == 0
    help_text = capsys.readouterr().out
    for flag in ("--total-steps", "--buffer.k", "--agent.net.hidden", "--resume"):
        assert flag in help_text

    assert cli("train", "nosuchpreset") != 0
    capsys.readouterr()

    out = tmp_path / "dqn"
    assert cli("train", "lang2d-quick", "--out", str(out), "--algo", "dqn", *TINY_CLI) == 2
    err = error_line(capsys.readouterr().err)  # after the encoder's loading bar
    assert err.startswith("lcrl: error:") and "dqn needs discrete actions" in err
    assert not out.exists()

    # the grounding loss and attribute slots: one line each, nothing written
    for extra, message in [
        (("--agent.net.slot-attributes", "0", "1", "2"), "needs slot_attributes: 8 values"),
        (("--agent.grounding", "-1"), "grounding must be 0 (off) or positive"),
    ]:
        assert cli("train", "lang2d-quick", "--out", str(out), *extra, *TINY_CLI) == 2
        err = error_line(capsys.readouterr().err)
        assert err.startswith("lcrl: error:") and message in err, err
        assert not out.exists()
    state = tmp_path / "state"
    assert cli("train", "state2d", "--out", str(state), "--agent.grounding", "1", *TINY_CLI) == 2
    assert "read object slots" in error_line(capsys.readouterr().err)


def test_act_saves_a_video_and_runs_state_goal_checkpoints(lang_run, state_full, tmp_path, capsys):
    import cv2

    trainer, _ = lang_run
    video = tmp_path / "videos" / "act.mp4"
    args = ("act", str(trainer.out), "--instruction", "reach the red cube", "--episodes", "2")
    assert cli(*args, "--video", str(video), "--fps", "5") == 0
    out = capsys.readouterr().out
    steps = [int(n) for n in re.findall(r"^episode \d: (\d+) steps", out, re.M)]
    assert len(steps) == 2 and f"video: {video}" in out
    cap = cv2.VideoCapture(str(video))
    # + each reset frame, + each last frame held 1 s (5 frames) with the outcome
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == sum(steps) + 2 * (1 + 5)
    ok, frame = cap.read()
    assert ok and frame.shape[2] == 3 and frame.std() > 0
    cap.release()

    assert cli("act", str(state_full.out), "--episodes", "1") == 0
    assert re.search(r"^success \d\.\d\d over 1 episodes$", capsys.readouterr().out, re.M)
    assert cli("act", str(state_full.out), "--instruction", "reach the red cube") == 2
    assert "not trained with language goals" in capsys.readouterr().err
    assert cli("act", str(trainer.out)) == 2
    assert "give an --instruction" in capsys.readouterr().err
    assert cli(*args, "--video", str(tmp_path / "x.avi")) == 2
    assert ".mp4" in capsys.readouterr().err


# --- 7. no pickle ------------------------------------------------------------------------
def test_checkpoints_load_without_pickle(lang_run, state_full, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a checkpoint must never be unpickled")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    trainer, _ = lang_run
    policy = load_policy(trainer.out)
    assert run_episode(policy.agent, policy.task, policy.env, seed=1)["steps"] > 0

    # a resume reads optimiser/RNG state and the replay buffer too
    resumed = Trainer(tiny("state2d", state_full.out, resume=True, total_steps=400))
    assert resumed.step == 300 and resumed.buffer.size == state_full.buffer.size
    for ckpt in (trainer.out, state_full.out):
        files = {p.suffix for p in find_latest(ckpt).iterdir()}
        assert files <= {".json", ".safetensors", ".npz"}


# --- 8. TD3 and DQN ----------------------------------------------------------------------
@pytest.mark.parametrize(("preset", "algo"), [("lang2d-td3", "td3"), ("lang2d-dqn", "dqn")])
def test_td3_and_dqn_presets_run_and_load(text_encoder, tmp_path, preset, algo):
    out = tmp_path / "run"
    trainer = Trainer(tiny(preset, out))
    results = trainer.run()
    assert trainer.algo == algo and trainer.agent.updates > 0
    assert set(results) == set(SETS)
    assert json.loads((out / "config.json").read_text())["resolved_algo"] == algo

    policy = load_policy(out)
    assert policy.checkpoint.meta["algo"] == algo
    assert type(policy.agent) is type(trainer.agent)
    assert policy.task.discrete == (algo == "dqn")
    a = run_episode(policy.agent, policy.task, policy.env, seed=3)
    b = run_episode(trainer.agent, trainer.task, trainer.env, seed=3)
    assert a == b


def test_saved_configs_keep_their_text_goal_normalisation():
    from train.configs.config import config_from_dict, config_to_dict

    cfg = PRESETS["lang2d"][1]
    cfg = dataclasses.replace(cfg, agent=dataclasses.replace(cfg.agent, text_goal_norm="whiten"))
    saved = config_to_dict(cfg)
    assert config_from_dict(saved).agent.text_goal_norm == "whiten"
    # A config saved before the option existed loads with the normalisation its weights
    # were trained with.
    del saved["agent"]["text_goal_norm"]
    assert config_from_dict(saved).agent.text_goal_norm == "standardize"


def test_scripted_episodes_are_stored_counted_and_resumed(text_encoder, tmp_path):
    out = tmp_path / "scripted"
    cfg = tiny("lang2d", out, total_steps=400, scripted_fraction=0.5, checkpoint_every=200)
    trainer = Trainer(cfg)
    trainer.run()
    assert 0 < trainer.scripted_episodes < trainer.episodes
    # the live success rate counts the policy's episodes only
    assert len(trainer.recent) == trainer.episodes - trainer.scripted_episodes
    buf = trainer.buffer
    acts = buf.action[: buf.size]
    assert np.all(np.abs(acts) <= 1.0)
    # Scripted episodes succeed at their instruction and end there (terminated), so the
    # buffer holds far more terminated episodes than 400 steps of a barely trained policy.
    assert buf.terminated[: buf.size].sum() >= 0.8 * trainer.scripted_episodes
    _, rows = read_csv(out / "progress.csv")
    assert int(rows[-1]["scripted_episodes"]) == trainer.scripted_episodes
    # resuming restores the scripted-episode generator: the continuation is identical
    twin = tmp_path / "twin"
    Trainer(dataclasses.replace(cfg, out=str(twin), total_steps=200)).run()
    resumed = Trainer(dataclasses.replace(cfg, out=str(twin), total_steps=400, resume=True))
    resumed.run()
    assert resumed.scripted_episodes == trainer.scripted_episodes
    assert resumed.episodes == trainer.episodes


def test_scripted_episode_settings_are_checked(text_encoder, tmp_path):
    with pytest.raises(LcrlError, match="scripted_fraction"):
        Trainer(tiny("lang2d", tmp_path / "a", scripted_fraction=1.5))
    with pytest.raises(LcrlError, match="scripted_noise"):
        Trainer(tiny("lang2d", tmp_path / "b", scripted_fraction=0.5, scripted_noise=-1.0))
    with pytest.raises(LcrlError, match="scripted controller"):
        Trainer(tiny("state2d", tmp_path / "c", scripted_fraction=0.5))


def test_a_stop_during_the_final_evaluation_keeps_the_last_step(one_thread, tmp_path, monkeypatch):
    out = tmp_path / "run"
    trainer = Trainer(tiny("state2d", out, total_steps=150))

    def stopped(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "evaluate", stopped)
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    assert load_checkpoint(find_latest(out)).meta["step"] == 150

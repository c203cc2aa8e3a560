"""Bad numbers and text get one clear line, never a silent wrong answer: non-finite
observations and goals, bytes where text belongs, text that was not UTF-8, a fractional
discrete action, a mistyped preset."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from helpers import cli, error_line, tiny

import envs
import lcrl
from lcrl.errors import LcrlError
from train.configs.presets import PRESETS
from train.policies.policy import check_instruction
from train.training.loop import Trainer

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def lang_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad") / "lang"
    Trainer(tiny("lang2d-quick", out, total_steps=120, learning_starts=100)).run()
    return out


@pytest.fixture(scope="module")
def state_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad") / "state"
    Trainer(tiny("state2d", out, total_steps=110, learning_starts=100)).run()
    return out


def test_non_finite_observations_and_goals_are_refused(lang_run, state_run):
    policy = lcrl.load(lang_run, device="cpu")
    obs, _ = policy.make_env().reset(seed=0)
    assert np.isfinite(policy.act(obs, "reach the red cube", initial=obs)).all()
    for bad in (np.nan, np.inf):
        broken = {**obs, "observation": obs["observation"].copy()}
        broken["observation"][3] = bad
        with pytest.raises(LcrlError) as e:
            policy.act(broken, "reach the red cube", initial=obs)
        assert str(e.value).startswith(f"observation['observation'] holds {bad} at index [3]")
        with pytest.raises(LcrlError, match=r"initial\['observation'\] holds"):
            policy.act(obs, "reach the red cube", initial=broken)

    state = lcrl.load(state_run, device="cpu")
    sobs, _ = state.make_env().reset(seed=0)
    goal = np.full_like(sobs["desired_goal"], np.nan)
    with pytest.raises(LcrlError, match=r"^goal holds nan at index \[0\] \(2 non-finite values"):
        state.act(sobs, goal=goal)


def test_bytes_are_not_text(lang_run):
    policy = lcrl.load(lang_run, device="cpu")
    obs, _ = policy.make_env().reset(seed=0)
    for instruction in (b"reach the red cube", [b"reach the red cube"]):
        with pytest.raises(LcrlError, match=r"must be text \(str\), not bytes: decode"):
            policy.act(obs, instruction, initial=obs)
    with pytest.raises(LcrlError, match="not bytes"):
        policy.embed(b"reach the red cube")


def test_text_that_was_not_utf8_says_so():
    undecodable = b"reach the r\xe9d cube".decode("utf-8", "surrogateescape")
    with pytest.raises(LcrlError, match=r"not valid UTF-8: b'reach the r\\xe9d cube'"):
        check_instruction(undecodable)
    with pytest.raises(LcrlError, match="U\\+FFFD"):
        check_instruction(b"reach the r\xe9d cube".decode("utf-8", "replace"))
    with pytest.raises(LcrlError, match="control characters"):
        check_instruction("reach the red\x07 cube")


def test_non_utf8_argument_on_the_command_line(lang_run):
    """The real command: Linux hands the bytes over, Python keeps them as surrogates."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "train.commands.cli",
            "act",
            str(lang_run),
            "--instruction",
            b"reach the r\xe9d cube",
            "--episodes",
            "1",
        ],
        cwd=ROOT,
        capture_output=True,
        timeout=300,
    )
    assert done.returncode == 2
    line = error_line(done.stderr.decode("utf-8", "replace"))
    assert line.startswith("lcrl: error: instruction is not valid UTF-8: b'reach the r\\xe9d")


def test_discrete_actions_are_whole_numbers():
    gym.register_envs(envs)
    env = gym.make("lcrl/Tabletop2DDiscrete-v0")
    env.reset(seed=0)
    for ok in (3, np.int64(3), 3.0, np.array(3), np.array([3])):
        env.step(ok)
    refused = [
        (2.5, "not a whole number"),
        (np.nan, "not a whole number"),
        (np.array([1, 2]), "must be one integer"),
        ("2", "must be one integer"),
    ]
    for bad, why in refused:
        with pytest.raises(ValueError, match=why):
            env.step(bad)


def test_a_mistyped_preset_is_named_first(capsys):
    from train.commands.pipeline import PIPELINES  # policies built in stages count as presets

    assert cli("train", "lang2dd", "--total-steps", "10", "--buffer.k", "2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "lcrl: error: unknown preset 'lang2dd': did you mean lang2d, lang2d-td3, "
        f"lang2d-dqn? lcrl train --help lists all {len(PRESETS) + len(PIPELINES)} presets"
    ]
    assert cli("train", "nothing-like-it") == 2
    assert "did you mean" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["eval", "act"])
def test_eval_and_act_take_torch_threads_and_refuse_a_negative_count(lang_run, command, capsys):
    import torch

    code = cli(command, str(lang_run), "--torch-threads", "-1", "--episodes", "1")
    assert code == 2
    assert error_line(capsys.readouterr().err) == (
        "lcrl: error: --torch-threads must be >= 0 (0: automatic), got -1"
    )
    before = torch.get_num_threads()
    try:
        extra = ["--instruction", "reach the red cube"] if command == "act" else []
        code = cli(command, str(lang_run), "--torch-threads", "2", "--episodes", "1", *extra)
        assert code == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)

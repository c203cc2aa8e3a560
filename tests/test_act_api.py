"""Querying trained policies with free text: the Python API (``lcrl.load``, ``Policy.act``,
``Policy.nearest``), ``lcrl act`` videos with the instruction drawn on them, the interactive
mode, the errors, and the README example (``examples/query_policy.py``).

The checkpoints are tiny (120 training steps, 32-unit networks); the tests check that the
plumbing is exact, not that the policies are good.
"""

from __future__ import annotations

import os
import re
import runpy
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from helpers import cli, tiny

import lcrl
from lcrl.errors import LcrlError
from train.commands.act import annotate_episode, upscale
from train.evaluation.evaluate import run_episode
from train.policies.policy import Policy
from train.training.loop import Trainer

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "query_policy.py"
TEXT = "touch the red block"  # the grammar reads it as "reach the red cube"


# --- fixtures and helpers ----------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def lang_ckpt(tmp_path_factory) -> Path:
    """A 120-step lang2d-quick run folder (reach instructions, 2 objects)."""
    out = tmp_path_factory.mktemp("act") / "lang"
    Trainer(tiny("lang2d-quick", out, total_steps=120, learning_starts=100)).run()
    return out


@pytest.fixture(scope="module")
def state_ckpt(tmp_path_factory) -> Path:
    """A 110-step state2d run folder (pusher-position goals)."""
    out = tmp_path_factory.mktemp("act") / "state"
    Trainer(tiny("state2d", out, total_steps=110, learning_starts=100)).run()
    return out


@pytest.fixture(scope="module")
def policy(lang_ckpt) -> Policy:
    return lcrl.load(lang_ckpt, device="cpu")


class RecordActions(gym.Wrapper):
    """Keeps every action passed to ``step``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.actions: list[np.ndarray] = []

    def step(self, action):
        self.actions.append(np.array(action, copy=True))
        return self.env.step(action)


def observations(policy: Policy, seeds: range) -> list[dict]:
    """The first observation of a fresh env for each seed."""
    env = policy.make_env()
    return [env.reset(seed=s)[0] for s in seeds]


def stack(obs: list[dict]) -> dict[str, np.ndarray]:
    return {"observation": np.stack([o["observation"] for o in obs])}


# --- the Python API ----------------------------------------------------------------------
def test_import_lcrl_stays_light():
    code = "import sys, lcrl; print(callable(lcrl.load), 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "False"]


def test_act_repeats_run_episode_exactly(policy):
    assert policy.language and policy.instructions and policy.families == ("reach",)
    assert str(policy.agent.device) == "cpu"
    options = {"instruction": "reach the red cube"}
    reference = RecordActions(policy.make_env())
    vector = policy.embed(TEXT)[0]
    r = run_episode(
        policy.agent, policy.task, reference, seed=5, options=options, goal_vector=vector
    )
    assert len(reference.actions) == r["steps"] > 0

    env = policy.make_env()
    obs, _ = env.reset(seed=5, options=options)
    policy.reset()
    mine = []
    for _ in range(r["steps"]):
        action = policy.act(obs, TEXT)
        mine.append(action)
        obs, *_ = env.step(action)
    assert mine[0].shape == (2,) and mine[0].dtype == np.float32
    low, high = env.action_space.low, env.action_space.high
    assert all(np.all((a >= low) & (a <= high)) for a in mine)
    for step, (a, b) in enumerate(zip(mine, reference.actions, strict=True)):
        np.testing.assert_array_equal(a, b, err_msg=f"step {step}")


def test_first_observation_is_remembered_until_reset(policy):
    first, later = observations(policy, range(20, 22))
    policy.reset()
    policy.act(first, TEXT)
    remembered = policy.act(later, TEXT)
    np.testing.assert_array_equal(remembered, policy.act(later, TEXT, initial=first))
    policy.reset()
    fresh = policy.act(later, TEXT)  # ``later`` now starts the episode
    np.testing.assert_array_equal(fresh, policy.act(later, TEXT, initial=later))
    assert not np.allclose(fresh, remembered)  # the network does read the first observation


def test_batched_act_equals_row_by_row(policy):
    obs = observations(policy, range(30, 34))
    starts = observations(policy, range(40, 44))
    texts = ["reach the red cube", "go to the blue cylinder", "dance a jig", TEXT]
    batched = policy.act(stack(obs), texts, initial=stack(starts))
    assert batched.shape == (4, 2)
    rows = np.stack(
        [policy.act(o, t, initial=s) for o, t, s in zip(obs, texts, starts, strict=True)]
    )
    np.testing.assert_allclose(batched, rows, rtol=0, atol=1e-5)
    assert not np.allclose(batched[0], batched[1])

    # one text for every row, remembered first observations, the env's own instruction
    policy.reset()
    one = policy.act(stack(obs), TEXT)
    np.testing.assert_allclose(one, policy.act(stack(obs), [TEXT] * 4, initial=stack(obs)))
    own = {"observation": stack(obs)["observation"], "instruction": np.array(texts)}
    np.testing.assert_allclose(own_action := policy.act(own, initial=stack(starts)), batched)
    assert own_action.shape == (4, 2)
    policy.reset()


def test_stochastic_actions_vary(policy):
    (obs,) = observations(policy, range(50, 51))
    samples = np.stack([policy.act(obs, TEXT, initial=obs, deterministic=False) for _ in range(5)])
    assert np.unique(samples.round(6), axis=0).shape[0] > 1


def test_nearest_training_instructions(policy):
    train = policy.instructions
    for text in train[:3]:
        (best,) = policy.nearest(text, k=1)
        assert best.text == text and best.similarity == pytest.approx(1.0, abs=1e-5)

    near = policy.nearest("bump into the crimson box", k=3)
    assert len(near) == 3 and all(n.text in train for n in near)
    sims = [n.similarity for n in near]
    assert sims == sorted(sims, reverse=True) and -1.0 <= sims[-1] <= sims[0] <= 1.0
    # the scores are the embeddings' cosine similarities, and no other instruction is closer
    query = policy.embed("bump into the crimson box")[0]
    table = policy.embed(train)
    cos = table @ query / (np.linalg.norm(table, axis=1) * np.linalg.norm(query))
    assert sims == pytest.approx(sorted(cos, reverse=True)[:3], abs=1e-5)
    assert [n.text for n in policy.nearest("reach the red cube", k=len(train) + 5)] == [
        train[i] for i in np.argsort(-(table @ policy.embed("reach the red cube")[0]))
    ]


def test_state_goal_policy_reads_the_desired_goal(state_ckpt):
    p = lcrl.load(state_ckpt)
    assert not p.language and p.instructions == []
    env = p.make_env()
    obs, _ = env.reset(seed=1)
    action = p.act(obs)
    assert action.shape == env.action_space.shape
    np.testing.assert_array_equal(action, p.act(obs, goal=obs["desired_goal"]))
    assert not np.allclose(action, p.act(obs, goal=obs["desired_goal"] + 0.3))
    with pytest.raises(LcrlError, match="not trained with language goals"):
        p.act(obs, "reach the red cube")
    with pytest.raises(LcrlError, match="not trained with language goals"):
        p.nearest("reach the red cube")
    with pytest.raises(LcrlError, match="desired_goal"):
        p.act({"observation": obs["observation"]})


# --- errors ------------------------------------------------------------------------------
def test_text_errors(policy):
    (obs,) = observations(policy, range(60, 61))
    for text, message in [
        ("   ", "empty instruction"),
        ("x" * 201, "201 characters long; the limit is 200"),
        ("reach the\x00red cube", "control characters"),
        (7, "must be a string"),
    ]:
        with pytest.raises(LcrlError, match=message):
            policy.act(obs, text, initial=obs)
    with pytest.raises(LcrlError, match="give an instruction"):
        policy.act({"observation": obs["observation"]}, initial=obs)
    with pytest.raises(LcrlError, match="k must be a positive integer"):
        policy.nearest("reach the red cube", k=0)
    # any other characters are free text, embedded like the rest
    assert policy.act(obs, "atteins le cube rouge, s'il te plaît", initial=obs).shape == (2,)


def test_observation_errors(policy):
    obs = observations(policy, range(70, 73))
    dim = obs[0]["observation"].shape[0]
    bad = [
        (np.zeros(dim), "must be the dict the environment returns"),
        ({"image": np.zeros((64, 64, 3), np.uint8)}, "no 'observation' entry"),
        ({"observation": obs[0]["observation"][:10]}, r"shape \(10,\).*another environment"),
        ({"observation": np.zeros((2, 3, dim))}, "shape"),
        ({"observation": np.array(["a"] * dim)}, "must be numbers"),
    ]
    for observation, message in bad:
        with pytest.raises(LcrlError, match=message):
            policy.act(observation, TEXT, initial=obs[0])

    # a robosuite tabletop observation given to a lang2d policy
    from envs.robosuite_tabletop import _OBS_DIM

    robo = {"observation": np.zeros(_OBS_DIM, np.float32), "image": np.zeros((84, 84, 3))}
    with pytest.raises(LcrlError) as e:
        policy.act(robo, TEXT, initial=robo)
    assert "2D tabletop" in str(e.value) and f"({_OBS_DIM},)" in str(e.value)

    # batch sizes: texts, initial observations and remembered first observations
    with pytest.raises(LcrlError, match="2 instructions for a batch of 3 observations"):
        policy.act(stack(obs), ["reach the red cube"] * 2, initial=stack(obs))
    with pytest.raises(LcrlError, match="2 instructions for one observation"):
        policy.act(obs[0], ["reach the red cube"] * 2, initial=obs[0])
    with pytest.raises(LcrlError, match="initial has batch size 2"):
        policy.act(stack(obs), TEXT, initial=stack(obs[:2]))
    policy.reset()
    policy.act(obs[0], TEXT)
    with pytest.raises(LcrlError, match=r"call policy.reset\(\)"):
        policy.act(stack(obs), TEXT)
    policy.reset()
    assert policy.act(stack(obs), TEXT).shape == (3, 2)
    policy.reset()


def test_load_errors(lang_ckpt, tmp_path):
    with pytest.raises(LcrlError, match="no checkpoint or run folder"):
        lcrl.load(tmp_path / "missing")
    with pytest.raises(LcrlError, match="neither a checkpoint"):
        lcrl.load(tmp_path)
    # the checkpoint was trained on wider observations than this environment gives
    with pytest.raises(LcrlError, match="does not match the environment"):
        lcrl.load(lang_ckpt, env_overrides={"displacements": False})


# --- lcrl act ------------------------------------------------------------------------------
def test_cli_act_shows_nearest_instructions(lang_ckpt, capsys):
    assert cli("act", str(lang_ckpt), "--instruction", "reach the red cube", "--episodes", "2") == 0
    out = capsys.readouterr().out
    near = re.findall(r"^  (\d\.\d{3})  (.+)$", out, re.M)
    assert len(near) == 3 and near[0] == ("1.000", "reach the red cube")
    assert re.search(r"^success \d\.\d\d over 2 episodes$", out, re.M)

    assert cli("act", str(lang_ckpt), "--instruction", "wiggle about", "--episodes", "1") == 0
    out = capsys.readouterr().out
    assert "cannot parse it" in out and "episode 0: " in out and "not checked" in out
    near = re.findall(r"^  (\d\.\d{3})  (.+)$", out, re.M)
    assert len(near) == 3 and all(float(s) < 0.99 for s, _ in near)

    # a family the environment cannot judge runs unchecked
    assert cli("act", str(lang_ckpt), "--instruction", "lift the red cube", "--episodes", "1") == 0
    assert "cannot check lift instructions" in capsys.readouterr().out


def test_cli_act_writes_a_gif_with_the_text(policy, lang_ckpt, tmp_path, capsys):
    from PIL import Image, ImageSequence

    text = "wiggle about"  # unparsed, so episode 0 starts from layout --seed exactly
    gif = tmp_path / "clips" / "act.gif"
    args = ("act", str(lang_ckpt), "--instruction", text, "--episodes", "1", "--seed", "3")
    assert cli(*args, "--video", str(gif), "--fps", "5") == 0
    out = capsys.readouterr().out
    steps = int(re.search(r"^episode 0: (\d+) steps", out, re.M).group(1))
    assert f"video: {gif}" in out

    env = policy.make_env(render=True)
    env.reset(seed=3)
    raw = upscale(env.render())
    with Image.open(gif) as im:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]
        durations = [f.info["duration"] for f in ImageSequence.Iterator(im)]
    first = frames[0].astype(int)
    assert first.shape == raw.shape and raw.shape[1] >= 384
    diff = np.abs(first - raw).mean(axis=(1, 2))
    assert diff[:12].mean() > 20  # the text band at the top
    assert diff[len(diff) // 4 :].mean() < 2  # the scene below it, unchanged
    # every frame of the episode plus the last one held 1 s (Pillow merges repeated frames)
    assert sum(durations) == (steps + 1 + 5) * 200


def test_annotated_episode_shows_the_outcome_on_its_last_frames(policy):
    env = policy.make_env(render=True)
    env.reset(seed=0)
    raw = env.render()
    frames = annotate_episode([raw, raw, raw], "reach the red cube", "success", hold=4)
    assert len(frames) == 3 + 4
    big = upscale(raw).astype(int)
    bottom = slice(big.shape[0] - 30, big.shape[0])
    assert np.array_equal(frames[0][bottom], big[bottom])  # no outcome before the end
    assert all(np.array_equal(f, frames[-1]) for f in frames[2:])
    band = frames[-1][bottom].astype(int)
    changed = np.abs(band - big[bottom]).sum(axis=-1) > 0
    assert changed.mean() > 0.5
    text_pixels = band[changed & (band.max(axis=-1) > 150)]
    assert len(text_pixels) and (text_pixels[:, 1] > text_pixels[:, 0]).all()  # green


def test_cli_act_errors(lang_ckpt, state_ckpt, tmp_path, capsys):
    for args, message in [
        (("--instruction", "x" * 300), "300 characters long"),
        (("--instruction", "  "), "give an --instruction"),
        (("--instruction", "reach the red cube", "--video", str(tmp_path / "a.avi")), ".gif"),
        (("--instruction", "reach the red cube", "--interactive"), "not both"),
        (("--instruction", "reach the red cube", "--hold", "-1"), "--hold"),
    ]:
        assert cli("act", str(lang_ckpt), *args) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert cli("act", str(tmp_path / "missing"), "--instruction", "reach the red cube") == 2
    assert "no checkpoint or run folder" in capsys.readouterr().err
    assert cli("act", str(state_ckpt), "--interactive") == 2
    assert "not trained with language goals" in capsys.readouterr().err


def test_cli_interactive_over_a_pipe(lang_ckpt, tmp_path):
    video = tmp_path / "inter.gif"
    lines = ["reach the red cube", "dance a jig", "y" * 250, "quit", "reach the blue cube"]
    command = ["act", str(lang_ckpt), "--interactive", "--episodes", "2", "--video", str(video)]
    proc = subprocess.run(
        [sys.executable, "-m", "train.commands.cli", *command],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "instruction>" not in out  # no prompt when the input is not a terminal
    assert "'reach the red cube' -> 'reach the red cube'" in out
    assert re.search(r"^success \d\.\d\d over 2 episodes$", out, re.M)
    assert "'dance a jig': the captioner cannot parse it" in out
    assert "error: instruction is 250 characters long" in out
    assert "'reach the blue cube' ->" not in out  # after quit
    assert out.count("nearest training instructions") == 2
    assert len(re.findall(r"^episode [01]: \d+ steps", out, re.M)) == 4
    assert out.rstrip().endswith("2 instructions run")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inter_001.gif", "inter_002.gif"]


def test_interactive_stops_at_an_empty_line_or_the_end(lang_ckpt, capsys, monkeypatch):
    import io

    monkeypatch.setattr(sys, "stdin", io.StringIO("go to the red cube\n\nreach the blue cube\n"))
    assert cli("act", str(lang_ckpt), "--interactive", "--episodes", "1") == 0
    out = capsys.readouterr().out
    assert "'go to the red cube' -> 'reach the red cube'" in out
    assert "'reach the blue cube' ->" not in out  # after the empty line
    monkeypatch.setattr(sys, "stdin", io.StringIO("go to the red cube"))  # no newline, then EOF
    assert cli("act", str(lang_ckpt), "--interactive", "--episodes", "1") == 0
    assert capsys.readouterr().out.rstrip().endswith("1 instructions run")


# --- the README example --------------------------------------------------------------------
def test_readme_example_runs(lang_ckpt, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", [str(EXAMPLE), str(lang_ckpt)])
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    out = capsys.readouterr().out
    assert re.search(r"^'go to the red cube': success \d\.\d\d over 3 episodes$", out, re.M)
    assert "batched actions: (2, 2)" in out
    assert len(re.findall(r"^[01]\.\d\d  reach the \w+ \w+$", out, re.M)) == 3


class SucceedEvery(gym.Wrapper):
    """Reports success on every ``n``-th step since the last success (the chain's
    mechanics are then exercised on a policy that has not learned yet)."""

    def __init__(self, env: gym.Env, n: int) -> None:
        super().__init__(env)
        self.n, self.count = n, 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.count += 1
        info = {**info, "is_success": self.count % self.n == 0}
        return obs, reward, terminated, truncated, info


def test_a_chain_of_typed_instructions_goes_on_in_the_same_scene(policy, tmp_path, capsys):
    from train.commands.act import ActSession
    from train.environments.tasks import find_language_wrapper

    made = policy.make_env(render=True)  # success faked under the time limit
    env = gym.wrappers.TimeLimit(SucceedEvery(made.env, 3), made._max_episode_steps)
    session = ActSession(policy, env, episodes=2, seed=0, fps=5, hold=0.4)
    gif = tmp_path / "chain.gif"
    chains = session.run_chain(["touch the red block", "reach the blue cube"], gif)
    out = capsys.readouterr().out
    assert chains == [[True, True], [True, True]]
    assert "chain 0: 'touch the red block' success in 3 steps, then 'reach the blue cube' " in out
    assert "2 in a row: 1.00 over 2 chains" in out
    lang = find_language_wrapper(env)
    assert lang.meaning.text == "reach the blue cube"  # switched, without a reset
    from PIL import Image, ImageSequence

    with Image.open(gif) as im:
        durations = [f.info["duration"] for f in ImageSequence.Iterator(im)]
    # per chain: 1 + 3 frames and a short pause, then 1 + 3 frames held 0.4 s
    assert sum(durations) == 2 * ((4 + 2) + (4 + 2)) * 200


def test_a_chain_that_fails_stops_and_is_counted(policy, capsys):
    from train.commands.act import ActSession

    made = policy.make_env()
    env = gym.wrappers.TimeLimit(SucceedEvery(made.env, 10**6), made._max_episode_steps)
    session = ActSession(policy, env, episodes=2, seed=0)
    assert session.run_chain(["reach the red cube", "reach the blue cube"]) == [[False], [False]]
    out = capsys.readouterr().out
    assert "1 in a row: 0.00 over 2 chains" in out and "then" not in out.split("chain 0:")[1]


def test_cli_chain_errors(lang_ckpt, capsys):
    for args, message in [
        (("--then", "reach the blue cube"), "--then continues an --instruction"),
        (("--instruction", "reach the red cube", "--then", "wiggle about"), "cannot parse"),
    ]:
        assert cli("act", str(lang_ckpt), *args) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert cli("act", str(lang_ckpt), "--instruction", "reach the red cube", "--then",
               "reach the blue cube", "--episodes", "1") == 0  # fmt: skip
    assert "1 in a row:" in capsys.readouterr().out

"""Detailed evaluation and reports: Wilson intervals, slot-value breakdowns, instruction
files, vector envs, chained instructions, ``lcrl eval --out``, ``lcrl report``.

Policies come from tiny training runs (300 steps, 32-unit networks) and from an oracle
that drives the pusher straight at the object its instruction names, so that chains
really continue after successes.
"""

from __future__ import annotations

import csv
import itertools
import json
import re
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from helpers import cli, error_line, tiny

from captioner.grammar import FAMILIES_2D, parse
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner
from captioner.scripted import ScriptedController2D
from captioner.splits import make_split
from envs.features import SlotFeatures, slot_layout
from envs.scene import OBJECT_KINDS
from envs.tabletop2d import MAX_STEP, Tabletop2DEnv
from lcrl.errors import LcrlError
from train.environments.tasks import make_env
from train.evaluation.eval_suite import (
    EpisodeResult,
    EpisodeSpec,
    EvalEpisodes,
    episode_seed,
    read_instruction_file,
    run_evaluation,
    summarise,
    wilson_interval,
)
from train.evaluation.report import compare_runs, load_evaluation, write_report
from train.policies.loading import load_policy
from train.training.loop import Trainer


# --- fixtures ------------------------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def lang_run(one_thread, tmp_path_factory) -> Path:
    """A finished 300-step lang2d-quick run (reach instructions, two objects)."""
    out = tmp_path_factory.mktemp("lang") / "run"
    Trainer(tiny("lang2d-quick", out)).run()
    return out


@pytest.fixture(scope="module")
def state_run(one_thread, tmp_path_factory) -> Path:
    """A finished 200-step state2d run (state goals)."""
    out = tmp_path_factory.mktemp("state") / "run"
    Trainer(tiny("state2d", out, total_steps=200)).run()
    return out


@pytest.fixture(scope="module")
def policy(lang_run):
    return load_policy(lang_run)


class ReachOracle:
    """Moves the pusher straight at the object its instruction names: the goal embedding
    is matched to the nearest text of the instruction table, parsed, and the object's
    slot gives its position relative to the pusher."""

    def __init__(self, task, env) -> None:
        self.texts = list(task.table)
        self.embeddings = np.asarray(task.embeddings)
        self.start, _, self.width, _ = slot_layout(env)
        self.calls = 0

    def act(self, obs, goal, deterministic=True, embedded=False):
        assert deterministic and embedded
        self.calls += 1
        out = []
        for row, g in zip(obs["observation"], np.asarray(goal), strict=True):
            meaning = parse(self.texts[int(np.argmax(self.embeddings @ g))])
            k = OBJECT_KINDS.index(meaning.obj)
            rel = row[self.start + k * self.width :][3:5]  # [x, y, present, rel x, rel y, ...]
            out.append(np.clip(rel / max(float(np.abs(rel).max()), 1e-6), -1.0, 1.0))
        return np.asarray(out, np.float32)


# --- statistics ----------------------------------------------------------------------------
def test_wilson_interval_values():
    z = 1.959963984540054
    # closed forms: k = 0 gives (0, z^2 / (n + z^2)); k = n mirrors it
    assert wilson_interval(0, 10) == (0.0, pytest.approx(z * z / (10 + z * z)))
    assert wilson_interval(10, 10) == (pytest.approx(10 / (10 + z * z)), 1.0)
    low, high = wilson_interval(5, 10)
    assert (low, high) == (pytest.approx(0.236593, abs=1e-6), pytest.approx(0.763407, abs=1e-6))
    assert wilson_interval(0, 0) == (0.0, 1.0)
    # the bounds are the two roots of (k/n - p)^2 = z^2 p (1 - p) / n
    for k, n in [(1, 3), (7, 20), (81, 263), (99, 100)]:
        low, high = wilson_interval(k, n)
        assert low < k / n < high
        for p in (low, high):
            assert (k / n - p) ** 2 == pytest.approx(z * z * p * (1 - p) / n, rel=1e-9)
    # narrower with more episodes, at the same rate
    assert np.diff(wilson_interval(50, 100)) < np.diff(wilson_interval(5, 10))
    with pytest.raises(LcrlError):
        wilson_interval(4, 3)


def _episode(index, text, success, steps=10, checked=True):
    meaning = parse(text) if checked else None
    slots = {}
    if meaning is not None:
        slots = {k: v for k, v in meaning.slots().items() if not k.startswith("target")}
        slots["object"] = f"{meaning.colour} {meaning.shape}"
    attempt = {
        "instruction": text,
        "slots": slots,
        "checked": checked,
        "success": success if checked else None,
        "steps": steps,
    }
    if attempt["success"]:
        attempt["steps_to_success"] = steps
    return EpisodeResult(index, index, [attempt], attempt["success"], steps, "")


def test_summary_breaks_down_by_family_and_slot_value():
    results = [
        _episode(0, "push the red cube left", True, 12),
        _episode(1, "push the red cylinder right", False, 50),
        _episode(2, "reach the blue cube", True, 4),
        _episode(3, "shove the red block to the left", True, 8),
        _episode(4, "put the red cube behind the blue cube", False, 50),
        _episode(5, "do a little dance", False, 50, checked=False),
    ]
    s = summarise(results)
    assert s["episodes"] == 6 and s["attempts"] == 5 and s["unchecked"] == 1
    assert s["successes"] == 3 and s["success"] == pytest.approx(0.6)
    assert s["ci"] == list(wilson_interval(3, 5))
    assert s["mean_steps_to_success"] == pytest.approx(8.0)  # (12 + 4 + 8) / 3
    fams = s["families"]
    assert set(fams) == {"push", "reach", "put"}
    assert (fams["push"]["episodes"], fams["push"]["successes"]) == (3, 2)
    assert fams["push"]["mean_steps_to_success"] == pytest.approx(10.0)
    assert fams["put"]["success"] == 0.0 and fams["put"]["mean_steps_to_success"] is None
    colour = s["slots"]["colour"]
    assert (colour["red"]["episodes"], colour["red"]["successes"]) == (4, 2)
    assert (colour["blue"]["episodes"], colour["blue"]["successes"]) == (1, 1)
    assert s["slots"]["shape"]["cylinder"]["success"] == 0.0
    assert set(s["slots"]["direction"]) == {"left", "right"}
    assert s["slots"]["direction"]["left"]["success"] == 1.0
    assert s["slots"]["relation"]["behind"]["episodes"] == 1
    # the reference object of put is not the object acted on
    assert "blue cube" not in s["family_object"]["put"]
    assert s["family_object"]["push"]["red cube"]["successes"] == 2
    # paraphrases are kept apart per instruction but share their meaning's slots
    assert s["instructions"]["shove the red block to the left"]["successes"] == 1
    assert s["unchecked_instructions"] == {"do a little dance": 1}


def test_combination_tables_list_failing_combinations_worst_first():
    from train.evaluation.report import _combinations_table, combinations

    seen = summarise(
        [
            _episode(0, "push the red cube left", True),
            _episode(1, "push the red cube right", True),
            _episode(2, "reach the blue cylinder", False),
            _episode(3, "touch the blue cylinder", True),
            _episode(4, "reach the red cube", False),
        ]
    )
    heldout = summarise([_episode(0, "reach the green cube", False)])
    rows = combinations({"train": seen, "heldout": heldout})
    assert [(r["set"], r["family"], r["object"], r["success"], r["fails"]) for r in rows] == [
        ("train", "reach", "red cube", 0.0, True),
        ("train", "reach", "blue cylinder", 0.5, False),
        ("train", "push", "red cube", 1.0, False),
        ("heldout", "reach", "green cube", 0.0, True),
    ]
    md = "\n".join(_combinations_table({"train": seen, "heldout": heldout}))
    assert "### train: 1 of 3 combinations fail" in md
    assert "### heldout: 1 of 1 combinations fail" in md
    assert "| reach | red cube | 0.00 | [0.00, 0.79] | 1 | yes |" in md


# --- instruction files ---------------------------------------------------------------------
def test_instruction_file_parsing(tmp_path):
    path = tmp_path / "mine.txt"
    path.write_text(
        "# my instructions\n"
        "\n"
        "reach the red cube\n"
        "   Touch the blue block,  please   # inline comment\n"
        "dance a little jig\n"
        "lift the green cube\n"
    )
    lines = read_instruction_file(path, FAMILIES_2D)
    assert [x.line for x in lines] == [3, 4, 5, 6]
    assert lines[1].text == "Touch the blue block, please"
    assert [x.checked for x in lines] == [True, True, False, False]
    assert "cannot parse" in lines[2].note
    assert "lift is not a family" in lines[3].note
    # without the env's families every parseable line is checked
    assert read_instruction_file(path)[3].checked


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("reach the red cube\npush the red cube → left\n", r"line 2: unsupported characters"),
        ("# only comments\n\n   \n", "has no instructions"),
        ("reach the red cube\n" + "go " * 80 + "\n", r"line 2: the instruction is \d+ characters"),
    ],
)
def test_instruction_file_errors(tmp_path, content, match):
    path = tmp_path / "bad.txt"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(LcrlError, match=match) as e:
        read_instruction_file(path)
    assert str(path) in str(e.value)


def test_instruction_file_canonical_parts(tmp_path):
    path = tmp_path / "mine.txt"
    path.write_text(
        "could you nudge the red block left\tpush the red cube left\n"
        "reach the red cube\n"
        "  go   to the green one\t  reach   the green cube # spaces collapse\n"
        "raise the green thing\tlift the green cube\n"
    )
    lines = read_instruction_file(path, FAMILIES_2D)
    assert [(x.text, x.canonical) for x in lines] == [
        ("could you nudge the red block left", "push the red cube left"),
        ("reach the red cube", ""),
        ("go to the green one", "reach the green cube"),
        ("raise the green thing", "lift the green cube"),
    ]
    assert [x.judged for x in lines[:3]] == [
        "push the red cube left",
        "reach the red cube",
        "reach the green cube",
    ]
    # a free text that does not parse is checked through its canonical part
    assert [x.checked for x in lines] == [True, True, True, False]
    assert "lift is not a family" in lines[3].note


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("reach the red cube\ngo there\tdance a jig\n", r"line 2: the canonical part 'dance a "),
        ("a\tb\tc\n", r"line 1: 2 tabs"),
        ("\treach the red cube\n", r"line 1: no free text before the tab"),
        ("reach the red cube\t  # nothing after\n", r"line 1: no canonical instruction after"),
        ("go\tpush the red cube → left\n", r"line 1: unsupported characters"),
    ],
)
def test_instruction_file_bad_canonical_parts(tmp_path, content, match):
    path = tmp_path / "bad.txt"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(LcrlError, match=match) as e:
        read_instruction_file(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


class MeaningOracle(ReachOracle):
    """A reach oracle that reads free text: each goal embedding is matched exactly to one
    of ``vectors``' texts, and ``means`` gives the instruction that text is taken for."""

    def __init__(self, task, env, vectors, means) -> None:
        super().__init__(task, env)
        self.texts = [means.get(t, t) for t in vectors]
        self.embeddings = np.stack([vectors[t] for t in vectors])
        self.read: set[str] = set()
        self.names = list(vectors)

    def act(self, obs, goal, deterministic=True, embedded=False):
        for g in np.asarray(goal):
            match = [i for i, e in enumerate(self.embeddings) if np.array_equal(e, g)]
            assert len(match) == 1
            self.read.add(self.names[match[0]])
        return super().act(obs, goal, deterministic, embedded)


def test_free_text_is_read_and_the_canonical_part_judged(policy, tmp_path):
    from train.evaluation.eval_suite import goal_vectors

    path = tmp_path / "mine.txt"
    path.write_text(
        "please touch the crimson box\treach the red cube\n"
        "please touch the scarlet box\treach the blue cube\n"
        "reach the red cube\n"
    )
    lines = read_instruction_file(path, FAMILIES_2D)
    texts = [x.text for x in lines]
    vectors = goal_vectors(policy.task, texts)
    # both free texts are taken for the red cube; only the first line means it
    means = {texts[0]: "reach the red cube", texts[1]: "reach the red cube"}
    oracle = MeaningOracle(policy.task, policy.env, vectors, means)
    res = run_evaluation(
        oracle, policy.task, policy.cfg, episodes=24, seed=0, sets=("custom",), instructions=lines
    )["custom"]
    assert oracle.read == set(texts)  # the policy read the free text, never the canonical
    per_line = res["instructions"]
    assert set(per_line) == set(texts)
    assert per_line[texts[0]]["success"] >= 0.75
    assert per_line[texts[1]]["success"] <= 0.25  # judged as reaching the blue cube
    assert per_line[texts[2]]["success"] >= 0.75
    firsts = [e["attempts"][0] for e in res["episode_results"]]
    assert firsts[1]["instruction"] == texts[1]
    assert firsts[1]["canonical"] == "reach the blue cube"
    assert firsts[1]["slots"]["object"] == "blue cube"
    assert "canonical" not in firsts[2]
    # the report's per-line table says what each line was judged as
    from train.evaluation.report import _breakdown

    md = "\n".join(_breakdown("custom", res))
    assert "| line | instruction | judged as | success |" in md
    assert "| 2 | please touch the scarlet box | reach the blue cube | " in md
    assert "| 3 | reach the red cube | reach the red cube | " in md


def test_instruction_file_missing_or_binary(tmp_path):
    with pytest.raises(LcrlError, match="not found"):
        read_instruction_file(tmp_path / "nope.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00reach")
    with pytest.raises(LcrlError, match="not UTF-8"):
        read_instruction_file(tmp_path / "bin.txt")


# --- switching instructions mid-episode ----------------------------------------------------
def _push_env():
    base = Tabletop2DEnv(num_objects=(2, 2))
    env = LanguageGoalWrapper(
        SlotFeatures(base, relative=True, displacement=True),
        split=make_split(0, FAMILIES_2D),
        families=FAMILIES_2D,
    )
    return base, env


def _run_scripted(env, base, steps=80):
    ctl = ScriptedController2D()
    for _ in range(steps):
        obs, _, term, _, info = env.step(ctl.act(env.meaning, env.s0, base.scene()))
        if term:
            return obs, info
    raise AssertionError("the scripted controller did not succeed")


def test_switch_instruction_judges_from_the_scene_at_the_switch():
    base, env = _push_env()
    cap = RuleCaptioner(FAMILIES_2D)
    for seed in range(20):  # a layout with room for two pushes left
        env.reset(seed=seed)
        name = base.scene().names[0]
        text = f"push the {name} left"
        env.reset(seed=seed, options={"instruction": text})
        x0 = base.scene().positions[0, 0]
        if cap.feasible(text, env.s0) and x0 > 0.0:
            break
    first_s0 = env.s0
    _, info = _run_scripted(env, base)
    assert info["is_success"]
    x1 = base.scene().positions[0, 0]

    assert env.switch_instruction(f"shove the {name} to the left") == (
        f"shove the {name} to the left"
    )
    assert env.meaning == parse(text) and env.s0 is not first_s0
    assert env.s0.positions[0, 0] == pytest.approx(x1)
    # the same meaning is no longer satisfied: it is judged from the scene at the switch
    assert not cap.satisfied(env.meaning, env.s0, base.scene())
    assert cap.satisfied(env.meaning, first_s0, base.scene())
    obs, info = _run_scripted(env, base)
    assert info["is_success"] and obs["instruction"] == f"shove the {name} to the left"
    x2 = base.scene().positions[0, 0]
    assert x2 < x1 < x0


def test_switch_instruction_draws_feasible_instructions():
    base, env = _push_env()
    cap = RuleCaptioner(FAMILIES_2D)
    with pytest.raises(LcrlError, match="reset"):
        env.switch_instruction()
    train = set(make_split(0, FAMILIES_2D).train)
    drawn = []
    for seed in range(10):
        env.reset(seed=seed)
        text = env.switch_instruction()
        assert text in train and env.instruction == text
        assert cap.feasible(text, base.scene())
        drawn.append(text)
    assert len(set(drawn)) > 1
    # from given candidates: only feasible ones; None (and nothing changes) when none is
    names = base.scene().names
    absent = next(f"{c} {s}" for c, s in OBJECT_KINDS if f"{c} {s}" not in names)
    before = (env.instruction, env.s0)
    assert env.switch_instruction(candidates=[f"reach the {absent}"]) is None
    assert (env.instruction, env.s0) == before
    got = env.switch_instruction(candidates=[f"reach the {absent}", f"reach the {names[0]}"])
    assert got == f"reach the {names[0]}"
    with pytest.raises(LcrlError, match="cannot parse"):
        env.switch_instruction("fly to the moon")


def _pushed(base: Tabletop2DEnv, env: SlotFeatures) -> tuple[dict, slice]:
    """The observation after the scripted controller pushed the scene's first object right
    for 40 steps from reset seed 3, and where that object's displacement sits in it."""
    start, _, width, dims = slot_layout(env)
    obs, _ = env.reset(seed=3)
    slot = base.scene().names[0].split()
    k = OBJECT_KINDS.index((slot[0], slot[1]))
    disp = slice(start + k * width + width - dims, start + (k + 1) * width)
    ctl, s0 = ScriptedController2D(), base.scene()
    meaning = parse(f"push the {slot[0]} {slot[1]} right")
    for _ in range(40):
        obs, *_ = env.step(ctl.act(meaning, s0, base.scene()))
    return obs, disp


def test_restart_displacements_measures_from_now():
    base = Tabletop2DEnv(num_objects=(2, 2))
    env = SlotFeatures(base, relative=True, displacement=True)
    with pytest.raises(LcrlError, match="reset"):
        env.restart_displacements()
    obs, disp = _pushed(base, env)
    moved = obs["observation"][disp].copy()
    assert np.abs(moved).max() > 0.02
    fresh = env.restart_displacements()
    np.testing.assert_array_equal(fresh[disp], 0.0)
    others = np.ones(len(fresh), bool)
    others[disp] = False
    np.testing.assert_array_equal(fresh[others], obs["observation"][others])
    obs, *_ = env.step(np.zeros(2, np.float32))  # still: displacements stay 0 from here
    np.testing.assert_allclose(obs["observation"][disp], 0.0, atol=1e-6)


class _WithTrueState(gym.ObservationWrapper):
    """A tabletop whose observation stands for an estimate, the true state beside it
    (``privileged``), as a camera policy's env gives both."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        spaces = env.observation_space.spaces
        self.observation_space = gym.spaces.Dict({**spaces, "privileged": spaces["observation"]})

    def observation(self, observation):
        return {**observation, "privileged": np.asarray(observation["observation"]).copy()}


def test_a_chained_instruction_restarts_the_true_states_displacements_too():
    base = Tabletop2DEnv(num_objects=(2, 2))
    env = SlotFeatures(_WithTrueState(base), relative=True, displacement=True)
    obs, disp = _pushed(base, env)
    assert np.abs(obs["privileged"][disp]).max() > 0.02
    fresh = env.restarted(obs)
    for key in ("observation", "privileged"):
        np.testing.assert_array_equal(fresh[key][disp], 0.0)
    np.testing.assert_array_equal(fresh["privileged"], fresh["observation"])
    later, *_ = env.step(np.zeros(2, np.float32))
    np.testing.assert_allclose(later["privileged"][disp], 0.0, atol=1e-6)


# --- evaluation runs -----------------------------------------------------------------------
def test_results_do_not_depend_on_num_envs(policy, tmp_path):
    path = tmp_path / "mine.txt"
    path.write_text("reach the red cube\ntouch the blue block\nwave hello\n")
    lines = read_instruction_file(path, FAMILIES_2D)
    runs = [
        run_evaluation(
            policy.agent,
            policy.task,
            policy.cfg,
            episodes=7,
            seed=2,
            sets=("train", "heldout"),
            instructions=lines,
            num_envs=n,
            vector=vector,
        )
        for n, vector in ((1, "sync"), (2, "sync"), (3, "async"))
    ]
    assert list(runs[0]) == ["train", "heldout", "custom"]
    for other in runs[1:]:
        assert other == runs[0]
    train = runs[0]["train"]["episode_results"]
    assert [e["seed"] for e in train] == [episode_seed(2, i) for i in range(7)]
    # each episode's instruction is the one the env draws for that seed
    env = policy.env
    for e in train:
        obs, _ = env.reset(seed=e["seed"])
        assert e["attempts"][0]["instruction"] == obs["instruction"]
    custom = runs[0]["custom"]
    assert [e["attempts"][0]["instruction"] for e in custom["episode_results"]] == [
        x.text for x in (lines * 3)[:7]
    ]
    assert custom["unchecked"] == 2 and custom["attempts"] == 5
    assert custom["unchecked_instructions"] == {"wave hello": 2}
    # another seed gives other layouts
    again = run_evaluation(policy.agent, policy.task, policy.cfg, 7, seed=3, sets=("train",))
    assert again["train"]["episode_results"] != train


def test_eval_episodes_chain_switches_restart_the_episode_reference(policy):
    cfg = policy.cfg.env
    specs = [EpisodeSpec(0, episode_seed(0, 0)), EpisodeSpec(1, episode_seed(0, 1))]
    env = EvalEpisodes(make_env(cfg, "train"), specs, True, cfg.max_episode_steps, chain=3)
    oracle = ReachOracle(policy.task, policy.env)
    vectors = dict(zip(policy.task.table, policy.task.embeddings, strict=True))
    start, count, width, dims = slot_layout(env)
    disp = np.zeros(len(env.observation_space["observation"].low), bool)
    for k in range(count):
        disp[start + (k + 1) * width - dims : start + (k + 1) * width] = True
    reference = make_env(cfg, "train")
    first = [reference.reset(seed=spec.seed)[0] for spec in specs]
    obs, info = env.reset()
    assert info["start"] and obs["instruction"] == first[0]["instruction"]
    switches, finished = 0, []
    while not env.idle:
        before = obs["instruction"]
        rows = {"observation": obs["observation"][None]}
        action = oracle.act(rows, vectors[obs["instruction"]][None], embedded=True)[0]
        obs, _, terminated, truncated, info = env.step(action)
        assert not terminated and not truncated
        if "episode" in info:
            finished.append(info["episode"])
            if len(finished) < len(specs):  # the next episode starts from its own seed
                assert info["start"] and obs["instruction"] == first[len(finished)]["instruction"]
                np.testing.assert_array_equal(
                    obs["observation"], first[len(finished)]["observation"]
                )
            else:
                assert info["idle"]
        elif info.get("start"):  # a switch inside the episode
            switches += 1
            assert obs["instruction"] != before and obs["instruction"] == env.lang.instruction
            np.testing.assert_array_equal(obs["observation"][disp], 0.0)
            scene = env.unwrapped.scene()
            np.testing.assert_array_equal(env.lang.s0.positions, scene.positions)
        assert len(finished) <= len(specs) and switches < 10
    assert [r.index for r in finished] == [0, 1]
    assert switches == sum(len(r.attempts) - 1 for r in finished) >= 1
    # idle envs return their last observation and do nothing
    last = obs
    obs, reward, _, _, info = env.step(np.ones(2, np.float32))
    assert info == {"idle": True} and reward == 0.0
    np.testing.assert_array_equal(obs["observation"], last["observation"])


def test_chains_with_an_oracle(policy):
    oracle = ReachOracle(policy.task, policy.env)
    kwargs = dict(episodes=8, seed=0, sets=("train",), num_envs=2)
    plain = run_evaluation(oracle, policy.task, policy.cfg, **kwargs)["train"]
    chained = run_evaluation(oracle, policy.task, policy.cfg, chain=3, **kwargs)["train"]
    c = chained["chain"]
    rates = [x["success"] for x in c["success"]]
    assert [x["length"] for x in c["success"]] == [1, 2, 3]
    assert all(a >= b for a, b in itertools.pairwise(rates))
    # the first instruction of a chain is the plain episode
    assert rates[0] == plain["success"] >= 0.75
    firsts = [e["attempts"][0] for e in chained["episode_results"]]
    assert firsts == [e["attempts"][0] for e in plain["episode_results"]]
    completed = []
    for e in chained["episode_results"]:
        attempts = e["attempts"]
        k = next((i for i, a in enumerate(attempts) if not a["success"]), len(attempts))
        completed.append(k)
        assert len(attempts) <= 3
        assert 1 <= sum(a["steps"] for a in attempts) == e["steps"]
        assert all(a["steps"] <= policy.cfg.env.max_episode_steps for a in attempts)
        if e["stop"] == "chain_complete":
            assert k == 3
        # after a success the next instruction names another object (the one reached
        # would already hold, so it is not feasible)
        for a, b in itertools.pairwise(attempts):
            assert a["success"] and a["instruction"] != b["instruction"]
    assert max(completed) == 3
    assert c["average_length"] == pytest.approx(np.mean(completed))
    assert rates == pytest.approx([np.mean([k >= n for k in completed]) for n in (1, 2, 3)])
    assert chained["attempts"] == sum(len(e["attempts"]) for e in chained["episode_results"])


class PusherOracle:
    """State goals (a pusher position): steps the pusher straight to the goal."""

    def act(self, obs, goal, deterministic=True, embedded=False):
        assert deterministic and not embedded
        delta = np.asarray(goal)[:, :2] - obs["observation"][:, :2]
        return np.clip(delta / MAX_STEP, -1.0, 1.0).astype(np.float32)


def test_goal_checkpoints_evaluate_one_set(state_run):
    p = load_policy(state_run)
    assert p.cfg.env.goal == "pusher"
    res = run_evaluation(p.agent, p.task, p.cfg, episodes=3, num_envs=2)
    assert list(res) == ["all"]
    assert res["all"]["episodes"] == 3 and set(res["all"]["families"]) == {"all"}
    limit = p.cfg.env.max_episode_steps
    assert all(e["steps"] == limit for e in res["all"]["episode_results"])
    # goal episodes run to the time limit; steps to success: when the goal was reached
    oracle = run_evaluation(PusherOracle(), p.task, p.cfg, episodes=4, num_envs=3)["all"]
    assert oracle["success"] == 1.0
    for e in oracle["episode_results"]:
        assert e["steps"] == limit and e["stop"] == "done"
        assert 1 <= e["attempts"][0]["steps_to_success"] < limit
    assert 1 <= oracle["mean_steps_to_success"] < limit
    with pytest.raises(LcrlError, match="language goals"):
        run_evaluation(p.agent, p.task, p.cfg, episodes=3, chain=2)


# --- the command line and reports ----------------------------------------------------------
def test_eval_cli_writes_json_markdown_and_figures(lang_run, tmp_path, capsys):
    ins = tmp_path / "mine.txt"
    ins.write_text("# two of mine\nreach the red cube\nwave hello\n")
    out = lang_run / "evals" / "chain2"
    args = ("eval", str(lang_run), "--episodes", "4", "--num-envs", "2", "--no-progress")
    assert cli(*args, "--instructions", str(ins), "--chain", "2", "--out", str(out)) == 0
    text = capsys.readouterr().out
    assert "(step 300)" in text
    for name in ("train", "heldout", "paraphrase", "custom"):
        line = rf"^{name}: success \d\.\d\d \(reach \d\.\d\d; \d+ instructions in 4 chains\)"
        assert re.search(line, text, re.M), name
    assert re.search(r"^  chains: 1:\d\.\d\d 2:\d\.\d\d; average length", text, re.M)

    doc = load_evaluation(out)
    assert doc["step"] == 300 and doc["run"] == str(lang_run.resolve())
    assert doc["settings"]["chain"] == 2 and doc["settings"]["episodes"] == 4
    assert "--chain 2" in doc["settings"]["command"]
    custom = doc["sets"]["custom"]
    assert [x["line"] for x in custom["file_instructions"]] == [2, 3]
    assert custom["unchecked_instructions"] == {"wave hello": 2}
    for res in doc["sets"].values():
        assert 0.0 <= res["ci"][0] <= res["ci"][1] <= 1.0
        assert len(res["chain"]["success"]) == 2
    md = (out / "eval.md").read_text()
    for part in ("## Success per set", "## Chains", "| family | reach |", "| colour |",
                 "Per line of the instruction file", "| 3 | wave hello | not checked",
                 "## Combinations (family x colour x shape, worst first)", "### heldout: ",
                 "(sets.png)", "(heatmap.png)", "(chain.png)", "(curves.png)"):  # fmt: skip
        assert part in md, part
    for png in ("sets.png", "heatmap.png", "chain.png", "curves.png"):
        assert (out / png).stat().st_size > 5000, png

    # the figures are reproducible: the same command, another number of envs
    again = tmp_path / "again.json"
    assert cli(*args[:-3], "--num-envs", "1", "--no-progress", "--instructions", str(ins),
               "--chain", "2", "--json", str(again)) == 0  # fmt: skip
    assert json.loads(again.read_text())["sets"] == doc["sets"]


def test_report_rebuilds_a_run_with_its_evaluations(lang_run, tmp_path, capsys):
    # a run folder of its own (the evaluation of the previous test may not exist)
    run = tmp_path / "run"
    shutil.copytree(lang_run, run, ignore=shutil.ignore_patterns("evals"))
    for name in ("report.md", "curves.png"):
        (run / name).unlink()
    assert cli("eval", str(run), "--episodes", "3", "--num-envs", "1", "--no-progress",
               "--sets", "heldout", "--out", str(run / "evals" / "final")) == 0  # fmt: skip
    capsys.readouterr()
    assert cli("report", str(run)) == 0
    assert f"report: {run / 'report.md'}" in capsys.readouterr().out
    report = (run / "report.md").read_text()
    assert (run / "curves.png").stat().st_size > 5000
    # the final table comes from the last row of eval.csv
    last = (run / "eval.csv").read_text().splitlines()[-1].split(",")
    assert f"| train | {float(last[2]):.2f} |" in report
    assert "Last evaluation in eval.csv (step 300)" in report
    assert "## Evaluations (lcrl eval --out)" in report
    assert "### final (checkpoint step 300)" in report
    assert "[evals/final/eval.md](evals/final/eval.md)" in report
    assert "![final](evals/final/sets.png)" in report
    assert re.search(r"\| heldout \| \d\.\d\d \| \[\d\.\d\d, \d\.\d\d\] \| 3 \|", report)

    # an interrupted run: logs stop early, no evaluation yet
    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(run / "config.json", cut)
    rows = (run / "progress.csv").read_text().splitlines()[:2]
    (cut / "progress.csv").write_text("\n".join(rows) + "\n")
    path = write_report(cut)
    text = path.read_text()
    step = int(rows[1].split(",")[0])
    assert f"The logs stop at step {step:,} of 300" in text and "| set |" not in text


def test_compare_runs(lang_run, state_run, tmp_path, capsys):
    # a copy of the language run, evaluated with lcrl eval into its folder
    lang = tmp_path / "copy" / "run"
    shutil.copytree(lang_run, lang, ignore=shutil.ignore_patterns("evals"))
    assert cli("eval", str(lang), "--episodes", "2", "--num-envs", "1", "--no-progress",
               "--sets", "heldout", "--out", str(lang / "evals" / "e")) == 0  # fmt: skip
    out = tmp_path / "cmp"
    assert cli("report", str(lang), str(state_run), "--out", str(out)) == 0
    assert "comparison:" in capsys.readouterr().out
    md = (out / "comparison.md").read_text()
    assert (out / "comparison.png").stat().st_size > 5000
    # both runs are called "run": their parent folders tell them apart
    la, lb = "copy/run", f"{state_run.parent.name}/run"
    rate = r"\d\.\d\d"
    row_a = rf"^\| {la} \| 2D tabletop reach \| sac \| 300 \| {rate} \| {rate} \| {rate} \|  \|$"
    row_b = rf"^\| {lb} \| 2D tabletop \(state goals\) \| sac \| 200 \|  \|  \|  \| {rate} \|$"
    assert re.search(row_a, md, re.M) and re.search(row_b, md, re.M)
    assert "| run | task | algo | steps | train (last eval) |" in md
    # the lcrl eval figures: the copy's heldout evaluation, nothing for the state run
    assert re.search(rf"^\| {la} \| 300 \| 2 \| {rate} \[{rate}, {rate}\] \|", md, re.M)
    assert f"| {lb} |  |  |  |  |" in md
    with pytest.raises(LcrlError, match="twice"):
        compare_runs([lang, lang], out)
    with pytest.raises(LcrlError, match="two or more"):
        compare_runs([lang], out)


def _seed_copy(run: Path, dest: Path, seed: int, train: float, heldout: float) -> Path:
    """A copy of ``run`` as if trained with another seed, whose last evaluation row has
    the given seen and held-out success."""
    shutil.copytree(run, dest, ignore=shutil.ignore_patterns("evals"))
    config = json.loads((dest / "config.json").read_text())
    config.update(seed=seed, out=str(dest))
    (dest / "config.json").write_text(json.dumps(config))
    with open(dest / "eval.csv") as f:
        rows = list(csv.DictReader(f))
    rows[-1].update({"train/success": str(train), "heldout/success": str(heldout)})
    with open(dest / "eval.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return dest


def test_compare_runs_shows_the_mean_and_spread_over_seeds(lang_run, state_run, tmp_path):
    from train.evaluation.report import seed_groups, spread

    seeds = [
        _seed_copy(lang_run, tmp_path / f"seed{k}", k, train, heldout)
        for k, (train, heldout) in enumerate([(0.8, 0.4), (0.9, 0.45), (1.0, 0.7)])
    ]
    configs = [json.loads((r / "config.json").read_text()) for r in [*seeds, state_run]]
    assert seed_groups(configs) == [[0, 1, 2], [3]]
    md = compare_runs([*seeds, state_run], tmp_path / "cmp").read_text()
    assert "## Across seeds" in md
    # train 0.8, 0.9, 1.0: mean 0.90, sample std 0.10; held-out / seen 0.5, 0.5, 0.7
    row = re.search(r"^\| seed0, seed1, seed2 \| last eval \|(.*)$", md, re.M)
    assert row is not None
    cells = [c.strip() for c in row.group(1).split("|")]
    header = re.search(r"^\| runs \| figures \|(.*)$", md, re.M).group(1)
    names = [c.strip() for c in header.split("|")]
    got = dict(zip(names, cells, strict=False))
    assert got["train"] == "0.90 ± 0.10 (0.80–1.00)"
    assert got["heldout"] == "0.52 ± 0.16 (0.40–0.70)"
    assert got["held-out / seen"] == "0.57 ± 0.12 (0.50–0.70)"
    assert "state" not in row.group(0)  # a run alone is not an experiment over seeds
    sp = spread([0.8, 0.9, 1.0])
    assert sp["mean"] == pytest.approx(0.9) and sp["std"] == pytest.approx(0.1)
    # runs of different configs only: no table
    md = compare_runs([seeds[0], state_run], tmp_path / "cmp2").read_text()
    assert "Across seeds" not in md


def test_cli_errors(lang_run, state_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    bad = tmp_path / "bad.txt"
    bad.write_text("reach the red cube\n\nreach the <red> cube\n")
    cases = [
        (("eval", str(tmp_path / "missing")), "missing"),
        (("eval", str(lang_run), "--instructions", str(bad)), "line 3: unsupported characters"),
        (("eval", str(lang_run), "--instructions", str(tmp_path / "no.txt")), "not found"),
        (("eval", str(lang_run), "--episodes", "0"), "--episodes must be positive"),
        (("eval", str(lang_run), "--num-envs", "-1"), "--num-envs"),
        (("eval", str(lang_run), "--vector", "threads"), "--vector"),
        (("eval", str(lang_run), "--sets", "custom"), "custom needs --instructions"),
        (("eval", str(lang_run), "--sets", "everything"), "unknown sets"),
        (("eval", str(state_run), "--chain", "3"), "language goals"),
        (("eval", str(state_run), "--instructions", str(tmp_path / "ok.txt")), "language goals"),
        (("report", str(tmp_path / "nowhere")), "nowhere is not a run folder: it does not exist"),
        (("report", str(tmp_path)), "not a run folder (no config.json)"),
        (("report", str(lang_run), str(state_run)), "needs --out"),
        (("report",), "give one run folder"),
    ]
    (tmp_path / "ok.txt").write_text("reach the red cube\n")
    (tmp_path / "afile").write_text("x")
    cases.append((("report", str(lang_run), "--out", str(tmp_path / "afile")), "is a file"))
    for args, message in cases:
        assert cli(*args) == 2, args
        err = capsys.readouterr().err
        line = error_line(err)
        assert line.startswith("lcrl: error:") and message in line, (args, line)
        assert "Traceback" not in err


def test_eval_steps_one_environment_per_core_other_processes_leave_free(monkeypatch):
    """On robosuite every environment is a process: beside a busy training run on two
    cores, ``lcrl eval`` starts one, not two."""
    from train.evaluation import eval_suite
    from train.runtime import machine

    for name in ("OMP_NUM_THREADS", machine.PROCESSES_VARIABLE):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(machine, "available_cores", lambda: 4)
    monkeypatch.setattr(machine, "busy_cores", lambda: 3)
    assert eval_suite.default_num_envs() == 1
    monkeypatch.setattr(machine, "busy_cores", lambda: 0)
    assert eval_suite.default_num_envs() == 4

"""Chains of instructions, hand-overs from the scripted controller and the family
curriculum of training episodes (``--explore.*``)."""

from __future__ import annotations

import dataclasses
import itertools
import json
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
from helpers import TINY_CLI, cli, error_line, tiny

from lcrl.errors import LcrlError
from train.configs.config import ExploreConfig
from train.environments.tasks import ScriptedActor, find_language_wrapper
from train.training.explore import Explorer
from train.training.loop import Trainer

#: lang2d observation: pusher x, y, then 8 slots of [x, y, present, x - pusher x,
#: y - pusher y, displacement x, displacement y].
SLOTS = (2, 8, 7)


def _slots(obs: np.ndarray) -> np.ndarray:
    start, count, width = SLOTS
    return np.asarray(obs[start:]).reshape(count, width)


def _collect(trainer: Trainer, episodes: int) -> list:
    """Collect until ``episodes`` are stored; the stored episodes (the loop's objects)."""
    seen: list = []
    store = trainer._store

    def keep(ep):
        seen.append(ep)
        store(ep)

    trainer._store = keep
    while len(seen) < episodes:
        trainer.collect_episode()
    return seen


def test_chained_episodes_go_on_in_the_scene_the_last_one_left(tmp_path):
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        scripted_fraction=1.0,  # the controller almost always succeeds: chains form
        scripted_noise=0.0,
        explore=ExploreConfig(chain=1.0, chain_length=3),
    )
    trainer = Trainer(cfg)
    try:
        eps = _collect(trainer, 12)
    finally:
        trainer.close()
    chained = [(a, b) for a, b in itertools.pairwise(eps) if b.chain_index > 0]
    assert chained, "no chain formed"
    assert trainer.explorer.chained == len(chained)
    for prev, ep in chained:
        assert ep.chain_index == prev.chain_index + 1 <= 2  # at most 3 in a row
        assert prev.succeeded
        last, first = _slots(prev.stored[-1]["observation"]), _slots(ep.stored[0]["observation"])
        # the same scene: positions and relative positions carry over ...
        np.testing.assert_allclose(first[:, :5], last[:, :5], atol=1e-6)
        pusher = prev.stored[-1]["observation"][:2], ep.stored[0]["observation"][:2]
        np.testing.assert_allclose(*pusher)
        # ... displacements restart at the switch, which is the episode's first observation
        assert np.all(first[:, 5:] == 0.0)
        np.testing.assert_array_equal(ep.stored[0]["initial"], ep.stored[0]["observation"])
        # a new instruction, judged from the scene at the switch: not achieved at once
        assert ep.goal != prev.goal or ep.t > 0
    # a chain never goes beyond its length: every third instruction in a row resets
    assert max(ep.chain_index for ep in eps) <= 2


def test_a_chained_episode_gets_the_whole_time_limit_again(tmp_path):
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        scripted_fraction=1.0,
        scripted_noise=0.0,
        explore=ExploreConfig(chain=1.0, chain_length=2),
    )
    trainer = Trainer(cfg)
    counted: list[tuple[int, int, int]] = []
    store = trainer._store

    def keep(ep):
        env = ep.env
        while not isinstance(env, gym.wrappers.TimeLimit):
            env = env.env
        counted.append((ep.chain_index, ep.t, env._elapsed_steps))
        store(ep)

    trainer._store = keep
    try:
        while sum(c > 0 for c, _, _ in counted) < 3:
            trainer.collect_episode()
    finally:
        trainer.close()
    # the time limit counts each instruction's own steps: it restarts at a switch
    assert all(elapsed == t for _, t, elapsed in counted)
    assert any(c > 0 and t > 0 for c, t, _ in counted)


def test_handover_episodes_begin_with_the_scripted_controller(tmp_path, monkeypatch):
    marker = np.full(2, 0.123, np.float32)
    monkeypatch.setattr(ScriptedActor, "act", lambda self, env, rng: marker.copy())
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        learning_starts=0,
        scripted_fraction=0.0,
        explore=ExploreConfig(handover=1.0, handover_steps=5),
    )
    trainer = Trainer(cfg)
    try:
        eps = _collect(trainer, 6)
    finally:
        trainer.close()
    for ep in eps:
        assert not ep.scripted and 1 <= ep.handover <= 5
        prefix = min(ep.handover, len(ep.actions))
        for a in ep.actions[:prefix]:
            np.testing.assert_array_equal(a, marker)  # the controller's steps ...
        for a in ep.actions[prefix:]:
            assert not np.array_equal(a, marker)  # ... then the policy's
        # the controller's steps are stored as demonstration steps (sac.demo_bc)
        assert ep.demo == [t < prefix for t in range(len(ep.actions))]
    flags = trainer.buffer.demo[trainer.buffer.valid]
    assert flags.sum() == sum(min(ep.handover, len(ep.actions)) for ep in eps)
    # they are not the policy's alone: the live success rate leaves them out
    assert not trainer.recent
    assert trainer.explorer.handovers == len(eps)
    assert trainer.explorer.columns()["handover_episodes"] == len(eps)


def _episode(family: str, succeeded: bool, scripted: bool = False, handover: int = 0):
    return SimpleNamespace(
        slot=0,
        obs={},
        succeeded=succeeded,
        chain_index=0,
        scripted=scripted,
        handover=handover,
        family=family,
    )


def test_the_curriculum_opens_the_next_family_on_live_success():
    cfg = ExploreConfig(curriculum=("reach", "push", "lift"), curriculum_window=4)
    ex = Explorer(cfg, ("reach", "push", "lift", "put"), np.random.default_rng(0))
    assert ex.families() == ("reach", "put")  # families it does not name are open
    for ok in (True, True, False):
        assert ex.finished(_episode("reach", ok), True, 10) is None
    # scripted and handed-over episodes do not count
    assert ex.finished(_episode("reach", True, scripted=True), True, 11) is None
    assert ex.finished(_episode("reach", True, handover=3), True, 11) is None
    assert ex.finished(_episode("reach", True), True, 12) == "push"  # 3 of the last 4
    assert ex.families() == ("reach", "push", "put")
    # now only the family opened last moves it on
    for _ in range(8):
        assert ex.finished(_episode("reach", True), True, 13) is None
    for _ in range(4):
        assert ex.finished(_episode("push", False), True, 14) is None
    assert ex.opened == 2
    state = ex.state_dict()
    again = Explorer(cfg, ("reach", "push", "lift", "put"), np.random.default_rng(0))
    again.load_state_dict(state)
    assert again.families() == ex.families() and again.openings == [(12, "push")]
    assert list(again.recent["push"]) == [0.0] * 4


def test_training_draws_only_open_families_and_checkpoints_the_curriculum(tmp_path):
    out = tmp_path / "run"
    cfg = tiny(
        "lang2d",
        out,
        total_steps=300,
        checkpoint_every=0,
        explore=ExploreConfig(curriculum=("push", "reach"), curriculum_window=1000),
    )
    trainer = Trainer(cfg)
    try:
        eps = _collect(trainer, 8)
        assert {ep.family for ep in eps} == {"push"}
        assert find_language_wrapper(trainer.envs[0]).families == ("reach", "push")
        trainer.explorer.opened = 2  # as if push had been learned
        trainer.explorer.apply(trainer.envs)
        eps = _collect(trainer, 30)
        assert {ep.family for ep in eps} == {"push", "reach"}
        trainer.save()
    finally:
        trainer.close()
    resumed = Trainer(tiny("lang2d", out, total_steps=600, resume=True))
    try:
        assert resumed.explorer.opened == 2
        assert {ep.family for ep in _collect(resumed, 30)} == {"push", "reach"}
    finally:
        resumed.close()


def test_failure_weights_follow_live_success_per_family():
    cfg = ExploreConfig(family_weights="failure", weight_floor=0.1, curriculum_window=4)
    ex = Explorer(cfg, ("reach", "push"), np.random.default_rng(0))
    assert ex.weights() == {"reach": 1.1, "push": 1.1}  # nothing tried yet
    for ok in (True, True, True, True, False):
        ex.finished(_episode("reach", ok), True, 1)
    ex.finished(_episode("push", False), True, 2)
    ex.finished(_episode("push", True, handover=5), True, 2)  # not counted
    ex.finished(_episode("push", True, scripted=True), True, 2)  # not counted
    w = ex.weights()
    assert w["reach"] == pytest.approx(0.1 + 0.25)  # the last 4: 3 of 4 succeeded
    assert w["push"] == pytest.approx(1.1)
    assert ex.columns()["weight_push"] == pytest.approx(1.1)
    again = Explorer(cfg, ("reach", "push"), np.random.default_rng(0))
    again.load_state_dict(ex.state_dict())
    assert again.weights() == pytest.approx(w)


def test_training_draws_families_by_failure(tmp_path):
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        total_steps=2000,
        checkpoint_every=0,
        explore=ExploreConfig(family_weights="failure", weight_floor=0.05),
    )
    trainer = Trainer(cfg)
    try:
        ex = trainer.explorer
        ex.recent["reach"].extend([1.0] * ex.recent["reach"].maxlen)  # reach mastered
        ex.recent["push"].extend([0.0] * ex.recent["push"].maxlen)  # push failing
        trainer.explorer.apply(trainer.envs)
        wrapper = find_language_wrapper(trainer.envs[0])

        def push_share(draws: int = 200) -> float:
            families = []
            for _ in range(draws):
                wrapper.reset()
                families.append(wrapper.meaning.family)
            return families.count("push") / draws

        assert push_share() > 0.85  # 1.05 / 1.1 expected, against 0.5 uniformly
        wrapper.weigh_families(None)
        assert 0.35 < push_share() < 0.65
        with pytest.raises(LcrlError, match="family weights"):
            wrapper.weigh_families({"push": -1.0})
    finally:
        trainer.close()


def test_draw_from_refuses_families_the_env_does_not_have(tmp_path):
    trainer = Trainer(tiny("lang2d", tmp_path / "run"))
    try:
        with pytest.raises(LcrlError, match="families"):
            find_language_wrapper(trainer.envs[0]).draw_from(("lift",))
    finally:
        trainer.close()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--explore.chain", "1.5"], "explore.chain must be in [0, 1]"),
        (["--explore.curriculum", "reach", "lift"], "explore.curriculum names lift"),
        (["--explore.curriculum", "reach", "reach"], "names a family twice"),
        (["--explore.chain", "0.5", "--explore.chain-length", "1"], "chain_length"),
        (["--explore.family-weights", "hard"], "explore.family_weights must be"),
        (["--explore.weight-floor", "2"], "explore.weight_floor must be in [0, 1]"),
        (["--explore.prelude", "2"], "explore.prelude must be in [0, 1]"),
        (
            ["--explore.prelude", "0.5", "--explore.prelude-families", "lift"],
            "explore.prelude_families names lift",
        ),
        (["--explore.prelude", "0.5", "--explore.prelude-steps", "0"], "prelude_steps"),
    ],
)
def test_bad_explore_settings_are_one_line_errors(tmp_path, capsys, args, message):
    status = cli("train", "lang2d", "--out", str(tmp_path / "r"), *args)
    assert status != 0
    assert message in error_line(capsys.readouterr().err)


def test_explore_needs_language_goals(tmp_path, capsys):
    status = cli("train", "state2d", "--out", str(tmp_path / "r"), "--explore.chain", "0.5")
    assert status != 0
    assert "train language goals" in error_line(capsys.readouterr().err)


def test_prelude_episodes_start_where_the_teacher_left_the_scene(tmp_path, monkeypatch):
    import train.training.collection as loop  # where episodes begin
    from captioner.rule import RuleCaptioner

    switches: list[tuple] = []
    original = loop.switch_in_place

    def spy(env, obs):
        wrapper = find_language_wrapper(env)
        before = (wrapper.meaning, wrapper.s0, env.unwrapped.scene())
        out = original(env, obs)
        switches.append((*before, wrapper.meaning, out))
        return out

    monkeypatch.setattr(loop, "switch_in_place", spy)
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        learning_starts=10_000,  # random actions: the teacher alone leaves the scenes
        scripted_fraction=0.0,
        explore=ExploreConfig(prelude=1.0, prelude_families=("reach",), prelude_steps=60),
    )
    cfg.env = dataclasses.replace(cfg.env, families=("push",))
    trainer = Trainer(cfg)
    try:
        eps = _collect(trainer, 8)
    finally:
        trainer.close()
    explorer = trainer.explorer
    assert explorer.preludes == len(eps) == len(switches)
    assert explorer.prelude_successes >= 0.75 * len(eps)
    # the teacher's steps are not stored and not counted in the run's steps
    assert explorer.prelude_steps > 0
    assert trainer.step == sum(len(ep.actions) for ep in eps)
    rule = RuleCaptioner()
    succeeded = 0
    for ep, (meaning, s0, scene, new, out) in zip(eps, switches, strict=True):
        assert meaning.family == "reach" and new.family == "push"
        assert out is not None and ep.goal is not None
        succeeded += rule.satisfied(meaning, s0, scene)
        # the policy's episode starts in the scene the teacher left, judged from there
        np.testing.assert_array_equal(ep.stored[0]["observation"], out["observation"])
        assert out["instruction"] == new.text or rule.parse(out["instruction"]) == new
    assert succeeded == explorer.prelude_successes
    cols = explorer.columns()
    assert cols["prelude_episodes"] == len(eps) and cols["prelude_steps"] == explorer.prelude_steps
    # the policy's own success from where the preludes left the scene
    assert all(ep.prelude for ep in eps) and len(explorer.prelude_recent) == len(eps)
    assert cols["prelude_policy_success"] == np.mean([ep.succeeded for ep in eps])
    # checkpoints keep the counts
    again = Explorer(cfg.explore, ("push",), np.random.default_rng(0))
    again.load_state_dict(explorer.state_dict())
    assert again.columns() == cols


def test_a_resumed_run_takes_the_explore_options_given(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["--out", str(out), *TINY_CLI, "--learning-starts", "50"]
    assert cli("train", "lang2d", *base, "--explore.chain", "0.5", "--total-steps", "100") == 0
    capsys.readouterr()
    status = cli(
        "train", "lang2d", "--out", str(out), "--resume", "--total-steps", "200",
        "--explore.prelude", "1.0", "--explore.prelude-families", "reach",
        "--batch-size", "64", "--no-progress",
    )  # fmt: skip
    assert status == 0
    err = capsys.readouterr().err
    assert "--batch-size 64" in err and "explore" not in err  # only batch-size is ignored
    cfg = json.loads((out / "config.json").read_text())
    # the given explore fields replace the saved ones; the others stay as saved
    assert cfg["explore"]["prelude"] == 1.0 and cfg["explore"]["prelude_families"] == ["reach"]
    assert cfg["explore"]["chain"] == 0.5 and cfg["batch_size"] == 32
    rows = (out / "progress.csv").read_text().splitlines()
    last = dict(zip(rows[0].split(","), rows[-1].split(","), strict=True))
    assert float(last["prelude_episodes"]) > 0

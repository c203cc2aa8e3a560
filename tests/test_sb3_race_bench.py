"""The time-to-success race against Stable-Baselines3: how a run's time is read, and the
commands each library runs (no training here; the benchmark itself trains)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pytest

from benchmarks import time_to_success_vs_sb3 as race


def _args(**over):
    ns = dict(
        steps=0,
        eval_every=1000,
        eval_episodes=50,
        threads=1,
        threshold=0.9,
        lcrl_options="",
    )
    ns.update(over)
    return argparse.Namespace(**ns)


def test_time_to_success_is_the_first_evaluation_at_the_threshold():
    rows = [
        {"step": 1000, "all/success": 0.2, "train_s": 10.0},
        {"step": 2000, "all/success": 0.9, "train_s": 21.0},
        {"step": 3000, "all/success": 0.5, "train_s": 33.0},
        {"step": 4000, "all/success": 1.0, "train_s": 44.0},
    ]
    assert race.time_to_success(rows, 0.9) == (21.0, True)
    assert race.time_to_success(rows, 0.95) == (44.0, True)


def test_a_run_that_never_gets_there_counts_its_whole_training_time():
    rows = [
        {"step": 1000, "train/success": 0.1, "train_s": 10.0},
        {"step": 2000, "train/success": 0.4, "train_s": 20.5},
    ]
    assert race.time_to_success(rows, 0.9) == (20.5, False)
    seconds, reached = race.time_to_success([], 0.9)
    assert math.isnan(seconds) and not reached


def test_lcrl_runs_its_preset_as_shipped_in_float32_on_the_shared_schedule():
    cmd = race.lcrl_command("tabletop2d", 2, _args(), Path("OUT"))
    i = cmd.index("train")
    assert cmd[i + 1] == "state2d"
    for flag, value in [
        ("--seed", "2"),
        ("--total-steps", "20000"),
        ("--eval-every", "1000"),
        ("--eval-episodes", "50"),
        ("--torch-threads", "1"),
        ("--agent.precision", "fp32"),
    ]:
        assert cmd[cmd.index(flag) + 1] == value
    fast = race.lcrl_command("fetch_reach", 0, _args(lcrl_options="--collect.envs 8"), Path("O"))
    assert fast[fast.index("train") + 1] == "fetch-reach"
    assert fast[-2:] == ["--collect.envs", "8"]


def test_sb3_gets_twice_lcrls_budget_and_the_same_threads_and_evaluations():
    cmd = race.sb3_command("fetch_reach", 1, _args(threads=2), Path("OUT"))
    assert cmd[cmd.index("--sb3-run") + 1 : cmd.index("--sb3-run") + 3] == ["fetch_reach", "1"]
    assert cmd[cmd.index("--sb3-steps") + 1] == "20000"
    assert cmd[cmd.index("--threads") + 1] == "2"
    assert cmd[cmd.index("--eval-episodes") + 1] == "50"
    assert race.SB3_SETTINGS["net_arch"] == [256, 256]  # lcrl's default networks


def test_sb3_trains_on_the_same_tabletop_lcrl_does():
    env = race.make_gym_env("tabletop2d")
    try:
        obs, _ = env.reset(seed=0)
        assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
        assert env.spec.max_episode_steps == 50
        same = env.unwrapped.compute_reward(obs["desired_goal"], obs["desired_goal"], None)
        assert same == 1.0
    finally:
        env.close()


@pytest.mark.parametrize("library", ["lcrl", "sb3"])
def test_a_finished_run_is_kept(tmp_path, library):
    assert not race.finished(library, tmp_path)
    (tmp_path / ("report.md" if library == "lcrl" else "done.json")).write_text("x")
    assert race.finished(library, tmp_path)


def _finished(folder: Path, library: str, rows: list[tuple[int, float, float]]) -> None:
    folder.mkdir(parents=True)
    key = "all/success" if library == "lcrl" else "train/success"
    lines = [f"step,{key},train_s"] + [f"{a},{b},{c}" for a, b, c in rows]
    (folder / "eval.csv").write_text("\n".join(lines) + "\n")
    (folder / ("report.md" if library == "lcrl" else "done.json")).write_text("{}")


def test_the_report_takes_medians_over_seeds_and_marks_a_missed_run_as_a_bound(
    tmp_path, monkeypatch
):
    for seed, (lcrl_s, sb3_s) in enumerate([(10.0, 40.0), (20.0, 50.0), (30.0, 90.0)]):
        _finished(
            tmp_path / f"fetch_reach-lcrl-s{seed}", "lcrl", [(1000, 0.5, 5), (2000, 1.0, lcrl_s)]
        )
        sb3_rows = [(1000, 0.2, 20), (2000, 0.95 if seed < 2 else 0.5, sb3_s)]
        _finished(tmp_path / f"fetch_reach-sb3-s{seed}", "sb3", sb3_rows)
    written = {}

    def publish(name, payload, title, body, fig=None, tried=()):
        written.update(name=name, payload=payload, body=body)

    monkeypatch.setattr(race, "publish", publish)
    monkeypatch.setattr(race, "run_logged", lambda *a: pytest.fail("a finished run ran again"))
    argv = ["--envs", "fetch_reach", "--work", str(tmp_path), "--libraries", "lcrl", "sb3"]
    assert race.main(argv) == 0
    head = written["payload"]["headline"]
    assert head["lcrl_s_fetch_reach"] == 20.0 and head["sb3_s_fetch_reach"] == 50.0
    assert head["ratio_fetch_reach"] == 2.5
    assert head["ratio_fetch_reach_exact"] is False  # SB3's seed 2 never got there
    assert written["payload"]["reached"] == {"ratio_fetch_reach": False}
    assert "90+" in written["body"] and "NOT reached" in written["body"]


def test_the_headline_peer_is_sb3s_faster_configuration_with_lcrls_networks(tmp_path, monkeypatch):
    times = {"lcrl": 10.0, "sb3": 60.0, "sb3-raw": 40.0, "sb3-zoo": 20.0}
    for lib, seconds in times.items():
        for seed in (0, 1, 2):
            rows = [(1000, 0.1, 1.0), (2000, 0.95, seconds + seed)]
            _finished(tmp_path / f"tabletop2d-{lib}-s{seed}", lib.split("-")[0], rows)
    written = {}
    monkeypatch.setattr(race, "publish", lambda name, payload, *a, **k: written.update(payload))
    assert race.main(["--envs", "tabletop2d", "--work", str(tmp_path)]) == 0
    head = written["headline"]
    # SB3 without VecNormalize was the faster like-for-like peer; the Zoo's smaller networks
    # are reported beside it but never taken as the headline peer
    assert head["ratio_tabletop2d_peer"] == "sb3-raw"
    assert head["ratio_tabletop2d"] == head["ratio_tabletop2d_sb3_raw"] == round(41 / 11, 2)
    assert head["ratio_tabletop2d_sb3_zoo"] == round(21 / 11, 2)
    assert head["ratio_tabletop2d_exact"] is True

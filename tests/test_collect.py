"""Collection from several environments at once (``collect.envs``) and the thread default."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import cli, error_line, tiny

from train.configs.config import CollectionConfig
from train.runtime.machine import default_threads
from train.training.loop import Trainer


def _buffer_after(tmp_path, envs: int, episodes: int, **overrides) -> dict[str, np.ndarray]:
    cfg = tiny(
        "lang2d",
        tmp_path / f"envs{envs}",
        collect=CollectionConfig(envs=envs),
        **{"total_steps": 10_000, "learning_starts": 10_000, **overrides},
    )
    trainer = Trainer(cfg)
    try:
        while trainer.episodes < episodes:
            trainer.advance()
        assert trainer.episodes == episodes
        assert trainer.step == trainer.buffer.size  # every step stored
        return trainer.buffer.arrays()
    finally:
        trainer.close()


def test_several_envs_store_the_episodes_of_one(tmp_path):
    """Episodes are reset with their index's seed and stored in index order: with the
    scripted controller acting (no noise, so no random draw interleaves), 3 environments
    stepped together store exactly what one environment stores."""
    one = _buffer_after(tmp_path, 1, 6, scripted_fraction=1.0, scripted_noise=0.0)
    three = _buffer_after(tmp_path, 3, 6, scripted_fraction=1.0, scripted_noise=0.0)
    assert one.keys() == three.keys()
    for key in one:
        np.testing.assert_array_equal(one[key], three[key], err_msg=key)


def test_several_envs_train_with_batched_acting(tmp_path):
    """Past learning_starts the policy acts for all environments at once and updates
    follow every environment's steps; the run ends at its budget with every episode
    stored whole."""
    cfg = tiny("lang2d", tmp_path / "run", collect=CollectionConfig(envs=4), total_steps=400)
    trainer = Trainer(cfg)
    try:
        trainer.advance()  # the first 4 episodes: no updates before anything is stored
        first, before = trainer.step, trainer.agent.updates
        while trainer.step < cfg.total_steps:
            trainer.advance()
        assert trainer.step >= cfg.total_steps and trainer.episodes % 4 == 0
        assert trainer.buffer.size == trainer.step
        # updates_per_step 1: one update per environment step once learning has started
        assert trainer.agent.updates - before == trainer.step - max(first, cfg.learning_starts)
        assert trainer.agent.acts > 0
    finally:
        trainer.close()


def test_bad_collect_settings_are_one_line_errors(tmp_path, capsys):
    status = cli("train", "lang2d-quick", "--out", str(tmp_path / "r"), "--collect.envs", "0")
    assert status != 0
    assert error_line(capsys.readouterr().err) == (
        "lcrl: error: collect.envs must be at least 1, got 0"
    )


@pytest.mark.parametrize(
    ("omp", "processes", "cores", "expected"),
    [("", "", 2, 2), ("", "2", 2, 1), ("", "3", 2, 1), ("1", "", 2, 1), ("", "2", 8, 4)],
)
def test_default_threads_never_oversubscribe(monkeypatch, omp, processes, cores, expected):
    monkeypatch.setenv("OMP_NUM_THREADS", omp)
    monkeypatch.setenv("LCRL_PROCESSES", processes)
    monkeypatch.setattr("train.runtime.machine.available_cores", lambda: cores)
    monkeypatch.setattr("train.runtime.machine.busy_cores", lambda: 0)
    assert default_threads() == expected


@pytest.mark.parametrize(("busy", "expected"), [(0, 2), (1, 1), (2, 1), (5, 1)])
def test_default_threads_leave_the_cores_other_processes_keep_busy(monkeypatch, busy, expected):
    """Two threads beside another busy process on two cores collapse several times: a
    run started on a busy machine takes the cores left."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("LCRL_PROCESSES", raising=False)
    monkeypatch.setattr("train.runtime.machine.available_cores", lambda: 2)
    monkeypatch.setattr("train.runtime.machine.busy_cores", lambda: busy)
    assert default_threads() == expected


def test_local_ray_workers_take_their_share_of_the_cores(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("LCRL_PROCESSES", raising=False)
    monkeypatch.setattr("train.runtime.machine.available_cores", lambda: 8)
    monkeypatch.setattr("train.runtime.machine.busy_cores", lambda: 0)
    assert default_threads(helpers=2) == 2
    assert default_threads(helpers=7) == 1


@pytest.mark.parametrize(
    ("busy_jiffies", "own_s", "expected"),
    [(0, 0.0, 0), (100, 0.0, 1), (200, 0.0, 2), (100, 1.0, 0)],
)
def test_busy_cores_count_what_others_use_now_not_the_load_average(
    monkeypatch, busy_jiffies, own_s, expected
):
    """Busy cores are read from the CPU time spent while watching, less this process's
    own: a load average left by a run that has just ended does not count."""
    import types

    from train.runtime import machine as m

    samples = iter([(1000, 5000), (1000 + busy_jiffies, 5200)])
    monkeypatch.setattr(m, "_cpu_jiffies", lambda: next(samples))
    monkeypatch.setattr(m.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(m.os, "getloadavg", lambda: (2.0, 2.0, 2.0))
    monkeypatch.setattr(m.time, "sleep", lambda s: None)
    times = iter([(0.0, 0.0, 0.0), (own_s, 0.0, 1.0)])

    def fake_times():
        user, system, elapsed = next(times)
        return types.SimpleNamespace(user=user, system=system, elapsed=elapsed)

    monkeypatch.setattr(m.os, "times", fake_times)
    assert m.busy_cores() == expected

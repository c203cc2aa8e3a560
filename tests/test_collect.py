"""Collection from several environments at once (``collect.envs``) and the thread default."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
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
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        collect=CollectionConfig(envs=4),
        total_steps=400,
        updates_per_step=1.0,  # the preset ships 0.5; this counts one update per step
    )
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


class _Load:
    """A fake machine for :class:`ThreadWatcher`: 2 cores, this process busy on
    ``own`` cores and other processes on ``others``, advanced by :meth:`tick` seconds."""

    def __init__(self) -> None:
        self.t, self.busy, self.total, self.own_s = 0.0, 0, 0, 0.0
        self.own, self.others = 2.0, 0.0

    def tick(self, seconds: float) -> None:
        jiffies = 100 * seconds * 2  # 2 cores, 100 jiffies a second each
        self.busy += round(jiffies * (self.own + self.others) / 2)
        self.total += round(jiffies)
        self.own_s += self.own * seconds
        self.t += seconds

    def times(self):
        import types

        return types.SimpleNamespace(user=self.own_s, system=0.0, elapsed=self.t)


def test_the_thread_watcher_gives_a_core_back_when_another_run_starts_and_takes_it_again(
    monkeypatch,
):
    """A run that took both cores drops to one thread when another busy process starts
    beside it, and takes two again when that process ends, each at the next reading."""
    from train.runtime import machine as m

    monkeypatch.setattr(m, "available_cores", lambda: 2)
    monkeypatch.setattr(m.os, "cpu_count", lambda: 2)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        load = _Load()
        watch = m.ThreadWatcher(
            every_s=20, clock=lambda: load.t, jiffies=lambda: (load.busy, load.total),
            times=load.times,
        )  # fmt: skip
        load.tick(30)
        assert watch.poll() is None and torch.get_num_threads() == 2  # alone: both cores
        load.others, load.own = 1.0, 1.0  # another run starts
        load.tick(5)
        assert watch.poll() is None  # not yet time to read again
        load.tick(20)
        assert watch.poll() == 1 and torch.get_num_threads() == 1
        load.tick(25)
        assert watch.poll() is None and torch.get_num_threads() == 1  # it still runs
        load.others = 0.0  # it ended
        load.tick(25)
        assert watch.poll() == 2 and torch.get_num_threads() == 2
        assert watch.changes == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("threads", "omp", "processes", "watched"),
    [(0, "", "", True), (1, "", "", False), (0, "1", "", False), (0, "", "2", False)],
)
def test_only_a_run_that_chooses_its_own_threads_has_them_chosen_again(
    monkeypatch, threads, omp, processes, watched
):
    from train.runtime.machine import automatic_threads

    monkeypatch.setenv("OMP_NUM_THREADS", omp)
    monkeypatch.setenv("LCRL_PROCESSES", processes)
    assert automatic_threads(threads) is watched


def test_a_run_that_chooses_its_threads_watches_them_and_logs_them(tmp_path, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("LCRL_PROCESSES", raising=False)
    before = torch.get_num_threads()
    try:
        chosen = Trainer(tiny("state2d", tmp_path / "auto", torch_threads=0))
        fixed = Trainer(tiny("state2d", tmp_path / "fixed", torch_threads=1))
        try:
            assert chosen.thread_watch is not None and fixed.thread_watch is None
            fixed.run()
        finally:
            chosen.close()
            fixed.close()
        with (tmp_path / "fixed" / "progress.csv").open() as f:
            rows = list(csv.DictReader(f))
        assert rows and {r["torch_threads"] for r in rows} == {"1"}
    finally:
        torch.set_num_threads(before)

"""Ray rollout workers (``--collect.backend ray``): 2 local workers at a tiny size."""

from __future__ import annotations

import os
import signal
import sys

import pytest
from helpers import cli, error_line, tiny

from train.configs.config import CollectionConfig
from train.training.loop import Trainer

ray = pytest.importorskip("ray")


def _config(tmp_path, **collect):
    return tiny(
        "lang2d-quick",
        tmp_path / "run",
        total_steps=400,
        learning_starts=100,
        collect=CollectionConfig(backend="ray", workers=2, sync_every=20, **collect),
    )


def _check_buffer(trainer: Trainer) -> None:
    """Every stored episode is whole: the buffer holds exactly the steps counted."""
    buf = trainer.buffer
    assert buf.size == trainer.step
    assert trainer.episodes >= 1


def test_two_local_workers_train_a_tiny_run(tmp_path):
    trainer = Trainer(_config(tmp_path))
    try:
        while trainer.step < trainer.cfg.total_steps:
            trainer.advance()
        _check_buffer(trainer)
        assert trainer.agent.updates > 0
        assert trainer.remote.version >= 1  # the workers got the learner's weights
        assert trainer.remote.restarts == 0
    finally:
        trainer.close()
    assert not ray.is_initialized()  # the local Ray it started is shut down


def test_a_killed_worker_is_restarted_and_loses_no_stored_episode(tmp_path, capsys):
    trainer = Trainer(_config(tmp_path))
    trainer.open_outputs()
    try:
        trainer.advance()
        stored, steps = trainer.episodes, trainer.step
        victim = trainer.remote.slots[0]
        os.kill(ray.get(victim.actor.pid.remote()), signal.SIGKILL)
        while trainer.remote.restarts == 0:
            trainer.advance()
        assert trainer.episodes >= stored and trainer.step >= steps
        _check_buffer(trainer)  # the killed worker's episode was not half stored
        while trainer.step < trainer.cfg.total_steps:
            trainer.advance()
        _check_buffer(trainer)
        assert trainer.remote.restarts == 1 and trainer.remote.dropped == 1
        trainer.log()
    finally:
        trainer.close()
    assert "a Ray rollout worker died" in capsys.readouterr().err
    header = (tmp_path / "run" / "progress.csv").read_text().splitlines()[0]
    assert "worker_restarts" in header.split(",")


def test_ray_backend_without_ray_names_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    status = cli(
        "train",
        "lang2d-quick",
        "--out",
        str(tmp_path / "r"),
        "--collect.backend",
        "ray",
        "--total-steps",
        "200",
        "--no-progress",
    )
    assert status != 0
    assert "pip install 'lcrl[ray]'" in error_line(capsys.readouterr().err)

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


def test_workers_on_another_node_of_a_cluster_survive_that_node_dying(tmp_path, capsys):
    """A real two-node Ray cluster on this machine: the learner's node (the head) and a
    worker node. With ``--collect.placement other-nodes`` the rollout workers run on the
    worker node; when that node dies mid-run, its workers are replaced beside the learner,
    their episodes in flight are dropped, never half stored, and the run goes on."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False}
    )
    try:
        node = cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        cfg = _config(tmp_path, address=cluster.address, placement="other-nodes")
        cfg.collect.workers = 1  # one worker process: a cluster at the smallest size
        trainer = Trainer(cfg)
        trainer.open_outputs()
        try:
            head = ray.get_runtime_context().get_node_id()
            assert trainer.remote.nodes() == [node.node_id] != [head]
            while trainer.step < 150:
                trainer.advance()
            _check_buffer(trainer)
            stored = trainer.episodes
            cluster.remove_node(node)
            while trainer.remote.restarts < 1:
                trainer.advance()
            assert trainer.episodes >= stored
            _check_buffer(trainer)
            while trainer.step < trainer.cfg.total_steps:
                trainer.advance()
            _check_buffer(trainer)
            assert trainer.remote.nodes() == [head]
            assert trainer.agent.updates > 0 and trainer.remote.dropped >= 1
            trainer.log()
        finally:
            trainer.close()
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
    err = capsys.readouterr().err
    assert "a Ray rollout worker died" in err and "no other Ray node is alive" in err


def test_an_unknown_placement_is_a_clear_error():
    from lcrl.errors import LcrlError

    with pytest.raises(LcrlError, match=r"collect\.placement must be one of"):
        CollectionConfig(backend="ray", placement="moon").validate()

"""Rollout workers on Ray: actors that collect whole captioned episodes for one learner.

``lcrl train PRESET --collect.backend ray --collect.workers N`` starts ``N`` Ray actors
(the Ape-X pattern). Each holds a training environment, a copy of the policy and the
task's captioner; asked for episode number ``i``, it resets with that episode's seed,
acts (randomly before ``learning_starts``, by the scripted controller for the scripted
share, by its policy copy otherwise), captions the finished episode and returns it
whole. The learner owns the replay buffer and the relabelling: it stores each returned
episode, runs the updates due for its steps, sends the workers its weights every
``collect.sync_every`` updates, and asks the worker for another episode, so collection
overlaps learning.

Ray is an optional extra (``pip install 'lcrl[ray]'``). ``ray.init()`` starts a local Ray
on this machine unless ``collect.address`` names a cluster (``ray start --head`` on the
head node, ``ray start --address HEAD:6379`` on the others, lcrl installed on each).

What the asynchronous mode gives up: the order in which episodes arrive, and so the run,
depends on timing (a seed no longer fixes it), and the policy that acted an episode may
be up to ``sync_every`` updates older than the learner's. ``--resume`` continues from the
checkpoint's buffer and weights; episodes in flight when the run stopped are dropped.

A worker that dies (its process killed, its node lost) is replaced by a new actor with
the learner's current weights; the episode it was collecting is dropped, never half
stored, because episodes only ever arrive whole. Restarts are counted in progress.csv
(``worker_restarts``) and reported on the console.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from typing import Any

import numpy as np

from lcrl.errors import LcrlError

INSTALL_HINT = (
    "--collect.backend ray needs Ray, an optional extra: pip install 'lcrl[ray]' "
    "(or pip install ray)"
)


def import_ray() -> Any:
    """The ``ray`` module, or an :class:`LcrlError` naming the extra to install."""
    try:
        import ray
    except ImportError:
        raise LcrlError(INSTALL_HINT) from None
    return ray


class RolloutWorker:
    """What one Ray actor runs: an environment, a policy copy and the task's captioner.

    Args:
        config: the run's config (:func:`train.configs.config.config_to_dict`).
        table: the learner's instruction table and how many are training instructions
            (None for goals that are not instructions), so that ids agree.
        embeddings: the table's text embeddings, so that no worker loads the encoder.
    """

    def __init__(
        self,
        config: dict[str, Any],
        table: tuple[list[str], int] | None,
        embeddings: np.ndarray | None = None,
    ) -> None:
        from train.configs.config import config_from_dict
        from train.environments.tasks import ScriptedActor, make_env
        from train.evaluation.evaluate import build_agent, build_task
        from train.runtime.machine import set_threads

        set_threads(1)  # a worker steps one env and acts for it: one thread is plenty
        cfg = config_from_dict(config)
        self.cfg = cfg
        self.env = make_env(cfg.env, "train", training=True)
        self.task = build_task(cfg, self.env, table=table, embeddings=embeddings)
        problem = self.task.problem()
        algo = cfg.resolved_algo(problem.discrete)
        self.agent = build_agent(algo, problem, cfg, self.task.goal_space.embed, self.env)
        self.scripted = (
            ScriptedActor(cfg.env, self.task, cfg.scripted_noise)
            if cfg.scripted_fraction > 0
            else None
        )
        self.version = -1

    def set_weights(self, weights: dict[str, Any], version: int) -> int:
        """Load the learner's weights (``{module name: state dict}``)."""
        modules = self.agent.modules()
        for name, state in weights.items():
            modules[name].load_state_dict(state)
        self.version = version
        return version

    def collect(self, index: int, random: bool, task_id: int | None = None) -> dict[str, Any]:
        """Collect and caption training episode number ``index``.

        Args:
            index: the episode's number (its seed and random draws follow from it).
            random: act with uniformly random actions (before ``learning_starts``).
            task_id: the task of a run with a task set.

        Returns:
            ``episode`` (what the buffer stores), ``steps``, ``succeeded``, ``scripted``,
            ``task_id``, ``sim_error``, ``index``, ``version`` (the weights it acted with)
            and ``seconds``.
        """
        from train.training.episodes import begin_episode, episode_record, step_episode

        t0 = time.perf_counter()
        cfg, task = self.cfg, self.task
        ep = begin_episode(cfg, task, self.env, index, self.scripted, task_id)
        while not ep.done and ep.t < cfg.total_steps:
            if ep.scripted:
                ep.action = self.scripted.act(self.env, ep.scripted_rng)
            elif random:
                if ep.t % cfg.random_action_repeat == 0:
                    ep.random_action = task.random_action(ep.rng)
                ep.action = ep.random_action
            else:
                obs = {k: v[None] for k, v in ep.stored[-1].items()}
                ep.action = self.agent.act(obs, np.asarray([ep.goal]))[0]
            step_episode(task, ep)
        return {
            "episode": episode_record(task, ep),
            "steps": ep.t,
            "succeeded": ep.succeeded,
            "scripted": ep.scripted,
            "task_id": task_id,
            "sim_error": bool(ep.info.get("sim_error", False)),
            "index": index,
            "version": self.version,
            "seconds": time.perf_counter() - t0,
        }

    def pid(self) -> int:
        """The worker's process id (tests kill it)."""
        import os

        return os.getpid()

    def node(self) -> str:
        """The id of the Ray node the worker runs on."""
        import ray

        return ray.get_runtime_context().get_node_id()


@dataclasses.dataclass
class _Slot:
    actor: Any
    future: Any = None
    index: int = -1


class RayCollector:
    """The learner's side: the actors, their requests in flight, weight syncs, restarts.

    Args:
        cfg: the run's config (``collect.workers``, ``collect.address``).
        table: the learner's instruction table (see :class:`RolloutWorker`).
        weights: the learner's initial weights.
        embeddings: the table's text embeddings.
    """

    def __init__(
        self,
        cfg: Any,
        table: tuple[list[str], int] | None,
        weights: dict[str, Any],
        embeddings: np.ndarray | None = None,
    ) -> None:
        from train.configs.config import config_to_dict

        ray = import_ray()
        self.ray = ray
        self.cfg = cfg
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {
                "include_dashboard": False,
                "log_to_driver": True,
                "configure_logging": False,
            }
            if cfg.collect.address:
                kwargs["address"] = cfg.collect.address
            else:
                kwargs["num_cpus"] = cfg.collect.workers
            try:
                ray.init(**kwargs)
            except (ConnectionError, RuntimeError, ValueError) as e:
                where = cfg.collect.address or "a local Ray"
                raise LcrlError(f"cannot start {where}: {e}") from None
            self._started = True
        else:
            self._started = False
        self._remote = ray.remote(num_cpus=1, max_restarts=0)(RolloutWorker)
        self._config = config_to_dict(cfg)
        self._table = table
        self._embeddings = None if embeddings is None else ray.put(np.asarray(embeddings))
        self.version = 0
        self._weights = ray.put(weights)
        self._placed = 0
        self._alone = False  # placement other-nodes found no other node alive
        self.slots = [self._new_slot() for _ in range(cfg.collect.workers)]
        self.restarts = 0
        self.dropped = 0

    def _options(self) -> dict[str, Any]:
        """Ray options that place the next worker (``collect.placement``): ``other-nodes``
        pins it to a live node other than the learner's, round robin; with none alive it
        runs beside the learner, said once on the console."""
        if self.cfg.collect.placement != "other-nodes":
            return {}
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        here = self.ray.get_runtime_context().get_node_id()
        others = sorted(
            n["NodeID"]
            for n in self.ray.nodes()
            if n.get("Alive") and n["NodeID"] != here and n.get("Resources", {}).get("CPU", 0)
        )
        if not others:
            if not self._alone:
                print(
                    "lcrl: no other Ray node is alive: rollout workers run beside the learner",
                    file=sys.stderr,
                    flush=True,
                )
            self._alone = True
            return {}
        self._alone = False
        node = others[self._placed % len(others)]
        self._placed += 1
        return {"scheduling_strategy": NodeAffinitySchedulingStrategy(node_id=node, soft=False)}

    def _new_slot(self) -> _Slot:
        options = self._options()
        remote = self._remote.options(**options) if options else self._remote
        actor = remote.remote(self._config, self._table, self._embeddings)
        actor.set_weights.remote(self._weights, self.version)
        return _Slot(actor)

    def nodes(self) -> list[str]:
        """The Ray node of each worker."""
        return self.ray.get([slot.actor.node.remote() for slot in self.slots])

    def sync(self, weights: dict[str, Any]) -> None:
        """Send the learner's weights to every worker (applied before its next episode)."""
        self.version += 1
        self._weights = self.ray.put(weights)
        for slot in self.slots:
            slot.actor.set_weights.remote(self._weights, self.version)

    def submit(self, slot: _Slot, index: int, random: bool, task_id: int | None) -> None:
        """Ask a worker for episode ``index``."""
        slot.index = index
        slot.future = slot.actor.collect.remote(index, random, task_id)

    def idle(self) -> list[_Slot]:
        """Workers with no request in flight."""
        return [s for s in self.slots if s.future is None]

    def next(self, timeout: float | None = None) -> tuple[_Slot, dict[str, Any] | None]:
        """Wait for the first finished request; returns its worker and the episode, or
        ``None`` for a worker that died (it is replaced, its episode dropped)."""
        ray = self.ray
        pending = {s.future: s for s in self.slots if s.future is not None}
        if not pending:
            raise LcrlError("no episode requested from the Ray workers")
        done, _ = ray.wait(list(pending), num_returns=1, timeout=timeout)
        if not done:
            raise LcrlError(f"no Ray worker returned an episode within {timeout} s")
        slot = pending[done[0]]
        slot.future = None
        try:
            return slot, ray.get(done[0])
        except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as e:
            self.restarts += 1
            self.dropped += 1
            print(
                f"lcrl: a Ray rollout worker died ({type(e).__name__}); its episode "
                f"{slot.index} is dropped and the worker restarted ({self.restarts} so far)",
                file=sys.stderr,
                flush=True,
            )
            fresh = self._new_slot()
            slot.actor = fresh.actor
            return slot, None

    def close(self) -> None:
        """Stop the actors (and the local Ray this collector started)."""
        for slot in self.slots:
            with contextlib.suppress(Exception):  # an actor already gone
                self.ray.kill(slot.actor)
        self.slots = []
        if self._started and self.ray.is_initialized():
            self.ray.shutdown()

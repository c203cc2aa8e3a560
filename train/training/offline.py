"""Offline goal-conditioned RL with hindsight relabelling (``lcrl train PRESET --offline FILE``).

A fixed HDF5 dataset (``lcrl demos record``, random play with ``--actor random``,
scripted or policy episodes, a robomimic / LIBERO import) is fed into the run's own
:class:`lcrl.buffer.HindsightReplayBuffer`, episode by episode, through the same labelling
as online training (the rule captioner on the stored privileged scene, the goal space's
achieved goals); the buffer relabels at sample time exactly as online. No environment is
stepped except to evaluate. ``total_steps`` and the ``*_every`` settings count gradient
updates.

Learners (``--algo``):

* ``td3``: TD3+BC (:attr:`lcrl.algos.td3.TD3Config.bc_alpha`), the critic learning the
  relabelled sparse rewards and the actor kept near the dataset's actions;
* ``crl``: contrastive RL (:mod:`lcrl.algos.crl`), the critic classifying which
  relabelled goal a state-action pair goes on to achieve, the actor climbing it with a BC
  term (:attr:`lcrl.algos.crl.CRLConfig.bc_alpha`);
* ``bc``: goal-conditioned behavioural cloning (GCBC): the actor regresses the dataset's
  action on the rows whose goal was relabelled in hindsight (a goal the episode went on to
  achieve). Rows keeping the recorded instruction are not cloned: random play rarely did
  what it was told.

``--buffer.k 0 --buffer.random-fraction 0`` turns relabelling off (the recorded
instructions only): the baseline that hindsight relabelling is measured against.

A file that fits in the buffer (``buffer.capacity`` observation slots) is loaded once. A
larger one is streamed: the buffer is filled, then the following episodes replace the
oldest at the pace that brings the whole file through the buffer once by the end of the
run, so memory stays at the buffer's size.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lcrl.buffer import batch_rows
from lcrl.errors import LcrlError
from train.configs.config import OFFLINE_ALGOS, TrainConfig
from train.training.demos import buffer_episode, check_dataset
from train.training.loop import Trainer

#: Gradient updates per :meth:`OfflineTrainer.advance` (one unit of rollback).
CHUNK = 100


class OfflineTrainer(Trainer):
    """Learns from ``cfg.offline`` through the replay buffer; evaluates like any run."""

    unit = "update"
    refills_buffer = True

    def check_algo(self, cfg: TrainConfig) -> None:
        """Only the learners of :data:`OFFLINE_ALGOS` train offline."""
        if cfg.algo not in OFFLINE_ALGOS:  # (TrainConfig.validate refuses the others first)
            raise LcrlError(f"--offline trains with --algo {' or '.join(OFFLINE_ALGOS)}")
        if cfg.algo == "bc" and cfg.buffer.k == 0:
            raise LcrlError(
                "--offline --algo bc (GCBC) clones the rows relabelled in hindsight: it needs "
                "--buffer.k above 0"
            )
        if cfg.collect.backend != "local":
            raise LcrlError("--offline steps no environment: leave --collect.backend local")
        if cfg.sequential.stages:
            raise LcrlError("--offline and --sequential.stages do not go together")
        if cfg.relabel.learned:
            raise LcrlError(
                "--offline labels what each step achieved with the rule captioner on the "
                "stored scene; learned relabelling (--relabel.*) is for online runs"
            )

    def __init__(self, cfg: TrainConfig) -> None:
        from lcrl.demos import DemoDataset

        if not cfg.offline:
            raise LcrlError("OfflineTrainer needs --offline FILE")
        self.data = DemoDataset(cfg.offline)
        try:
            super().__init__(cfg)
            self.agent.offline = True  # TD3+BC's actor loss
            self._check_data()
        except BaseException:
            self.data.close()
            raise

    #: The next episode of the file to feed, and the observation slots fed so far.
    cursor = 0
    fed = 0
    #: The buffer rng state of a resumed checkpoint, set once the buffer is refilled.
    _resumed_rng: Any = None

    @property
    def streamed(self) -> bool:
        """The file does not fit in the buffer: it streams through it."""
        return self.data.num_observations > self.buffer.capacity

    # --- the dataset -------------------------------------------------------------------
    def _check_data(self) -> None:
        """The file has what this run's observations, actions and goals need."""
        check_dataset(self.data, self.cfg.offline, self.problem, self.task, self.env)

    def _episode(self, e: int) -> dict[str, Any]:
        """Episode ``e`` of the file as the buffer stores it, labelled by the task."""
        return buffer_episode(self.data, e, self.cfg.offline, self.task, self.env)

    def _feed(self, slots: float, observe: bool = True) -> None:
        """Add episodes of the file (in order, cycling) until ``slots`` have been fed; with
        ``observe`` off (refilling after a resume) the normalisers, restored from the
        checkpoint, have seen them already."""
        lengths = self.data.episode_lengths
        while self.fed < slots:
            e = self.cursor % self.data.num_episodes
            episode = self._episode(e)
            self.buffer.add_episode(episode)
            if observe:
                self.agent.observe(episode["obs"], episode.get("achieved_goal"))
            self.fed += int(lengths[e]) + 1
            self.cursor += 1
            self.episodes = self.cursor

    def _target(self, step: int) -> float:
        """Slots fed by the time ``step`` updates are done: a buffer-full first, then the
        rest of the file at an even pace over the run."""
        n, cap = self.data.num_observations, self.buffer.capacity
        return min(n, cap) + max(n - cap, 0) * step / max(self.cfg.total_steps, 1)

    def _fill(self) -> None:
        """The buffer at the current step (the first fill, or again after resuming)."""
        from tqdm import tqdm

        target = self._target(self.step)
        if self.fed >= target:
            return
        with tqdm(
            total=int(target),
            disable=not self.cfg.progress,
            desc="loading",
            unit="slot",
            leave=False,
        ) as bar:
            while self.fed < target:
                before = self.fed
                self._feed(min(target, self.fed + 5_000), observe=self._resumed_rng is None)
                bar.update(self.fed - before)
        if self.buffer.size == 0:
            raise LcrlError(f"{self.cfg.offline} gave no transition to learn from")
        if self.buffer.k and self.buffer._relabelable_indices().size == 0:
            raise LcrlError(
                f"nothing in {self.cfg.offline} achieves a training instruction, so hindsight "
                "relabelling has no goal to give"
            )

    def begin(self) -> None:
        """Load the file (or its first buffer-full; on resume, what had been fed) and say
        what the run learns from."""
        self._fill()
        if self._resumed_rng is not None:
            self.buffer.rng.bit_generator.state = self._resumed_rng
            self._resumed_rng = None
        what = "streamed through" if self.streamed else "loaded into"
        print(
            f"offline {self.algo} on {self.cfg.offline}: {self.data.num_episodes} episodes, "
            f"{self.data.num_steps} steps {what} the buffer ({self.buffer.size} transitions, "
            f"relabel k={self.cfg.buffer.k}); no environment step except to evaluate",
            flush=True,
        )

    # --- the loop ----------------------------------------------------------------------
    def advance(self) -> None:
        """:data:`CHUNK` updates (fewer at the end), streaming the file as they go."""
        self._start = self.snapshot()
        n = min(CHUNK, self.cfg.total_steps - self.step)
        if self.streamed:
            self._feed(self._target(self.step + n))
        self._update(n)
        self.step += n
        self._start = None

    def _update(self, n: int) -> None:
        if self.algo != "bc":
            super()._update(n)
            return
        for _ in range(n):  # GCBC: clone the rows with a goal achieved later
            batch = self.buffer.sample(self.cfg.batch_size)
            keep = np.flatnonzero(batch.relabelled)
            if keep.size == 0:
                continue
            for k, v in self.agent.update(batch_rows(batch, keep)).items():
                self._metrics[k] = self._metrics.get(k, 0.0) + v
            self._metric_count += 1

    def postfix(self) -> str:
        """Dataset passes and the last evaluation."""
        passes = self.fed / max(self.data.num_observations, 1)
        return f"data {passes:.2f}x " + super(Trainer, self).postfix()

    def restore(self, ckpt: Any) -> None:
        """Weights and counters of a checkpoint; :meth:`begin` refills the buffer from the
        file in the same order, so the resumed run samples what the uninterrupted one
        would."""
        super().restore(ckpt)
        self.cursor = self.fed = 0
        self._resumed_rng = self.buffer.rng.bit_generator.state

    def close(self) -> None:
        super().close()
        data = getattr(self, "data", None)
        if data is not None:
            data.close()

"""Training data and its configuration: observation pairs from a caption dataset, the
training config, label onsets and the sampler of positives and negatives."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from captioner.dataset import CaptionDataset
from captioner.grammar import FAMILIES, Instruction
from captioner.learned.models import CaptionModelConfig
from captioner.learned.vocabulary import MODELS
from lcrl.errors import LcrlError

# --------------------------------------------------------------------------- data


def _observations(data: CaptionDataset, episodes: np.ndarray) -> np.ndarray:
    """Observation indices of the given episodes."""
    if len(episodes) == 0:
        return np.zeros(0, np.int64)
    starts, ends = data.episode_start[episodes], data.episode_start[episodes + 1]
    return np.concatenate([np.arange(a, b) for a, b in zip(starts, ends, strict=True)])


class _Pairs:
    """Frame pairs of a caption dataset, in memory, with the episode split."""

    def __init__(
        self,
        data: CaptionDataset,
        val_fraction: float,
        seed: int,
        perceive: Any = None,
    ) -> None:
        self.data = data
        self.proprio = data.proprio.astype(np.float32)
        # uint8 frames (N, H, W, 3), or perception's estimates of them, computed once (read
        # from the file a batch at a time)
        self.frames = data.frames[:] if perceive is None else perceive(data.frames, self.proprio)
        n_ep = data.num_episodes
        perm = np.random.default_rng(seed).permutation(n_ep)
        n_val = max(1, round(val_fraction * n_ep)) if n_ep > 1 else 0
        self.val_episodes = np.sort(perm[:n_val])
        self.train_episodes = np.sort(perm[n_val:])
        self.seen = np.asarray([s == "train" for s in data.instruction_set])
        self.first = data.first_of(np.arange(data.num_observations))
        p = self.proprio
        self.p_mean = p.mean(0) if len(p) else np.zeros(p.shape[1], np.float32)
        self.p_std = p.std(0).clip(1e-3) if len(p) else np.ones(p.shape[1], np.float32)

    def observations(self, episodes: np.ndarray) -> np.ndarray:
        return _observations(self.data, episodes)

    def tensors(self, idx: np.ndarray, device: torch.device) -> tuple[torch.Tensor, ...]:
        first = self.first[idx]
        p0 = (self.proprio[first] - self.p_mean) / self.p_std
        p = (self.proprio[idx] - self.p_mean) / self.p_std
        return (
            torch.as_tensor(self.frames[first], device=device),
            torch.as_tensor(self.frames[idx], device=device),
            torch.as_tensor(p0, device=device),
            torch.as_tensor(p, device=device),
        )


# --------------------------------------------------------------------------- training


@dataclass
class CaptionTrainConfig:
    """Train the learned captioner and reward model on a caption dataset
    (``lcrl caption train``)."""

    data: str = "data/captions-lang2d.h5"
    """The caption dataset (``lcrl caption collect``)."""
    out: str = "runs/captioner"
    """Checkpoint folder to write."""
    models: tuple[str, ...] = MODELS
    """Which models to train: ``captioner``, ``reward`` or both."""
    steps: int = 3000
    """Gradient steps per model."""
    batch_size: int = 64
    """Frame pairs per step."""
    lr: float = 3e-4
    """Adam learning rate."""
    none_fraction: float = 0.25
    """Captioner: fraction of each batch drawn from observations that achieved nothing
    (target ``<none>``)."""
    augment_pad: int = 4
    """Random-shift augmentation of training frame pairs: pad by this many edge pixels and
    crop back at a random offset, the same for both frames of a pair (0: off)."""
    hard_negative_fraction: float = 0.5
    """Reward model: fraction of the negatives that share the object or the family of an
    instruction the observation satisfies (the rest are any other instruction)."""
    near_negative_fraction: float = 0.0
    """Reward model: fraction of the negatives that are near misses: the same instruction
    on an observation of the same episode, within ``near_window`` steps, that does not
    satisfy it (where the achievement begins or ends). Captioner: the same fraction of its
    ``<none>`` targets are observations that achieved nothing within ``near_window``
    steps of one that did. They teach the boundary of an achievement, where relabelling
    in a training loop asks most."""
    near_window: int = 10
    """Steps around an achievement that count as near (``near_negative_fraction``)."""
    onset_delay: tuple[str, ...] = ()
    """``FAMILY=STEPS`` entries (e.g. ``push=1``): an instruction of the family counts as
    achieved, for both models, only from STEPS steps after the rule captioner first accepts
    it (its first accepted steps become near misses). A model whose boundary is blurred by
    perception error then judges the achievement a little after the rule does, not before:
    a push it rewards has moved its object far enough."""
    val_fraction: float = 0.2
    """Episodes held out of training for evaluation."""
    model: CaptionModelConfig = field(default_factory=CaptionModelConfig)
    """Network sizes."""
    text_model: str = ""
    """Frozen text encoder for the reward model (empty: the packaged all-MiniLM-L6-v2)."""
    perception: str = ""
    """With ``--model.encoder perception``: the perception model (``lcrl perception
    train --out``) whose estimated object slots both models read (frozen; saved with
    them)."""
    device: str = "cpu"
    """``cpu`` or ``cuda``."""
    seed: int = 0
    """Seed of the episode split, sampling and initialisation."""
    threads: int = 0
    """Torch CPU threads (0: leave torch's default)."""
    overwrite: bool = False
    """Replace an existing checkpoint in ``out``."""
    progress: bool = True
    """Show progress bars."""

    def validate(self) -> None:
        bad = [m for m in self.models if m not in MODELS]
        if bad or not self.models:
            raise LcrlError(f"models must be among {MODELS}, got {self.models}")
        self.model.validate()
        for name in ("steps", "batch_size"):
            if getattr(self, name) <= 0:
                raise LcrlError(f"{name} must be positive")
        if self.augment_pad < 0:
            raise LcrlError("augment_pad must be >= 0")
        if self.near_window < 1:
            raise LcrlError("near_window must be at least 1")
        onset_delays(self.onset_delay)  # raises on a bad entry
        for name in ("none_fraction", "hard_negative_fraction", "near_negative_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise LcrlError(f"{name} must be in [0, 1]")
        if not 0.0 < self.val_fraction < 1.0:
            raise LcrlError("val_fraction must be in (0, 1)")
        if self.device not in ("cpu", "cuda") and not self.device.startswith("cuda:"):
            raise LcrlError(f"device must be cpu or cuda, got {self.device!r}")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise LcrlError("device cuda was asked for but torch sees no CUDA device")


def onset_delays(entries: Sequence[str]) -> dict[str, int]:
    """``("push=1", ...)`` as ``{"push": 1}``.

    Raises:
        LcrlError: an entry that is not ``FAMILY=STEPS`` with a known family and STEPS >= 0.
    """
    out: dict[str, int] = {}
    for entry in entries:
        family, sep, value = str(entry).partition("=")
        steps = int(value) if sep and value.strip().isdigit() else -1
        if family not in FAMILIES or steps < 0:
            raise LcrlError(
                f"onset_delay entry {entry!r}: give FAMILY=STEPS with a family of {FAMILIES} "
                "and STEPS a whole number >= 0 (e.g. push=1)"
            )
        out[family] = steps
    return out


def delayed_labels(
    data: Any, observations: np.ndarray, delays: dict[str, int], families: Sequence[str]
) -> dict[int, np.ndarray]:
    """Each of ``observations``' labels (instruction ids) whose family has a delay ``d`` in
    ``delays``, kept only where the same instruction was also accepted at each of the ``d``
    steps before, in the same episode; labels of other families as they are."""
    out: dict[int, np.ndarray] = {}
    for j in observations:
        j = int(j)
        lab = data.labels(j).astype(np.int64)
        if lab.size and delays:
            start = int(data.first_of(j))
            keep = []
            for i in lab:
                d = delays.get(families[int(i)], 0)
                ok = j - d > start and all(int(i) in data.labels(j - m) for m in range(1, d + 1))
                keep.append(d == 0 or ok)
            lab = lab[np.asarray(keep, bool)]
        out[j] = lab
    return out


def _text_encoder(name: str) -> Any:
    from lcrl.text_encoder import FrozenTextEncoder, TextEncoderConfig

    cfg = TextEncoderConfig() if not name else TextEncoderConfig(model=name)
    return FrozenTextEncoder(cfg)


class _Sampler:
    """Training batches for both models from the training episodes."""

    def __init__(
        self,
        pairs: _Pairs,
        table: list[Instruction],
        rng: np.random.Generator,
        near_window: int = 10,
        onset_delay: dict[str, int] | None = None,
    ):
        self.pairs, self.rng, self.table = pairs, rng, table
        self.near_window = int(near_window)
        data = pairs.data
        obs = pairs.observations(pairs.train_episodes)
        seen = pairs.seen
        #: Each training observation's labels, after the families' onset delays.
        self._labels = delayed_labels(
            data, obs, dict(onset_delay or {}), [ins.family for ins in table]
        )
        self.labelled: list[int] = []
        self.targets: list[np.ndarray] = []
        self.empty: list[int] = []
        for j in obs:
            lab = self.labels(int(j))
            if lab.size == 0:
                self.empty.append(int(j))
            elif seen[lab].any():
                self.labelled.append(int(j))
                self.targets.append(lab[seen[lab]])
            # observations whose labels are all held-out never enter training
        self.labelled_arr = np.asarray(self.labelled, np.int64)
        self.empty_arr = np.asarray(self.empty, np.int64)
        # near misses: observations that achieved nothing within near_window steps of one
        # that achieved something, in the same episode (where an achievement begins or ends)
        ep = data.episode_of(self.empty_arr) if len(self.empty_arr) else self.empty_arr
        lab_ep = data.episode_of(self.labelled_arr)
        near = []
        for j, e in zip(self.empty_arr, ep, strict=True):
            lo = np.searchsorted(self.labelled_arr, j - self.near_window)
            hi = np.searchsorted(self.labelled_arr, j + self.near_window, side="right")
            if np.any(lab_ep[lo:hi] == e):
                near.append(int(j))
        self.near_empty_arr = np.asarray(near, np.int64)
        self.seen_ids = np.flatnonzero(seen)
        if not self.labelled:
            raise LcrlError("no training observation carries a training instruction label")
        # hard negatives: seen instructions sharing the object or the family
        self.related: list[np.ndarray] = []
        for ins in table:
            rel = [
                k
                for k in self.seen_ids
                if table[k] != ins and (table[k].obj == ins.obj or table[k].family == ins.family)
            ]
            self.related.append(np.asarray(rel, np.int64))

    def labels(self, j: int) -> np.ndarray:
        """Instruction ids that training observation ``j`` counts as achieved."""
        return self._labels[int(j)]

    def caption_batch(
        self, n: int, none_fraction: float, near: float = 0.0
    ) -> tuple[np.ndarray, list[int | None]]:
        """Observation indices and target instruction ids (None: ``<none>``); a fraction
        ``near`` of the ``<none>`` rows are near misses."""
        n_none = int(self.rng.binomial(n, none_fraction)) if self.empty else 0
        k = self.rng.integers(len(self.labelled), size=n - n_none)
        idx = list(self.labelled_arr[k])
        texts: list[int | None] = [
            int(self.targets[i][self.rng.integers(len(self.targets[i]))]) for i in k
        ]
        if n_none:
            n_near = int(self.rng.binomial(n_none, near)) if len(self.near_empty_arr) else 0
            pools = ((self.empty_arr, n_none - n_near), (self.near_empty_arr, n_near))
            for pool, m in pools:
                idx += list(pool[self.rng.integers(len(pool), size=m)])
            texts += [None] * n_none
        return np.asarray(idx, np.int64), texts

    def near_negative(self, j: int, instruction: int) -> int:
        """An observation of ``j``'s episode, within ``near_window`` steps, where
        ``instruction`` is not satisfied (-1: none): the boundary of an achievement."""
        data = self.pairs.data
        e = int(data.episode_of(np.asarray([j]))[0])
        lo = max(int(data.episode_start[e]) + 1, j - self.near_window)
        hi = min(int(data.episode_start[e + 1]), j + self.near_window + 1)
        for _ in range(8):
            c = int(self.rng.integers(lo, hi)) if hi > lo else -1
            if c >= 0 and instruction not in self.labels(c):
                return c
        return -1

    def reward_batch(
        self, n: int, hard: float, near: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Observation indices, instruction ids and 0/1 targets, half positives; a
        fraction ``near`` of the negatives are near misses (:meth:`near_negative`)."""
        n_pos = n // 2
        k = self.rng.integers(len(self.labelled), size=n)
        idx = self.labelled_arr[k].copy()
        ids = np.empty(n, np.int64)
        y = np.zeros(n, np.float32)
        for r in range(n):
            sat = self.targets[k[r]]
            if r < n_pos:
                ids[r] = sat[self.rng.integers(len(sat))]
                y[r] = 1.0
                continue
            if near and self.rng.random() < near:  # the same instruction, just before or after
                i = int(sat[self.rng.integers(len(sat))])
                c = self.near_negative(int(idx[r]), i)
                if c >= 0:
                    idx[r], ids[r] = c, i
                    continue
            if self.empty and self.rng.random() < 0.3:  # nothing achieved: any instruction
                idx[r] = self.empty_arr[self.rng.integers(len(self.empty))]
                ids[r] = self.seen_ids[self.rng.integers(len(self.seen_ids))]
                continue
            all_labels = self.labels(int(idx[r]))
            pool = self.related[int(sat[self.rng.integers(len(sat))])]
            if self.rng.random() >= hard or pool.size == 0:
                pool = self.seen_ids
            for _ in range(10):
                cand = int(pool[self.rng.integers(len(pool))])
                if cand not in all_labels:
                    break
            else:
                cand = -1
            if cand < 0:  # every candidate was satisfied: fall back to a positive
                ids[r] = sat[0]
                y[r] = 1.0
            else:
                ids[r] = cand
        return idx, ids, y

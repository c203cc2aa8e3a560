"""Relabelling stored episodes with the learned models (:class:`LearnedLabeller`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from captioner.learned.saved import LearnedCaptioner
from captioner.learned.vocabulary import NONE_TEXT
from lcrl.errors import LcrlError

# --------------------------------------------------------------------------- relabelling


class LearnedLabeller:
    """Labels a stored episode with the learned models, once per episode.

    ``labels`` are the relabelling candidates of each observation (what the learned
    captioner says the change since the first frame achieved, every beam caption whose
    log-likelihood is at least ``min_logprob``, restricted to the training instructions);
    ``achieved`` are the instructions the learned reward model judges satisfied at each
    observation (probability at least ``threshold``), scored for every candidate of the
    episode and its own instruction in one batch.

    Args:
        models: the loaded checkpoint.
        table: the run's instruction table; ids ``< num_train`` may be labels.
        num_train: number of training instructions at the front of ``table``.
        captioner: use the learned captioner for ``labels`` (else the caller's rule
            labels are kept).
        reward: use the learned reward model for ``achieved``.
        captioner_rewards: the captions are the rewards too (no reward model; the caller
            stores no separate ``achieved``).
        min_logprob: captions less likely than this are skipped.
        beam: beam width (0 or 1: greedy, one caption per observation).
        threshold: reward-model probability that counts as satisfied.
        family_thresholds: per-family overrides of ``threshold`` (``{"push": 0.9}``).
        agree: count an instruction as achieved at an observation only where the
            captioner's labels of that observation hold it too (both models agree).
        confirm: keep a caption as a relabelling candidate of an observation only where
            the reward model judges it achieved there (:meth:`confirmed`).
        reward_labels: the relabelling candidates of each observation are the training
            instructions the reward model judges achieved there, every one of them scored
            (with ``captioner`` too: together with the captions read there).
    """

    def __init__(
        self,
        models: LearnedCaptioner,
        table: Sequence[str],
        num_train: int,
        captioner: bool = True,
        reward: bool = True,
        captioner_rewards: bool = False,
        min_logprob: float = -1.0,
        beam: int = 3,
        threshold: float = 0.5,
        agree: bool = False,
        family_thresholds: dict[str, float] | None = None,
        confirm: bool = False,
        reward_labels: bool = False,
    ) -> None:
        if captioner and not models.has("captioner"):
            raise LcrlError("learned relabelling needs a checkpoint with a captioner")
        if reward and not models.has("reward"):
            raise LcrlError("learned rewards need a checkpoint with a reward model")
        self.models = models
        self.table = list(table)
        self.train_ids = {t: i for i, t in enumerate(self.table[:num_train])}
        if captioner_rewards and (reward or not captioner):
            raise LcrlError("captioner rewards need the learned captioner and no reward model")
        self.use_captioner, self.use_reward = captioner, reward
        self.captioner_rewards = captioner_rewards
        self.min_logprob, self.beam, self.threshold = float(min_logprob), int(beam), threshold
        if agree and not (captioner and reward):
            raise LcrlError("agreement needs both the learned captioner and the reward model")
        self.agree = bool(agree)
        if confirm and not (captioner and reward):
            raise LcrlError("confirmation needs both the learned captioner and the reward model")
        self.confirm = bool(confirm)
        if reward_labels and not reward:
            raise LcrlError("reward-model labels need the reward model")
        self.reward_labels = bool(reward_labels)
        self.num_train = int(num_train)
        self.skipped = 0  # captions dropped by the threshold
        self.kept = 0
        # each instruction's family (its first word), for the agreement of each family
        self.families = [t.split()[0] if t.split() else "" for t in self.table]
        self.family_names = sorted(set(self.families[:num_train]) - {""})
        self.family_thresholds = dict(family_thresholds or {})
        self._agreement: dict[str, dict[str, int]] = {}

    def compare(self, kind: str, learned: Sequence[Sequence[int]], rule: Sequence[Sequence[int]],
                among: Sequence[int] | None = None) -> None:  # fmt: skip
        """Count how the learned ``kind`` (``labels`` or ``rewards``) agree with the rule
        captioner's, observation by observation (only ids in ``among``, if given)."""
        keep = None if among is None else set(int(i) for i in among)
        for pred, true in zip(learned, rule, strict=True):
            a, b = set(int(i) for i in pred), set(int(i) for i in true)
            if keep is not None:
                a, b = a & keep, b & keep
            for key, ids in (("tp", a & b), ("fp", a - b), ("fn", b - a)):
                for i in ids:
                    for name in (kind, f"{kind}_{self.families[i]}"):
                        self._agreement.setdefault(name, {"tp": 0, "fp": 0, "fn": 0})[key] += 1

    def agreement(self) -> dict[str, float]:
        """Precision and recall of the learned labels / rewards against the rule captioner
        since the last call (``nan`` where there was nothing to count), then reset: over
        all instructions (``labels_precision``, ...) and per family of the training
        instructions (``labels_push_precision``, ``rewards_reach_recall``, ...)."""
        out = {}
        for kind in ("labels", "rewards"):
            for name in (kind, *(f"{kind}_{f}" for f in self.family_names)):
                n = self._agreement.get(name, {"tp": 0, "fp": 0, "fn": 0})
                tp, fp, fn = n["tp"], n["fp"], n["fn"]
                out[f"{name}_precision"] = tp / (tp + fp) if tp + fp else float("nan")
                out[f"{name}_recall"] = tp / (tp + fn) if tp + fn else float("nan")
        self._agreement = {}
        return out

    def labels(self, frames: np.ndarray, proprio: np.ndarray) -> list[list[int]]:
        """Training-instruction ids the captioner reads in each observation."""
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        per_obs = self.models.captions(first, frames, p0, proprio, beam=self.beam)
        out = []
        for caps in per_obs:
            ids = []
            for text, score in caps:
                if text == NONE_TEXT or text not in self.train_ids:
                    continue
                if score < self.min_logprob:
                    self.skipped += 1
                    continue
                self.kept += 1
                ids.append(self.train_ids[text])
            out.append(sorted(set(ids)))
        out[0] = []  # nothing is achieved by the first observation relative to itself
        return out

    def satisfied(
        self,
        goals: Sequence[int],
        first: np.ndarray,
        frames: np.ndarray,
        p0: np.ndarray,
        proprio: np.ndarray,
    ) -> np.ndarray:
        """Whether the reward model judges each pair's instruction ``goals[i]`` achieved
        between ``first[i]`` and ``frames[i]`` (its family's threshold), ``(N,)`` bool: the
        online check that ends a training episode where the learned reward says so."""
        goals = [int(g) for g in goals]
        if not goals:
            return np.zeros(0, bool)
        cands = sorted(set(goals))
        col = {c: k for k, c in enumerate(cands)}
        probs = self.models.score_matrix([self.table[c] for c in cands], first, frames, p0, proprio)
        p = probs[np.arange(len(goals)), [col[g] for g in goals]]
        bar = [self.family_thresholds.get(self.families[g], self.threshold) for g in goals]
        return p >= np.asarray(bar, np.float32)

    def confirmed(
        self, labels: Sequence[Sequence[int]], achieved: Sequence[Sequence[int]]
    ) -> list[list[int]]:
        """With ``confirm``, each observation's labels that the reward model judges achieved
        there too (else the labels as they are)."""
        if not self.confirm:
            return [list(ids) for ids in labels]
        kept = []
        for ids, hit in zip(labels, achieved, strict=True):
            rewarded = set(hit)
            kept.append([i for i in ids if i in rewarded])
        return kept

    def judged(
        self, labels: Sequence[Sequence[int]], achieved: Sequence[Sequence[int]]
    ) -> list[list[int]]:
        """With ``reward_labels``: each observation's relabelling candidates, the training
        ids among what the reward model judges ``achieved`` there, together with the
        captions' ``labels`` there when the captioner is on too."""
        out = [[i for i in a if i < self.num_train] for a in achieved]
        if self.use_captioner:
            out = [sorted(set(c) | set(j)) for c, j in zip(labels, out, strict=True)]
        return out

    def achieved(
        self,
        frames: np.ndarray,
        proprio: np.ndarray,
        candidates: Sequence[int],
        labels: Sequence[Sequence[int]] | None = None,
    ) -> list[list[int]]:
        """For each observation, the candidate ids the reward model judges satisfied
        (with ``agree``, only those among that observation's ``labels`` too)."""
        cands = sorted(set(int(c) for c in candidates))
        if not cands:
            return [[] for _ in range(len(frames))]
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        probs = self.models.score_matrix([self.table[c] for c in cands], first, frames, p0, proprio)
        bar = [self.family_thresholds.get(self.families[c], self.threshold) for c in cands]
        hit = probs >= np.asarray(bar, np.float32)
        hit[0] = False
        out = [[cands[k] for k in np.flatnonzero(row)] for row in hit]
        if self.agree:
            if labels is None:
                raise LcrlError("agreement needs each observation's captioner labels")
            out = [
                [c for c in row if c in keep]
                for row, keep in zip(out, map(set, labels), strict=True)
            ]
        return out

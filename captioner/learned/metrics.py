"""Caption metrics: BLEU-4, ROC AUC, per-slot agreement with the label, and intervals."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from captioner.grammar import Instruction
from lcrl.statistics import wilson_interval

# --------------------------------------------------------------------------- metrics


def bleu4(candidate: str, references: Sequence[str]) -> float:
    """Sentence BLEU-4 against several references (uniform weights, brevity penalty, +1
    smoothing of the higher n-gram precisions as in Lin and Och 2004)."""
    cand = candidate.split()
    refs = [r.split() for r in references]
    if not cand or not refs:
        return 0.0
    logs = []
    for n in range(1, 5):
        grams = Counter(tuple(cand[i : i + n]) for i in range(len(cand) - n + 1))
        if not grams:
            logs.append(math.log(1.0 / (1.0 + 1.0)))  # smoothed empty order
            continue
        best: Counter = Counter()
        for r in refs:
            rg = Counter(tuple(r[i : i + n]) for i in range(len(r) - n + 1))
            for g in grams:
                best[g] = max(best[g], rg[g])
        hit = sum(min(c, best[g]) for g, c in grams.items())
        total = sum(grams.values())
        if n == 1:
            if hit == 0:
                return 0.0
            logs.append(math.log(hit / total))
        else:
            logs.append(math.log((hit + 1.0) / (total + 1.0)))
    ref_len = min((abs(len(r) - len(cand)), len(r)) for r in refs)[1]
    bp = 1.0 if len(cand) > ref_len else math.exp(1.0 - ref_len / len(cand))
    return bp * math.exp(sum(logs) / 4.0)


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (ties count one half); NaN without both classes."""
    scores = np.asarray(scores, np.float64)
    labels = np.asarray(labels, bool)
    pos, neg = labels.sum(), (~labels).sum()
    if pos == 0 or neg == 0:
        return float("nan")
    order = np.argsort(scores, kind="mergesort")
    ranks = np.empty(len(scores), np.float64)
    sorted_scores = scores[order]
    i = 0
    while i < len(scores):  # average ranks over ties
        j = i
        while j + 1 < len(scores) and sorted_scores[j + 1] == sorted_scores[i]:
            j += 1
        ranks[order[i : j + 1]] = 0.5 * (i + j) + 1.0
        i = j + 1
    return float((ranks[labels].sum() - pos * (pos + 1) / 2.0) / (pos * neg))


SLOT_GROUPS: dict[str, tuple[str, ...]] = {
    "verb": ("family",),
    "object": ("colour", "shape"),
    "colour": ("colour",),
    "shape": ("shape",),
    "direction": ("direction",),
    "relation": ("relation",),
    "reference": ("target_colour", "target_shape"),
}


def slot_matches(generated: Instruction | None, label: Instruction) -> dict[str, bool]:
    """For each slot group the label has, whether the generated instruction agrees."""
    want = label.slots()
    got = generated.slots() if generated is not None else {}
    out = {}
    for group, keys in SLOT_GROUPS.items():
        if all(k in want for k in keys):
            out[group] = all(got.get(k) == want[k] for k in keys)
    return out


def rate_interval(
    hits: Sequence[bool], clusters: Sequence[int] | None = None
) -> dict[str, float | int | list[float]]:
    """A rate with its 95% Wilson interval: ``{"rate", "ci", "n"}`` (and ``"clusters"``,
    ``"effective_n"``).

    Without ``clusters`` the observations are independent. With them (each observation's
    episode), the frames of one episode move together, as consecutive frames do: the
    interval is Wilson's at the effective sample size, ``n`` shrunk by the design effect
    that the spread of the episodes' own rates shows: between the effective number of
    whole episodes (Kish's, which weighs long episodes more) and ``n``, and that number of
    episodes where every observation agrees."""
    n, k = len(hits), int(sum(bool(h) for h in hits))
    out: dict[str, float | int | list[float]] = {"rate": k / n if n else float("nan"), "n": n}
    if clusters is None or n == 0:
        out["ci"] = list(wilson_interval(k, n))
        return out
    ids, inverse = np.unique(np.asarray(clusters), return_inverse=True)
    c = len(ids)
    per_k = np.bincount(inverse, weights=np.asarray(hits, float), minlength=c)
    per_n = np.bincount(inverse, minlength=c).astype(float)
    r = k / n
    # the ratio estimator's variance over clusters
    var = c / max(c - 1, 1) * float(np.sum((per_k - r * per_n) ** 2)) / n**2
    # at least the sample of whole episodes (Kish's n^2 / sum n_i^2: the number of
    # episodes when they are of one length), at most every observation
    floor = n**2 / float(np.sum(per_n**2))
    n_eff = floor if var <= 0 or r in (0.0, 1.0) else r * (1 - r) / var
    n_eff = float(min(max(n_eff, floor), n))
    out["ci"] = list(wilson_interval(r * n_eff, n_eff))  # type: ignore[arg-type]
    out["clusters"], out["effective_n"] = c, round(n_eff, 1)
    return out


def auc_interval(
    scores: np.ndarray,
    labels: np.ndarray,
    rounds: int = 200,
    seed: int = 0,
    clusters: Sequence[int] | None = None,
) -> list[float]:
    """95% bootstrap interval of :func:`roc_auc`, ``rounds`` resamples with replacement:
    of the pairs, or of whole ``clusters`` (each pair's episode: its frames and their
    negatives move together) where given. NaN where one class is missing."""
    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    if labels.all() or not labels.any():
        return [float("nan"), float("nan")]
    rng = np.random.default_rng(seed)
    if clusters is None:
        groups = [np.asarray([i]) for i in range(len(scores))]
    else:
        ids, inverse = np.unique(np.asarray(clusters), return_inverse=True)
        groups = [np.flatnonzero(inverse == c) for c in range(len(ids))]
    values = []
    for _ in range(rounds):
        pick = np.concatenate([groups[g] for g in rng.integers(len(groups), size=len(groups))])
        if labels[pick].all() or not labels[pick].any():
            continue
        values.append(roc_auc(scores[pick], labels[pick]))
    return [float(np.quantile(values, 0.025)), float(np.quantile(values, 0.975))]

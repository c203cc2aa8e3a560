"""Evaluating the models on held-out episodes and combinations, and their agreement
with the rule captioner as relabellers."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from captioner.dataset import CaptionDataset
from captioner.grammar import try_parse
from captioner.learned.data import _observations
from captioner.learned.labeller import LearnedLabeller
from captioner.learned.metrics import (
    SLOT_GROUPS,
    auc_interval,
    bleu4,
    rate_interval,
    roc_auc,
    slot_matches,
)
from captioner.learned.saved import LearnedCaptioner
from captioner.learned.training import _parse
from captioner.learned.vocabulary import NEAR_WINDOW, NONE_TEXT
from lcrl.errors import LcrlError

# --------------------------------------------------------------------------- evaluation


def evaluate_models(
    lc: LearnedCaptioner,
    data: CaptionDataset,
    episodes: np.ndarray | None = None,
    max_pairs: int = 2000,
    batch_size: int = 128,
    beam: int = 0,
    seed: int = 0,
) -> dict[str, Any]:
    """Captioner and reward-model figures on ``episodes`` (default: the checkpoint's
    held-out episodes when it was trained on ``data``, else every episode).

    Returns a dict with ``seen`` (observations that achieved a training instruction) and
    ``heldout_combinations`` (observations that achieved a held-out combination), each
    with captioner ``exact_match``, ``slot_accuracy`` per slot group, ``bleu4``, and the
    reward model's ``precision``, ``recall`` and ``auc``; plus ``none_accuracy`` (the
    captioner says ``<none>`` where nothing was achieved). The reward model's ``auc``
    ranks each satisfied instruction against an unsatisfied one of the same family on the
    same frames (about the same object where the family allows: the instruction alone
    decides); ``auc_with_idle`` adds observations that achieved nothing, paired with any
    instruction, to the negatives; ``auc_near`` ranks each satisfied instruction against
    the same instruction a few steps before or after in the same episode, where it is not
    satisfied (near misses: the boundary a training loop's relabelling asks about most),
    and ``near_false_positive_rate`` is how often those score as satisfied.
    """
    lc.check_dataset(data)
    if episodes is None:
        same = lc.meta.get("dataset_meta") == data.meta and "val_episodes" in lc.meta
        episodes = (
            np.asarray(lc.meta["val_episodes"], np.int64) if same else np.arange(data.num_episodes)
        )
    rng = np.random.default_rng(seed)
    obs = _observations(data, np.asarray(episodes, np.int64))
    names = data.instructions  # matched to the models by text, never by id
    heldout_names = {t for t, s in zip(names, data.instruction_set, strict=True) if s == "heldout"}
    groups: dict[str, list[tuple[int, list[str]]]] = {"seen": [], "heldout_combinations": []}
    empty: list[int] = []
    for j in obs:
        lab = [names[i] for i in data.labels(int(j))]
        if not lab:
            empty.append(int(j))
            continue
        if any(t in heldout_names for t in lab):
            groups["heldout_combinations"].append((int(j), lab))
        if any(t not in heldout_names for t in lab):
            groups["seen"].append((int(j), lab))
    first_of = data.first_of

    def batches(idx: list[int]) -> Any:
        for s in range(0, len(idx), batch_size):
            sl = np.asarray(idx[s : s + batch_size], np.int64)
            f = data.read_frames(first_of(sl))
            c = data.read_frames(sl)
            yield sl, f, c, data.proprio[first_of(sl)], data.proprio[sl]

    results: dict[str, Any] = {"episodes": len(episodes)}
    for name, items in groups.items():
        if len(items) > max_pairs:
            items = [items[i] for i in np.sort(rng.choice(len(items), max_pairs, replace=False))]
        res: dict[str, Any] = {"observations": len(items)}
        if lc.has("captioner") and items:
            idx = [j for j, _ in items]
            # intervals over episodes: an episode's frames are not independent draws
            episode = data.episode_of(np.asarray(idx, np.int64)).tolist()
            captions = []
            for _, f, c, p0, p in batches(idx):
                captions += lc.caption(f, c, p0, p, beam=beam)
            exact, bleu, slots = [], [], {g: [] for g in SLOT_GROUPS}
            slot_episodes: dict[str, list[int]] = {g: [] for g in SLOT_GROUPS}
            made_heldout = []
            for (_, lab), (text, _), e in zip(items, captions, episode, strict=True):
                # the references: the labels of the group's kind (seen or held-out)
                refs = [t for t in lab if (t in heldout_names) == (name != "seen")]
                exact.append(text in lab)
                made_heldout.append(text in heldout_names and text in lab)
                bleu.append(bleu4(text, refs))
                gen = try_parse(text) if text != NONE_TEXT else None
                best = max(
                    (slot_matches(gen, _parse(r)) for r in refs),
                    key=lambda m: sum(m.values()),
                )
                for g, ok in best.items():
                    slots[g].append(ok)
                    slot_episodes[g].append(e)
            res["exact_match"] = float(np.mean(exact))
            res["exact_match_ci"] = rate_interval(exact, episode)["ci"]
            res["episodes_observed"] = len(set(episode))
            res["bleu4"] = float(np.mean(bleu))
            res["slot_accuracy"] = {g: float(np.mean(v)) for g, v in slots.items() if v}
            res["slot_accuracy_ci"] = {
                g: rate_interval(v, slot_episodes[g])["ci"] for g, v in slots.items() if v
            }
            # per family of the observation's most demanding reference (a lift also
            # reaches its object; a stack also lifts it)
            fams: dict[str, tuple[list[bool], list[int]]] = {}
            for (_, lab), ok, e in zip(items, exact, episode, strict=True):
                refs = [t for t in lab if (t in heldout_names) == (name != "seen")]
                hits, eps = fams.setdefault(family_of(refs), ([], []))
                hits.append(ok), eps.append(e)
            res["exact_match_by_family"] = {
                f: rate_interval(v, eps) for f, (v, eps) in sorted(fams.items())
            }
            if name != "seen":
                res["heldout_caption_rate"] = float(np.mean(made_heldout))
            res["examples"] = [
                {"labels": lab[:4], "caption": text}
                for (_, lab), (text, _) in list(zip(items, captions, strict=True))[:5]
            ]
        if lc.has("reward") and items:
            pos_idx, pos_txt, neg_idx, neg_txt = [], [], [], []
            pool = (
                sorted(heldout_names)
                if name != "seen"
                else [t for t in names if t not in heldout_names]
            )
            by_family: dict[str, list[str]] = {}
            for t in pool:
                by_family.setdefault(t.split()[0], []).append(t)
            for j, lab in items:
                mine = [t for t in lab if (t in heldout_names) == (name != "seen")]
                if not mine:
                    continue
                pos_idx.append(j)
                pos_txt.append(mine[rng.integers(len(mine))])
                # A hard negative for the same frames: an unsatisfied instruction of the
                # same family, about the same object when the family allows (push the red
                # cube right, not left), so that the instruction alone decides.
                pos = _parse(pos_txt[-1])
                same = [t for t in by_family[pos.family] if t not in lab]
                close = [t for t in same if _parse(t).obj == pos.obj]
                cands = close or same
                if cands:
                    neg_idx.append(j)
                    neg_txt.append(cands[rng.integers(len(cands))])
            n_hard = len(neg_idx)
            # near misses: the positive's instruction a few steps before or after, in the
            # same episode, where it is not satisfied (the boundary of the achievement)
            near_pos, near_idx, near_txt = [], [], []
            for k, (j, text) in enumerate(zip(pos_idx, pos_txt, strict=True)):
                e = int(data.episode_of(np.asarray([j]))[0])
                lo, hi = int(data.episode_start[e]) + 1, int(data.episode_start[e + 1])
                cands = [
                    c
                    for c in range(max(lo, j - NEAR_WINDOW), min(hi, j + NEAR_WINDOW + 1))
                    if text not in {names[i] for i in data.labels(c)}
                ]
                if cands:
                    near_pos.append(k)
                    near_idx.append(cands[rng.integers(len(cands))])
                    near_txt.append(text)
            for j in (
                rng.choice(empty, min(len(empty), len(pos_idx) // 2), replace=False)
                if empty
                else []
            ):  # observations that achieved nothing, with any instruction
                neg_idx.append(int(j))
                neg_txt.append(pool[rng.integers(len(pool))])
            all_idx = pos_idx + neg_idx + near_idx
            all_txt = pos_txt + neg_txt + near_txt
            y = np.asarray([1] * len(pos_idx) + [0] * len(neg_idx), bool)
            scores = []
            for s in range(0, len(all_idx), batch_size):
                sl = np.asarray(all_idx[s : s + batch_size], np.int64)
                f = data.read_frames(first_of(sl))
                c = data.read_frames(sl)
                scores.append(
                    lc.score(
                        all_txt[s : s + batch_size],
                        f,
                        c,
                        data.proprio[first_of(sl)],
                        data.proprio[sl],
                    )
                )
            sc = np.concatenate(scores) if scores else np.zeros(0)
            near_sc = sc[len(pos_idx) + len(neg_idx) :]
            sc = sc[: len(pos_idx) + len(neg_idx)]
            if near_pos:
                pos_sc = sc[np.asarray(near_pos)]
                res["auc_near"] = roc_auc(
                    np.concatenate([pos_sc, near_sc]),
                    np.concatenate([np.ones(len(pos_sc), bool), np.zeros(len(near_sc), bool)]),
                )
                res["near_false_positive_rate"] = float(np.mean(near_sc >= 0.5))
            pred = sc >= 0.5
            tp = int(np.sum(pred & y))
            res["reward_pairs"] = len(y)
            res["precision"] = float(tp / max(int(pred.sum()), 1))
            res["recall"] = float(tp / max(int(y.sum()), 1))
            hard = np.concatenate([np.ones(len(pos_idx), bool), np.arange(len(neg_idx)) < n_hard])
            res["auc"] = roc_auc(sc[hard], y[hard])
            # resampled by episode: a positive and its hard negative share their frames
            pair_episode = data.episode_of(np.asarray(pos_idx + neg_idx[:n_hard], np.int64))
            res["auc_ci"] = auc_interval(sc[hard], y[hard], seed=seed, clusters=pair_episode)
            # per family: each positive with the hard negative drawn for its frames
            fam = [t.split()[0] for t in pos_txt] + [t.split()[0] for t in neg_txt[:n_hard]]
            hs, hy = sc[hard], y[hard]
            res["auc_by_family"] = {
                f: {
                    "auc": roc_auc(hs[m], hy[m]),
                    "ci": auc_interval(hs[m], hy[m], seed=seed, clusters=pair_episode[m]),
                    "pairs": int(m.sum()),
                }
                for f in sorted(set(fam))
                if (m := np.asarray([g == f for g in fam])).any()
                and hy[m].any()
                and not hy[m].all()
            }
            res["auc_with_idle"] = roc_auc(sc, y)
        results[name] = res
    if lc.has("captioner") and empty:
        sample = (
            empty if len(empty) <= max_pairs else list(rng.choice(empty, max_pairs, replace=False))
        )
        said = []
        for _, f, c, p0, p in batches(sorted(int(j) for j in sample)):
            said += [t == NONE_TEXT for t, _ in lc.caption(f, c, p0, p, beam=beam)]
        results["none_accuracy"] = float(np.mean(said))
    return results


#: Families from the most demanding to the least: an achievement of one often satisfies
#: those after it too (a lift reaches its object).
FAMILY_ORDER = ("stack", "put", "lift", "push", "reach")


def family_of(texts: Sequence[str]) -> str:
    """The most demanding family among instructions (:data:`FAMILY_ORDER`)."""
    fams = {t.split()[0] for t in texts}
    return next((f for f in FAMILY_ORDER if f in fams), sorted(fams)[0])


def relabel_agreement(
    lc: LearnedCaptioner,
    data: CaptionDataset,
    thresholds: Sequence[float],
    families: Sequence[str] = (),
    episodes: np.ndarray | None = None,
    beam: int = 3,
    min_logprob: float = -1.0,
) -> dict[str, Any]:
    """How learned relabelling agrees with the rule captioner on whole episodes, scored as
    a training loop's :class:`LearnedLabeller` scores them: the candidates of an episode are
    the captioner's beam captions among the training instructions (of ``families``, if
    given) plus the episode's own instruction; the reward model judges every candidate at
    every step. Precision and recall count (step, candidate) pairs against the dataset's
    rule labels, at each reward threshold; the labels' precision and recall need none.
    Far more pairs are negative here than in :func:`evaluate_models`' balanced pairs, so
    this is the figure a threshold for ``--relabel.threshold`` is chosen on.

    Returns:
        ``{"episodes", "labels": {precision, recall}, "rewards": [{threshold, precision,
        recall, f1}, ...], "best_threshold"}`` (best: the highest F1).
    """
    lc.check_dataset(data)
    if not (lc.has("captioner") and lc.has("reward")):
        raise LcrlError(
            "relabelling agreement needs a checkpoint with a captioner and a reward model"
        )
    if episodes is None:
        same = lc.meta.get("dataset_meta") == data.meta and "val_episodes" in lc.meta
        episodes = (
            np.asarray(lc.meta["val_episodes"], np.int64) if same else np.arange(data.num_episodes)
        )
    texts = list(data.instructions)
    known = sorted({t.split()[0] for t in texts})
    unknown = [f for f in families if f not in known]
    if unknown:
        raise LcrlError(f"no instruction of family {unknown[0]!r} in the dataset; it has {known}")
    train = [
        t
        for t, kind in zip(texts, data.instruction_set, strict=True)
        if kind == "train" and (not families or t.split()[0] in families)
    ]
    # the loop's table: its training instructions first, the rest after
    in_train = set(train)
    table = train + [t for t in texts if t not in in_train]
    at = {t: i for i, t in enumerate(table)}
    to_table = [at[t] for t in texts]  # dataset instruction id -> table id
    lab = LearnedLabeller(lc, table, len(train), min_logprob=min_logprob, beam=beam)
    thresholds = sorted(float(x) for x in thresholds)
    counts = np.zeros((len(thresholds), 3), np.int64)  # tp, fp, fn per threshold
    for e in episodes:
        ep = data.episode(int(e))
        frames, proprio = ep["frames"], ep["proprio"]
        labels = lab.labels(frames, proprio)
        rule = [[to_table[i] for i in ids if to_table[i] < len(train)] for ids in ep["labels"]]
        lab.compare("labels", labels, rule)
        own = [to_table[ep["instruction"]]] if ep["instruction"] >= 0 else []
        cands = sorted({i for ids in labels for i in ids} | {i for i in own if i < len(train)})
        if not cands:
            continue
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        probs = lc.score_matrix([table[c] for c in cands], first, frames, p0, proprio)
        column = {c: k for k, c in enumerate(cands)}
        truth = np.zeros_like(probs, bool)
        for t, ids in enumerate(rule):
            for i in ids:
                if i in column:
                    truth[t, column[i]] = True
        truth[0] = False
        for k, thr in enumerate(thresholds):
            hit = probs >= thr
            hit[0] = False
            counts[k] += [(hit & truth).sum(), (hit & ~truth).sum(), (~hit & truth).sum()]
    agreement = lab.agreement()
    rows = []
    for thr, (tp, fp, fn) in zip(thresholds, counts, strict=True):
        precision = tp / (tp + fp) if tp + fp else float("nan")
        recall = tp / (tp + fn) if tp + fn else float("nan")
        f1 = 2 * precision * recall / (precision + recall) if tp else 0.0
        rows.append({"threshold": thr, "precision": precision, "recall": recall, "f1": f1})
    best = max(rows, key=lambda r: r["f1"])["threshold"] if rows else None
    return {
        "episodes": len(episodes),
        "families": list(families),
        "labels": {
            "precision": agreement["labels_precision"],
            "recall": agreement["labels_recall"],
        },
        "rewards": rows,
        "best_threshold": best,
    }


def format_agreement(result: dict[str, Any]) -> str:
    """:func:`relabel_agreement` as a few lines of text."""
    lab = result["labels"]
    lines = [
        f"learned relabelling against the rule captioner, {result['episodes']} whole episodes"
        + (f" ({', '.join(result['families'])})" if result["families"] else ""),
        f"labels: precision {lab['precision']:.2f}, recall {lab['recall']:.2f}",
        "rewards (every candidate at every step):",
    ]
    for r in result["rewards"]:
        lines.append(
            f"  threshold {r['threshold']:.2f}: precision {r['precision']:.2f}, recall "
            f"{r['recall']:.2f}, F1 {r['f1']:.2f}"
        )
    if result["best_threshold"] is not None:
        lines.append(f"best F1 at --relabel.threshold {result['best_threshold']:.2f}")
    return "\n".join(lines)


def format_results(results: dict[str, Any]) -> str:
    """A few lines for the terminal."""
    lines = [f"episodes evaluated: {results['episodes']}"]
    for name in ("seen", "heldout_combinations"):
        r = results.get(name)
        if not r:
            continue
        parts = [f"{name}: {r['observations']} observations"]
        if "exact_match" in r:
            slots = ", ".join(f"{g} {v:.2f}" for g, v in r["slot_accuracy"].items())
            parts.append(
                f"exact match {r['exact_match']:.2f}, BLEU-4 {r['bleu4']:.2f}, slots: {slots}"
            )
        if "auc" in r:
            parts.append(
                f"reward model AUC {r['auc']:.3f}, precision {r['precision']:.2f}, "
                f"recall {r['recall']:.2f} ({r['reward_pairs']} pairs)"
            )
        lines.append("; ".join(parts))
        if "exact_match_ci" in r:
            lo, hi = r["exact_match_ci"]
            lines.append(f"  exact match 95% interval [{lo:.2f}, {hi:.2f}]")
        for f, v in r.get("exact_match_by_family", {}).items():
            lo, hi = v["ci"]
            auc = r.get("auc_by_family", {}).get(f)
            extra = (
                f", reward AUC {auc['auc']:.3f} [{auc['ci'][0]:.3f}, {auc['ci'][1]:.3f}]"
                if auc
                else ""
            )
            lines.append(
                f"  {f}: exact match {v['rate']:.2f} [{lo:.2f}, {hi:.2f}] of {v['n']}{extra}"
            )
    if "none_accuracy" in results:
        lines.append(f"'<none>' where nothing was achieved: {results['none_accuracy']:.2f}")
    return "\n".join(lines)


def save_results(results: dict[str, Any], path: str | Path) -> Path:
    """Write evaluation results as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
    return path

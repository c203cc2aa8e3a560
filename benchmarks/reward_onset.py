"""How sharp a learned reward model is at the step an instruction first succeeds.

    python benchmarks/reward_onset.py runs/bench/captioner-lang2d-sq \
        data/captions-lang2d-96-policy-a10.h5 --source policy --thresholds 0.5 0.9

For every held-out episode of the caption dataset (the checkpoint's validation episodes,
optionally of one source) and every training instruction the rule captioner accepts at
some step, the reward model scores the instruction at each step from a few before the
first accepted one to a few after. Printed per family and threshold: the fraction of those
steps the model accepts, by offset from the first accepted step. A sharp model accepts
nothing before offset 0 and everything from it; a blurred one shifts its errors between
false rewards a step early and missed first successes as the threshold moves.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def first_steps(labels: Sequence[Sequence[int]], keep: Sequence[bool]) -> dict[int, int]:
    """The first step at which each kept instruction id appears among ``labels``."""
    out: dict[int, int] = {}
    for j, ids in enumerate(labels):
        for i in ids:
            if keep[int(i)]:
                out.setdefault(int(i), j)
    return out


def onset_rates(
    episodes: Sequence[tuple[np.ndarray, dict[int, int]]],
    families: Sequence[str],
    offsets: Sequence[int],
    threshold: float,
) -> dict[str, dict[int, tuple[float, int]]]:
    """Per family and offset, the fraction of steps accepted (``prob >= threshold``) and
    how many were counted. Each episode is ``(probs, firsts)``: ``probs[j, k]`` the model's
    probability for the ``k``-th instruction of ``firsts`` (in key order) at step ``j``;
    step 0 (the first frame) is never counted."""
    hits: dict[str, dict[int, list[bool]]] = {}
    for probs, firsts in episodes:
        for k, (i, j0) in enumerate(sorted(firsts.items())):
            by = hits.setdefault(families[i], {o: [] for o in offsets})
            for o in offsets:
                j = j0 + o
                if 1 <= j < len(probs):
                    by[o].append(bool(probs[j, k] >= threshold))
    return {
        f: {o: (float(np.mean(v)) if v else float("nan"), len(v)) for o, v in by.items()}
        for f, by in sorted(hits.items())
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="lcrl caption train --out")
    parser.add_argument("data", help="the caption dataset it was trained on")
    parser.add_argument("--source", default="", help="only episodes of this source (policy, ...)")
    parser.add_argument("--episodes", type=int, default=400)
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.5, 0.9])
    parser.add_argument("--before", type=int, default=3)
    parser.add_argument("--after", type=int, default=5)
    parser.add_argument("--json", default="", help="also write the rates to this file")
    args = parser.parse_args(argv)

    from captioner.dataset import SOURCES, CaptionDataset
    from captioner.learned import LearnedCaptioner
    from lcrl.errors import LcrlError

    try:
        lc = LearnedCaptioner.load(args.checkpoint)
        data = CaptionDataset(args.data)
    except (LcrlError, OSError) as e:
        raise SystemExit(f"error: {e}") from None
    if lc.reward is None:
        raise SystemExit(f"error: {args.checkpoint} has no reward model")
    eps = np.asarray(lc.meta.get("val_episodes", range(data.num_episodes)), np.int64)
    if args.source:
        if args.source not in SOURCES:
            raise SystemExit(f"error: --source must be one of {SOURCES}, got {args.source!r}")
        eps = eps[data.episode_source[eps] == SOURCES.index(args.source)]
    eps = eps[: args.episodes]
    texts = list(data.instructions)
    keep = [k == "train" for k in data.instruction_set]
    families = [t.split()[0] if t.split() else "" for t in texts]
    scored = []
    for e in eps:
        ep = data.episode(int(e))
        firsts = first_steps(ep["labels"], keep)
        if not firsts:
            continue
        frames, proprio = ep["frames"], ep["proprio"]
        n = len(frames)
        probs = lc.score_matrix(
            [texts[i] for i in sorted(firsts)],
            np.repeat(frames[:1], n, 0),
            frames,
            np.repeat(proprio[:1], n, 0),
            proprio,
        )
        scored.append((probs, firsts))
    offsets = list(range(-args.before, args.after + 1))
    out = {}
    for thr in args.thresholds:
        rates = onset_rates(scored, families, offsets, thr)
        out[str(thr)] = {f: {str(o): r for o, r in by.items()} for f, by in rates.items()}
        print(f"threshold {thr}: accepted, by steps from the first the rule captioner accepts")
        for fam, by in rates.items():
            cells = " ".join(f"{o:+d}: {r:.2f}" for o, (r, n) in by.items() if n)
            print(f"  {fam:8s} {cells}")
    print(f"{len(scored)} episodes")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

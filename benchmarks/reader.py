"""How well the canonical instruction reader reads phrasings it never trained on.

Run from the repository root::

    python -m benchmarks.reader                            # lang2d, seeds 0 1 2
    python -m benchmarks.reader --preset robosuite-manip   # robosuite's five families

The canonical reader (``--env.canonical-reader``, :mod:`train.environments.text_reading`) is fitted,
as a run fits it, on the training instructions of the env's split and their
training-only phrasings (words the grammar does not know). It is then scored without any
policy, on:

- ``paraphrase_forms``: every sentence the grammar makes for a training meaning, the
  canonical one aside (the population the ``paraphrase`` evaluation set samples);
- ``paraphrase_set``: the split's ``paraphrase`` set itself (what ``lcrl eval`` runs);
- ``heldout``: the held-out combinations' canonical sentences;
- ``heldout_forms``: every grammar sentence of a held-out meaning;
- ``validation``: the choice's set, which uses no grammar word. Every other extra word,
  phrase and template of :mod:`captioner.phrasings`' narrow lists is held out
  (:func:`validation_words`); a second reader of the arm is fitted without them and
  scored on narrow phrasings that use them (8 per training meaning).

A sentence counts as read when the reader's meaning equals the grammar's parse. An arm is
a design of the readers (``shared``: all slots pool the tokens with the same queries;
``per-slot``: each slot has queries of its own, ``CANONICAL_DESIGN``), a token-state
dropout while fitting them (``--dropout``), the vocabulary of the training-only
phrasings (``narrow``: 16 per meaning from the ``EXTRA_*`` lists; ``wide``:
``CANONICAL_PHRASINGS`` from those and the ``WIDE_*`` lists) and the weight of the family
head when a meaning is decoded (1, and ``FAMILY_WEIGHT``: the same fitted readers,
decoded twice). Members fit on minibatches of ``READER_BATCH``. The headline is the
default reader (per-slot, ``CANONICAL_DROPOUT``, wide, ``FAMILY_WEIGHT``) beside the same
reader with the narrow vocabulary. The misread words are counted per arm.

Writes ``benchmarks/results/reader-<preset>.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from benchmarks.common import (
    machine,
    new_figure,
    save_figure,
    save_json,
    save_markdown,
)

SETS = ("validation", "paraphrase_forms", "paraphrase_set", "heldout", "heldout_forms")
#: Validation sentences per training meaning.
VALIDATION_PER_MEANING = 8


def validation_words() -> set[str]:
    """Every other extra word, phrase and template of the narrow lists (the second, the
    fourth ...): held out of the validation readers' fitting."""
    from captioner import phrasings as ph

    held: set[str] = set()
    for lists in (
        ph.EXTRA_SHAPE_WORDS,
        ph.EXTRA_DIRECTION_WORDS,
        ph.EXTRA_RELATION_WORDS,
        ph.EXTRA_TEMPLATES,
    ):
        for words in lists.values():
            held.update(words[1::2])
    return held


def validation_set(train: list[Any], held: set[str]) -> list[tuple[str, Any]]:
    """Narrow phrasings of the training meanings that use a held-out word: all of a
    meaning's phrasings less those without one, :data:`VALIDATION_PER_MEANING` drawn."""
    from captioner.phrasings import training_phrasings

    rng = np.random.default_rng(0)
    out: list[tuple[str, Any]] = []
    for m in train:
        without = set(training_phrasings(m, 10**6, exclude=held))
        using = [t for t in training_phrasings(m, 10**6) if t not in without]
        picks = rng.permutation(len(using))[:VALIDATION_PER_MEANING]
        out += [(using[i], m) for i in sorted(picks)]
    return out


def reader_sets(wrapper: Any) -> dict[str, list[tuple[str, Any]]]:
    """The scored sentences with the meaning each must read as."""
    from captioner.grammar import parse, surface_forms

    fams = wrapper.families
    train = [m for m in wrapper.split.instructions("train") if m.family in fams]
    held = [m for m in wrapper.split.instructions("heldout") if m.family in fams]
    para = [t for t in wrapper.split.texts("paraphrase") if parse(t).family in fams]
    return {
        "paraphrase_forms": [(t, m) for m in train for t in list(surface_forms(m))[1:]],
        "paraphrase_set": [(t, parse(t)) for t in para],
        "heldout": [(m.text, m) for m in held],
        "heldout_forms": [(t, m) for m in held for t in surface_forms(m)],
    }


def misread_word(text: str, truth: Any) -> str:
    """The words of ``text`` that the canonical sentence lacks (the culprits are among
    them; the benchmark counts each word of a misread sentence)."""
    canon = set(truth.text.split())
    extra = [w for w in text.split() if w not in canon]
    return " ".join(extra) if extra else "(canonical words)"


#: Reader designs (:class:`lcrl.text_reader.TokenReader` options) by arm name.
DESIGNS: dict[str, dict[str, Any]] = {
    "shared": {"per_slot": False, "queries": 4, "hidden": 64},
    "per-slot": {},  # filled with CANONICAL_DESIGN when scored
}


VOCABULARIES = ("narrow", "wide")


class TokenCache:
    """The frozen encoder with every text's token states kept (unpadded): the benchmark
    fits and scores the same sentences with many readers.

    Args:
        encoder: a :class:`lcrl.text_encoder.FrozenTextEncoder`.
    """

    def __init__(self, encoder: Any) -> None:
        self.encoder = encoder
        self._rows: dict[str, np.ndarray] = {}

    def encode_tokens(self, texts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """As the encoder's, each text encoded once."""
        missing = [t for t in dict.fromkeys(texts) if t not in self._rows]
        if missing:
            states, mask = self.encoder.encode_tokens(missing)
            for i, text in enumerate(missing):
                self._rows[text] = states[i, : int(mask[i].sum())]
        rows = [self._rows[t] for t in texts]
        longest = max((len(r) for r in rows), default=0)
        states = np.zeros((len(rows), longest, self.encoder.dim), np.float32)
        mask = np.zeros((len(rows), longest), bool)
        for i, r in enumerate(rows):
            states[i, : len(r)], mask[i, : len(r)] = r, True
        return states, mask

    def __getattr__(self, name: str) -> Any:
        return getattr(self.encoder, name)


def arm_name(design: str, dropout: float, family_weight: float, vocabulary: str) -> str:
    """The name of an arm, e.g. ``per-slot d0.5 wide fw0.5``."""
    return f"{design} d{dropout:g} {vocabulary} fw{family_weight:g}"


def score(
    env_preset: str,
    seeds: list[int],
    dropouts: list[float],
    designs: list[str],
    vocabularies: list[str],
) -> dict[str, Any]:
    """Per arm and seed: the fraction read right in each set, and misread words."""
    from lcrl.text_encoder import FrozenTextEncoder
    from train.configs.presets import PRESETS
    from train.environments.tasks import find_language_wrapper, make_env
    from train.environments.text_reading import (
        CANONICAL_DESIGN,
        CANONICAL_MEMBERS,
        FAMILY_WEIGHT,
        CanonicalEncoder,
        train_reading_encoder,
    )

    cfg = PRESETS[env_preset][1]
    encoder = TokenCache(FrozenTextEncoder())
    wrapper = find_language_wrapper(make_env(cfg.env))
    train = [m for m in wrapper.split.instructions("train") if m.family in wrapper.families]
    held = validation_words()
    sets = {"validation": validation_set(train, held), **reader_sets(wrapper)}
    weights = sorted({1.0, float(FAMILY_WEIGHT)}, reverse=True)
    out: dict[str, Any] = {
        "sizes": {k: len(v) for k, v in sets.items()},
        "validation_words": sorted(held),
        "arms": {},
    }
    for design, dropout, vocabulary in itertools.product(designs, dropouts, vocabularies):
        options = DESIGNS[design] or dict(CANONICAL_DESIGN)
        wide = vocabulary == "wide"
        arms = {
            w: {"per_seed": {}, "misread": Counter(), "design": design, "dropout": dropout,
                "vocabulary": vocabulary, "family_weight": w, "options": options}
            for w in weights
        }  # fmt: skip
        for seed in seeds:
            fit = (encoder, train, seed, CANONICAL_MEMBERS, dropout, options, wide)
            t0 = time.perf_counter()
            reading = train_reading_encoder(*fit)
            fit_s = round(time.perf_counter() - t0, 1)
            validating = train_reading_encoder(*fit, exclude=held)
            for w, arm in arms.items():
                row: dict[str, Any] = {"fit_s": fit_s}
                scored = CanonicalEncoder(reading, family_weight=w)
                validated = CanonicalEncoder(validating, family_weight=w)
                for name, items in sets.items():
                    reader = validated if name == "validation" else scored
                    got = reader.meanings([t for t, _ in items])
                    pairs = list(zip(items, got, strict=True))
                    wrong = [(t, m) for (t, m), g in pairs if g != m]
                    row[name] = round(1 - len(wrong) / max(1, len(items)), 4)
                    if name == "paraphrase_forms":
                        arm["misread"].update(
                            x for t, m in wrong for x in misread_word(t, m).split()
                        )
                    if name == "paraphrase_set":
                        row["paraphrase_set_misread"] = [
                            [t, g.text] for (t, m), g in pairs if g != m
                        ]
                arm["per_seed"][str(seed)] = row
                name_ = arm_name(design, dropout, w, vocabulary)
                print(f"{name_} seed {seed}: {row}", flush=True)
        for w, arm in arms.items():
            for name in SETS:
                values = [arm["per_seed"][str(s)][name] for s in seeds]
                arm[name] = {"mean": float(np.mean(values)), "std": float(np.std(values))}
            arm["misread"] = dict(arm["misread"].most_common(12))
            out["arms"][arm_name(design, dropout, w, vocabulary)] = arm
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="lang2d", help="a language preset (its env)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--dropout",
        type=float,
        nargs="+",
        default=None,
        help="token-state dropout of each arm (default: the canonical reader's)",
    )
    parser.add_argument(
        "--designs",
        nargs="+",
        choices=sorted(DESIGNS),
        default=["per-slot"],
        help="reader designs: shared queries, or queries of each slot's own",
    )
    parser.add_argument(
        "--vocabularies",
        nargs="+",
        choices=VOCABULARIES,
        default=list(VOCABULARIES),
        help="training-only phrasings: the narrow lists (16 per meaning), or the wide ones",
    )
    parser.add_argument("--name", default="", help="the result's name (default: reader-PRESET)")
    args = parser.parse_args(argv)
    from train.configs.presets import PRESETS
    from train.environments.text_reading import CANONICAL_DROPOUT, FAMILY_WEIGHT

    if args.preset not in PRESETS or PRESETS[args.preset][1].env.goal_type != "language":
        language = sorted(k for k, v in PRESETS.items() if v[1].env.goal_type == "language")
        parser.error(f"--preset {args.preset!r}: choose a language preset ({', '.join(language)})")
    args.dropout = args.dropout or [CANONICAL_DROPOUT]
    if any(not 0.0 <= d < 1.0 for d in args.dropout):
        parser.error("--dropout values must be in [0, 1)")
    if (
        CANONICAL_DROPOUT not in args.dropout
        or "per-slot" not in args.designs
        or set(args.vocabularies) != set(VOCABULARIES)
    ):
        parser.error(
            f"the headline compares the default reader (per-slot, dropout {CANONICAL_DROPOUT}, "
            "wide) with the narrow vocabulary: keep them among the arms"
        )
    info = machine()
    res = score(args.preset, args.seeds, args.dropout, args.designs, args.vocabularies)
    new_arm = arm_name("per-slot", CANONICAL_DROPOUT, FAMILY_WEIGHT, "wide")
    base_arm = arm_name("per-slot", CANONICAL_DROPOUT, FAMILY_WEIGHT, "narrow")
    base, new = res["arms"][base_arm], res["arms"][new_arm]
    head: dict[str, Any] = {k: round(new[k]["mean"], 4) for k in SETS}
    head.update({f"{k}_baseline": round(base[k]["mean"], 4) for k in SETS})
    head["arm"], head["baseline_arm"] = new_arm, base_arm
    head["seeds"] = len(args.seeds)
    head["fit_s"] = round(float(np.mean([r["fit_s"] for r in new["per_seed"].values()])), 1)
    name = args.name or f"reader-{args.preset}"
    save_json(
        name,
        {
            "headline": head,
            "machine": info,
            "settings": vars(args),
            **res,
        },
    )
    lines = [
        "| design | dropout | vocabulary | family weight | " + " | ".join(SETS) + " |",
        "|---|---:|---|---:|" + "---|" * len(SETS),
    ]
    for name_, arm in res["arms"].items():
        cells = [f"{arm[k]['mean']:.3f} ± {arm[k]['std']:.3f}" for k in SETS]
        mark = "**" if name_ == new_arm else ""
        lines.append(
            f"| {mark}{arm['design']}{mark} | {arm['dropout']:g} | {arm['vocabulary']} | "
            f"{arm['family_weight']:g} | " + " | ".join(cells) + " |"
        )  # fmt: skip
    sizes = ", ".join(f"{k} {v}" for k, v in res["sizes"].items())
    words = "\n".join(
        f"- {d}: " + ", ".join(f"{w} ({n})" for w, n in arm["misread"].items())
        for d, arm in res["arms"].items()
    )
    missed = "\n".join(
        f"- seed {seed}: "
        + ("; ".join(f"{t!r} read as {g!r}" for t, g in row["paraphrase_set_misread"]) or "none")
        for seed, row in new["per_seed"].items()
    )
    body = (
        f"Canonical reader ({args.preset}'s split and families), fitted as a run fits it; "
        f"fraction of sentences whose meaning it reads right, mean ± sd over seeds "
        f"{args.seeds}. Sentences per set: {sizes}. Designs: `shared` (every slot pools "
        f"the tokens with the same {DESIGNS['shared']['queries']} queries), `per-slot` "
        f"(each slot with queries of its own, {new['options']}); the family weight scales "
        "the family head's log-probabilities when a meaning is decoded. Vocabularies: "
        "`narrow` (16 training-only phrasings per meaning from the `EXTRA_*` lists of "
        "`captioner/phrasings.py`), `wide` (`CANONICAL_PHRASINGS` per meaning, from those "
        "and the `WIDE_*` lists). Choices are made on `validation` alone: every other "
        "word of the narrow lists held out of a second fit, scored on sentences using "
        f"them; it uses no grammar word. Fitting one reader of the default took "
        f"{head['fit_s']} s. In bold: the default.\n\n" + "\n".join(lines)
        + f"\n\nThe default's misread sentences of the `paraphrase` set:\n\n{missed}"
        + "\n\nWords the canonical sentence lacks, counted over the misread paraphrases "
        "(summed over seeds):\n\n"
        f"{words}\n"
    )  # fmt: skip
    save_markdown(name, f"Canonical reader accuracy ({args.preset})", body, info)

    fig, ax = new_figure(figsize=(9, 4.5))
    width = 0.8 / len(res["arms"])
    for j, (d, arm) in enumerate(res["arms"].items()):
        xs = [i + (j - (len(res["arms"]) - 1) / 2) * width for i in range(len(SETS))]
        ax.bar(xs, [arm[k]["mean"] for k in SETS], width, yerr=[arm[k]["std"] for k in SETS],
               capsize=3, label=d, alpha=0.8)  # fmt: skip
    ax.set_xticks(range(len(SETS)), [k.replace("_", "\n") for k in SETS])
    ax.set(ylim=(0, 1.02), ylabel="read right (mean ± sd over seeds)")
    ax.set_title(f"canonical reader, {args.preset}")
    ax.legend(fontsize=7, ncol=2, loc="lower left")
    save_figure(name, fig, info)
    print(head)
    return 0


if __name__ == "__main__":
    sys.exit(main())

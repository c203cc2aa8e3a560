"""How well the canonical instruction reader reads phrasings it never trained on.

Run from the repository root::

    python benchmarks/reader.py   # lang2d, seeds 0 1 2: both designs, dropout 0 and 0.5

The canonical reader (``--env.canonical-reader``, :mod:`train.environments.text_reading`) is fitted,
as a run fits it, on the training instructions of the env's split and their
training-only phrasings (words the grammar does not know). It is then scored without any
policy, on:

- ``paraphrase_forms``: every sentence the grammar makes for a training meaning, the
  canonical one aside (the population the ``paraphrase`` evaluation set samples);
- ``paraphrase_set``: the split's ``paraphrase`` set itself (what ``lcrl eval`` runs);
- ``heldout``: the held-out combinations' canonical sentences;
- ``heldout_forms``: every grammar sentence of a held-out meaning.

A sentence counts as read when the reader's meaning equals the grammar's parse. An arm is
a design of the readers (``shared``: all slots pool the tokens with the same queries;
``per-slot``: each slot has queries of its own, ``CANONICAL_DESIGN``), a token-state
dropout while fitting them (``--dropout``) and the weight of the family head when a
meaning is decoded (1, and ``FAMILY_WEIGHT``: the same fitted readers, decoded twice).
The headline is the default reader (per-slot, ``CANONICAL_DROPOUT``, ``FAMILY_WEIGHT``)
beside the previous default (shared queries, ``CANONICAL_DROPOUT``, family weight 1).
The misread words are counted per arm.

Writes ``benchmarks/results/reader-<env>.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from typing import Any

import numpy as np

from benchmarks.common import (
    machine,
    new_figure,
    save_figure,
    save_json,
    save_markdown,
)

SETS = ("paraphrase_forms", "paraphrase_set", "heldout", "heldout_forms")


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


def arm_name(design: str, dropout: float, family_weight: float) -> str:
    """The name of an arm, e.g. ``per-slot d0.5 fw0.5``."""
    return f"{design} d{dropout:g} fw{family_weight:g}"


def score(
    env_preset: str, seeds: list[int], dropouts: list[float], designs: list[str]
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
    encoder = FrozenTextEncoder()
    wrapper = find_language_wrapper(make_env(cfg.env))
    train = [m for m in wrapper.split.instructions("train") if m.family in wrapper.families]
    sets = reader_sets(wrapper)
    weights = sorted({1.0, float(FAMILY_WEIGHT)}, reverse=True)
    out: dict[str, Any] = {"sizes": {k: len(v) for k, v in sets.items()}, "arms": {}}
    for design in designs:
        options = DESIGNS[design] or dict(CANONICAL_DESIGN)
        for dropout in dropouts:
            arms = {
                w: {"per_seed": {}, "misread": Counter(), "design": design, "dropout": dropout,
                    "family_weight": w, "options": options}
                for w in weights
            }  # fmt: skip
            for seed in seeds:
                t0 = time.perf_counter()
                reading = train_reading_encoder(
                    encoder, train, seed, CANONICAL_MEMBERS, dropout, options
                )
                fit_s = round(time.perf_counter() - t0, 1)
                for w, arm in arms.items():
                    reader = CanonicalEncoder(reading, family_weight=w)
                    row: dict[str, Any] = {"fit_s": fit_s}
                    for name, items in sets.items():
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
                    print(f"{arm_name(design, dropout, w)} seed {seed}: {row}", flush=True)
            for w, arm in arms.items():
                for name in SETS:
                    values = [arm["per_seed"][str(s)][name] for s in seeds]
                    arm[name] = {"mean": float(np.mean(values)), "std": float(np.std(values))}
                arm["misread"] = dict(arm["misread"].most_common(12))
                out["arms"][arm_name(design, dropout, w)] = arm
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="lang2d", help="a language preset (its env)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--dropout",
        type=float,
        nargs="+",
        default=[0.0, 0.5],
        help="token-state dropout of each arm",
    )
    parser.add_argument(
        "--designs",
        nargs="+",
        choices=sorted(DESIGNS),
        default=["shared", "per-slot"],
        help="reader designs: shared queries, or queries of each slot's own",
    )
    args = parser.parse_args(argv)
    if any(not 0.0 <= d < 1.0 for d in args.dropout):
        parser.error("--dropout values must be in [0, 1)")
    from train.environments.text_reading import CANONICAL_DROPOUT, FAMILY_WEIGHT

    if CANONICAL_DROPOUT not in args.dropout or set(args.designs) != set(DESIGNS):
        parser.error(
            f"the headline compares both designs at the default dropout {CANONICAL_DROPOUT}: "
            "keep it among --dropout and both --designs"
        )
    info = machine()
    res = score(args.preset, args.seeds, args.dropout, args.designs)
    new_arm = arm_name("per-slot", CANONICAL_DROPOUT, FAMILY_WEIGHT)
    base_arm = arm_name("shared", CANONICAL_DROPOUT, 1.0)
    base, new = res["arms"][base_arm], res["arms"][new_arm]
    head: dict[str, Any] = {k: round(new[k]["mean"], 4) for k in SETS}
    head.update({f"{k}_baseline": round(base[k]["mean"], 4) for k in SETS})
    head["arm"], head["baseline_arm"] = new_arm, base_arm
    head["seeds"] = len(args.seeds)
    name = f"reader-{args.preset}"
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
        "| design | dropout | family weight | " + " | ".join(SETS) + " |",
        "|---|---:|---:|" + "---|" * len(SETS),
    ]
    for name_, arm in res["arms"].items():
        cells = [f"{arm[k]['mean']:.3f} ± {arm[k]['std']:.3f}" for k in SETS]
        mark = "**" if name_ == new_arm else ""
        lines.append(
            f"| {mark}{arm['design']}{mark} | {arm['dropout']:g} | {arm['family_weight']:g} | "
            + " | ".join(cells) + " |"
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
        "the family head's log-probabilities when a meaning is decoded. In bold: the "
        "default.\n\n" + "\n".join(lines)
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

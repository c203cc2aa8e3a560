"""Compositional instruction splits: train, held-out combinations, paraphrases.

A split is data. It records the seed it was made from, which (family, colour, shape)
combinations are held out, and the explicit instruction lists of its three sets, so a
checkpoint that stores the split says exactly what its policy was trained on.

- ``train``: canonical sentences of every meaning not held out.
- ``heldout``: canonical sentences whose *combination* never appears in training, although
  every word in them does. A combination is a (family, colour, shape) triple for the
  object acted on: holding out ``("push", "blue", "cylinder")`` removes every "push the blue
  cylinder ..." from training, while blue things and cylinders are still pushed and the
  blue cylinder is still reached, put and stacked.
- ``paraphrase``: the meanings of training instructions in phrasings never used in
  training (synonyms and templates other than the canonical one): the policy saw the
  meaning, not the words.

The held-out choice is constrained so that within every family each colour and each shape
still occurs in training, and (when there is more than one family) every object kind is
acted on in training in some family.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from captioner.grammar import (
    FAMILIES,
    Instruction,
    all_instructions,
    parse,
    random_paraphrase,
)
from envs.scene import COLOURS, OBJECT_KINDS, SHAPES
from lcrl.errors import LcrlError

SPLIT_SETS: tuple[str, ...] = ("train", "heldout", "paraphrase")
SPLIT_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Split:
    """An instruction split. Build one with :func:`make_split`; store with :meth:`save`.

    Attributes:
        seed: the seed it was made from.
        families: the instruction families it covers.
        heldout_combos: held-out (family, colour, shape) triples, sorted.
        train, heldout, paraphrase: the instruction sentences of each set.
    """

    seed: int
    families: tuple[str, ...]
    heldout_combos: tuple[tuple[str, str, str], ...]
    train: tuple[str, ...]
    heldout: tuple[str, ...]
    paraphrase: tuple[str, ...]
    version: int = SPLIT_FORMAT_VERSION
    _parsed: dict[str, tuple[Instruction, ...]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def texts(self, name: str) -> tuple[str, ...]:
        """Sentences of one set (``train``, ``heldout`` or ``paraphrase``)."""
        if name not in SPLIT_SETS:
            raise LcrlError(f"unknown split set {name!r}; choose one of {', '.join(SPLIT_SETS)}")
        return getattr(self, name)

    def instructions(self, name: str) -> tuple[Instruction, ...]:
        """Parsed meanings of one set, aligned with :meth:`texts` (cached)."""
        if name not in self._parsed:
            self._parsed[name] = tuple(parse(t) for t in self.texts(name))
        return self._parsed[name]

    def is_heldout(self, instruction: Instruction) -> bool:
        """Whether a meaning belongs to a held-out combination."""
        return (instruction.family, instruction.colour, instruction.shape) in set(
            self.heldout_combos
        )

    def fingerprint(self) -> str:
        """Short content hash: two splits with the same fingerprint are identical."""
        payload = json.dumps(self.to_dict(), sort_keys=True).encode()
        return hashlib.sha256(payload).hexdigest()[:12]

    def to_dict(self) -> dict:
        """JSON-ready dictionary."""
        return {
            "version": self.version,
            "seed": self.seed,
            "families": list(self.families),
            "heldout_combos": [list(c) for c in self.heldout_combos],
            **{name: list(getattr(self, name)) for name in SPLIT_SETS},
        }

    @classmethod
    def from_dict(cls, d: dict) -> Split:
        """Inverse of :meth:`to_dict`; checks the format and that every sentence parses."""
        try:
            version = int(d.get("version", 0))
            if version != SPLIT_FORMAT_VERSION:
                raise LcrlError(
                    f"split format version {version} is not supported "
                    f"(this lcrl reads version {SPLIT_FORMAT_VERSION})"
                )
            split = cls(
                seed=int(d["seed"]),
                families=tuple(d["families"]),
                heldout_combos=tuple(tuple(c) for c in d["heldout_combos"]),
                train=tuple(d["train"]),
                heldout=tuple(d["heldout"]),
                paraphrase=tuple(d["paraphrase"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise LcrlError(f"not a valid split: {e!r}") from e
        for name in SPLIT_SETS:
            split.instructions(name)  # every sentence must parse
        return split

    def save(self, path: str | os.PathLike) -> Path:
        """Write the split as JSON, atomically (temporary file, then rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Split:
        """Read a split written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise LcrlError(f"split file not found: {path}")
        try:
            d = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise LcrlError(f"split file {path} is not valid JSON: {e}") from e
        return cls.from_dict(d)

    def summary(self) -> str:
        """A few human-readable lines: counts per set and family, held-out combinations."""
        lines = [f"split seed={self.seed} fingerprint={self.fingerprint()}"]
        for name in SPLIT_SETS:
            counts = {f: 0 for f in self.families}
            for ins in self.instructions(name):
                counts[ins.family] += 1
            per = ", ".join(f"{f} {n}" for f, n in counts.items())
            lines.append(f"  {name:<10} {len(self.texts(name)):>4} instructions ({per})")
        combos = ", ".join(f"{f}:{c} {s}" for f, c, s in self.heldout_combos)
        lines.append(f"  held-out combinations: {combos}")
        return "\n".join(lines)


def _valid_holdout(combos: set[tuple[str, str, str]], families: Sequence[str]) -> bool:
    for fam in families:
        kept = [(c, s) for c, s in OBJECT_KINDS if (fam, c, s) not in combos]
        if {c for c, _ in kept} != set(COLOURS) or {s for _, s in kept} != set(SHAPES):
            return False
    if len(families) == 1:
        return True  # with one family a held-out object cannot be seen acted on elsewhere
    # every object kind is acted on in training in at least one family
    return all(any((fam, c, s) not in combos for fam in families) for c, s in OBJECT_KINDS)


def make_split(
    seed: int = 0,
    families: Sequence[str] = FAMILIES,
    heldout_per_family: int = 2,
    paraphrases_per_instruction: int = 1,
    max_paraphrases: int | None = 400,
) -> Split:
    """Make a compositional split, deterministically from ``seed``.

    Args:
        seed: the only source of randomness.
        families: instruction families to include.
        heldout_per_family: object kinds held out of each family.
        paraphrases_per_instruction: random non-canonical phrasings per train meaning.
        max_paraphrases: cap on the paraphrase set (a deterministic subsample), or None.

    Returns:
        The split.

    Raises:
        LcrlError: an unknown family, or more held out than the constraints allow.
    """
    families = tuple(families)
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or not families:
        raise LcrlError(f"unknown or no instruction families {unknown}; known: {FAMILIES}")
    max_holdout = len(OBJECT_KINDS) - max(len(COLOURS), len(SHAPES))
    if not 0 <= heldout_per_family <= max_holdout:
        raise LcrlError(
            f"heldout_per_family must be between 0 and {max_holdout} so that every colour and "
            f"shape stays in training, got {heldout_per_family}"
        )
    rng = np.random.default_rng(seed)
    for _ in range(10_000):
        combos: set[tuple[str, str, str]] = set()
        for fam in families:
            picks = rng.choice(len(OBJECT_KINDS), size=heldout_per_family, replace=False)
            combos.update((fam, *OBJECT_KINDS[k]) for k in picks)
        if _valid_holdout(combos, families):
            break
    else:  # pragma: no cover - only reachable with extreme settings
        raise LcrlError("could not find a held-out set that keeps every word in training")

    meanings = all_instructions(families)
    train = [m for m in meanings if (m.family, m.colour, m.shape) not in combos]
    heldout = [m for m in meanings if (m.family, m.colour, m.shape) in combos]
    paraphrases: list[str] = []
    train_texts = {m.text for m in train}
    for m in train:
        options = set()
        for _ in range(paraphrases_per_instruction):
            options.add(random_paraphrase(m, rng))
        paraphrases.extend(sorted(options - train_texts))
    if max_paraphrases is not None and len(paraphrases) > max_paraphrases:
        keep = np.sort(rng.choice(len(paraphrases), size=max_paraphrases, replace=False))
        paraphrases = [paraphrases[k] for k in keep]
    return Split(
        seed=seed,
        families=families,
        heldout_combos=tuple(sorted(combos)),
        train=tuple(m.text for m in train),
        heldout=tuple(m.text for m in heldout),
        paraphrase=tuple(paraphrases),
    )

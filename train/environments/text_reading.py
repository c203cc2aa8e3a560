"""The token reader of ``--env.text-reader`` and ``--env.canonical-reader``: trained on the
run's training instructions and their training-only phrasings before reinforcement
learning, saved with every checkpoint, rebuilt from it for evaluation and queries
(:mod:`lcrl.text_reader`).

With ``--env.text-reader`` the policy reads the sentence vector followed by the reader's
slot probabilities. With ``--env.canonical-reader`` (:class:`CanonicalEncoder`) the reader
decides the meaning of every instruction, and the policy reads the sentence vector of
that meaning's canonical sentence: a phrasing it never trained on reaches it as the
sentence it trained on, and a canonical sentence reads as itself.
"""

from __future__ import annotations

import sys
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from captioner.grammar import (
    DIRECTIONS,
    FAMILIES,
    RELATIONAL_FAMILIES,
    RELATIONS,
    Instruction,
    InstructionParseError,
)
from captioner.phrasings import training_phrasings
from envs.scene import COLOURS, SHAPES
from lcrl.checkpoint import load_checkpoint, save_checkpoint
from lcrl.errors import LcrlError
from lcrl.text_reader import ReadingEncoder, fit_ensemble, fit_reader

#: The meaning slots the reader predicts, with their values (None: the slot is empty).
SLOT_VALUES: dict[str, tuple[Any, ...]] = {
    "family": tuple(FAMILIES),
    "colour": tuple(COLOURS),
    "shape": tuple(SHAPES),
    "direction": (None, *DIRECTIONS),
    "relation": (None, *RELATIONS),
    "target_colour": (None, *COLOURS),
    "target_shape": (None, *SHAPES),
}
#: Training-only phrasings per training instruction that a ``--env.text-reader`` reader
#: also learns from.
PHRASINGS = 16
#: Training-only phrasings per training instruction of a canonical reader, drawn from the
#: wide vocabulary (:data:`captioner.phrasings.WIDE_TEMPLATES` ...). On robosuite's five
#: families, with every other extra word of the narrow vocabulary held out of fitting,
#: the ensemble reads 0.80 of the sentences that use them right against 0.63 with 16
#: narrow phrasings, and 0.72 of the grammar's paraphrase set against 0.37 (3 seeds,
#: ``benchmarks/reader.py --preset robosuite-manip``; chosen on the first alone).
CANONICAL_PHRASINGS = 32
#: Texts per gradient step of a canonical reader's members (:func:`fit_reader`
#: ``batch_size``): a robosuite reader fits in about 2 minutes instead of 22.
READER_BATCH = 512
#: Readers in the ensemble of a canonical reader: with one, held-out word combinations
#: are misread whenever that reader tied a colour to a shape (one reader in three on the
#: reach-only splits); the mean of five read them all right on 3 splits x 3 seeds.
CANONICAL_MEMBERS = 5
#: Gradient steps of each reader a run fits (:func:`lcrl.text_reader.fit_reader`).
READER_STEPS = 600
#: Token-state dropout while fitting a canonical reader's members: with it the reader
#: reads more of the grammar's phrasings of lang2d's training meanings right, and more
#: of its phrasings of held-out meanings (``benchmarks/reader.py``: 0.964 and 0.943
#: against 0.936 and 0.838 without; weight decay, token dropout and 4x the phrasings
#: did no better with shared queries).
CANONICAL_DROPOUT = 0.5
#: The design of a canonical reader's members: every meaning slot pools the tokens with
#: queries of its own (:class:`lcrl.text_reader.TokenReader` ``per_slot``). Against
#: shared queries, on lang2d over seeds 0-2 (``benchmarks/reader.py``) it reads 0.96
#: of the grammar's phrasings of training meanings right (0.94 shared) and 0.94 of its
#: phrasings of held-out meanings (0.74 shared).
CANONICAL_DESIGN: dict[str, Any] = {"per_slot": True, "queries": 2, "hidden": 32}
#: The weight of the family head's log-probabilities when a canonical reader decodes a
#: meaning. The family is also told by which slots a sentence fills (a direction: push;
#: a relation: put), read from closed classes of words, while the family head reads the
#: verb, often one it never trained on ("move to the blue box" reads as push with a
#: confidence the direction head's "no direction" would otherwise not outweigh).
FAMILY_WEIGHT = 0.5
#: The state name of the reader in checkpoints.
STATE = "text_reader"


def reader_texts(
    train: Sequence[Instruction], phrasings: int, wide: bool, exclude: Collection[str] = ()
) -> tuple[list[str], list[Instruction]]:
    """The texts a reader fits on: every training meaning's canonical sentence and up to
    ``phrasings`` of its training-only phrasings (``wide``: from the wide vocabulary too;
    never with a word of ``exclude``), each with its meaning."""
    texts: list[str] = []
    meanings: list[Instruction] = []
    for i, m in enumerate(train):
        found = training_phrasings(m, phrasings, seed=i, wide=wide, exclude=exclude)
        for text in (m.text, *found):
            texts.append(text)
            meanings.append(m)
    return texts, meanings


def train_reading_encoder(
    encoder: Any,
    train: list[Instruction],
    seed: int = 0,
    members: int = 0,
    dropout: float | None = None,
    design: Mapping[str, Any] | None = None,
    wide: bool | None = None,
    exclude: Collection[str] = (),
) -> ReadingEncoder:
    """A reader fitted on the canonical texts of ``train`` and their training-only
    phrasings, labelled by their meaning (the values the labels use are kept as
    ``reading.seen``: per slot, the value indices the reader may answer).

    With ``members``, a canonical reader's ensemble of that many readers
    (:func:`lcrl.text_reader.fit_ensemble`): :data:`CANONICAL_PHRASINGS` phrasings per
    meaning from the wide vocabulary (``wide=False``: :data:`PHRASINGS` from the narrow
    one), minibatches of :data:`READER_BATCH`, token-state ``dropout`` (default
    :data:`CANONICAL_DROPOUT`) and the members' ``design`` (default
    :data:`CANONICAL_DESIGN`). Without, one full-batch reader on :data:`PHRASINGS`
    narrow phrasings (``--env.text-reader``). ``exclude``: words no phrasing uses."""
    wide = bool(members) if wide is None else wide
    count = CANONICAL_PHRASINGS if members and wide else PHRASINGS
    texts, meanings = reader_texts(train, count, wide, exclude)
    states, mask = encoder.encode_tokens(texts)
    labels = {
        slot: [values.index(getattr(m, slot)) for m in meanings]
        for slot, values in SLOT_VALUES.items()
    }
    slots = {slot: len(values) for slot, values in SLOT_VALUES.items()}
    if members:
        reader: Any = fit_ensemble(
            states, mask, labels, slots, members, READER_STEPS, seed=seed,
            dropout=CANONICAL_DROPOUT if dropout is None else dropout,
            batch_size=READER_BATCH,
            **(CANONICAL_DESIGN if design is None else design),
        )  # fmt: skip
    else:
        reader = fit_reader(states, mask, labels, slots, READER_STEPS, seed=seed)
    reading = ReadingEncoder(encoder, reader)
    reading.seen = {slot: sorted(set(ids)) for slot, ids in labels.items()}  # type: ignore[attr-defined]
    return reading


class CanonicalEncoder:
    """A reader in front of the frozen encoder: each text becomes the canonical sentence
    of the meaning the reader reads in it (:meth:`meanings`), and its vector is that
    sentence's (``encode``, ``dim``: the frozen encoder's, so the policy is the one a run
    without a reader has).

    Args:
        reading: a trained reader over the encoder (:func:`train_reading_encoder`).
        seen: per slot of :data:`SLOT_VALUES`, the value indices the reader may answer
            (those its training labels use); default every value.
        family_weight: the weight of the family head's log-probabilities in a meaning's
            score (:data:`FAMILY_WEIGHT`).
    """

    def __init__(
        self,
        reading: ReadingEncoder,
        seen: Mapping[str, Sequence[int]] | None = None,
        family_weight: float = FAMILY_WEIGHT,
    ) -> None:
        self.reading = reading
        self.family_weight = float(family_weight)
        self.encoder = reading.encoder
        self.reader = reading.reader
        self.dim = int(self.encoder.dim)
        found = seen if seen is not None else getattr(reading, "seen", None)
        self.seen = {
            slot: sorted(int(i) for i in (found or {}).get(slot, range(len(values))))
            for slot, values in SLOT_VALUES.items()
        }
        self._cache: dict[str, Instruction] = {}

    def meanings(self, texts: Sequence[str]) -> list[Instruction]:
        """The meaning the reader reads in each text."""
        missing = [t for t in dict.fromkeys(texts) if t not in self._cache]
        if missing:
            states, mask = self.encoder.encode_tokens(missing)
            with torch.no_grad():
                logits = self.reader(torch.as_tensor(states), torch.as_tensor(mask))
            scores = {k: v.numpy() for k, v in logits.items()}
            for i, text in enumerate(missing):
                self._cache[text] = self._decode({k: v[i] for k, v in scores.items()})
        return [self._cache[t] for t in texts]

    def canonical(self, texts: Sequence[str]) -> list[str]:
        """The canonical sentence of each text's meaning."""
        return [m.text for m in self.meanings(texts)]

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """The frozen encoder's vectors of :meth:`canonical` sentences."""
        items = list(texts)
        if not items:
            return np.zeros((0, self.dim), np.float32)
        return np.asarray(self.encoder.encode(self.canonical(items)), np.float32)

    def _values(self, slot: str, none: bool) -> list[int]:
        """The value indices of ``slot`` a meaning may take: its empty value (``none``), or
        those it may answer that are not empty."""
        values = SLOT_VALUES[slot]
        if none:
            return [values.index(None)]
        allowed = [i for i in self.seen[slot] if values[i] is not None]
        return allowed or [i for i, v in enumerate(values) if v is not None]

    def _decode(self, scores: Mapping[str, np.ndarray]) -> Instruction:
        """The most probable valid meaning under the reader's per-slot distributions: for
        each family it may answer, the best values of the slots that family fills, the
        empty value of those it leaves empty (so "move to the red cube", which names no
        direction, reads as reach rather than push), and a reference object other than
        the object; then the family whose meaning scores highest, the family head's
        log-probability weighted by ``family_weight``."""
        logp = {
            k: np.asarray(v, np.float64) - np.logaddexp.reduce(np.asarray(v, np.float64))
            for k, v in scores.items()
        }
        values = SLOT_VALUES

        def best(slot: str, none: bool) -> tuple[float, Any]:
            i = max(self._values(slot, none), key=lambda j: logp[slot][j])
            return float(logp[slot][i]), values[slot][i]

        (lc, colour), (ls, shape) = best("colour", False), best("shape", False)
        found: list[tuple[float, Instruction]] = []
        for family in (values["family"][i] for i in self._values("family", False)):
            family_logp = float(logp["family"][values["family"].index(family)])
            total = self.family_weight * family_logp + lc + ls
            fields: dict[str, Any] = {"colour": colour, "shape": shape}
            for slot, filled in (("direction", family == "push"), ("relation", family == "put")):
                score, value = best(slot, not filled)
                total += score
                if filled:
                    fields[slot] = value
            if family in RELATIONAL_FAMILIES:  # the best reference object but the object
                pairs = [
                    (logp["target_colour"][c] + logp["target_shape"][t], c, t)
                    for c in self._values("target_colour", False)
                    for t in self._values("target_shape", False)
                    if (values["target_colour"][c], values["target_shape"][t]) != (colour, shape)
                ]
                if not pairs:
                    continue
                score, c, t = max(pairs)
                fields["target_colour"] = values["target_colour"][c]
                fields["target_shape"] = values["target_shape"][t]
            else:
                score = sum(best(k, True)[0] for k in ("target_colour", "target_shape"))
            try:
                found.append((total + float(score), Instruction(family, **fields)))
            except InstructionParseError:  # a slot combination the grammar refuses
                continue
        if not found:
            raise LcrlError("the reader found no valid meaning for an instruction")
        return max(found, key=lambda f: f[0])[1]

    def __getattr__(self, name: str) -> Any:
        # everything else (the model's name, its cache) is the encoder's
        return getattr(self.encoder, name)

    def state_dict(self) -> dict[str, Any]:
        """The reader's weights, and the values it may answer (what a checkpoint keeps)."""
        return {**self.reading.state_dict(), "output": "canonical", "seen": dict(self.seen)}


def reading_encoder(
    encoder: Any, env: Any, ckpt: Any = None, seed: int = 0, canonical: bool = False
) -> ReadingEncoder | CanonicalEncoder:
    """The reader of a checkpoint (``ckpt``), or one trained on the training instructions
    of ``env``'s split and families; as a :class:`CanonicalEncoder` with ``canonical``.

    A canonical reader may be fitted for a checkpoint that holds none (its policy reads
    canonical sentences as a run without a reader does); a ``text_reader`` policy cannot
    do without the reader it trained with, nor can the two kinds stand in for each other.
    """
    if ckpt is not None and ckpt.has_state(STATE):
        state = ckpt.state(STATE)
        saved = str(state.get("output", "append"))
        if saved != ("canonical" if canonical else "append"):
            raise LcrlError(
                f"this checkpoint's reader was trained with --env."
                f"{'canonical' if saved == 'canonical' else 'text'}-reader; evaluate it "
                "with its own config"
            )
        reading = ReadingEncoder.from_state(encoder, state)
        return CanonicalEncoder(reading, state.get("seen")) if canonical else reading
    if ckpt is not None and not canonical:
        raise LcrlError(
            "this checkpoint was trained without --env.text-reader (it holds no reader): "
            "evaluate it with its own config"
        )
    from train.environments.tasks import find_language_wrapper

    wrapper = find_language_wrapper(env)
    # a checkpoint's reader reads the families it was trained on, whatever the families
    # of this run (``lcrl eval --families``): one reader per checkpoint, never refitted
    trained = ((ckpt.meta.get("config") or {}).get("env") or {}).get("families") if ckpt else None
    families = tuple(trained) if trained else wrapper.families
    train = [m for m in wrapper.split.instructions("train") if m.family in families]
    if canonical and ckpt is not None:
        return cached_canonical_reader(encoder, ckpt.path, train, seed)
    if canonical:
        return CanonicalEncoder(train_reading_encoder(encoder, train, seed, CANONICAL_MEMBERS))
    return train_reading_encoder(encoder, train, seed)


#: The folder beside a checkpoint's files where a canonical reader fitted for it is kept.
READER_CACHE = "canonical-reader"


def _reader_key(train: Sequence[Instruction], seed: int, encoder: Any) -> dict[str, Any]:
    """What a fitted reader depends on: the training meanings, the seed, the encoder and
    the reader's design."""
    return {
        "train": [m.text for m in train],
        "seed": int(seed),
        "encoder": str(getattr(encoder, "name", type(encoder).__name__)),
        "members": CANONICAL_MEMBERS,
        "steps": READER_STEPS,
        "phrasings": CANONICAL_PHRASINGS,
        "vocabulary": "wide",
        "batch": READER_BATCH,
        "dropout": CANONICAL_DROPOUT,
        "design": dict(CANONICAL_DESIGN),
    }


def cached_canonical_reader(
    encoder: Any, checkpoint: Any, train: Sequence[Instruction], seed: int
) -> CanonicalEncoder:
    """The canonical reader of a checkpoint that holds none (one kept with its weights
    and configs only, or trained without a reader): fitted from its split's training
    instructions (what its instruction table was built from) and kept in
    ``CHECKPOINT/canonical-reader`` so that later commands load it instead of fitting it
    again. A cache fitted for other instructions, seed or encoder is fitted anew; a
    checkpoint folder that cannot be written is read from, not written to."""
    folder = Path(checkpoint) / READER_CACHE
    key = _reader_key(train, seed, encoder)
    if (folder / "meta.json").is_file():
        try:
            cached = load_checkpoint(folder)
            if cached.meta.get("reader") == key and cached.has_state(STATE):
                state = cached.state(STATE)
                return CanonicalEncoder(ReadingEncoder.from_state(encoder, state), state["seen"])
        except LcrlError as e:
            print(f"lcrl: note: the cached reader in {folder} is not used ({e})", file=sys.stderr)
    print(
        f"lcrl: fitting a canonical reader for {checkpoint} from its {len(train)} training "
        "instructions (once; it is kept beside the checkpoint)",
        file=sys.stderr,
        flush=True,
    )
    reader = CanonicalEncoder(train_reading_encoder(encoder, list(train), seed, CANONICAL_MEMBERS))
    try:
        state = {STATE: reader.state_dict()}
        save_checkpoint(folder, modules={}, states=state, meta={"reader": key})
    except (LcrlError, OSError) as e:
        print(f"lcrl: note: the reader could not be kept in {folder} ({e})", file=sys.stderr)
    return reader

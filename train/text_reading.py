"""The token reader of ``--env.text-reader``: trained on the run's training instructions
and their training-only phrasings before reinforcement learning, saved with every
checkpoint, rebuilt from it for evaluation and queries (:mod:`lcrl.text_reader`)."""

from __future__ import annotations

from typing import Any

from captioner.grammar import DIRECTIONS, FAMILIES, RELATIONS, Instruction
from captioner.phrasings import training_phrasings
from envs.scene import COLOURS, SHAPES
from lcrl.errors import LcrlError
from lcrl.text_reader import ReadingEncoder, fit_reader

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
#: Training-only phrasings per training instruction that the reader also learns from.
PHRASINGS = 16
#: The state name of the reader in checkpoints.
STATE = "text_reader"


def train_reading_encoder(encoder: Any, train: list[Instruction], seed: int = 0) -> ReadingEncoder:
    """A reader fitted on the canonical texts of ``train`` and :data:`PHRASINGS` phrasings
    of each, labelled by their meaning."""
    texts: list[str] = []
    meanings: list[Instruction] = []
    for i, m in enumerate(train):
        for text in (m.text, *training_phrasings(m, PHRASINGS, seed=i)):
            texts.append(text)
            meanings.append(m)
    states, mask = encoder.encode_tokens(texts)
    labels = {
        slot: [values.index(getattr(m, slot)) for m in meanings]
        for slot, values in SLOT_VALUES.items()
    }
    slots = {slot: len(values) for slot, values in SLOT_VALUES.items()}
    return ReadingEncoder(encoder, fit_reader(states, mask, labels, slots, seed=seed))


def reading_encoder(encoder: Any, env: Any, ckpt: Any = None, seed: int = 0) -> ReadingEncoder:
    """The reader of a checkpoint (``ckpt``), or one trained on the training instructions
    of ``env``'s split and families."""
    if ckpt is not None:
        if not ckpt.has_state(STATE):
            raise LcrlError(
                "this checkpoint was trained without --env.text-reader (it holds no reader): "
                "evaluate it with its own config"
            )
        return ReadingEncoder.from_state(encoder, ckpt.state(STATE))
    from train.tasks import find_language_wrapper

    wrapper = find_language_wrapper(env)
    train = [m for m in wrapper.split.instructions("train") if m.family in wrapper.families]
    return train_reading_encoder(encoder, train, seed)

"""The token-level instruction reader (``--env.text-reader``, :mod:`lcrl.text_reader`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import tiny

from lcrl.checkpoint import load_checkpoint
from lcrl.errors import LcrlError
from lcrl.text_reader import ReadingEncoder, fit_reader
from train.evaluate import resolve_checkpoint
from train.loop import Trainer
from train.text_reading import SLOT_VALUES, reading_encoder


def test_the_reader_learns_which_token_carries_a_slot():
    """The label is carried by one token whose position varies: attention over tokens
    finds it where the mean over tokens blurs it with the rest."""
    rng = np.random.default_rng(0)
    n, t, d = 240, 6, 16
    words = rng.normal(size=(3, d)).astype(np.float32)  # three "direction" words
    states = rng.normal(size=(n, t, d)).astype(np.float32) * 0.5
    mask = np.ones((n, t), bool)
    labels = rng.integers(0, 3, n)
    where = rng.integers(0, t, n)
    states[np.arange(n), where] = words[labels]
    reader = fit_reader(states, mask, {"direction": labels}, {"direction": 3}, steps=300)
    with torch.no_grad():
        logits = reader(torch.as_tensor(states), torch.as_tensor(mask))["direction"]
    assert (logits.argmax(-1).numpy() == labels).mean() > 0.95
    assert not any(p.requires_grad for p in reader.parameters())  # frozen


class _Encoder:
    """A stand-in frozen encoder: token states from a fixed table of words."""

    dim = 8

    def __init__(self) -> None:
        self.vocab: dict[str, np.ndarray] = {}

    def _vec(self, word: str) -> np.ndarray:
        if word not in self.vocab:
            seed = sum(map(ord, word))
            self.vocab[word] = np.random.default_rng(seed).normal(size=self.dim)
        return self.vocab[word].astype(np.float32)

    def encode_tokens(self, texts):
        longest = max(len(t.split()) for t in texts)
        states = np.zeros((len(texts), longest, self.dim), np.float32)
        mask = np.zeros((len(texts), longest), bool)
        for i, text in enumerate(texts):
            for j, w in enumerate(text.split()):
                states[i, j], mask[i, j] = self._vec(w), True
        return states, mask

    def encode(self, texts):
        states, mask = self.encode_tokens(texts)
        return (states.sum(1) / mask.sum(1, keepdims=True)).astype(np.float32)


def test_reading_encoder_rows_are_the_sentence_vector_and_a_soft_parse():
    enc = _Encoder()
    texts = ["go left now", "go right now", "left go", "right go"]
    states, mask = enc.encode_tokens(texts)
    reader = fit_reader(states, mask, {"d": [0, 1, 0, 1], "v": [0, 0, 0, 0]}, {"d": 2, "v": 3})
    reading = ReadingEncoder(enc, reader)
    rows = reading.encode(["go left now", "right go"])
    assert rows.shape == (2, enc.dim + 5) and rows.dtype == np.float32
    np.testing.assert_allclose(rows[:, : enc.dim], enc.encode(["go left now", "right go"]))
    probs = rows[:, enc.dim :]
    np.testing.assert_allclose(probs[:, :2].sum(1), 1.0, atol=1e-5)  # one slot after another
    np.testing.assert_allclose(probs[:, 2:].sum(1), 1.0, atol=1e-5)
    # the weights travel in a checkpoint's state and give the same rows back
    again = ReadingEncoder.from_state(enc, reading.state_dict())
    np.testing.assert_array_equal(again.encode(["go left now", "right go"]), rows)
    assert reading.encode([]).shape == (0, enc.dim + 5)


def test_a_run_with_the_reader_saves_it_and_queries_read_through_it(tmp_path):
    out = tmp_path / "run"
    cfg = tiny("lang2d-grounded", out, total_steps=200)
    cfg.env.text_reader = True
    trainer = Trainer(cfg)
    try:
        encoder = trainer.task.encoder
        assert isinstance(encoder, ReadingEncoder)
        width = encoder.encoder.dim + sum(len(v) for v in SLOT_VALUES.values())
        assert trainer.task.embeddings.shape[1] == width
        # the training instructions' parse: the reader names their family
        families = SLOT_VALUES["family"]
        fam = trainer.task.embeddings[:, encoder.encoder.dim : encoder.encoder.dim + len(families)]
        parsed = [trainer.task.captioner.parse(t).family for t in trainer.task.table]
        assert np.mean([families[i] == f for i, f in zip(fam.argmax(1), parsed, strict=True)]) > 0.9
        trainer.run()
    finally:
        trainer.close()
    ckpt = load_checkpoint(resolve_checkpoint(out))
    assert ckpt.has_state("text_reader")
    import lcrl

    policy = lcrl.load(out)
    text = "shove the red block to the left side"
    np.testing.assert_allclose(
        policy.task.encoder.encode([text]), encoder.encode([text]), atol=1e-6
    )


def test_a_checkpoint_without_a_reader_is_a_clear_error(tmp_path):
    out = tmp_path / "run"
    trainer = Trainer(tiny("lang2d", out, total_steps=200))
    try:
        trainer.run()
        with pytest.raises(LcrlError, match="trained without"):
            reading_encoder(
                trainer.task.encoder, trainer.env, load_checkpoint(resolve_checkpoint(out))
            )
    finally:
        trainer.close()

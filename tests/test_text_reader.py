"""The token-level instruction reader (``--env.text-reader``, :mod:`lcrl.text_reader`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import tiny

from lcrl.checkpoint import load_checkpoint
from lcrl.errors import LcrlError
from lcrl.text_reader import ReadingEncoder, fit_reader, keep_mask
from train.environments.text_reading import SLOT_VALUES, reading_encoder
from train.evaluation.evaluate import resolve_checkpoint
from train.training.loop import Trainer


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


def test_reader_dropout_is_seeded_learns_and_refuses_bad_values():
    """Token-state dropout while fitting draws from the seed: the same seed fits the same
    reader, the reader still learns the slot, and a fraction outside [0, 1) is refused."""
    rng = np.random.default_rng(1)
    n, t, d = 120, 5, 16
    words = rng.normal(size=(2, d)).astype(np.float32)
    states = rng.normal(size=(n, t, d)).astype(np.float32) * 0.5
    mask = np.ones((n, t), bool)
    labels = rng.integers(0, 2, n)
    states[np.arange(n), rng.integers(0, t, n)] = words[labels]
    fit = {"labels": {"d": labels}, "slots": {"d": 2}, "steps": 200, "seed": 3}
    a = fit_reader(states, mask, dropout=0.3, **fit)
    b = fit_reader(states, mask, dropout=0.3, **fit)
    plain = fit_reader(states, mask, **fit)
    x, m = torch.as_tensor(states), torch.as_tensor(mask)
    with torch.no_grad():
        la, lb, lp = a(x, m)["d"], b(x, m)["d"], plain(x, m)["d"]
    torch.testing.assert_close(la, lb)
    assert not torch.allclose(la, lp)  # the dropout did change the fit
    assert (la.argmax(-1).numpy() == labels).mean() > 0.95
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="dropout"):
            fit_reader(states, mask, dropout=bad, **fit)


@pytest.mark.parametrize("p", [0.5, 0.3, 0.9])
def test_the_dropout_mask_zeroes_the_fraction_asked_from_the_generator(p):
    """keep_mask: uint8 ones and zeros, zeros at rate p (to 1/256), an odd element count
    included, drawn from the generator given (the same seed gives the same mask)."""
    shape = torch.Size((64, 7, 33))
    a = keep_mask(shape, p, torch.Generator().manual_seed(5))
    b = keep_mask(shape, p, torch.Generator().manual_seed(5))
    c = keep_mask(shape, p, torch.Generator().manual_seed(6))
    assert a.shape == shape and a.dtype == torch.uint8 and set(a.unique().tolist()) == {0, 1}
    assert torch.equal(a, b) and not torch.equal(a, c)
    dropped = 1.0 - a.float().mean().item()
    assert abs(dropped - round(p * 256) / 256) < 0.01, dropped
    # the product keeps the kept elements as they are and zeroes the rest
    x = torch.randn(shape)
    kept = x * a
    assert torch.equal(kept[a == 1], x[a == 1]) and (kept[a == 0] == 0).all()


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


def test_an_ensemble_of_readers_averages_them_and_round_trips():
    from lcrl.text_reader import fit_ensemble

    enc = _Encoder()
    texts = ["go left now", "go right now", "left go", "right go"]
    states, mask = enc.encode_tokens(texts)
    labels, slots = {"d": [0, 1, 0, 1], "v": [0, 0, 0, 0]}, {"d": 2, "v": 3}
    ensemble = fit_ensemble(states, mask, labels, slots, members=3)
    x, m = torch.as_tensor(states), torch.as_tensor(mask)
    with torch.no_grad():
        mean = torch.stack([r(x, m)["d"].log_softmax(-1) for r in ensemble.members]).mean(0)
        np.testing.assert_allclose(ensemble(x, m)["d"], mean, atol=1e-6)
        assert (ensemble(x, m)["d"].argmax(-1).numpy() == labels["d"]).all()
    reading = ReadingEncoder(enc, ensemble)
    state = reading.state_dict()
    assert state["members"] == 3
    again = ReadingEncoder.from_state(enc, state)
    np.testing.assert_array_equal(again.encode(texts), reading.encode(texts))
    assert ReadingEncoder(enc, ensemble.members[0]).state_dict()["members"] == 0


def test_a_per_slot_reader_reads_each_slot_from_its_own_token_and_round_trips():
    """With queries of its own per slot, each head finds the token of its slot; the
    design travels in the state, and a state saved before the option reads as shared."""
    rng = np.random.default_rng(2)
    n, t, d = 240, 6, 16
    words = {"a": rng.normal(size=(3, d)), "b": rng.normal(size=(2, d))}
    states = rng.normal(size=(n, t, d)).astype(np.float32) * 0.5
    mask = np.ones((n, t), bool)
    labels = {"a": rng.integers(0, 3, n), "b": rng.integers(0, 2, n)}
    where = np.stack([rng.permutation(t)[:2] for _ in range(n)])  # two distinct positions
    states[np.arange(n), where[:, 0]] = words["a"][labels["a"]]
    states[np.arange(n), where[:, 1]] = words["b"][labels["b"]]
    reader = fit_reader(
        states, mask, labels, {"a": 3, "b": 2}, steps=300, per_slot=True, queries=2, hidden=16
    )
    assert reader.per_slot and reader.query.out_features == 4
    with torch.no_grad():
        logits = reader(torch.as_tensor(states), torch.as_tensor(mask))
    for k in ("a", "b"):
        assert (logits[k].argmax(-1).numpy() == labels[k]).mean() > 0.95, k
    enc = _Encoder()
    enc.dim = d
    state = ReadingEncoder(enc, reader).state_dict()
    assert state["per_slot"] is True and state["queries"] == 2 and state["hidden"] == 16
    again = ReadingEncoder.from_state(enc, state).reader
    with torch.no_grad():
        torch.testing.assert_close(again(torch.as_tensor(states), torch.as_tensor(mask)), logits)
    shared = fit_reader(states, mask, labels, {"a": 3, "b": 2}, steps=1)
    old = ReadingEncoder(enc, shared).state_dict()
    del old["per_slot"]  # as saved before the option existed
    assert not ReadingEncoder.from_state(enc, old).reader.per_slot


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


def _canonical_on_split(seed: int = 0):
    """A canonical reader fitted (as a run fits it) on the lang2d reach and push split."""
    from captioner.splits import make_split
    from lcrl.text_encoder import FrozenTextEncoder
    from train.environments.text_reading import (
        CANONICAL_MEMBERS,
        CanonicalEncoder,
        train_reading_encoder,
    )

    split = make_split(0, ("reach", "push"))
    train = list(split.instructions("train"))
    reading = train_reading_encoder(FrozenTextEncoder(), train, seed, CANONICAL_MEMBERS)
    return split, CanonicalEncoder(reading)


def test_the_canonical_reader_keeps_canonical_sentences_and_canonicalises_phrasings():
    """Training sentences read as themselves; held-out combinations (seen words, unseen
    pairs) as themselves; most unseen phrasings of the grammar as their meaning's
    canonical sentence; the vectors are the frozen encoder's of those sentences."""
    from captioner.grammar import parse

    split, canonical = _canonical_on_split()
    train = [m.text for m in split.instructions("train")]
    assert canonical.canonical(train) == train
    heldout = [m.text for m in split.instructions("heldout")]
    assert canonical.canonical(heldout) == heldout
    para = list(split.paraphrase)
    right = [c == parse(t).text for t, c in zip(para, canonical.canonical(para), strict=True)]
    assert np.mean(right) >= 0.8, np.mean(right)
    rows = canonical.encode(para[:3])
    assert rows.shape == (3, canonical.dim) and canonical.dim == canonical.encoder.dim
    np.testing.assert_allclose(rows, canonical.encoder.encode(canonical.canonical(para[:3])))
    # families, colours and directions the training labels never use are never answered
    assert {m.family for m in canonical.meanings(["stack the red cube on the blue cube"])} <= {
        "reach",
        "push",
    }


def test_the_canonical_decoder_gives_valid_meanings():
    """Scores that favour an invalid meaning (a reference object equal to the object)
    decode to the best valid one."""
    from train.environments.text_reading import CanonicalEncoder

    enc = _Encoder()
    slots = {k: len(v) for k, v in SLOT_VALUES.items()}
    states, mask = enc.encode_tokens(["a b", "c d"])
    reader = fit_reader(states, mask, {k: [0, 0] for k in slots}, slots, steps=1)
    canonical = CanonicalEncoder(ReadingEncoder(enc, reader))
    scores = {k: np.zeros(n, np.float32) for k, n in slots.items()}

    def favour(slot: str, value) -> None:
        scores[slot][SLOT_VALUES[slot].index(value)] = 5.0

    favour("family", "stack")
    favour("colour", "red")
    favour("shape", "cube")
    favour("target_colour", "red")  # the object itself: refused
    favour("target_shape", "cube")
    scores["target_colour"][SLOT_VALUES["target_colour"].index("blue")] = 4.0
    scores["target_colour"][SLOT_VALUES["target_colour"].index(None)] = 9.0  # never None
    meaning = canonical._decode(scores)
    assert meaning.text == "stack the red cube on the blue cube"
    favour("family", "push")
    scores["family"][SLOT_VALUES["family"].index("stack")] = 0.0
    scores["direction"][SLOT_VALUES["direction"].index(None)] = 6.0  # a push names one
    favour("direction", "left")
    assert canonical._decode(scores).text == "push the red cube left"
    # a confident family head against a confident "no direction": the family head's
    # log-probability counts at half weight, so the sentence reads as reach; at full
    # weight the family head alone would decide
    for k in scores:
        scores[k][:] = 0.0
    favour("colour", "red")
    favour("shape", "cube")
    scores["family"][SLOT_VALUES["family"].index("push")] = 10.0
    scores["direction"][SLOT_VALUES["direction"].index(None)] = 9.0
    assert canonical._decode(scores).text == "reach the red cube"
    full = CanonicalEncoder(ReadingEncoder(enc, reader), family_weight=1.0)
    assert full._decode(scores).family == "push"
    # the state keeps the values it may answer
    state = canonical.state_dict()
    assert state["output"] == "canonical" and set(state["seen"]) == set(SLOT_VALUES)


def test_a_run_with_the_canonical_reader_saves_it_and_eval_can_add_one(
    tmp_path, tiny_canonical_reader
):
    """Training with --env.canonical-reader keeps the policy's goal width and saves the
    reader; queries read through it. A checkpoint without a reader gets one fitted by
    ``lcrl eval --canonical-reader``; a --env.text-reader checkpoint cannot swap readers."""
    from train.commands.cli import EvalCommand
    from train.environments.simulators import check_env_config
    from train.environments.text_reading import CanonicalEncoder

    # saving, loading and fitting for eval are what is checked (tiny_canonical_reader)
    out = tmp_path / "run"
    cfg = tiny("lang2d-grounded", out, total_steps=200)
    cfg.env.canonical_reader = True
    trainer = Trainer(cfg)
    try:
        encoder = trainer.task.encoder
        assert isinstance(encoder, CanonicalEncoder)
        assert trainer.task.embeddings.shape[1] == encoder.encoder.dim
        trainer.run()
    finally:
        trainer.close()
    ckpt = load_checkpoint(resolve_checkpoint(out))
    assert ckpt.state("text_reader")["output"] == "canonical"
    import lcrl

    policy = lcrl.load(out)
    text = "shove the red block to the left"
    assert policy.task.encoder.canonical([text]) == encoder.canonical([text])
    with pytest.raises(LcrlError, match="canonical-reader; evaluate"):  # saved: canonical
        reading_encoder(encoder.encoder, trainer.env, ckpt, canonical=False)
    # both readers at once, or a reader without language goals: one-line errors
    cfg.env.text_reader = True
    with pytest.raises(LcrlError, match="choose one"):
        check_env_config(cfg.env)
    cfg.env.text_reader = cfg.env.canonical_reader = False
    plain = tmp_path / "plain"
    trainer = Trainer(tiny("lang2d", plain, total_steps=200))
    try:
        trainer.run()
    finally:
        trainer.close()
    doc = tmp_path / "eval.json"
    EvalCommand(
        str(plain),
        episodes=4,
        sets=("paraphrase",),
        canonical_reader=True,
        json=str(doc),
        progress=False,
        num_envs=1,
    ).run()
    import json

    saved = json.loads(doc.read_text())
    assert saved["settings"]["canonical_reader"] is True
    assert saved["settings"]["command"].endswith("--canonical-reader")
    assert saved["sets"]["paraphrase"]["episodes"] == 4


def test_minibatch_fitting_is_repeatable_learns_and_refuses_bad_sizes():
    """Minibatches drawn from the seed's generator: the same seed fits the same reader,
    another seed another; the fit still learns the labels; a negative size is refused."""
    rng = np.random.default_rng(0)
    states = rng.normal(size=(64, 5, 8)).astype(np.float32)
    mask = np.ones((64, 5), bool)
    labels = (states[:, 1, 0] > 0).astype(np.int64)
    states[:, 1, 1] = np.where(labels == 1, 2.0, -2.0)
    fit = dict(labels={"d": labels.tolist()}, slots={"d": 2}, steps=200, batch_size=16)
    a = fit_reader(states, mask, seed=1, **fit)
    b = fit_reader(states, mask, seed=1, **fit)
    c = fit_reader(states, mask, seed=2, **fit)
    x, m = torch.as_tensor(states), torch.as_tensor(mask)
    with torch.no_grad():
        la, lb, lc = a(x, m)["d"], b(x, m)["d"], c(x, m)["d"]
    assert torch.equal(la, lb) and not torch.equal(la, lc)
    assert (la.argmax(-1).numpy() == labels).mean() >= 0.95
    with pytest.raises(ValueError, match="batch_size"):
        fit_reader(states, mask, {"d": [0] * 64}, {"d": 2}, steps=1, batch_size=-1)

"""Instruction augmentation with training-only phrasings (``--env.phrasings``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from captioner.grammar import (
    DIRECTION_WORDS,
    FAMILIES,
    RELATION_WORDS,
    SHAPE_WORDS,
    TEMPLATES,
    all_instructions,
    parse,
    surface_forms,
)
from captioner.phrasings import (
    EXTRA_DIRECTION_WORDS,
    EXTRA_RELATION_WORDS,
    EXTRA_SHAPE_WORDS,
    EXTRA_TEMPLATES,
    training_phrasings,
)
from captioner.splits import make_split
from lcrl.algos import SAC, AgentOptions, Problem
from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from lcrl.nets import NetConfig


def test_phrasings_are_new_words_never_grammar_sentences() -> None:
    """The extra words are not the grammar's; no phrasing parses or is a surface form of
    any meaning; every phrasing keeps the colours; draws are distinct and repeatable."""
    for extra, grammar in (
        (EXTRA_SHAPE_WORDS, SHAPE_WORDS),
        (EXTRA_DIRECTION_WORDS, DIRECTION_WORDS),
        (EXTRA_RELATION_WORDS, RELATION_WORDS),
        (EXTRA_TEMPLATES, TEMPLATES),
    ):
        assert set(extra) == set(grammar)
        for key, words in extra.items():
            assert not set(words) & set(grammar[key]), key
    meanings = all_instructions(FAMILIES)
    forms = {t for m in meanings[::7] for t in surface_forms(m)}
    for m in meanings[::7]:
        found = training_phrasings(m, 12, seed=3)
        assert len(found) == 12 and len(set(found)) == 12
        assert found == training_phrasings(m, 12, seed=3)
        assert found != training_phrasings(m, 12, seed=4)
        assert not set(found) & forms
        for text in found:
            assert m.colour in text
            with pytest.raises(LcrlError):
                parse(text)
    # a meaning with few combinations gives what there is, never the canonical sentence
    reach = parse("reach the red cube")
    everything = training_phrasings(reach, 1000)
    combinations = (1 + len(EXTRA_TEMPLATES["reach"])) * (1 + len(EXTRA_SHAPE_WORDS["cube"]))
    assert len(everything) == combinations - 1 and reach.text not in everything


def test_phrasings_never_hit_the_paraphrase_set() -> None:
    """What the augmentation trains on and what the paraphrase set evaluates are
    disjoint."""
    split = make_split(0, families=("reach", "push"))
    trained = {t for m in split.instructions("train") for t in training_phrasings(m, 64)}
    assert trained and not trained & set(split.paraphrase)


def _agent(share: float = 0.5):
    rng = np.random.default_rng(0)
    table = rng.normal(size=(4, 8)).astype(np.float32)

    def embed(ids, device):
        return torch.as_tensor(table[np.asarray(ids, np.int64)], device=device)

    prob = Problem({"observation": (5,)}, "text", (8,), 2)
    agent = SAC(prob, AgentOptions(net=NetConfig(hidden=(16,)), seed=0), embed)
    agent.observe({}, table)
    return agent, table


def test_updates_read_other_phrasings_in_a_share_of_rows() -> None:
    """With phrasings, about ``share`` of the rows of goal ids that have some read one of
    them (never a slot past the id's count); ids without any, acting, and agents without
    phrasings read the instruction's own embedding."""
    agent, _ = _agent()
    variants = np.full((3, 2, 8), 100.0, np.float32)
    variants[:, 1] = -100.0
    counts = np.array([2, 1, 0])
    agent.set_phrasings(variants, counts, share=0.5)
    ids = np.repeat(np.arange(4), 500)
    raw = agent.batch_goal(ids)
    plain = agent.goal_tensor(ids)
    changed = ~torch.isclose(raw, plain).all(-1)
    for i, low, high in ((0, 0.4, 0.6), (1, 0.4, 0.6), (2, 0.0, 0.0), (3, 0.0, 0.0)):
        share = float(changed[ids == i].float().mean())
        assert low <= share <= high, (i, share)
    big = agent.norms["goal"](torch.full((1, 8), 100.0))
    small = agent.norms["goal"](torch.full((1, 8), -100.0))
    rows0 = raw[torch.as_tensor(ids == 0) & changed]
    assert torch.isclose(rows0, big).all(-1).any() and torch.isclose(rows0, small).all(-1).any()
    rows1 = raw[torch.as_tensor(ids == 1) & changed]
    assert torch.isclose(rows1, big).all(-1).all()  # id 1 has only its first phrasing
    # the update path reads them; acting does not
    batch = Batch(
        obs={"observation": np.zeros((6, 5), np.float32)},
        action=np.zeros((6, 2), np.float32),
        reward=np.zeros(6, np.float32),
        next_obs={"observation": np.zeros((6, 5), np.float32)},
        terminated=np.zeros(6, np.float32),
        goal=np.zeros(6, np.int64),
        relabelled=np.zeros(6, bool),
        index=np.arange(6),
    )
    assert np.isfinite(agent.update(batch)["critic_loss"])
    a1 = agent.act({"observation": np.zeros((1, 5), np.float32)}, np.zeros(1, np.int64), True)
    fresh, _ = _agent()
    a2 = fresh.act({"observation": np.zeros((1, 5), np.float32)}, np.zeros(1, np.int64), True)
    assert a1.shape == a2.shape
    torch.testing.assert_close(fresh.batch_goal(ids), fresh.goal_tensor(ids))


def test_bad_phrasings_are_clear_errors() -> None:
    agent, _ = _agent()
    with pytest.raises(LcrlError, match=r"\(ids, P, d\)"):
        agent.set_phrasings(np.zeros((3, 8), np.float32), np.zeros(3, np.int64))
    with pytest.raises(LcrlError, match="between 0 and 2"):
        agent.set_phrasings(np.zeros((3, 2, 8), np.float32), np.array([0, 3, 1]))
    with pytest.raises(LcrlError, match=r"\(0, 1\]"):
        agent.set_phrasings(np.zeros((3, 2, 8), np.float32), np.array([0, 1, 1]), share=0)


def test_training_embeds_phrasings_for_the_updates(tmp_path) -> None:
    """``--env.phrasings`` embeds that many phrasings per training instruction once, gives
    them to the learner and to the goal normaliser's statistics; evaluation needs none."""
    import dataclasses

    from helpers import tiny

    from train.training.loop import Trainer, text_goal_sample

    base = tiny("lang2d-quick", tmp_path / "run", total_steps=200)
    cfg = dataclasses.replace(base, env=dataclasses.replace(base.env, phrasings=3))
    trainer = Trainer(cfg)
    try:
        task = trainer.task
        variants, counts = task.phrasing_embeddings()
        assert variants.shape == (task.num_train, 3, task.embeddings.shape[1])
        assert (counts == 3).all()
        assert trainer.agent.phrasings is not None
        assert len(text_goal_sample(task)) == task.num_train * 4
        # the phrasings are the encoder's vectors of training-only sentences
        from captioner.grammar import parse

        text = training_phrasings(parse(task.table[0]), 3, seed=0)[1]
        np.testing.assert_allclose(variants[0, 1], task.embed_fn([text])[0], atol=1e-5)
    finally:
        trainer.close()


def test_the_wide_vocabulary_adds_new_words_and_exclude_drops_words():
    """The reader's wide lists share no word with the grammar or the narrow lists; its
    phrasings never parse nor hit the paraphrase set; ``exclude`` keeps a word out."""
    from captioner.phrasings import (
        WIDE_DIRECTION_WORDS,
        WIDE_RELATION_WORDS,
        WIDE_SHAPE_WORDS,
        WIDE_TEMPLATES,
    )

    for wide, extra, grammar in (
        (WIDE_SHAPE_WORDS, EXTRA_SHAPE_WORDS, SHAPE_WORDS),
        (WIDE_DIRECTION_WORDS, EXTRA_DIRECTION_WORDS, DIRECTION_WORDS),
        (WIDE_RELATION_WORDS, EXTRA_RELATION_WORDS, RELATION_WORDS),
        (WIDE_TEMPLATES, EXTRA_TEMPLATES, TEMPLATES),
    ):
        assert set(wide) == set(grammar)
        for key, words in wide.items():
            assert len(set(words)) == len(words)
            assert not set(words) & (set(grammar[key]) | set(extra[key])), key
    grammar_shapes = {w for ws in SHAPE_WORDS.values() for w in ws}
    for words in WIDE_SHAPE_WORDS.values():  # no grammar noun hides inside a new one
        assert not any(set(w.split()) & grammar_shapes for w in words)
    split = make_split(0, families=FAMILIES)
    meanings = list(split.instructions("train"))[::9]
    forms = {t for m in meanings for t in surface_forms(m)}
    for m in meanings:
        narrow = set(training_phrasings(m, 10**6))
        wide = training_phrasings(m, 64, seed=1, wide=True)
        assert len(wide) == 64 and set(wide) - narrow  # new words among them
        assert not set(wide) & (forms | set(split.paraphrase))
        for text in wide:
            assert m.colour in text
            with pytest.raises(LcrlError):
                parse(text)
    push = parse("push the red cube left")
    kept = training_phrasings(push, 10**6, exclude={"brick", "drag {obj} {dir}"})
    assert kept and not any("brick" in t or t.startswith("drag ") for t in kept)
    assert len(kept) < len(training_phrasings(push, 10**6))

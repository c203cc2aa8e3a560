"""The reader benchmark's scored sets: every grammar phrasing of the training meanings
(never the canonical sentence), the split's paraphrase set, and the held-out meanings."""

from __future__ import annotations

from types import SimpleNamespace

from benchmarks.reader import misread_word, reader_sets
from captioner.grammar import parse, surface_forms
from captioner.splits import make_split


def test_the_sets_hold_what_each_must_read_as():
    split = make_split(0, ("reach", "push"))
    sets = reader_sets(SimpleNamespace(split=split, families=("push",)))
    train = [m for m in split.instructions("train") if m.family == "push"]
    forms = sets["paraphrase_forms"]
    assert len(forms) == sum(len(list(surface_forms(m))) - 1 for m in train)
    assert all(parse(t) == m and t != m.text for t, m in forms)  # paraphrases only
    assert all(m.family == "push" for _, m in sets["paraphrase_set"])
    assert {m.text for _, m in sets["heldout"]} == {
        m.text for m in split.instructions("heldout") if m.family == "push"
    }
    assert all(parse(t) == m for t, m in sets["heldout_forms"])
    truth = parse("push the red cube backward")
    assert misread_word("push the red cube back", truth) == "back"
    assert misread_word("push the red cube backward", truth) == "(canonical words)"


def test_the_validation_set_uses_held_out_extra_words_and_no_grammar_word():
    """The choice's set: narrow phrasings of training meanings that each use a word held
    out of the validation readers' fitting; what those readers fit on never uses one."""
    from benchmarks.reader import VALIDATION_PER_MEANING, validation_set, validation_words
    from captioner.grammar import try_parse
    from captioner.phrasings import EXTRA_SHAPE_WORDS, training_phrasings

    held = validation_words()
    assert "square" in held and "brick" not in held  # every other word: the second ...
    assert set(EXTRA_SHAPE_WORDS["cube"][1::2]) <= held
    split = make_split(0, ("reach", "push"))
    train = list(split.instructions("train"))[:6]
    items = validation_set(train, held)
    assert len(items) == VALIDATION_PER_MEANING * len(train)
    assert items == validation_set(train, held)  # the same draw every time
    for text, m in items:
        assert try_parse(text) is None and m in train
        fitted = training_phrasings(m, 10**6, exclude=held)
        assert text not in fitted
        assert not any(f" {w} " in f" {t} " for t in fitted for w in held if " " not in w)


def test_the_token_cache_encodes_each_text_once_and_pads_as_the_encoder_does():
    import numpy as np

    from benchmarks.reader import TokenCache

    class Words:  # one token state per word, the word's length in every feature
        dim, name, calls = 3, "words", 0

        def encode_tokens(self, texts):
            self.calls += len(texts)
            longest = max(len(t.split()) for t in texts)
            states = np.zeros((len(texts), longest, 3), np.float32)
            mask = np.zeros((len(texts), longest), bool)
            for i, t in enumerate(texts):
                for j, w in enumerate(t.split()):
                    states[i, j], mask[i, j] = len(w), True
            return states, mask

    inner = Words()
    cache = TokenCache(inner)
    texts = ["reach the red cube", "push it", "reach the red cube"]
    states, mask = cache.encode_tokens(texts)
    want_states, want_mask = Words().encode_tokens(texts)
    np.testing.assert_array_equal(states, want_states)
    np.testing.assert_array_equal(mask, want_mask)
    assert inner.calls == 2  # the repeated text once
    states, mask = cache.encode_tokens(["push it"])
    assert states.shape == (1, 2, 3) and mask.all() and inner.calls == 2
    assert cache.name == "words"


def test_a_preset_without_language_goals_is_a_one_line_error(capsys):
    import pytest

    from benchmarks.reader import main

    for preset in ("nonexistent", "state2d"):
        with pytest.raises(SystemExit) as stop:
            main(["--preset", preset])
        assert stop.value.code == 2
        assert "choose a language preset" in capsys.readouterr().err

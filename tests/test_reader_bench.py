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

"""Compositional splits: no leakage, every word in training, determinism, serialisation."""

import json

import pytest

from captioner.grammar import FAMILIES, FAMILIES_2D, all_instructions
from captioner.splits import Split, make_split
from envs.scene import COLOURS, OBJECT_KINDS, SHAPES
from lcrl.errors import LcrlError


@pytest.fixture(scope="module", params=[0, 1, 7])
def split(request):
    return make_split(request.param)


def combo(ins):
    return (ins.family, ins.colour, ins.shape)


def test_no_heldout_combination_leaks_into_train(split):
    held = set(split.heldout_combos)
    assert held, "a split must hold something out"
    train = split.instructions("train")
    assert all(combo(i) not in held for i in train)
    assert all(combo(i) in held for i in split.instructions("heldout"))
    assert not set(split.train) & set(split.heldout)


def test_sets_partition_the_grammar(split):
    every = {m.text for m in all_instructions(split.families)}
    assert set(split.train) | set(split.heldout) == every
    assert len(split.train) + len(split.heldout) == len(every)


def test_every_word_of_heldout_appears_in_training(split):
    train = split.instructions("train")
    for fam in split.families:
        fam_train = [i for i in train if i.family == fam]
        assert {i.colour for i in fam_train} == set(COLOURS), fam
        assert {i.shape for i in fam_train} == set(SHAPES), fam
    acted_on = {i.obj for i in train}
    assert acted_on == set(OBJECT_KINDS)
    train_words = {w for t in split.train for w in t.split()}
    for t in split.heldout:
        assert set(t.split()) <= train_words, t


def test_paraphrases_are_new_words_for_seen_meanings(split):
    train_meanings = set(split.instructions("train"))
    assert len(split.paraphrase) > 50
    assert not set(split.paraphrase) & set(split.train)
    assert all(m in train_meanings for m in split.instructions("paraphrase"))


def test_deterministic_given_seed():
    a, b, c = make_split(3), make_split(3), make_split(4)
    assert a == b and a.fingerprint() == b.fingerprint()
    assert a.heldout_combos != c.heldout_combos or a.paraphrase != c.paraphrase


def test_save_load_roundtrip(tmp_path, split):
    path = split.save(tmp_path / "split.json")
    again = Split.load(path)
    assert again == split and again.fingerprint() == split.fingerprint()
    assert json.loads(path.read_text())["seed"] == split.seed


def test_family_subset_and_counts():
    s = make_split(0, FAMILIES_2D, heldout_per_family=3)
    assert set(s.families) == set(FAMILIES_2D)
    assert {i.family for i in s.instructions("train")} == set(FAMILIES_2D)
    assert len({c for c in s.heldout_combos}) == 3 * len(FAMILIES_2D)
    assert s.is_heldout(s.instructions("heldout")[0])
    assert not s.is_heldout(s.instructions("train")[0])


def test_bad_arguments_and_files(tmp_path):
    with pytest.raises(LcrlError, match="unknown"):
        make_split(0, ("reach", "fly"))
    with pytest.raises(LcrlError, match="heldout_per_family"):
        make_split(0, FAMILIES, heldout_per_family=7)
    with pytest.raises(LcrlError, match="not found"):
        Split.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(LcrlError, match="not valid JSON"):
        Split.load(bad)
    d = make_split(0).to_dict()
    d["train"] = ["push the purple cube left"]
    with pytest.raises(LcrlError, match="purple"):
        Split.from_dict(d)
    d = make_split(0).to_dict()
    d["version"] = 99
    with pytest.raises(LcrlError, match="version"):
        Split.from_dict(d)

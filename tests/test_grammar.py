"""Grammar: canonical forms, paraphrases, parsing and clear errors."""

import pytest

from captioner.grammar import (
    FAMILIES,
    Instruction,
    InstructionParseError,
    all_instructions,
    explain,
    parse,
    surface_forms,
)
from envs.scene import COLOURS, SHAPES


def test_every_family_and_object_kind_is_covered():
    meanings = all_instructions()
    assert {m.family for m in meanings} == set(FAMILIES)
    assert len(COLOURS) >= 4 and len(SHAPES) >= 2
    counts = {f: sum(m.family == f for m in meanings) for f in FAMILIES}
    n_obj = len(COLOURS) * len(SHAPES)
    assert counts == {
        "reach": n_obj,
        "push": n_obj * 4,
        "put": n_obj * (n_obj - 1) * 4,
        "lift": n_obj,
        "stack": n_obj * (n_obj - 1),
    }


def test_every_surface_form_parses_back_to_its_meaning():
    n_forms = 0
    for meaning in all_instructions():
        forms = list(surface_forms(meaning))
        assert forms[0] == meaning.text
        assert len(forms) == len(set(forms))
        for text in forms:
            assert parse(text) == meaning, text
        n_forms += len(forms)
    assert n_forms > 10_000


@pytest.mark.parametrize(
    ("text", "canonical"),
    [
        ("Shove the red block to the left, please!", "push the red cube left"),
        ("slide the blue can away from you", "push the blue cylinder forward"),
        ("push the green tube back", "push the green cylinder backward"),
        ("touch a yellow box", "reach the yellow cube"),
        ("go to the red cylinder", "reach the red cylinder"),
        (
            "move the blue cube to the left of the green cylinder",
            "put the blue cube left of the green cylinder",
        ),
        (
            "place the red can in back of the yellow block",
            "put the red cylinder behind the yellow cube",
        ),
        ("pick the green cube up", "lift the green cube"),
        (
            "put the yellow box on top of the red cylinder",
            "stack the yellow cube on the red cylinder",
        ),
        ("  PUSH   the RED cube   RIGHT  ", "push the red cube right"),
    ],
)
def test_paraphrases_and_synonyms(text, canonical):
    assert parse(text).text == canonical


def test_push_and_put_are_told_apart_by_the_whole_sentence():
    assert parse("move the red cube to the left").family == "push"
    assert parse("move the red cube to the left of the blue cube").family == "put"
    assert parse("put the red cube on top of the blue cube").family == "stack"


def test_slots_and_objects():
    ins = parse("put the red cube in front of the blue cylinder")
    assert ins.slots() == {
        "family": "put",
        "colour": "red",
        "shape": "cube",
        "relation": "in front of",
        "target_colour": "blue",
        "target_shape": "cylinder",
    }
    assert ins.objects == (("red", "cube"), ("blue", "cylinder"))
    assert str(ins) == "put the red cube in front of the blue cylinder"


def test_unknown_colour_says_what_was_understood():
    with pytest.raises(InstructionParseError) as e:
        parse("push the purple cube left")
    msg = str(e.value)
    assert "'purple'" in msg and "unknown" in msg
    assert "'push' = a push verb" in msg
    assert "'cube' = a shape (cube)" in msg
    for colour in COLOURS:
        assert colour in msg


@pytest.mark.parametrize("text", ["", "   ", "?!", "please"])
def test_empty_instruction(text):
    with pytest.raises(InstructionParseError, match="empty instruction"):
        parse(text)


def test_unparseable_and_non_string():
    with pytest.raises(InstructionParseError, match="cannot parse"):
        parse("push the red cube diagonally")
    with pytest.raises(InstructionParseError, match="cannot parse"):
        parse("red cube")
    with pytest.raises(InstructionParseError, match="must be a string"):
        parse(42)  # type: ignore[arg-type]


def test_same_object_twice_is_rejected():
    with pytest.raises(InstructionParseError, match="same"):
        parse("stack the red cube on the red block")


def test_invalid_meanings_are_rejected():
    with pytest.raises(InstructionParseError, match="colour"):
        Instruction("reach", "purple", "cube")
    with pytest.raises(InstructionParseError, match="direction"):
        Instruction("push", "red", "cube")
    with pytest.raises(InstructionParseError, match="reference object"):
        Instruction("put", "red", "cube", relation="behind")


def test_explain_lists_unknown_words():
    text = explain("make me a sandwich")
    assert "'sandwich'" in text and "'make'" in text

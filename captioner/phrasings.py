"""Training-only phrasings: instruction augmentation with words the grammar does not know.

A policy trained on canonical sentences alone reads every other phrasing of the same
meaning ("nudge the red block left") as a point of the frozen encoder's space it never
trained on. Training on several phrasings of each instruction teaches it which changes
of wording do not change the meaning.

The phrasings here use synonyms and templates that are *not* in the grammar
(:mod:`captioner.grammar`): the grammar's other surface forms make up the ``paraphrase``
evaluation set (:mod:`captioner.splits`), so training on these never trains on a phrasing
that set evaluates. No phrasing here parses (``tests/test_phrasings.py`` checks it), so
none is also a grammar sentence.
"""

from __future__ import annotations

import numpy as np

from captioner.grammar import (
    DIRECTION_WORDS,
    RELATION_WORDS,
    SHAPE_WORDS,
    TEMPLATES,
    Instruction,
    try_parse,
)

#: Shape synonyms the grammar does not know.
EXTRA_SHAPE_WORDS: dict[str, tuple[str, ...]] = {
    "cube": ("brick", "square", "cuboid", "crate", "dice", "carton", "cubic object"),
    "cylinder": (
        "barrel",
        "drum",
        "pillar",
        "tin",
        "pipe",
        "canister",
        "jar",
        "column",
        "round object",
        "cylindrical object",
    ),
}
#: Direction phrases the grammar does not know (viewer frame, as the grammar's).
EXTRA_DIRECTION_WORDS: dict[str, tuple[str, ...]] = {
    "left": (
        "towards the left",
        "in the left direction",
        "sideways left",
        "to my left",
        "toward the left-hand side",
    ),
    "right": (
        "towards the right",
        "in the right direction",
        "sideways right",
        "to my right",
        "toward the right-hand side",
    ),
    "forward": (
        "further away",
        "away from the camera",
        "ahead",
        "away from me",
        "toward the far side",
        "farther off",
    ),
    "backward": (
        "closer",
        "towards the camera",
        "nearer",
        "toward me",
        "closer to me",
        "toward the near side",
    ),
}
#: Relation phrases the grammar does not know.
EXTRA_RELATION_WORDS: dict[str, tuple[str, ...]] = {
    "left of": ("to the left side of", "leftward of"),
    "right of": ("to the right side of", "rightward of"),
    "in front of": ("before", "nearer than"),
    "behind": ("beyond", "farther than"),
}
#: Templates the grammar does not know, per family.
EXTRA_TEMPLATES: dict[str, tuple[str, ...]] = {
    "reach": (
        "get to {obj}",
        "approach {obj}",
        "go near {obj}",
        "reach for {obj}",
        "put the hand on {obj}",
        "bring the gripper to {obj}",
        "poke {obj}",
        "press {obj}",
        "contact {obj}",
        "head for {obj}",
        "travel to {obj}",
        "proceed to {obj}",
        "come to {obj}",
        "navigate to {obj}",
        "head over to {obj}",
        "drive the gripper to {obj}",
    ),
    "push": (
        "drag {obj} {dir}",
        "shift {obj} {dir}",
        "displace {obj} {dir}",
        "send {obj} {dir}",
        "propel {obj} {dir}",
        "roll {obj} {dir}",
        "bump {obj} {dir}",
        "relocate {obj} {dir}",
        "budge {obj} {dir}",
        "carry {obj} {dir}",
    ),
    "put": ("set {obj} {rel} {obj2}", "bring {obj} {rel} {obj2}", "drag {obj} {rel} {obj2}"),
    "lift": ("hoist {obj}", "elevate {obj}", "get {obj} off the table"),
    "stack": ("pile {obj} onto {obj2}", "heap {obj} onto {obj2}", "rest {obj} upon {obj2}"),
}


def _options(instruction: Instruction) -> dict[str, tuple[str, ...]]:
    """Per field, the canonical word first, then the extra ones."""
    fam = instruction.family
    out = {
        "template": (TEMPLATES[fam][0], *EXTRA_TEMPLATES[fam]),
        "shape": (SHAPE_WORDS[instruction.shape][0], *EXTRA_SHAPE_WORDS[instruction.shape]),
    }
    if instruction.direction is not None:
        d = instruction.direction
        out["dir"] = (DIRECTION_WORDS[d][0], *EXTRA_DIRECTION_WORDS[d])
    if instruction.relation is not None:
        r = instruction.relation
        out["rel"] = (RELATION_WORDS[r][0], *EXTRA_RELATION_WORDS[r])
    if instruction.target_shape is not None:
        ts = instruction.target_shape
        out["shape2"] = (SHAPE_WORDS[ts][0], *EXTRA_SHAPE_WORDS[ts])
    return out


def training_phrasings(instruction: Instruction, count: int, seed: int = 0) -> list[str]:
    """Up to ``count`` distinct training-only phrasings of ``instruction``, drawn
    deterministically from ``seed``: each field (template, shape words, direction or
    relation) is its canonical word or one of the extra ones above, and at least one is
    an extra one, so none is a sentence of the grammar.

    Args:
        instruction: the meaning.
        count: phrasings wanted (fewer come back when the combinations run out).
        seed: seed of the draw.

    Returns:
        The phrasings, in the order drawn.
    """
    options = _options(instruction)
    names = list(options)
    sizes = [len(options[k]) for k in names]
    total = int(np.prod(sizes)) - 1  # every combination but the all-canonical one
    rng = np.random.default_rng(seed)
    picks = rng.permutation(total)[: max(0, count)] + 1
    out: list[str] = []
    for code in picks:
        choice = {}
        for name, size in zip(names, sizes, strict=True):
            choice[name] = options[name][int(code) % size]
            code = int(code) // size
        fields = {"obj": f"the {instruction.colour} {choice['shape']}"}
        if "dir" in choice:
            fields["dir"] = choice["dir"]
        if "rel" in choice:
            fields["rel"] = choice["rel"]
        if "shape2" in choice:
            fields["obj2"] = f"the {instruction.target_colour} {choice['shape2']}"
        text = choice["template"].format(**fields)
        if try_parse(text) is None:  # never a grammar sentence
            out.append(text)
    return out

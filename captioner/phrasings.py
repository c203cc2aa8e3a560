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

from collections.abc import Collection

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


#: More words the grammar does not know, for the instruction reader only
#: (``training_phrasings(..., wide=True)``; :mod:`train.environments.text_reading`). A
#: reader that met more synonyms of each meaning reads more of the words it never met:
#: on words of the lists above held out from fitting, robosuite's reader read 0.46 of
#: the sentences right when fitted on a quarter of those lists and 0.59 on half. Verbs
#: are shared across families here (``shift`` pushes, ``shift ... left of ...`` puts, ``set
#: ... upon ...`` stacks), so that a reader tells a family by the sentence's structure (a
#: direction; a relation and a second object) as well as by its verb.
WIDE_SHAPE_WORDS: dict[str, tuple[str, ...]] = {
    "cube": (
        "parcel", "package", "chest", "case", "square piece", "cubic piece", "square prism",
        "angular object", "die", "cubelet", "square solid", "hexahedron", "trunk",
    ),
    "cylinder": (
        "rod", "post", "pole", "cup", "mug", "bottle", "pot", "log", "spool", "bucket",
        "vase", "flask", "round piece", "cylindrical piece", "round solid", "capsule",
    ),
}  # fmt: skip
WIDE_DIRECTION_WORDS: dict[str, tuple[str, ...]] = {
    "left": (
        "leftward", "over leftward", "toward the left side", "a bit leftward",
        "in a leftward direction", "to the port side",
    ),
    "right": (
        "rightward", "over rightward", "toward the right side", "a bit rightward",
        "in a rightward direction", "to the starboard side",
    ),
    "forward": (
        "farther away", "further from me", "away", "onward", "to the far end", "outward",
        "deeper into the table", "further off",
    ),
    "backward": (
        "nearer to me", "toward the viewer", "in my direction", "close to me",
        "near the camera", "toward the near edge", "inward", "this way", "to the near end",
    ),
}  # fmt: skip
WIDE_RELATION_WORDS: dict[str, tuple[str, ...]] = {
    "left of": ("on the left side of", "at the left of", "left-hand of", "by the left side of"),
    "right of": (
        "on the right side of", "at the right of", "right-hand of", "by the right side of",
    ),
    "in front of": ("closer than", "nearer to me than", "on the near side of", "at the front of"),
    "behind": ("farther away than", "on the far side of", "at the rear of", "past"),
}  # fmt: skip
WIDE_TEMPLATES: dict[str, tuple[str, ...]] = {
    "reach": (
        "find {obj}", "point at {obj}", "hover over {obj}", "visit {obj}",
        "make contact with {obj}", "bring your hand to {obj}", "put your gripper on {obj}",
        "get close to {obj}", "stop at {obj}", "arrive at {obj}",
    ),
    "push": (
        "transfer {obj} {dir}", "guide {obj} {dir}", "steer {obj} {dir}", "sweep {obj} {dir}",
        "scoot {obj} {dir}", "jostle {obj} {dir}", "bring {obj} {dir}", "set {obj} {dir}",
    ),
    "put": (
        "transfer {obj} {rel} {obj2}", "guide {obj} {rel} {obj2}",
        "relocate {obj} {rel} {obj2}", "shift {obj} {rel} {obj2}",
        "carry {obj} {rel} {obj2}", "leave {obj} {rel} {obj2}",
        "arrange {obj} {rel} {obj2}", "deposit {obj} {rel} {obj2}",
        "drop {obj} {rel} {obj2}",
    ),
    "lift": (
        "hold {obj} up in the air", "take {obj} off the table", "heave {obj} upward",
        "hold {obj} aloft", "haul {obj} upward", "get {obj} into the air",
        "carry {obj} upward", "bring {obj} up off the table",
    ),
    "stack": (
        "set {obj} upon {obj2}", "balance {obj} atop {obj2}", "lay {obj} onto {obj2}",
        "mount {obj} onto {obj2}", "sit {obj} atop {obj2}", "load {obj} onto {obj2}",
        "deposit {obj} upon {obj2}", "drop {obj} onto {obj2}", "rest {obj} atop {obj2}",
    ),
}  # fmt: skip


def _options(instruction: Instruction, wide: bool = False) -> dict[str, tuple[str, ...]]:
    """Per field, the canonical word first, then the extra ones (and the wide ones)."""
    fam = instruction.family

    def words(
        grammar: dict[str, tuple[str, ...]],
        extra: dict[str, tuple[str, ...]],
        more: dict[str, tuple[str, ...]],
        key: str,
    ) -> tuple[str, ...]:
        return (grammar[key][0], *extra[key], *(more[key] if wide else ()))

    shapes = (SHAPE_WORDS, EXTRA_SHAPE_WORDS, WIDE_SHAPE_WORDS)
    out = {
        "template": words(TEMPLATES, EXTRA_TEMPLATES, WIDE_TEMPLATES, fam),
        "shape": words(*shapes, instruction.shape),
    }
    if instruction.direction is not None:
        out["dir"] = words(
            DIRECTION_WORDS, EXTRA_DIRECTION_WORDS, WIDE_DIRECTION_WORDS, instruction.direction
        )
    if instruction.relation is not None:
        out["rel"] = words(
            RELATION_WORDS, EXTRA_RELATION_WORDS, WIDE_RELATION_WORDS, instruction.relation
        )
    if instruction.target_shape is not None:
        out["shape2"] = words(*shapes, instruction.target_shape)
    return out


def training_phrasings(
    instruction: Instruction,
    count: int,
    seed: int = 0,
    wide: bool = False,
    exclude: Collection[str] = (),
) -> list[str]:
    """Up to ``count`` distinct training-only phrasings of ``instruction``, drawn
    deterministically from ``seed``: each field (template, shape words, direction or
    relation) is its canonical word or one of the extra ones above, and at least one is
    an extra one, so none is a sentence of the grammar.

    Args:
        instruction: the meaning.
        count: phrasings wanted (fewer come back when the combinations run out).
        seed: seed of the draw.
        wide: draw from the wide vocabulary too (``WIDE_*``; the instruction reader's).
        exclude: extra words, phrases and templates never to use (a validation split of
            the vocabulary, ``benchmarks/reader.py``); canonical words always stay.

    Returns:
        The phrasings, in the order drawn.
    """
    options = {
        k: (v[0], *(w for w in v[1:] if w not in exclude))
        for k, v in _options(instruction, wide).items()
    }
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

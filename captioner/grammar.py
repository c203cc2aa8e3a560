"""Instruction grammar: families with slots, canonical text, paraphrases and a parser.

An :class:`Instruction` is the *meaning* of an instruction: a family plus slot values.
Its :attr:`Instruction.text` is the canonical sentence; every other phrasing the grammar
knows (synonyms, paraphrase templates) parses back to the same ``Instruction``.

Families and their canonical forms (``{obj}`` is ``<colour> <shape>``)::

    reach   reach the {obj}                       touch / go to / move to ...
    push    push the {obj} {direction}            shove / slide / move ...
    put     put the {obj} {relation} the {obj2}   place / move ...
    lift    lift the {obj}                        pick up / raise ...
    stack   stack the {obj} on the {obj2}         put ... on top of ...

Directions are left, right, forward, backward; relations are left of, right of, in front
of, behind.

Directions and relations are in the viewer frame (see :mod:`envs.scene`): ``forward`` is
away from the viewer, ``behind X`` is farther from the viewer than X, ``in front of X`` is
nearer to the viewer than X.

``reach``, ``push`` and ``put`` are the 2D families (the fast tabletop); ``lift`` and
``stack`` need a third dimension (the robosuite tabletop).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from envs.scene import COLOURS, OBJECT_KINDS, SHAPES
from lcrl.errors import LcrlError

FAMILIES: tuple[str, ...] = ("reach", "push", "put", "lift", "stack")
FAMILIES_2D: tuple[str, ...] = ("reach", "push", "put")
DIRECTIONS: tuple[str, ...] = ("left", "right", "forward", "backward")
RELATIONS: tuple[str, ...] = ("left of", "right of", "in front of", "behind")
#: Families whose instructions name a second (reference) object.
RELATIONAL_FAMILIES: tuple[str, ...] = ("put", "stack")

#: Unit vectors of each direction in the viewer frame (x right, y away from the viewer).
DIRECTION_VECTORS: dict[str, tuple[float, float]] = {
    "left": (-1.0, 0.0),
    "right": (1.0, 0.0),
    "forward": (0.0, 1.0),
    "backward": (0.0, -1.0),
}
#: ``A <relation> B`` holds when A - B points along this vector (see the rule captioner).
RELATION_VECTORS: dict[str, tuple[float, float]] = {
    "left of": (-1.0, 0.0),
    "right of": (1.0, 0.0),
    "in front of": (0.0, -1.0),
    "behind": (0.0, 1.0),
}

# --- surface forms ------------------------------------------------------------------------
# The first entry of every list is the canonical word or template.
SHAPE_WORDS: dict[str, tuple[str, ...]] = {
    "cube": ("cube", "block", "box"),
    "cylinder": ("cylinder", "can", "tube"),
}
DIRECTION_WORDS: dict[str, tuple[str, ...]] = {
    "left": ("left", "to the left", "leftwards"),
    "right": ("right", "to the right", "rightwards"),
    "forward": ("forward", "forwards", "away from you"),
    "backward": ("backward", "backwards", "back", "towards you"),
}
RELATION_WORDS: dict[str, tuple[str, ...]] = {
    "left of": ("left of", "to the left of", "on the left of"),
    "right of": ("right of", "to the right of", "on the right of"),
    "in front of": ("in front of",),
    "behind": ("behind", "in back of"),
}
#: Templates per family. ``{obj}``/``{obj2}`` render with an article ("the red cube").
TEMPLATES: dict[str, tuple[str, ...]] = {
    "reach": (
        "reach {obj}",
        "touch {obj}",
        "go to {obj}",
        "move to {obj}",
        "move the gripper to {obj}",
        "tap {obj}",
    ),
    "push": (
        "push {obj} {dir}",
        "shove {obj} {dir}",
        "slide {obj} {dir}",
        "move {obj} {dir}",
        "nudge {obj} {dir}",
    ),
    "put": (
        "put {obj} {rel} {obj2}",
        "place {obj} {rel} {obj2}",
        "move {obj} {rel} {obj2}",
        "push {obj} {rel} {obj2}",
        "position {obj} {rel} {obj2}",
    ),
    "lift": (
        "lift {obj}",
        "pick up {obj}",
        "pick {obj} up",
        "raise {obj}",
        "lift up {obj}",
    ),
    "stack": (
        "stack {obj} on {obj2}",
        "stack {obj} on top of {obj2}",
        "put {obj} on top of {obj2}",
        "place {obj} on {obj2}",
        "place {obj} on top of {obj2}",
    ),
}
#: Words that carry no meaning and are dropped before parsing.
FILLER_WORDS: tuple[str, ...] = ("please", "now", "can you", "could you")


class InstructionParseError(LcrlError):
    """An instruction the grammar cannot parse. The message says what was understood."""


@dataclass(frozen=True, order=True)
class Instruction:
    """The meaning of an instruction: a family and its slot values.

    Attributes:
        family: one of :data:`FAMILIES`.
        colour, shape: the object acted on.
        direction: for ``push``: one of :data:`DIRECTIONS`.
        relation: for ``put``: one of :data:`RELATIONS`.
        target_colour, target_shape: the reference object of ``put`` and ``stack``.
    """

    family: str
    colour: str
    shape: str
    direction: str | None = None
    relation: str | None = None
    target_colour: str | None = None
    target_shape: str | None = None

    def __post_init__(self) -> None:
        problems = []
        if self.family not in FAMILIES:
            problems.append(f"family {self.family!r} (known: {', '.join(FAMILIES)})")
        if self.colour not in COLOURS:
            problems.append(f"colour {self.colour!r} (known: {', '.join(COLOURS)})")
        if self.shape not in SHAPES:
            problems.append(f"shape {self.shape!r} (known: {', '.join(SHAPES)})")
        needs_dir = self.family == "push"
        if needs_dir != (self.direction is not None) or (
            needs_dir and self.direction not in DIRECTIONS
        ):
            problems.append(f"direction {self.direction!r} for family {self.family!r}")
        needs_rel = self.family == "put"
        if needs_rel != (self.relation is not None) or (
            needs_rel and self.relation not in RELATIONS
        ):
            problems.append(f"relation {self.relation!r} for family {self.family!r}")
        needs_target = self.family in RELATIONAL_FAMILIES
        has_target = self.target_colour is not None or self.target_shape is not None
        if needs_target != has_target:
            problems.append(f"reference object for family {self.family!r}")
        elif needs_target:
            if self.target_colour not in COLOURS or self.target_shape not in SHAPES:
                problems.append(f"reference object {self.target_colour} {self.target_shape}")
            elif (self.target_colour, self.target_shape) == (self.colour, self.shape):
                problems.append("the object and the reference object are the same")
        if problems:
            raise InstructionParseError("invalid instruction: " + "; ".join(problems))

    @property
    def obj(self) -> tuple[str, str]:
        """(colour, shape) of the object acted on."""
        return (self.colour, self.shape)

    @property
    def target(self) -> tuple[str, str] | None:
        """(colour, shape) of the reference object, or ``None``."""
        if self.target_colour is None or self.target_shape is None:
            return None
        return (self.target_colour, self.target_shape)

    @property
    def objects(self) -> tuple[tuple[str, str], ...]:
        """Every object the instruction names, acted-on object first."""
        return (self.obj,) if self.target is None else (self.obj, self.target)

    @property
    def text(self) -> str:
        """Canonical sentence, e.g. ``"push the red cube left"``."""
        return render(self, 0, 0, 0, 0)

    def slots(self) -> dict[str, str]:
        """Slot values by name (only the slots this family has)."""
        out = {"family": self.family, "colour": self.colour, "shape": self.shape}
        if self.direction is not None:
            out["direction"] = self.direction
        if self.relation is not None:
            out["relation"] = self.relation
        if self.target is not None:
            out["target_colour"], out["target_shape"] = self.target
        return out

    def __str__(self) -> str:
        return self.text


def render(
    instruction: Instruction, template: int, shape_word: int, slot_word: int, target_word: int
) -> str:
    """Render an instruction with the given surface-form choices (indices wrap around).

    Args:
        instruction: the meaning to render.
        template: index into ``TEMPLATES[family]``.
        shape_word: index into ``SHAPE_WORDS[shape]`` for the object acted on.
        slot_word: index into the direction or relation synonyms.
        target_word: index into ``SHAPE_WORDS`` for the reference object.

    Returns:
        The sentence. ``render(i, 0, 0, 0, 0)`` is the canonical text.
    """
    templates = TEMPLATES[instruction.family]

    def pick(options: tuple[str, ...], k: int) -> str:
        return options[k % len(options)]

    fields = {"obj": f"the {instruction.colour} {pick(SHAPE_WORDS[instruction.shape], shape_word)}"}
    if instruction.direction is not None:
        fields["dir"] = pick(DIRECTION_WORDS[instruction.direction], slot_word)
    if instruction.relation is not None:
        fields["rel"] = pick(RELATION_WORDS[instruction.relation], slot_word)
    if instruction.target is not None:
        tc, ts = instruction.target
        fields["obj2"] = f"the {tc} {pick(SHAPE_WORDS[ts], target_word)}"
    return pick(templates, template).format(**fields)


def surface_forms(instruction: Instruction) -> Iterator[str]:
    """Every distinct sentence the grammar produces for this meaning, canonical first."""
    fam = instruction.family
    n_slot = 1
    if instruction.direction is not None:
        n_slot = len(DIRECTION_WORDS[instruction.direction])
    elif instruction.relation is not None:
        n_slot = len(RELATION_WORDS[instruction.relation])
    n_target = len(SHAPE_WORDS[instruction.target_shape]) if instruction.target_shape else 1
    seen: set[str] = set()
    for t in range(len(TEMPLATES[fam])):
        for s in range(len(SHAPE_WORDS[instruction.shape])):
            for d in range(n_slot):
                for g in range(n_target):
                    text = render(instruction, t, s, d, g)
                    if text not in seen:
                        seen.add(text)
                        yield text


def all_instructions(families: Iterable[str] = FAMILIES) -> list[Instruction]:
    """Every meaning of the given families over all object kinds, in a fixed order."""
    out: list[Instruction] = []
    for fam in families:
        if fam not in FAMILIES:
            raise LcrlError(f"unknown instruction family {fam!r}; known: {', '.join(FAMILIES)}")
        for colour, shape in OBJECT_KINDS:
            if fam in ("reach", "lift"):
                out.append(Instruction(fam, colour, shape))
            elif fam == "push":
                out.extend(Instruction(fam, colour, shape, direction=d) for d in DIRECTIONS)
            else:
                for tc, ts in OBJECT_KINDS:
                    if (tc, ts) == (colour, shape):
                        continue
                    if fam == "put":
                        out.extend(
                            Instruction(
                                fam, colour, shape, relation=r, target_colour=tc, target_shape=ts
                            )
                            for r in RELATIONS
                        )
                    else:
                        out.append(
                            Instruction(fam, colour, shape, target_colour=tc, target_shape=ts)
                        )
    return out


# --- parser -------------------------------------------------------------------------------


def _alt(words: Iterable[str]) -> str:
    # Longest first so that "to the left of" wins over "left".
    return "|".join(re.escape(w) for w in sorted(set(words), key=len, reverse=True))


_COLOUR_RE = _alt(COLOURS)
_SHAPE_WORD_TO_SHAPE = {w: shape for shape, words in SHAPE_WORDS.items() for w in words}
_SHAPE_RE = _alt(_SHAPE_WORD_TO_SHAPE)
_DIR_WORD_TO_DIR = {w: d for d, words in DIRECTION_WORDS.items() for w in words}
_REL_WORD_TO_REL = {w: r for r, words in RELATION_WORDS.items() for w in words}


def _object_re(tag: str) -> str:
    return rf"(?:(?:the|a|an) )?(?P<c{tag}>{_COLOUR_RE}) (?P<s{tag}>{_SHAPE_RE})"


def _compile(template: str) -> re.Pattern[str]:
    pattern = re.escape(template)
    pattern = pattern.replace(re.escape("{obj2}"), _object_re("2"))
    pattern = pattern.replace(re.escape("{obj}"), _object_re("1"))
    pattern = pattern.replace(re.escape("{dir}"), rf"(?P<dir>{_alt(_DIR_WORD_TO_DIR)})")
    pattern = pattern.replace(re.escape("{rel}"), rf"(?P<rel>{_alt(_REL_WORD_TO_REL)})")
    return re.compile(pattern.replace(r"\ ", " "))


_PATTERNS: tuple[tuple[str, re.Pattern[str]], ...] = tuple(
    (fam, _compile(t)) for fam in FAMILIES for t in TEMPLATES[fam]
)
_LEADING_FILLER = re.compile(r"^(?:(?:" + _alt(FILLER_WORDS) + r")(?: |$))+")
_TRAILING_FILLER = re.compile(r"(?:(?:^| )(?:please|now))+$")


def normalise(text: str) -> str:
    """Lower-case, turn punctuation into spaces, collapse spaces, drop filler words."""
    text = re.sub(r"[^a-z0-9 ]+", " ", text.lower())
    text = " ".join(text.split())
    text = _LEADING_FILLER.sub("", text)
    return _TRAILING_FILLER.sub("", text).strip()


def _vocabulary() -> dict[str, str]:
    """word -> what it is, for error messages."""
    vocab: dict[str, str] = {}
    for w in ("the", "a", "an", "to", "of", "on", "top", "up", "you", "from", "away", "in"):
        vocab[w] = "a function word"
    for c in COLOURS:
        vocab[c] = "a colour"
    for w, shape in _SHAPE_WORD_TO_SHAPE.items():
        vocab[w] = f"a shape ({shape})"
    for phrase, d in _DIR_WORD_TO_DIR.items():
        for w in phrase.split():
            vocab.setdefault(w, f"a direction ({d})")
    for phrase, r in _REL_WORD_TO_REL.items():
        for w in phrase.split():
            vocab.setdefault(w, f"a relation ({r})")
    for fam, templates in TEMPLATES.items():
        for t in templates:
            for w in re.sub(r"\{\w+\}", " ", t).split():
                vocab.setdefault(w, f"a {fam} verb")
    return vocab


_VOCAB = _vocabulary()


def explain(text: str) -> str:
    """Describe what the grammar recognises in ``text``, word by word, for error messages."""
    words = normalise(text).split()
    known = [f"{w!r} = {_VOCAB[w]}" for w in words if w in _VOCAB]
    unknown = [w for w in words if w not in _VOCAB]
    parts = []
    if known:
        parts.append("understood " + ", ".join(known))
    if unknown:
        parts.append("unknown word(s) " + ", ".join(repr(w) for w in unknown))
        parts.append(
            f"known colours: {', '.join(COLOURS)}; shapes: {', '.join(_SHAPE_WORD_TO_SHAPE)}; "
            f"directions: {', '.join(DIRECTIONS)}; relations: {', '.join(RELATIONS)}"
        )
    return "; ".join(p for p in parts if p)


def parse(text: str) -> Instruction:
    """Parse any phrasing the grammar knows into its :class:`Instruction`.

    Args:
        text: an instruction such as ``"Shove the red block to the left, please"``.

    Returns:
        The meaning; ``parse(x).text`` is the canonical sentence.

    Raises:
        InstructionParseError: empty or non-string input, or a sentence no template
            matches; the message lists which words were understood and which were not.
    """
    if not isinstance(text, str):
        raise InstructionParseError(f"an instruction must be a string, got {type(text).__name__}")
    norm = normalise(text)
    if not norm:
        raise InstructionParseError(
            "empty instruction: say what to do, e.g. 'push the red cube left'"
        )
    for fam, pattern in _PATTERNS:
        m = pattern.fullmatch(norm)
        if m is None:
            continue
        g = m.groupdict()
        kwargs: dict[str, str | None] = {}
        if g.get("dir"):
            kwargs["direction"] = _DIR_WORD_TO_DIR[g["dir"]]
        if g.get("rel"):
            kwargs["relation"] = _REL_WORD_TO_REL[g["rel"]]
        if g.get("c2"):
            kwargs["target_colour"] = g["c2"]
            kwargs["target_shape"] = _SHAPE_WORD_TO_SHAPE[g["s2"]]
        try:
            return Instruction(fam, g["c1"], _SHAPE_WORD_TO_SHAPE[g["s1"]], **kwargs)
        except InstructionParseError as e:
            raise InstructionParseError(f"cannot use {text!r}: {e}") from None
    raise InstructionParseError(
        f"cannot parse {text!r}: {explain(text)}. "
        f"Examples of instructions the grammar knows: 'reach the red cube', "
        f"'push the blue cylinder left', 'put the green cube behind the red cylinder', "
        f"'lift the yellow cube', 'stack the red cube on the blue cube'."
    )


def try_parse(text: str) -> Instruction | None:
    """Like :func:`parse` but returns ``None`` instead of raising."""
    try:
        return parse(text)
    except InstructionParseError:
        return None


def random_paraphrase(instruction: Instruction, rng: np.random.Generator) -> str:
    """A random non-canonical phrasing of ``instruction`` drawn with ``rng``."""
    forms = list(surface_forms(instruction))[1:]
    return forms[int(rng.integers(len(forms)))]

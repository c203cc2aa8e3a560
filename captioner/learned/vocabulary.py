"""The captioner's vocabulary: the grammar's words and the special tokens."""

from __future__ import annotations

from collections.abc import Sequence

from captioner.grammar import FAMILIES, all_instructions
from lcrl.errors import LcrlError

SPECIALS: tuple[str, ...] = ("<pad>", "<bos>", "<eos>", "<none>")
#: Steps around an achievement whose observations count as near misses in evaluation.
NEAR_WINDOW = 10
PAD, BOS, EOS, NONE = 0, 1, 2, 3
NONE_TEXT = "<none>"
CHECKPOINT_KIND = "lcrl-learned-captioner"
MODELS: tuple[str, ...] = ("captioner", "reward")


# --------------------------------------------------------------------------- vocabulary


class Vocabulary:
    """Words of the grammar's canonical instructions, after the special tokens."""

    def __init__(self, words: Sequence[str]) -> None:
        words = [w for w in words if w not in SPECIALS]
        self.words: list[str] = list(SPECIALS) + sorted(set(words))
        self.index = {w: i for i, w in enumerate(self.words)}

    @classmethod
    def from_grammar(cls, families: Sequence[str] = FAMILIES) -> Vocabulary:
        """Every word of every canonical instruction of ``families``."""
        return cls([w for ins in all_instructions(families) for w in ins.text.split()])

    def __len__(self) -> int:
        return len(self.words)

    def encode(self, text: str, max_len: int) -> list[int]:
        """``<bos> words <eos>`` (``<bos> <none> <eos>`` for :data:`NONE_TEXT`), padded to
        ``max_len`` tokens."""
        words = [NONE_TEXT] if text == NONE_TEXT else text.split()
        unknown = [w for w in words if w not in self.index]
        if unknown:
            raise LcrlError(f"words outside the captioner's vocabulary: {unknown}")
        ids = [BOS, *(self.index[w] for w in words), EOS]
        if len(ids) > max_len:
            raise LcrlError(f"{text!r} is longer than {max_len - 2} words")
        return ids + [PAD] * (max_len - len(ids))

    def decode(self, ids: Sequence[int]) -> str:
        """Text of a generated id sequence (up to ``<eos>``; ``<bos>`` skipped)."""
        out = []
        for i in ids:
            i = int(i)
            if i in (EOS, PAD):
                break
            if i == BOS:
                continue
            out.append(self.words[i])
        return " ".join(out)

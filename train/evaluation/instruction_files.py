"""Instruction files for ``lcrl eval --instructions FILE``: one instruction per line, with
its set and family read by the grammar."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lcrl.errors import LcrlError


@dataclass(frozen=True)
class FileInstruction:
    """One instruction of a user file.

    Attributes:
        line: its line number (1-based).
        text: the instruction the policy reads, spaces collapsed.
        checked: whether the rule captioner can judge its success in this environment.
        note: why it is not checked (empty when it is).
        canonical: the canonical instruction written after a tab on the line (empty when
            the line has none): success is judged by its meaning, while the policy reads
            ``text``.
    """

    line: int
    text: str
    checked: bool = True
    note: str = ""
    canonical: str = ""

    @property
    def judged(self) -> str:
        """The instruction whose meaning success is judged by."""
        return self.canonical or self.text


def read_instruction_file(
    path: str | Path, env_families: Sequence[str] | None = None
) -> list[FileInstruction]:
    """Read instructions, one per line; blank lines and ``#`` comments are skipped.

    A line may carry its canonical instruction after a tab (``could you nudge the red
    block left<TAB>push the red cube left``): the policy reads the free text before the
    tab, and success is judged by the meaning of the canonical part, which must parse.

    Lines without a tab that the grammar cannot parse, or whose family the environment
    cannot do (not in ``env_families``), are kept: the policy still runs on them, but
    their success is not checked.

    Raises:
        LcrlError: a missing or unreadable file, a line with characters an instruction
            cannot hold or longer than the limit, a line with more than one tab or an
            empty part, a canonical part that does not parse (each message names the
            line), or a file without instructions.
    """
    from captioner.grammar import try_parse
    from captioner.lang_env import INSTRUCTION_CHARSET, MAX_INSTRUCTION_LENGTH

    p = Path(path)
    if not p.is_file():
        raise LcrlError(f"instruction file not found: {p}")
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as e:
        raise LcrlError(f"instruction file {p} is not UTF-8 text: {e}") from None
    allowed = set(INSTRUCTION_CHARSET)
    out = []

    def check(text: str, number: int) -> None:
        bad = sorted(set(text) - allowed)
        if bad:
            raise LcrlError(
                f"{p}, line {number}: unsupported characters {''.join(bad)!r} in {text!r} "
                "(instructions hold letters, digits, spaces and .,;:!?'-)"
            )
        if len(text) > MAX_INSTRUCTION_LENGTH:
            raise LcrlError(
                f"{p}, line {number}: the instruction is {len(text)} characters long; the "
                f"limit is {MAX_INSTRUCTION_LENGTH}"
            )

    for number, raw in enumerate(lines, 1):
        content = raw.split("#", 1)[0]
        parts = [" ".join(part.split()) for part in content.split("\t")]
        if not any(parts):
            continue
        if len(parts) > 2:
            raise LcrlError(
                f"{p}, line {number}: {len(parts) - 1} tabs; a line holds an instruction and "
                "optionally, after one tab, its canonical form"
            )
        text, canonical = parts[0], parts[1] if len(parts) == 2 else ""
        if len(parts) == 2 and not (text and canonical):
            which = "free text before" if not text else "canonical instruction after"
            raise LcrlError(f"{p}, line {number}: no {which} the tab")
        check(text, number)
        if canonical:
            check(canonical, number)
            meaning = try_parse(canonical)
            if meaning is None:
                raise LcrlError(
                    f"{p}, line {number}: the canonical part {canonical!r} does not parse "
                    "(see `lcrl parse` for the instructions the grammar reads)"
                )
        else:
            meaning = try_parse(text)
        if meaning is None:
            out.append(FileInstruction(number, text, False, "the rule captioner cannot parse it"))
        elif env_families is not None and meaning.family not in env_families:
            can = ", ".join(env_families)
            note = f"{meaning.family} is not a family of this environment ({can})"
            out.append(FileInstruction(number, text, False, note, canonical))
        else:
            out.append(FileInstruction(number, text, canonical=canonical))
    if not out:
        raise LcrlError(
            f"instruction file {p} has no instructions (one per line; blank lines and "
            "lines starting with # are skipped)"
        )
    return out

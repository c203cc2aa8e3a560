"""The ``lcrl`` command line.

Subcommands:
    demo    caption scripted and random episodes on the 2D tabletop, write a report
    split   make a compositional instruction split and save it as JSON
    parse   show how the grammar reads instructions (canonical form and slots)

User mistakes (bad options, unparseable instructions, missing files) print one line
starting with ``lcrl: error:`` and exit with status 2; Ctrl-C exits with status 130.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import tyro

from lcrl.errors import LcrlError


@dataclass
class SplitCommand:
    """Make a compositional instruction split (train / held-out combinations / paraphrases)."""

    out: str = "split.json"
    """Where to write the split (JSON)."""
    seed: int = 0
    """The split's seed; the same seed always gives the same split."""
    families: tuple[str, ...] = ("reach", "push", "put", "lift", "stack")
    """Instruction families to include."""
    heldout_per_family: int = 2
    """Object kinds held out of each family."""
    list: bool = False
    """Also print every instruction of every set."""

    def run(self) -> None:
        from captioner.splits import SPLIT_SETS, make_split

        split = make_split(self.seed, self.families, self.heldout_per_family)
        path = split.save(self.out)
        print(split.summary())
        if self.list:
            for name in SPLIT_SETS:
                print(f"\n[{name}]")
                print("\n".join(split.texts(name)))
        print(f"saved {path}")


@dataclass
class ParseCommand:
    """Parse instructions with the grammar and print their canonical form and slots."""

    instructions: tyro.conf.Positional[tuple[str, ...]]
    """One or more instructions (quote each)."""
    json: bool = False
    """Print JSON instead of text."""

    def run(self) -> None:
        from captioner.grammar import parse

        results = []
        for text in self.instructions:
            ins = parse(text)
            results.append({"text": text, "canonical": ins.text, "slots": ins.slots()})
        if self.json:
            print(json.dumps(results, indent=1))
        else:
            for r in results:
                slots = " ".join(f"{k}={v}" for k, v in r["slots"].items())
                print(f"{r['text']!r} -> {r['canonical']!r}  [{slots}]")


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the ``lcrl`` console script."""
    from train.demo import DemoConfig, run_demo

    commands = {"demo": DemoConfig, "split": SplitCommand, "parse": ParseCommand}
    try:
        cfg = tyro.extras.subcommand_cli_from_dict(
            commands,
            prog="lcrl",
            description="lcrl: language-conditioned reinforcement learning toolkit.",
            args=argv,
        )
        if isinstance(cfg, DemoConfig):
            run_demo(cfg)
        else:
            cfg.run()
    except LcrlError as e:
        print(f"lcrl: error: {e}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("lcrl: interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()

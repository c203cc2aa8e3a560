"""The measuring protocol every headline follows (``docs/evaluation.md``, "How results are
measured").

- **Validation and test seeds.** Variants, thresholds, budgets and builds are chosen on
  evaluation seeds of :data:`VALIDATION_SEEDS`; the chosen one is evaluated once on a test
  seed that no choice used (:func:`check_test_seed`), and that figure is the headline.
  Everything tried goes into the result's ``tried``.
- **One policy.** A headline that names a policy is what the named preset or command gives
  a user: one network (:func:`check_single_policy`), never an ensemble, a router or separate
  per-family runs. Composite systems are reported beside it.
- **Like for like.** A ratio against a peer is measured side by side in one run, at the same
  precision and settings (:func:`check_like_for_like`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from lcrl.errors import LcrlError

#: Evaluation seeds on which choices are made (``lcrl eval MODEL --seed S``).
VALIDATION_SEEDS = (1, 2, 3)
#: Keys of a checkpoint's ``meta.json`` that mark a policy made of others.
COMPOSITE_KEYS = ("ensemble", "router")


def check_test_seed(seed: int, used: Iterable[int] = VALIDATION_SEEDS) -> int:
    """Refuse a test seed that a choice was made on."""
    if seed in set(used):
        raise LcrlError(
            f"evaluation seed {seed} was used for choices ({sorted(set(used))}): a headline is "
            "measured on a seed no choice used"
        )
    return seed


def check_single_policy(path: str | Path) -> Path:
    """Refuse a headline model made of others (an ensemble or a router): the product is one
    network. ``path`` is a checkpoint folder (with ``meta.json``)."""
    meta_path = Path(path) / "meta.json"
    if not meta_path.is_file():
        raise LcrlError(f"{path} is not a checkpoint (no meta.json)")
    meta = json.loads(meta_path.read_text())
    found = [key for key in COMPOSITE_KEYS if key in meta]
    if found:
        raise LcrlError(
            f"{path} is made of other policies ({', '.join(found)}): report it beside the "
            "headline, not as it"
        )
    return Path(path)


def check_like_for_like(
    ours: Mapping[str, Any], theirs: Mapping[str, Any], keys: Iterable[str] = ("precision",)
) -> None:
    """Refuse a ratio between two settings that differ in any of ``keys``."""
    differ = [k for k in keys if ours.get(k) != theirs.get(k)]
    if differ:
        raise LcrlError(
            "a ratio against a peer compares like with like: "
            + ", ".join(f"{k} {ours.get(k)!r} against {theirs.get(k)!r}" for k in differ)
        )

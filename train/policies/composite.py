"""Checkpoint folders made of others (:mod:`train.policies.ensemble`,
:mod:`train.policies.route`): written
whole or not at all, from policies that read the same inputs."""

from __future__ import annotations

import json
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lcrl.checkpoint import ARRAYS_FILE, META_FILE, seal_checkpoint
from lcrl.errors import LcrlError
from train.evaluation.evaluate import describe_problem


def check_same_inputs(other: Any, who: str, ref: Any, ref_name: str, plural: str) -> None:
    """Refuse a policy ``other`` that cannot stand beside ``ref``: another env kind, other
    observation features, goals or actions, or another text encoder; one line naming both
    (``who``, ``ref_name``)."""
    if other.cfg.env.kind != ref.cfg.env.kind:
        raise LcrlError(
            f"{who} was trained on the {other.cfg.env.kind} env, {ref_name} on the "
            f"{ref.cfg.env.kind} env"
        )
    if other.task.problem() != ref.task.problem():
        raise LcrlError(
            f"{who} reads {describe_problem(other.task.problem())}; {ref_name} reads "
            f"{describe_problem(ref.task.problem())}: {plural} must read the same observation "
            "features"
        )
    if other.cfg.text_encoder.model != ref.cfg.text_encoder.model:
        raise LcrlError(
            f"{who} embeds instructions with {other.cfg.text_encoder.model}, {ref_name} with "
            f"{ref.cfg.text_encoder.model}"
        )


def _copy_checkpoint(src: Path, dst: Path) -> None:
    """A checkpoint folder without its replay buffer."""
    dst.mkdir(parents=True)
    for p in sorted(src.iterdir()):
        if p.is_file() and p.name != ARRAYS_FILE:
            shutil.copy2(p, dst / p.name)


def write_composite(
    out: Path, first: str | Path, parts: Mapping[str, str | Path], key: str, entry: Any
) -> Path:
    """Write a checkpoint folder made of others: a copy of ``first`` (without its replay
    buffer) with each of ``parts`` (``{folder inside it: checkpoint}``) copied under it and
    ``entry`` under ``key`` in its ``meta.json``; written to a temporary folder beside
    ``out`` and renamed, so an interrupted write leaves nothing.

    Raises:
        LcrlError: ``out`` is or holds a checkpoint it is made from.
    """
    target = Path(out).resolve()
    for path in (first, *parts.values()):
        source = Path(path).resolve()
        if source == target or target in source.parents:
            raise LcrlError(f"{out} holds {path}, which it is made from: choose another folder")
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        _copy_checkpoint(Path(first), tmp)
        for rel, path in parts.items():
            _copy_checkpoint(Path(path), tmp / rel)
        meta = json.loads((tmp / META_FILE).read_text())
        meta[key] = entry
        (tmp / META_FILE).write_text(json.dumps(meta, indent=1))
        seal_checkpoint(tmp)  # the meta changed, and the copy has no replay buffer
        if out.exists():
            shutil.rmtree(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out

"""Loading any trained policy: one run's checkpoint, experts routed by instruction family
(``lcrl route``, :mod:`train.policies.route`) or the mean of policies trained apart (``lcrl
ensemble``, :mod:`train.policies.ensemble`). Every command that acts with a saved policy loads it
here."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from lcrl import algos
from lcrl.checkpoint import drop_modules, find_latest, seal_checkpoint
from lcrl.errors import LcrlError
from train.environments.text_reading import READER_CACHE
from train.evaluation.evaluate import ACTING_ONLY, LoadedPolicy, load_single
from train.policies.ensemble import ENSEMBLE, ensembled
from train.policies.route import ROUTER, routed

__all__ = ["LoadedPolicy", "keep_checkpoint", "load_policy"]

#: Files of a checkpoint that only resuming reads (replay arrays, optimiser and loop state).
RESUME_ONLY = ("arrays.npz", "state.json", "state.safetensors")


def load_policy(
    path: str | Path,
    env_overrides: dict[str, Any] | None = None,
    device: str | None = None,
    render: bool = False,
) -> LoadedPolicy:
    """Load a checkpoint, whatever it is made of, and rebuild its env, task and agent; the
    arguments and errors are those of :func:`train.evaluation.evaluate.load_single`."""
    loaded = load_single(path, env_overrides, device, render)
    if ROUTER in loaded.checkpoint.meta:  # experts routed by instruction family
        loaded = routed(loaded, device)
    if ENSEMBLE in loaded.checkpoint.meta:  # the mean of policies trained apart
        loaded = ensembled(loaded, device)
    return loaded


def keep_checkpoint(
    source: str | Path,
    dest: str | Path,
    canonical_reader: bool | None = None,
    acting_only: bool = False,
    reader_cache: bool = True,
) -> Path:
    """Copy a run's latest checkpoint (or the checkpoint folder ``source``) to ``dest`` as a
    policy to keep: weights and configs, with its fitted canonical reader, and none of what
    only resuming reads (:data:`RESUME_ONLY`: replay data, optimiser state). With
    ``canonical_reader`` set, the kept policy reads instructions through the canonical
    reader by default (True) or not (False). With ``acting_only``, the modules only
    learning reads (the algorithm's ``LEARNING_ONLY``: critics, target networks) are left
    out too, named in ``meta.json`` under
    :data:`train.evaluation.evaluate.ACTING_ONLY`. Without ``reader_cache``
    the fitted canonical reader stays behind (a few MB; fitted again when asked for). The
    copy is sealed (checksums) and replaces ``dest`` whole; ``lcrl act``, ``lcrl eval``
    and :func:`lcrl.load` take it.

    Raises:
        LcrlError: ``source`` is neither a checkpoint nor a run with one.
    """
    src = Path(source)
    latest = src if (src / "meta.json").is_file() else find_latest(src)
    if latest is None or not (latest / "meta.json").is_file():
        raise LcrlError(f"{source} is neither a checkpoint nor a run with one (no latest.json)")
    out = Path(dest)
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for f in latest.iterdir():
        if f.is_file() and f.name not in RESUME_ONLY:
            shutil.copy2(f, tmp / f.name)
        elif f.is_dir() and not f.name.startswith(".") and (reader_cache or f.name != READER_CACHE):
            # the fitted reader; a router's experts, an ensemble's members
            shutil.copytree(f, tmp / f.name)
    meta = json.loads((tmp / "meta.json").read_text())
    if canonical_reader is not None:
        meta["config"]["env"]["canonical_reader"] = canonical_reader
    if acting_only and meta.get("algo") in algos.ALGOS:
        learning = algos.ALGOS[meta["algo"]].agent.LEARNING_ONLY
        dropped = [*meta.get(ACTING_ONLY, []), *drop_modules(tmp, learning)]
        meta[ACTING_ONLY] = dropped
    meta.pop("checksums", None), meta.pop("meta_checksum", None)
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    seal_checkpoint(tmp)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return out

"""Loading any trained policy: one run's checkpoint, experts routed by instruction family
(``lcrl route``, :mod:`train.policies.route`) or the mean of policies trained apart (``lcrl
ensemble``, :mod:`train.policies.ensemble`). Every command that acts with a saved policy loads it
here."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from train.evaluation.evaluate import LoadedPolicy, load_single
from train.policies.ensemble import ENSEMBLE, ensembled
from train.policies.route import ROUTER, routed

__all__ = ["LoadedPolicy", "load_policy"]


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

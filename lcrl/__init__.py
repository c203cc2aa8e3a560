"""lcrl: the learning core (frozen text encoder, goal spaces, replay, learners).

``lcrl.load(path)`` loads a trained policy (:class:`train.policy.Policy`) for querying from
Python; it imports the training stack on first use, so ``import lcrl`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from lcrl.errors import LcrlError

if TYPE_CHECKING:
    from collections.abc import Mapping
    from pathlib import Path

    from train.policy import Policy

__all__ = ["LcrlError", "load"]
__version__ = "0.1.0"


def load(
    path: str | Path,
    device: str | None = None,
    env_overrides: Mapping[str, Any] | None = None,
) -> Policy:
    """Load a trained policy: ``lcrl.load("runs/lang2d").act(obs, "push the red cube left")``.

    Args:
        path: a checkpoint folder, or a run folder (its latest checkpoint).
        device: run the networks here (``"cpu"``, ``"cuda"``) instead of the checkpoint's
            device.
        env_overrides: env config fields to change; the environment must still give the
            checkpoint's observation and action shapes.

    Returns:
        A :class:`train.policy.Policy` (``act``, ``reset``, ``nearest``, ``make_env``).

    Raises:
        LcrlError: no checkpoint at ``path``, or it does not match its environment.
    """
    # The one import from the layer above: the policy needs the task and env wiring that
    # lives in ``train``, and is only imported when a policy is loaded.
    from train.policy import load as _load

    return _load(path, device=device, env_overrides=env_overrides)

"""lcrl: the learning core (frozen text encoder, goal spaces, replay, learners).

``lcrl.load(path)`` loads a trained policy for querying from Python; it imports the
training stack on first use, so ``import lcrl`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from lcrl.errors import LcrlError

if TYPE_CHECKING:
    from train.policies.policy import Policy

__all__ = ["LcrlError", "load"]
__version__ = "0.1.0"


def load(path: Any, device: str | None = None, env_overrides: Any = None) -> Policy:
    """Load a trained policy: ``lcrl.load("runs/main").act(obs, "reach the red cube")``.

    The same as :func:`train.policies.policy.load` (arguments, errors), which is imported here only
    when called: it is the one name from the layer above, since a policy needs the task
    and env wiring that lives in ``train``.
    """
    from train.policies.policy import load as _load

    return _load(path, device=device, env_overrides=env_overrides)

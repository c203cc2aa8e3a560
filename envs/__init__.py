"""Simulators: the fast 2D tabletop (and later robosuite); each exposes a SceneState.

Importing this package registers the gymnasium ids:

* ``lcrl/Tabletop2D-v0``: :class:`~envs.tabletop2d.Tabletop2DEnv`, continuous actions;
* ``lcrl/Tabletop2DDiscrete-v0``: the same with 8-direction discrete actions.

Both truncate after 50 steps; keyword arguments of ``gymnasium.make`` reach the
constructor.
"""

import gymnasium

from envs.scene import COLOURS, OBJECT_KINDS, SHAPES, SceneState, object_name
from envs.tabletop2d import Tabletop2DEnv

__all__ = ["COLOURS", "OBJECT_KINDS", "SHAPES", "SceneState", "Tabletop2DEnv", "object_name"]

_TABLETOP2D_IDS = {
    "lcrl/Tabletop2D-v0": {"action_type": "continuous"},
    "lcrl/Tabletop2DDiscrete-v0": {"action_type": "discrete", "num_directions": 8},
}


def _register() -> None:
    for env_id, kwargs in _TABLETOP2D_IDS.items():
        if env_id not in gymnasium.registry:  # importing twice (reload) must not fail
            gymnasium.register(
                id=env_id,
                entry_point="envs.tabletop2d:Tabletop2DEnv",
                max_episode_steps=50,
                kwargs=kwargs,
            )


_register()

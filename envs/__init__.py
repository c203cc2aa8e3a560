"""Simulators: the fast 2D tabletop (and later robosuite); each exposes a SceneState.

Importing this package registers the gymnasium ids:

* ``lcrl/Tabletop2D-v0``: :class:`~envs.tabletop2d.Tabletop2DEnv`, continuous actions;
* ``lcrl/Tabletop2DDiscrete-v0``: the same with 8-direction discrete actions.

Both truncate after 50 steps. With the ``robot`` extra (``pip install -e ".[robot]"``):

* ``lcrl/RobosuiteTabletop-v0``: :class:`~envs.robosuite_tabletop.RobosuiteTabletopEnv`,
  a robosuite Panda tabletop; truncates after 100 steps (5 s at 20 Hz).

Keyword arguments of ``gymnasium.make`` reach the constructor. The robosuite id is
registered by name only: importing this package does not import robosuite or mujoco.
"""

import gymnasium

from envs.scene import COLOURS, OBJECT_KINDS, SHAPES, SceneState, object_name
from envs.tabletop2d import Tabletop2DEnv

__all__ = [
    "COLOURS",
    "OBJECT_KINDS",
    "SHAPES",
    "RobosuiteTabletopEnv",
    "SceneState",
    "Tabletop2DEnv",
    "object_name",
]

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
    if "lcrl/RobosuiteTabletop-v0" not in gymnasium.registry:
        gymnasium.register(
            id="lcrl/RobosuiteTabletop-v0",
            entry_point="envs.robosuite_tabletop:RobosuiteTabletopEnv",
            max_episode_steps=100,
        )


def __getattr__(name: str) -> object:
    # Lazy: envs.robosuite_tabletop imports robosuite only when an env is created, but
    # keeping the module itself out of `import envs` keeps that import light.
    if name == "RobosuiteTabletopEnv":
        from envs.robosuite_tabletop import RobosuiteTabletopEnv

        return RobosuiteTabletopEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


_register()

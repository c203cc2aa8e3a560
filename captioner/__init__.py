"""Instruction grammar, splits, rule captioner and the language-goal environment wrapper.

Importing this package registers the gymnasium ids:

* ``lcrl/LangTabletop2D-v0``: the 2D tabletop with an instruction per episode (train set of
  split 0 by default; pass ``split_set="heldout"`` or ``"paraphrase"`` to gymnasium.make);
* ``lcrl/LangTabletop2DDiscrete-v0``: the same with 8-direction discrete actions.

``ScriptedController3D`` (the robosuite tabletop's scripted controller,
:mod:`captioner.scripted3d`) is imported on first use, so that
``python -m captioner.scripted3d`` runs the module only once.
"""

from typing import Any

import gymnasium

import envs  # noqa: F401  (registers the base environments)
from captioner.grammar import FAMILIES, FAMILIES_2D, Instruction, InstructionParseError, parse
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner, Thresholds
from captioner.splits import Split, make_split

__all__ = [
    "FAMILIES",
    "FAMILIES_2D",
    "Instruction",
    "InstructionParseError",
    "LanguageGoalWrapper",
    "RuleCaptioner",
    "ScriptedController3D",
    "Split",
    "Thresholds",
    "make_split",
    "parse",
]

_LANG_IDS = {
    "lcrl/LangTabletop2D-v0": {"action_type": "continuous"},
    "lcrl/LangTabletop2DDiscrete-v0": {"action_type": "discrete", "num_directions": 8},
}
for _env_id, _kwargs in _LANG_IDS.items():
    if _env_id not in gymnasium.registry:
        gymnasium.register(
            id=_env_id,
            entry_point="captioner.lang_env:make_language_tabletop2d",
            max_episode_steps=50,
            kwargs=_kwargs,
        )


def __getattr__(name: str) -> Any:
    if name == "ScriptedController3D":
        from captioner.scripted3d import ScriptedController3D

        return ScriptedController3D
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

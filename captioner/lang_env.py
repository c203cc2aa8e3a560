"""Language-goal wrapper: an instruction per episode, sparse reward from the rule captioner.

Wraps any environment whose unwrapped env has ``scene() -> SceneState``. At reset it
samples an instruction from one set of a :class:`~captioner.splits.Split` among those
feasible in the new scene (objects present, not already satisfied, room to do it), or takes
the one passed as ``reset(options={"instruction": "..."})``. The observation gains an
``instruction`` text entry; reward is 1.0 when ``satisfied(instruction, s0, s)`` and 0.0
otherwise, ``info["is_success"]`` says the same, and the episode terminates on success by
default. :meth:`LanguageGoalWrapper.switch_instruction` gives a running episode its next
instruction (chained tasks).
"""

from __future__ import annotations

import string
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from captioner.grammar import FAMILIES, FAMILIES_2D, Instruction
from captioner.rule import RuleCaptioner
from captioner.splits import SPLIT_SETS, Split, make_split
from envs.scene import SceneState
from lcrl.errors import LcrlError

#: Characters an ``instruction`` observation may contain.
INSTRUCTION_CHARSET = string.ascii_letters + string.digits + " .,;:!?'-"
MAX_INSTRUCTION_LENGTH = 200


class LanguageGoalWrapper(gym.Wrapper):
    """Adds an instruction to a scene-describing environment and rewards following it.

    Args:
        env: an environment whose ``unwrapped`` has ``scene()``.
        split: the instruction split; default ``make_split(0, families)``.
        split_set: which set to sample from: ``train``, ``heldout`` or ``paraphrase``.
        families: families to sample; default the env's ``instruction_families``
            attribute (all families if it has none).
        captioner: the rule captioner that judges success.
        terminate_on_success: end the episode when the instruction is satisfied.
        family_balanced: draw a family uniformly among those with a feasible instruction,
            then an instruction of it; otherwise draw uniformly over all feasible
            instructions (``put`` has far more instructions than ``reach``).
        max_resample: layouts to try before giving up when no instruction is feasible.
    """

    def __init__(
        self,
        env: gym.Env,
        split: Split | None = None,
        split_set: str = "train",
        families: tuple[str, ...] | None = None,
        captioner: RuleCaptioner | None = None,
        terminate_on_success: bool = True,
        family_balanced: bool = True,
        max_resample: int = 100,
    ) -> None:
        super().__init__(env)
        if not callable(getattr(env.unwrapped, "scene", None)):
            raise LcrlError(
                f"{type(env.unwrapped).__name__} has no scene() method: the language wrapper "
                "needs an environment that describes its scene (see envs.scene.SceneState)"
            )
        if split_set not in SPLIT_SETS:
            raise LcrlError(f"unknown split set {split_set!r}; choose one of {SPLIT_SETS}")
        if families is None:
            families = tuple(getattr(env.unwrapped, "instruction_families", FAMILIES))
        self.families = tuple(families)
        self.split = split if split is not None else make_split(0, self.families)
        self.split_set = split_set
        self.captioner = captioner or RuleCaptioner(self.families)
        self.terminate_on_success = terminate_on_success
        self.family_balanced = family_balanced
        self.max_resample = max_resample
        self._candidates = self._instructions(self.families)
        #: Draw weights of the families (:meth:`weigh_families`); None: uniform.
        self._family_weights: dict[str, float] | None = None
        self.observation_space = gym.spaces.Dict(
            {
                **dict(env.observation_space.spaces),
                "instruction": gym.spaces.Text(
                    max_length=MAX_INSTRUCTION_LENGTH, charset=INSTRUCTION_CHARSET
                ),
            }
        )
        self.instruction: str = ""
        self.meaning: Instruction | None = None
        self.s0: SceneState | None = None

    def _instructions(self, families: Sequence[str]) -> list[tuple[str, Instruction]]:
        """The (text, meaning) pairs of the split set whose family is in ``families``."""
        texts = self.split.texts(self.split_set)
        meanings = self.split.instructions(self.split_set)
        out = [(t, m) for t, m in zip(texts, meanings, strict=True) if m.family in families]
        if not out:
            raise LcrlError(
                f"the {self.split_set!r} set of this split has no instruction of the families "
                f"{tuple(families)} (split families: {self.split.families})"
            )
        return out

    def draw_from(self, families: Sequence[str]) -> None:
        """Draw instructions of ``families`` only, from the next reset or switch on (a
        curriculum over families); the captioner still judges and labels every family.

        Raises:
            LcrlError: a family the wrapper does not have, or one without instructions.
        """
        bad = [f for f in families if f not in self.families]
        if bad or not families:
            raise LcrlError(
                f"cannot draw instructions of {tuple(families)}: this env's families are "
                f"{self.families}"
            )
        self._candidates = self._instructions(tuple(families))

    def weigh_families(self, weights: Mapping[str, float] | None) -> None:
        """Draw the family of the next instructions with probability proportional to
        ``weights`` (families it does not name weigh 1) instead of uniformly, among the
        families with a feasible instruction; None: uniformly again. Only with
        ``family_balanced``.

        Raises:
            LcrlError: a weight that is negative or not finite.
        """
        if weights is not None:
            bad = {f: w for f, w in weights.items() if not (np.isfinite(w) and w >= 0.0)}
            if bad:
                raise LcrlError(f"family weights must be finite and >= 0, got {bad}")
            weights = dict(weights)
        self._family_weights = weights

    def _scene(self) -> SceneState:
        return self.env.unwrapped.scene()

    def _choose(
        self, s0: SceneState, pool: list[tuple[str, Instruction]] | None = None
    ) -> tuple[str, Instruction] | None:
        candidates = self._candidates if pool is None else pool
        feasible = [(t, m) for t, m in candidates if self.captioner.feasible(m, s0)]
        if not feasible:
            return None
        rng = self.env.unwrapped.np_random
        if self.family_balanced:
            families = sorted({m.family for _, m in feasible})
            w = self._family_weights
            p = None if w is None else np.array([w.get(f, 1.0) for f in families])
            if p is None or not p.sum() > 0.0:
                family = families[int(rng.integers(len(families)))]
            else:
                family = families[int(rng.choice(len(families), p=p / p.sum()))]
            feasible = [(t, m) for t, m in feasible if m.family == family]
        return feasible[int(rng.integers(len(feasible)))]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset the env and pick the episode's instruction.

        ``options={"instruction": text}`` fixes the instruction (any phrasing the grammar
        parses); the other options go to the wrapped env. ``info["feasible"]`` says whether
        the instruction can be followed in the new layout (drawn instructions always can).
        """
        options = dict(options or {})
        given = options.pop("instruction", None)
        obs, info = self.env.reset(seed=seed, options=options or None)
        s0 = self._scene()
        if given is not None:
            text = _check_text(given)
            meaning = self.captioner.parse(text)
        else:
            choice = self._choose(s0)
            tries = 1
            while choice is None:
                if tries >= self.max_resample:
                    raise LcrlError(
                        f"no instruction of the {self.split_set!r} set is feasible in "
                        f"{self.max_resample} random layouts; check the split's families "
                        f"{self.split.families} against the env's {self.families}"
                    )
                obs, info = self.env.reset(options=options or None)
                s0 = self._scene()
                choice = self._choose(s0)
                tries += 1
            text, meaning = choice
        self.instruction, self.meaning, self.s0 = text, meaning, s0
        obs["instruction"] = text
        info = dict(info)
        info["instruction"] = text
        # a given instruction may name an object that is not on the table, or already hold
        info["feasible"] = bool(self.captioner.feasible(meaning, s0))
        info["is_success"] = False
        return obs, info

    def switch_instruction(
        self, instruction: str | None = None, candidates: Sequence[str] | None = None
    ) -> str | None:
        """Give the running episode a new instruction without resetting the scene.

        For chained tasks (one instruction after another in the same scene, as in
        CALVIN): the scene now becomes the reference ``s0`` that success is judged
        against, so after a switch "push the red cube left" means left of where the cube
        is now. The next observation carries the new instruction.

        Args:
            instruction: the new instruction (any phrasing the grammar parses); default:
                draw one, as :meth:`reset` does, among the instructions feasible in the
                current scene, with the env's seeded ``np_random``.
            candidates: sentences to draw from instead of this wrapper's set (ignored
                when ``instruction`` is given).

        Returns:
            The new instruction, or ``None`` when no candidate is feasible in the current
            scene (the episode then keeps its instruction and its ``s0``).

        Raises:
            LcrlError: called before :meth:`reset`, or an instruction that does not parse.
        """
        if self.meaning is None:
            raise LcrlError("call reset() before switch_instruction()")
        s0 = self._scene()
        if instruction is not None:
            text = _check_text(instruction)
            meaning = self.captioner.parse(text)
        else:
            pool = None
            if candidates is not None:
                pool = [(t, self.captioner.parse(t)) for t in candidates]
            choice = self._choose(s0, pool)
            if choice is None:
                return None
            text, meaning = choice
        self.instruction, self.meaning, self.s0 = text, meaning, s0
        return text

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """Step the env; reward 1.0 when the instruction is satisfied, else 0.0."""
        if self.meaning is None:
            raise LcrlError("call reset() before step()")
        obs, _, terminated, truncated, info = self.env.step(action)
        success = self.captioner.satisfied(self.meaning, self.s0, self._scene())
        obs["instruction"] = self.instruction
        info = dict(info)
        info["is_success"] = success
        info["instruction"] = self.instruction
        if success and self.terminate_on_success:
            terminated = True
        return obs, float(success), bool(terminated), bool(truncated), info


def _check_text(text: Any) -> str:
    if not isinstance(text, str):
        raise LcrlError(f"an instruction must be a string, got {type(text).__name__}")
    text = " ".join(text.split())
    if not text:
        raise LcrlError("empty instruction")
    if len(text) > MAX_INSTRUCTION_LENGTH:
        raise LcrlError(
            f"instruction is {len(text)} characters long; the limit is {MAX_INSTRUCTION_LENGTH}"
        )
    bad = sorted(set(text) - set(INSTRUCTION_CHARSET))
    if bad:
        raise LcrlError(f"instruction contains unsupported characters {''.join(bad)!r}")
    return text


def make_language_tabletop2d(
    split_seed: int = 0,
    split_set: str = "train",
    terminate_on_success: bool = True,
    family_balanced: bool = True,
    **env_kwargs: Any,
) -> LanguageGoalWrapper:
    """Entry point of ``lcrl/LangTabletop2D-v0``: the 2D tabletop with language goals.

    Args:
        split_seed: seed of the instruction split (2D families).
        split_set: ``train``, ``heldout`` or ``paraphrase``.
        terminate_on_success: end episodes on success.
        family_balanced: sample the family uniformly first (see the wrapper).
        **env_kwargs: passed to :class:`envs.tabletop2d.Tabletop2DEnv`.
    """
    from envs.tabletop2d import Tabletop2DEnv

    env = Tabletop2DEnv(**env_kwargs)
    return LanguageGoalWrapper(
        env,
        split=make_split(split_seed, FAMILIES_2D),
        split_set=split_set,
        families=FAMILIES_2D,
        terminate_on_success=terminate_on_success,
        family_balanced=family_balanced,
    )

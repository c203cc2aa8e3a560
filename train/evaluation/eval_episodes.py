"""Evaluation episodes in a vector env: what each episode is asked (:class:`EpisodeSpec`),
what it gave (:class:`EpisodeResult`), and the wrapper that runs them, chains included
(:class:`EvalEpisodes`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym

from train.environments.tasks import (
    FEASIBLE_TRIES,
    features_wrapper,
    find_language_wrapper,
    reset_feasible,
)


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode: its place in the set, its reset seed and, optionally, a
    fixed instruction (``checked=False``: free text the captioner cannot judge) or the
    index of a task of a fixed task set (``instruction`` is then the task's text, and the
    layout is the first from ``seed`` where it is feasible, as in the training loop)."""

    index: int
    seed: int
    instruction: str | None = None
    checked: bool = True
    task: int | None = None
    reads: str | None = None
    """What the policy reads instead of ``instruction`` (a free-text line whose canonical
    form, ``instruction``, judges success)."""


@dataclass
class EpisodeResult:
    """What happened in one evaluation episode (a chain of attempts in chain mode).

    Attributes:
        index, seed: from the :class:`EpisodeSpec`.
        attempts: one dict per instruction tried: ``instruction``, ``slots`` (the parsed
            slots, empty for free text), ``checked``, ``success`` (None when not
            checked), ``steps`` (steps spent on it) and, for successes,
            ``steps_to_success`` (for goal tasks, which run to their time limit: the step
            from which the goal stayed reached).
        success: the episode's (first instruction's) success; None when not checked.
        steps: steps of the whole episode.
        stop: why the episode ended: ``success``, ``failure``, ``chain_complete``,
            ``no_feasible`` (no next instruction of the set fits the scene) or ``done``
            (goal tasks).
    """

    index: int
    seed: int
    attempts: list[dict[str, Any]] = field(default_factory=list)
    success: bool | None = None
    steps: int = 0
    stop: str = ""


def _slots(meaning: Any) -> dict[str, str]:
    if meaning is None:
        return {}
    slots = meaning.slots()
    keys = ("family", "colour", "shape", "direction", "relation")
    out = {k: slots[k] for k in keys if k in slots}
    out["object"] = f"{meaning.colour} {meaning.shape}"
    return out


class EvalEpisodes(gym.Wrapper):
    """Runs a fixed list of evaluation episodes inside one sub-env of a vector env.

    The wrapper never reports ``terminated`` or ``truncated``: when an episode ends it
    puts an :class:`EpisodeResult` in ``info["episode"]``, resets itself with the next
    episode's seed and returns that episode's first observation (``info["start"]`` marks
    the first observation of every instruction). After the last episode it idles: steps
    return the last observation and ``info["idle"]``.

    Args:
        env: the task's env, as :func:`train.environments.tasks.make_env` builds it.
        specs: the episodes to run, in order.
        language: the env has language goals (its time limit is replaced by a budget of
            ``max_steps`` per instruction).
        max_steps: steps per instruction (language goals).
        chain: instructions per episode at most (1: no chaining).
        pool: sentences to draw the next instruction of a chain from (default: the
            wrapper's instruction set).
        start_info: ``env -> goal information`` put in ``info["goal"]`` at each start
            (:meth:`train.environments.tasks.Task.start_info`: the goal frame of image goals).
        aliases: canonical instruction -> the free text the policy reads for it (lines of
            an instruction file with a canonical part), also when a chain switches to it.
    """

    def __init__(
        self,
        env: gym.Env,
        specs: Sequence[EpisodeSpec],
        language: bool,
        max_steps: int,
        chain: int = 1,
        pool: Sequence[str] | None = None,
        start_info: Callable[[gym.Env], Any] | None = None,
        aliases: dict[str, str] | None = None,
    ) -> None:
        if language and isinstance(env, gym.wrappers.TimeLimit):
            env = env.env  # the budget is counted here, per instruction
        super().__init__(env)
        self.specs = list(specs)
        self.language = language
        self.max_steps = int(max_steps)
        self.chain = max(1, int(chain))
        self.pool = list(pool) if pool is not None else None
        self.start_info = start_info
        self.aliases = dict(aliases or {})
        self._reads: str | None = None  # the free text read for the canonical instruction
        self.lang = find_language_wrapper(env) if language else None
        self.features = features_wrapper(env) if language else None
        self._next = 0
        self._spec: EpisodeSpec | None = None
        self._result: EpisodeResult | None = None
        self._attempt_steps = 0
        self._success_since: int | None = None  # goal tasks: start of the last success run
        self._last_obs: Any = None
        self.idle = False

    # the episode machinery ----------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start the first episode of the list (the vector env's seed is not used: each
        episode has its own)."""
        self._next = 0
        self.idle = False
        return self._start_next({})

    def _start_next(self, info: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        if self._next >= len(self.specs):
            self.idle = True
            info["idle"] = True
            return self._last_obs, info
        spec = self.specs[self._next]
        self._next += 1
        self._spec = spec
        self._result = EpisodeResult(spec.index, spec.seed)
        self._reads = spec.reads
        obs = self._reads_instead(self._reset_episode(spec))
        self._begin_attempt(info)
        self._last_obs = obs
        return obs, info

    def _reset_episode(self, spec: EpisodeSpec) -> Any:
        if not self.language:
            obs, _ = self.env.reset(seed=spec.seed)
            return obs
        if spec.instruction is None:
            obs, _ = self.env.reset(seed=spec.seed)
            return obs
        if spec.task is not None:  # a task of a fixed task set: the training loop's layouts
            obs, _ = reset_feasible(self.env, spec.seed, spec.instruction, FEASIBLE_TRIES)
            return obs
        if not spec.checked:  # free text: the language wrapper (its check) is bypassed
            obs, _ = self.lang.env.reset(seed=spec.seed)
            obs = dict(obs)
            obs["instruction"] = spec.instruction
            return obs
        # a fixed instruction: draw layouts (from the seed on) until it is feasible
        options = {"instruction": spec.instruction}
        obs, _ = self.env.reset(seed=spec.seed, options=options)
        for _ in range(self.lang.max_resample - 1):
            if self.lang.captioner.feasible(self.lang.meaning, self.lang.s0):
                break
            obs, _ = self.env.reset(options=options)
        return obs

    def _reads_instead(self, obs: Any) -> Any:
        """The observation with the free text the policy reads, where one is set."""
        if self._reads is None:
            return obs
        obs = dict(obs)
        obs["instruction"] = self._reads
        return obs

    def _begin_attempt(self, info: dict[str, Any]) -> None:
        self._attempt_steps = 0
        self._success_since = None
        info["start"] = True
        if self.start_info is not None:
            goal = self.start_info(self.env)
            if goal is not None:
                info["goal"] = goal
        spec = self._spec
        if self.language:
            if spec.checked:
                text, meaning = self.lang.instruction, self.lang.meaning
                checked = self.lang.captioner.feasible(meaning, self.lang.s0)
                slots = _slots(meaning)
            else:
                text, checked, slots = spec.instruction, False, {}
            attempt = {"instruction": text, "slots": slots, "checked": checked, "success": None}
            if self._reads is not None:  # reported per line: the free text, and its meaning
                attempt.update(instruction=self._reads, canonical=text)
            self._result.attempts.append(attempt)

    def _finish_attempt(self, success: bool | None) -> None:
        attempt = self._result.attempts[-1]
        attempt["steps"] = self._attempt_steps
        if attempt["checked"]:
            attempt["success"] = bool(success)
        if attempt["success"]:
            since = self._success_since if not self.language else None
            attempt["steps_to_success"] = since if since is not None else self._attempt_steps

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the running episode; on its end, report it and start the next one."""
        if self.idle:
            return self._last_obs, 0.0, False, False, {"idle": True}
        res, spec = self._result, self._spec
        if self.language and not spec.checked:
            obs, reward, terminated, truncated, info = self.lang.env.step(action)
            obs = dict(obs)
            obs["instruction"] = spec.instruction
            success = False
        else:
            obs, reward, terminated, truncated, info = self.env.step(action)
            obs = self._reads_instead(obs)
            success = bool(info.get("is_success", False))
        self._attempt_steps += 1
        res.steps += 1
        out: dict[str, Any] = {}
        if not self.language:
            # goal episodes run to their time limit: success is judged at the last step,
            # and reached at the first step of the success run that lasts to it
            if not success:
                self._success_since = None
            elif self._success_since is None:
                self._success_since = self._attempt_steps
            if terminated or truncated:
                res.success = success
                res.attempts.append(
                    {"instruction": None, "slots": {}, "checked": True, "success": success}
                )
                self._finish_attempt(success)
                res.stop = "done"
                return self._end(out, reward)
            self._last_obs = obs
            return obs, float(reward), False, False, out
        attempt = res.attempts[-1]
        if success and attempt["checked"]:
            self._finish_attempt(True)
            if len(res.attempts) >= self.chain:
                res.stop = "chain_complete" if self.chain > 1 else "success"
                return self._end(out, reward)
            if self.lang.switch_instruction(candidates=self.pool) is None:
                res.stop = "no_feasible"
                return self._end(out, reward)
            self._reads = self.aliases.get(self.lang.instruction)
            obs = dict(obs) if self.features is None else self.features.restarted(obs)
            obs["instruction"] = self._reads or self.lang.instruction
            self._begin_attempt(out)
            self._last_obs = obs
            return obs, float(reward), False, False, out
        if terminated or self._attempt_steps >= self.max_steps:
            self._finish_attempt(False)
            res.stop = "failure"
            return self._end(out, reward)
        self._last_obs = obs
        return obs, float(reward), False, False, out

    def _end(self, info: dict[str, Any], reward: float) -> tuple[Any, float, bool, bool, dict]:
        res = self._result
        if self.language:
            first = res.attempts[0]
            res.success = first["success"] if first["checked"] else None
        info["episode"] = res
        obs, info = self._start_next(info)
        return obs, float(reward), False, False, info

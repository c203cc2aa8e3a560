"""One training episode as collected: reset (or carried on from where a chained one
ended), stepped with the learner's or the scripted controller's actions, and turned into
the record the replay buffer stores. Shared by the trainer's own environments
(:mod:`train.training.loop`) and the Ray rollout workers (:mod:`train.training.ray_collect`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from train.configs.config import TrainConfig
from train.environments.tasks import ScriptedActor, reset_feasible, task_texts


@dataclasses.dataclass
class Episode:
    """An episode being collected in one of the training environments."""

    env: Any
    slot: int
    #: Random actions are drawn from ``rng``, the scripted controller's noise from
    #: ``scripted_rng``.
    rng: np.random.Generator
    scripted_rng: np.random.Generator
    first: dict[str, Any]
    goal: Any
    stored: list[dict[str, np.ndarray]]
    records: list[Any]
    task_id: int | None
    scripted: bool
    info: dict[str, Any]
    actions: list[Any] = dataclasses.field(default_factory=list)
    rewards: list[float] = dataclasses.field(default_factory=list)
    terms: list[bool] = dataclasses.field(default_factory=list)
    #: Per step: whether the scripted controller acted it (a demonstration step).
    demo: list[bool] = dataclasses.field(default_factory=list)
    succeeded: bool = False  # at any step (episodes may go on after success)
    done: bool = False
    t: int = 0
    action: Any = None
    random_action: Any = None
    #: The last observation the env returned (where a chained episode goes on).
    obs: Any = None
    #: Steps the scripted controller acts before the policy takes over (0: none).
    handover: int = 0
    #: Position in a chain of instructions in one scene (0: began at a reset).
    chain_index: int = 0
    #: The family of its instruction (language goals), for a curriculum.
    family: str = ""
    #: It began where the scripted teacher's prelude left the scene (``explore.prelude``).
    prelude: bool = False
    #: The learned reward model ended it at its instruction's success (``relabel.end``).
    learned_end: bool = False

    @property
    def scripted_now(self) -> bool:
        """Whether the scripted controller acts the next step."""
        return self.scripted or self.t < self.handover


def begin_episode(
    cfg: TrainConfig,
    task: Any,
    env: Any,
    index: int,
    scripted: ScriptedActor | None,
    task_id: int | None = None,
    rng: np.random.Generator | None = None,
    scripted_rng: np.random.Generator | None = None,
) -> Episode:
    """Reset ``env`` for the training episode of number ``index`` (its reset seed follows
    from ``cfg.seed`` and ``index``); ``task_id`` picks a task of the run's task set (reset
    in a layout where it is feasible). Random actions are drawn from ``rng`` and the
    scripted controller's choice and noise from ``scripted_rng`` (the trainer's streams);
    without them, from a generator of the episode's index alone (a rollout worker's)."""
    seed = int(cfg.seed * 1_000_003 + index)
    if rng is None:
        rng = np.random.default_rng([cfg.seed, 7, index])
    scripted_rng = rng if scripted_rng is None else scripted_rng
    if task_id is not None:
        obs, info = reset_feasible(env, seed, task_texts(cfg.env)[task_id])
    else:
        obs, info = env.reset(seed=seed)
    return start_episode(cfg, task, env, obs, info, scripted, rng, scripted_rng, task_id)


def start_episode(
    cfg: TrainConfig,
    task: Any,
    env: Any,
    obs: Any,
    info: dict[str, Any],
    scripted: ScriptedActor | None,
    rng: np.random.Generator,
    scripted_rng: np.random.Generator,
    task_id: int | None = None,
) -> Episode:
    """An episode that starts from ``obs`` (after a reset, or where a chained one ended);
    whether the scripted controller acts it is drawn from ``scripted_rng``."""
    acted = scripted is not None and scripted_rng.random() < cfg.scripted_fraction
    if acted:
        scripted.reset()
    return Episode(
        env=env,
        slot=0,
        rng=rng,
        scripted_rng=scripted_rng,
        first=obs,
        goal=task.goal(obs, env),
        stored=[task.training_obs(obs, obs)],
        records=[task.step_record(obs, env)],
        task_id=task_id,
        scripted=acted,
        info=info,
        obs=obs,
    )


def step_episode(task: Any, ep: Episode) -> None:
    """Step an episode's env with its action (``ep.action``) and record what happened."""
    ep.demo.append(ep.scripted_now)
    obs, reward, terminated, truncated, info = ep.env.step(task.scale_action(ep.action))
    ep.t += 1
    ep.obs = obs
    ep.stored.append(task.training_obs(obs, ep.first))
    ep.records.append(task.step_record(obs, ep.env))
    ep.actions.append(ep.action)
    ep.rewards.append(reward)
    ep.terms.append(terminated)
    ep.succeeded = ep.succeeded or bool(info.get("is_success", False))
    ep.info = info
    ep.done = bool(terminated or truncated)


def episode_record(task: Any, ep: Episode) -> dict[str, Any]:
    """A finished episode as the buffer stores it, labelled by the task (captions,
    achieved goals)."""
    return {
        "obs": {k: np.stack([s[k] for s in ep.stored]) for k in ep.stored[0]},
        "action": np.asarray(ep.actions),
        "reward": np.asarray(ep.rewards, np.float32),
        "terminated": np.asarray(ep.terms, bool),
        "demo": np.asarray(ep.demo, bool),
        **task.episode_fields(ep.records, ep.goal, ep.env),
    }

"""Recording demonstrations with the scripted controllers (``lcrl demos record``)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from envs.scene import OBJECT_KINDS, object_name
from lcrl.demos import DemoWriter
from lcrl.errors import LcrlError
from train.training.demo_episodes import EPISODE_SCENE, scene_arrays


@dataclass
class RecordConfig:
    """Record scripted-controller (or random-play) episodes on a language-goal preset's
    env (``lcrl demos record --preset lang2d --episodes 500``)."""

    out: str = ""
    """The dataset file to write (default: ``data/demos-PRESET.h5``)."""
    preset: str = "lang2d"
    """Training preset whose env is recorded (``lcrl train --help`` lists them): the
    observations match what that preset's policy sees. Language-goal presets only
    (``lang2d``, ``lang2d-quick``, ``lang2d-dqn``, ``robosuite``, ``robosuite-image`` ...)."""
    families: tuple[str, ...] = ()
    """Instruction families to record (default: the preset's)."""
    episodes: int = 200
    """Episodes to run (with --no-keep-failures only the successful ones are stored)."""
    actor: str = "scripted"
    """Who acts: ``scripted`` (the scripted controllers, with ``--noise``) or ``random``
    (uniformly random actions: random-play data, which offline training with hindsight
    relabelling learns from; ``lcrl train --offline FILE``)."""
    noise: float = 0.3
    """Standard deviation of the Gaussian noise on the scripted actions (policy units):
    varied demonstrations, and near misses that hindsight relabelling turns into
    examples of other instructions."""
    seed: int = 0
    """Seed of the layouts, instructions and action noise."""
    images: bool = False
    """Also store the camera image (``image``) and the robot's proprioception
    (``proprio``) of every step; always on for image-observation presets."""
    image_size: int = 0
    """Camera image side in pixels (0: the preset's; robosuite renders 64 or 84)."""
    max_episode_steps: int = 0
    """Time limit of an episode (0: the preset's)."""
    perception: str = ""
    """A perception model (``lcrl perception train --out``): record what a policy acting
    through it reads (its estimate as ``observation``, the true state as ``privileged``),
    for ``--finetune.demos`` of a run with ``--env.perception`` (default: the preset's
    own, for presets that act through perception)."""
    keep_failures: bool = True
    """Store episodes whose instruction was not achieved (without a segment for it:
    ``lcrl demos relabel`` labels what they did achieve)."""
    overwrite: bool = False
    """Replace an existing file."""
    progress: bool = True
    """Show a progress bar."""

    def resolved_out(self) -> Path:
        """The output path."""
        return Path(self.out or f"data/demos-{self.preset}.h5")

    def env_config(self) -> Any:
        """The recorded env config: the preset's, with this command's overrides."""
        from train.configs.presets import PRESETS
        from train.environments.simulators import env_spec
        from train.environments.tasks import is_language

        if self.preset not in PRESETS:
            raise LcrlError(
                f"unknown preset {self.preset!r}; choose one of {', '.join(_language_presets())}"
            )
        env = PRESETS[self.preset][1].env
        if not is_language(env) and (self.actor != "random" or env.goal_type != "state"):
            raise LcrlError(
                f"preset {self.preset!r} has no language goals, so no scripted controller; "
                f"choose one of {', '.join(_language_presets())}"
                + (
                    ", or record random play with --actor random"
                    if env.goal_type == "state"
                    else ""
                )
            )
        if not is_language(env) and self.families:
            raise LcrlError(f"preset {self.preset!r} has state goals: it has no --families")
        changes: dict[str, Any] = {}
        if self.families:
            allowed = env_spec(env.kind).families
            bad = [f for f in self.families if f not in allowed]
            if bad:
                raise LcrlError(f"the {env.kind} env has the families {allowed}, not {bad}")
            changes["families"] = tuple(self.families)
        if self.max_episode_steps:
            changes["max_episode_steps"] = self.max_episode_steps
        if self.image_size and env.image_obs:
            changes["image_size"] = self.image_size
        if self.perception:
            if env.image_obs:
                raise LcrlError(
                    f"preset {self.preset!r} acts from camera frames itself: --perception "
                    "is for presets that read state"
                )
            changes["perception"] = self.perception
        return dataclasses.replace(env, **changes)

    def validate(self) -> None:
        """Raise :class:`LcrlError` for bad settings."""
        if self.episodes <= 0:
            raise LcrlError(f"--episodes must be positive, got {self.episodes}")
        if self.noise < 0:
            raise LcrlError(f"--noise must be >= 0, got {self.noise}")
        if self.actor not in ACTORS:
            raise LcrlError(f"unknown --actor {self.actor!r}; choose one of {', '.join(ACTORS)}")
        if self.image_size < 0 or self.max_episode_steps < 0:
            raise LcrlError("--image-size and --max-episode-steps must be >= 0 (0: the preset's)")
        out = self.resolved_out()
        if out.is_dir():
            raise LcrlError(f"--out {out} is a folder; give a file name (e.g. {out}/demos.h5)")
        if out.exists() and not self.overwrite:
            raise LcrlError(f"{out} exists; pass --overwrite to replace it")
        self.env_config()

    def run(self) -> None:
        """``lcrl demos record``."""
        record(self)


#: Who acts in recorded episodes (:attr:`RecordConfig.actor`).
ACTORS = ("scripted", "random")


class RandomActor:
    """Uniformly random actions (random play), with the scripted actor's interface."""

    def __init__(self, task: Any) -> None:
        self.task = task

    def reset(self) -> None:
        return None

    def act(self, env: Any, rng: np.random.Generator) -> np.ndarray:
        return self.task.random_action(rng)


def _language_presets() -> list[str]:
    from train.configs.presets import PRESETS
    from train.environments.tasks import is_language

    return [name for name, (_, cfg) in PRESETS.items() if is_language(cfg.env)]


def _recording_env(env_cfg: Any, images: bool, image_size: int) -> Any:
    """The env to record: the preset's, rendering the camera when images are asked for."""
    from train.environments.tasks import make_env

    if images and not env_cfg.image_obs:
        size = image_size or env_cfg.image_size
        env_cfg = dataclasses.replace(
            env_cfg, extra={**env_cfg.extra, "image": True, "image_size": size}
        )
    return make_env(env_cfg, "train", training=False)


def record(cfg: RecordConfig) -> Path:
    """Record ``cfg.episodes`` scripted episodes into ``cfg.out``; returns the path.

    Prints the scripted success rate per family at the end. Ctrl-C stops recording and
    keeps the episodes finished so far (the file is completed and moved into place
    before the interrupt goes on; with no finished episode nothing is written).
    """
    from tqdm import tqdm

    from train.environments.tasks import ScriptedActor, Task, find_language_wrapper, is_language

    cfg.validate()
    env_cfg = cfg.env_config()
    if not is_language(env_cfg):
        return _record_play(cfg, env_cfg)
    images = bool(cfg.images or env_cfg.image_obs)
    env = _recording_env(env_cfg, images, cfg.image_size)
    task = Task(env)
    if cfg.actor == "scripted":
        actor: ScriptedActor | RandomActor = ScriptedActor(env_cfg, task, cfg.noise)
    else:
        actor = RandomActor(task)
    wrapper = find_language_wrapper(env)
    base = env.unwrapped
    proprio_dim = int(getattr(base, "proprio_dim", 0))
    rng = np.random.default_rng([cfg.seed, 1])
    meta: dict[str, Any] = {
        "env": asdict(env_cfg),
        "preset": cfg.preset,
        "split_seed": env_cfg.split_seed,
        "split_fingerprint": wrapper.split.fingerprint(),
        "split_families": list(wrapper.split.families),
        "families": list(env_cfg.families),
        "source": cfg.actor,
        "scene_kinds": [object_name(c, s) for c, s in OBJECT_KINDS],
        "recording": {
            "episodes": cfg.episodes,
            "actor": cfg.actor,
            "noise": cfg.noise if cfg.actor == "scripted" else None,
            "seed": cfg.seed,
            "images": images,
            "image_size": int(env.observation_space["image"].shape[0]) if images else None,
            "keep_failures": cfg.keep_failures,
            "max_episode_steps": env_cfg.max_episode_steps,
        },
    }
    train_texts = [
        t
        for t, m in zip(wrapper.split.train, wrapper.split.instructions("train"), strict=True)
        if m.family in env_cfg.families
    ]
    writer = DemoWriter(
        cfg.resolved_out(),
        meta,
        instructions=train_texts,
        episode_scene=EPISODE_SCENE,
        overwrite=cfg.overwrite,
    )
    tried: dict[str, int] = {f: 0 for f in env_cfg.families}
    won: dict[str, int] = {f: 0 for f in env_cfg.families}
    stats = {"sim_errors": 0, "dropped_failures": 0, "steps": 0}
    bar = tqdm(total=cfg.episodes, disable=not cfg.progress, desc="record", unit="ep")
    started = time.perf_counter()
    try:
        for i in range(cfg.episodes):
            ep = _record_episode(
                env, wrapper, actor, rng, int(cfg.seed * 1_000_003 + i), images, proprio_dim
            )
            bar.update(1)
            if ep is None:
                stats["sim_errors"] += 1
                continue
            family = ep.pop("family")
            tried[family] = tried.get(family, 0) + 1
            won[family] = won.get(family, 0) + int(ep["success"])
            if not ep["success"] and not cfg.keep_failures:
                stats["dropped_failures"] += 1
                continue
            stats["steps"] += len(ep["actions"])
            writer.add_episode(**ep, source=cfg.actor)
            bar.set_postfix(success=f"{sum(won.values()) / max(1, sum(tried.values())):.2f}")
    except BaseException as e:
        _stop_recording(writer, env, bar, e, {"per_family": _rates(tried, won), **stats})
        raise
    bar.close()
    env.close()
    if writer.num_episodes == 0:
        writer.discard()
        raise LcrlError(
            "no episode to store: every episode failed and --no-keep-failures drops them"
        )
    stats["record_s"] = round(time.perf_counter() - started, 1)
    writer.update_meta({"per_family": _rates(tried, won), **stats})
    stored = writer.num_episodes
    path = writer.close()
    print(_format_rates(tried, won, cfg.actor))
    extra = []
    if stats["dropped_failures"]:
        extra.append(f"{stats['dropped_failures']} failed episodes dropped")
    if stats["sim_errors"]:
        extra.append(f"{stats['sim_errors']} ended by simulator errors, dropped")
    note = f" ({'; '.join(extra)})" if extra else ""
    print(f"saved {stored} episodes, {stats['steps']} steps to {path}{note}")
    return path


def _rates(tried: Mapping[str, int], won: Mapping[str, int]) -> dict[str, dict[str, Any]]:
    return {
        f: {"episodes": n, "successes": won.get(f, 0), "rate": won.get(f, 0) / n if n else None}
        for f, n in tried.items()
    }


def _format_rates(tried: Mapping[str, int], won: Mapping[str, int], actor: str = "scripted") -> str:
    lines = [f"{actor} success per family:"]
    for f, n in tried.items():
        rate = f"{won.get(f, 0) / n:.2f}" if n else "  - "
        lines.append(f"  {f:<6} {rate}  ({won.get(f, 0)}/{n})")
    total = sum(tried.values())
    if total:
        lines.append(f"  {'all':<6} {sum(won.values()) / total:.2f}  ({sum(won.values())}/{total})")
    return "\n".join(lines)


def _stop_recording(
    writer: DemoWriter, env: Any, bar: Any, error: BaseException, meta: Mapping[str, Any]
) -> None:
    """A recording stopped by ``error``: on Ctrl-C the finished episodes are kept (the
    file completed with ``meta`` and moved into place), on any other error nothing."""
    bar.close()
    env.close()
    if not isinstance(error, KeyboardInterrupt):
        writer.discard()
    elif writer.num_episodes:
        writer.update_meta({**meta, "interrupted": True})
        path = writer.close()
        print(f"interrupted: kept the {writer.num_episodes} finished episodes in {path}")
    else:
        writer.discard()
        print("interrupted before the first episode finished: nothing written")


def _record_play(cfg: RecordConfig, env_cfg: Any) -> Path:
    """Random play on a state-goal preset's env: per step ``observation``,
    ``achieved_goal`` and ``desired_goal`` (what offline HER relabels state goals from), no
    instruction and no scene. Ctrl-C keeps the finished episodes."""
    from tqdm import tqdm

    from train.environments.tasks import Task, make_env

    env = make_env(env_cfg, "train", training=False)
    task = Task(env)
    rng = np.random.default_rng([cfg.seed, 1])
    meta = {
        "env": asdict(env_cfg),
        "preset": cfg.preset,
        "source": "random",
        "recording": {"episodes": cfg.episodes, "actor": "random", "noise": None,
                      "seed": cfg.seed, "max_episode_steps": env_cfg.max_episode_steps},
    }  # fmt: skip
    writer = DemoWriter(cfg.resolved_out(), meta, overwrite=cfg.overwrite)
    keys = ("observation", "achieved_goal", "desired_goal")
    won = 0
    bar = tqdm(total=cfg.episodes, disable=not cfg.progress, desc="record", unit="ep")
    try:
        for i in range(cfg.episodes):
            obs, _ = env.reset(seed=int(cfg.seed * 1_000_003 + i))
            rows, actions, info = [obs], [], {}
            while True:
                a = task.random_action(rng)
                obs, _, terminated, truncated, info = env.step(task.scale_action(a))
                rows.append(obs)
                actions.append(a)
                if terminated or truncated:
                    break
            success = bool(info.get("is_success", False))
            won += success
            arrays = {k: np.stack([np.asarray(r[k], np.float32) for r in rows]) for k in keys}
            writer.add_episode(arrays, np.asarray(actions), success=success, source="random")
            bar.update(1)
    except BaseException as e:
        _stop_recording(writer, env, bar, e, {})
        raise
    bar.close()
    env.close()
    path = writer.close()
    print(f"random play reached its goal in {won}/{cfg.episodes} episodes")
    print(f"saved {cfg.episodes} episodes to {path}")
    return path


def _record_episode(
    env: Any,
    wrapper: Any,
    actor: Any,
    rng: np.random.Generator,
    seed: int,
    images: bool,
    proprio_dim: int,
) -> dict[str, Any] | None:
    """One scripted episode, or None when a simulator error ended it."""
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    instruction = obs["instruction"]
    family = wrapper.meaning.family
    actor.reset()
    rows = [obs]
    scenes = [base.scene()]
    actions = []
    info: dict[str, Any] = {}
    while True:
        a = actor.act(env, rng)
        obs, _, terminated, truncated, info = env.step(actor.task.scale_action(a))
        rows.append(obs)
        scenes.append(base.scene())
        actions.append(a)
        if terminated or truncated:
            break
    if info.get("sim_error"):
        return None
    out_obs = {"observation": np.stack([np.asarray(r["observation"], np.float32) for r in rows])}
    if "privileged" in rows[0]:  # acting through perception: the true state beside it
        out_obs["privileged"] = np.stack([np.asarray(r["privileged"], np.float32) for r in rows])
    if images:
        out_obs["image"] = np.stack([np.asarray(r["image"], np.uint8) for r in rows])
        out_obs["proprio"] = out_obs["observation"][:, :proprio_dim].copy()
    return {
        "obs": out_obs,
        "actions": np.asarray(actions),
        "instruction": instruction,
        "scene": scene_arrays(scenes),
        "success": bool(info.get("is_success", False)),
        "family": family,
    }

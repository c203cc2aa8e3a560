"""``lcrl demos``: record, relabel, inspect and import demonstration datasets.

* :func:`record` runs the scripted controller of a language-goal preset (``lang2d``,
  ``robosuite`` ...) on instructions of the split's training set and writes what the policy
  of that preset observes, the actions in policy units, the instruction as a segment
  ending at the success step, the privileged scene of every step (so the rule captioner
  can run later) and the recording settings (:mod:`lcrl.demos` describes the file).
* :func:`relabel` is instruction augmentation in hindsight (as in DIAL): every segment
  ``[start, t]`` of every episode is captioned, and each instruction an episode achieved
  becomes a segment ending at the first step it holds. Failed demonstrations, which teach
  nothing about their own instruction, teach what they did do.
* :func:`info` and :func:`import_robomimic` (robomimic / LIBERO files) round it off.

Scene arrays (``scene/<name>``) use one slot per object kind of
:data:`envs.scene.OBJECT_KINDS`: per step ``positions`` ``(K, 3)``, ``gripper`` ``(3,)``,
``grasped`` and ``touching`` ``(K,)`` (when the env reports them); per episode
``present`` ``(K,)``, ``colours`` and ``shapes`` ``(K,)`` (empty where absent),
``half_extents`` ``(K, 3)``, ``table_bounds`` ``(4,)`` and ``table_height``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from envs.scene import OBJECT_KINDS, SceneState, object_name
from lcrl.demos import GIVEN, HINDSIGHT, DemoDataset, DemoWriter, append_segments
from lcrl.errors import LcrlError

#: Scene arrays that describe a whole episode (one row per episode).
EPISODE_SCENE: tuple[str, ...] = (
    "present",
    "colours",
    "shapes",
    "half_extents",
    "table_bounds",
    "table_height",
)

__all__ = [
    "EPISODE_SCENE",
    "ImportRobomimicCommand",
    "InfoCommand",
    "RecordConfig",
    "RelabelCommand",
    "family_of",
    "info",
    "record",
    "relabel",
    "scene_arrays",
    "scenes_from_arrays",
]


# --------------------------------------------------------------------------- scenes


def scene_arrays(scenes: Sequence[SceneState]) -> dict[str, np.ndarray]:
    """An episode's scenes as fixed-width arrays, one slot per object kind."""
    s0 = scenes[0]
    k = len(OBJECT_KINDS)
    kinds = [object_name(c, s) for c, s in OBJECT_KINDS]
    slot = np.asarray([kinds.index(n) for n in s0.names], np.int64)
    n = len(scenes)
    positions = np.zeros((n, k, 3), np.float64)
    gripper = np.zeros((n, 3), np.float64)
    grasped = np.zeros((n, k), bool)
    touching = np.zeros((n, k), bool)
    for t, s in enumerate(scenes):
        if s.names != s0.names:
            raise LcrlError("the objects on the table changed within an episode")
        positions[t, slot] = s.positions
        gripper[t] = s.gripper
        if s.grasped is not None:
            grasped[t, slot] = s.grasped
        if s.touching is not None:
            touching[t, slot] = s.touching
    present = np.zeros(k, bool)
    present[slot] = True
    colours = np.full(k, "", dtype=object)
    shapes = np.full(k, "", dtype=object)
    colours[slot] = s0.colours
    shapes[slot] = s0.shapes
    half = np.zeros((k, 3), np.float64)
    half[slot] = s0.half_extents
    out = {
        "positions": positions,
        "gripper": gripper,
        "present": present,
        "colours": colours.astype(str),
        "shapes": shapes.astype(str),
        "half_extents": half,
        "table_bounds": np.asarray(s0.table_bounds, np.float64),
        "table_height": np.asarray(s0.table_height, np.float64),
    }
    if s0.grasped is not None:
        out["grasped"] = grasped
    if s0.touching is not None:
        out["touching"] = touching
    return out


def check_dataset(data: DemoDataset, path: str, problem: Any, task: Any, env: Any) -> None:
    """Raise :class:`LcrlError` naming what a dataset lacks for a run that fills its
    replay buffer from it (``lcrl train --offline``, ``--finetune.demos``): episodes, the
    run's action space, a language-goal task, the observation keys and shapes, the scene."""
    if data.num_episodes == 0:
        raise LcrlError(f"{path} holds no episode")
    want = () if problem.discrete else (problem.action_dim,)
    if tuple(data.action_shape) != want or data.discrete != problem.discrete:
        raise LcrlError(
            f"{path} has {'discrete' if data.discrete else 'continuous'} actions of shape "
            f"{data.action_shape}; this run acts with {want or 'discrete'} actions"
        )
    if task.table is None and task.goal_kind != "vector":
        raise LcrlError(
            f"{path}: offline runs relabel instructions (from the stored scene) or state "
            f"goals (from stored achieved_goal), not {task.goal_kind} goals"
        )
    _check_perception(data, path, env)
    episode = buffer_episode(data, 0, path, task, env)  # names a missing key
    for key, shape in problem.obs_shapes.items():
        got = tuple(episode["obs"][key].shape[1:])
        if got != tuple(shape):
            raise LcrlError(
                f"{path}: observation {key!r} has shape {got}, this run's policy reads "
                f"{tuple(shape)}: record the file with this run's preset"
            )


def _check_perception(data: DemoDataset, path: str, env: Any) -> None:
    """A run acting through perception reads its estimate: the file must hold one (and a
    run reading the true state must not be given an estimate as its state)."""
    from train.environments.perception import find_perception

    acts = env is not None and find_perception(env) is not None
    recorded = (data.meta.get("env") or {}).get("perception") or ""
    has_estimate = bool(recorded) and "privileged" in data.obs_shapes
    if acts and not has_estimate:
        raise LcrlError(
            f"{path} stores the true state, and this run acts through a perception model: "
            "record the file through it (lcrl demos record --perception MODEL)"
        )
    if not acts and has_estimate:
        raise LcrlError(
            f"{path} stores a perception model's estimate ({recorded}) as its observation, and "
            "this run reads the true state: record it without --perception"
        )


#: Episode sources whose actions are no demonstrator's (``sac.demo_bc`` leaves them out).
NOT_DEMONSTRATIONS = ("random", "policy")


def buffer_episode(data: DemoDataset, e: int, path: str, task: Any, env: Any) -> dict[str, Any]:
    """Episode ``e`` of a dataset as the replay buffer stores it, labelled like a training
    episode: the task's observations, and what the rule captioner says each step achieved
    on the stored scene. An episode without a (known) instruction keeps goal 0: its
    recorded-goal rows are scored against that instruction like any other, the relabelled
    ones by what it did."""
    ep = data.episode(e)
    t = int(ep["length"])
    rows = [{k: v[i] for k, v in ep["obs"].items()} for i in range(t + 1)]
    try:
        stored = [task.training_obs(row, rows[0]) for row in rows]
    except KeyError as err:
        raise LcrlError(
            f"{path} has no observation key {err.args[0]!r} (it has "
            f"{', '.join(sorted(ep['obs']))}), which this run's policy and critic read: "
            "record the file with this run's preset (lcrl demos record --preset ...)"
        ) from None
    obs = {k: np.stack([s[k] for s in stored]) for k in stored[0]}
    if task.table is not None:  # language: the captioner on the scene
        text = ep["instruction"]
        goal = task.ids[text] if text is not None and text in task.ids else 0
        records: list[Any] = scenes_from_arrays(ep["scene"])
    else:  # state goals: the stored achieved and desired goals
        missing = [k for k in ("achieved_goal", "desired_goal") if k not in ep["obs"]]
        if missing:
            raise LcrlError(
                f"{path} stores no {' or '.join(missing)}, which state goals are relabelled "
                "from: record it with lcrl demos record --actor random --preset PRESET"
            )
        records = [task.step_record(row, env) for row in rows]
        goal = task.goal(rows[0], env)
    return {
        "obs": obs,
        "action": ep["action"],
        "reward": np.zeros(t, np.float32),
        # successes end episodes through the goal space (terminate_on_success), from labels
        "terminated": np.zeros(t, bool),
        # a demonstrator's actions (scripted, robomimic, LIBERO), not random play's
        "demo": np.full(t, ep["source"] not in NOT_DEMONSTRATIONS, bool),
        **task.episode_fields(records, goal, env),
    }


def scenes_from_arrays(scene: Mapping[str, np.ndarray]) -> list[SceneState]:
    """Rebuild an episode's :class:`~envs.scene.SceneState` list from its scene arrays."""
    needed = ("positions", "gripper", "present", "colours", "shapes", "half_extents")
    missing = [k for k in needed if k not in scene]
    if missing:
        raise LcrlError(
            f"the episode's privileged scene lacks {missing}: the rule captioner needs a "
            "file recorded by lcrl demos record"
        )
    idx = np.flatnonzero(np.asarray(scene["present"], bool))
    colours = tuple(str(c) for c in np.asarray(scene["colours"])[idx])
    shapes = tuple(str(s) for s in np.asarray(scene["shapes"])[idx])
    half = np.asarray(scene["half_extents"], np.float64)[idx]
    bounds = tuple(float(v) for v in np.asarray(scene.get("table_bounds", (-1, 1, -1, 1))))
    height = float(np.asarray(scene.get("table_height", 0.0)))
    positions = np.asarray(scene["positions"], np.float64)
    grasped = scene.get("grasped")
    touching = scene.get("touching")
    return [
        SceneState(
            colours=colours,
            shapes=shapes,
            positions=positions[t][idx],
            half_extents=half,
            gripper=np.asarray(scene["gripper"][t], np.float64),
            table_bounds=bounds,  # type: ignore[arg-type]
            table_height=height,
            grasped=None if grasped is None else np.asarray(grasped[t], bool)[idx],
            touching=None if touching is None else np.asarray(touching[t], bool)[idx],
        )
        for t in range(len(positions))
    ]


def family_of(text: str) -> str:
    """The instruction family of a text (its first word when the grammar cannot read it)."""
    from captioner.grammar import try_parse

    meaning = try_parse(text)
    if meaning is not None:
        return meaning.family
    return text.split()[0] if text.split() else "?"


# --------------------------------------------------------------------------- recording


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


# --------------------------------------------------------------------------- relabelling


def _split_of(meta: Mapping[str, Any], path: Path) -> Any:
    """The compositional split a dataset was recorded with (from its meta)."""
    from captioner.splits import make_split
    from train.environments.simulators import ENVS, canonical_kind

    env = meta.get("env")
    kind = canonical_kind(str(env.get("kind"))) if isinstance(env, dict) else ""
    if kind not in ENVS or not ENVS[kind].families:
        raise LcrlError(
            f"{path} does not say which tabletop it was recorded on (no env in its meta): "
            "relabel needs a file written by lcrl demos record"
        )
    families = meta.get("split_families") or ENVS[kind].families
    split = make_split(int(meta.get("split_seed", env.get("split_seed", 0))), tuple(families))
    want = meta.get("split_fingerprint")
    if want and split.fingerprint() != want:
        raise LcrlError(
            f"{path} was recorded with split {want}, but this lcrl makes "
            f"{split.fingerprint()} from its seed: the split code changed since"
        )
    return split


def relabel(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    captioner: str = "rule",
    starts_every: int = 0,
    train_only: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    beam: int = 3,
    min_logprob: float = -1.0,
    device: str = "cpu",
) -> dict[str, Any]:
    """Add hindsight segments for everything each episode achieved (DIAL-style).

    For every episode and every segment start (0, and every ``starts_every`` steps when
    positive) the captioner reads the change from the start to each later step; each
    instruction it finds gives the segment ``[start, t]`` with ``t`` the first step where
    it holds (instructions that already hold at the start are skipped, and so is a
    segment identical to a given one). Existing hindsight segments of ``src`` are
    replaced. The result is written atomically to ``dst`` (which may be ``src``).

    Args:
        src: a dataset recorded by :func:`record`.
        dst: where to write the relabelled dataset.
        captioner: ``rule`` (the rule captioner on the stored privileged scene) or the
            path of a learned-captioner checkpoint (``lcrl caption train``), which reads
            the stored camera frames and proprioception.
        starts_every: also start segments every this many steps (0: only at step 0).
            Later starts judge the instruction against that step's observation (the
            displacement features of the observation still count from the reset).
        train_only: only add instructions of the split's training set for the recorded
            families, so that held-out combinations never enter training data.
        overwrite: replace an existing ``dst`` (other than ``src``).
        progress: show a progress bar.
        beam: beam width of the learned captioner.
        min_logprob: learned captions less likely than this are skipped.
        device: torch device of the learned captioner.

    Returns:
        Counts (also printed by the CLI): episodes, given and added hindsight segments,
        distinct instructions before and after, per-family segments, segments per
        episode, and how many failed episodes gained at least one instruction.
    """
    from tqdm import tqdm

    from captioner.rule import RuleCaptioner

    src, dst = Path(src), Path(dst)
    if starts_every < 0:
        raise LcrlError(f"--starts-every must be >= 0, got {starts_every}")
    same = dst.exists() and src.exists() and os.path.samefile(src, dst)
    if dst.exists() and not same and not overwrite:
        raise LcrlError(f"{dst} exists; pass --overwrite to replace it")
    with DemoDataset(src) as data:
        meta = data.meta
        split = _split_of(meta, src)
        families = tuple(meta.get("families") or meta["env"].get("families", ()))
        pairs = [(t, m) for t, m in zip(split.train, split.instructions("train"), strict=True)]
        if not train_only:
            pairs += list(zip(split.heldout, split.instructions("heldout"), strict=True))
        allowed = {t for t, m in pairs if m.family in families}
        heldout = set(split.heldout)
        learned = captioner != "rule"
        labeller = None
        if learned:
            labeller = _learned_labeller(
                captioner, data, sorted(allowed), beam, min_logprob, device
            )
        if not learned and "positions" not in data.scene_keys:
            raise LcrlError(
                f"{src} stores no privileged scene (it was not recorded by lcrl demos "
                "record): the rule captioner cannot run; use a learned captioner on its images"
            )
        rule = RuleCaptioner(families)
        given = data.segments(hindsight=False)
        given_keys = {tuple(r[:4]) for r in given.tolist()}
        rows: list[tuple[int, int, int, str]] = []
        gained = np.zeros(data.num_episodes, bool)
        bar = tqdm(range(data.num_episodes), disable=not progress, desc="relabel", unit="ep")
        for e in bar:
            ep = data.episode(e)
            t_len = int(ep["length"])
            starts = [0]
            if starts_every > 0:
                starts += list(range(starts_every, t_len, starts_every))
            if labeller is None:
                found = _rule_segments(rule, scenes_from_arrays(ep["scene"]), starts, allowed)
            else:
                found = _learned_segments(labeller, ep["obs"], starts)
            for start, end, text in found:
                iid = data.instructions.index(text) if text in data.instructions else -1
                if (e, start, end, iid) in given_keys:
                    continue  # the given segment, found again
                rows.append((e, start, end, text))
                gained[e] = True
        failed = data.episode_success == 0
        before = data.counts()
        table = list(data.instructions)
    leaked = sorted({t for _, _, _, t in rows if t in heldout}) if train_only else []
    if leaked:  # pragma: no cover - a bug, never a user mistake
        raise RuntimeError(f"held-out instructions in a train-only relabelling: {leaked[:3]}")
    settings = {
        "captioner": captioner,
        "starts_every": starts_every,
        "train_only": train_only,
        "source": str(src),
    }
    out = append_segments(src, rows, dst, drop_hindsight=True, meta={"relabel": settings})
    with DemoDataset(out) as result:
        seg = result.segments()
        after = result.counts()
        texts = result.instructions
    per_family: dict[str, dict[str, int]] = {}
    for iid, origin in seg[:, 3:5].tolist():
        row = per_family.setdefault(family_of(texts[iid]), {"given": 0, "hindsight": 0})
        row["given" if origin == GIVEN else "hindsight"] += 1
    n_eps = int(before["episodes"])
    counts = {
        "episodes": n_eps,
        "failed_episodes": int(failed.sum()),
        "failed_with_hindsight": int((failed & gained).sum()),
        "given_segments": int(np.sum(seg[:, 4] == GIVEN)),
        "hindsight_segments": int(np.sum(seg[:, 4] == HINDSIGHT)),
        "instructions_before": int(before["distinct_instructions"]["given"]),
        "instructions_after": int(after["distinct_instructions"]["all"]),
        "new_instructions": len(set(texts) - set(table)),
        "segments_per_episode": len(seg) / max(1, n_eps),
        "per_family": dict(sorted(per_family.items())),
        **settings,
        "out": str(out),
    }
    return counts


def _rule_segments(
    rule: Any, scenes: Sequence[SceneState], starts: Sequence[int], allowed: set[str]
) -> list[tuple[int, int, str]]:
    """(start, first step, text) of every allowed instruction the scenes achieve."""
    out = []
    for start in starts:
        s0 = scenes[start]
        already = {i.text for i in rule.caption(s0, s0)}
        first: dict[str, int] = {}
        for t in range(start + 1, len(scenes)):
            for ins in rule.caption(s0, scenes[t]):
                text = ins.text
                if text in allowed and text not in already and text not in first:
                    first[text] = t
        out.extend((start, t, text) for text, t in sorted(first.items(), key=lambda x: x[1]))
    return out


def _learned_labeller(
    path: str, data: DemoDataset, table: list[str], beam: int, min_logprob: float, device: str
) -> Any:
    from captioner.learned import LearnedCaptioner, LearnedLabeller

    if "image" not in data.obs_shapes:
        raise LcrlError(
            f"a learned captioner reads camera frames and {data.path} has none: record with "
            "--images, or relabel with --captioner rule"
        )
    if not Path(path).exists():
        raise LcrlError(
            f"--captioner must be 'rule' or a learned-captioner checkpoint; {path} does not exist"
        )
    models = LearnedCaptioner.load(path, device=device)
    shape = data.obs_shapes["image"]
    if tuple(shape) != tuple(models.frame_shape):
        raise LcrlError(
            f"the captioner reads {'x'.join(map(str, models.frame_shape))} frames; {data.path} "
            f"has {'x'.join(map(str, shape))} (record with --image-size {models.frame_shape[0]})"
        )
    if "proprio" not in data.obs_shapes and "observation" not in data.obs_shapes:
        raise LcrlError(f"{data.path} stores no proprioception for the learned captioner")
    return LearnedLabeller(
        models,
        table,
        len(table),
        captioner=True,
        reward=False,
        min_logprob=min_logprob,
        beam=beam,
    )


def _learned_segments(
    labeller: Any, obs: Mapping[str, np.ndarray], starts: Sequence[int]
) -> list[tuple[int, int, str]]:
    frames = np.asarray(obs["image"], np.uint8)
    dim = labeller.models.proprio_dim
    proprio = obs["proprio"] if "proprio" in obs else obs["observation"][:, :dim]
    proprio = np.asarray(proprio, np.float32)
    if proprio.shape[1] != dim:
        raise LcrlError(
            f"the captioner reads {dim} proprioception values; the file stores {proprio.shape[1]}"
        )
    out = []
    for start in starts:
        labels = labeller.labels(frames[start:], proprio[start:])
        first: dict[str, int] = {}
        for k, ids in enumerate(labels):
            for i in ids:
                text = labeller.table[i]
                first.setdefault(text, start + k)
        out.extend((start, t, text) for text, t in first.items() if t > start)
    return out


def format_relabel(counts: Mapping[str, Any]) -> str:
    """The counts of :func:`relabel` for the terminal."""
    n = counts["starts_every"]
    every = f" and every {n} steps" if n else ""
    lines = [
        f"relabelled {counts['episodes']} episodes with the {counts['captioner']} captioner "
        f"(segments from step 0{every}; "
        f"{'training instructions only' if counts['train_only'] else 'held-out ones included'})",
        f"  segments: {counts['given_segments']} given + {counts['hindsight_segments']} "
        f"hindsight ({counts['segments_per_episode']:.2f} per episode)",
        f"  distinct instructions: {counts['instructions_before']} before, "
        f"{counts['instructions_after']} after",
        f"  failed episodes that gained an instruction: {counts['failed_with_hindsight']} of "
        f"{counts['failed_episodes']}",
        "  per family (given / hindsight):",
    ]
    for fam, row in counts["per_family"].items():
        lines.append(f"    {fam:<6} {row['given']:>6} / {row['hindsight']}")
    lines.append(f"saved {counts['out']}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- info


def info(path: str | os.PathLike) -> dict[str, Any]:
    """The dataset's counts with segments per family and its recording settings."""
    with DemoDataset(path) as data:
        c = data.counts()
        per_family: dict[str, dict[str, int]] = {}
        for text, row in c["per_instruction"].items():
            fam = per_family.setdefault(family_of(text), {"given": 0, "hindsight": 0})
            fam["given"] += row["given"]
            fam["hindsight"] += row["hindsight"]
        c["per_family"] = dict(sorted(per_family.items()))
        c["summary"] = data.summary()
        c["meta"] = data.meta
        c["obs_shapes"] = {k: list(v) for k, v in data.obs_shapes.items()}
        c["action_shape"] = list(data.action_shape)
        c["discrete"] = data.discrete
    return c


# --------------------------------------------------------------------------- commands


@dataclass
class RelabelCommand:
    """Add hindsight segments to a dataset: every instruction each episode achieved,
    ending at the first step it holds (``lcrl demos relabel SRC --out DST``)."""

    src: tyro.conf.Positional[str]
    """The dataset to relabel (recorded by ``lcrl demos record``)."""
    out: str = ""
    """Where to write the relabelled dataset (required; may be SRC itself, replaced
    atomically)."""
    captioner: str = "rule"
    """``rule`` (privileged scene) or the folder of a learned-captioner checkpoint
    (``lcrl caption train``; needs a dataset recorded with --images)."""
    starts_every: int = 0
    """Also caption segments starting every this many steps (0: only from step 0)."""
    train_only: bool = True
    """Only add instructions of the split's training set (held-out combinations never
    enter the training data); --no-train-only adds held-out ones too."""
    beam: int = 3
    """Beam width of a learned captioner."""
    min_logprob: float = -1.0
    """Learned captions less likely than this are skipped."""
    overwrite: bool = False
    """Replace an existing --out file."""
    json: str = ""
    """Also write the counts to this JSON file."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> None:
        """``lcrl demos relabel``."""
        if not self.out:
            raise LcrlError("pass --out DST (the relabelled dataset; SRC itself to replace it)")
        if self.json:  # before the work: a --json that cannot be written fails now
            from train.runtime.run_lock import check_output_file

            check_output_file(self.json, "--json")
        counts = relabel(
            self.src,
            self.out,
            captioner=self.captioner,
            starts_every=self.starts_every,
            train_only=self.train_only,
            overwrite=self.overwrite,
            progress=self.progress,
            beam=self.beam,
            min_logprob=self.min_logprob,
        )
        print(format_relabel(counts))
        if self.json:
            _write_json(self.json, counts)


@dataclass
class InfoCommand:
    """Summarise a demonstration dataset: episodes, outcomes, observations, segments and
    instructions (given and hindsight) per family (``lcrl demos info FILE``)."""

    path: tyro.conf.Positional[str]
    """The dataset file."""
    instructions: bool = False
    """Also list the segments per instruction."""
    json: bool = False
    """Print the counts as JSON instead of text."""

    def run(self) -> None:
        """``lcrl demos info``."""
        c = info(self.path)
        if self.json:
            print(json.dumps({k: v for k, v in c.items() if k != "summary"}, indent=1))
            return
        print(c["summary"])
        print("  segments per family (given / hindsight):")
        for fam, row in c["per_family"].items():
            print(f"    {fam:<8} {row['given']:>6} / {row['hindsight']}")
        rec = c["meta"].get("recording")
        if isinstance(rec, dict):
            settings = ", ".join(f"{k} {v}" for k, v in rec.items())
            print(f"  recording: {settings}")
        rates = c["meta"].get("per_family")
        if isinstance(rates, dict) and rates:
            parts = [f"{f} {r['rate']:.2f}" for f, r in rates.items() if r.get("rate") is not None]
            print(f"  scripted success: {', '.join(parts)}")
        relabelled = c["meta"].get("relabel")
        if isinstance(relabelled, dict):
            n = relabelled.get("starts_every")
            which = "training instructions only"
            if not relabelled.get("train_only"):
                which = "held-out ones included"
            print(
                f"  relabelled by the {relabelled.get('captioner')} captioner (segments from "
                f"step 0{f' and every {n} steps' if n else ''}; {which})"
            )
        if self.instructions:
            print("  segments per instruction (given / hindsight):")
            for text, row in c["per_instruction"].items():
                print(f"    {row['given']:>6} / {row['hindsight']:<6} {text}")


@dataclass
class ImportRobomimicCommand:
    """Convert a robomimic-style HDF5 file (robomimic, LIBERO) into a demonstration
    dataset (``lcrl demos import-robomimic SRC --out DST``)."""

    src: tyro.conf.Positional[str]
    """The robomimic file (``data/demo_<i>/{obs, actions, ...}``)."""
    out: str = ""
    """The dataset file to write (required)."""
    instruction: str = ""
    """The instruction of every demo (default: LIBERO's ``problem_info``
    ``language_instruction``)."""
    obs_keys: tuple[str, ...] = ()
    """Low-dimensional observation keys concatenated into ``observation``, in this order
    (default: every non-image key, sorted)."""
    image_key: str = "auto"
    """Camera key stored as ``image`` (``auto``: ``agentview_image`` / ``agentview_rgb`` /
    the first image key; ``none``: no image)."""
    proprio_keys: tuple[str, ...] = ()
    """Keys concatenated into ``proprio`` (the robot's state for camera policies)."""
    overwrite: bool = False
    """Replace an existing --out file."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> None:
        """``lcrl demos import-robomimic``."""
        import warnings

        from tqdm import tqdm

        from lcrl.demos import import_robomimic

        if not self.out:
            raise LcrlError("pass --out DST (the demonstration dataset to write)")
        image_key = None if self.image_key.lower() in ("", "none") else self.image_key

        def bar(items: Any) -> Any:
            return tqdm(items, disable=not self.progress, desc="import", unit="demo")

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the clipped count is printed below
            path = import_robomimic(
                self.src,
                self.out,
                instruction=self.instruction or None,
                obs_keys=tuple(self.obs_keys) or None,
                image_key=image_key,
                proprio_keys=self.proprio_keys,
                overwrite=self.overwrite,
                progress=bar,
            )
        with DemoDataset(path) as data:
            print(data.summary())
            settings = data.meta["import"]
        print(
            f"  imported keys: observation = {' + '.join(settings['obs_keys']) or '-'}, "
            f"image = {settings['image_key'] or '-'}"
        )
        if settings.get("clipped_values"):
            print(
                f"warning: {settings['clipped_values']} of {settings['action_values']} action "
                "values were outside [-1, 1] and were clipped"
            )


def _write_json(path: str, value: Any) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=1) + "\n")
    os.replace(tmp, p)
    print(f"saved {p}")


#: ``lcrl demos`` subcommands.
COMMANDS: dict[str, type] = {
    "record": RecordConfig,
    "relabel": RelabelCommand,
    "info": InfoCommand,
    "import-robomimic": ImportRobomimicCommand,
}

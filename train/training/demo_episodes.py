"""Demonstration episodes as the trainers read them: scenes to and from arrays, the checks a
file passes before training, an episode in the replay buffer's layout, and a file's summary."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from envs.scene import OBJECT_KINDS, SceneState, object_name
from lcrl.demos import DemoDataset
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
        if getattr(task, "labeller", None) is not None:  # learned labels read the frames
            records = _with_frames(records, ep["obs"], path)
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


def _with_frames(
    scenes: list[SceneState], obs: Mapping[str, np.ndarray], path: str
) -> list[tuple[SceneState, np.ndarray, np.ndarray]]:
    """Each step's scene with its camera frame and the robot's state, as a learned
    captioner and reward model read them (:meth:`LanguageTask.step_record`)."""
    missing = [k for k in ("image", "proprio") if k not in obs]
    if missing:
        raise LcrlError(
            f"{path} stores no camera frames ({' or '.join(missing)}), which learned "
            "relabelling reads: record it with lcrl demos record --images"
        )
    frames, proprio = np.asarray(obs["image"]), np.asarray(obs["proprio"], np.float32)
    return [(s, frames[i], proprio[i]) for i, s in enumerate(scenes)]


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

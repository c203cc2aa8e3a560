"""``lcrl perception collect | train | eval``: learn to read object slots from camera frames.

* ``collect`` writes a caption dataset (:mod:`captioner.dataset`): random, scripted and
  policy episodes, every frame with the privileged observation the simulator labels it
  with.
* ``train`` fits :class:`lcrl.perception.Perception` by regression on the episodes of a
  dataset, holding out a fraction of them (their layouts) for evaluation; Ctrl-C saves the
  model trained so far.
* ``eval`` reports, on held-out episodes (or another dataset: new layouts), the position
  error per object kind in cm, the presence accuracy, and how often the error stays within
  the rule captioner's success thresholds of reach (2 cm) and push (5 cm).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import tyro

from lcrl.checkpoint import save_checkpoint
from lcrl.errors import LcrlError
from lcrl.perception import (
    FORMAT,
    MIN_POSITION_STD,
    HeldSlots,
    Perception,
    PerceptionConfig,
    SlotLayout,
    embedded_meta,
    fit_stats,
    load_model,
    model_meta,
    perception_loss,
)
from train.runtime.memory import check_memory

__all__ = [
    "PerceptionEvalCommand",
    "PerceptionObservation",
    "PerceptionTrainConfig",
    "embedded_meta",
    "evaluate",
    "find_perception",
    "load_model",
    "model_meta",
    "read_dataset",
    "save_model",
    "train",
]

#: The rule captioner's reach margin and push distance, in metres (captioner.rule).
REACH_MARGIN, PUSH_DISTANCE = 0.02, 0.05
#: Frames with the agent this close to an object (in the plane) are reported apart: where
#: reach and push are judged, and where the gripper hides objects from the camera.
NEAR_DISTANCE = 0.05


@dataclass
class PerceptionTrainConfig:
    """Train a perception model on a caption dataset (``lcrl perception train``)."""

    data: str = "data/perception-robosuite.h5"
    """Caption dataset with privileged observations (``lcrl perception collect``)."""
    out: str = "runs/perception"
    """Folder of the model checkpoint (and its evaluation, eval.json)."""
    steps: int = 3000
    """Gradient steps."""
    batch_size: int = 64
    """Frames per step."""
    lr: float = 1e-3
    """Adam learning rate (cosine decay to a tenth)."""
    heldout_fraction: float = 0.1
    """Fraction of the episodes (layouts) kept out of training, for evaluation."""
    seed: int = 0
    """Seed of the held-out episodes, the batches and the augmentation."""
    extra_data: tuple[str, ...] = ()
    """More caption datasets of the same env, camera and objects, every episode of which
    trains as well (more layouts); the held-out episodes come from ``data`` alone."""
    model: PerceptionConfig = field(default_factory=PerceptionConfig)
    """The network."""
    init: str = ""
    """Start from this perception model's weights and normalisers instead of a new network
    (continue training, e.g. at a lower ``--lr``; its network settings replace
    ``--model.*``, all but ``--model.hold-radius``). It must read frames of the dataset's
    size and its slot layout, and have been trained with the same held-out episodes (same
    ``--seed`` and ``--heldout-fraction``)."""
    device: str = "cpu"
    """Torch device."""
    threads: int = 0
    """Torch threads (0: torch's default)."""
    progress: bool = True
    """Show a progress bar."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for inconsistent settings."""
        if self.steps <= 0 or self.batch_size <= 0 or self.lr <= 0:
            raise LcrlError("steps, batch_size and lr must be positive")
        if not 0.0 <= self.heldout_fraction < 1.0:
            raise LcrlError("heldout_fraction must be in [0, 1)")
        self.model.validate()


@dataclass
class Frames:
    """Frames, proprioception and privileged observations of some dataset episodes."""

    frames: np.ndarray
    proprio: np.ndarray
    state: np.ndarray
    episodes: np.ndarray

    FIELDS = ("frames", "proprio", "state", "episodes")


def read_dataset(path: str, episodes: np.ndarray | None = None) -> tuple[Frames, dict[str, Any]]:
    """The frames and labels of a caption dataset (all episodes, or the given ones), and
    its meta.

    Raises:
        LcrlError: no such file, or a dataset without privileged observations.
    """
    from captioner.dataset import CaptionDataset

    if not Path(path).is_file():
        raise LcrlError(f"no dataset at {path}: collect one with lcrl perception collect")
    with CaptionDataset(path) as data:
        if data.state is None or "slot_layout" not in data.meta:
            raise LcrlError(
                f"{path} holds no privileged observations (written by an earlier lcrl): "
                "collect it again with lcrl perception collect"
            )
        eps = np.arange(data.num_episodes) if episodes is None else np.asarray(episodes)
        idx = np.concatenate(
            [np.arange(data.episode_start[e], data.episode_start[e + 1]) for e in eps]
        )
        frame = int(np.prod(data.frame_shape))
        what = f"the camera frames of {path} ({len(idx):,} frames of {frame:,} bytes)"
        check_memory(len(idx) * frame, what, "the dataset (collect fewer --episodes)")
        return (
            Frames(data.read_frames(idx), data.proprio[idx], data.state[idx], data.episode_of(idx)),
            dict(data.meta),
        )


def with_extra_data(data: Frames, meta: Mapping[str, Any], paths: tuple[str, ...]) -> Frames:
    """``data`` followed by every episode of the datasets at ``paths`` (episode numbers
    continue after ``data``'s).

    Raises:
        LcrlError: a dataset of another env, frame size or slot layout than ``meta``'s.
    """
    parts, top = [data], int(np.max(data.episodes)) + 1 if len(data.episodes) else 0
    for path in paths:
        more, more_meta = read_dataset(path)
        for key, what in (("env", "env"), ("slot_layout", "slot layout")):
            if more_meta.get(key) != meta.get(key):
                raise LcrlError(
                    f"--extra-data {path} has the {what} {more_meta.get(key)}; the training "
                    f"dataset has {meta.get(key)}"
                )
        if more.frames.shape[1:] != data.frames.shape[1:]:
            raise LcrlError(
                f"--extra-data {path} holds {more.frames.shape[1:]} frames; the training "
                f"dataset holds {data.frames.shape[1:]}"
            )
        parts.append(Frames(more.frames, more.proprio, more.state, more.episodes + top))
        top += int(np.max(more.episodes)) + 1 if len(more.episodes) else 0
    return Frames(*(np.concatenate([getattr(p, k) for p in parts]) for k in Frames.FIELDS))


def split_episodes(num: int, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out episode indices (at least one of each when ``fraction > 0``)."""
    order = np.random.default_rng(seed).permutation(num)
    held = round(num * fraction)
    if fraction > 0:
        held = min(max(held, 1), num - 1)
    return np.sort(order[held:]), np.sort(order[:held])


def train(cfg: PerceptionTrainConfig) -> dict[str, Any]:
    """Train, save and evaluate a perception model; returns the held-out evaluation."""
    cfg.validate()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    from captioner.dataset import CaptionDataset

    if not Path(cfg.data).is_file():
        raise LcrlError(f"no dataset at {cfg.data}: collect one with lcrl perception collect")
    with CaptionDataset(cfg.data) as data:
        num = data.num_episodes
    if num < 2:
        raise LcrlError(f"{cfg.data} has {num} episode(s): perception needs at least 2")
    train_eps, held_eps = split_episodes(num, cfg.heldout_fraction, cfg.seed)
    data, meta = read_dataset(cfg.data, train_eps)
    layout = SlotLayout.of(meta["slot_layout"])
    if cfg.extra_data:
        data = with_extra_data(data, meta, cfg.extra_data)
    device = torch.device(cfg.device)
    torch.manual_seed(cfg.seed)
    if cfg.init:
        model = initial_model(cfg, data.frames.shape[1:], layout, held_eps)
        widen_normalisers(model, fit_stats(layout, data.state))
    else:
        stats = fit_stats(layout, data.state)
        model = Perception(data.frames.shape[1:], layout, cfg.model, stats)
    model.to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps, eta_min=cfg.lr / 10)
    gen = torch.Generator(device=device)
    gen.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    _, positions, present = layout.split(data.state)
    tensors = {
        "frames": torch.as_tensor(data.frames),
        "proprio": torch.as_tensor(data.proprio[:, : layout.start]),
        "positions": torch.as_tensor(positions),
        "present": torch.as_tensor(present),
    }
    from tqdm.auto import tqdm

    bar = tqdm(total=cfg.steps, disable=not cfg.progress, unit="step", desc="perception")
    history: list[dict[str, float]] = []
    step, t0 = 0, time.perf_counter()
    out = Path(cfg.out)
    try:
        for step in range(1, cfg.steps + 1):
            idx = torch.as_tensor(rng.integers(len(data.frames), size=cfg.batch_size))
            batch = {k: v[idx].to(device) for k, v in tensors.items()}
            loss, parts = perception_loss(
                model, batch["frames"], batch["proprio"], batch["positions"], batch["present"],
                gen,
            )  # fmt: skip
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if step % 50 == 0 or step == cfg.steps:
                history.append({"step": step, **parts})
                bar.set_postfix_str(f"loss {parts['loss']:.4f}", refresh=False)
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        path = save_model(out, model, cfg, meta, step - 1, history, held_eps)
        print(f"interrupted at step {step - 1}: saved {path}")
        raise
    bar.close()
    path = save_model(out, model, cfg, meta, cfg.steps, history, held_eps)
    print(f"trained in {time.perf_counter() - t0:.0f} s: {path}")
    if not len(held_eps):
        return {}
    held, _ = read_dataset(cfg.data, held_eps)
    results = evaluate(model, held, layout)
    (out / "eval.json").write_text(json.dumps({"heldout_episodes": results}, indent=1))
    print(format_results(results, "held-out episodes"))
    return results


def initial_model(
    cfg: PerceptionTrainConfig,
    frame_shape: tuple[int, ...],
    layout: SlotLayout,
    heldout: np.ndarray,
) -> Perception:
    """The model of ``--init``, checked against the dataset; ``cfg.model`` becomes its
    network settings (the checkpoint records them).

    Raises:
        LcrlError: another frame size, slot layout or set of held-out episodes.
    """
    model, meta = load_model(cfg.init)
    if tuple(model.frame_shape) != tuple(frame_shape):
        raise LcrlError(
            f"--init {cfg.init} reads {tuple(model.frame_shape)} frames; {cfg.data} holds "
            f"{tuple(frame_shape)} frames"
        )
    if model.layout.to_list() != layout.to_list():
        raise LcrlError(
            f"--init {cfg.init} estimates slot layout {model.layout.to_list()}; {cfg.data} "
            f"has {layout.to_list()} (another object set)"
        )
    trained_on = meta.get("train", {}).get("data")
    if trained_on and Path(trained_on).resolve() == Path(cfg.data).resolve():
        before = sorted(int(e) for e in meta.get("heldout_episodes", []))
        if before != sorted(int(e) for e in heldout):
            raise LcrlError(
                f"--init {cfg.init} held out other episodes of {cfg.data}: its held-out "
                "evaluation would read frames it trained on (use its --seed and "
                "--heldout-fraction)"
            )
    # the network is the checkpoint's; holding positions while acting is this command's
    model.cfg = cfg.model = replace(model.cfg, hold_radius=cfg.model.hold_radius)
    return model


def widen_normalisers(model: Perception, stats: dict[str, np.ndarray]) -> None:
    """Widen the position spreads of an ``--init`` model to those of its new training
    data where they are larger (objects lifted in long episodes, never in short ones), and
    to at least :data:`lcrl.perception.MIN_POSITION_STD`: a target a hundred spreads away
    would swamp the loss. The network's outputs for the widened coordinates then mean
    larger moves; the training that follows refits them."""
    wide = np.maximum(stats["pos_std"], MIN_POSITION_STD)
    with torch.no_grad():
        before = model.pos_std.detach().cpu().numpy().copy()
        after = np.maximum(before, wide)
        if (after > before).any():
            model.pos_std.copy_(torch.as_tensor(after, dtype=model.pos_std.dtype))
            print(
                f"--init: position spreads widened in {int((after > before).sum())} of "
                f"{after.size} slot coordinates to fit the new data"
            )


def save_model(
    out: Path,
    model: Perception,
    cfg: PerceptionTrainConfig,
    meta: dict[str, Any],
    step: int,
    history: list[dict[str, float]],
    heldout: np.ndarray,
) -> Path:
    """Write the model checkpoint ``out/model`` (weights, normalisers, layout, camera)."""
    doc = {
        "format": FORMAT,
        "frame_shape": list(model.frame_shape),
        "slot_layout": model.layout.to_list(),
        "env": meta.get("env"),
        "image_size": meta.get("image_size"),
        "model": asdict(cfg.model),
        "train": {**asdict(cfg), "model": None},
        "step": int(step),
        "heldout_episodes": [int(e) for e in heldout],
    }
    path = save_checkpoint(
        out / "model", modules={"perception": model}, meta=doc, json_files={"history": history}
    )
    return path


def find_perception(env: gym.Env) -> PerceptionObservation | None:
    """The :class:`PerceptionObservation` wrapper inside ``env``, if any."""
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, PerceptionObservation):
            return e
        e = e.env
    return None


def evaluate(
    model: Perception,
    data: Frames,
    layout: SlotLayout,
    batch: int = 256,
    hold_radius: float | None = None,
) -> dict[str, Any]:
    """Position error (cm) of present objects per object kind and overall, presence
    accuracy (per object and whole frames), and the fractions of errors within the reach
    margin and push distance; the same for the objects the agent is within
    :data:`NEAR_DISTANCE` of (``near_*``), where a gripper over the table hides them.

    Presence is judged as policies read it: the flags of each episode's first frame (the
    dataset's episodes start at reset) hold for its later frames
    (:class:`PerceptionObservation`); ``*_per_frame`` judges every frame's own flags.

    Positions too are judged as policies read them: those of objects the gripper stays
    away from held from frame to frame (:class:`lcrl.perception.HeldSlots`, the model's
    ``hold_radius`` or the one given); ``position_error_cm_without_hold`` judges every
    frame's own estimate."""
    frames, proprio = data.frames, data.proprio[:, : layout.start]
    estimate = np.concatenate(
        [
            model.observation(frames[s : s + batch], proprio[s : s + batch])
            for s in range(0, len(frames), batch)
        ]
    )
    frame_present = model.presence(estimate)
    episodes = np.asarray(data.episodes)
    starts = np.r_[True, episodes[1:] != episodes[:-1]] if len(episodes) else np.zeros(0, bool)
    first = np.maximum.accumulate(np.where(starts, np.arange(len(episodes)), 0))
    present_hat = frame_present[first]
    # frames whose own flags missed an object the first frame saw: estimate its position
    redo = np.flatnonzero((present_hat & ~frame_present).any(axis=1))
    for s in range(0, len(redo), batch):
        idx = redo[s : s + batch]
        estimate[idx] = model.observation(frames[idx], proprio[idx], present_hat[idx])
    _, pos, present = layout.split(data.state)
    seen = present & present_hat
    _, pos_hat, _ = layout.split(estimate)
    err_alone = np.linalg.norm(pos_hat - pos, axis=-1)[seen]
    radius = model.cfg.hold_radius if hold_radius is None else float(hold_radius)
    held = HeldSlots(layout, radius)
    for i in range(len(estimate) if radius else 0):  # the frames of an episode in order
        if starts[i]:
            held.reset()
        estimate[i] = held(estimate[i : i + 1])[0]
    _, pos_hat, _ = layout.split(estimate)
    err = np.linalg.norm(pos_hat - pos, axis=-1)  # metres
    per_kind = {}
    for k in range(layout.count):
        e = err[seen[:, k], k]
        per_kind[str(k)] = {
            "position_error_cm": float(e.mean() * 100) if e.size else None,
            "frames": int(e.size),
        }
    e = err[seen]
    # where the success thresholds are judged: the agent within NEAR_DISTANCE of an object
    # (in the plane), where a gripper over the table hides what it reaches for
    agent = data.state[:, : layout.position_dims]
    gap = np.linalg.norm(pos[..., :2] - agent[:, None, :2], axis=-1)
    near_object = present & (gap <= NEAR_DISTANCE)
    near = near_object.any(axis=1)
    e_near = err[seen & near_object]  # the objects the agent is near
    frame_ok = (present_hat == present).all(axis=1)
    own_ok = frame_present == present
    return {
        "position_error_cm": float(e.mean() * 100) if e.size else None,
        "position_error_cm_without_hold": float(err_alone.mean() * 100) if e.size else None,
        "hold_radius": radius,
        "position_error_cm_median": float(np.median(e) * 100) if e.size else None,
        "position_error_cm_p90": float(np.percentile(e, 90) * 100) if e.size else None,
        "within_reach_margin": float((e < REACH_MARGIN).mean()) if e.size else None,
        "within_push_distance": float((e < PUSH_DISTANCE).mean()) if e.size else None,
        "presence_accuracy": float((present_hat == present).mean()),
        "frames_all_present_right": float(frame_ok.mean()),
        "presence_accuracy_per_frame": float(own_ok.mean()),
        "frames_all_present_right_per_frame": float(own_ok.all(axis=1).mean()),
        "near_frames": int(near.sum()),
        "near_position_error_cm": float(e_near.mean() * 100) if e_near.size else None,
        "near_within_reach_margin": float((e_near < REACH_MARGIN).mean()) if e_near.size else None,
        "near_frames_all_present_right": float(frame_ok[near].mean()) if near.any() else None,
        "near_frames_all_present_right_per_frame": (
            float(own_ok.all(axis=1)[near].mean()) if near.any() else None
        ),
        "frames": len(data.frames),
        "objects": int(present.sum()),
        "per_kind": per_kind,
    }


def format_results(res: dict[str, Any], name: str) -> str:
    """Two lines for the terminal."""
    if res.get("position_error_cm") is None:
        return f"{name}: no present object was seen"
    return (
        f"{name}: position error {res['position_error_cm']:.2f} cm (median "
        f"{res['position_error_cm_median']:.2f}, 90% {res['position_error_cm_p90']:.2f}"
        + (
            f"; each frame alone {res['position_error_cm_without_hold']:.2f}"
            if res.get("hold_radius")
            else ""
        )
        + "), "
        f"presence accuracy {res['presence_accuracy']:.3f}"
        + (
            f" (each frame's own flags {res['presence_accuracy_per_frame']:.3f})"
            if "presence_accuracy_per_frame" in res
            else ""
        )
        + "\n"
        f"  within 2 cm (reach margin) {res['within_reach_margin']:.2f}, within 5 cm (push "
        f"distance) {res['within_push_distance']:.2f}; {res['frames']} frames, every "
        f"object's presence right in {res['frames_all_present_right']:.2f}" + _near_line(res)
    )


def _near_line(res: dict[str, Any]) -> str:
    """The line on frames with the agent near an object (files before it: none)."""
    if not res.get("near_frames") or res.get("near_position_error_cm") is None:
        return ""
    return (
        f"\n  agent within {NEAR_DISTANCE * 100:.0f} cm of an object ({res['near_frames']} "
        f"frames): that object's position error {res['near_position_error_cm']:.2f} cm, "
        f"within 2 cm "
        f"{res['near_within_reach_margin']:.2f}, every presence right "
        f"{res['near_frames_all_present_right']:.2f}"
    )


@dataclass
class PerceptionEvalCommand:
    """Evaluate a perception model (``lcrl perception eval MODEL``): on its held-out
    episodes, or on another dataset (new layouts)."""

    model: tyro.conf.Positional[str]
    """The folder of ``lcrl perception train --out``."""
    data: str = ""
    """Dataset to evaluate on (default: the training dataset's held-out episodes)."""
    json: str = ""
    """Also write the figures to this JSON file."""
    hold_radius: float | None = None
    """Judge positions held this far from the gripper (:class:`lcrl.perception.HeldSlots`;
    0: every frame alone; default: the model's own ``hold_radius``)."""

    def run(self) -> dict[str, Any]:
        if self.hold_radius is not None and not self.hold_radius >= 0:
            raise LcrlError(f"--hold-radius must be >= 0, got {self.hold_radius}")
        if self.json:  # before the work: a --json that cannot be written fails now
            from train.runtime.run_lock import check_output_file

            check_output_file(self.json, "--json")
        model, meta = load_model(self.model)
        layout = model.layout
        if self.data:
            data, data_meta = read_dataset(self.data)
            if SlotLayout.of(data_meta["slot_layout"]) != layout:
                raise LcrlError(
                    f"{self.data} has the slot layout {data_meta['slot_layout']}; the model "
                    f"reads {layout.to_list()} (another object set?)"
                )
            name = f"{self.data}"
        else:
            data, _ = read_dataset(meta["train"]["data"], np.asarray(meta["heldout_episodes"]))
            name = "held-out episodes"
        results = evaluate(model, data, layout, hold_radius=self.hold_radius)
        print(format_results(results, name))
        if self.json:
            Path(self.json).write_text(json.dumps(results, indent=1))
        return results


class PerceptionObservation(gym.ObservationWrapper):
    """A simulator whose ``observation`` is perception's estimate, not the privileged state.

    Each step, the camera frame and the proprioception (the first ``start`` values) go
    through the frozen perception model, and the estimate replaces the object slots of
    ``observation``: everything downstream (relative positions, displacements, the policy,
    the replay buffer) reads what the camera shows. The estimate is computed once per
    frame and stored, so an update costs what a privileged-state update costs. Rewards and
    relabelling still judge the privileged scene (``env.unwrapped.scene()``), as the rule
    captioner does in training; acting never needs it. The true state stays beside the
    estimate as ``privileged``, for a critic that reads it in training
    (``--agent.privileged-critic``); a policy never reads it.

    Args:
        env: a tabletop made with camera frames (``image=True``), not yet wrapped by
            :class:`envs.features.SlotFeatures`.
        model: the perception model (or the folder it was trained into).
        hold_radius: object permanence (:class:`lcrl.perception.HeldSlots`) in the env's
            units; ``None``: the model's own ``hold_radius``.

    Raises:
        LcrlError: the env gives no frames, frames of another size, or another slot
            layout than the model reads.
    """

    def __init__(
        self, env: gym.Env, model: Perception | str | Path, hold_radius: float | None = None
    ) -> None:
        super().__init__(env)
        if not isinstance(model, Perception):
            model = load_model(model)[0]
        self.model = model
        base = env.unwrapped
        space = env.observation_space
        if not isinstance(space, gym.spaces.Dict) or "image" not in space.spaces:
            raise LcrlError("perception reads camera frames: the env gives no 'image'")
        frame = tuple(space["image"].shape)
        if frame != model.frame_shape:
            raise LcrlError(
                f"the env's camera frames are {frame}; the perception model reads "
                f"{model.frame_shape} (set --env.image-size {model.frame_shape[0]})"
            )
        layout = [*map(int, base.slot_layout), int(base.position_dims)]
        if layout != model.layout.to_list():
            raise LcrlError(
                f"the env's object slots are {layout}; the perception model reads "
                f"{model.layout.to_list()} (trained on another object set or simulator)"
            )
        box = space["observation"]
        if box.shape != (model.layout.dim,):
            raise LcrlError(
                f"the env's observation has shape {box.shape}; the perception model "
                f"assembles ({model.layout.dim},)"
            )
        self.observation_space = gym.spaces.Dict({**space.spaces, "privileged": box})
        self._present: np.ndarray | None = None
        self.held = model.held_slots(hold_radius)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        """Reset; the first frame's presence flags then hold for the episode, and the
        positions of objects the gripper stays away from (:class:`HeldSlots`)."""
        self._present = None
        self.held.reset()
        return super().reset(**kwargs)

    def observation(self, observation: Mapping[str, Any]) -> dict[str, Any]:
        """The observation with perception's estimate of the object slots."""
        out = dict(observation)
        start = self.model.layout.start
        state = np.asarray(observation["observation"], np.float32)
        present = self._present
        estimate = self.model.observation(
            observation["image"][None],
            state[None, :start],
            None if present is None else present[None],
        )[0]
        if present is None:
            self._present = self.model.presence(estimate)
        estimate = self.held(estimate[None])[0]
        out["observation"] = estimate.astype(np.float32)
        out["privileged"] = state
        return out

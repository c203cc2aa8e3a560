"""Caption datasets on the registered simulators, with episodes acted by a trained policy
(``lcrl caption collect``, ``lcrl perception collect``).

:func:`captioner.dataset.collect` writes random and scripted episodes on the simulator it
is given; this layer gives it one from :data:`train.environments.simulators.ENVS`
(:func:`caption_simulator`: any simulator registered with instruction families and a
scene reader collects). Episodes of the ``policy`` source need a trained policy, which
lives here too: this module loads the checkpoint, acts its episodes and hands them to the
collector.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from captioner.dataset import (
    CaptionDatasetWriter,
    CaptionSimulator,
    CollectConfig,
    collect as collect_dataset,
)
from captioner.rule import RuleCaptioner
from lcrl.errors import LcrlError
from train.environments.simulators import ENVS, EnvConfig, canonical_kind
from train.environments.tasks import find_language_wrapper
from train.evaluation.evaluate import LoadedPolicy
from train.policies.loading import load_policy


class PolicyEpisodes:
    """Acts caption-dataset episodes with a trained privileged-state policy, rendering
    the camera frames the learned captioner reads.

    Args:
        cfg: the collection config (``policy`` is the checkpoint or run folder).
        families: the families every frame is labelled with (the dataset's); empty:
            those the policy was trained on.

    Raises:
        LcrlError: the policy was trained on another env, or from images.
    """

    def __init__(self, cfg: CollectConfig, families: tuple[str, ...] = ()) -> None:
        p = load_policy(cfg.policy)
        kind = p.cfg.env.kind
        if kind != canonical_kind(cfg.env) or p.cfg.env.image_obs:
            images = " from images" if p.cfg.env.image_obs else ""
            raise LcrlError(
                f"the policy was trained on {kind!r}{images}; policy episodes need a "
                f"privileged-state {cfg.env!r} policy"
            )
        extra = {**p.cfg.env.extra, "image": True, "image_size": cfg.image_size}
        self.policy: LoadedPolicy = load_policy(cfg.policy, env_overrides={"extra": extra})
        self.checkpoint_name = str(self.policy.checkpoint.path)
        # every frame is labelled with the dataset's families, not only those the policy
        # was trained on: a put teacher's episodes also reach and lift, and a frame left
        # without those labels would teach the captioner a false negative
        wrapper = find_language_wrapper(self.policy.env)
        rule = wrapper.captioner
        self.captioner = RuleCaptioner(families, rule.thresholds) if families else rule

    def episode(self, cfg: CollectConfig, seed: int, writer: CaptionDatasetWriter) -> dict:
        """One episode of the policy from reset seed ``seed``, labelled by the rule
        captioner at every step."""
        env, task, agent = self.policy.env, self.policy.task, self.policy.agent
        obs, _ = env.reset(seed=seed)
        first = obs
        goal = np.asarray([task.goal(obs, env)])
        base = env.unwrapped
        # the agent values lead the observation, unchanged by the slot feature wrappers
        dim = int(base.slot_layout[0])
        wrapper = find_language_wrapper(env)
        s0 = base.scene()
        frames, proprio, scenes = [obs["image"]], [_proprio(obs, dim)], [s0]
        states = [base_observation(obs, env)]
        for _ in range(cfg.max_episode_steps):
            st = {k: v[None] for k, v in task.storage_obs(obs, first).items()}
            a = agent.act(st, goal)[0]
            obs, _, terminated, truncated, _ = env.step(task.scale_action(a))
            frames.append(obs["image"])
            proprio.append(_proprio(obs, dim))
            states.append(base_observation(obs, env))
            scenes.append(base.scene())
            if terminated or truncated:
                break
        labels = [writer.ids([i.text for i in self.captioner.caption(s0, s)]) for s in scenes]
        ids = writer.ids([wrapper.meaning.text])
        return {
            "frames": np.stack(frames),
            "proprio": np.stack(proprio),
            "state": np.stack(states),
            "labels": labels,
            "source": "policy",
            "instruction": ids[0] if ids else -1,
        }


def base_observation(obs: dict[str, Any], env: Any) -> np.ndarray:
    """The simulator's own ``observation`` inside one widened by
    :class:`envs.features.SlotFeatures`: the agent values, then each slot's original
    values (the features come after them in every slot). A policy that acts through
    perception sees estimated slots; the true state beside them (``"privileged"``) is the
    one stored."""
    from envs.features import slot_layout

    vec = np.asarray(obs.get("privileged", obs["observation"]), np.float32)
    start, count, width = env.unwrapped.slot_layout
    _, _, wide, _ = slot_layout(env)
    slots = vec[start : start + count * wide].reshape(count, wide)[:, :width]
    return np.concatenate([vec[:start], slots.reshape(-1)])


def _proprio(obs: dict[str, Any], dim: int) -> np.ndarray:
    return np.asarray(obs["observation"][:dim], np.float32)


def caption_simulator(name: str) -> CaptionSimulator:
    """The simulator of ``--env NAME`` as :func:`captioner.dataset.collect` takes it: a
    kind of :data:`train.environments.simulators.ENVS` (an older kind, or the name its caption
    datasets record, such as ``lang2d``) built with camera frames. Its datasets record
    the entry's ``caption_name`` (else the kind).

    Raises:
        LcrlError: no registered simulator of that name with instruction families and a
            scene reader (what the rule captioner needs).
    """
    kind = canonical_kind(name)
    spec = ENVS.get(kind)
    if spec is None or not spec.families or spec.scene is None:
        usable = tuple(k for k, s in ENVS.items() if s.families and s.scene is not None)
        raise LcrlError(
            f"unknown env {name!r} for caption datasets; choose one of {usable} (lang2d "
            "names tabletop2d)"
        )

    def make(cfg: CollectConfig) -> Any:
        env_cfg = EnvConfig(
            kind=kind,
            image_obs=True,
            image_size=cfg.image_size,
            min_objects=cfg.min_objects,
            max_objects=cfg.max_objects,
        )
        return spec.make(env_cfg)

    return CaptionSimulator(
        name=spec.caption_name or kind,
        make=make,
        families=tuple(spec.families),
        scripted=spec.scripted,
        scene=spec.scene,
    )


def collect(cfg: CollectConfig) -> Path:
    """:func:`captioner.dataset.collect` on the simulator ``cfg.env`` names
    (:func:`caption_simulator`), with the ``policy`` source's episodes acted by
    ``cfg.policy`` when the sources ask for them."""
    simulator = caption_simulator(cfg.env)
    cfg.validate(simulator)
    families = cfg.resolved_families(simulator)
    policy = None
    if "policy" in cfg.sources:
        from train.runtime.machine import apply_threads

        apply_threads(cfg.torch_threads)
        policy = PolicyEpisodes(cfg, families)
    return collect_dataset(cfg, simulator, policy)

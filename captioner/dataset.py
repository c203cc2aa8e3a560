"""Caption datasets: camera episodes with the rule captioner's labels, in one HDF5 file.

A learned captioner reads (first frame, current frame) and writes the instruction that the
change between them achieved; a learned reward model scores (instruction, first frame,
current frame). Both learn from episodes labelled by the rule captioner, which
:func:`collect` gathers on a simulator the caller gives (a :class:`CaptionSimulator`;
``lcrl caption collect`` passes an entry of :data:`train.environments.simulators.ENVS`): random
episodes (held random actions), scripted episodes (the scripted controller following an
instruction feasible in the layout, train or held-out, with action noise) and, given a
checkpoint, policy episodes.

File layout (``format = "lcrl-caption-dataset"``, ``version = 1``)::

    attrs      format, version, meta (JSON: env (the simulator's name, ``lang2d`` for
               the 2D tabletop), families, split seed, image size, sources, collect
               settings; with policy episodes, policy_checkpoint: the checkpoint that
               acted them)
    instructions         (I,) str   canonical instructions: the split's train set first,
                                    then its held-out combinations
    instruction_set      (I,) str   "train" or "heldout" for each instruction
    frames               (N, H, W, 3) uint8  every observation's camera frame
    proprio              (N, P) float32      the robot's own state (pusher or gripper)
    state                (N, S) float32      the privileged observation of each frame (the
                                             env's ``observation``: the robot's state, then
                                             the object slots of ``meta["slot_layout"]``);
                                             what perception learns to read from frames.
                                             Files written before it existed lack it.
    episode_start        (E + 1,) int64      episode e's observations are
                                             [episode_start[e], episode_start[e + 1])
    episode_source       (E,) uint8          index into meta["sources"] (random, scripted,
                                             policy)
    episode_instruction  (E,) int32          the instruction followed (-1: random)
    label_start          (N + 1,) int64      observation j's labels are
    label_ids            (L,) int16          label_ids[label_start[j]:label_start[j + 1]]:
                                             every instruction of the table that the
                                             change from the episode's first scene to
                                             observation j satisfies (the rule captioner)

The labels are complete over the table, so an instruction missing from an observation's
labels is a true negative for the reward model. :class:`CaptionDataset` reads the file
lazily (frames are read per batch, not loaded whole).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from captioner.caption_files import (
    FORMAT as FORMAT,
    SOURCES as SOURCES,
    VERSION as VERSION,
    CaptionDataset as CaptionDataset,
    CaptionDatasetWriter as CaptionDatasetWriter,
    instruction_table as instruction_table,
    iter_pairs as iter_pairs,
    merge as merge,
)
from captioner.grammar import DIRECTION_VECTORS, Instruction
from captioner.rule import RuleCaptioner
from captioner.splits import make_split
from envs.scene import SceneState
from lcrl.errors import LcrlError

__all__ = [
    "FORMAT",
    "SOURCES",
    "VERSION",
    "CaptionDataset",
    "CaptionDatasetWriter",
    "CaptionSimulator",
    "CollectConfig",
    "collect",
    "instruction_table",
    "merge",
]


# --------------------------------------------------------------------------- collection


@dataclass
class CollectConfig:
    """Collect labelled camera episodes into a caption dataset (``lcrl caption collect``)."""

    out: str = "data/captions-lang2d.h5"
    """The HDF5 file to write."""
    env: str = "lang2d"
    """The simulator: a kind of :data:`train.environments.simulators.ENVS` with instructions,
    ``lang2d`` or ``tabletop2d`` (the 2D tabletop, top-down frames) or ``robosuite`` (the
    Panda tabletop's agentview camera)."""
    episodes: int = 200
    """Episodes to collect, shared out over ``sources`` in turn."""
    sources: tuple[str, ...] = ("random", "scripted")
    """Where episodes come from: ``random`` (held random actions), ``scripted`` (the
    scripted controller on an instruction feasible in the layout, from the split's
    training set or its held-out combinations), ``policy`` (the ``policy`` checkpoint)."""
    policy: str = ""
    """Checkpoint or run folder acting the ``policy`` episodes (its env must be ``env``)."""
    families: tuple[str, ...] = ()
    """Instruction families labelled (and followed by scripted episodes); empty: every
    family of the simulator (reach, push and put on the 2D tabletop, all five on
    robosuite)."""
    split_seed: int = 0
    """Seed of the compositional split whose held-out combinations are marked."""
    image_size: int = 64
    """Camera frame side in pixels."""
    min_objects: int = 2
    """Fewest objects on the table."""
    max_objects: int = 3
    """Most objects on the table."""
    max_episode_steps: int = 50
    """Steps per episode at most (scripted episodes stop at success)."""
    random_action_repeat: int = 5
    """Hold each random action for this many steps (held actions travel and push)."""
    scripted_noise: float = 0.3
    """Standard deviation of the Gaussian noise on scripted actions."""
    after_success: int = 0
    """Scripted episodes go on for this many steps of held random actions once their
    instruction is satisfied (0: they end there; ``max_episode_steps`` still bounds
    them). Without them a moved object is nearly always seen with the robot beside it
    (a push ends in contact), and a reward model can read "reached" into any moved
    object."""
    stop_short: float = 0.0
    """Fraction of scripted push episodes that stop short: the push ends at a random 0.3
    to 0.95 of the rule captioner's push distance, and held random actions follow (for
    ``after_success`` steps, at least 10). A policy learning to push leaves many objects
    part of the way; without such episodes a reward model sees few of them and can read a
    push into them."""
    heldout_fraction: float = 0.25
    """Fraction of scripted episodes that follow a held-out combination (so that held-out
    evaluation has examples; training code decides whether to use them)."""
    seed: int = 0
    """Seed of layouts, instructions and actions."""
    overwrite: bool = False
    """Replace an existing file."""
    resume: bool = False
    """Go on with the file at ``out`` that an interrupted collection kept: its episodes
    stay and the ones it lacks are added (no file there: a new one). A file collected with
    other settings is refused, or replaced when ``overwrite`` is given too."""
    progress: bool = True
    """Show a progress bar."""
    torch_threads: int = 0
    """Torch threads of the policy that acts the ``policy`` episodes (0: this machine's
    share, fewer where other processes keep cores busy)."""

    def validate(self, simulator: CaptionSimulator | None = None) -> None:
        """Raise :class:`LcrlError` for bad settings (with ``simulator``: also families
        outside its own, and scripted episodes on a simulator without a controller)."""
        bad = [s for s in self.sources if s not in SOURCES]
        if bad or not self.sources:
            raise LcrlError(f"sources must be among {SOURCES}, got {self.sources}")
        if "policy" in self.sources and not self.policy:
            raise LcrlError("policy episodes need --policy CHECKPOINT")
        if simulator is not None:
            allowed = simulator.families
            bad = [f for f in self.families if f not in allowed]
            if bad:
                raise LcrlError(f"the {self.env} env supports the families {allowed}, not {bad}")
            if "scripted" in self.sources and simulator.scripted is None:
                raise LcrlError(
                    f"the {self.env} env has no scripted controller: collect with --sources "
                    "random (or policy)"
                )
        for name in ("episodes", "max_episode_steps", "random_action_repeat"):
            if getattr(self, name) <= 0:
                raise LcrlError(f"{name} must be positive, got {getattr(self, name)}")
        if self.after_success < 0:
            raise LcrlError(f"after_success must be >= 0, got {self.after_success}")
        for name in ("heldout_fraction", "stop_short"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise LcrlError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.scripted_noise < 0:
            raise LcrlError("scripted_noise must be >= 0")
        if self.min_objects > self.max_objects:
            raise LcrlError("min_objects is larger than max_objects")

    def resolved_families(self, simulator: CaptionSimulator) -> tuple[str, ...]:
        """The families to label: :attr:`families`, or all of the simulator's."""
        if self.families:
            return tuple(self.families)
        return tuple(simulator.families)


def _scene(env: Any) -> SceneState:
    return env.unwrapped.scene()


@dataclass(frozen=True)
class CaptionSimulator:
    """The simulator a caption dataset is collected on, given by the caller of
    :func:`collect` (``lcrl caption collect`` builds it from an entry of
    :data:`train.environments.simulators.ENVS`, so any simulator registered there with instruction
    families and a scene reader can collect).

    Attributes:
        name: recorded as the dataset's ``meta["env"]`` (``lang2d`` for the 2D tabletop,
            as files have always said).
        make: ``cfg -> env``: the simulator with camera frames of ``cfg.image_size``
            (``image`` in its observation) and ``cfg.min_objects`` to
            ``cfg.max_objects`` objects, without a time limit. Its unwrapped env has
            ``slot_layout = (start, count, width)`` (the first ``start`` values of
            ``observation`` are the robot's own state) and ``position_dims``.
        families: the instruction families of its rule captioner (the split's).
        scripted: ``() -> controller`` with ``act(meaning, s0, scene)`` (and optionally
            ``reset()``), for scripted episodes; None: it has none.
        scene: ``env -> SceneState``: the privileged scene the rule captioner reads
            (default: ``env.unwrapped.scene()``).
    """

    name: str
    make: Callable[[CollectConfig], Any]
    families: tuple[str, ...]
    scripted: Callable[[], Any] | None = None
    scene: Callable[[Any], SceneState] = _scene


class _Source:
    """One simulator with camera frames, its scripted controller and the rule captioner."""

    def __init__(
        self, cfg: CollectConfig, simulator: CaptionSimulator, families: tuple[str, ...]
    ) -> None:
        self.env: Any = simulator.make(cfg)
        self.controller: Any = simulator.scripted() if simulator.scripted else None
        self._scene = simulator.scene
        base = self.env.unwrapped
        self.slot_layout = tuple(int(v) for v in base.slot_layout)
        self.position_dims = int(base.position_dims)
        self.proprio_dim = self.slot_layout[0]
        self.captioner = RuleCaptioner(families)

    def scene(self) -> SceneState:
        """The privileged scene now."""
        return self._scene(self.env)

    def close(self) -> None:
        self.env.close()


def _proprio(obs: dict[str, Any], dim: int) -> np.ndarray:
    return np.asarray(obs["observation"][:dim], np.float32)


def _choose(
    captioner: RuleCaptioner,
    table: Sequence[Instruction],
    sets: Sequence[str],
    s0: SceneState,
    want: str,
    rng: np.random.Generator,
) -> int | None:
    """A feasible instruction of set ``want`` (family first, uniformly), or None."""
    ok = [i for i, m in enumerate(table) if sets[i] == want and captioner.feasible(m, s0)]
    if not ok:
        return None
    families = sorted({table[i].family for i in ok})
    fam = families[int(rng.integers(len(families)))]
    ok = [i for i in ok if table[i].family == fam]
    return ok[int(rng.integers(len(ok)))]


class EpisodeSource(Protocol):
    """Something that acts whole labelled episodes (a trained policy: see
    :class:`train.commands.captions.PolicyEpisodes`)."""

    #: The checkpoint that acts (a resumed collection must be acted by the same one).
    checkpoint_name: str

    def episode(self, cfg: CollectConfig, seed: int, writer: CaptionDatasetWriter) -> dict:
        """One episode from reset seed ``seed``: ``frames``, ``proprio``, ``labels`` (ids
        of ``writer``), ``source`` and ``instruction`` (an id, or -1)."""
        ...


def collect(
    cfg: CollectConfig, simulator: CaptionSimulator, policy: EpisodeSource | None = None
) -> Path:
    """Collect ``cfg.episodes`` labelled episodes into ``cfg.out``; returns the path.

    Args:
        cfg: what to collect.
        simulator: where (``lcrl caption collect`` passes the entry of
            :data:`train.environments.simulators.ENVS` that ``cfg.env`` names:
            :func:`train.commands.captions.collect`).
        policy: acts the ``policy`` episodes (``lcrl caption collect`` loads
            ``cfg.policy`` with :func:`train.commands.captions.collect`).

    Ctrl-C stops collecting and keeps the episodes finished so far (the file is
    completed before the interrupt is raised again).
    """
    cfg.validate(simulator)
    if "policy" in cfg.sources and policy is None:
        raise LcrlError(
            "policy episodes need a trained policy to act them: collect them with "
            "lcrl caption collect --policy CHECKPOINT (train.commands.captions.collect)"
        )
    from tqdm import tqdm

    from captioner.grammar import parse

    families = cfg.resolved_families(simulator)
    split = make_split(cfg.split_seed, simulator.families)
    texts, sets = instruction_table(split)
    keep = [i for i, t in enumerate(texts) if t.split()[0] in families]
    texts = [texts[i] for i in keep]
    sets = [sets[i] for i in keep]
    table = [parse(t) for t in texts]
    src = _Source(cfg, simulator, families)
    rng = np.random.default_rng(cfg.seed)
    meta = {
        "env": simulator.name,
        "families": list(families),
        "split_seed": cfg.split_seed,
        "split_fingerprint": split.fingerprint(),
        "image_size": cfg.image_size,
        "sources": list(SOURCES),
        "collect": asdict(cfg),
        # where the object slots are in each stored state (what perception predicts)
        "slot_layout": [*src.slot_layout, src.position_dims],
    }
    if policy is not None:  # which weights acted: a later checkpoint is another dataset
        meta["policy_checkpoint"] = policy.checkpoint_name
    resume = cfg.resume and Path(cfg.out).exists()
    if resume:
        problem = resume_problem(cfg.out, meta)
        if problem and not cfg.overwrite:
            raise LcrlError(
                f"--resume: {cfg.out} {problem}; pass --overwrite as well to collect it anew"
            )
        resume = not problem
    first = src.env.reset(seed=cfg.seed)[0]
    writer = CaptionDatasetWriter(
        cfg.out,
        texts,
        sets,
        first["image"].shape,
        src.proprio_dim,
        meta,
        overwrite=cfg.overwrite,
        state_dim=int(np.shape(first["observation"])[0]),
        resume=resume,
    )
    start = writer.episodes
    if start:  # the rest of an interrupted collection (its own stream of random draws)
        rng = np.random.default_rng([cfg.seed, start])
        print(f"resumed {cfg.out}: {start} episodes kept, {max(cfg.episodes - start, 0)} to add")
    bar = tqdm(
        total=cfg.episodes, initial=min(start, cfg.episodes), disable=not cfg.progress,
        desc="collect", unit="ep",
    )  # fmt: skip
    try:
        for e in range(start, cfg.episodes):
            kind = cfg.sources[e % len(cfg.sources)]
            seed = int(cfg.seed * 1_000_003 + e)
            if kind == "policy":
                ep = policy.episode(cfg, seed, writer)
            else:
                ep, _ = _episode(src, kind, cfg, seed, rng, table, sets, writer)
            writer.add_episode(**ep)
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        src.close()
        if writer.episodes:
            path = writer.close()
            print(f"interrupted: kept {writer.episodes} episodes in {path}")
        else:
            writer.discard()
        raise
    bar.close()
    src.close()
    return writer.close()


#: Collection settings a resumed collection may change (the rest must be the file's).
RESUMABLE = ("episodes", "overwrite", "resume", "progress", "out", "torch_threads")


def resume_problem(path: str | Path, meta: dict[str, Any]) -> str:
    """Why the dataset at ``path`` cannot be resumed by a collection of ``meta``, or ""."""
    with CaptionDataset(path) as old:
        found = old.meta

    def settings(m: dict[str, Any]) -> dict[str, Any]:
        flat = {k: v for k, v in m.items() if k != "collect"}
        flat.update(
            (f"collect.{k}", v) for k, v in m.get("collect", {}).items() if k not in RESUMABLE
        )
        return json.loads(json.dumps(flat))  # tuples and lists alike

    a, b = settings(found), settings(meta)
    differ = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
    return f"was collected with other settings ({', '.join(differ)})" if differ else ""


def _episode(
    src: _Source,
    kind: str,
    cfg: CollectConfig,
    seed: int,
    rng: np.random.Generator,
    table: Sequence[Instruction],
    sets: Sequence[str],
    writer: CaptionDatasetWriter,
) -> tuple[dict[str, Any], list[SceneState]]:
    """One random or scripted episode and the scenes it went through."""
    env = src.env
    obs, _ = env.reset(seed=seed)
    s0 = src.scene()
    target = -1
    if kind == "scripted":
        want = "heldout" if rng.random() < cfg.heldout_fraction else "train"
        for _ in range(20):
            choice = _choose(src.captioner, table, sets, s0, want, rng)
            if choice is not None:
                break
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
            s0 = src.scene()
        if choice is None:
            raise LcrlError(f"no {want} instruction is feasible in 20 layouts")
        target = choice
        reset = getattr(src.controller, "reset", None)
        if reset is not None:
            reset()
    short = _short_push(src, kind, cfg, rng, table, target, s0)
    frames = [obs["image"]]
    proprio = [_proprio(obs, src.proprio_dim)]
    states = [np.asarray(obs["observation"], np.float32)]
    scenes = [s0]
    low, high = env.action_space.low, env.action_space.high
    action = None
    done_at = -1  # the step a scripted episode's instruction was satisfied at
    for t in range(cfg.max_episode_steps):
        if kind == "random" or done_at >= 0:  # held random actions (after success too)
            if (t - max(done_at, 0)) % cfg.random_action_repeat == 0:
                action = rng.uniform(low, high).astype(np.float32)
        else:
            a = src.controller.act(table[target], s0, scenes[-1])
            a = a + rng.normal(0.0, cfg.scripted_noise, a.shape)
            action = np.clip(a, low, high).astype(np.float32)
        obs, _, terminated, truncated, info = env.step(action)
        frames.append(obs["image"])
        proprio.append(_proprio(obs, src.proprio_dim))
        states.append(np.asarray(obs["observation"], np.float32))
        scenes.append(src.scene())
        if done_at >= 0:
            if t + 1 - done_at >= max(cfg.after_success, 10 if short else 0):
                break
        elif short is not None and _along(short, s0, scenes[-1]) >= short[2]:
            done_at = t + 1  # stopped short: held random actions from here
        elif kind == "scripted" and src.captioner.satisfied(table[target], s0, scenes[-1]):
            if cfg.after_success <= 0:
                break
            done_at = t + 1
        if terminated or truncated or info.get("sim_error"):
            break
    labels = [writer.ids([i.text for i in src.captioner.caption(s0, s)]) for s in scenes]
    episode = {
        "frames": np.stack(frames),
        "proprio": np.stack(proprio),
        "state": np.stack(states),
        "labels": labels,
        "source": kind,
        "instruction": target,
    }
    return episode, scenes


def _short_push(
    src: _Source,
    kind: str,
    cfg: CollectConfig,
    rng: np.random.Generator,
    table: Sequence[Instruction],
    target: int,
    s0: SceneState,
) -> tuple[int, np.ndarray, float] | None:
    """For a scripted push episode drawn to stop short (``stop_short``): the pushed
    object's index, its direction and the distance to stop at (None: a whole episode)."""
    if kind != "scripted" or cfg.stop_short <= 0 or table[target].family != "push":
        return None
    if rng.random() >= cfg.stop_short:
        return None
    ins = table[target]
    vec = np.asarray(DIRECTION_VECTORS[ins.direction], np.float64)
    stop = float(rng.uniform(0.3, 0.95)) * src.captioner.thresholds.push_distance
    return s0.index(*ins.obj), vec, stop


def _along(short: tuple[int, np.ndarray, float], s0: SceneState, s: SceneState) -> float:
    """How far the short push's object has moved along its direction."""
    k, vec, _ = short
    return float((s.positions[k, :2] - s0.positions[k, :2]) @ vec)

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
               settings)
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
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from captioner.grammar import DIRECTION_VECTORS, Instruction
from captioner.rule import RuleCaptioner
from captioner.splits import Split, make_split
from envs.scene import SceneState
from lcrl.errors import LcrlError

FORMAT = "lcrl-caption-dataset"
VERSION = 1
SOURCES: tuple[str, ...] = ("random", "scripted", "policy")

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


def _h5py() -> Any:
    try:
        import h5py
    except ImportError:  # pragma: no cover - h5py is a dependency
        raise LcrlError("caption datasets need h5py: pip install h5py") from None
    return h5py


def instruction_table(split: Split) -> tuple[list[str], list[str]]:
    """The canonical instructions of a split (train set first, then held-out
    combinations) and the set each belongs to."""
    train = list(split.texts("train"))
    heldout = [t for t in split.texts("heldout") if t not in set(train)]
    return train + heldout, ["train"] * len(train) + ["heldout"] * len(heldout)


class CaptionDatasetWriter:
    """Appends labelled episodes to a new HDF5 caption dataset.

    The file is written under a temporary name and moved into place by :meth:`close`, so
    a finished file is always complete; episodes are flushed as they come, and closing
    after an interruption keeps every episode written so far.

    Args:
        path: the dataset file to create.
        instructions: the instruction table (canonical texts).
        instruction_set: ``"train"`` or ``"heldout"`` per instruction.
        frame_shape: ``(H, W, 3)`` of the camera frames.
        proprio_dim: width of the proprioception vector.
        meta: JSON-able description (env, families, settings).
        state_dim: width of the privileged observation stored per frame (0: none).
        overwrite: replace an existing file instead of refusing.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        instructions: Sequence[str],
        instruction_set: Sequence[str],
        frame_shape: Sequence[int],
        proprio_dim: int,
        meta: dict[str, Any],
        overwrite: bool = False,
        state_dim: int = 0,
    ) -> None:
        h5py = _h5py()
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise LcrlError(f"{self.path} exists; pass --overwrite to replace it")
        if len(instructions) != len(instruction_set):
            raise LcrlError("instructions and instruction_set differ in length")
        if len(instructions) >= 2**15:
            raise LcrlError(f"at most {2**15 - 1} instructions, got {len(instructions)}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".part")
        self._ids = {t: i for i, t in enumerate(instructions)}
        self.num_instructions = len(instructions)
        f = self._file = h5py.File(self._tmp, "w")
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        f.attrs["meta"] = json.dumps(meta)
        text = h5py.string_dtype("utf-8")
        f.create_dataset("instructions", data=np.asarray(instructions, dtype=object), dtype=text)
        f.create_dataset(
            "instruction_set", data=np.asarray(instruction_set, dtype=object), dtype=text
        )
        h, w, c = (int(v) for v in frame_shape)
        f.create_dataset(
            "frames",
            (0, h, w, c),
            np.uint8,
            maxshape=(None, h, w, c),
            chunks=(1, h, w, c),
            compression="lzf",
        )
        f.create_dataset("proprio", (0, proprio_dim), np.float32, maxshape=(None, proprio_dim))
        self.state_dim = int(state_dim)
        if self.state_dim:
            f.create_dataset(
                "state", (0, self.state_dim), np.float32, maxshape=(None, self.state_dim)
            )
        f.create_dataset("episode_start", data=np.zeros(1, np.int64), maxshape=(None,))
        f.create_dataset("episode_source", (0,), np.uint8, maxshape=(None,))
        f.create_dataset("episode_instruction", (0,), np.int32, maxshape=(None,))
        f.create_dataset("label_start", data=np.zeros(1, np.int64), maxshape=(None,))
        f.create_dataset("label_ids", (0,), np.int16, maxshape=(None,), chunks=(4096,))
        self.episodes = 0
        self.observations = 0

    def ids(self, texts: Sequence[str]) -> list[int]:
        """Table ids of canonical instructions (texts outside the table are dropped)."""
        return sorted({self._ids[t] for t in texts if t in self._ids})

    def add_episode(
        self,
        frames: np.ndarray,
        proprio: np.ndarray,
        labels: Sequence[Sequence[int]],
        source: str,
        instruction: int = -1,
        state: np.ndarray | None = None,
    ) -> None:
        """Append one episode: ``T + 1`` frames, proprioception rows and label-id lists
        (and privileged observations, when the file stores them)."""
        if source not in SOURCES:
            raise LcrlError(f"unknown episode source {source!r}; choose one of {SOURCES}")
        n = len(frames)
        if n < 1 or len(proprio) != n or len(labels) != n:
            raise LcrlError(
                f"an episode needs as many frames ({n}), proprio rows ({len(proprio)}) and "
                f"label lists ({len(labels)}), at least one"
            )
        if self.state_dim and (state is None or np.shape(state) != (n, self.state_dim)):
            raise LcrlError(
                f"this dataset stores privileged observations: give state of shape "
                f"({n}, {self.state_dim}), got {None if state is None else np.shape(state)}"
            )
        if not -1 <= instruction < self.num_instructions:
            raise LcrlError(f"instruction id {instruction} is outside the table")
        flat = np.asarray([i for lab in labels for i in lab], np.int64)
        if flat.size and (flat.min() < 0 or flat.max() >= self.num_instructions):
            raise LcrlError(f"label ids must be in [0, {self.num_instructions})")
        f = self._file

        def grow(name: str, values: np.ndarray) -> None:
            ds = f[name]
            start = ds.shape[0]
            ds.resize(start + len(values), axis=0)
            ds[start:] = values

        lab_start = f["label_start"][-1] + np.cumsum([len(lab) for lab in labels])
        grow("frames", np.asarray(frames, np.uint8))
        grow("proprio", np.asarray(proprio, np.float32))
        if self.state_dim:
            grow("state", np.asarray(state, np.float32))
        grow("label_ids", flat.astype(np.int16))
        grow("label_start", lab_start.astype(np.int64))
        grow("episode_start", np.asarray([self.observations + n], np.int64))
        grow("episode_source", np.asarray([SOURCES.index(source)], np.uint8))
        grow("episode_instruction", np.asarray([instruction], np.int32))
        f.flush()
        self.episodes += 1
        self.observations += n

    def discard(self) -> None:
        """Close and delete the unfinished file."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._tmp.unlink(missing_ok=True)

    def close(self) -> Path:
        """Finish the file and move it into place; returns its path."""
        if self._file is None:
            return self.path
        self._file.close()
        self._file = None
        if self.episodes == 0:
            self._tmp.unlink(missing_ok=True)
            raise LcrlError("no episode was collected: nothing written")
        os.replace(self._tmp, self.path)
        return self.path


class CaptionDataset:
    """Read a caption dataset written by :class:`CaptionDatasetWriter`.

    Args:
        path: the HDF5 file.

    Raises:
        LcrlError: the file is missing or is not a caption dataset of a known version.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        h5py = _h5py()
        self.path = Path(path)
        if not self.path.is_file():
            raise LcrlError(f"no caption dataset at {self.path}")
        try:
            f = h5py.File(self.path, "r")
        except OSError as e:
            raise LcrlError(f"{self.path} is not an HDF5 file ({e})") from None
        if f.attrs.get("format") != FORMAT:
            f.close()
            raise LcrlError(f"{self.path} is not an lcrl caption dataset (no format {FORMAT!r})")
        if int(f.attrs.get("version", -1)) != VERSION:
            version = f.attrs.get("version")
            f.close()
            raise LcrlError(f"{self.path} has format version {version}; this lcrl reads {VERSION}")
        self._file = f
        self.meta: dict[str, Any] = json.loads(f.attrs["meta"])
        self.instructions: list[str] = [s.decode() for s in f["instructions"][:]]
        self.instruction_set: list[str] = [s.decode() for s in f["instruction_set"][:]]
        self.episode_start = f["episode_start"][:]
        self.episode_source = f["episode_source"][:]
        self.episode_instruction = f["episode_instruction"][:]
        self.label_start = f["label_start"][:]
        self.label_ids = f["label_ids"][:]
        self.frames = f["frames"]
        self.proprio = f["proprio"][:]
        #: The privileged observation of every frame (None in files without it).
        self.state = f["state"][:] if "state" in f else None

    def __enter__(self) -> CaptionDataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        if self._file is not None:
            self._file.close()
            self._file = None

    @property
    def num_episodes(self) -> int:
        return len(self.episode_start) - 1

    @property
    def num_observations(self) -> int:
        return int(self.episode_start[-1])

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self.frames.shape[1:])

    def labels(self, j: int) -> np.ndarray:
        """Instruction ids that observation ``j`` satisfies (relative to its episode's
        first observation)."""
        return self.label_ids[self.label_start[j] : self.label_start[j + 1]]

    def episode_of(self, j: np.ndarray | int) -> np.ndarray:
        """Episode index of observation(s) ``j``."""
        return np.searchsorted(self.episode_start, j, side="right") - 1

    def first_of(self, j: np.ndarray | int) -> np.ndarray:
        """Index of the first observation of ``j``'s episode."""
        return self.episode_start[self.episode_of(j)]

    def read_frames(self, idx: np.ndarray) -> np.ndarray:
        """Frames at the observation indices ``idx`` (any order, repeats allowed)."""
        idx = np.asarray(idx, np.int64)
        order = np.unique(idx)
        block = self.frames[order]  # h5py reads increasing unique indices
        return block[np.searchsorted(order, idx)]

    def episode(self, e: int) -> dict[str, Any]:
        """Episode ``e``: frames, proprio, labels (lists of ids), source, instruction and
        state (None in files without it): the arguments of
        :meth:`CaptionDatasetWriter.add_episode`."""
        if not 0 <= e < self.num_episodes:
            raise LcrlError(f"episode {e} is outside [0, {self.num_episodes})")
        a, b = int(self.episode_start[e]), int(self.episode_start[e + 1])
        return {
            "frames": self.frames[a:b],
            "proprio": self.proprio[a:b],
            "labels": [self.labels(j).tolist() for j in range(a, b)],
            "source": SOURCES[int(self.episode_source[e])],
            "instruction": int(self.episode_instruction[e]),
            "state": None if self.state is None else self.state[a:b],
        }

    def counts(self) -> dict[str, Any]:
        """Episodes per source, labelled observations, labels per family and set."""
        per_source = {s: int(np.sum(self.episode_source == i)) for i, s in enumerate(SOURCES)}
        fam = np.asarray([t.split()[0] for t in self.instructions])
        sets = np.asarray(self.instruction_set)
        per_family: dict[str, dict[str, int]] = {}
        for f in sorted(set(fam.tolist())):
            for s in ("train", "heldout"):
                n = int(np.isin(self.label_ids, np.flatnonzero((fam == f) & (sets == s))).sum())
                per_family.setdefault(f, {})[s] = n
        labelled = int(np.sum(np.diff(self.label_start) > 0))
        return {
            "episodes": self.num_episodes,
            "observations": self.num_observations,
            "labelled_observations": labelled,
            "episodes_per_source": per_source,
            "labels_per_family": per_family,
        }

    def summary(self) -> str:
        """A few lines for the terminal."""
        c = self.counts()
        src = ", ".join(f"{k} {v}" for k, v in c["episodes_per_source"].items() if v)
        fams = "; ".join(
            f"{f}: {v['train']} seen / {v['heldout']} held-out"
            for f, v in c["labels_per_family"].items()
        )
        return (
            f"{self.path}: {c['episodes']} episodes ({src}), {c['observations']} frames "
            f"{'x'.join(map(str, self.frame_shape))}, {c['labelled_observations']} with labels\n"
            f"labels per family: {fams}"
        )


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
    progress: bool = True
    """Show a progress bar."""

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
    )
    bar = tqdm(total=cfg.episodes, disable=not cfg.progress, desc="collect", unit="ep")
    try:
        for e in range(cfg.episodes):
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


def iter_pairs(
    data: CaptionDataset, episodes: np.ndarray | None = None
) -> Iterator[tuple[int, int, np.ndarray]]:
    """``(first observation, observation, labels)`` of every labelled observation (of the
    given episodes)."""
    eps = range(data.num_episodes) if episodes is None else episodes
    for e in eps:
        a, b = int(data.episode_start[e]), int(data.episode_start[e + 1])
        for j in range(a, b):
            lab = data.labels(j)
            if lab.size:
                yield a, j, lab


#: Meta entries that must agree for caption datasets to be merged.
_MERGE_KEYS = ("env", "families", "split_seed", "split_fingerprint", "image_size", "slot_layout")


def merge(
    paths: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Concatenate caption datasets of one simulator and instruction split into one file
    (``lcrl caption merge``): episodes collected apart (say, more policy episodes from a
    later policy) then train the models together. Returns the new file's path.

    The files must share the instruction table, frame shape, proprioception and privileged
    widths and the simulator settings of :data:`_MERGE_KEYS`; the first file's meta is
    kept, with ``merged`` listing each input and its collect settings. Ctrl-C discards the
    unfinished file (the inputs are never changed).
    """
    from tqdm import tqdm

    if len(paths) < 2:
        raise LcrlError(f"merge needs at least two caption datasets, got {len(paths)}")
    resolved = [Path(p).resolve() for p in paths]
    if len(set(resolved)) < len(resolved):
        raise LcrlError("a caption dataset is named twice: its episodes would be duplicated")
    if Path(out).resolve() in resolved:
        raise LcrlError(f"--out {out} is one of the inputs: write the merge to a new file")
    datasets = [CaptionDataset(p) for p in paths]
    try:
        first = datasets[0]
        for d in datasets[1:]:
            _check_mergeable(first, d)
        meta = dict(first.meta)
        meta["merged"] = [
            {"path": str(d.path), "episodes": d.num_episodes, "collect": d.meta.get("collect")}
            for d in datasets
        ]
        state_dim = 0 if first.state is None else int(first.state.shape[1])
        writer = CaptionDatasetWriter(
            out,
            first.instructions,
            first.instruction_set,
            first.frame_shape,
            int(first.proprio.shape[1]),
            meta,
            overwrite=overwrite,
            state_dim=state_dim,
        )
        total = sum(d.num_episodes for d in datasets)
        with tqdm(total=total, disable=not progress, desc="merge", unit="ep") as bar:
            try:
                for d in datasets:
                    for e in range(d.num_episodes):
                        writer.add_episode(**d.episode(e))
                        bar.update(1)
            except BaseException:
                writer.discard()
                raise
        return writer.close()
    finally:
        for d in datasets:
            d.close()


def _check_mergeable(a: CaptionDataset, b: CaptionDataset) -> None:
    """Refuse to merge datasets of different simulators, splits, cameras or widths."""
    if a.instructions != b.instructions or a.instruction_set != b.instruction_set:
        raise LcrlError(
            f"{a.path} and {b.path} have different instruction tables "
            f"({len(a.instructions)} and {len(b.instructions)} instructions): collect both "
            "with the same env, --families and --split-seed"
        )
    for key in _MERGE_KEYS:
        if a.meta.get(key) != b.meta.get(key):
            raise LcrlError(
                f"{a.path} has {key} {a.meta.get(key)!r}, {b.path} has {b.meta.get(key)!r}: "
                "only datasets of one simulator and split merge"
            )
    if tuple(a.frame_shape) != tuple(b.frame_shape):
        raise LcrlError(
            f"{a.path} has {'x'.join(map(str, a.frame_shape))} frames, {b.path} has "
            f"{'x'.join(map(str, b.frame_shape))}"
        )
    widths = [
        (
            int(d.proprio.shape[1]),
            None if d.state is None else int(d.state.shape[1]),
        )
        for d in (a, b)
    ]
    if widths[0] != widths[1]:
        raise LcrlError(
            f"{a.path} stores (proprioception, privileged) widths {widths[0]}, {b.path} "
            f"stores {widths[1]}"
        )

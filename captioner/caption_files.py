"""Caption dataset files (HDF5): the writer, the reader, observation pairs and merging files."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from captioner.splits import Split
from lcrl.errors import LcrlError

FORMAT = "lcrl-caption-dataset"


VERSION = 1


SOURCES: tuple[str, ...] = ("random", "scripted", "policy")


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
        resume: go on with the finished file at ``path`` (one an interrupted collection
            kept): its episodes are kept and new ones follow them. Its instruction table,
            frame, proprioception and state widths must be those given; ``meta``
            replaces its own.
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
        resume: bool = False,
    ) -> None:
        h5py = _h5py()
        self.path = Path(path)
        if resume:
            self._resume(instructions, instruction_set, frame_shape, proprio_dim, meta, state_dim)
            return
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

    def _resume(
        self,
        instructions: Sequence[str],
        instruction_set: Sequence[str],
        frame_shape: Sequence[int],
        proprio_dim: int,
        meta: dict[str, Any],
        state_dim: int,
    ) -> None:
        """Open a copy of the file at ``self.path`` to append to (the file itself stays
        as it is until :meth:`close` moves the copy into place)."""
        with CaptionDataset(self.path) as old:
            found = {
                "instruction table": (old.instructions, old.instruction_set),
                "frame shape": old.frame_shape,
                "proprioception width": old.proprio.shape[1],
                "state width": 0 if old.state is None else old.state.shape[1],
            }
            episodes, observations = old.num_episodes, old.num_observations
        wanted = {
            "instruction table": (list(instructions), list(instruction_set)),
            "frame shape": tuple(int(v) for v in frame_shape),
            "proprioception width": int(proprio_dim),
            "state width": int(state_dim),
        }
        for what, value in wanted.items():
            if found[what] != value:
                raise LcrlError(
                    f"{self.path} has another {what} ({found[what]}) than this collection's "
                    f"({value}): it cannot be resumed"
                )
        self._tmp = self.path.with_name(self.path.name + ".part")
        self._ids = {t: i for i, t in enumerate(instructions)}
        self.num_instructions = len(instructions)
        self.state_dim = int(state_dim)
        shutil.copyfile(self.path, self._tmp)
        self._file = _h5py().File(self._tmp, "a")
        self._file.attrs["meta"] = json.dumps(meta)
        self.episodes, self.observations = episodes, observations

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

"""Demonstration datasets: instruction-labelled episodes in one HDF5 file.

A demonstration dataset holds whole episodes (every observation, every action in policy
units) and a table of *segments*: stretches ``[start, end]`` of an episode labelled with
the instruction they accomplish, judged against the observation at ``start``. An
episode's own instruction gives one segment; hindsight relabelling adds one for every
other instruction the episode happened to achieve (:func:`append_segments`), so a failed
attempt at "push the red cube left" still teaches "reach the red cube" (a failed episode
keeps the instruction it attempted in ``episode_instruction`` but has no given segment for
it: it did not demonstrate it). Behavioural
cloning samples ``(observation, action, instruction)`` rows from the segments with
:meth:`DemoDataset.batches`.

File layout (``format = "lcrl-demos"``, ``version = 1``)::

    attrs                 format, version, meta (JSON given to the writer), discrete (bool)
    instructions          (I,) str       the instruction table: an id is an index into it
    obs/<key>             (N, ...)       every observation of every episode, concatenated;
                                         episode e's T_e + 1 observations are the rows
                                         [episode_start[e], episode_start[e + 1]).
                                         float32 vectors; uint8 images chunked one frame per
                                         chunk and lzf-compressed (random reads stay cheap)
    action                (M, A) float32 actions in policy units [-1, 1], or (M,) int64
                                         discrete actions; M = sum of T_e; episode e's T_e
                                         actions are the rows
                                         [action_start[e], action_start[e + 1]) and action t
                                         leads from observation t to observation t + 1
    episode_start         (E + 1,) int64 observation rows where each episode starts
    action_start          (E + 1,) int64 action rows where each episode starts
                                         (episode_start[e] - e)
    episode_success       (E,) int8      1 succeeded, 0 failed, -1 unknown
    episode_instruction   (E,) int32     the instruction the episode followed (-1: none)
    episode_source        (E,) str       where it came from (scripted, robomimic, ...)
    segments              (S, 5) int64   episode, start, end, instruction id, origin
                                         (0 given, 1 hindsight); the segment's transitions
                                         are steps start .. end - 1, observation end is
                                         the first where the instruction holds (or T_e)
    scene/<name>          per-step arrays (N, ...) aligned with obs/, or per-episode arrays
                                         (E, ...) whose dataset attribute per_episode is
                                         true: the privileged scene, stored as given (dtype
                                         kept, strings allowed) and opaque to this module

``initial`` is never stored: :meth:`DemoDataset.batches` gives, under that key, the
``observation`` row at the start of each row's segment. Files are written under a
temporary name and moved into place, so a file at the destination is always complete.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np

from lcrl.errors import LcrlError

FORMAT = "lcrl-demos"
VERSION = 1
#: Segment origins (the last column of :meth:`DemoDataset.segments`).
GIVEN, HINDSIGHT = 0, 1
#: The observation key that batches derive from the segment start.
INITIAL = "initial"
#: Tolerance on stored continuous actions beyond [-1, 1] (rounding of scaled actions).
ACTION_TOLERANCE = 1e-4

__all__ = [
    "FORMAT",
    "GIVEN",
    "HINDSIGHT",
    "INITIAL",
    "VERSION",
    "DemoBatch",
    "DemoDataset",
    "DemoWriter",
    "append_segments",
    "import_robomimic",
]


class DemoBatch(NamedTuple):
    """Rows sampled from the segments of a demonstration dataset.

    Attributes:
        obs: the requested observation keys, ``(B, ...)``: float32 vectors, uint8 images.
            ``initial`` is the ``observation`` row at the start of the row's segment.
        action: ``(B, A)`` float32 in policy units ``[-1, 1]``, or ``(B,)`` int64.
        goal: ``(B,)`` int64 ids into :attr:`DemoDataset.instructions`.
        episode: ``(B,)`` int64 episode index.
        step: ``(B,)`` int64 step index within its episode.
    """

    obs: dict[str, np.ndarray]
    action: np.ndarray
    goal: np.ndarray
    episode: np.ndarray
    step: np.ndarray


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def _dumps(meta: Mapping[str, Any]) -> str:
    try:
        return json.dumps(dict(meta), default=_json_default)
    except (TypeError, ValueError) as e:
        raise LcrlError(f"the dataset meta must be JSON-serialisable: {e}") from None


def _is_text(arr: np.ndarray) -> bool:
    return arr.dtype.kind in "USO"


def _text_dtype() -> Any:
    return h5py.string_dtype("utf-8")


def _decode(values: np.ndarray) -> np.ndarray:
    """h5py string data (bytes or str objects) as a numpy str array."""
    flat = [v.decode() if isinstance(v, bytes) else str(v) for v in values.reshape(-1)]
    return np.asarray(flat, dtype=str).reshape(values.shape)


def _store_dtype(arr: np.ndarray) -> np.dtype:
    if arr.dtype.kind == "f":
        return np.dtype(np.float32)
    return arr.dtype


def _chunks(row_shape: tuple[int, ...], dtype: np.dtype) -> tuple[int, ...]:
    """One frame per chunk for images, about 64 KiB per chunk for everything else."""
    if len(row_shape) >= 2:
        return (1, *row_shape)
    row_bytes = max(1, int(np.prod(row_shape, dtype=np.int64)) * max(1, dtype.itemsize))
    return (max(1, min(65536 // row_bytes, 8192)), *row_shape)


def _create_growable(group: Any, name: str, row_shape: tuple[int, ...], dtype: np.dtype) -> Any:
    if dtype.kind in "USO":
        return group.create_dataset(
            name,
            (0, *row_shape),
            _text_dtype(),
            maxshape=(None, *row_shape),
            chunks=(256, *row_shape),
        )
    image = dtype == np.uint8 and len(row_shape) >= 2
    return group.create_dataset(
        name,
        (0, *row_shape),
        dtype,
        maxshape=(None, *row_shape),
        chunks=_chunks(row_shape, dtype),
        compression="lzf" if image else None,
    )


def _grow(ds: Any, values: np.ndarray) -> None:
    start = ds.shape[0]
    ds.resize(start + len(values), axis=0)
    if _is_text(values):
        values = np.asarray(values, dtype=object)
    ds[start:] = values


# --------------------------------------------------------------------------- writing


class DemoWriter:
    """Writes episodes to a new demonstration dataset (see the module docstring).

    Episodes are appended to a temporary file as they come (memory stays bounded);
    :meth:`close` completes it and moves it into place, so the destination only ever
    holds a finished file. Used as a context manager, an exception inside the ``with``
    block (Ctrl-C included) discards the temporary file and leaves the destination as it
    was; call :meth:`close` in an ``except`` clause to keep the episodes written so far.

    Args:
        path: the ``.h5`` file to create.
        meta: JSON-able description stored with the data (env config, settings).
        instructions: instructions to put first in the table (ids in this order); any
            other instruction is appended when an episode first names it.
        episode_scene: names of the ``scene`` arrays that describe a whole episode (one
            row per episode); every other scene array has one row per observation.
        overwrite: replace an existing file at ``path`` when closing (else refuse now).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        meta: dict[str, Any] | None = None,
        *,
        instructions: Sequence[str] = (),
        episode_scene: Sequence[str] = (),
        overwrite: bool = True,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and (not overwrite or self.path.is_dir()):
            kind = "a folder" if self.path.is_dir() else "a file"
            raise LcrlError(f"{self.path} is {kind} already; choose another path or remove it")
        self.meta = dict(meta or {})
        meta_json = _dumps(self.meta)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".part")
        self._ids: dict[str, int] = {}
        for text in instructions:
            self._id(text)
        self._episode_scene = set(episode_scene)
        self._file: Any = h5py.File(self._tmp, "w")
        f = self._file
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        f.attrs["meta"] = meta_json
        f.create_group("obs")
        f.create_group("scene")
        self._obs_spec: dict[str, tuple[tuple[int, ...], np.dtype]] | None = None
        self._scene_spec: dict[str, tuple[tuple[int, ...], np.dtype, bool]] | None = None
        self._action_spec: tuple[tuple[int, ...], bool] | None = None
        self._episode_start = [0]
        self._action_start = [0]
        self._success: list[int] = []
        self._instruction: list[int] = []
        self._source: list[str] = []
        self._segments: list[tuple[int, int, int, int, int]] = []

    # -- context manager
    def __enter__(self) -> DemoWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.discard()
        else:
            self.close()

    @property
    def num_episodes(self) -> int:
        """Episodes added so far."""
        return len(self._success)

    @property
    def instructions(self) -> list[str]:
        """The instruction table so far."""
        return list(self._ids)

    def update_meta(self, values: Mapping[str, Any]) -> None:
        """Set keys of the meta stored with the data (merged over the current meta)."""
        if self._file is None:
            raise LcrlError("this DemoWriter is closed")
        meta = {**self.meta, **dict(values)}
        self._file.attrs["meta"] = _dumps(meta)
        self.meta = meta

    def _id(self, text: str) -> int:
        if not isinstance(text, str) or not text.strip():
            raise LcrlError(f"an instruction must be a non-empty string, got {text!r}")
        return self._ids.setdefault(text, len(self._ids))

    def add_episode(
        self,
        obs: Mapping[str, np.ndarray],
        actions: np.ndarray,
        instruction: str | None = None,
        segments: Sequence[tuple[int, int, str]] = (),
        scene: Mapping[str, np.ndarray] | None = None,
        success: bool | None = None,
        source: str = "scripted",
    ) -> int:
        """Append one episode; returns its index.

        Args:
            obs: per key ``(T + 1, ...)``: every observation, the first before any action.
                A key ``initial`` is ignored (batches derive it from segment starts).
            actions: ``(T, A)`` in policy units ``[-1, 1]``, or ``(T,)`` integers.
            instruction: the instruction the episode followed. It gives the segment
                ``[0, T]`` (the episode ends at its success step, or at its time limit
                when ``success`` is unknown); a failed episode (``success=False``) keeps
                the instruction as what it attempted but gets no segment for it: it did
                not demonstrate it (hindsight relabelling finds what it did achieve).
            segments: extra given segments ``(start, end, text)``, ``0 <= start < end <= T``.
            scene: privileged scene arrays: ``(T + 1, ...)`` per observation, or one
                episode-wide array for the names listed in ``episode_scene``.
            success: whether the episode achieved its instruction (None: unknown).
            source: where the episode came from.

        Raises:
            LcrlError: inconsistent lengths, keys or shapes, actions outside ``[-1, 1]``,
                a bad segment, or the writer is closed.
        """
        if self._file is None:
            raise LcrlError("this DemoWriter is closed; open a new one to add episodes")
        arrays = {k: np.asarray(v) for k, v in obs.items() if k != INITIAL}
        if not arrays:
            raise LcrlError("an episode needs at least one observation array")
        act = np.asarray(actions)
        if act.ndim == 0 or len(act) < 1:
            raise LcrlError("an episode needs at least one action")
        t = len(act)
        for k, v in arrays.items():
            if v.ndim == 0 or len(v) != t + 1:
                raise LcrlError(
                    f"observation {k!r} has {len(v) if v.ndim else 0} rows; an episode of "
                    f"{t} actions needs {t + 1} observations (the first before any action)"
                )
            if _is_text(v):
                raise LcrlError(f"observation {k!r} holds text: observations must be numbers")
        act = self._check_actions(act)
        scene_arrays = {k: np.asarray(v) for k, v in (scene or {}).items()}
        self._check_obs(arrays)
        self._check_scene(scene_arrays, t)
        e = self.num_episodes
        rows: list[tuple[int, int, int, int, int]] = []
        if instruction is not None:
            iid = self._id(instruction)
            if success is not False:
                rows.append((e, 0, t, iid, GIVEN))
        else:
            iid = -1
        for seg in segments:
            try:
                start, end, text = seg
                start, end = int(start), int(end)
            except (TypeError, ValueError):
                raise LcrlError(f"a segment is (start, end, text), got {seg!r}") from None
            if not 0 <= start < end <= t:
                raise LcrlError(
                    f"segment ({start}, {end}, {text!r}) is outside the episode: need "
                    f"0 <= start < end <= {t}"
                )
            row = (e, start, end, self._id(text), GIVEN)
            if row not in rows:
                rows.append(row)
        f = self._file
        for k, v in arrays.items():
            _grow(f["obs"][k], v.astype(self._obs_spec[k][1], copy=False))
        _grow(f["action"], act)
        for k, v in scene_arrays.items():
            _grow(f["scene"][k], v[None] if self._scene_spec[k][2] else v)
        f.flush()
        self._episode_start.append(self._episode_start[-1] + t + 1)
        self._action_start.append(self._action_start[-1] + t)
        self._success.append(-1 if success is None else int(bool(success)))
        self._instruction.append(iid)
        self._source.append(str(source))
        self._segments.extend(rows)
        return e

    def _check_actions(self, act: np.ndarray) -> np.ndarray:
        if act.dtype.kind in "iub":
            if act.ndim != 1:
                raise LcrlError(f"discrete actions must be (T,) integers, got shape {act.shape}")
            act = act.astype(np.int64)
            spec: tuple[tuple[int, ...], bool] = ((), True)
        elif act.dtype.kind == "f":
            if act.ndim != 2:
                raise LcrlError(
                    f"continuous actions must be (T, A), got shape {act.shape} "
                    "(discrete actions must be integers)"
                )
            act = act.astype(np.float32)
            if not np.all(np.isfinite(act)):
                raise LcrlError("actions contain NaN or inf")
            worst = float(np.abs(act).max())
            if worst > 1.0 + ACTION_TOLERANCE:
                raise LcrlError(
                    f"actions must be in policy units [-1, 1]; the largest is {worst:.3g}: "
                    "map them from the env's bounds first"
                )
            act = np.clip(act, -1.0, 1.0)
            spec = ((int(act.shape[1]),), False)
        else:
            raise LcrlError(f"actions must be numbers, got dtype {act.dtype}")
        if self._action_spec is None:
            self._action_spec = spec
            shape, discrete = spec
            _create_growable(self._file, "action", shape, act.dtype)
            self._file.attrs["discrete"] = discrete
        elif spec != self._action_spec:
            raise LcrlError(
                f"actions of shape {act.shape[1:]} ({'discrete' if spec[1] else 'continuous'}) "
                f"differ from the first episode's {self._action_spec[0]} "
                f"({'discrete' if self._action_spec[1] else 'continuous'})"
            )
        return act

    def _check_obs(self, arrays: dict[str, np.ndarray]) -> None:
        spec = {k: (tuple(int(s) for s in v.shape[1:]), _store_dtype(v)) for k, v in arrays.items()}
        if self._obs_spec is None:
            self._obs_spec = spec
            for k, (shape, dtype) in spec.items():
                _create_growable(self._file["obs"], k, shape, dtype)
            return
        if set(spec) != set(self._obs_spec):
            raise LcrlError(
                f"observation keys {sorted(spec)} differ from the first episode's "
                f"{sorted(self._obs_spec)}"
            )
        for k, (shape, _) in spec.items():
            if shape != self._obs_spec[k][0]:
                raise LcrlError(
                    f"observation {k!r} rows have shape {shape}; the first episode's had "
                    f"{self._obs_spec[k][0]}"
                )

    def _check_scene(self, arrays: dict[str, np.ndarray], t: int) -> None:
        spec: dict[str, tuple[tuple[int, ...], np.dtype, bool]] = {}
        for k, v in arrays.items():
            per_episode = k in self._episode_scene
            if not per_episode and (v.ndim == 0 or len(v) != t + 1):
                raise LcrlError(
                    f"scene array {k!r} has {len(v) if v.ndim else 0} rows, not one per "
                    f"observation ({t + 1}); name it in DemoWriter(episode_scene=...) if it "
                    "describes the whole episode"
                )
            shape = tuple(int(s) for s in (v.shape if per_episode else v.shape[1:]))
            spec[k] = (shape, np.dtype(object) if _is_text(v) else v.dtype, per_episode)
        if self._scene_spec is None:
            self._scene_spec = spec
            for k, (shape, dtype, per_episode) in spec.items():
                ds = _create_growable(self._file["scene"], k, shape, dtype)
                ds.attrs["per_episode"] = per_episode
            return
        if set(spec) != set(self._scene_spec):
            raise LcrlError(
                f"scene arrays {sorted(spec)} differ from the first episode's "
                f"{sorted(self._scene_spec)}"
            )
        for k, (shape, _, _) in spec.items():
            if shape != self._scene_spec[k][0]:
                raise LcrlError(
                    f"scene array {k!r} has shape {shape}; the first episode's had "
                    f"{self._scene_spec[k][0]} (pad per-episode arrays to one width)"
                )

    def discard(self) -> None:
        """Close and delete the unfinished file (the destination is left untouched)."""
        if self._file is not None:
            try:
                self._file.close()
            finally:
                self._file = None
        self._tmp.unlink(missing_ok=True)

    def close(self) -> Path:
        """Write the tables, close the file and move it into place; returns its path.

        Raises:
            LcrlError: no episode was added (nothing is written).
        """
        if self._file is None:
            return self.path
        try:
            if self.num_episodes == 0:
                raise LcrlError("no episode was added: nothing written")
            f = self._file
            _write_tables(
                f,
                list(self._ids),
                np.asarray(self._segments, np.int64).reshape(-1, 5),
            )
            f.create_dataset("episode_start", data=np.asarray(self._episode_start, np.int64))
            f.create_dataset("action_start", data=np.asarray(self._action_start, np.int64))
            f.create_dataset("episode_success", data=np.asarray(self._success, np.int8))
            f.create_dataset("episode_instruction", data=np.asarray(self._instruction, np.int32))
            f.create_dataset(
                "episode_source",
                data=np.asarray(self._source, dtype=object),
                dtype=_text_dtype(),
            )
            f.close()
            self._file = None
            os.replace(self._tmp, self.path)
        except BaseException:
            self.discard()
            raise
        return self.path


def _write_tables(f: Any, instructions: list[str], segments: np.ndarray) -> None:
    """Write the instruction table and the segment table (growable, resized in place)."""
    tables = {
        "instructions": np.asarray(instructions, dtype=object).reshape(-1),
        "segments": segments.astype(np.int64).reshape(-1, 5),
    }
    for name, values in tables.items():
        if name in f:
            ds = f[name]
            ds.resize(len(values), axis=0)
            if len(values):
                ds[...] = values
        elif name == "instructions":
            f.create_dataset(
                name, data=values, dtype=_text_dtype(), maxshape=(None,), chunks=(256,)
            )
        else:
            f.create_dataset(name, data=values, maxshape=(None, 5), chunks=(1024, 5))


# --------------------------------------------------------------------------- reading


def _open(path: str | os.PathLike, mode: str = "r") -> Any:
    p = Path(path)
    if not p.is_file():
        hint = " (record one with lcrl demos record)" if not p.exists() else ""
        raise LcrlError(f"no demonstration dataset at {p}{hint}")
    try:
        f = h5py.File(p, mode)
    except OSError as e:
        raise LcrlError(f"{p} is not an HDF5 file ({e})") from None
    fmt = f.attrs.get("format")
    if fmt != FORMAT:
        f.close()
        what = f"a {fmt!r} file" if isinstance(fmt, str) else "not an lcrl file"
        hint = ""
        if isinstance(fmt, str) and "caption" in fmt:  # frames and labels, no actions
            hint = (
                ": a caption dataset stores no actions, so no policy learns from it; record "
                "random play with lcrl demos record --actor random"
            )
        raise LcrlError(f"{p} is {what}, not an {FORMAT} dataset{hint}")
    version = int(f.attrs.get("version", -1))
    if version != VERSION:
        f.close()
        raise LcrlError(f"{p} has {FORMAT} version {version}; this lcrl reads version {VERSION}")
    return f


def _ranges(starts: np.ndarray, stops: np.ndarray) -> list[tuple[int, int]]:
    """Merge sorted half-open ranges that touch."""
    out: list[tuple[int, int]] = []
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        if out and out[-1][1] == a:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


class DemoDataset:
    """Read a demonstration dataset lazily (observations are read per block of episodes).

    Args:
        path: the ``.h5`` file written by :class:`DemoWriter`.

    Raises:
        LcrlError: the file is missing, is not an lcrl-demos file, or has another version.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        f = self._file = _open(self.path)
        try:
            self.meta: dict[str, Any] = json.loads(f.attrs["meta"])
            self.instructions: list[str] = _decode(f["instructions"][:]).tolist()
            self.episode_start: np.ndarray = f["episode_start"][:].astype(np.int64)
            self.action_start: np.ndarray = f["action_start"][:].astype(np.int64)
            self.episode_success: np.ndarray = f["episode_success"][:].astype(np.int8)
            self.episode_instruction: np.ndarray = f["episode_instruction"][:].astype(np.int64)
            self.episode_source: list[str] = _decode(f["episode_source"][:]).tolist()
            self._segments = f["segments"][:].astype(np.int64).reshape(-1, 5)
            self.discrete: bool = bool(f.attrs["discrete"])
            self.obs_shapes: dict[str, tuple[int, ...]] = {
                k: tuple(int(s) for s in ds.shape[1:]) for k, ds in f["obs"].items()
            }
            self.action_shape: tuple[int, ...] = tuple(int(s) for s in f["action"].shape[1:])
            self.scene_keys: dict[str, bool] = {
                k: bool(ds.attrs.get("per_episode", False)) for k, ds in f["scene"].items()
            }
        except (KeyError, ValueError, json.JSONDecodeError) as e:
            f.close()
            raise LcrlError(f"{self.path} is a damaged {FORMAT} file ({e})") from None
        #: The most observations one block of :meth:`batches` held in memory.
        self.cache_high_water = 0

    def __enter__(self) -> DemoDataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def _f(self) -> Any:
        if self._file is None:
            raise LcrlError(f"{self.path} is closed")
        return self._file

    @property
    def num_episodes(self) -> int:
        """Episodes in the file."""
        return len(self.episode_start) - 1

    @property
    def num_steps(self) -> int:
        """Transitions (actions) in the file."""
        return int(self.action_start[-1])

    @property
    def num_observations(self) -> int:
        """Observations in the file (``num_steps + num_episodes``)."""
        return int(self.episode_start[-1])

    @property
    def episode_lengths(self) -> np.ndarray:
        """``(E,)`` transitions per episode."""
        return np.diff(self.action_start)

    def segments(self, hindsight: bool = True) -> np.ndarray:
        """``(S, 5)`` int64 rows: episode, start, end, instruction id, origin (0 given,
        1 hindsight). A segment's transitions are steps ``start .. end - 1`` of its
        episode, judged against observation ``start``."""
        seg = self._segments
        if not hindsight:
            seg = seg[seg[:, 4] == GIVEN]
        return seg.copy()

    # -- sampling
    def batches(
        self,
        batch_size: int,
        keys: Sequence[str],
        seed: int = 0,
        hindsight: bool = True,
        cache_steps: int = 200_000,
    ) -> Iterator[DemoBatch]:
        """An endless stream of random segment rows ``(observation, action, instruction)``.

        Every (segment, step) pair is one row, so a step inside two segments is drawn
        with either instruction. Episodes are read in random blocks of at most about
        ``cache_steps`` observations (one episode at least); the rows of a block are
        shuffled and served, then the next block is read, so every row comes once per
        pass and memory stays bounded. The stream depends only on ``seed``.

        Args:
            batch_size: rows per batch.
            keys: observation keys to return (``initial``: the segment's first
                ``observation``); e.g. a task's ``obs_shapes``.
            seed: seed of the order.
            hindsight: include hindsight segments (else only the given ones).
            cache_steps: observations held in memory at a time, about.

        Raises:
            LcrlError: bad sizes, unknown keys, or no segment to sample.
        """
        keys = list(keys)
        if batch_size <= 0:
            raise LcrlError(f"batch_size must be positive, got {batch_size}")
        if cache_steps <= 0:
            raise LcrlError(f"cache_steps must be positive, got {cache_steps}")
        unknown = [k for k in keys if k not in self.obs_shapes and k != INITIAL]
        if unknown:
            raise LcrlError(
                f"{self.path} stores the observation keys {sorted(self.obs_shapes)}, not {unknown}"
            )
        if INITIAL in keys and "observation" not in self.obs_shapes:
            raise LcrlError(
                f"'initial' is the segment's first 'observation', and {self.path} stores no "
                "'observation' key"
            )
        seg = self.segments(hindsight)
        seg = seg[seg[:, 2] > seg[:, 1]]
        if not len(seg):
            which = "segments" if hindsight else "given segments (try with hindsight)"
            raise LcrlError(f"{self.path} has no {which} to sample from")
        return self._stream(seg, keys, int(batch_size), int(seed), int(cache_steps))

    def _stream(
        self, seg: np.ndarray, keys: list[str], batch_size: int, seed: int, cache_steps: int
    ) -> Iterator[DemoBatch]:
        rng = np.random.default_rng(seed)
        load = [k for k in keys if k != INITIAL]
        if INITIAL in keys and "observation" not in load:
            load.append("observation")
        order_seg = np.argsort(seg[:, 0], kind="stable")
        seg = seg[order_seg]
        eps, first = np.unique(seg[:, 0], return_index=True)
        bounds = np.append(first, len(seg))
        seg_of = {int(e): seg[bounds[i] : bounds[i + 1]] for i, e in enumerate(eps)}
        n_obs = self.episode_start[eps + 1] - self.episode_start[eps]
        size_of = dict(zip(eps.tolist(), n_obs.tolist(), strict=True))
        pending: list[DemoBatch] = []
        have = 0
        kept: tuple[Any, ...] | None = None
        while True:
            order = rng.permutation(eps)
            blocks: list[list[int]] = [[]]
            used = 0
            for e in order.tolist():
                if blocks[-1] and used + size_of[e] > cache_steps:
                    blocks.append([])
                    used = 0
                blocks[-1].append(e)
                used += size_of[e]
            for block in blocks:
                if kept is not None:
                    data = kept
                else:
                    data = self._load_block(sorted(block), seg_of, load)
                    if len(blocks) == 1:
                        kept = data  # everything fits: read once
                obs, action, rows = data
                perm = rng.permutation(len(rows["goal"]))
                i = 0
                while i < len(perm):
                    take = min(batch_size - have, len(perm) - i)
                    idx = perm[i : i + take]
                    i += take
                    pending.append(self._gather(obs, action, rows, idx, keys))
                    have += take
                    if have == batch_size:
                        yield _concat(pending)
                        pending, have = [], 0

    def _load_block(
        self, block: list[int], seg_of: dict[int, np.ndarray], load: list[str]
    ) -> tuple[dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray]]:
        f = self._f()
        eb = np.asarray(block, np.int64)
        o0, o1 = self.episode_start[eb], self.episode_start[eb + 1]
        a0, a1 = self.action_start[eb], self.action_start[eb + 1]
        obs = {}
        for k in load:
            ds = f["obs"][k]
            obs[k] = np.concatenate([ds[a:b] for a, b in _ranges(o0, o1)])
        ads = f["action"]
        action = np.concatenate([ads[a:b] for a, b in _ranges(a0, a1)])
        if not self.discrete:
            action = action.astype(np.float32, copy=False)
        else:
            action = action.astype(np.int64, copy=False)
        self.cache_high_water = max(self.cache_high_water, int((o1 - o0).sum()))
        # local offsets of each episode inside the block arrays
        obs_off = np.concatenate([[0], np.cumsum(o1 - o0)[:-1]])
        act_off = np.concatenate([[0], np.cumsum(a1 - a0)[:-1]])
        parts: dict[str, list[np.ndarray]] = {
            n: [] for n in ("obs", "act", "init", "goal", "episode", "step")
        }
        for j, e in enumerate(block):
            for ep, start, end, iid, _ in seg_of[e].tolist():
                steps = np.arange(start, end, dtype=np.int64)
                parts["obs"].append(obs_off[j] + steps)
                parts["act"].append(act_off[j] + steps)
                parts["init"].append(np.full(len(steps), obs_off[j] + start, np.int64))
                parts["goal"].append(np.full(len(steps), iid, np.int64))
                parts["episode"].append(np.full(len(steps), ep, np.int64))
                parts["step"].append(steps)
        rows = {n: np.concatenate(v) for n, v in parts.items()}
        return obs, action, rows

    @staticmethod
    def _gather(
        obs: dict[str, np.ndarray],
        action: np.ndarray,
        rows: dict[str, np.ndarray],
        idx: np.ndarray,
        keys: list[str],
    ) -> DemoBatch:
        out = {}
        for k in keys:
            if k == INITIAL:
                out[k] = obs["observation"][rows["init"][idx]]
            else:
                out[k] = obs[k][rows["obs"][idx]]
        return DemoBatch(
            obs=out,
            action=action[rows["act"][idx]],
            goal=rows["goal"][idx],
            episode=rows["episode"][idx],
            step=rows["step"][idx],
        )

    # -- whole episodes
    def episode(self, e: int) -> dict[str, Any]:
        """Episode ``e``: ``obs`` (per key ``(T + 1, ...)``), ``action`` ``(T, ...)``,
        ``scene`` (per name: per-step ``(T + 1, ...)`` or the episode's row), ``success``
        (bool or None), ``instruction`` (text or None), ``source``, ``segments`` (its rows
        of :meth:`segments`) and ``length`` ``T``."""
        if not 0 <= e < self.num_episodes:
            raise LcrlError(f"episode {e} is outside [0, {self.num_episodes})")
        f = self._f()
        a, b = int(self.episode_start[e]), int(self.episode_start[e + 1])
        c, d = int(self.action_start[e]), int(self.action_start[e + 1])
        scene: dict[str, np.ndarray] = {}
        for k, per_episode in self.scene_keys.items():
            ds = f["scene"][k]
            v = ds[e] if per_episode else ds[a:b]
            if h5py.check_string_dtype(ds.dtype) is not None:
                v = _decode(np.asarray(v, dtype=object))
            scene[k] = np.asarray(v)
        success = int(self.episode_success[e])
        iid = int(self.episode_instruction[e])
        action = f["action"][c:d]
        return {
            "obs": {k: f["obs"][k][a:b] for k in self.obs_shapes},
            "action": action.astype(np.int64 if self.discrete else np.float32, copy=False),
            "scene": scene,
            "success": None if success < 0 else bool(success),
            "instruction": self.instructions[iid] if iid >= 0 else None,
            "source": self.episode_source[e],
            "segments": self._segments[self._segments[:, 0] == e].copy(),
            "length": d - c,
        }

    def read_obs(self, key: str, e: int) -> np.ndarray:
        """One observation key of episode ``e``, ``(T + 1, ...)``."""
        if key not in self.obs_shapes:
            raise LcrlError(f"{self.path} stores no observation {key!r}")
        if not 0 <= e < self.num_episodes:
            raise LcrlError(f"episode {e} is outside [0, {self.num_episodes})")
        a, b = int(self.episode_start[e]), int(self.episode_start[e + 1])
        return self._f()["obs"][key][a:b]

    # -- reporting
    def counts(self) -> dict[str, Any]:
        """Episodes, steps, successes, segments given / hindsight, distinct instructions
        and per-instruction segment counts (``{text: {"given": n, "hindsight": n}}``)."""
        seg = self._segments
        per: dict[str, dict[str, int]] = {}
        for iid, origin in seg[:, 3:5].tolist():
            row = per.setdefault(self.instructions[iid], {"given": 0, "hindsight": 0})
            row["given" if origin == GIVEN else "hindsight"] += 1
        given = seg[seg[:, 4] == GIVEN]
        return {
            "episodes": self.num_episodes,
            "steps": self.num_steps,
            "successes": int(np.sum(self.episode_success == 1)),
            "failures": int(np.sum(self.episode_success == 0)),
            "unknown_outcome": int(np.sum(self.episode_success < 0)),
            "segments": {"given": len(given), "hindsight": int(len(seg) - len(given))},
            "segment_steps": int(np.sum(seg[:, 2] - seg[:, 1])),
            "distinct_instructions": {
                "given": len(np.unique(given[:, 3])),
                "all": len(np.unique(seg[:, 3])),
            },
            "per_instruction": dict(sorted(per.items())),
        }

    def summary(self) -> str:
        """A few lines for the terminal."""
        c = self.counts()
        obs = ", ".join(f"{k} {'x'.join(map(str, s)) or '()'}" for k, s in self.obs_shapes.items())
        act = f"{'discrete' if self.discrete else 'continuous'} " + (
            "x".join(map(str, self.action_shape)) or "(one integer)"
        )
        src = ", ".join(
            f"{s} {n}" for s, n in sorted(_count(self.episode_source).items(), key=lambda x: -x[1])
        )
        outcome = ", ".join(
            f"{n} {what}"
            for n, what in (
                (c["successes"], "succeeded"),
                (c["failures"], "failed"),
                (c["unknown_outcome"], "of unknown outcome"),
            )
            if n
        )
        seg = c["segments"]
        lines = [
            f"{self.path}: {c['episodes']} episodes ({src}; {outcome}), {c['steps']} steps",
            f"  observations: {obs}; actions: {act}",
            f"  segments: {seg['given']} given, {seg['hindsight']} hindsight "
            f"({c['segment_steps']} labelled steps); instructions: "
            f"{c['distinct_instructions']['given']} given, {c['distinct_instructions']['all']} "
            f"with hindsight, {len(self.instructions)} in the table",
        ]
        env = self.meta.get("env")
        if isinstance(env, dict) and env.get("kind"):
            preset = self.meta.get("preset")
            fams = ", ".join(self.meta.get("families", env.get("families", ())))
            lines.append(
                f"  env: {env['kind']}"
                + (f" (preset {preset})" if preset else "")
                + (f", families {fams}" if fams else "")
            )
        return "\n".join(lines)


def _count(values: Iterable[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


def _concat(parts: list[DemoBatch]) -> DemoBatch:
    if len(parts) == 1:
        return parts[0]
    return DemoBatch(
        obs={k: np.concatenate([p.obs[k] for p in parts]) for k in parts[0].obs},
        action=np.concatenate([p.action for p in parts]),
        goal=np.concatenate([p.goal for p in parts]),
        episode=np.concatenate([p.episode for p in parts]),
        step=np.concatenate([p.step for p in parts]),
    )


# --------------------------------------------------------------------------- updating


def append_segments(
    path: str | os.PathLike,
    new: Sequence[tuple[int, int, int, str]],
    dst: str | os.PathLike | None = None,
    *,
    origin: int = HINDSIGHT,
    drop_hindsight: bool = False,
    meta: Mapping[str, Any] | None = None,
) -> Path:
    """Add segments ``(episode, start, end, text)`` to a dataset, atomically.

    The source is copied to a temporary file next to the destination, the segments (and
    any new instructions) are added there, and the copy is moved into place: the
    destination (``path`` itself when ``dst`` is None) is never half-written, Ctrl-C
    included. Rows already in the table (same episode, start, end, instruction) are
    skipped.

    Args:
        path: the dataset to read.
        new: segments to add; ``0 <= start < end <= T`` of the episode.
        dst: where to write the result (default: replace ``path``).
        origin: origin of the new rows (:data:`HINDSIGHT` or :data:`GIVEN`).
        drop_hindsight: remove the existing hindsight segments first (a fresh relabelling).
        meta: keys to set in the dataset's meta (merged over the existing meta).

    Returns:
        The path written.

    Raises:
        LcrlError: bad file, or a segment outside its episode.
    """
    src = Path(path)
    out = Path(dst) if dst is not None else src
    if origin not in (GIVEN, HINDSIGHT):
        raise LcrlError(f"origin must be {GIVEN} (given) or {HINDSIGHT} (hindsight), got {origin}")
    with DemoDataset(src) as data:
        lengths = data.episode_lengths
        table = list(data.instructions)
        old = data.segments()
        old_meta = dict(data.meta)
    if out.exists() and out.is_dir():
        raise LcrlError(f"{out} is a folder; give a file path for the dataset")
    ids = {t: i for i, t in enumerate(table)}
    if drop_hindsight:
        old = old[old[:, 4] != HINDSIGHT]
    seen = {tuple(r[:4]) for r in old.tolist()}
    rows = []
    for item in new:
        try:
            e, start, end, text = item
            e, start, end = int(e), int(start), int(end)
        except (TypeError, ValueError):
            raise LcrlError(f"a segment is (episode, start, end, text), got {item!r}") from None
        if not 0 <= e < len(lengths):
            raise LcrlError(f"segment episode {e} is outside [0, {len(lengths)})")
        if not 0 <= start < end <= lengths[e]:
            raise LcrlError(
                f"segment ({e}, {start}, {end}, {text!r}) is outside the episode: need "
                f"0 <= start < end <= {int(lengths[e])}"
            )
        if not isinstance(text, str) or not text.strip():
            raise LcrlError(f"a segment's instruction must be a non-empty string, got {text!r}")
        iid = ids.setdefault(text, len(ids))
        key = (e, start, end, iid)
        if key in seen:
            continue
        seen.add(key)
        rows.append((e, start, end, iid, origin))
    table = list(ids)
    segments = np.concatenate([old, np.asarray(rows, np.int64).reshape(-1, 5)])
    segments = segments[np.lexsort((segments[:, 4], segments[:, 1], segments[:, 0]))]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    try:
        shutil.copyfile(src, tmp)
        with h5py.File(tmp, "r+") as f:
            _write_tables(f, table, segments)
            if meta:
                f.attrs["meta"] = _dumps({**old_meta, **dict(meta)})
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


# --------------------------------------------------------------------------- robomimic


def _demo_names(group: Any) -> list[str]:
    def key(name: str) -> tuple[int, str]:
        tail = name.rsplit("_", 1)[-1]
        return (int(tail), name) if tail.isdigit() else (1 << 62, name)

    return sorted((n for n in group if n.startswith("demo")), key=key)


def _instruction_from(attrs: Any) -> str | None:
    raw = attrs.get("problem_info")
    if raw is None:
        return None
    if isinstance(raw, bytes):
        raw = raw.decode()
    try:
        info = json.loads(raw)
    except (TypeError, json.JSONDecodeError):
        return None
    text = info.get("language_instruction") if isinstance(info, dict) else None
    if isinstance(text, (list, tuple)):
        text = " ".join(str(t) for t in text)
    if not isinstance(text, str) or not text.strip():
        return None
    return " ".join(text.split())


def _attr_json(attrs: Any, name: str) -> Any:
    raw = attrs.get(name)
    if raw is None:
        return None
    if isinstance(raw, bytes):
        raw = raw.decode()
    try:
        return json.loads(raw)
    except (TypeError, json.JSONDecodeError):
        return str(raw)


def import_robomimic(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    instruction: str | None = None,
    obs_keys: Sequence[str] | None = None,
    image_key: str | None = "auto",
    proprio_keys: Sequence[str] = (),
    overwrite: bool = False,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
) -> Path:
    """Convert a robomimic-style HDF5 file (robomimic, LIBERO) into a demonstration dataset.

    The source holds ``data/demo_<i>/{obs/<key>, actions, next_obs/<key>, ...}``;
    ``data.attrs["env_args"]`` (JSON) is kept in the meta, and LIBERO's
    ``data.attrs["problem_info"]`` (JSON) may carry the ``"language_instruction"``.
    Each demo becomes one episode whose whole length is one given segment (outcome
    unknown). Its ``T`` observations are completed by the last ``next_obs`` row; without
    ``next_obs`` the last action is dropped instead.

    Args:
        src: the robomimic file.
        dst: the demonstration dataset to write.
        instruction: the instruction of every demo (default: ``problem_info``'s
            ``language_instruction``).
        obs_keys: low-dimensional observation keys concatenated, in this order, into
            ``observation`` (default: every non-image key of the first demo, sorted).
        image_key: the camera key stored as ``image`` (``"auto"``: ``agentview_image``,
            ``agentview_rgb`` or the first image key; None or ``""``: no image).
        proprio_keys: keys concatenated into ``proprio`` (the robot's own state for
            camera policies; none by default).
        overwrite: replace an existing ``dst``.
        progress: wraps the iteration over demos (e.g. ``tqdm``).

    Returns:
        The path written. ``meta["import"]["clipped_values"]`` counts action values that
        were outside ``[-1, 1]`` and were clipped (a warning is printed too).

    Raises:
        LcrlError: missing or malformed source, no instruction, unknown keys.
    """
    import warnings

    src_path, dst_path = Path(src), Path(dst)
    if not src_path.is_file():
        raise LcrlError(f"no robomimic file at {src_path}")
    if dst_path.exists() and not overwrite:
        raise LcrlError(f"{dst_path} exists; pass --overwrite to replace it")
    try:
        f = h5py.File(src_path, "r")
    except OSError as e:
        raise LcrlError(f"{src_path} is not an HDF5 file ({e})") from None
    with f:
        if "data" not in f or not isinstance(f["data"], h5py.Group):
            raise LcrlError(f"{src_path} has no 'data' group: not a robomimic-style file")
        data = f["data"]
        demos = _demo_names(data)
        if not demos:
            raise LcrlError(f"{src_path} has no data/demo_<i> groups")
        text = instruction if instruction and instruction.strip() else None
        if text is None:
            text = _instruction_from(data.attrs)
        if text is None:
            raise LcrlError(
                f"{src_path} names no instruction (no language_instruction in "
                "data.attrs['problem_info']): pass --instruction TEXT"
            )
        text = " ".join(text.split())
        first = data[demos[0]]
        if "obs" not in first or "actions" not in first:
            raise LcrlError(f"{src_path}: {demos[0]} has no obs group or no actions")
        available = {k: first["obs"][k] for k in first["obs"]}

        def is_image(ds: Any) -> bool:
            return ds.dtype == np.uint8 and ds.ndim == 4

        if obs_keys is None:
            obs_keys = sorted(k for k, ds in available.items() if not is_image(ds))
        if image_key == "auto":
            images = sorted(k for k, ds in available.items() if is_image(ds))
            preferred = [k for k in ("agentview_image", "agentview_rgb") if k in images]
            image_key = (preferred or images or [None])[0]
        wanted = [*obs_keys, *proprio_keys, *([image_key] if image_key else [])]
        missing = [k for k in wanted if k not in available]
        if missing:
            raise LcrlError(
                f"{src_path} has no observation keys {missing}; it has {sorted(available)}"
            )
        if not obs_keys and not image_key:
            raise LcrlError("choose at least one observation key or an image key")
        env_args = _attr_json(data.attrs, "env_args")
        clipped = 0
        total = 0
        settings = {
            "source": str(src_path),
            "obs_keys": list(obs_keys),
            "image_key": image_key or None,
            "proprio_keys": list(proprio_keys),
            "demos": len(demos),
        }
        meta = {"env": None, "robomimic_env_args": env_args, "import": settings}
        writer = DemoWriter(dst_path, meta, instructions=[text], overwrite=overwrite)
        try:
            iterator = progress(demos) if progress is not None else demos
            for name in iterator:
                demo = data[name]
                actions = np.asarray(demo["actions"][:], np.float64)
                if actions.ndim == 1:
                    actions = actions[:, None]
                has_next = "next_obs" in demo

                def rows(key: str, demo: Any = demo, has_next: bool = has_next) -> np.ndarray:
                    v = np.asarray(demo["obs"][key][:])
                    if has_next and key in demo["next_obs"]:
                        return np.concatenate([v, np.asarray(demo["next_obs"][key][-1:])])
                    return v

                def vec(keys: Sequence[str], rows: Any = rows) -> np.ndarray:
                    parts = [rows(k) for k in keys]
                    n = min(len(p) for p in parts)
                    flat = [p[:n].reshape(n, -1).astype(np.float32) for p in parts]
                    return np.concatenate(flat, axis=1)

                obs: dict[str, np.ndarray] = {}
                if obs_keys:
                    obs["observation"] = vec(obs_keys)
                if proprio_keys:
                    obs["proprio"] = vec(proprio_keys)
                if image_key:
                    obs["image"] = rows(image_key).astype(np.uint8)
                n_obs = min(len(v) for v in obs.values())
                t = min(len(actions), n_obs - 1)
                if t < 1:
                    continue
                obs = {k: v[: t + 1] for k, v in obs.items()}
                actions = actions[:t]
                outside = np.abs(actions) > 1.0
                clipped += int(outside.sum())
                total += actions.size
                writer.add_episode(
                    obs,
                    np.clip(actions, -1.0, 1.0).astype(np.float32),
                    instruction=text,
                    source="robomimic",
                )
            settings["clipped_values"] = clipped
            settings["action_values"] = total
            writer.update_meta(meta)
            path = writer.close()
        except BaseException:
            writer.discard()
            raise
    if clipped:
        warnings.warn(
            f"{clipped} of {total} action values were outside [-1, 1] and were clipped",
            stacklevel=2,
        )
    return path

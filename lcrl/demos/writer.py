"""Writing demonstrations episode by episode (:class:`DemoWriter`), and appending segments to
a file (:func:`append_segments`)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from lcrl.demos.hdf5 import (
    ACTION_TOLERANCE,
    FORMAT,
    GIVEN,
    INITIAL,
    VERSION,
    _create_growable,
    _dumps,
    _grow,
    _is_text,
    _store_dtype,
    _text_dtype,
    _write_tables,
)
from lcrl.errors import LcrlError


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

"""Reading a demonstration file as a dataset of steps and episodes (:class:`DemoDataset`)."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np

from lcrl.demos.hdf5 import (
    FORMAT,
    GIVEN,
    HINDSIGHT,
    INITIAL,
    _decode,
    _dumps,
    _open,
    _ranges,
    _write_tables,
)
from lcrl.errors import LcrlError


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

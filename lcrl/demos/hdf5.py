"""The HDF5 layout of a demonstration file: its format tag and version, growable datasets,
text columns and JSON attributes."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from lcrl.errors import LcrlError

FORMAT = "lcrl-demos"

#: Segment origins (the last column of :meth:`DemoDataset.segments`).
GIVEN, HINDSIGHT = 0, 1


VERSION = 1


#: The observation key that batches derive from the segment start.
INITIAL = "initial"


#: Tolerance on stored continuous actions beyond [-1, 1] (rounding of scaled actions).
ACTION_TOLERANCE = 1e-4


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

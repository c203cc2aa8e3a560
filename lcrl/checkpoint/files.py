"""The files of a checkpoint: their names, checksums, errors, and writes that reach the disk
whole (temporary file, fsync, rename)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import uuid
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.errors import LcrlError

FORMAT_VERSION = 1


META_FILE = "meta.json"


WEIGHTS_FILE = "weights.safetensors"


STATE_TENSORS_FILE = "state.safetensors"


STATE_JSON_FILE = "state.json"


ARRAYS_FILE = "arrays.npz"


LATEST_FILE = "latest.json"


#: ``meta.json`` keys of the checksums: every other file's, and its own content's.
CHECKSUMS_KEY = "checksums"


META_CHECKSUM_KEY = "meta_checksum"


_RESERVED_META_KEYS = frozenset({"format_version", CHECKSUMS_KEY, META_CHECKSUM_KEY})


_HASH_CHUNK = 1 << 20


# weights.safetensors header metadata: JSON {module name: [parameter names in saved order]}.
_MODULES_METADATA_KEY = "lcrl.modules"


_RESERVED_JSON_NAMES = frozenset({"meta", "state"})


# np.savez takes these as its own keyword arguments, so they cannot name an array.
_RESERVED_ARRAY_NAMES = frozenset({"file", "allow_pickle"})


_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")


_MAX_LISTED_MISMATCHES = 5


class CheckpointError(LcrlError, ValueError):
    """A checkpoint cannot be written or read (missing or corrupt file, wrong format, mismatch)."""


class CheckpointCorruptError(CheckpointError):
    """A checkpoint file's bytes differ from those its checksum recorded when it was saved.

    Attributes:
        path: the corrupt file.
    """

    def __init__(self, path: Path, why: str) -> None:
        super().__init__(f"corrupt checkpoint file {path}: {why}")
        self.path = path


class CheckpointWriteError(CheckpointError):
    """Writing a checkpoint failed (a full disk, a folder that became read-only): nothing
    was changed at the checkpoint's path.

    Attributes:
        path: the file (or folder) whose write failed, named by its final place.
        problem: what went wrong, in a few words (``No space left on device``).
    """

    def __init__(self, path: Path, problem: str) -> None:
        super().__init__(f"cannot write {path}: {problem}")
        self.path = path
        self.problem = problem


def write_problem(exc: BaseException) -> str:
    """What a failed write says, in a few words: the ``strerror`` of an ``OSError``, the
    operating system's message inside a safetensors error (``No space left on device``),
    else the first line of the exception."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    text = str(exc).strip()
    found = re.search(r"I/O error: (.+?)(?: \(os error \d+\))?$", text, re.MULTILINE)
    if found is None:
        found = re.search(r'message: "([^"]+)"', text)
    if found is not None:
        return found.group(1)
    return text.splitlines()[0] if text else type(exc).__name__


def _move_into_place(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` to ``target``, replacing an existing ``target`` via a hidden ``.old``."""
    parent = target.parent
    if not target.exists():
        os.rename(tmp, target)
        _fsync_dir(parent)
        return
    old = parent / f".{target.name}.old-{uuid.uuid4().hex[:12]}"
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.rename(old, target)
        raise
    _fsync_dir(parent)
    shutil.rmtree(old, ignore_errors=True)


def _check_name(name: Any, what: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        raise CheckpointError(
            f"bad {what} name {name!r}: expected a non-empty str of letters, digits, '_', "
            f"'.', '-' not starting with '.' or '-'"
        )
    return name


def _json_dumps(doc: Any, what: str) -> str:
    try:
        return json.dumps(doc, indent=2, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(
            f"cannot save {what}: expected JSON-serialisable data ({exc})"
        ) from exc


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"Object of type {type(obj).__name__} is not JSON serializable")


def file_checksum(path: Path) -> str:
    """``sha256:<hex>`` of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            digest.update(chunk)
    return f"sha256:{digest.hexdigest()}"


def meta_checksum(doc: Mapping[str, Any]) -> str:
    """``sha256:<hex>`` of a ``meta.json`` document without its own checksum, keys sorted."""
    body = {k: v for k, v in doc.items() if k != META_CHECKSUM_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), default=_json_default)
    return f"sha256:{hashlib.sha256(text.encode()).hexdigest()}"


def compresses(array: np.ndarray) -> bool:
    """Whether :func:`write_npz` deflates an array: integer, boolean and byte arrays
    (labels, ids, flags, camera frames) shrink several times at the fastest zlib level;
    float arrays (observations, actions) hardly shrink and would only cost time."""
    return array.dtype.kind in "biu" and array.nbytes >= 1024


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` as an ``.npz`` archive that :func:`numpy.load` reads, deflating
    the arrays :func:`compresses` picks (zlib level 1) and storing the rest; fsynced. The
    archive is closed on every path, a failed write included (a full disk)."""
    from numpy.lib import format as npy_format

    with open(path, "wb") as f:
        with zipfile.ZipFile(f, "w", allowZip64=True) as zf:
            for name, array in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                if compresses(array):
                    info.compress_type = zipfile.ZIP_DEFLATED
                    info._compresslevel = 1  # ZipInfo.compress_level from Python 3.13 on
                with zf.open(info, "w", force_zip64=True) as entry:
                    npy_format.write_array(entry, np.asanyarray(array), allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())


def _write_text(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    if os.name != "posix":
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _read_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CheckpointError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise CheckpointError(f"corrupt {path}: expected UTF-8 JSON ({exc})") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise CheckpointError(
            f"corrupt {path}: expected valid JSON but parsing failed at line {exc.lineno} "
            f"column {exc.colno}: {exc.msg}"
        ) from exc


def _describe(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"

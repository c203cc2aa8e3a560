"""Pickle-free, atomic training checkpoints: weights, optimiser/RNG state, JSON and arrays.

Layout
    A checkpoint is a directory::

        meta.json             # the caller's ``meta`` plus ``"format_version"``
        weights.safetensors   # module weights, keys "<module>.<parameter>"
        state.safetensors     # the tensors of every ``states[name]`` (see flatten_state)
        state.json            # the skeletons that put those tensors back together
        <name>.json           # one per ``json_files`` entry
        arrays.npz            # only when ``arrays`` was given (e.g. the replay buffer)

No pickle
    Nothing in a checkpoint is ever unpickled: tensors are read with safetensors, documents
    with :mod:`json`, arrays with ``np.load(..., allow_pickle=False)``. Arbitrary Python state
    (optimiser state dicts, RNG states, counters) is split by :func:`flatten_state` into
    named tensors plus a JSON skeleton of dicts, lists, tuples and scalars.

Checksums
    ``meta.json`` records the SHA-256 of every other file (``"checksums"``) and of its own
    content (``"meta_checksum"``: the document without that key, keys sorted). Each file
    is verified the first time a :class:`Checkpoint` reads it, so acting reads and checks
    the weights and never the replay buffer, while resuming checks everything it reads. A
    file whose bytes changed after the save (a flipped bit, a partial copy) raises
    :class:`CheckpointCorruptError` naming it; checkpoints written before checksums
    existed load unverified. :func:`verify_checkpoint` checks every file at once.

Atomicity
    :func:`save_checkpoint` writes everything into a hidden temporary sibling directory,
    fsyncs every file and the directory, then renames it into place. An existing checkpoint
    at the same path is first renamed to a hidden ``.<name>.old-*`` sibling and deleted only
    after the new one is in place, so at every instant a complete checkpoint exists at some
    path and ``directory`` itself is never half-written. :func:`write_latest` updates
    ``latest.json`` with write-to-temp + :func:`os.replace`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import uuid
import zipfile
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import safetensors.torch
import torch

from lcrl.errors import LcrlError

__all__ = [
    "FORMAT_VERSION",
    "Checkpoint",
    "CheckpointCorruptError",
    "CheckpointError",
    "CheckpointWriteError",
    "find_latest",
    "flatten_state",
    "load_checkpoint",
    "remove_stale",
    "save_checkpoint",
    "seal_checkpoint",
    "unflatten_state",
    "verify_checkpoint",
    "write_latest",
]

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

# numpy dtypes stored as tensors of the same dtype; every other dtype is stored as raw bytes.
_NATIVE_NUMPY_DTYPES = frozenset(
    np.dtype(t)
    for t in (
        np.bool_,
        np.uint8,
        np.int8,
        np.int16,
        np.int32,
        np.int64,
        np.float16,
        np.float32,
        np.float64,
    )
)


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


# ----------------------------------------------------------------------------------------------
# flatten_state / unflatten_state
# ----------------------------------------------------------------------------------------------


def flatten_state(state: Any, prefix: str = "") -> tuple[dict[str, torch.Tensor], Any]:
    """Split a nested structure into flat named tensors and a JSON-able skeleton.

    Supported values: dicts (including ``OrderedDict``, whose ``_metadata`` attribute, as set
    by ``Module.state_dict()``, is kept) with ``str`` or ``int`` keys, lists, tuples,
    tensors, numpy arrays and scalars, and ``None``/``bool``/``int``/``float``/``str``.
    Integers of any size are kept exactly (JSON integers are unbounded in Python); non-finite
    floats are encoded explicitly.

    Every tensor and numpy array is replaced in the skeleton by a node naming its entry in
    the returned tensor dict, so :func:`unflatten_state` can rebuild the structure with int
    keys as int, tuples as tuples, and numpy arrays as numpy arrays of the same dtype and
    shape. Tensors are neither copied nor moved; the same tensor object appearing twice is
    stored once and comes back as one object. Numpy arrays of the common numeric and bool
    dtypes become tensors of that dtype (sharing memory where possible); other dtypes
    (unsigned 16/32/64-bit, complex, strings, datetimes, non-native byte order) become
    ``uint8`` tensors of their raw bytes.

    Args:
        state: The structure to split.
        prefix: Prepended, followed by ``"."``, to every tensor name (e.g. the state's name),
            so that several flattened states can share one tensor file.

    Returns:
        ``(tensors, skeleton)``: tensor names to tensors, and a structure made only of JSON
        types (dicts with str keys, lists, str, int, float, bool, None).

    Raises:
        CheckpointError: If the structure holds an unsupported value (object arrays,
            structured dtypes, sparse tensors, sets, arbitrary objects, keys other than
            str/int); the message gives the value's location.
    """
    flattener = _Flattener(prefix)
    skeleton = flattener.encode(state, [])
    return flattener.tensors, skeleton


def unflatten_state(tensors: Mapping[str, torch.Tensor], skeleton: Any) -> Any:
    """Rebuild the structure that :func:`flatten_state` split.

    Args:
        tensors: Tensor names to tensors (at least every name the skeleton refers to).
        skeleton: The skeleton returned by :func:`flatten_state` (possibly after a JSON round
            trip).

    Returns:
        The rebuilt structure. Tensors are the objects from ``tensors`` (not copied); numpy
        arrays stored natively are views of them (moved to CPU first if needed).

    Raises:
        CheckpointError: If the skeleton is malformed or names a tensor that is missing or
            has the wrong dtype or size.
    """
    return _decode(skeleton, tensors, "<root>")


class _Flattener:
    """Walks a structure, collecting tensors and producing the skeleton."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.tensors: dict[str, torch.Tensor] = {}
        self._names_by_id: dict[int, str] = {}

    def _name(self, path: list[str]) -> str:
        base = ".".join([self.prefix, *path]) if self.prefix else ".".join(path)
        base = base or "value"
        name, n = base, 1
        while name in self.tensors:
            n += 1
            name = f"{base}#{n}"
        return name

    def encode(self, obj: Any, path: list[str]) -> Any:
        if obj is None or isinstance(obj, (bool, int, str)):
            return obj
        if isinstance(obj, float):
            if math.isfinite(obj):
                return obj
            return {"type": "float", "value": repr(obj)}  # 'nan', 'inf' or '-inf'
        if isinstance(obj, torch.Tensor):
            return self._tensor(obj, path)
        if isinstance(obj, np.ndarray):
            return self._ndarray(obj, path, "ndarray")
        if isinstance(obj, np.generic):
            return self._ndarray(np.asarray(obj), path, "npscalar")
        if isinstance(obj, Mapping):
            return self._mapping(obj, path)
        if isinstance(obj, (list, tuple)):
            items = [self.encode(v, [*path, str(i)]) for i, v in enumerate(obj)]
            return {"type": "tuple" if isinstance(obj, tuple) else "list", "items": items}
        raise CheckpointError(
            f"cannot store state at '{_where(path)}': expected a tensor, numpy array, "
            f"dict, list, tuple, str, int, float, bool or None but found {type(obj).__name__}"
        )

    def _mapping(self, obj: Mapping[Any, Any], path: list[str]) -> dict[str, Any]:
        items = []
        for key, value in obj.items():
            if not isinstance(key, (str, int)):
                raise CheckpointError(
                    f"cannot store state at '{_where(path)}': expected str or int dict keys "
                    f"but found key {key!r} of type {type(key).__name__}"
                )
            items.append([key, self.encode(value, [*path, str(key)])])
        node: dict[str, Any] = {"type": "dict", "items": items}
        if isinstance(obj, OrderedDict):
            node["ordered"] = True
            metadata = getattr(obj, "_metadata", None)
            if isinstance(metadata, Mapping):
                node["metadata"] = self.encode(metadata, [*path, "_metadata"])
        return node

    def _tensor(self, t: torch.Tensor, path: list[str]) -> dict[str, Any]:
        if t.layout != torch.strided:
            raise CheckpointError(
                f"cannot store state at '{_where(path)}': expected a dense (strided) tensor "
                f"but found layout {t.layout}"
            )
        name = self._names_by_id.get(id(t))
        if name is None:
            name = self._name(path)
            self.tensors[name] = t
            self._names_by_id[id(t)] = name
        return {"type": "tensor", "name": name}

    def _ndarray(self, a: np.ndarray, path: list[str], kind: str) -> dict[str, Any]:
        dtype = a.dtype
        if dtype.hasobject or dtype.names is not None:
            what = "object" if dtype.hasobject else "structured"
            raise CheckpointError(
                f"cannot store state at '{_where(path)}': expected a numpy array of a plain "
                f"dtype but found {what} dtype {dtype}"
            )
        name = self._name(path)
        # (np.ascontiguousarray would turn a 0-d array into a 1-d one.)
        if not a.flags.c_contiguous or not a.flags.writeable:
            a = a.copy(order="C")
        if dtype in _NATIVE_NUMPY_DTYPES and dtype.isnative:
            self.tensors[name] = torch.from_numpy(a)
            encoding = "native"
        else:
            self.tensors[name] = torch.from_numpy(a.reshape(-1).view(np.uint8))
            encoding = "bytes"
        return {
            "type": kind,
            "name": name,
            "dtype": dtype.str,
            "shape": list(a.shape),
            "encoding": encoding,
        }


def _where(path: list[str]) -> str:
    return ".".join(path) if path else "<root>"


def _decode(node: Any, tensors: Mapping[str, torch.Tensor], where: str) -> Any:
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if not isinstance(node, dict) or "type" not in node:
        raise CheckpointError(
            f"malformed state skeleton at '{where}': expected a value or a typed node "
            f"but found {type(node).__name__}"
        )
    kind = node["type"]
    try:
        if kind == "dict":
            out: Any = OrderedDict() if node.get("ordered") else {}
            for key, value in node["items"]:
                out[key] = _decode(value, tensors, f"{where}.{key}")
            if "metadata" in node:
                out._metadata = _decode(node["metadata"], tensors, f"{where}._metadata")
            return out
        if kind in ("list", "tuple"):
            items = [_decode(v, tensors, f"{where}.{i}") for i, v in enumerate(node["items"])]
            return tuple(items) if kind == "tuple" else items
        if kind == "float":
            return float(node["value"])
        if kind == "tensor":
            return _lookup(tensors, node["name"], where)
        if kind in ("ndarray", "npscalar"):
            array = _decode_ndarray(node, tensors, where)
            return array[()] if kind == "npscalar" else array
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(
            f"malformed state skeleton at '{where}': bad {kind!r} node ({exc!r})"
        ) from exc
    raise CheckpointError(
        f"malformed state skeleton at '{where}': expected a node type among dict, list, "
        f"tuple, float, tensor, ndarray, npscalar but found {kind!r}"
    )


def _lookup(tensors: Mapping[str, torch.Tensor], name: str, where: str) -> torch.Tensor:
    try:
        return tensors[name]
    except KeyError:
        raise CheckpointError(
            f"state at '{where}' expected tensor '{name}' but no tensor of that name was found"
        ) from None


def _decode_ndarray(
    node: dict[str, Any], tensors: Mapping[str, torch.Tensor], where: str
) -> np.ndarray:
    t = _lookup(tensors, node["name"], where).detach().cpu()
    dtype = np.dtype(node["dtype"])
    shape = tuple(int(n) for n in node["shape"])
    if node["encoding"] == "native":
        array = t.numpy()
        if array.dtype != dtype or array.shape != shape:
            raise CheckpointError(
                f"state at '{where}': expected array '{node['name']}' of dtype {dtype} and "
                f"shape {shape} but found dtype {array.dtype} and shape {array.shape}"
            )
        return array
    raw = t.numpy()
    expected = dtype.itemsize * math.prod(shape)
    if raw.dtype != np.uint8 or raw.size != expected:
        raise CheckpointError(
            f"state at '{where}': expected {expected} raw bytes for array '{node['name']}' "
            f"but found {raw.size} elements of dtype {raw.dtype}"
        )
    return np.frombuffer(bytearray(raw.tobytes()), dtype=dtype).reshape(shape)


# ----------------------------------------------------------------------------------------------
# save_checkpoint
# ----------------------------------------------------------------------------------------------


def save_checkpoint(
    directory: str | Path,
    *,
    modules: Mapping[str, torch.nn.Module | Mapping[str, torch.Tensor]],
    states: Mapping[str, Any] | None = None,
    meta: Mapping[str, Any] | None = None,
    json_files: Mapping[str, Any] | None = None,
    arrays: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write a checkpoint directory atomically, replacing any checkpoint already there.

    Everything is validated before anything is written. Files go into a hidden temporary
    sibling directory (``.<name>.tmp-*``), are fsynced, and the directory is renamed into
    place. If ``directory`` already holds a checkpoint, it is renamed to a hidden
    ``.<name>.old-*`` sibling first and deleted once the new one is in place, so a crash
    leaves either the old or the new complete checkpoint (the old one possibly under its
    hidden name), never a half-written ``directory``. On an exception the temporary
    directory is removed and the previous checkpoint is left (or put back) at ``directory``.

    Args:
        directory: Where the checkpoint goes. Its parent is created if needed. If it exists
            it must be a checkpoint (contain ``meta.json``) or an empty directory.
        modules: Name to ``nn.Module`` (its ``state_dict()`` is saved) or to a mapping of
            parameter names to tensors. Saved to ``weights.safetensors`` under keys
            ``"<name>.<param>"``. Names must not contain ``"."``.
        states: Name to any structure :func:`flatten_state` accepts (optimiser state dicts,
            RNG states, counters). Saved to ``state.safetensors`` + ``state.json``.
        meta: JSON document saved as ``meta.json`` with ``"format_version"`` added (the key
            is reserved). Dict keys are converted to strings, as :mod:`json` does.
        json_files: Name to JSON document, each saved as ``<name>.json``. Names ``meta`` and
            ``state`` are reserved.
        arrays: Name to numpy array, saved as ``arrays.npz`` (:func:`write_npz`: integer
            and byte arrays deflated, float arrays stored; the file is only written when
            this is given). Dtypes holding Python objects are rejected.

    Returns:
        The checkpoint path, ``Path(directory)``.

    Raises:
        CheckpointError: If an input cannot be stored (bad name, non-JSON value, object
            array, unsupported state value) or ``directory`` exists and is not a checkpoint.
        CheckpointWriteError: If a file cannot be written (a full disk, a read-only
            folder: safetensors, JSON and npz writes alike); the message names the file
            by its final path, and whatever was at ``directory`` is left there.
    """
    final = Path(directory)
    target = Path(os.path.abspath(final))
    parent = target.parent

    # Validate and serialise everything in memory before touching the disk.
    weights, module_keys = _collect_weights(modules)
    state_tensors, skeletons = _collect_states(states or {})
    _meta_text(meta or {})  # refused before anything is written
    json_texts = _json_texts(json_files or {})
    array_dict = _collect_arrays(arrays) if arrays is not None else None

    if target.exists() or target.is_symlink():
        if not target.is_dir() or target.is_symlink():
            raise CheckpointError(
                f"cannot save checkpoint to {final}: expected a checkpoint directory or no "
                f"file there but found a {'symlink' if target.is_symlink() else 'file'}"
            )
        if not (target / META_FILE).is_file() and any(target.iterdir()):
            raise CheckpointError(
                f"refusing to replace {final}: expected an existing checkpoint (with "
                f"{META_FILE}) or an empty directory but found a non-empty directory "
                f"without {META_FILE}"
            )

    writing = final  # what is being written, named by its final place
    try:
        parent.mkdir(parents=True, exist_ok=True)
        # (Not tempfile.mkdtemp: its 0o700 mode would stick to the checkpoint; os.mkdir
        # uses umask.)
        tmp = parent / f".{target.name}.tmp-{uuid.uuid4().hex[:12]}"
        os.mkdir(tmp)
    except OSError as exc:
        raise CheckpointWriteError(final, write_problem(exc)) from exc
    try:
        writing = final / WEIGHTS_FILE
        safetensors.torch.save_file(
            weights,
            tmp / WEIGHTS_FILE,
            metadata={_MODULES_METADATA_KEY: json.dumps(module_keys)},
        )
        _fsync_file(tmp / WEIGHTS_FILE)
        writing = final / STATE_TENSORS_FILE
        safetensors.torch.save_file(state_tensors, tmp / STATE_TENSORS_FILE)
        _fsync_file(tmp / STATE_TENSORS_FILE)
        writing = final / STATE_JSON_FILE
        state_doc = {"format_version": FORMAT_VERSION, "states": skeletons}
        _write_text(tmp / STATE_JSON_FILE, json.dumps(state_doc))
        for name, text in json_texts.items():
            writing = final / f"{name}.json"
            _write_text(tmp / f"{name}.json", text)
        if array_dict is not None:
            writing = final / ARRAYS_FILE
            write_npz(tmp / ARRAYS_FILE, array_dict)
        # meta.json last, with every other file's checksum: a directory with meta.json
        # is a complete checkpoint.
        checksums = {f.name: file_checksum(f) for f in sorted(tmp.iterdir())}
        writing = final / META_FILE
        _write_text(tmp / META_FILE, _meta_text(meta or {}, checksums))
        writing = final
        _fsync_dir(tmp)
        _move_into_place(tmp, target)
    except (OSError, safetensors.SafetensorError) as exc:
        # a full disk, a folder that became read-only: one error naming the file
        shutil.rmtree(tmp, ignore_errors=True)
        raise CheckpointWriteError(writing, write_problem(exc)) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


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


def _collect_weights(
    modules: Mapping[str, torch.nn.Module | Mapping[str, torch.Tensor]],
) -> tuple[dict[str, torch.Tensor], dict[str, list[str]]]:
    raw: dict[str, torch.Tensor] = {}
    module_keys: dict[str, list[str]] = {}
    for name, module in modules.items():
        _check_name(name, "module")
        if "." in name:
            raise CheckpointError(
                f"bad module name {name!r}: expected no '.' (it separates module and "
                f"parameter names in {WEIGHTS_FILE})"
            )
        if isinstance(module, torch.nn.Module):
            params: Mapping[str, Any] = module.state_dict()
        elif isinstance(module, Mapping):
            params = module
        else:
            raise CheckpointError(
                f"cannot save module '{name}': expected an nn.Module or a mapping of "
                f"tensors but found {type(module).__name__}"
            )
        for key, t in params.items():
            if not isinstance(t, torch.Tensor):
                raise CheckpointError(
                    f"cannot save module '{name}': expected a tensor for '{key}' but found "
                    f"{type(t).__name__} (modules with non-tensor extra state are unsupported)"
                )
            raw[f"{name}.{key}"] = t
        module_keys[name] = [str(key) for key in params]
    return _prepare_tensors(raw, "weights"), module_keys


def _collect_states(states: Mapping[str, Any]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    tensors: dict[str, torch.Tensor] = {}
    skeletons: dict[str, Any] = {}
    for name, value in states.items():
        _check_name(name, "state")
        if "." in name:
            raise CheckpointError(
                f"bad state name {name!r}: expected no '.' (it separates the state name from "
                f"the tensor path in {STATE_TENSORS_FILE})"
            )
        # Every tensor name starts with "<name>." and names hold no ".", so none collide.
        flat, skeleton = flatten_state(value, prefix=name)
        tensors.update(flat)
        skeletons[name] = skeleton
    return _prepare_tensors(tensors, "states"), skeletons


def _prepare_tensors(tensors: Mapping[str, torch.Tensor], what: str) -> dict[str, torch.Tensor]:
    """Detach, move to CPU, make contiguous, and give every tensor its own storage."""
    out: dict[str, torch.Tensor] = {}
    seen: set[int] = set()
    for key, t in tensors.items():
        if t.layout != torch.strided:
            raise CheckpointError(
                f"cannot save {what} tensor '{key}': expected a dense (strided) tensor but "
                f"found layout {t.layout}"
            )
        t = t.detach()
        if t.device.type != "cpu":
            t = t.to("cpu")
        t = t.resolve_conj().resolve_neg().contiguous()
        storage = t.untyped_storage()
        ptr = storage.data_ptr()
        if ptr in seen or t.storage_offset() != 0 or storage.nbytes() != t.nbytes:
            t = t.clone()
            ptr = t.untyped_storage().data_ptr()
        seen.add(ptr)
        out[key] = t
    return out


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


def _meta_text(meta: Mapping[str, Any], checksums: Mapping[str, str] | None = None) -> str:
    if not isinstance(meta, Mapping):
        raise CheckpointError(
            f"cannot save meta: expected a mapping but found {type(meta).__name__}"
        )
    reserved = sorted(_RESERVED_META_KEYS & set(meta))
    if reserved:
        raise CheckpointError(
            f"cannot save meta: key {reserved[0]!r} is reserved (it is added automatically)"
        )
    doc = {"format_version": FORMAT_VERSION, **meta, CHECKSUMS_KEY: dict(checksums or {})}
    # the document as it will read back, so that its checksum is that of what is loaded
    doc = json.loads(_json_dumps(doc, META_FILE))
    doc[META_CHECKSUM_KEY] = meta_checksum(doc)
    return _json_dumps(doc, META_FILE)


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


def _json_texts(json_files: Mapping[str, Any]) -> dict[str, str]:
    texts = {}
    for name, doc in json_files.items():
        _check_name(name, "json file")
        if name in _RESERVED_JSON_NAMES:
            raise CheckpointError(
                f"bad json file name {name!r}: expected a name other than "
                f"{', '.join(sorted(_RESERVED_JSON_NAMES))} (reserved)"
            )
        texts[name] = _json_dumps(doc, f"{name}.json")
    return texts


def _collect_arrays(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for name, array in arrays.items():
        _check_name(name, "array")
        if name in _RESERVED_ARRAY_NAMES:
            raise CheckpointError(
                f"bad array name {name!r}: expected a name other than "
                f"{', '.join(sorted(_RESERVED_ARRAY_NAMES))} (np.savez arguments)"
            )
        if not isinstance(array, np.ndarray):
            raise CheckpointError(
                f"cannot save array '{name}': expected a numpy array but found "
                f"{type(array).__name__}"
            )
        if array.dtype.hasobject:
            raise CheckpointError(
                f"cannot save array '{name}': expected a non-object dtype (object arrays "
                f"need pickle) but found dtype {array.dtype}"
            )
        out[name] = array
    return out


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


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------


class Checkpoint:
    """A checkpoint directory opened by :func:`load_checkpoint`; files are read on demand.

    Attributes:
        path: The checkpoint directory.
        meta: The contents of ``meta.json`` (including ``"format_version"``; the
            checksums are in :attr:`checksums`).
        checksums: File name to ``sha256:<hex>`` of every file but ``meta.json``.
    """

    def __init__(
        self, path: Path, meta: dict[str, Any], checksums: Mapping[str, str] | None = None
    ) -> None:
        """Wrap an already validated checkpoint directory; use :func:`load_checkpoint`.

        Args:
            path: The checkpoint directory.
            meta: The parsed ``meta.json``, without its checksums.
            checksums: Every other file's recorded checksum (empty for checkpoints saved
                without them).
        """
        self.path = path
        self.meta = meta
        self.checksums = dict(checksums or {})
        self._skeletons: dict[str, Any] | None = None
        self._verified: set[str] = set()

    def verify(self, filename: str) -> None:
        """Check ``filename``'s bytes against its recorded checksum (once per file; files
        without one, as in older checkpoints, pass).

        Raises:
            CheckpointCorruptError: the bytes differ, naming the file.
        """
        if filename in self._verified:
            return
        expected = self.checksums.get(filename)
        path = self.path / filename
        if expected is not None and path.is_file():
            try:
                found = file_checksum(path)
            except OSError as exc:
                raise CheckpointError(f"cannot read {path}: {exc.strerror or exc}") from exc
            if found != expected:
                raise CheckpointCorruptError(
                    path,
                    "its bytes changed after it was saved (the SHA-256 recorded in "
                    f"{META_FILE} does not match)",
                )
        self._verified.add(filename)

    def verify_all(self) -> None:
        """:meth:`verify` every file the checkpoint recorded a checksum for.

        Raises:
            CheckpointCorruptError: a file differs from its checksum.
            CheckpointError: a recorded file is missing.
        """
        for filename in self.checksums:
            self._require(filename)

    def __repr__(self) -> str:
        return f"Checkpoint({str(self.path)!r})"

    def json(self, name: str) -> Any:
        """Load the JSON document saved as ``json_files[name]``.

        Args:
            name: The document's name (the file is ``<name>.json``).

        Returns:
            The parsed document.

        Raises:
            CheckpointError: If the file is absent or not valid JSON.
        """
        _check_name(name, "json file")
        path = self.path / f"{name}.json"
        if not path.is_file():
            found = sorted(
                p.stem for p in self.path.glob("*.json") if p.stem not in _RESERVED_JSON_NAMES
            )
            raise CheckpointError(
                f"checkpoint {self.path}: expected {name}.json but found no such file "
                f"(json documents: {', '.join(found) or 'none'})"
            )
        self.verify(path.name)
        return _read_json(path)

    def _module_keys(self) -> dict[str, list[str]]:
        path = self._require(WEIGHTS_FILE)
        try:
            with safetensors.safe_open(path, framework="pt") as f:
                metadata = f.metadata() or {}
        except Exception as exc:
            raise _corrupt_safetensors(path, exc) from exc
        try:
            module_keys = json.loads(metadata[_MODULES_METADATA_KEY])
        except (KeyError, json.JSONDecodeError) as exc:
            module_keys = exc
        if not isinstance(module_keys, dict):
            raise CheckpointError(
                f"corrupt {path}: expected a module index under {_MODULES_METADATA_KEY!r} in "
                f"its header metadata but found {_describe(module_keys)}"
            )
        return module_keys

    def weights(self, name: str) -> dict[str, torch.Tensor]:
        """Load the tensors saved for module ``name`` (on CPU).

        Args:
            name: The module's name in ``modules``.

        Returns:
            Parameter names (without the ``"<name>."`` prefix) to tensors, in saved order.

        Raises:
            CheckpointError: If the module was not saved or the file is missing or corrupt.
        """
        module_keys = self._module_keys()
        if name not in module_keys:
            raise CheckpointError(
                f"checkpoint {self.path}: expected module '{name}' but found only "
                f"{', '.join(module_keys) or 'no modules'}"
            )
        path = self._require(WEIGHTS_FILE)
        try:
            with safetensors.safe_open(path, framework="pt") as f:
                available = set(f.keys())
                missing = [k for k in module_keys[name] if f"{name}.{k}" not in available]
                if not missing:
                    return {k: f.get_tensor(f"{name}.{k}") for k in module_keys[name]}
        except Exception as exc:
            raise _corrupt_safetensors(path, exc) from exc
        raise CheckpointError(
            f"corrupt {path}: module '{name}' expected tensors "
            f"{', '.join(missing[:_MAX_LISTED_MISMATCHES])} but they are absent"
        )

    def load_module(
        self, name: str, module: torch.nn.Module, device: torch.device | str | None = None
    ) -> None:
        """Copy module ``name``'s saved weights into ``module`` (strictly).

        Args:
            name: The module's name in ``modules``.
            module: The module to load into; its parameter names and shapes must match the
                checkpoint's exactly.
            device: Where to materialise the loaded tensors before they are copied into the
                module (like ``map_location``); ``None`` means CPU. The module itself is not
                moved: its parameters keep their device and dtype.

        Raises:
            CheckpointError: If names or shapes differ; the message lists up to 5
                mismatches, e.g. ``actor: parameter 'net.0.weight' has shape (256, 30) in the
                checkpoint but (256, 26) in the model``.
        """
        saved = self.weights(name)
        expected = module.state_dict()
        param_names = {n for n, _ in module.named_parameters()}
        problems = []
        for key, t in expected.items():
            kind = "parameter" if key in param_names else "buffer"
            if key not in saved:
                problems.append(f"{name}: {kind} '{key}' is in the model but not in the checkpoint")
            elif isinstance(t, torch.Tensor) and tuple(saved[key].shape) != tuple(t.shape):
                problems.append(
                    f"{name}: {kind} '{key}' has shape {tuple(saved[key].shape)} in the "
                    f"checkpoint but {tuple(t.shape)} in the model"
                )
        problems.extend(
            f"{name}: tensor '{key}' is in the checkpoint but not in the model"
            for key in saved
            if key not in expected
        )
        if problems:
            shown = problems[:_MAX_LISTED_MISMATCHES]
            more = len(problems) - len(shown)
            raise CheckpointError(
                f"cannot load module '{name}' from {self.path}: {len(problems)} mismatch(es): "
                + "; ".join(shown)
                + (f"; and {more} more" if more else "")
            )
        if device is not None:
            saved = {k: v.to(device) for k, v in saved.items()}
        module.load_state_dict(saved, strict=True)

    def _state_skeletons(self) -> dict[str, Any]:
        if self._skeletons is None:
            doc = _read_json(self._require(STATE_JSON_FILE))
            if (
                not isinstance(doc, dict)
                or doc.get("format_version") != FORMAT_VERSION
                or not isinstance(doc.get("states"), dict)
            ):
                raise CheckpointError(
                    f"corrupt {self.path / STATE_JSON_FILE}: expected an object with "
                    f"format_version {FORMAT_VERSION} and 'states' but found "
                    f"{_describe(doc)}"
                )
            self._skeletons = doc["states"]
        return self._skeletons

    def state(self, name: str) -> Any:
        """Rebuild the object saved as ``states[name]``.

        Args:
            name: The state's name in ``states``.

        Returns:
            The structure, with tensors on CPU (see :func:`unflatten_state`).

        Raises:
            CheckpointError: If the state was not saved or its files are missing or corrupt.
        """
        skeletons = self._state_skeletons()
        if name not in skeletons:
            raise CheckpointError(
                f"checkpoint {self.path}: expected state '{name}' but found only "
                f"{', '.join(skeletons) or 'no states'}"
            )
        skeleton = skeletons[name]
        wanted = set(_tensor_names(skeleton))
        path = self._require(STATE_TENSORS_FILE)
        try:
            with safetensors.safe_open(path, framework="pt") as f:
                available = set(f.keys())
                tensors = {key: f.get_tensor(key) for key in wanted & available}
        except Exception as exc:
            raise _corrupt_safetensors(path, exc) from exc
        missing = sorted(wanted - available)
        if missing:
            raise CheckpointError(
                f"corrupt {path}: state '{name}' expected tensors "
                f"{', '.join(missing[:_MAX_LISTED_MISMATCHES])} but they are absent"
            )
        return unflatten_state(tensors, skeleton)

    def has_state(self, name: str) -> bool:
        """Whether ``states[name]`` was saved (older checkpoints may lack newer states, and
        a checkpoint kept with its weights and configs only has no states at all)."""
        if not (self.path / STATE_JSON_FILE).is_file():
            return False
        return name in self._state_skeletons()

    def has_arrays(self) -> bool:
        """Return whether the checkpoint has an ``arrays.npz`` file.

        Returns:
            True if ``arrays`` was given when saving.
        """
        return (self.path / ARRAYS_FILE).is_file()

    def arrays(self) -> dict[str, np.ndarray]:
        """Load every array from ``arrays.npz`` (with ``allow_pickle=False``).

        Returns:
            Array names to arrays.

        Raises:
            CheckpointError: If the file is absent or corrupt.
        """
        path = self._require(ARRAYS_FILE)
        try:
            with np.load(path, allow_pickle=False) as npz:
                return {key: npz[key] for key in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise CheckpointError(
                f"corrupt {path}: expected an npz archive of plain arrays ({exc})"
            ) from exc

    def _require(self, filename: str) -> Path:
        """The path of a file the checkpoint must have, its checksum verified."""
        path = self.path / filename
        if not path.is_file():
            raise CheckpointError(
                f"checkpoint {self.path}: expected {filename} but found no such file"
            )
        self.verify(filename)
        return path


def load_checkpoint(directory: str | Path) -> Checkpoint:
    """Open a checkpoint directory written by :func:`save_checkpoint`.

    Only ``meta.json`` is read now; the other files are read by the accessors.

    Args:
        directory: The checkpoint directory.

    Returns:
        The opened checkpoint.

    Raises:
        CheckpointError: If the directory or ``meta.json`` is missing, ``meta.json`` is not a
            JSON object, or its ``format_version`` is not :data:`FORMAT_VERSION`.
    """
    path = Path(directory)
    if not path.is_dir():
        hint = ""
        absolute = Path(os.path.abspath(path))
        if absolute.parent.is_dir():
            olds = sorted(
                p for p in absolute.parent.iterdir() if p.name.startswith(f".{absolute.name}.old-")
            )
            if olds:
                hint = f" (an interrupted save left the previous checkpoint at {olds[-1]})"
        found = "a file" if path.exists() else "nothing"
        raise CheckpointError(
            f"cannot load checkpoint {path}: expected a directory but found {found}{hint}"
        )
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise CheckpointError(
            f"cannot load checkpoint {path}: expected {META_FILE} but found no such file"
        )
    meta = _read_json(meta_path)
    if not isinstance(meta, dict):
        raise CheckpointError(
            f"corrupt {meta_path}: expected a JSON object but found {_describe(meta)}"
        )
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"unsupported checkpoint {path}: expected format_version {FORMAT_VERSION} in "
            f"{META_FILE} but found {version!r}"
        )
    recorded = meta.pop(META_CHECKSUM_KEY, None)
    if recorded is not None and recorded != meta_checksum(meta):
        raise CheckpointCorruptError(
            meta_path,
            f"its content changed after it was saved (its {META_CHECKSUM_KEY} does not match)",
        )
    checksums = meta.pop(CHECKSUMS_KEY, None)
    if checksums is not None and not (
        isinstance(checksums, dict)
        and all(isinstance(k, str) and isinstance(v, str) for k, v in checksums.items())
    ):
        raise CheckpointError(
            f"corrupt {meta_path}: expected {CHECKSUMS_KEY!r} to map file names to checksums "
            f"but found {_describe(checksums)}"
        )
    return Checkpoint(path, meta, checksums or {})


def seal_checkpoint(directory: str | Path) -> Path:
    """Record the checksums of a checkpoint's files as they are now: for a checkpoint
    written before checksums existed, or one whose files were changed on purpose. Every
    file beside ``meta.json`` is summed and ``meta.json`` is rewritten (atomically) with
    the sums and its own.

    Raises:
        CheckpointError: not a checkpoint (no valid ``meta.json``).
    """
    path = Path(directory)
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise CheckpointError(f"cannot seal {path}: expected {META_FILE} but found no such file")
    meta = _read_json(meta_path)
    if not isinstance(meta, dict):
        raise CheckpointError(f"corrupt {meta_path}: expected a JSON object")
    body = {k: v for k, v in meta.items() if k not in _RESERVED_META_KEYS}
    files = sorted(p for p in path.iterdir() if p.is_file() and p.name != META_FILE)
    text = _meta_text(body, {f.name: file_checksum(f) for f in files})
    tmp = path / f".{META_FILE}.{uuid.uuid4().hex[:12]}.tmp"
    _write_text(tmp, text)
    os.replace(tmp, meta_path)
    _fsync_dir(path)
    return path


def verify_checkpoint(directory: str | Path) -> Checkpoint:
    """Open a checkpoint and verify every file against its checksum now (rather than as
    each is read).

    Raises:
        CheckpointCorruptError: a file's bytes differ from its checksum, naming it.
        CheckpointError: the checkpoint cannot be opened or a file is missing.
    """
    ckpt = load_checkpoint(directory)
    ckpt.verify_all()
    return ckpt


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


def _corrupt_safetensors(path: Path, exc: BaseException) -> CheckpointError:
    message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return CheckpointError(f"corrupt {path}: expected a safetensors file ({message})")


def _tensor_names(node: Any) -> list[str]:
    """Every tensor name a skeleton refers to."""
    names: list[str] = []
    stack = [node]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            if item.get("type") in ("tensor", "ndarray", "npscalar") and isinstance(
                item.get("name"), str
            ):
                names.append(item["name"])
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
    return names


# ----------------------------------------------------------------------------------------------
# latest.json
# ----------------------------------------------------------------------------------------------


def write_latest(run_dir: str | Path, checkpoint_dir: str | Path) -> None:
    """Atomically point ``run_dir/latest.json`` at a checkpoint.

    Writes ``{"checkpoint": <checkpoint_dir relative to run_dir>}`` to a temporary file in
    ``run_dir``, fsyncs it, and renames it over ``latest.json`` with :func:`os.replace`.

    Args:
        run_dir: The run directory (created if missing).
        checkpoint_dir: A checkpoint directory, usually inside ``run_dir``.

    Raises:
        CheckpointError: If ``checkpoint_dir`` is not a checkpoint (no ``meta.json``).
    """
    run = Path(run_dir)
    ckpt = Path(checkpoint_dir)
    if not (ckpt / META_FILE).is_file():
        raise CheckpointError(
            f"cannot point {run / LATEST_FILE} at {ckpt}: expected a checkpoint directory "
            f"with {META_FILE} but found none"
        )
    run.mkdir(parents=True, exist_ok=True)
    try:
        relative = Path(os.path.relpath(ckpt, run)).as_posix()
    except ValueError:  # different drives on Windows
        relative = Path(os.path.abspath(ckpt)).as_posix()
    tmp_name = run / f".{LATEST_FILE}.{uuid.uuid4().hex[:12]}.tmp"
    fd = os.open(tmp_name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # mode subject to umask
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps({"checkpoint": relative}) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp_name, run / LATEST_FILE)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        raise
    _fsync_dir(run)


def find_latest(run_dir: str | Path) -> Path | None:
    """Return the checkpoint that ``run_dir/latest.json`` points at.

    Args:
        run_dir: The run directory.

    Returns:
        The checkpoint path (``run_dir`` joined with the stored relative path), or ``None``
        if ``latest.json`` is absent.

    Raises:
        CheckpointError: If ``latest.json`` exists but is not valid JSON of the form
            ``{"checkpoint": "<path>"}``, or names a checkpoint that does not exist.
    """
    latest = Path(run_dir) / LATEST_FILE
    if not latest.is_file():
        return None
    doc = _read_json(latest)
    if not isinstance(doc, dict) or not isinstance(doc.get("checkpoint"), str):
        raise CheckpointError(
            f'corrupt {latest}: expected {{"checkpoint": "<path>"}} but found {_describe(doc)}'
        )
    path = Path(run_dir) / doc["checkpoint"]
    if not path.is_dir():
        raise CheckpointError(
            f"{latest} points at the checkpoint {doc['checkpoint']!r}, which does not exist "
            f"(deleted or moved?): restore it, or point {LATEST_FILE} at another checkpoint "
            f"of {Path(run_dir) / 'checkpoints'}"
        )
    return path


def remove_stale(run_dir: str | Path) -> list[Path]:
    """Clean up after a process killed while writing a checkpoint of ``run_dir``.

    :func:`save_checkpoint` writes into hidden ``.<name>.tmp-*`` folders and moves a
    replaced checkpoint to ``.<name>.old-*`` until the new one is in place;
    :func:`write_latest` writes ``.latest.json.*.tmp``. A kill between those steps leaves
    them behind. Temporary folders and files are deleted; an ``.old`` folder whose
    checkpoint is missing is the only complete copy and is renamed back, others are deleted.

    Returns:
        The paths removed or restored.
    """
    run = Path(run_dir)
    done: list[Path] = []
    for folder in (run, run / "checkpoints"):
        if not folder.is_dir():
            continue
        for path in sorted(folder.glob(".*")):
            name = path.name
            if ".tmp-" in name or (name.startswith(f".{LATEST_FILE}.") and name.endswith(".tmp")):
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
                done.append(path)
            elif ".old-" in name and path.is_dir():
                original = folder / name[1:].split(".old-")[0]
                if not original.exists() and (path / META_FILE).is_file():
                    os.rename(path, original)
                else:
                    shutil.rmtree(path, ignore_errors=True)
                done.append(path)
    return done

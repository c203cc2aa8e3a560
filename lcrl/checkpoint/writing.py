"""Saving a checkpoint: weights, states, JSON files and arrays into a temporary folder, summed,
then moved into place."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import safetensors.torch
import torch

from lcrl.checkpoint.files import (
    _MODULES_METADATA_KEY,
    _RESERVED_ARRAY_NAMES,
    _RESERVED_JSON_NAMES,
    _RESERVED_META_KEYS,
    ARRAYS_FILE,
    CHECKSUMS_KEY,
    FORMAT_VERSION,
    META_CHECKSUM_KEY,
    META_FILE,
    STATE_JSON_FILE,
    STATE_TENSORS_FILE,
    WEIGHTS_FILE,
    CheckpointError,
    CheckpointWriteError,
    _check_name,
    _fsync_dir,
    _fsync_file,
    _json_dumps,
    _move_into_place,
    _write_text,
    file_checksum,
    meta_checksum,
    write_npz,
    write_problem,
)
from lcrl.checkpoint.state import flatten_state


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


def drop_modules(directory: str | Path, names: tuple[str, ...] | list[str]) -> list[str]:
    """Rewrite a checkpoint's ``weights.safetensors`` without the modules ``names`` (those
    it holds), for a copy that only acts; returns the modules dropped. The file's
    checksum changes: seal the checkpoint again afterwards (``seal_checkpoint``).

    Raises:
        CheckpointError: the folder has no weights file, or one without a module index.
    """
    path = Path(directory) / WEIGHTS_FILE
    if not path.is_file():
        raise CheckpointError(f"{directory} is not a checkpoint: expected {WEIGHTS_FILE}")
    with safetensors.safe_open(str(path), framework="pt") as f:
        index = json.loads((f.metadata() or {}).get(_MODULES_METADATA_KEY, "null"))
        if not isinstance(index, dict):
            raise CheckpointError(f"corrupt {path}: no module index in its header")
        dropped = [n for n in names if n in index]
        kept = {m: keys for m, keys in index.items() if m not in dropped}
        tensors = {f"{m}.{k}": f.get_tensor(f"{m}.{k}") for m, keys in kept.items() for k in keys}
    tmp = path.with_name(f".{path.name}.tmp")
    safetensors.torch.save_file(tensors, tmp, metadata={_MODULES_METADATA_KEY: json.dumps(kept)})
    _fsync_file(tmp)
    os.replace(tmp, path)
    return dropped

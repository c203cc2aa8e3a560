"""Opening a checkpoint: ``meta.json`` at once, every other file when it is asked for, each
checked against its checksum; sealing and verifying."""

from __future__ import annotations

import json
import os
import uuid
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import safetensors.torch
import torch

from lcrl.checkpoint.files import (
    _MAX_LISTED_MISMATCHES,
    _MODULES_METADATA_KEY,
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
    CheckpointCorruptError,
    CheckpointError,
    _check_name,
    _describe,
    _fsync_dir,
    _read_json,
    _write_text,
    file_checksum,
    meta_checksum,
)
from lcrl.checkpoint.state import unflatten_state
from lcrl.checkpoint.writing import _meta_text


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

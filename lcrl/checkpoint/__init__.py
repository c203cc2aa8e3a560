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

from lcrl.checkpoint.files import (
    ARRAYS_FILE as ARRAYS_FILE,
    CHECKSUMS_KEY as CHECKSUMS_KEY,
    FORMAT_VERSION as FORMAT_VERSION,
    LATEST_FILE as LATEST_FILE,
    META_CHECKSUM_KEY as META_CHECKSUM_KEY,
    META_FILE as META_FILE,
    STATE_JSON_FILE as STATE_JSON_FILE,
    STATE_TENSORS_FILE as STATE_TENSORS_FILE,
    WEIGHTS_FILE as WEIGHTS_FILE,
    CheckpointCorruptError as CheckpointCorruptError,
    CheckpointError as CheckpointError,
    CheckpointWriteError as CheckpointWriteError,
    compresses as compresses,
    file_checksum as file_checksum,
    meta_checksum as meta_checksum,
    write_npz as write_npz,
    write_problem as write_problem,
)
from lcrl.checkpoint.latest import (
    find_latest as find_latest,
    remove_stale as remove_stale,
    write_latest as write_latest,
)
from lcrl.checkpoint.reading import (
    Checkpoint as Checkpoint,
    load_checkpoint as load_checkpoint,
    seal_checkpoint as seal_checkpoint,
    verify_checkpoint as verify_checkpoint,
)
from lcrl.checkpoint.state import (
    flatten_state as flatten_state,
    unflatten_state as unflatten_state,
)
from lcrl.checkpoint.writing import (
    drop_modules as drop_modules,
    save_checkpoint as save_checkpoint,
)

__all__ = [
    "FORMAT_VERSION",
    "Checkpoint",
    "CheckpointCorruptError",
    "CheckpointError",
    "CheckpointWriteError",
    "drop_modules",
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

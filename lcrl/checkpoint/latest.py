"""A run's checkpoints over time: ``latest.json``, finding the newest, removing the stale."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import uuid
from pathlib import Path

from lcrl.checkpoint.files import (
    LATEST_FILE,
    META_FILE,
    CheckpointError,
    _describe,
    _fsync_dir,
    _read_json,
)


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

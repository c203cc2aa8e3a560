"""A camera pipeline's parts, kept and taken up again: ``--export-parts`` and ``--parts``.

The perception model and the privileged-state teachers take most of a build's hours and
change least from one student to the next. ``--export-parts DIR`` writes the finished
stages before the student (their records, and their artefacts as weights and configs: no
replay buffers, optimiser state or data files) to a folder of a few MB that can be kept
with the code. ``--parts DIR`` starts a pipeline from such a folder: each stage it holds
is taken as done and its artefacts are copied into ``--out``, except a stage whose data
file a stage still to run reads (``perception-data``, read again by ``perception-ft``),
which runs again. The records keep each stage's seconds, so the build's wall clock still
counts every stage from nothing.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

from lcrl.errors import LcrlError

#: Files a kept part leaves out: data and locks everywhere; a training run's checkpoint
#: also leaves out its state (optimiser, counters), and its TensorBoard events in ``tb/``
#: stay out too. A model folder (perception's) keeps its small state files.
LEFT_OUT = ("arrays.npz", ".lock")
RUN_STATE = ("state.json", "state.safetensors")
#: The first stage that is never a part (it and every stage after it are the student's).
FIRST_NOT_A_PART = "student"


class StageLike(Protocol):
    name: str
    needs: tuple[str, ...]
    outputs: tuple[str, ...]


def _relative(out: Path, path: str) -> Path:
    try:
        return Path(path).resolve().relative_to(out.resolve())
    except ValueError:
        raise LcrlError(f"{path} is outside the pipeline's folder {out}") from None


def _copy_run(src: Path, dest: Path) -> None:
    """A run or model folder without its data: a training run keeps only the checkpoint
    its ``latest.json`` names."""
    latest = src / "latest.json"
    keep = None
    if latest.is_file():
        keep = json.loads(latest.read_text())["checkpoint"]
    for f in sorted(src.rglob("*")):
        rel = f.relative_to(src)
        if f.is_dir() or f.name in LEFT_OUT or f.suffix == ".h5" or rel.parts[0] == "tb":
            continue
        if keep is not None and f.name in RUN_STATE:
            continue
        earlier = rel.parts[0] == "checkpoints" and not str(rel).startswith(f"{keep}/")
        if keep is not None and earlier:
            continue  # an earlier checkpoint
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, dest / rel)
    if keep is not None and (dest / keep / "meta.json").is_file():
        from lcrl.checkpoint import seal_checkpoint

        seal_checkpoint(dest / keep)  # its checksums name the files it now has


def export_parts(out: Path, every: Sequence[StageLike], dest: Path) -> list[str]:
    """Write the finished stages before the student (records and artefacts, no data) to
    ``dest``; the names of the stages written."""
    out, dest = out.resolve(), dest.resolve()
    if dest == out or out.is_relative_to(dest) or dest.is_relative_to(out):
        raise LcrlError(f"--export-parts {dest}: give a folder outside the build's {out}")
    if dest.exists() and not (dest / "stages").is_dir():
        raise LcrlError(f"--export-parts {dest}: the folder exists and holds no parts")
    names = [s.name for s in every]
    cut = names.index(FIRST_NOT_A_PART) if FIRST_NOT_A_PART in names else len(names)
    written = []
    tmp = dest.with_name(f".{dest.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "stages").mkdir(parents=True)
    for stage in every[:cut]:
        record = out / "stages" / f"{stage.name}.json"
        if not record.is_file():
            continue
        for path in stage.outputs:
            src = Path(path)
            if src.is_dir():
                _copy_run(src, tmp / _relative(out, path))
        shutil.copy2(record, tmp / "stages" / record.name)
        written.append(stage.name)
    if not written:
        shutil.rmtree(tmp)
        raise LcrlError(f"{out} has no finished stage before the student to export")
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return written


def check_parts(parts: Path) -> None:
    """Refuse a folder that holds no parts."""
    if not (parts / "stages").is_dir():
        raise LcrlError(f"--parts {parts}: no stages/ folder (write one with --export-parts)")


def import_parts(
    out: Path, every: Sequence[StageLike], parts: Path, unused: Sequence[str] = ()
) -> list[str]:
    """Take up the stages that ``parts`` holds and ``out`` has not finished: copy their
    artefacts into ``out`` and their records; the names taken up. A stage whose output is
    not in ``parts`` while a stage still to run needs it is left to run again; the stages
    named in ``unused`` (those of a camera build, for a student of the state) are left
    where they are."""
    check_parts(parts)
    held = {f.stem: f for f in (parts / "stages").glob("*.json") if f.stem not in unused}
    known = {s.name for s in every}
    unknown = sorted(set(held) - known)
    if unknown:
        raise LcrlError(f"--parts {parts} holds stages this pipeline does not have: {unknown}")
    done = {s.name for s in every if (out / "stages" / f"{s.name}.json").is_file()}
    taken: list[str] = []
    pending = [s for s in every if s.name not in held and s.name not in done]
    needed = {_relative(out, n.rpartition("<")[0]) for s in pending for n in s.needs}
    for stage in every:
        if stage.name not in held or stage.name in done:
            continue
        rels = [_relative(out, p) for p in stage.outputs]
        if any(r in needed and not (parts / r).exists() for r in rels):
            continue  # its data file is read again later: it runs again
        for r in rels:
            if (parts / r).is_dir():
                shutil.rmtree(out / r, ignore_errors=True)
                shutil.copytree(parts / r, out / r)
        (out / "stages").mkdir(parents=True, exist_ok=True)
        record: dict[str, Any] = json.loads(held[stage.name].read_text())
        record["from_parts"] = str(parts)
        (out / "stages" / f"{stage.name}.json").write_text(json.dumps(record, indent=1))
        taken.append(stage.name)
    return taken


__all__ = ["check_parts", "export_parts", "import_parts"]

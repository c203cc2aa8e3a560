"""Corrupt checkpoints and outputs that cannot be written end in one clear line.

Checkpoint files are really edited or removed; outputs really fail: a file where a folder
should be, a read-only file system and a full one (small tmpfs mounts where this machine
allows them, else a writer that fails as a full disk does).
"""

from __future__ import annotations

import errno
import json
import re
import shutil
import subprocess
import uuid
from pathlib import Path

import pytest
from helpers import cli, error_line

import lcrl
from lcrl.checkpoint import (
    CheckpointCorruptError,
    CheckpointError,
    find_latest,
    load_checkpoint,
    seal_checkpoint,
)

TINY = [
    "--learning-starts", "50",
    "--batch-size", "16",
    "--eval-every", "0",
    "--eval-episodes", "2",
    "--checkpoint-every", "0",
    "--log-every", "50",
    "--buffer.capacity", "2000",
    "--agent.net.hidden", "16", "16",
    "--collect.envs", "1",  # one environment: checkpoints land on the steps named
    "--no-progress",
    "--no-tensorboard",
]  # fmt: skip


@pytest.fixture(scope="module")
def state_run(tmp_path_factory) -> Path:
    """A finished 100-step state2d run."""
    out = tmp_path_factory.mktemp("state") / "run"
    assert cli("train", "state2d", "--out", str(out), "--total-steps", "100", *TINY) == 0
    return out


@pytest.fixture
def copy_run(state_run, tmp_path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(state_run, out)
    return out


def edit_meta(run: Path, change) -> Path:
    """Change a checkpoint's meta.json and record the change in its checksums (a writer's
    mistake, not a corruption on disk: the fields themselves are what is checked)."""
    path = find_latest(run) / "meta.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))
    seal_checkpoint(path.parent)
    return path


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda m: m.pop("algo"), "'algo'"),
        (lambda m: m.update(algo="ppo"), "'algo' is 'ppo'"),
        (lambda m: m.update(step="many"), "'step'"),
        (lambda m: m.update(config=[1, 2]), "'config'"),
        (lambda m: m["config"].update(env=7), "'config.env' should be an object, not int 7"),
        (
            lambda m: m["config"]["agent"]["net"].update(hidden="big"),
            "'config.agent.net.hidden' should be a list of integers, not str 'big'",
        ),
        (
            lambda m: m["config"]["buffer"].update(k=2.5),
            "'config.buffer.k' should be an integer, not float 2.5",
        ),
        (
            lambda m: m["config"]["env"].update(discrete="no"),
            "'config.env.discrete' should be true or false, not str 'no'",
        ),
        (
            lambda m: m["config"]["sac"].update(max_grad_norm=[1]),
            "'config.sac.max_grad_norm' should be a number or null, not list [1]",
        ),
        (lambda m: m["problem"].pop("goal_kind"), "'problem.goal_kind' is missing"),
        (
            lambda m: m["problem"].update(action_dim="3"),
            "'problem.action_dim' should be a positive integer, not str '3'",
        ),
        (
            lambda m: m["problem"].update(goal_shape=["3"]),
            "'problem.goal_shape' should be a list of integers, not list ['3']",
        ),
        (
            lambda m: m["problem"].update(discrete=0),
            "'problem.discrete' should be true or false, not int 0",
        ),
        (lambda m: m["problem"].update(goal_kind="smell"), "'problem.goal_kind' should be one"),
        (lambda m: m.pop("problem"), "'problem'"),
        (lambda m: m.update(eval_pending="yes"), "'eval_pending' should be true or false"),
    ],
)
def test_bad_meta_fields_name_the_file_and_the_field(copy_run, capsys, change, field):
    meta = edit_meta(copy_run, change)
    assert cli("eval", str(copy_run), "--episodes", "1", "--no-progress") == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith("lcrl: error:") and str(meta) in line and field in line
    with pytest.raises(CheckpointError, match=re.escape(field)):
        lcrl.load(copy_run)
    assert resume(copy_run) == 2
    line = error_line(capsys.readouterr().err)
    assert str(meta) in line and field in line


def resume(run: Path) -> int:
    return cli("train", "state2d", "--out", str(run), "--resume", "--total-steps", "200")


def edit_state(run: Path, name: str, change) -> Path:
    """Edit the JSON skeleton of one state in state.json (a dict node: ``items`` of
    ``[key, value]`` pairs)."""
    path = find_latest(run) / "state.json"
    doc = json.loads(path.read_text())
    change(doc["states"][name])
    path.write_text(json.dumps(doc))
    seal_checkpoint(path.parent)
    return path


def drop(key):
    return lambda node: node.update(items=[kv for kv in node["items"] if kv[0] != key])


def set_item(key, value):
    return lambda node: node.update(items=[[k, value if k == key else v] for k, v in node["items"]])


@pytest.mark.parametrize(
    ("name", "change", "message"),
    [
        ("trainer", drop("credit"), "the field 'trainer.credit' is missing"),
        ("trainer", set_item("episodes", "7"), "'trainer.episodes' should be an integer >= 0"),
        ("trainer", set_item("recent", "none"), "'trainer.recent' should be a list of numbers"),
        ("counters", drop("updates"), "the field 'updates' of the learner's states is missing"),
        ("trainer_rng", drop("state"), "the field 'state' of the state 'trainer_rng' is missing"),
        ("trainer_rng", set_item("bit_generator", "MT19937"), "'trainer_rng' cannot be restored"),
    ],
)
def test_bad_state_fields_name_the_file_and_the_field(copy_run, capsys, name, change, message):
    path = edit_state(copy_run, name, change)
    assert resume(copy_run) == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith(f"lcrl: error: {path}: ") and message in line


def test_latest_json_naming_a_missing_checkpoint(copy_run, capsys):
    shutil.rmtree(find_latest(copy_run))
    for args in (("train", "state2d", "--out", str(copy_run), "--resume"), ("eval", str(copy_run))):
        assert cli(*args) == 2
        line = error_line(capsys.readouterr().err)
        assert "latest.json points at the checkpoint 'checkpoints/step_000000100'" in line
        assert "does not exist" in line


def test_out_that_is_a_file_and_json_that_is_a_folder(state_run, tmp_path, capsys):
    file = tmp_path / "a-file"
    file.write_text("x")
    assert cli("train", "state2d", "--out", str(file), *TINY) == 2
    line = error_line(capsys.readouterr().err)
    assert line == f"lcrl: error: --out {file} is a file, not a folder: choose another --out"
    assert cli("eval", str(state_run), "--episodes", "1", "--json", str(tmp_path)) == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith(f"lcrl: error: --json {tmp_path} is a folder")


@pytest.fixture
def small_fs(tmp_path):
    """Mount a 2 MB tmpfs (read-write) at a fresh folder; yields a function that remounts
    it read-only. Skipped where mounting is not allowed."""
    where = tmp_path / f"fs-{uuid.uuid4().hex[:6]}"
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(where)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")

    def read_only() -> None:
        subprocess.run(["mount", "-o", "remount,ro", str(where)], check=True)

    yield where, read_only
    subprocess.run(["umount", "-l", str(where)], check=False)


def test_out_inside_a_read_only_folder(small_fs, capsys):
    where, read_only = small_fs
    read_only()
    out = where / "runs" / "x"
    assert cli("train", "state2d", "--out", str(out), *TINY) == 2
    line = error_line(capsys.readouterr().err)
    assert line == f"lcrl: error: cannot write the run folder {out}: Read-only file system"


def test_a_full_disk_keeps_the_previous_checkpoint(small_fs, capsys):
    """A real 2 MB file system: the first checkpoint fits, the replay buffer of the next
    does not."""
    where, _ = small_fs
    out = where / "run"
    args = ["train", "state2d", "--out", str(out), "--total-steps", "100", *TINY]
    assert cli(*args) == 0
    first = find_latest(out)
    filler = where / "filler"
    free = shutil.disk_usage(where).free
    filler.write_bytes(b"\0" * max(free - 64 * 1024, 0))  # leave 64 kB: too little
    capsys.readouterr()
    assert resume(out) == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith("lcrl: error: cannot write a checkpoint at step 200")
    assert "No space left on device" in line
    assert f"the previous checkpoint {first} is kept" in line
    assert find_latest(out) == first and load_checkpoint(first).meta["step"] == 100
    assert not list((out / "checkpoints").glob(".*"))  # the half-written folder is gone


def test_a_failing_writer_keeps_the_previous_checkpoint(copy_run, capsys, monkeypatch):
    """The same, on any machine: the replay buffer's write fails as a full disk does."""
    from numpy.lib import format as npy_format

    first = find_latest(copy_run)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(npy_format, "write_array", full)
    assert resume(copy_run) == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith("lcrl: error: cannot write a checkpoint at step 200")
    assert "No space left on device" in line and str(first) in line
    assert find_latest(copy_run) == first
    assert not list((copy_run / "checkpoints").glob(".*"))
    monkeypatch.undo()
    assert resume(copy_run) == 0  # space again: the run goes on from the kept checkpoint
    assert load_checkpoint(find_latest(copy_run)).meta["step"] == 200


def fill(where: Path) -> None:
    """Fill the file system at ``where`` to the last byte."""
    with (where / "filler").open("wb") as f:
        try:
            f.write(b"\0" * (shutil.disk_usage(where).free + 65536))
            f.flush()
        except OSError:
            pass  # full
    assert shutil.disk_usage(where).free == 0


def test_a_full_disk_during_the_weights_write(small_fs, capsys):
    """A real file system filled to the last byte: the logs still append into their last
    block, and the first write that needs space is the weights' (safetensors)."""
    where, _ = small_fs
    out = where / "run"
    args = ["train", "state2d", "--out", str(out), "--total-steps", "100", *TINY]
    assert cli(*args) == 0
    first = find_latest(out)
    fill(where)
    capsys.readouterr()
    assert resume(out) == 2
    line = error_line(capsys.readouterr().err)
    step = out / "checkpoints" / "step_000000200"
    assert line == (
        f"lcrl: error: cannot write a checkpoint at step 200 in {step}/weights.safetensors: "
        f"No space left on device; the previous checkpoint {first} is kept (latest.json "
        "points at it)"
    )
    assert find_latest(out) == first and load_checkpoint(first).meta["step"] == 100
    assert not list((out / "checkpoints").glob(".*"))


@pytest.mark.parametrize(("call", "name"), [(0, "weights.safetensors"), (1, "state.safetensors")])
def test_a_failing_safetensors_write_keeps_the_previous_checkpoint(
    copy_run, capsys, monkeypatch, call, name
):
    """safetensors reports a full disk as its own error, not an OSError: the weights'
    write (or the state's) fails as it does on a full disk."""
    import safetensors
    import safetensors.torch

    first = find_latest(copy_run)
    write = safetensors.torch.save_file
    calls = []

    def full(*args, **kwargs):
        calls.append(args[1])
        if len(calls) == call + 1:
            raise safetensors.SafetensorError(
                "Error while serializing: I/O error: No space left on device (os error 28)"
            )
        return write(*args, **kwargs)

    monkeypatch.setattr(safetensors.torch, "save_file", full)
    assert resume(copy_run) == 2
    line = error_line(capsys.readouterr().err)
    where = copy_run / "checkpoints" / "step_000000200" / name
    assert line == (
        f"lcrl: error: cannot write a checkpoint at step 200 in {where}: No space left on "
        f"device; the previous checkpoint {first} is kept (latest.json points at it)"
    )
    assert find_latest(copy_run) == first
    assert json.loads((copy_run / "latest.json").read_text())["checkpoint"] == (
        "checkpoints/step_000000100"
    )
    assert not list((copy_run / "checkpoints").glob(".*"))
    monkeypatch.undo()
    assert resume(copy_run) == 0
    assert load_checkpoint(find_latest(copy_run)).meta["step"] == 200


def test_a_full_disk_under_the_progress_log_names_it(tmp_path, capsys):
    """progress.csv on a real file system with no space left (a 4 kB tmpfs, linked into
    the run folder): the error names the file."""
    where = tmp_path / f"fs-{uuid.uuid4().hex[:6]}"
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=4k", "tmpfs", str(where)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        (where / "progress.csv").touch()
        fill(where)
        out = tmp_path / "run"
        out.mkdir()
        (out / "progress.csv").symlink_to(where / "progress.csv")
        assert cli("train", "state2d", "--out", str(out), "--total-steps", "100", *TINY) == 2
        line = error_line(capsys.readouterr().err)
        assert line == f"lcrl: error: cannot write {out / 'progress.csv'}: No space left on device"
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_json_below_a_file_fails_before_the_evaluation(state_run, tmp_path, capsys, monkeypatch):
    import train.evaluation.eval_suite

    def never(*args, **kwargs):
        raise AssertionError("the evaluation ran")

    monkeypatch.setattr(train.evaluation.eval_suite, "run_evaluation", never)
    file = tmp_path / "a-file"
    file.write_text("x")
    target = file / "x.json"
    assert cli("eval", str(state_run), "--episodes", "1", "--json", str(target)) == 2
    captured = capsys.readouterr()
    assert error_line(captured.err) == (
        f"lcrl: error: --json {target} cannot be written: {file} is a file, not a folder"
    )
    assert "checkpoint" not in captured.out  # nothing was loaded or run
    out = file / "evaluation"
    assert cli("eval", str(state_run), "--episodes", "1", "--out", str(out)) == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith(f"lcrl: error: cannot write the evaluation folder {out}: ")


def flip(path: Path, count: int = 4) -> None:
    """Flip ``count`` bytes in the middle of a file: same size, header untouched."""
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    for i in range(mid, mid + count):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def test_flipped_bytes_in_the_weights_are_caught_by_eval_act_and_load(copy_run, capsys):
    weights = find_latest(copy_run) / "weights.safetensors"
    flip(weights)
    for args in (
        ("eval", str(copy_run), "--episodes", "1", "--no-progress"),
        ("act", str(copy_run), "--episodes", "1"),
    ):
        assert cli(*args) == 2
        line = error_line(capsys.readouterr().err)
        assert line.startswith("lcrl: error: corrupt checkpoint file") and str(weights) in line
    with pytest.raises(CheckpointCorruptError, match=re.escape(str(weights))):
        lcrl.load(copy_run)


def test_a_changed_value_in_meta_json_is_caught(copy_run, capsys):
    """Valid JSON with one value changed (a bit flipped in a digit) is still caught."""
    path = find_latest(copy_run) / "meta.json"
    text = path.read_text()
    path.write_text(text.replace('"step": 100', '"step": 900', 1))
    assert cli("eval", str(copy_run), "--episodes", "1", "--no-progress") == 2
    line = error_line(capsys.readouterr().err)
    assert f"corrupt checkpoint file {path}" in line and "content changed" in line


def test_resume_falls_back_to_the_newest_intact_checkpoint_and_keeps_the_corrupt_one(
    tmp_path, capsys
):
    out = tmp_path / "run"
    args = ["train", "state2d", "--out", str(out), *TINY, "--checkpoint-every", "100"]
    assert cli(*args, "--total-steps", "300", "--keep-checkpoints", "3") == 0
    latest = find_latest(out)
    assert latest.name == "step_000000300"
    flip(latest / "arrays.npz")  # the replay buffer: only a resume reads it
    assert cli("eval", str(out), "--episodes", "1", "--no-progress") == 0  # acting is fine
    capsys.readouterr()
    assert cli("train", "state2d", "--out", str(out), "--resume", "--total-steps", "400") == 0
    err = capsys.readouterr().err
    assert f"corrupt checkpoint file {latest / 'arrays.npz'}" in err
    assert "resuming from the newest intact checkpoint" in err and "step_000000200" in err
    kept = latest.with_name("step_000000300.corrupt")
    assert kept.is_dir() and (kept / "arrays.npz").is_file()  # never deleted
    assert find_latest(out).name == "step_000000400"
    steps = [int(r.split(",")[0]) for r in (out / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 400  # cut back to 200, then on


def test_resume_with_every_checkpoint_corrupt_says_so(copy_run, capsys):
    latest = find_latest(copy_run)
    flip(latest / "state.safetensors")
    assert resume(copy_run) == 2
    line = error_line(capsys.readouterr().err)
    assert f"corrupt checkpoint file {latest / 'state.safetensors'}" in line
    assert "no other intact checkpoint" in line
    assert latest.is_dir()


def test_checkpoints_without_checksums_still_load(copy_run):
    """Checkpoints saved before checksums existed (the meta has none) load unverified."""
    path = find_latest(copy_run) / "meta.json"
    meta = json.loads(path.read_text())
    meta.pop("checksums"), meta.pop("meta_checksum")
    path.write_text(json.dumps(meta))
    flip(path.parent / "weights.safetensors", 0)
    assert lcrl.load(copy_run).checkpoint.checksums == {}

"""Memory known up front: buffers are estimated before they are allocated, and a run whose
buffer the machine cannot hold is refused in one line (from the command line and from a
saved config alike)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import cli, error_line

from lcrl.buffer import HindsightReplayBuffer
from lcrl.checkpoint import find_latest, seal_checkpoint
from lcrl.errors import LcrlError
from lcrl.goals import ImageGoals, LabelGoals, StateGoals, TaskGoals
from train.runtime.memory import WARN_SHARE, check_memory, fmt_bytes

TINY = ["--total-steps", "100", "--learning-starts", "50", "--batch-size", "16"]
TINY += ["--eval-episodes", "1", "--eval-every", "0", "--no-progress", "--no-tensorboard"]
TINY += ["--agent.net.hidden", "16", "16"]


def allocated(buffer: HindsightReplayBuffer) -> int:
    """Every array a buffer and its goal space hold, in bytes (an array both refer to,
    the frames image goals read, once)."""
    seen: dict[int, int] = {}
    for owner in (buffer, buffer.goal_space):
        for value in vars(owner).values():
            arrays = value.values() if isinstance(value, dict) else [value]
            seen.update((id(a), a.nbytes) for a in arrays if isinstance(a, np.ndarray))
    return sum(seen.values())


def reward(a, d):
    return (np.linalg.norm(a - d, axis=-1) < 0.05).astype(np.float32)


@pytest.mark.parametrize(
    "goal_space",
    [
        StateGoals(3, reward),
        LabelGoals(40, np.zeros((40, 8), np.float32)),
        TaskGoals(5),
        ImageGoals(3, reward, (16, 16, 3)),
    ],
    ids=["state", "label", "task", "image"],
)
def test_the_estimate_is_what_the_buffer_allocates(goal_space) -> None:
    spec = {"observation": ((7,), np.float32), "image": ((16, 16, 3), np.uint8)}
    args = (500, spec, (2,), np.float32, goal_space)
    need = HindsightReplayBuffer.estimate_bytes(*args)
    k = 0 if goal_space.kind == "task" else 4
    buffer = HindsightReplayBuffer(*args, k=k)
    assert need == allocated(buffer)


def test_check_memory_refuses_above_and_warns_near_what_is_available(capsys) -> None:
    gib = 2**30
    check_memory(gib, "the thing", "--thing.size", 1000, available=4 * gib)
    assert capsys.readouterr().err == ""
    check_memory(int(3.5 * gib), "the thing", "--thing.size", 1000, available=4 * gib)
    warning = capsys.readouterr().err
    assert warning.startswith("lcrl: warning: the thing will take 3.5 GiB of the 4.0 GiB")
    with pytest.raises(LcrlError) as e:
        check_memory(5 * gib, "the thing", "--thing.size", 1000, available=4 * gib)
    fit = int(WARN_SHARE * 4 * gib // 1000)
    assert str(e.value) == (
        "the thing needs 5.0 GiB, more than the 4.0 GiB this machine has available: lower "
        f"--thing.size (about {fit:,} slots fit comfortably)"
    )
    assert fmt_bytes(1536) == "1.5 KiB"


def test_an_oversized_buffer_is_refused_in_one_line(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    args = ["train", "state2d", "--out", str(out), *TINY, "--buffer.capacity", "400000000"]
    assert cli(*args) == 2
    err = capsys.readouterr().err
    line = error_line(err)
    assert line.startswith("lcrl: error: the replay buffer (400,000,000 slots of ")
    assert "more than the" in line and "lower --buffer.capacity (about" in line
    assert "Traceback" not in err and not (out / "progress.csv").exists()
    assert cli("train", "state2d", "--out", str(out), *TINY, "--buffer.capacity", "1") == 2
    assert "buffer.capacity must be at least 2 slots" in error_line(capsys.readouterr().err)


def test_a_saved_config_is_checked_as_the_command_line_is(tmp_path, capsys) -> None:
    """--resume reads the buffer's size from the checkpoint: an oversized one is refused
    the same way, and an invalid one is named."""
    out = tmp_path / "run"
    assert cli("train", "state2d", "--out", str(out), *TINY, "--buffer.capacity", "2000") == 0
    meta = find_latest(out) / "meta.json"
    doc = json.loads(meta.read_text())
    doc["config"]["buffer"]["capacity"] = 400_000_000
    meta.write_text(json.dumps(doc))
    seal_checkpoint(meta.parent)
    capsys.readouterr()
    resume = ["train", "state2d", "--out", str(out), "--resume", "--total-steps", "200"]
    assert cli(*resume) == 2
    assert "the replay buffer (400,000,000 slots of " in error_line(capsys.readouterr().err)
    doc["config"]["buffer"]["capacity"] = 1
    meta.write_text(json.dumps(doc))
    seal_checkpoint(meta.parent)
    assert cli(*resume) == 2
    line = error_line(capsys.readouterr().err)
    assert "buffer.capacity must be at least 2 slots" in line and str(meta) in line

"""Policies trained apart acting as the mean of their actions (``lcrl ensemble``), at a tiny
size: the folder acts and evaluates like any checkpoint, its action is the members' mean,
and members that cannot act beside each other are refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import cli, error_line, train_tiny, untrained_perception

import lcrl


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


def _train(out: Path, seed: int = 0, steps: int = 200, **env) -> Path:
    return train_tiny(out, "lang2d-quick", seed, steps, **env)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ensemble")
    return {"a": _train(root / "a"), "b": _train(root / "b", seed=1), "root": root}


def test_the_ensemble_acts_as_the_mean_of_its_members(runs, tmp_path):
    out = runs["root"] / "ens"
    assert cli("ensemble", str(out), str(runs["a"]), str(runs["b"])) == 0
    meta = json.loads((out / "meta.json").read_text())["ensemble"]
    assert meta["members"] == ["members/1"] and len(meta["sources"]) == 2
    assert not (out / "arrays.npz").exists()  # no replay buffer

    ens, a, b = lcrl.load(out), lcrl.load(runs["a"]), lcrl.load(runs["b"])
    obs, _ = ens.make_env().reset(seed=3)
    for text in ("reach the red cube", "push the blue ball left"):
        for p in (ens, a, b):
            p.reset()
        want = (a.act(obs, text) + b.act(obs, text)) / 2
        got = ens.act(obs, text)
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert not np.allclose(a.act(obs, text), b.act(obs, text))  # the members differ
    # a batch: each row its own mean
    batch = {k: np.stack([v, v]) for k, v in obs.items() if isinstance(v, np.ndarray)}
    ens.reset()
    rows = ens.act(batch, ["reach the red cube", "push the blue ball left"])
    assert rows.shape[0] == 2 and not np.allclose(rows[0], rows[1])

    report = tmp_path / "eval.json"
    args = ["eval", str(out), "--episodes", "2", "--sets", "train", "--no-progress"]
    assert cli(*args, "--json", str(report)) == 0
    assert json.loads(report.read_text())["sets"]["train"]["episodes"] == 2


def test_members_that_cannot_act_together_get_one_line(runs, tmp_path, capsys):
    root = runs["root"]
    a, b = str(runs["a"]), str(runs["b"])
    other = _train(root / "no-disp", displacements=False)
    ens = root / "ens2"
    assert cli("ensemble", str(ens), a, b) == 0
    out = str(tmp_path / "e")
    cases = [
        ([a], "name at least two runs to average, got 1"),
        ([a, a], "a run is named twice"),
        ([a, str(other)], "members must read the same observation features"),
        ([a, str(ens)], "is itself an ensemble or routed"),
        ([str(ens), a], "is itself an ensemble or routed"),
        ([a, str(root / "nothing")], "no checkpoint or run folder"),
    ]
    for members, message in cases:
        assert cli("ensemble", out, *members) == 2, members
        line = error_line(capsys.readouterr().err)
        assert line.startswith("lcrl: error:") and message in line, line
    assert not Path(out).exists()
    assert cli("ensemble", str(ens), a, b) == 2
    assert "already exists" in error_line(capsys.readouterr().err)
    assert cli("ensemble", a, a, b, "--overwrite") == 2  # would delete a member it copies
    assert "which it is made from" in error_line(capsys.readouterr().err)
    assert (Path(a) / "latest.json").is_file()


def test_camera_members_must_read_one_estimate(runs, tmp_path, capsys):
    root = runs["root"]
    seen = untrained_perception(root / "perception-0", seed=0)
    other = untrained_perception(root / "perception-1", seed=1)
    x = _train(root / "px", steps=80, perception=str(seen))
    y = _train(root / "py", seed=1, steps=80, perception=str(seen))
    z = _train(root / "pz", seed=2, steps=80, perception=str(other))
    held = _train(root / "ph", seed=3, steps=80, perception=str(seen), perception_hold_radius=0.0)
    out = root / "pens"
    assert cli("ensemble", str(out), str(x), str(y)) == 0
    policy = lcrl.load(out)
    obs, _ = policy.make_env().reset(seed=0)
    frames = {"image": obs["image"], "proprio": obs["privileged"][:2]}
    assert policy.act(frames, "reach the red cube").shape == (2,)
    for member, message in ((z, "perception from"), (held, "held at 0.0")):
        assert cli("ensemble", str(tmp_path / "bad"), str(x), str(member)) == 2
        line = error_line(capsys.readouterr().err)
        assert "members must read one estimate" in line and message in line, line
    # a state policy reads the same features, from the simulator instead of the frames
    assert cli("ensemble", str(tmp_path / "bad"), str(x), str(runs["a"])) == 2
    assert "acts through the simulator's state" in error_line(capsys.readouterr().err)

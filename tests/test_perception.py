"""Perception learns to read object slots from a few hundred rendered 2D-tabletop frames,
through the real commands (collect, train, eval) and files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import cli, error_line

from lcrl.errors import LcrlError
from lcrl.perception import Perception, SlotLayout, fit_stats
from train.perception import evaluate, load_model, read_dataset


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """160 short episodes (160 layouts, about 950 frames) of the 2D tabletop."""
    path = tmp_path_factory.mktemp("perception") / "frames.h5"
    args = ["perception", "collect", "--env", "lang2d", "--episodes", "160"]
    args += ["--max-episode-steps", "5", "--out", str(path), "--no-progress"]
    assert cli(*args) == 0
    return path


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("perception") / "model"
    args = ["perception", "train", "--data", str(dataset), "--out", str(out)]
    args += ["--steps", "500", "--heldout-fraction", "0.15", "--no-progress"]
    assert cli(*args) == 0
    return out


def test_the_dataset_holds_the_privileged_state(dataset):
    data, meta = read_dataset(str(dataset))
    layout = SlotLayout.of(meta["slot_layout"])
    assert (layout.start, layout.count, layout.width) == (2, 8, 3)
    assert data.state.shape == (len(data.frames), layout.dim)
    np.testing.assert_array_equal(data.state[:, :2], data.proprio)
    _, _, present = layout.split(data.state)
    assert (present.sum(1) >= 2).all()  # every frame shows its 2 or 3 objects


def test_perception_learns_against_the_mean_and_majority(trained, dataset):
    model, meta = load_model(trained)
    held = np.asarray(meta["heldout_episodes"])
    data, _ = read_dataset(str(dataset), held)
    layout = model.layout
    learned = evaluate(model, data, layout)

    # the baseline: every object at its mean training position, the majority presence
    train_eps = np.setdiff1d(np.arange(160), held)
    train_data, _ = read_dataset(str(dataset), train_eps)
    stats = fit_stats(layout, train_data.state)
    _, pos, present = layout.split(data.state)
    _, _, train_present = layout.split(train_data.state)
    base_err = np.linalg.norm(pos - stats["pos_mean"], axis=-1)[present].mean() * 100
    base_presence = (present == (train_present.mean(0) > 0.5)).mean()
    print(f"perception {learned['position_error_cm']:.2f} cm vs mean {base_err:.2f} cm")
    assert learned["position_error_cm"] < 0.8 * base_err
    assert learned["presence_accuracy"] > base_presence
    saved = json.loads((trained / "eval.json").read_text())["heldout_episodes"]
    assert saved["position_error_cm"] == pytest.approx(learned["position_error_cm"])


def test_the_estimate_has_the_observation_layout(trained, dataset):
    model, _ = load_model(trained)
    data, _ = read_dataset(str(dataset), np.arange(3))
    est = model.observation(data.frames, data.proprio)
    assert est.shape == data.state.shape
    np.testing.assert_array_equal(est[:, :2], data.proprio)  # proprioception passes through
    _, pos, present = model.layout.split(est)
    assert set(np.unique(present)) <= {True, False}
    assert (pos[~present] == 0).all()  # absent objects sit at 0, as the env writes them


def test_eval_command_and_wrong_inputs(trained, dataset, capsys, tmp_path):
    out = tmp_path / "e.json"
    assert cli("perception", "eval", str(trained), "--json", str(out)) == 0
    assert "held-out episodes: position error" in capsys.readouterr().out
    assert json.loads(out.read_text())["frames"] > 0
    model, _ = load_model(trained)
    with pytest.raises(LcrlError, match=r"frames of shape \(84, 84, 3\): this perception model"):
        model(torch.zeros(1, 84, 84, 3, dtype=torch.uint8), torch.zeros(1, 2))
    assert cli("perception", "train", "--data", str(tmp_path / "none.h5")) == 2
    assert "no dataset at" in error_line(capsys.readouterr().err)


def test_a_dataset_without_state_is_refused(tmp_path, capsys):
    from captioner.dataset import CaptionDatasetWriter

    path = tmp_path / "old.h5"
    writer = CaptionDatasetWriter(path, ["reach the red cube"], ["train"], (8, 8, 3), 2, {})
    writer.add_episode(np.zeros((2, 8, 8, 3), np.uint8), np.zeros((2, 2)), [[], []], "random")
    writer.add_episode(np.zeros((2, 8, 8, 3), np.uint8), np.zeros((2, 2)), [[], []], "random")
    writer.close()
    assert cli("perception", "train", "--data", str(path)) == 2
    assert "holds no privileged observations" in error_line(capsys.readouterr().err)


def test_perception_statistics_ignore_absent_objects():
    layout = SlotLayout(1, 2, 3, 2)
    state = np.array([[0.5, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0], [0.7, 3.0, 4.0, 1.0, 9.0, 9.0, 0.0]])
    stats = fit_stats(layout, state)
    np.testing.assert_allclose(stats["pos_mean"][0], [2.0, 3.0])
    np.testing.assert_allclose(stats["pos_mean"][1], [0.0, 0.0])  # never present
    model = Perception((8, 8, 3), layout, stats=stats)
    assert torch.equal(model.pos_mean, torch.as_tensor(stats["pos_mean"]))


def test_a_policy_reads_the_estimate_not_the_privileged_state(trained, tmp_path):
    """``--env.perception``: the env's observation is perception's estimate from the frame
    (the privileged slots never reach the policy or the buffer), training and loading
    work as for any run, and a checkpoint's policy acts on what make_env shows."""
    from helpers import tiny

    import lcrl
    from train.loop import Trainer
    from train.tasks import make_env

    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=120, learning_starts=60)
    cfg.env.perception = str(trained)
    env = make_env(cfg.env, "train")
    obs, _ = env.reset(seed=3)
    model, _ = load_model(trained)
    raw = env.unwrapped._observe()[0]  # the privileged observation of the same frame
    estimate = model.observation(raw["image"][None], raw["observation"][None, :2])[0]
    slots = obs["observation"][2:].reshape(8, 7)[:, :3].reshape(-1)  # base values of slots
    np.testing.assert_allclose(slots, estimate[2:], atol=1e-6)
    assert not np.allclose(estimate, raw["observation"])  # an estimate, not the truth

    trainer = Trainer(cfg)
    trainer.run()
    stored = trainer.buffer.obs["observation"][: trainer.buffer.high]
    assert np.isfinite(stored).all() and trainer.step == 120
    policy = lcrl.load(tmp_path / "run", device="cpu")
    o, _ = policy.make_env().reset(seed=0)
    assert policy.act(o, "reach the red cube", initial=o).shape == (2,)


def test_perception_that_does_not_fit_the_env_is_refused(trained, tmp_path, capsys):
    args = ["train", "robosuite", "--env.perception", str(trained), "--out", str(tmp_path / "r")]
    assert cli(*args) == 2
    line = error_line(capsys.readouterr().err)
    assert "the perception model reads [2, 8, 3, 2]" in line and "object slots are" in line
    assert cli("train", "lang2d-quick", "--env.perception", str(tmp_path)) == 2
    assert "no perception model at" in error_line(capsys.readouterr().err)

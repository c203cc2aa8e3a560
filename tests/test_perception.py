"""Perception learns to read object slots from a few hundred rendered 2D-tabletop frames,
through the real commands (collect, train, eval) and files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import cli, error_line

from lcrl.checkpoint import seal_checkpoint
from lcrl.errors import LcrlError
from lcrl.perception import Perception, SlotLayout, fit_stats
from train.environments.perception import evaluate, load_model, read_dataset


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


def test_evaluation_reports_frames_near_an_object_apart():
    """Frames with the agent within 5 cm of an object (where reach and push are judged)
    get their own error and presence figures; a frame counts as right only when every
    object's presence is."""
    from types import SimpleNamespace

    layout = SlotLayout(2, 2, 3, 2)
    state = np.zeros((4, layout.dim), np.float32)
    state[:, 2:5] = [0.5, 0.5, 1.0]  # object 0 at (0.5, 0.5)
    state[:, 5:8] = [0.0, 0.0, 1.0]  # object 1 at (0, 0)
    state[:, :2] = [[0.51, 0.5], [0.3, 0.3], [0.3, 0.3], [0.02, 0.0]]  # frames 0 and 3 near
    estimate = state.copy()
    estimate[0, 2] += 0.03  # 3 cm off, near
    estimate[1, 7] = 0.0  # object 1 missed, far

    class Model:
        def observation(self, frames, proprio, present=None):
            assert present is None
            return estimate[frames[:, 0, 0, 0]]

        def presence(self, observation):
            return layout.split(observation)[2]

    data = SimpleNamespace(
        frames=np.arange(4, dtype=np.uint8)[:, None, None, None].repeat(3, -1),
        proprio=state[:, :2],
        state=state,
        episodes=np.arange(4),  # one frame each: every frame judged by its own flags
    )
    res = evaluate(Model(), data, layout, hold_radius=0.0)
    assert res["near_frames"] == 2
    assert res["near_position_error_cm"] == pytest.approx(1.5, abs=1e-4)  # (3 + 0) / 2
    assert res["near_within_reach_margin"] == 0.5
    assert res["near_frames_all_present_right"] == 1.0
    assert res["frames_all_present_right"] == 0.75
    assert res["presence_accuracy"] == 7 / 8


def two_episodes_of_two_frames(state):
    """Evaluation data of four frames, two episodes of two: frame ``i`` is filled with the
    value ``i``, so a fake model knows which frame it reads."""
    from types import SimpleNamespace

    return SimpleNamespace(
        frames=np.arange(4, dtype=np.uint8)[:, None, None, None].repeat(3, -1),
        proprio=state[:, :2],
        state=state,
        episodes=np.array([0, 0, 1, 1]),
    )


def test_evaluation_takes_presence_from_each_episodes_first_frame():
    """Objects are placed at reset and stay: policies read the presence flags of the
    episode's first frame, so evaluation judges those, re-estimating the position of an
    object a later frame's own flags missed; each frame's own flags are reported beside."""

    layout = SlotLayout(2, 2, 3, 2)
    state = np.zeros((4, layout.dim), np.float32)
    state[:, 2:5] = [0.5, 0.5, 1.0]
    state[:, 5:8] = [0.1, 0.1, 1.0]
    own = state.copy()
    own[1, 5:8] = 0.0  # episode 0, second frame: object 1 missed (gripper over it)
    own[3, 2:5] = 0.0  # episode 1, second frame: object 0 missed
    own[2, 2:5] = 0.0  # episode 1, first frame: object 0 missed there too
    calls = []

    class Model:
        def observation(self, frames, proprio, present=None):
            rows = frames[:, 0, 0, 0]
            out = own[rows].copy()
            if present is not None:
                calls.append(rows.tolist())
                for i, r in enumerate(rows):
                    for k in range(2):
                        sl = slice(2 + 3 * k, 5 + 3 * k)
                        out[i, sl] = state[r, sl] if present[i, k] else 0.0
            return out

        def presence(self, observation):
            return layout.split(observation)[2]

    data = two_episodes_of_two_frames(state)
    res = evaluate(Model(), data, layout, hold_radius=0.0)
    assert calls == [[1]]  # only the frame whose own flags missed what its first frame saw
    assert res["presence_accuracy"] == 6 / 8  # episode 1 misses object 0 in both frames
    assert res["presence_accuracy_per_frame"] == 5 / 8
    assert res["frames_all_present_right"] == 0.5
    assert res["frames_all_present_right_per_frame"] == 0.25
    assert res["position_error_cm"] == pytest.approx(0.0, abs=1e-6)
    assert res["objects"] == 8


def test_position_spreads_have_a_floor_and_init_widens_them(capsys):
    """Objects resting on the table barely vary in height: the normaliser divides by at
    least MIN_POSITION_STD, and an --init model's spreads grow to its new data's where
    those are wider (lifted objects), never shrink."""
    from lcrl.perception import MIN_POSITION_STD, PerceptionConfig
    from train.environments.perception import widen_normalisers

    layout = SlotLayout(2, 2, 3, 2)
    state = np.zeros((50, layout.dim), np.float32)
    state[:, 2:5] = [0.1, 0.2, 1.0]
    state[:, 5] = np.linspace(-0.3, 0.3, 50)  # object 1 moves along x only
    state[:, 7] = 1.0
    stats = fit_stats(layout, state)
    assert (stats["pos_std"] >= MIN_POSITION_STD).all()
    assert stats["pos_std"][1, 0] == pytest.approx(np.linspace(-0.3, 0.3, 50).std(), rel=1e-5)

    model = Perception((8, 8, 3), layout, PerceptionConfig(channels=(4,), strides=(1,)), stats)
    wider = {"pos_std": stats["pos_std"].copy()}
    wider["pos_std"][0, 1] = 0.5
    wider["pos_std"][1, 0] = 0.01  # narrower: kept
    widen_normalisers(model, wider)
    got = model.pos_std.numpy()
    assert got[0, 1] == pytest.approx(0.5) and got[1, 0] == pytest.approx(stats["pos_std"][1, 0])
    assert "widened in 1 of 4" in capsys.readouterr().out


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


def test_training_continues_from_a_model(trained, dataset, capsys, tmp_path):
    """--init starts from a model's weights and normalisers: its first losses are the
    trained model's, not a new network's; another held-out split is refused."""
    out = tmp_path / "more"
    args = ["perception", "train", "--data", str(dataset), "--heldout-fraction", "0.15"]
    assert cli(*args, "--out", str(out), "--init", str(trained), "--steps", "50",
               "--lr", "1e-4", "--no-progress") == 0  # fmt: skip
    fresh = tmp_path / "fresh"
    assert cli(*args, "--out", str(fresh), "--steps", "50", "--no-progress") == 0
    capsys.readouterr()
    continued = json.loads((out / "model" / "history.json").read_text())
    new = json.loads((fresh / "model" / "history.json").read_text())
    assert continued[0]["position_loss"] < 0.5 * new[0]["position_loss"]
    before = json.loads((trained / "eval.json").read_text())["heldout_episodes"]
    after = json.loads((out / "eval.json").read_text())["heldout_episodes"]
    assert after["position_error_cm"] < 1.2 * before["position_error_cm"]
    assert load_model(out)[1]["train"]["init"] == str(trained)
    assert cli(*args[:-1], "0.3", "--out", str(tmp_path / "x"), "--init", str(trained)) == 2
    assert "held out other episodes" in error_line(capsys.readouterr().err)


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
    from train.environments.tasks import make_env
    from train.training.loop import Trainer

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

    # its episodes collected for a caption dataset store the true state, not the estimate
    out = tmp_path / "policy.h5"
    args = ["caption", "collect", "--env", "lang2d", "--sources", "policy", "--episodes", "2"]
    args += ["--policy", str(tmp_path / "run"), "--max-episode-steps", "5"]
    assert cli(*args, "--out", str(out), "--no-progress") == 0
    data, _ = read_dataset(str(out))
    again = model.observation(data.frames, data.proprio)
    assert not np.allclose(again, data.state, atol=1e-3)
    _, _, present = model.layout.split(data.state)
    assert set(np.unique(present)) <= {0.0, 1.0}  # the simulator's flags


def test_perception_that_does_not_fit_the_env_is_refused(trained, tmp_path, capsys):
    args = ["train", "robosuite", "--env.perception", str(trained), "--out", str(tmp_path / "r")]
    assert cli(*args) == 2
    line = error_line(capsys.readouterr().err)
    assert "the perception model reads [2, 8, 3, 2]" in line and "object slots are" in line
    assert cli("train", "lang2d-quick", "--env.perception", str(tmp_path)) == 2
    assert "no perception model at" in error_line(capsys.readouterr().err)


def test_the_kept_perception_model_is_found_from_any_folder(tmp_path, monkeypatch):
    """The camera presets name the kept model by its path in the repository; from another
    working folder it is looked up there, and a missing one is still refused."""
    from lcrl.perception import model_meta
    from train.configs.presets import PERCEPTION_KEPT

    monkeypatch.chdir(tmp_path)
    assert not Path(PERCEPTION_KEPT).exists()
    assert model_meta(PERCEPTION_KEPT)["frame_shape"][0] == 84
    with pytest.raises(LcrlError, match="no perception model at benchmarks/models/none"):
        model_meta("benchmarks/models/none/model")


def test_cached_estimates_equal_recomputed_ones(trained, tmp_path):
    """The replay buffer stores perception's estimate (with the slot features) computed
    once per frame; recomputed from the same frames and proprioception (presence from the
    episode's first frame, as policies read it) it is the same."""
    from helpers import tiny

    from envs.features import SlotFeatures
    from lcrl.buffer import HindsightReplayBuffer
    from lcrl.perception import HeldSlots
    from train.environments.tasks import make_env
    from train.evaluation.evaluate import build_task

    cfg = tiny("lang2d-quick", tmp_path / "run")
    cfg.env.perception = str(trained)
    cfg.agent.privileged_critic = True
    env = make_env(cfg.env, "train")
    task = build_task(cfg, env)
    assert task.privileged == ("privileged", "privileged_initial")
    shapes = task.problem().obs_shapes
    buffer = HindsightReplayBuffer(
        200, {k: (s, np.float32) for k, s in shapes.items()}, (2,), np.float32,
        task.goal_space, k=0,
    )  # fmt: skip
    obs, _ = env.reset(seed=5)
    first, frames, proprio, stored, records = obs, [], [], [], []
    rng = np.random.default_rng(0)
    for _ in range(6):
        frames.append(obs["image"])
        proprio.append(obs["privileged"][:2])
        stored.append(task.training_obs(obs, first))
        records.append(task.step_record(obs, env))
        obs, *_ = env.step(task.scale_action(rng.uniform(-1, 1, 2).astype(np.float32)))
    frames.append(obs["image"])
    proprio.append(obs["privileged"][:2])
    stored.append(task.training_obs(obs, first))
    records.append(task.step_record(obs, env))
    buffer.add_episode(
        {
            "obs": {k: np.stack([s[k] for s in stored]) for k in stored[0]},
            "action": np.zeros((6, 2), np.float32),
            "reward": np.zeros(6, np.float32),
            "terminated": np.zeros(6, bool),
            **task.episode_fields(records, task.goal(first, env), env),
        }
    )
    model, _ = load_model(trained)
    assert model.cfg.hold_radius > 0  # objects the gripper stays away from are held
    # presence is read in the episode's first frame and holds for its later frames
    first_flags = model.presence(model.observation(frames[0][None], proprio[0][None]))
    flags = np.repeat(first_flags, len(frames), axis=0)
    estimate = model.observation(np.stack(frames), np.stack(proprio), flags)
    held = HeldSlots(model.layout, model.cfg.hold_radius)
    estimate = np.concatenate([held(row[None]) for row in estimate])
    features = next(w for w in _wrappers(env) if isinstance(w, SlotFeatures))
    recomputed = features.features(estimate, estimate[:1])
    cached = buffer.obs["observation"][: buffer.high]
    np.testing.assert_allclose(cached, recomputed, atol=1e-6)
    np.testing.assert_allclose(buffer.obs["initial"][: buffer.high], recomputed[[0] * 7], atol=1e-6)
    # the critic's copy is the true state, with the same features
    truth = buffer.obs["privileged"][: buffer.high]
    assert not np.allclose(truth, cached)
    np.testing.assert_array_equal(truth[:, :2], cached[:, :2])  # proprioception is shared


def read_every_frame_alone(env) -> None:
    """Turn object permanence off in ``env``'s perception wrapper: each observation is then
    its own frame's estimate, what the differentiable reader of a run that fine-tunes
    perception computes."""
    from lcrl.perception import HeldSlots
    from train.environments.perception import find_perception

    wrapper = find_perception(env)
    wrapper.held = HeldSlots(wrapper.model.layout, 0.0)


def _wrappers(env):
    import gymnasium as gym

    while isinstance(env, gym.Wrapper):
        yield env
        env = env.env


def test_a_perception_policy_acts_from_frames_alone(trained, tmp_path):
    """A run whose critic read the true state (``--agent.privileged-critic``) gives a
    checkpoint that carries its perception model and acts through ``lcrl.load`` from camera
    frames and proprioception alone, exactly as from the env's own observations."""
    import shutil

    from helpers import tiny

    import lcrl
    from train.training.loop import Trainer

    model_dir = tmp_path / "perception"
    shutil.copytree(trained, model_dir)
    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=150, learning_starts=60)
    cfg.env.perception = str(model_dir)
    cfg.agent.privileged_critic = True
    Trainer(cfg).run()
    meta = json.loads((tmp_path / "run" / "config.json").read_text())
    assert meta["agent"]["privileged_critic"] is True
    shutil.rmtree(model_dir)  # the checkpoint carries its own copy
    policy, twin = lcrl.load(tmp_path / "run"), lcrl.load(tmp_path / "run")
    assert policy.perceives
    problem = policy.checkpoint.meta["problem"]
    assert problem["privileged"] == ["privileged", "privileged_initial"]
    env = policy.make_env()
    obs, _ = env.reset(seed=1)
    for _ in range(4):
        a = policy.act(obs, "reach the red cube")
        frames = {"image": obs["image"], "proprio": obs["privileged"][:2]}
        np.testing.assert_array_equal(a, twin.act(frames, "reach the red cube"))
        obs, *_ = env.step(a)
    with pytest.raises(LcrlError, match="acts from camera frames"):
        twin.act({"proprio": obs["privileged"][:2]}, "reach the red cube")
    with pytest.raises(LcrlError, match=r"perception reads \(64, 64, 3\) frames"):
        twin.act({"image": obs["image"][:32], "proprio": np.zeros(2)}, "reach the red cube")


def test_a_privileged_critic_needs_an_actor_that_does_not_read_the_state(tmp_path, capsys):
    args = ["train", "lang2d-quick", "--agent.privileged-critic", "--out", str(tmp_path / "r")]
    assert cli(*args) == 2
    assert "this actor reads the true state already" in error_line(capsys.readouterr().err)


def test_perception_fine_tuned_end_to_end(trained, tmp_path):
    """``--agent.perception-lr``: the buffer stores the frames (once, uint8), the
    networks read them through the perception model at every update, and the critic's
    loss moves its weights; the checkpoint carries the tuned model and acts from it."""
    from helpers import tiny

    import lcrl
    from lcrl.perception import PerceivedSlots
    from train.training.loop import Trainer

    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=160, learning_starts=100)
    cfg.env.perception = str(trained)
    cfg.agent.perception_lr = 1e-3
    trainer = Trainer(cfg)
    assert trainer.problem.perceived == PerceivedSlots.KEYS
    assert trainer.buffer.obs["image"].dtype == np.uint8 and "observation" not in trainer.buffer.obs
    before = {k: v.clone() for k, v in trainer.agent.perceiver.state_dict().items()}
    trainer.run()
    tuned = trainer.agent.perceiver.state_dict()
    assert any(not torch.equal(before[k], tuned[k]) for k in before if "convs" in k)
    policy = lcrl.load(tmp_path / "run")
    saved = policy.agent.perceiver.state_dict()
    for k, v in tuned.items():
        torch.testing.assert_close(saved[k], v, rtol=0, atol=0)
    o, _ = policy.make_env().reset(seed=0)
    assert policy.act(
        {"image": o["image"], "proprio": o["privileged"][:2]}, "reach the red cube"
    ).shape == (2,)


def test_perceived_slots_match_the_env_features(trained):
    """The differentiable reader computes what the env's wrappers compute from a frame."""
    from lcrl.perception import PerceivedSlots
    from train.configs.presets import PRESETS
    from train.environments.tasks import make_env

    cfg = PRESETS["lang2d-quick"][1].env
    cfg = type(cfg)(**{**vars(cfg), "perception": str(trained)})
    env = make_env(cfg, "train")
    read_every_frame_alone(env)
    first, _ = env.reset(seed=2)
    obs, *_ = env.step(env.action_space.sample())
    model, _ = load_model(trained)
    reader = PerceivedSlots(model, cfg.relative_positions, cfg.displacements)
    origin = torch.as_tensor(reader.origin(first["observation"])[None])
    with torch.no_grad():
        x = reader(
            torch.as_tensor(obs["image"][None]),
            torch.as_tensor(obs["privileged"][None, :2]),
            origin,
        )
    np.testing.assert_allclose(x[0].numpy(), obs["observation"], atol=1e-5)


def test_demonstrations_recorded_through_perception_fill_a_perception_run(
    trained, tmp_path, capsys
):
    """``lcrl demos record --perception``: the file holds perception's estimate as the
    observation and the true state beside it; a run acting through the same model loads it
    (``--finetune.demos``), and runs that read the other one are refused in one line."""
    import h5py
    from helpers import tiny

    from train.training.loop import Trainer

    demos = tmp_path / "demos.h5"
    args = ["demos", "record", "--preset", "lang2d-quick", "--perception", str(trained)]
    args += ["--families", "reach", "--episodes", "3", "--out", str(demos), "--no-progress"]
    assert cli(*args) == 0
    with h5py.File(demos) as f:
        keys = set(f["obs"])
        observation, privileged = f["obs/observation"][:], f["obs/privileged"][:]
    assert {"observation", "privileged"} <= keys
    assert observation.shape == privileged.shape
    assert not np.allclose(observation, privileged, atol=1e-3)  # estimate beside the truth
    np.testing.assert_allclose(observation[:, :2], privileged[:, :2])  # same proprioception

    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=60, learning_starts=40)
    cfg.env.perception = str(trained)
    cfg.env.families = ("reach",)
    cfg.finetune.demos, cfg.finetune.pretrain_updates = str(demos), 10
    trainer = Trainer(cfg)
    trainer.run()
    assert trainer.step == 60 and trainer.buffer.high > 60  # the demonstrations are stored

    out = tmp_path / "state"
    assert cli("train", "lang2d-quick", "--finetune.demos", str(demos), "--out", str(out)) == 2
    line = error_line(capsys.readouterr().err)
    assert "stores a perception model's estimate" in line and "without --perception" in line

    plain = tmp_path / "plain.h5"
    args = ["demos", "record", "--preset", "lang2d-quick", "--families", "reach"]
    assert cli(*args, "--episodes", "2", "--out", str(plain), "--no-progress") == 0
    args = ["train", "lang2d-quick", "--env.perception", str(trained)]
    assert cli(*args, "--finetune.demos", str(plain), "--out", str(tmp_path / "p")) == 2
    line = error_line(capsys.readouterr().err)
    assert "stores the true state" in line and "--perception MODEL" in line


def test_presence_holds_from_the_first_frame(trained, monkeypatch):
    """Objects are placed at reset and stay: the env wrapper and the differentiable reader
    keep the presence flags of the episode's first frame when a later frame's own flags
    (a gripper over an object) say otherwise, and the next reset reads them again."""
    from lcrl.perception import PerceivedSlots
    from train.configs.presets import PRESETS
    from train.environments.perception import find_perception
    from train.environments.tasks import make_env

    cfg = PRESETS["lang2d-quick"][1].env
    cfg = type(cfg)(**{**vars(cfg), "perception": str(trained)})
    env = make_env(cfg, "train")
    model = find_perception(env).model
    read_every_frame_alone(env)
    first, _ = env.reset(seed=2)
    flags = first["observation"][2:].reshape(8, 7)[:, 2]
    assert 0 < flags.sum() < 8

    forward = type(model).forward

    def nothing_seen(self, frames, proprio, generator=None):
        pos, logit = forward(self, frames, proprio, generator)
        return pos, torch.full_like(logit, -10.0)

    monkeypatch.setattr(type(model), "forward", nothing_seen)
    obs, *_ = env.step(env.action_space.sample())
    slots = obs["observation"][2:].reshape(8, 7)
    np.testing.assert_array_equal(slots[:, 2], flags)
    assert (np.abs(slots[flags > 0, :2]) > 0).all()  # positions of the first frame's objects
    reader = PerceivedSlots(model, cfg.relative_positions, cfg.displacements)
    origin = torch.as_tensor(reader.origin(first["observation"])[None])
    with torch.no_grad():
        image, proprio = obs["image"][None], obs["privileged"][None, :2]
        x = reader(torch.as_tensor(image), torch.as_tensor(proprio), origin)
    np.testing.assert_allclose(x[0].numpy(), obs["observation"], atol=1e-5)
    again, _ = env.reset(seed=2)
    assert again["observation"][2:].reshape(8, 7)[:, 2].sum() == 0  # read anew at reset


def test_held_slots_keep_what_the_gripper_stays_away_from():
    """Objects move only when the robot moves them: an object's position is held while
    the gripper is farther than the radius from it (now and one frame before); near it,
    the frame's own estimate is taken and held from then on."""
    from lcrl.perception import HeldSlots

    layout = SlotLayout(2, 2, 3, 2)  # the agent (x, y); two slots [x, y, present]

    def obs(agent, a, b=None):
        b_slot = [0.0, 0.0, 0.0] if b is None else [*b, 1.0]
        return np.array([[*agent, *a, 1.0, *b_slot]], np.float32)

    held = HeldSlots(layout, 0.1)
    first = held(obs((0.0, 0.0), (0.5, 0.5)))
    np.testing.assert_array_equal(first, obs((0.0, 0.0), (0.5, 0.5)))
    # far from the object: a later frame's misreading is not taken
    np.testing.assert_array_equal(held(obs((0.1, 0.0), (0.53, 0.48))), obs((0.1, 0.0), (0.5, 0.5)))
    # the gripper arrives: the frame's own estimate
    np.testing.assert_array_equal(
        held(obs((0.45, 0.5), (0.52, 0.5))), obs((0.45, 0.5), (0.52, 0.5))
    )
    # it leaves at once: still taken (near one frame before), then held
    np.testing.assert_array_equal(held(obs((0.0, 0.0), (0.65, 0.5))), obs((0.0, 0.0), (0.65, 0.5)))
    np.testing.assert_array_equal(held(obs((0.0, 0.0), (0.7, 0.4))), obs((0.0, 0.0), (0.65, 0.5)))
    # the absent object stays 0; a reset takes the next estimate whole
    held.reset()
    np.testing.assert_array_equal(held(obs((0.0, 0.0), (0.7, 0.4))), obs((0.0, 0.0), (0.7, 0.4)))
    # rows are episodes in parallel; radius 0 passes everything through
    two = np.concatenate([obs((0.0, 0.0), (0.5, 0.5), (0.2, 0.2)), obs((0.5, 0.5), (0.5, 0.5))])
    held.reset()
    held(two)
    moved = two.copy()
    moved[:, 2:4] += 0.05
    out = held(moved)
    np.testing.assert_array_equal(out[0], two[0])  # gripper far: held
    np.testing.assert_array_equal(out[1], moved[1])  # gripper on it: taken
    np.testing.assert_array_equal(HeldSlots(layout, 0.0)(moved), moved)


def test_held_slots_take_an_object_again_where_the_frame_sees_it_by_the_gripper():
    """An object carried off while its estimate lagged behind (hidden under the gripper)
    is not held where the estimate was left: the frame that sees it by the gripper is
    taken, although the position held is far from it."""
    from lcrl.perception import HeldSlots

    layout = SlotLayout(2, 1, 3, 2)  # the agent (x, y); one slot [x, y, present]

    def obs(agent, a):
        return np.array([[*agent, *a, 1.0]], np.float32)

    held = HeldSlots(layout, 0.1)
    held(obs((0.0, 0.0), (0.5, 0.5)))
    held(obs((0.45, 0.5), (0.5, 0.5)))  # the gripper reaches the object
    # it carries it off; under the gripper the frame misreads it, far behind: the
    # misreading is near the gripper one frame before, so it is taken and held
    lagged = held(obs((0.6, 0.5), (0.35, 0.5)))
    np.testing.assert_array_equal(lagged, obs((0.6, 0.5), (0.35, 0.5)))
    # the gripper goes on: the position held is far from it now, but the frame sees the
    # object by the gripper again, and that is taken
    np.testing.assert_array_equal(held(obs((0.8, 0.5), (0.78, 0.5))), obs((0.8, 0.5), (0.78, 0.5)))
    # the gripper leaves; then a frame that misreads it away from the gripper, with the
    # position held away too, is not taken
    held(obs((0.0, 0.0), (0.78, 0.5)))
    np.testing.assert_array_equal(held(obs((0.0, 0.0), (0.5, 0.2))), obs((0.0, 0.0), (0.78, 0.5)))


def test_evaluation_judges_held_positions_and_each_frame_alone():
    """Evaluation reads positions as policies do (held away from the gripper) and reports
    each frame's own estimates beside."""
    from types import SimpleNamespace

    layout = SlotLayout(2, 1, 3, 2)
    state = np.zeros((4, layout.dim), np.float32)
    state[:, 2:5] = [0.5, 0.5, 1.0]  # the object never moves; the agent stays at (0, 0)
    seen = state.copy()
    seen[[1, 3], 2] += 0.02  # later frames misread it by 2 cm

    class Model:
        cfg = SimpleNamespace(hold_radius=0.1)

        def observation(self, frames, proprio, present=None):
            return seen[frames[:, 0, 0, 0]].copy()

        def presence(self, observation):
            return layout.split(observation)[2]

    data = two_episodes_of_two_frames(state)
    res = evaluate(Model(), data, layout)
    assert res["hold_radius"] == 0.1
    assert res["position_error_cm"] == pytest.approx(0.0, abs=1e-4)
    assert res["position_error_cm_without_hold"] == pytest.approx(1.0, abs=1e-4)
    alone = evaluate(Model(), data, layout, hold_radius=0.0)
    assert alone["position_error_cm"] == pytest.approx(1.0, abs=1e-4)


def test_models_saved_before_object_permanence_hold_nothing(trained, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(trained, old)
    meta_path = old / "model" / "meta.json"
    meta = json.loads(meta_path.read_text())
    del meta["model"]["hold_radius"]
    meta_path.write_text(json.dumps(meta))
    seal_checkpoint(old / "model")  # as such a model was saved: its own sums
    assert load_model(old)[0].cfg.hold_radius == 0.0
    assert load_model(trained)[0].cfg.hold_radius == 0.06


def test_extra_datasets_train_too_and_must_match(trained, dataset, capsys, tmp_path):
    """--extra-data adds every episode of more datasets to training (held out: --data's
    alone); one of another frame size is refused, naming both."""
    more = tmp_path / "more.h5"
    collect = ["perception", "collect", "--env", "lang2d", "--max-episode-steps", "5"]
    assert (
        cli(*collect, "--episodes", "20", "--seed", "7", "--out", str(more), "--no-progress") == 0
    )
    out = tmp_path / "model"
    args = ["perception", "train", "--data", str(dataset), "--heldout-fraction", "0.15"]
    args += ["--steps", "20", "--no-progress"]
    assert cli(*args, "--out", str(out), "--extra-data", str(more)) == 0
    _, meta = load_model(out)
    assert meta["heldout_episodes"] == load_model(trained)[1]["heldout_episodes"]
    assert meta["train"]["extra_data"] == [str(more)]
    small = tmp_path / "small.h5"
    assert cli(*collect, "--episodes", "2", "--image-size", "32", "--out", str(small),
               "--no-progress") == 0  # fmt: skip
    capsys.readouterr()
    assert cli(*args, "--out", str(tmp_path / "x"), "--extra-data", str(small)) == 2
    line = error_line(capsys.readouterr().err)
    assert "(32, 32, 3) frames" in line and "(64, 64, 3)" in line


def test_the_hold_radius_is_set_when_acting_and_refused_where_it_cannot_apply(
    trained, tmp_path, capsys
):
    """``--env.perception-hold-radius`` (``lcrl eval --hold-radius`` for a saved policy)
    replaces the model's own object permanence in the env and in ``lcrl.load``'s policy;
    it needs a perception model and a radius >= 0."""
    from helpers import tiny

    import lcrl
    from train.environments.tasks import make_env
    from train.training.loop import Trainer

    model, _ = load_model(trained)
    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=80, learning_starts=40)
    cfg.env.perception = str(trained)
    assert make_env(cfg.env, "train").get_wrapper_attr("held").radius == model.cfg.hold_radius
    cfg.env.perception_hold_radius = 0.0
    assert make_env(cfg.env, "train").get_wrapper_attr("held").radius == 0.0
    Trainer(cfg).run()
    policy = lcrl.load(tmp_path / "run", device="cpu")
    obs, _ = policy.make_env().reset(seed=0)
    policy.act({"image": obs["image"], "proprio": obs["privileged"][:2]}, "reach the red cube")
    assert policy._held.radius == 0.0  # the frames-alone path holds as the env does

    cfg.env.perception_hold_radius = -1.0
    with pytest.raises(LcrlError, match="perception_hold_radius must be >= 0"):
        make_env(cfg.env, "train")
    args = ["eval", str(tmp_path / "run"), "--episodes", "2", "--sets", "train"]
    assert cli(*args, "--hold-radius", "-0.5", "--no-progress") == 2
    assert "--hold-radius must be >= 0" in error_line(capsys.readouterr().err)
    out = tmp_path / "eval.json"
    args += ["--hold-radius", "0.05", "--json", str(out), "--no-progress"]
    assert cli(*args) == 0
    settings = json.loads(out.read_text())["settings"]
    assert settings["hold_radius"] == 0.05 and "--hold-radius 0.05" in settings["command"]

    state = tiny("lang2d-quick", tmp_path / "state", total_steps=40, learning_starts=20)
    Trainer(state).run()
    assert cli("eval", str(tmp_path / "state"), "--hold-radius", "0.05") == 2
    assert "through no perception model" in error_line(capsys.readouterr().err)
    args = ["train", "lang2d-quick", "--env.perception-hold-radius", "0.05"]
    assert cli(*args, "--out", str(tmp_path / "refused")) == 2
    assert "set --env.perception MODEL too" in error_line(capsys.readouterr().err)


def test_eval_acts_through_another_perception_model_where_one_applies(trained, tmp_path, capsys):
    """``lcrl eval --perception MODEL`` swaps the model a camera policy acts through (what a
    figure owes to the student and what to its perception); refused for a policy on the
    state, beside --true-state, and for a folder that is not there."""
    from helpers import tiny

    from train.training.loop import Trainer

    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=60, learning_starts=30)
    cfg.env.perception = str(trained)
    Trainer(cfg).run()
    args = ["eval", str(tmp_path / "run"), "--episodes", "2", "--sets", "train", "--no-progress"]
    out = tmp_path / "eval.json"
    assert cli(*args, "--perception", str(trained), "--json", str(out)) == 0
    assert f"--perception {trained}" in json.loads(out.read_text())["settings"]["command"]
    assert cli(*args, "--perception", str(tmp_path / "nothing")) == 2
    assert "no such folder" in error_line(capsys.readouterr().err)
    assert cli(*args, "--perception", str(trained), "--true-state") == 2
    assert "use one of them" in error_line(capsys.readouterr().err)
    state = tiny("lang2d-quick", tmp_path / "state", total_steps=40, learning_starts=20)
    Trainer(state).run()
    assert cli("eval", str(tmp_path / "state"), "--perception", str(trained)) == 2
    assert "acts on the simulator's state" in error_line(capsys.readouterr().err)

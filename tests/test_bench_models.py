"""The models kept in ``benchmarks/models`` (see its README) load and act: the perception
models read the robosuite tabletop's 84 px frames into its object slots, and the push
teacher acts on the tabletop's privileged state, without the replay buffer or optimiser
state that its folder leaves out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

MODELS = Path(__file__).resolve().parent.parent / "benchmarks" / "models"
RESULTS = MODELS.parent / "results"


@pytest.mark.parametrize(
    "name", ["perception-3k", "perception-push", "perception-push-student", "perception-80x3"]
)
def test_a_kept_perception_model_reads_robosuite_frames(name):
    from lcrl.perception import load_model

    model, meta = load_model(MODELS / name / "model")
    assert meta["env"] == "robosuite" and model.frame_shape == (84, 84, 3)
    assert model.layout.to_list() == [4, 8, 4, 3]
    frames = np.random.default_rng(0).integers(0, 256, (2, 84, 84, 3), dtype=np.uint8)
    estimate = model.observation(frames, np.zeros((2, 4), np.float32))
    assert estimate.shape == (2, model.layout.dim) and np.isfinite(estimate).all()
    figures = json.loads((MODELS / name / "eval.json").read_text())
    assert figures  # the evaluation its README quotes is kept beside it
    assert f"`{name}/`" in (MODELS / "README.md").read_text()


def test_the_perception_headline_is_the_kept_model_on_a_test_set():
    """``perception-robosuite.json``'s headline is the kept ``perception-80x3`` on episodes of
    a seed no choice used, the held-out episodes that chose the build beside."""
    result = json.loads((MODELS.parent / "results" / "perception-robosuite.json").read_text())
    assert "--keep benchmarks/models/perception-80x3" in result["command"]
    headline = result["headline"]
    assert headline["test_data"] in result["datasets"]
    assert "validation_position_error_cm" in headline
    tested = result["test_episodes"]["data/perception-80x3/model"]["held"]
    assert headline["position_error_cm"] == round(tested["position_error_cm"], 3)


def test_the_kept_2d_perception_model_reads_96_px_frames():
    from lcrl.perception import load_model

    model, meta = load_model(MODELS / "perception-lang2d-96" / "model")
    assert meta["env"] == "lang2d" and model.frame_shape == (96, 96, 3)
    frames = np.random.default_rng(0).integers(0, 256, (2, 96, 96, 3), dtype=np.uint8)
    start = model.layout.start
    estimate = model.observation(frames, np.zeros((2, start), np.float32))
    assert estimate.shape == (2, model.layout.dim) and np.isfinite(estimate).all()
    assert json.loads((MODELS / "perception-lang2d-96" / "eval.json").read_text())
    assert "`perception-lang2d-96/`" in (MODELS / "README.md").read_text()


def test_the_kept_factored_captioner_captions_and_scores_robosuite_frames():
    from captioner.learned import LearnedCaptioner

    lc = LearnedCaptioner.load(MODELS / "captioner-factored-robosuite" / "model")
    assert lc.factored is not None and lc.cfg.head == "factored"
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (3, 84, 84, 3), dtype=np.uint8)
    proprio = np.zeros((3, lc.proprio_dim), np.float32)
    texts = ["pick up the yellow cube", "lift the yellow block", "reach the red cylinder"]
    probs = lc.score_matrix(texts, frames, frames, proprio, proprio)
    assert probs.shape == (3, 3) and ((probs >= 0) & (probs <= 1)).all()
    np.testing.assert_allclose(probs[:, 0], probs[:, 1], atol=1e-6)  # one meaning
    for text, logp in lc.caption(frames, frames, proprio, proprio):
        assert (text in lc.instructions or text == "<none>") and logp <= 0
    figures = json.loads((MODELS / "captioner-factored-robosuite" / "eval.json").read_text())
    assert figures["heldout_combinations"]["exact_match"] >= 0.85
    assert "`captioner-factored-robosuite/`" in (MODELS / "README.md").read_text()


@pytest.mark.parametrize(
    "kept, result",
    [
        ("captioner-factored-robosuite-policy", "captioner-robosuite-policy"),
        ("captioner-factored-robosuite-80x3", "captioner-robosuite-policy-perception-80x3"),
    ],
)
def test_the_kept_robosuite_captioners_trained_with_policy_episodes_match_their_figures(
    kept, result
):
    """The three with-policy captioners of a captioner-robosuite-policy result (over
    perception-3k, and over perception-80x3): each loads, scores frames, and the seed means
    of their test figures are the file's headline."""
    from captioner.learned import LearnedCaptioner

    folder = MODELS / kept
    head = json.loads((RESULTS / f"{result}.json").read_text())["headline"]
    held, auc = [], []
    for seed in range(3):
        lc = LearnedCaptioner.load(folder / f"seed{seed}" / "model")
        assert lc.factored is not None and lc.cfg.head == "factored"
        frames = np.random.default_rng(seed).integers(0, 256, (2, 84, 84, 3), dtype=np.uint8)
        proprio = np.zeros((2, lc.proprio_dim), np.float32)
        probs = lc.score_matrix(["lift the red cube"], frames, frames, proprio, proprio)
        assert probs.shape == (2, 1) and ((probs >= 0) & (probs <= 1)).all()
        test = json.loads((folder / f"seed{seed}" / "eval-test.json").read_text())
        held.append(test["heldout_combinations"]["exact_match"])
        auc.append(test["heldout_combinations"]["auc"])
    assert round(float(np.mean(held)), 3) == head["heldout_combinations_exact_match"]
    assert round(float(np.mean(auc)), 3) == head["heldout_combinations_reward_auc"]
    assert f"`{kept}/`" in (MODELS / "README.md").read_text()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_kept_2d_factored_captioners_score_frames_and_match_their_figures(seed):
    """The captioners that relabelled learned-her-lang2d.json's runs (seed s: training
    seed s), self-contained with their perception model."""
    from captioner.learned import LearnedCaptioner

    folder = MODELS / "captioner-factored-lang2d" / f"seed{seed}"
    lc = LearnedCaptioner.load(folder / "model")
    assert lc.factored is not None and lc.cfg.head == "factored"
    frames = np.random.default_rng(seed).integers(0, 256, (2, 96, 96, 3), dtype=np.uint8)
    proprio = np.zeros((2, lc.proprio_dim), np.float32)
    texts = ["push the red cube left", "shove the red block to the left"]
    probs = lc.score_matrix(texts, frames, frames, proprio, proprio)
    assert probs.shape == (2, 2) and ((probs >= 0) & (probs <= 1)).all()
    np.testing.assert_allclose(probs[:, 0], probs[:, 1], atol=1e-6)  # one meaning
    figures = json.loads((folder / "eval.json").read_text())
    assert figures["heldout_combinations"]["exact_match"] >= 0.85
    assert "`captioner-factored-lang2d/`" in (MODELS / "README.md").read_text()


def test_the_kept_push_teacher_acts_on_the_privileged_state(one_thread):
    pytest.importorskip("robosuite")
    from train.evaluation.evaluate import resolve_checkpoint
    from train.policies.loading import load_policy

    policy = load_policy(resolve_checkpoint(str(MODELS / "push-teacher")))
    try:
        assert policy.cfg.env.kind == "robosuite" and policy.agent.name == "sac"
        assert not (policy.checkpoint.path / "arrays.npz").exists()  # weights only
        obs, _ = policy.env.reset(seed=0)
        goal = np.asarray([policy.task.goal(obs, policy.env)])
        view = policy.task.storage_obs(obs, obs)
        action = policy.agent.act({k: v[None] for k, v in view.items()}, goal, deterministic=True)
        assert action.shape == (1, policy.task.problem().action_dim)
        assert np.abs(action).max() <= 1.0
    finally:
        policy.env.close()
    assert "`push-teacher/`" in (MODELS / "README.md").read_text()


def test_the_kept_push_student_acts_from_frames_as_one_network(one_thread):
    """The push student behind distill-robosuite.json's headline: one network (not an
    ensemble) acting through its own perception model, without its learning state."""
    pytest.importorskip("robosuite")
    import lcrl
    from benchmarks.protocol import check_single_policy
    from lcrl.checkpoint import verify_checkpoint

    folder = check_single_policy(MODELS / "push-student")
    ckpt = verify_checkpoint(folder)
    assert "perception" in ckpt.meta and ckpt.meta["config"]["env"]["families"] == ["push"]
    assert not list(folder.glob("state*")) and not list(folder.glob("arrays.npz"))
    policy = lcrl.load(folder)
    try:
        assert policy.perceives and policy.agent.name == "bc"
        obs, _ = policy.env.reset(seed=5)
        action = policy.act(obs, "push the red cube left")
        assert action.shape == policy.env.action_space.shape and np.isfinite(action).all()
    finally:
        policy.env.close()
    result = json.loads((MODELS.parent / "results" / "distill-robosuite.json").read_text())
    assert result["push"]["kept"] == "benchmarks/models/push-student"
    assert result["push"]["final_seed"] == 17
    assert "`push-student/`" in (MODELS / "README.md").read_text()


def test_every_kept_checkpoint_carries_checksums_that_hold():
    """Each kept checkpoint records the SHA-256 of every file beside its meta.json, and
    the files match them (a model changed by hand must be sealed again)."""
    from lcrl.checkpoint import verify_checkpoint

    folders = sorted(p.parent for p in MODELS.rglob("meta.json"))
    assert len(folders) >= 5
    for folder in folders:
        ckpt = verify_checkpoint(folder)
        files = {p.name for p in folder.iterdir() if p.is_file() and p.name != "meta.json"}
        assert set(ckpt.checksums) == files, folder


PARTS = MODELS / "robosuite-camera-parts"


def test_the_camera_builds_parts_are_kept_and_a_build_takes_them_up(tmp_path, one_thread):
    """The perception model and the put and stack teachers of the robosuite-camera build,
    with their stage records: its perception reads frames, its teachers act on the
    privileged state, and ``--parts`` copies them into a new build's folder."""
    pytest.importorskip("robosuite")
    from lcrl.perception import load_model
    from train.commands.pipeline import robosuite_camera, stages
    from train.commands.pipeline_parts import import_parts
    from train.evaluation.evaluate import resolve_checkpoint
    from train.policies.loading import load_policy

    records = {f.stem: json.loads(f.read_text()) for f in (PARTS / "stages").glob("*.json")}
    assert set(records) == {
        "perception-data", "perception", "demos-robosuite-manip", "teacher-put", "teacher-stack"
    }  # fmt: skip
    assert all(r["seconds"] > 0 and len(r["span"]) == 2 for r in records.values())
    model, meta = load_model(PARTS / "perception" / "model")
    assert meta["env"] == "robosuite" and model.frame_shape == (84, 84, 3)
    frames = np.random.default_rng(0).integers(0, 256, (2, 84, 84, 3), dtype=np.uint8)
    assert np.isfinite(model.observation(frames, np.zeros((2, 4), np.float32))).all()
    for family in ("put", "stack"):
        policy = load_policy(resolve_checkpoint(str(PARTS / "teachers" / family)))
        try:
            assert policy.cfg.env.families == (family,)
            assert not list(policy.checkpoint.path.glob("arrays.npz"))  # weights only
            obs, _ = policy.env.reset(seed=0)
            goal = np.asarray([policy.task.goal(obs, policy.env)])
            view = policy.task.storage_obs(obs, obs)
            act = policy.agent.act({k: v[None] for k, v in view.items()}, goal, deterministic=True)
            assert act.shape == (1, policy.task.problem().action_dim)
        finally:
            policy.env.close()
    out = tmp_path / "camera"
    import dataclasses

    p = dataclasses.replace(robosuite_camera(), out=str(out))
    taken = import_parts(out, stages(p), PARTS)
    # perception's data is not kept (perception-ft reads it again): that stage runs again
    assert taken == ["perception", "demos-robosuite-manip", "teacher-put", "teacher-stack"]
    assert (out / "teachers" / "put" / "latest.json").is_file()
    # a student of the state takes the teachers up and leaves the perception stages be
    from train.commands.pipeline import robosuite_privileged

    state = dataclasses.replace(robosuite_privileged(), out=str(tmp_path / "state"))
    unused = ("perception-data", "perception")
    taken = import_parts(tmp_path / "state", stages(state), PARTS, unused)
    assert taken == ["demos-robosuite-manip", "teacher-put", "teacher-stack"]
    assert not (tmp_path / "state" / "perception").exists()
    assert "`robosuite-camera-parts/`" in (MODELS / "README.md").read_text()


CAMERA = MODELS / "robosuite-camera"


def test_the_kept_camera_policy_acts_from_frames_reads_free_text_and_is_evaluated(
    tmp_path, one_thread, capsys
):
    """The policy ``lcrl train robosuite-camera`` keeps: one network acting through its own
    copy of the perception model on 84 px agentview frames and proprioception, with the
    canonical reader on by default (kept beside it, no replay state), that ``lcrl act`` and
    ``lcrl eval`` take in a fresh clone."""
    pytest.importorskip("robosuite")
    from helpers import cli

    from lcrl.checkpoint import verify_checkpoint
    from train.environments.text_reading import READER_CACHE

    ckpt = verify_checkpoint(CAMERA)
    env = ckpt.meta["config"]["env"]
    assert env["kind"] == "robosuite" and env["canonical_reader"]
    assert sorted(env["families"]) == ["lift", "push", "put", "reach", "stack"]
    assert "perception" in ckpt.meta and (CAMERA / READER_CACHE).is_dir()
    assert not list(CAMERA.glob("arrays.npz")) and not list(CAMERA.glob("state*"))
    assert sum(f.stat().st_size for f in CAMERA.rglob("*") if f.is_file()) < 10e6

    import lcrl

    policy = lcrl.load(CAMERA)
    try:
        assert policy.perceives and policy.agent.name == "bc"  # one network, distilled
        obs, _ = policy.env.reset(seed=3)
        frame = np.asarray(obs["image"], np.uint8)
        assert frame.shape == (84, 84, 3)
        start = policy._frame_reader()[0].layout.start  # the gripper's state leads the vector
        camera = {"image": frame, "proprio": obs["observation"][:start]}
        action = policy.act(camera, "pick up the yellow cube")
        assert action.shape == policy.env.action_space.shape
        policy.reset()
        # the env's observation is perception's reading of the same frame
        np.testing.assert_allclose(action, policy.act(obs, "pick up the yellow cube"), atol=1e-4)
    finally:
        policy.env.close()

    video = tmp_path / "lift.gif"
    args = ["act", str(CAMERA), "--instruction", "pick up the yellow cube", "--episodes", "1"]
    assert cli(*args, "--video", str(video), "--seed", "11") == 0
    said = capsys.readouterr().out
    assert "the reader reads it as" in said and video.stat().st_size > 10_000
    out = tmp_path / "eval.json"
    args = ["eval", str(CAMERA), "--episodes", "2", "--sets", "train", "--seed", "12"]
    assert cli(*args, "--json", str(out), "--no-progress") == 0
    train = json.loads(out.read_text())["sets"]["train"]
    assert train["episodes"] == 2 and 0.0 <= train["success"] <= 1.0
    assert set(train["families"]) <= {"reach", "push", "lift", "put", "stack"}
    result = json.loads((MODELS.parent / "results" / "robosuite-camera.json").read_text())
    assert result["headline"]["model"] == "benchmarks/models/robosuite-camera"
    assert "`robosuite-camera/`" in (MODELS / "README.md").read_text()


STATE = MODELS / "robosuite-privileged"


def test_the_kept_state_policy_follows_every_family_from_one_network(tmp_path, one_thread):
    """The policy ``lcrl train robosuite-privileged`` keeps: one network (no router, no
    ensemble) acting on the privileged state for all five families, the canonical reader
    on by default and kept beside it; ``lcrl eval`` takes it in a fresh clone."""
    pytest.importorskip("robosuite")
    from helpers import cli

    from benchmarks.protocol import check_single_policy
    from lcrl.checkpoint import verify_checkpoint
    from train.environments.text_reading import READER_CACHE

    ckpt = verify_checkpoint(check_single_policy(STATE))
    env = ckpt.meta["config"]["env"]
    assert env["kind"] == "robosuite" and env["canonical_reader"] and not env["perception"]
    assert sorted(env["families"]) == ["lift", "push", "put", "reach", "stack"]
    assert (STATE / READER_CACHE).is_dir() and not list(STATE.glob("state*"))
    import lcrl

    policy = lcrl.load(STATE)
    try:
        assert policy.agent.name == "bc" and not policy.perceives
        obs, _ = policy.env.reset(seed=3)
        action = policy.act(obs, "put the red cylinder left of the green cube")
        assert action.shape == policy.env.action_space.shape and np.isfinite(action).all()
    finally:
        policy.env.close()
    out = tmp_path / "eval.json"
    args = ["eval", str(STATE), "--episodes", "2", "--sets", "train", "--seed", "12"]
    assert cli(*args, "--json", str(out), "--no-progress") == 0
    assert json.loads(out.read_text())["sets"]["train"]["episodes"] == 2
    result = json.loads((MODELS.parent / "results" / "robosuite-manipulation.json").read_text())
    assert result["headline"]["model"] == "benchmarks/models/robosuite-privileged"
    assert "`robosuite-privileged/`" in (MODELS / "README.md").read_text()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_kept_lang2d_grounded_policies_act_on_free_text(seed):
    """The policies behind compositional-lang2d.json, kept to act: no critics, the
    canonical reader on by default and fitted beside them (no refit when loaded)."""
    import lcrl

    folder = MODELS / "lang2d-grounded" / f"seed{seed}"
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["acting_only"] == ["critic", "critic_target"]
    assert meta["config"]["env"]["canonical_reader"] and (folder / "canonical-reader").is_dir()
    policy = lcrl.load(folder)
    obs, _ = policy.make_env().reset(seed=0)
    action = policy.act(obs, "touch the red cube")
    assert action.shape == (2,) and np.abs(action).max() <= 1.0
    assert "`lang2d-grounded/`" in (MODELS / "README.md").read_text()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_kept_robosuite_reach_policies_act_on_the_privileged_state(seed, one_thread):
    """The policies behind compositional-robosuite.json, kept to act (no critics)."""
    pytest.importorskip("robosuite")
    import lcrl

    folder = MODELS / "robosuite-reach" / f"seed{seed}"
    assert json.loads((folder / "meta.json").read_text())["acting_only"] == [
        "critic", "critic_target",
    ]  # fmt: skip
    policy = lcrl.load(folder)
    env = policy.make_env()
    try:
        obs, _ = env.reset(seed=0)
        action = policy.act(obs, policy.instructions[0])
        assert action.shape == (4,) and np.abs(action).max() <= 1.0
    finally:
        env.close()
    assert "`robosuite-reach/`" in (MODELS / "README.md").read_text()


@pytest.mark.parametrize("run", ["ids", "ids-pcgrad", "ids-gradnorm", "lang", "lang-pcgrad"])
def test_the_kept_multitask_policies_act_and_are_the_results_runs(run):
    """The policies behind multitask.json, every arm and seed kept to act (no critics):
    task-id arms take a task id, language arms an instruction."""
    import lcrl

    result = json.loads((MODELS.parent / "results" / "multitask.json").read_text())
    for seed in (0, 1, 2):
        folder = MODELS / "multitask" / run / f"seed{seed}"
        kept = result["runs"][f"{run}-s{seed}"]["kept"]
        assert kept == f"benchmarks/models/multitask/{run}/seed{seed}"
        meta = json.loads((folder / "meta.json").read_text())
        assert meta["acting_only"] == ["critic", "critic_target"] and meta["step"] == 30_000
    policy = lcrl.load(MODELS / "multitask" / run / "seed0")
    obs, _ = policy.make_env().reset(seed=0)
    action = policy.act(obs, 3 if run.startswith("ids") else "reach the yellow cube")
    assert action.shape == (2,) and np.abs(action).max() <= 1.0
    assert "`multitask/`" in (MODELS / "README.md").read_text()


def test_the_kept_learned_her_policies_act_and_are_the_results_runs():
    """The six policies behind learned-her-lang2d.json (rule and learned relabelling, seeds
    0 to 2), kept to act: each is the 30k-step run the file evaluated."""
    import lcrl

    result = json.loads((MODELS.parent / "results" / "learned-her-lang2d.json").read_text())
    for seed in (0, 1, 2):
        for run in ("rule", "learned"):
            kept = result["kept"][str(seed)][run]
            assert kept == f"benchmarks/models/learned-her-lang2d/{run}/seed{seed}"
            meta = json.loads((MODELS.parent.parent / kept / "meta.json").read_text())
            assert meta["acting_only"] == ["critic", "critic_target"]
            assert 30_000 <= meta["step"] <= 30_010
    policy = lcrl.load(MODELS / "learned-her-lang2d" / "learned" / "seed0")
    obs, _ = policy.make_env().reset(seed=0)
    action = policy.act(obs, "push the red cube left")
    assert action.shape == (2,) and np.abs(action).max() <= 1.0
    assert "`learned-her-lang2d/`" in (MODELS / "README.md").read_text()


def test_the_kept_robosuite_learned_her_policies_are_the_results_runs(one_thread):
    """The camera policies behind learned-her-robosuite.json (reach, push and lift; rule and
    learned relabelling, each training seed), kept to act, with each seed's evaluations
    kept beside them (``seedS.json``) as the figures the file pools."""
    result = json.loads((RESULTS / "learned-her-robosuite.json").read_text())
    kept, folder = result["kept"], MODELS / "learned-her-robosuite"
    assert sorted(kept) == sorted(result["final"]) and len(kept) == result["headline"]["seeds"]
    for seed, runs in kept.items():
        record = json.loads((folder / f"seed{seed}.json").read_text())
        assert record["kept"] == runs and record["eval_seed"] == result["headline"]["eval_seed"]
        for run, path in runs.items():
            assert path == f"benchmarks/models/learned-her-robosuite/{run}/seed{seed}"
            meta = json.loads((MODELS.parent.parent / path / "meta.json").read_text())
            assert meta["acting_only"] == ["critic", "critic_target"]
            assert meta["step"] >= result["headline"]["steps"]
            assert sorted(meta["config"]["env"]["families"]) == ["lift", "push", "reach"]
            for name in ("train", "heldout"):
                got = record["final"][run][name]["success"]
                assert got == pytest.approx(result["final"][seed][run][name]["success"])
    assert "`learned-her-robosuite/`" in (MODELS / "README.md").read_text()
    pytest.importorskip("robosuite")
    import lcrl

    policy = lcrl.load(folder / "learned" / f"seed{next(iter(kept))}")
    env = policy.make_env()
    try:
        obs, _ = env.reset(seed=0)
        action = policy.act(obs, "pick up the red cube")
        assert action.shape == (4,) and np.abs(action).max() <= 1.0
    finally:
        env.close()

"""The compositional benchmark's figures over seeds: means, spreads and the ratios of
held-out and paraphrase success to seen success, for the headline the issue names."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.compositional import headline, reached, summarise


def _sets(train, heldout, paraphrase):
    return {
        k: {"success": v, "ci": [max(0.0, v - 0.1), min(1.0, v + 0.1)]}
        for k, v in (("train", train), ("heldout", heldout), ("paraphrase", paraphrase))
    }


def test_summary_over_seeds_and_headline():
    grounded = summarise(
        {0: _sets(0.9, 0.7, 0.9), 1: _sets(1.0, 0.8, 0.9), 2: _sets(0.8, 0.6, 0.6)}
    )
    pooled = summarise({0: _sets(0.9, 0.3, 0.8), 1: _sets(0.9, 0.2, 0.8), 2: _sets(0.9, 0.4, 0.8)})
    assert grounded["seeds"] == [0, 1, 2]
    assert grounded["train"]["mean"] == pytest.approx(0.9)
    assert grounded["train"]["std"] == pytest.approx(0.1)
    assert (grounded["heldout"]["min"], grounded["heldout"]["max"]) == (0.6, 0.8)
    # ratios: mean over mean, and the spread of the per-seed ratios beside
    assert grounded["heldout_ratio"] == pytest.approx(0.7 / 0.9)
    assert grounded["heldout_ratio_per_seed"]["mean"] == pytest.approx((0.7 / 0.9 + 0.8 + 0.75) / 3)
    assert grounded["paraphrase_ratio"] == pytest.approx(0.8 / 0.9)
    h = headline("lang2d", {"pooled": pooled, "grounded": grounded})
    assert h["seen"] == 0.9 and h["heldout_ratio"] == round(0.7 / 0.9, 3)
    assert h["pooled_heldout_ratio"] == round(0.3 / 0.9, 3) and h["seeds"] == 3
    ok = reached("lang2d", h)
    assert ok == {"seen": True, "heldout_ratio": True, "paraphrase_ratio": False}
    assert reached("robosuite", h) == {"seen": True, "heldout_ratio": True}


def test_a_seed_that_learned_nothing_counts_in_the_means():
    arm = summarise({0: _sets(0.0, 0.0, 0.0), 1: _sets(0.8, 0.4, 0.8)})
    assert arm["train"]["mean"] == pytest.approx(0.4)
    assert arm["heldout_ratio"] == pytest.approx(0.5)
    assert arm["heldout_ratio_per_seed"]["mean"] == pytest.approx(0.5)  # the other seed only
    nothing = summarise({0: _sets(0.0, 0.0, 0.0)})
    assert nothing["heldout_ratio"] == 0.0 and nothing["heldout_ratio_per_seed"] is None


def test_report_from_finished_runs_with_an_arm_of_fewer_seeds(tmp_path, monkeypatch):
    """Finished runs are never trained again; ``--also`` adds an arm with the seeds it
    has; the headline is the last of ``--arms``, the pooled arm's figures beside it."""
    import json

    import benchmarks.common as common
    import benchmarks.compositional as comp

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    work = tmp_path / "work"
    values = {
        ("pooled", 0): (0.9, 0.2, 0.8),
        ("pooled", 1): (0.9, 0.3, 0.8),
        ("phrased", 0): (1.0, 0.9, 0.95),
        ("phrased", 1): (0.9, 0.8, 0.85),
        ("grounded", 0): (1.0, 1.0, 0.5),
    }
    for (arm, seed), v in values.items():
        run = work / f"{arm}-s{seed}"
        run.mkdir(parents=True)
        sets = _sets(*v)
        sets["heldout"]["family_object"] = {"reach": {"blue cube": {"success": v[1]}}}
        (run / "final-eval.json").write_text(json.dumps({"sets": sets}))
    args = ["--work", str(work), "--seeds", "0", "1", "--arms", "pooled", "phrased"]
    assert comp.main([*args, "--also", "grounded", "attributes"]) == 0
    out = json.loads((tmp_path / "results" / "compositional-lang2d.json").read_text())
    h = out["headline"]
    assert h["seen"] == 0.95 and h["heldout_ratio"] == round(0.85 / 0.95, 3)
    assert h["paraphrase_ratio"] == round(0.9 / 0.95, 3) and h["seeds"] == 2
    assert h["pooled_heldout_ratio"] == round(0.25 / 0.9, 3)
    assert out["reached"] == {"seen": True, "heldout_ratio": True, "paraphrase_ratio": True}
    assert out["arms"]["grounded"]["seeds"] == [0] and "attributes" not in out["arms"]
    assert "--env.phrasings" in out["arm_options"]["phrased"]
    md = (tmp_path / "results" / "compositional-lang2d.md").read_text()
    assert "| grounded | 0 |" in md and "Headline (phrased)" in md
    # how the headline arm was chosen, beside the other arm with the highest ratio
    assert out["selection"] in md and "named on the command line" in out["selection"]
    assert "the other arm with the highest ratio (grounded) has seen 1.00" in out["selection"]
    assert (tmp_path / "results" / "compositional-lang2d.png").is_file()


def test_combination_tables_pool_seeds_and_list_failures():
    from benchmarks.compositional import combination_success, combination_tables

    def run(held, seen):
        sets = _sets(0.9, 0.5, 0.8)
        sets["heldout"]["family_object"] = {"reach": {"blue cube": held}}
        sets["train"]["family_object"] = {"push": {"red cube": seen}}
        return sets

    per_arm = {
        "pooled": {
            0: run({"success": 0.0, "successes": 0, "episodes": 4},
                   {"success": 0.25, "successes": 1, "episodes": 4}),
            1: run({"success": 0.5, "successes": 2, "episodes": 4},
                   {"success": 0.5, "successes": 2, "episodes": 4}),
        },
        "grounded": {0: run({"success": 1.0, "successes": 2, "episodes": 2},
                            {"success": 1.0, "successes": 3, "episodes": 3})},
    }  # fmt: skip
    held = combination_success(per_arm, "heldout")
    assert held == {"reach blue cube": {"pooled": 0.25, "grounded": 1.0}}
    seen = combination_success(per_arm, "train")
    assert seen["push red cube"] == {"pooled": 3 / 8, "grounded": 1.0}
    md = combination_tables({"heldout": held, "train": seen})
    assert "| reach blue cube | 1.00 | 0.25 |" in md  # arms in sorted order
    assert "| push red cube | 1.00 | 0.38 |" in md
    assert "below 0.50 in some arm: none" in combination_tables(
        {"heldout": held, "train": {"push red cube": {"pooled": 0.9}}}
    )


def test_slot_selection_of_a_trained_run(tmp_path):
    """The actor's pick per instruction of each set, against the object named; a run
    without checkpoints has none."""
    import dataclasses

    from helpers import tiny

    import lcrl
    from benchmarks.compositional import selection_table, slot_selection
    from train.configs.presets import PRESETS
    from train.training.loop import Trainer

    out = tmp_path / "run"
    cfg = tiny("lang2d-quick", out, total_steps=120, learning_starts=100)
    net = dataclasses.replace(PRESETS["lang2d-quick"][1].agent.net, hidden=(32, 32))
    Trainer(dataclasses.replace(cfg, agent=dataclasses.replace(cfg.agent, net=net))).run()
    sel = slot_selection(out)
    split = lcrl.load(out).task.split  # the run's own, of the reach family

    def texts(name):
        pairs = zip(split.texts(name), split.instructions(name), strict=True)
        return [t for t, m in pairs if m.family == "reach"]

    for name in ("train", "heldout", "paraphrase"):
        n = len(texts(name))
        assert n > 0
        assert sel[name]["instructions"] == n
        assert 0.0 <= sel[name]["accuracy"] <= 1.0
        assert len(sel[name]["wrong"]) == round((1 - sel[name]["accuracy"]) * n)
        assert set(sel[name]["wrong"]) <= set(texts(name))
    assert slot_selection(tmp_path) is None
    plain = tmp_path / "plain"  # networks without a slot reader
    Trainer(tiny("lang2d-quick", plain, total_steps=110, learning_starts=100)).run()
    assert slot_selection(plain) is None
    md = selection_table({"grounded": {"0": sel, "1": None}})
    assert md.count("| grounded |") == 1 and f"{sel['train']['accuracy']:.2f}" in md
    assert selection_table({"grounded": {"0": None}}) == ""


def test_every_arm_parses_as_train_options():
    import dataclasses

    from benchmarks.compositional import ARMS, arm_args
    from train.commands.cli import parse_train_args

    configs = {arm: parse_train_args(["robosuite-reach", *arm_args(arm, 1.0)]) for arm in ARMS}
    assert configs["clipped"].sac.target_clip == 1.0
    assert configs["grounded"].sac.target_clip is None
    # the clipped arm is the grounded arm in every other option
    same = dataclasses.replace(configs["clipped"], sac=configs["grounded"].sac)
    assert same == configs["grounded"]
    assert configs["pooled"].agent.net.slot_mode == "select"
    # the preset ships 8 environments at batch 128; the benchmark's runs keep the
    # collection its results were measured with
    from benchmarks.compositional import COLLECTION

    assert (configs["clipped"].collect.envs, configs["clipped"].batch_size) == (8, 128)
    pinned = parse_train_args(["robosuite-reach", *COLLECTION["robosuite-reach"]])
    assert (pinned.collect.envs, pinned.batch_size) == (1, 256)
    # but the preset arm is the preset as shipped
    import argparse

    from benchmarks.compositional import train_command

    args = argparse.Namespace(work="w", preset="robosuite-reach", steps=30, grounding=1.0)
    args.phrasings = 16
    assert "--collect.envs" in train_command(args, "clipped", 0)
    shipped = train_command(args, "preset", 0)
    assert "--collect.envs" not in shipped and shipped[-8:] == [
        "--out", "w/preset-s0", "--seed", "0", "--total-steps", "30", "--overwrite",
        "--no-progress",
    ]  # fmt: skip


FAKE_LCRL = """
import json, sys, time
from pathlib import Path
argv = sys.argv[1:]
with open({calls!r}, "a") as f:
    f.write(argv[0] + " " + argv[argv.index("--out") + 1 if "--out" in argv else 1] + "\\n")
if argv[0] == "train" and "--seed" in argv and argv[argv.index("--seed") + 1] == "9":
    sys.exit(3)
if argv[0] == "train":
    Path(argv[argv.index("--out") + 1]).mkdir(parents=True)
if argv[0] == "eval":
    Path(argv[argv.index("--json") + 1]).write_text(json.dumps({{"sets": {{}}}}))
"""


def test_each_run_trains_then_evaluates_and_a_failure_stops_the_rest(tmp_path, monkeypatch):
    """run_all starts lcrl train, then lcrl eval of the same run, each a child that dies
    with the benchmark; a run that fails is named and its evaluation never starts."""
    import argparse
    import sys

    import benchmarks.compositional as comp

    calls = tmp_path / "calls.txt"
    fake = tmp_path / "fake_lcrl.py"
    fake.write_text(FAKE_LCRL.format(calls=str(calls)))
    monkeypatch.setattr(comp, "LCRL", [sys.executable, str(fake)])
    monkeypatch.setattr(comp.time, "sleep", lambda s: None)
    args = argparse.Namespace(
        seeds=[0, 1],
        arms=["pooled"],
        work=str(tmp_path / "w"),
        preset="lang2d",
        steps=10,
        grounding=1.0,
        phrasings=16,
        episodes=2,
        parallel=2,
    )
    seconds = comp.run_all(args)
    assert sorted(seconds) == ["pooled-s0", "pooled-s1"]
    lines = calls.read_text().split("\n")
    for seed in (0, 1):
        run = tmp_path / "w" / f"pooled-s{seed}"
        assert lines.index(f"train {run}") < lines.index(f"eval {run}")
        assert (run / "final-eval.json").is_file()

    args.seeds, args.work = [9], str(tmp_path / "bad")
    with pytest.raises(SystemExit, match="pooled-s9 failed"):
        comp.run_all(args)
    assert "eval " + str(tmp_path / "bad" / "pooled-s9") not in calls.read_text()


def test_canonical_arms_reuse_the_runs_and_add_their_own_evaluation(tmp_path, monkeypatch):
    """``--canonical phrased`` evaluates the phrased runs again with ``lcrl eval
    --canonical-reader`` into canonical-eval.json (never retraining), reports them as
    ``phrased-canonical`` and can head the results; evaluations already there are kept."""
    import json

    import benchmarks.common as common
    import benchmarks.compositional as comp

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    work = tmp_path / "work"
    for seed in (0, 1):
        run = work / f"phrased-s{seed}"
        run.mkdir(parents=True)
        (run / "final-eval.json").write_text(json.dumps({"sets": _sets(0.9, 0.9, 0.6)}))
    calls = []

    def fake_run(cmd, **kwargs):  # what lcrl eval --canonical-reader would write
        calls.append(cmd)
        out = cmd[cmd.index("--json") + 1]
        with open(out, "w") as f:
            json.dump({"sets": _sets(0.9, 0.9, 0.85)}, f)

        class Done:
            returncode = 0

        return Done()

    monkeypatch.setattr(comp.subprocess, "run", fake_run)
    monkeypatch.setattr(common, "git_commit", lambda: "abc")  # no git through the fake
    args = ["--work", str(work), "--seeds", "0", "1", "--arms", "phrased"]
    args += ["--canonical", "phrased", "--headline-arm", "phrased-canonical"]
    assert comp.main(args) == 0
    assert len(calls) == 2 and all("--canonical-reader" in c for c in calls)
    assert all(c[c.index("eval") + 1].endswith(("phrased-s0", "phrased-s1")) for c in calls)
    out = json.loads((tmp_path / "results" / "compositional-lang2d.json").read_text())
    assert out["headline"]["paraphrase_ratio"] == round(0.85 / 0.9, 3)
    assert out["arms"]["phrased"]["paraphrase"]["mean"] == pytest.approx(0.6)
    assert out["eval_options"] == {"phrased-canonical": ["--canonical-reader"]}
    assert out["arm_options"]["phrased-canonical"] == out["arm_options"]["phrased"]
    calls.clear()
    assert comp.main(args) == 0 and calls == []  # kept, not evaluated again


def test_rerunning_one_arm_keeps_the_other_arms_of_the_previous_file(tmp_path, monkeypatch):
    """An invocation that trains only the new arm keeps the previous file's other arms
    (the pooled baseline the headline compares with), marked with where they came from;
    the arms it reran are replaced."""
    import json

    import benchmarks.common as common
    import benchmarks.compositional as comp

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    work = tmp_path / "work"

    def finish(arm, seed, v):
        run = work / f"{arm}-s{seed}"
        run.mkdir(parents=True, exist_ok=True)
        (run / "final-eval.json").write_text(json.dumps({"sets": _sets(*v)}))

    for seed in (0, 1):
        finish("pooled", seed, (0.9, 0.2, 0.8))
        finish("phrased", seed, (0.8, 0.7, 0.6))
    args = ["--work", str(work), "--seeds", "0", "1"]
    assert comp.main([*args, "--arms", "pooled", "phrased"]) == 0
    first = json.loads((tmp_path / "results" / "compositional-lang2d.json").read_text())
    assert first["headline"]["seen"] == 0.8 and "kept_from" not in first
    # the phrased runs are redone (better); the pooled runs are gone from the work folder
    import shutil

    for seed in (0, 1):
        shutil.rmtree(work / f"pooled-s{seed}")
        shutil.rmtree(work / f"phrased-s{seed}")
        finish("phrased", seed, (1.0, 0.9, 0.95))
    assert comp.main([*args, "--arms", "phrased"]) == 0
    out = json.loads((tmp_path / "results" / "compositional-lang2d.json").read_text())
    assert out["headline"]["seen"] == 1.0 and out["headline"]["paraphrase_ratio"] == 0.95
    assert out["headline"]["pooled_heldout_ratio"] == round(0.2 / 0.9, 3)  # kept beside
    assert out["arms"]["pooled"] == first["arms"]["pooled"]
    assert set(out["per_seed"]["pooled"]) == {"0", "1"}
    assert list(out["kept_from"]) == ["pooled"]
    assert out["kept_from"]["pooled"]["command"] == first["command"]
    md = (tmp_path / "results" / "compositional-lang2d.md").read_text()
    assert "kept from the previous file" in md and "| pooled | 0 |" in md


def test_a_test_seed_headline_and_the_policies_kept(tmp_path, monkeypatch):
    """``--test-seed`` reports the headline arm's evaluation on that seed (a seed no choice
    used), its own evaluation beside it; ``--keep`` keeps the arm's policies, reading
    through the canonical reader; seeds where choices were made are refused."""
    import json

    import benchmarks.common as common
    import benchmarks.compositional as comp

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    work = tmp_path / "work"
    kept: list[tuple[str, str, bool]] = []

    def keep(source, dest, reader, acting_only=False, reader_cache=True):
        kept.append((Path(source).name, Path(dest).name, reader and acting_only and reader_cache))
        return Path(dest)

    monkeypatch.setattr("train.policies.loading.keep_checkpoint", keep)
    for seed, (own, read, test) in enumerate([(0.9, 0.95, 0.8), (1.0, 0.9, 0.7)]):
        run = work / f"preset-s{seed}"
        run.mkdir(parents=True)
        (run / "final-eval.json").write_text(json.dumps({"sets": _sets(own, own, own)}))
        (run / "canonical-eval.json").write_text(json.dumps({"sets": _sets(read, read, read)}))
        (run / "test-eval-13.json").write_text(json.dumps({"sets": _sets(test, 0.6, 0.5)}))
    args = ["--work", str(work), "--seeds", "0", "1", "--arms", "preset", "--canonical"]
    args += ["preset", "--headline-arm", "preset-canonical", "--name", "comp-test"]
    for used in (0, 1):  # lcrl eval's default seed, a validation seed
        with pytest.raises(SystemExit):
            comp.main([*args, "--test-seed", str(used)])
    keep = ["--keep", str(tmp_path / "models"), "--note", "re-measured on a test seed"]
    assert comp.main([*args, "--test-seed", "13", *keep]) == 0
    out = json.loads((tmp_path / "results" / "comp-test.json").read_text())
    assert set(out["arms"]) == {"preset", "preset-canonical", "preset-canonical@seed13"}
    h = out["headline"]
    assert h["seen"] == 0.75 and h["heldout_ratio"] == round(0.6 / 0.75, 3)
    assert out["arms"]["preset-canonical"]["train"]["mean"] == pytest.approx(0.925)
    assert out["eval_options"]["preset-canonical@seed13"] == ["--canonical-reader", "--seed", "13"]
    assert "test seed 13, which no choice used" in out["selection"]
    assert out["arm_options"]["preset-canonical@seed13"] == []  # the preset as shipped
    assert kept == [("preset-s0", "seed0", True), ("preset-s1", "seed1", True)]
    assert set(out["models"]) == {"0", "1"} and out["note"] == "re-measured on a test seed"
    md = (tmp_path / "results" / "comp-test.md").read_text()
    assert "re-measured on a test seed" in md and "Policies kept (to act)" in md


def test_a_kept_checkpoint_has_weights_not_replay(tmp_path):
    """keep_checkpoint copies a run's latest checkpoint without what only resuming reads,
    sets the canonical reader's default, seals it, and it loads; a folder without a
    checkpoint is refused in one line."""
    import json

    import numpy as np
    from helpers import tiny

    import lcrl
    from lcrl.errors import LcrlError
    from train.policies.loading import RESUME_ONLY, keep_checkpoint
    from train.training.loop import Trainer

    run = tmp_path / "run"
    Trainer(tiny("lang2d-quick", run, total_steps=110, learning_starts=100)).run()
    dest = keep_checkpoint(run, tmp_path / "kept" / "seed0", canonical_reader=True)
    names = {f.name for f in dest.iterdir()}
    assert "weights.safetensors" in names and not names & set(RESUME_ONLY)
    assert json.loads((dest / "meta.json").read_text())["config"]["env"]["canonical_reader"]
    assert lcrl.load(dest, env_overrides={"canonical_reader": False}).task is not None
    again = keep_checkpoint(dest, dest, canonical_reader=False)  # a checkpoint, kept in place
    assert not json.loads((again / "meta.json").read_text())["config"]["env"]["canonical_reader"]
    # kept to act: without the critics, a fraction of the size, acting the same
    small = keep_checkpoint(run, tmp_path / "small", acting_only=True)
    assert json.loads((small / "meta.json").read_text())["acting_only"] == [
        "critic", "critic_target",
    ]  # fmt: skip
    size = (small / "weights.safetensors").stat().st_size
    assert size < 0.5 * (dest / "weights.safetensors").stat().st_size
    policy, kept_policy = lcrl.load(run), lcrl.load(small)
    obs, _ = policy.make_env().reset(seed=3)
    text = policy.instructions[0]
    assert np.allclose(policy.act(obs, text), kept_policy.act(obs, text))
    with pytest.raises(LcrlError, match="neither a checkpoint nor a run"):
        keep_checkpoint(tmp_path / "nothing", tmp_path / "x")
    # a policy made of others keeps its members (folders inside the checkpoint)
    from train.policies.ensemble import write_ensemble

    other = tmp_path / "other"
    Trainer(tiny("lang2d-quick", other, total_steps=110, learning_starts=100, seed=1)).run()
    ensemble = write_ensemble(tmp_path / "ens", [str(run), str(other)], False)
    kept_ensemble = keep_checkpoint(ensemble, tmp_path / "ens-kept", acting_only=True)
    assert (kept_ensemble / "members" / "1" / "meta.json").is_file()
    assert np.allclose(lcrl.load(ensemble).act(obs, text), lcrl.load(kept_ensemble).act(obs, text))
    # lcrl export: the same copy, refusing to replace a folder unless told to
    from train.commands.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(run), str(dest)])
    assert exit_info.value.code == 2
    main(["export", str(run), str(dest), "--overwrite", "--canonical-reader", "off"])
    assert not json.loads((dest / "meta.json").read_text())["config"]["env"]["canonical_reader"]

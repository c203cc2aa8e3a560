"""The learning-curve benchmark reads a finished run again only when it learned the same
thing: same config apart from where it was written and how long it ran."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.learning_curves import SUITES, reusable, run_config
from train.configs.config import BufferConfig


@pytest.fixture
def job(tmp_path):
    suite = SUITES["lang2d-learned"]
    return ("lang2d", {}, tmp_path / "new", suite, 20_000, 0)


def _finished_run(folder, cfg, steps):
    folder.mkdir()
    saved = json.loads(json.dumps(dataclasses.asdict(cfg)))
    saved.update(out=str(folder), total_steps=steps[-1], resolved_algo="sac")
    saved.pop("relabel")  # a run saved before the option existed ran with its default
    (folder / "config.json").write_text(json.dumps(saved))
    rows = ["step,train/success"] + [f"{s},{s / 100_000}" for s in steps]
    (folder / "eval.csv").write_text("\n".join(rows) + "\n")


def test_a_run_with_the_same_config_is_cut_at_the_budget(job, tmp_path):
    cfg = run_config(*job)
    old = tmp_path / "old"
    _finished_run(old, dataclasses.replace(cfg, total_steps=50_000), [10_003, 20_011, 30_002])
    curve = reusable(cfg, old)
    assert [int(r["step"]) for r in curve] == [10_003, 20_011]  # first evaluation >= 20k
    # too short a run, or a different learner, is trained again
    assert reusable(dataclasses.replace(cfg, total_steps=40_000), old) is None
    other = dataclasses.replace(cfg, buffer=BufferConfig(k=0))
    assert reusable(other, old) is None
    assert reusable(cfg, tmp_path / "missing") is None
    # an option added later, set away from its default, is a different config
    learned = run_config(
        *job[:1], {"relabel": SUITES["lang2d-learned"]["runs"]["learned"][1]["relabel"]}, *job[2:]
    )
    assert reusable(learned, old) is None


def test_the_captioner_markdown_takes_the_relabelling_figures(tmp_path):
    from benchmarks.learned_her import update_captioner_markdown

    md = tmp_path / "captioner-lang2d.md"
    old = "- learned_her_seen: 0.61 (see learned-relabelling results)."
    md.write_text(f"# t\n\nCommand: `x`\n\n{old}\n")
    update_captioner_markdown(md, {"learned_her_seen": 0.7, "rule_her_seen": 0.74})
    lines = md.read_text().splitlines()
    assert "- learned_her_seen: 0.70 (see learned-relabelling results)." in lines
    assert lines[-1] == "- rule_her_seen: 0.74 (see learned-relabelling results)."
    assert "Command: `x`" in lines and sum("learned_her_seen" in x for x in lines) == 1


def test_runs_started_one_by_one_are_taken_only_with_their_own_config(tmp_path):
    import argparse

    from benchmarks.learned_her import reuse, run_args
    from train.commands.cli import parse_train_args

    def _config_of(cmd):
        cfg = parse_train_args(cmd[cmd.index("train") + 1 :])
        return json.loads(json.dumps({**dataclasses.asdict(cfg), "resolved_algo": "sac"}))

    args = argparse.Namespace(
        env="lang2d",
        work=str(tmp_path),
        steps=1000,
        eval_every=500,
        eval_episodes=5,
        seed=0,
        perception="",
        target_clip=1.0,
        captioner="runs/cap",
        threshold=0.7,
    )
    for name in ("rule", "learned"):
        run = tmp_path / name
        run.mkdir()
        (run / "config.json").write_text(json.dumps(_config_of(run_args(args, name))))
    with pytest.raises(SystemExit, match="not a finished run"):
        reuse(tmp_path / "rule", tmp_path / "rule", args, "rule")
    for name in ("rule", "learned"):
        (tmp_path / name / "report.md").write_text("done\n")
    assert reuse(tmp_path / "rule", tmp_path / "rule", args, "rule") >= 0
    assert reuse(tmp_path / "learned", tmp_path / "learned", args, "learned") >= 0
    with pytest.raises(SystemExit, match="differs from the learned run's"):
        reuse(tmp_path / "rule", tmp_path / "learned", args, "learned")
    # a run saved before an option existed ran with its default
    saved = json.loads((tmp_path / "rule" / "config.json").read_text())
    del saved["relabel"]["agree"]
    (tmp_path / "rule" / "config.json").write_text(json.dumps(saved))
    (tmp_path / "rule" / "report.md").write_text("done\n")  # written at the end of a run
    assert reuse(tmp_path / "rule", tmp_path / "rule", args, "rule") >= 0
    # the target clip is part of the config: a run without it is another run
    with pytest.raises(SystemExit, match="differs"):
        reuse(
            tmp_path / "rule",
            tmp_path / "rule",
            argparse.Namespace(**{**vars(args), "target_clip": 0.0}),
            "rule",
        )


def test_learned_her_pools_seeds():
    import argparse

    from benchmarks.learned_her import mean_interval, pool, seed_args

    def result(k, n, push):
        return {"episodes": n, "successes": k, "success": k / n, "families": {"push": push}}

    a = result(6, 10, {"episodes": 4, "successes": 1, "success": 0.25})
    b = result(9, 10, {"episodes": 6, "successes": 3, "success": 0.5})
    got = pool([a, b])
    assert got["success"] == pytest.approx(15 / 20) and got["episodes"] == 20
    assert got["ci"][0] < 0.75 < got["ci"][1]
    assert got["families"]["push"]["success"] == pytest.approx(4 / 10)
    low, high = mean_interval([0.1, 0.2, 0.3])
    assert low < 0.2 < high and high - 0.2 == pytest.approx(0.2 - low)
    args = argparse.Namespace(work="runs/x", seed=0)
    assert seed_args(args, 2, multi=True).work == "runs/x/seed2"
    assert seed_args(args, 2, multi=False).work == "runs/x" and args.seed == 0


def test_learned_her_gaps_along_the_curves_use_the_points_every_run_has():
    from benchmarks.learned_her import curve_gaps

    def rows(values, push):
        return [
            {"step": 5000 * (i + 1), "train/success": v, "train/push": p}
            for i, (v, p) in enumerate(zip(values, push, strict=True))
        ]

    curves = {
        "0": {
            "rule": rows([0.4, 0.8, 0.9], [0.0, 0.6, 0.8]),
            "learned": rows([0.2, 0.6], [0, 0.2]),
        },
        "1": {"rule": rows([0.6, 1.0], [0.2, 1.0]), "learned": rows([0.4, 0.8], [0.2, 0.6])},
    }
    got = curve_gaps(curves)
    assert [g["step"] for g in got] == [5000, 10000]
    assert got[1]["rule"] == pytest.approx(0.9) and got[1]["learned"] == pytest.approx(0.7)
    assert got[1]["gap"] == pytest.approx(0.2) and got[0]["gap"] == pytest.approx(0.2)
    assert got[1]["rule_push"] == pytest.approx(0.8) and got[1]["learned_push"] == pytest.approx(
        0.4
    )


def test_reward_onset_counts_steps_around_the_first_success():
    from benchmarks.reward_onset import first_steps, onset_rates

    labels = [[], [], [0], [0, 1], [1]]
    assert first_steps(labels, [True, True]) == {0: 2, 1: 3}
    assert first_steps(labels, [True, False]) == {0: 2}
    # instruction 0 accepted from its first step on, instruction 1 a step late
    probs = np.array([[0, 0], [0.1, 0], [0.95, 0.2], [0.95, 0.3], [0.9, 0.95]])
    rates = onset_rates([(probs, {0: 2, 1: 3})], ["push", "reach"], [-1, 0, 1], 0.9)
    assert rates["push"] == {-1: (0.0, 1), 0: (1.0, 1), 1: (1.0, 1)}
    assert rates["reach"][0] == (0.0, 1) and rates["reach"][1] == (1.0, 1)


def test_push_misses_sort_failures_by_how_far_the_object_got():
    from benchmarks.learned_her import push_failure_lines
    from benchmarks.push_misses import miss_bin, summarise

    assert [miss_bin(a) for a in (0.0, 0.09, 0.5, 0.99, 1.0, 1.7)] == [
        "untouched",
        "untouched",
        "short",
        "short",
        "drift",
        "drift",
    ]
    eps = [
        {"success": True, "along": 1.2, "reached": True, "other_moved": False},
        {"success": False, "along": 0.0, "reached": True, "other_moved": False},
        {"success": False, "along": 0.0, "reached": False, "other_moved": True},
        {"success": False, "along": 0.6, "reached": True, "other_moved": False},
    ]
    got = summarise(eps)
    assert got["success"] == pytest.approx(0.25) and got["failures"] == 3
    assert got["untouched"] == pytest.approx(2 / 3, abs=1e-3) and got["short"] == pytest.approx(
        1 / 3, abs=1e-3
    )
    assert got["drift"] == 0 and got["reached"] == pytest.approx(2 / 3, abs=1e-3)
    assert got["other_moved"] == pytest.approx(1 / 3, abs=1e-3) and got["median_along"] == 0.0
    lines = push_failure_lines({"rule": got})
    assert any(line.startswith("| rule | 4 | 0.25 | 0.67 | 0.33 | 0.00 | 0.67 |") for line in lines)
    assert push_failure_lines({}) == []


def test_push_misses_sort_the_reward_models_verdicts_against_the_rule():
    from benchmarks.push_misses import summarise_rewards

    steps = [
        {"rule": False, "learned": False, "along": 0.0, "at_object": True},
        {"rule": False, "learned": True, "along": 0.85, "at_object": True},  # a step early
        {"rule": False, "learned": True, "along": 0.05, "at_object": True},  # never moved
        {"rule": True, "learned": True, "along": 1.1, "at_object": True},
        {"rule": True, "learned": False, "along": 1.3, "at_object": False},
    ]
    got = summarise_rewards(steps)
    assert (got["steps"], got["rule_rewards"], got["learned_rewards"]) == (5, 2, 3)
    assert got["precision"] == pytest.approx(1 / 3, abs=1e-3) and got["recall"] == pytest.approx(
        0.5
    )
    assert got["false_rewards"] == 2 and got["missed_rewards"] == 1
    assert got["false_short"] == pytest.approx(0.5) and got["false_untouched"] == pytest.approx(0.5)
    assert got["false_untouched_at_object"] == pytest.approx(0.5) and got["false_drift"] == 0
    from benchmarks.push_misses import episode_rewards

    def ep(rule, learned):
        return {"steps": [{"rule": r, "learned": x} for r, x in zip(rule, learned, strict=True)]}

    got = episode_rewards(
        [
            ep([0, 0, 1], [1, 0, 1]),  # rewarded early, and at its success
            ep([0, 1, 1], [0, 0, 1]),  # a step late
            ep([0, 0, 0], [0, 1, 1]),  # rewarded, never succeeded
            ep([0, 0, 0], [0, 0, 0]),
        ]
    )
    assert got == {"episodes": 4, "false_before_success": 2, "successes": 2, "hit_at_success": 1}
    empty = summarise_rewards([])
    assert empty["false_rewards"] == 0 and np.isnan(empty["precision"])


def test_reach_rewards_count_the_reward_models_reach_verdicts_against_the_rule():
    from benchmarks.reach_rewards import summarise

    steps = [
        {"rule": True, "prob": 0.95, "moving": True, "gap": 0.015},  # in contact, pushing
        {"rule": True, "prob": 0.6, "moving": True, "gap": 0.016},  # missed at 0.7 and 0.9
        {"rule": True, "prob": 0.75, "moving": False, "gap": 0.019},
        {"rule": False, "prob": 0.8, "moving": False, "gap": 0.025},  # false at 0.5, 0.7
        {"rule": False, "prob": 0.1, "moving": False, "gap": 0.2},
    ]
    got = summarise(steps)
    assert (got["steps"], got["rule_reached"], got["moving"]) == (5, 3, 2)
    at5, at7, at9 = (got["thresholds"][t] for t in ("0.5", "0.7", "0.9"))
    assert at5["recall"] == 1.0 and at5["precision"] == pytest.approx(3 / 4, abs=1e-3)
    assert at7["recall"] == pytest.approx(2 / 3, abs=1e-3) and at7["recall_moving"] == 0.5
    assert at7["recall_still"] == 1.0 and at7["precision"] == pytest.approx(2 / 3, abs=1e-3)
    assert at9["recall"] == pytest.approx(1 / 3, abs=1e-3) and at9["precision"] == 1.0
    first, second, *_, last = got["bands"]
    assert (
        first["steps"] == 3
        and first["rule"] == 1.0
        and first["at_0.9"] == pytest.approx(1 / 3, abs=1e-3)
    )
    assert second["steps"] == 1 and second["rule"] == 0.0 and second["mean_prob"] == 0.8
    assert last["steps"] == 1 and sum(b["steps"] for b in got["bands"]) == 5


def test_push_misses_follow_a_checkpoint_on_its_push_instructions(tmp_path, one_thread):
    from helpers import tiny

    from benchmarks.push_misses import run_pushes
    from lcrl.errors import LcrlError
    from train.training.loop import Trainer

    out = tmp_path / "run"
    Trainer(tiny("lang2d", out, total_steps=120, learning_starts=100)).run()
    eps = run_pushes(out, 3)
    assert len(eps) == 3 and all(e["instruction"].startswith("push ") for e in eps)
    for e in eps:
        assert {"success", "along", "reached", "other_moved"} <= set(e)
        assert not e["success"] or e["along"] >= 1.0  # a success moved it far enough
    reach = tmp_path / "reach"
    Trainer(tiny("lang2d-quick", reach, total_steps=120, learning_starts=100)).run()
    with pytest.raises(LcrlError, match="no push instruction"):
        run_pushes(reach, 1)


def test_captioner_benchmark_trains_its_models_apart_with_one_progress_bar():
    from benchmarks.captioning import side_by_side_parts
    from captioner.learned import CaptionTrainConfig

    cfg = CaptionTrainConfig(data="d.h5", out="ckpt", models=("captioner", "reward"), threads=2)
    parts = side_by_side_parts(cfg)
    assert list(parts) == ["captioner", "reward"]
    assert [p.models for p in parts.values()] == [("captioner",), ("reward",)]
    assert [p.out for p in parts.values()] == ["ckpt-captioner", "ckpt-reward"]
    assert [p.progress for p in parts.values()] == [True, False]
    assert all(p.threads == 1 for p in parts.values())
    quiet = side_by_side_parts(dataclasses.replace(cfg, progress=False))
    assert not any(p.progress for p in quiet.values())


def test_learned_her_keeps_each_seeds_runs_to_act(tmp_path):
    import argparse
    import shutil

    from benchmarks.learned_her import keep_runs

    models = Path(__file__).resolve().parent.parent / "benchmarks" / "models"
    work = tmp_path / "work"
    for run in ("rule", "learned"):  # a kept policy is a checkpoint folder too
        shutil.copytree(models / "learned-her-lang2d" / run / "seed1", work / run)
    ns = argparse.Namespace(seed=1, work=str(work))
    kept = keep_runs(str(tmp_path / "keep"), [ns], ("rule", "learned"))
    assert kept == {"1": {r: str(tmp_path / "keep" / r / "seed1") for r in ("rule", "learned")}}
    for run in ("rule", "learned"):
        folder = tmp_path / "keep" / run / "seed1"
        meta = json.loads((folder / "meta.json").read_text())
        assert meta["acting_only"] == ["critic", "critic_target"]
        assert (folder / "weights.safetensors").is_file()


def test_learned_her_seeds_kept_by_an_earlier_invocation_are_read_back_only_if_alike(tmp_path):
    import argparse

    from benchmarks.learned_her import read_record, run_args, write_record

    ns = argparse.Namespace(
        env="robosuite",
        work=str(tmp_path / "work" / "seed1"),
        steps=1000,
        eval_every=500,
        eval_episodes=5,
        seed=1,
        perception="p/model",
        target_clip=1.0,
        captioner="cap/seed{seed}/model",
        threshold=0.5,
        families=["reach", "push", "lift"],
        max_episode_steps=100,
        eval_seed=1000,
        final_episodes=100,
    )
    keep = str(tmp_path / "kept")
    assert read_record(keep, ns) is None
    final = {"rule": {"train": {"success": 0.9}}, "learned": {"train": {"success": 0.8}}}
    write_record(keep, ns, final, {"rule": []}, {"rule": 10.0}, {}, {"rule": "k/rule/seed1"})
    assert "--env.families" in run_args(ns, "rule") and "cap/seed1/model" in run_args(ns, "learned")
    moved = argparse.Namespace(**{**vars(ns), "work": str(tmp_path / "elsewhere")})
    assert read_record(keep, moved)["final"] == final  # where the runs were written: no matter
    for change in ({"threshold": 0.7}, {"eval_seed": 7}, {"steps": 2000}):
        with pytest.raises(SystemExit, match="other settings"):
            read_record(keep, argparse.Namespace(**{**vars(ns), **change}))


def test_learned_her_takes_kept_rule_runs_only_from_the_same_rule_command(tmp_path):
    import argparse
    import shutil

    from benchmarks.learned_her import (
        keep_runs,
        read_record,
        rule_record,
        run_curve,
        run_path,
        write_record,
    )

    ns = argparse.Namespace(
        env="lang2d", work=str(tmp_path / "work"), steps=1000, eval_every=500, eval_episodes=5,
        seed=1, perception="", target_clip=0.0, captioner="cap/seed{seed}/model",
        threshold=0.5, eval_seed=1000, final_episodes=100,
    )  # fmt: skip
    keep = tmp_path / "kept"
    models = Path(__file__).resolve().parent.parent / "benchmarks" / "models"
    shutil.copytree(models / "learned-her-lang2d" / "rule" / "seed1", keep / "rule" / "seed1")
    curve = [{"step": 500.0, "train/success": 0.4}]
    final = {"rule": {"train": {"success": 0.9}}, "learned": {"train": {"success": 0.8}}}
    write_record(str(keep), ns, final, {"rule": curve}, {"rule": 10.0}, {}, {})
    # another learned run (a new captioner), another evaluation seed: the same rule run
    new = argparse.Namespace(**{**vars(ns), "captioner": "other/seed{seed}", "eval_seed": 1001})
    new.rule_from = str(keep)
    new.rule_record = rule_record(str(keep), new)
    assert run_curve(new, "rule") == curve
    assert read_record(str(keep), new) is None  # the source it replaces, not its own record
    # evaluated in a copy (an evaluation writes beside the policy), kept where it is
    assert run_path(new, "rule") == tmp_path / "work" / "rule"
    assert (tmp_path / "work" / "rule" / "weights.safetensors").is_file()
    (tmp_path / "work" / "rule" / "eval-seed1001.json").write_text("{}")
    kept = keep_runs(str(keep), [new], ("rule",))
    assert kept == {"1": {"rule": str(keep / "rule" / "seed1")}}
    assert not (keep / "rule" / "seed1" / "eval-seed1001.json").exists()
    with pytest.raises(SystemExit, match="another command"):
        rule_record(str(keep), argparse.Namespace(**{**vars(new), "steps": 2000}))
    with pytest.raises(SystemExit, match="no kept rule run of seed 2"):
        rule_record(str(keep), argparse.Namespace(**{**vars(new), "seed": 2}))

"""benchmarks/preset_stability.py: its verdicts on written curves, and the result file that
keeps finished runs so that another machine adds to them instead of training them again."""

from __future__ import annotations

import argparse
import json
import re

import pytest

from benchmarks import common, preset_stability


def write_run(folder, q, seen):
    folder.mkdir(parents=True)
    rows = ["step,success,q,q_max"] + [
        f"{100 * (i + 1)},0.5,{v},{v + 0.1}" for i, v in enumerate(q)
    ]
    (folder / "progress.csv").write_text("\n".join(rows) + "\n")
    evals = ["step,train/success,heldout/success"]
    evals += [f"{100 * (i + 1)},{v},{v / 2}" for i, v in enumerate(seen)]
    (folder / "eval.csv").write_text("\n".join(evals) + "\n")


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.setattr(preset_stability, "WORK", tmp_path / "runs")
    monkeypatch.setattr(preset_stability, "RESULTS_DIR", tmp_path / "results")
    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    return tmp_path


def test_a_run_diverges_when_q_leaves_the_bound_or_success_falls(work):
    folder = preset_stability.run_folder
    write_run(folder("lang2d", 21), q=[0.5, 0.8, 0.9], seen=[0.5, 0.9, 0.95])
    write_run(folder("lang2d", 22), q=[0.5, 1.2, 3.0], seen=[0.5, 0.9, 0.95])
    write_run(folder("lang2d", 23), q=[0.5, 0.8, 0.9], seen=[0.5, 0.9, 0.6])
    calm, high, fallen = (preset_stability.analyse("lang2d", s) for s in (21, 22, 23))
    assert preset_stability.bounds("lang2d")[1] == pytest.approx(1.0)
    assert not calm["diverged"] and calm["final_seen"] == 0.95 and calm["final_heldout"] == 0.475
    assert high["diverged"] and high["q_left_bound_at"] == [200, 300]
    assert fallen["diverged"] and fallen["largest_fall"] == pytest.approx(0.3)
    assert calm["curves"]["q"] == [0.5, 0.8, 0.9] and calm["curves"]["step"] == [100, 200, 300]


def test_the_result_file_keeps_finished_runs_for_the_next_machine(work):
    write_run(preset_stability.run_folder("lang2d", 21), q=[0.5, 0.8], seen=[0.5, 0.9])
    args = argparse.Namespace(presets=["lang2d", "robosuite-reach"], seeds=[21, 22])
    preset_stability.write([preset_stability.analyse("lang2d", 21)], args, common.machine())
    saved = json.loads((work / "results" / "preset-stability.json").read_text())
    assert saved["headline"] == {
        "runs": 1,
        "diverged": 0,
        "min_seen": {"lang2d": 0.9},
        "planned": 4,
        "complete": False,
    }
    assert saved["git"] == "unknown" and saved["date"]  # results outside a checkout
    assert saved["runs"][0]["commit"] == "unknown"
    markdown = (work / "results" / "preset-stability.md").read_text()
    assert "1 of 4 planned runs finished" in markdown
    assert "robosuite-reach seed 22" in markdown  # what is still to train, named
    kept = preset_stability.recorded()
    assert set(kept) == {("lang2d", 21)}
    # the run folder gone (another machine), the run is still counted, and not trained again
    import shutil

    shutil.rmtree(work / "runs")
    assert kept[("lang2d", 21)]["final_seen"] == 0.9
    totals = {"lang2d": 400, "robosuite-reach": 300}
    names = [name for name, _, _ in preset_stability.pending(args.presets, [21, 22], totals, kept)]
    assert names == ["robosuite-reach seed 21", "lang2d seed 22", "robosuite-reach seed 22"]
    _, argv, _ = preset_stability.pending(["lang2d"], [22], totals, kept)[0]
    assert argv[-6:] == ["--seed", "22", "--agent.seed", "22", "--overwrite", "--no-progress"]
    # the code that trains a run is named when it starts, beside the run folders
    assert preset_stability.trained_by("lang2d", 22) == common.git_commit()
    assert (work / "results" / "preset-stability.png").is_file()


def test_results_name_the_commit_they_were_measured_on():
    commit = common.git_commit()  # this checkout
    assert commit == "unknown" or re.fullmatch(r"[0-9a-f]{12}(\+changes)?", commit)


def test_the_protocol_refuses_a_validation_seed_a_composite_or_unlike_peers(tmp_path):
    from benchmarks import protocol
    from lcrl.errors import LcrlError

    assert protocol.check_test_seed(7) == 7
    with pytest.raises(LcrlError, match="used for choices"):
        protocol.check_test_seed(protocol.VALIDATION_SEEDS[0])
    single, mean = tmp_path / "single", tmp_path / "mean"
    for folder, meta in ((single, {"config": {}}), (mean, {"ensemble": {"members": []}})):
        folder.mkdir()
        (folder / "meta.json").write_text(json.dumps(meta))
    assert protocol.check_single_policy(single) == single
    with pytest.raises(LcrlError, match="made of other policies"):
        protocol.check_single_policy(mean)
    with pytest.raises(LcrlError, match="not a checkpoint"):
        protocol.check_single_policy(tmp_path)
    protocol.check_like_for_like({"precision": "float32"}, {"precision": "float32"})
    with pytest.raises(LcrlError, match="precision 'bfloat16' against 'float32'"):
        protocol.check_like_for_like({"precision": "bfloat16"}, {"precision": "float32"})


def test_the_speed_ratio_of_each_round_pairs_the_rounds_that_ran_next_to_each_other():
    pytest.importorskip("matplotlib")
    from benchmarks.speed_vs_sb3 import like_for_like_headline, paired_ratios

    rates = {"1": {"lcrl": [90.0, 60.0], "lcrl-bf16": [100.0, 80.0], "sb3": [60.0, 50.0]}}
    assert paired_ratios(rates) == {"1": [1.5, 1.2]}
    ratios = {"1": {"lcrl": 1.4, "lcrl-bf16": 1.8}, "2": {"lcrl": 1.6, "lcrl-bf16": 1.7}}
    head = like_for_like_headline(ratios)
    assert (head["ratio_1thread"], head["ratio_2threads"], head["precision"]) == (1.4, 1.6, "fp32")
    assert head["ratio_1thread_bf16"] == 1.8

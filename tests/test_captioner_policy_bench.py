"""benchmarks/captioner_policy.py: its datasets, arms and headline (no training)."""

from __future__ import annotations

from pathlib import Path

from benchmarks import captioner_policy as cp
from benchmarks.captioner_heads import TARGETS


def _res(seen: float, held: float, auc: float) -> dict:
    fam = {"reach": {"rate": seen, "n": 10}}
    return {
        "seen": {"exact_match": seen, "auc": auc, "exact_match_by_family": fam},
        "heldout_combinations": {"exact_match": held, "auc": auc - 0.01},
    }


def _results(offset: float) -> dict:
    splits = ("val", *cp.SPLITS)
    return {
        "factored": {
            s: {str(k): _res(0.8 + offset + 0.01 * k, 0.7 + offset, 0.9) for k in range(3)}
            for s in splits
        }
    }


def test_headline_is_the_with_policy_arm_with_the_scripted_arm_beside():
    results = {"with-policy": _results(0.1), "scripted": _results(0.0)}
    head = cp.headline_of(results)
    assert set(TARGETS["robosuite"]) <= set(head)
    assert head["exact_match"] == 0.91 and head["scripted_exact_match"] == 0.81
    assert head["camera_heldout_combinations_exact_match"] == 0.8
    assert head["scripted_teachers_heldout_combinations_reward_auc"] == 0.89
    text = cp.table(results)
    assert "| with-policy | camera | 0.910 [0.900, 0.920] |" in text
    assert "| scripted | reach |" not in text and "| reach | 0.81 (30) | - |" in cp.family_table(
        results
    )


def test_policy_episodes_are_collected_once_per_policy_and_split(tmp_path, monkeypatch):
    calls = []

    def record(path: Path, argv: list[str]) -> Path:
        calls.append((path.name, argv))
        return path

    monkeypatch.setattr(cp, "record_once", record)
    sets = cp.policy_sets(tmp_path)
    assert set(sets) == set(cp.POLICIES) and all(set(v) == {"train", "test"} for v in sets.values())
    names = [name for name, _ in calls]
    assert names == [f"{p}-{s}.h5" for p in cp.POLICIES for s in ("train", "test")]
    seeds = [argv[argv.index("--seed") + 1] for _, argv in calls]
    assert len(set(seeds)) == len(seeds)  # no two sets share episodes
    for _, argv in calls:
        assert Path(argv[argv.index("--policy") + 1]).is_dir()  # the kept policies
        assert "--families" not in argv  # every family labelled


def test_another_perception_model_trains_in_folders_of_its_own():
    import argparse

    from benchmarks.captioner_heads import KEPT_PERCEPTION

    args = argparse.Namespace(seeds=[0], steps=10, parallel=1, work="w")
    args.perception = KEPT_PERCEPTION["robosuite"]
    assert cp.arm_args(args, "with-policy").work == str(Path("w", "with-policy"))
    args.perception = "benchmarks/models/perception-80x3/model"
    assert cp.perception_tag(args.perception) == "perception-80x3"
    assert cp.arm_args(args, "with-policy").work == str(Path("w", "with-policy-perception-80x3"))
    # one arm alone: the headline and the tables hold that arm
    head = cp.headline_of({"with-policy": _results(0.1)})
    assert head["exact_match"] == 0.91 and not any(k.startswith("scripted_") for k in head)
    assert "| scripted |" not in cp.table({"with-policy": _results(0.1)})

"""benchmarks/manipulation.py: its headline, budget and refusals, without training."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import manipulation


def test_headline_reads_seen_success_per_family_and_the_second_chain_link():
    ev = {
        "families": {
            "reach": {"train": {"success": 0.9, "ci": [0.8, 0.95], "episodes": 100}},
            "push": {"train": None},
        },
        "chain": {"success": [{"length": 1, "success": 0.7}, {"length": 2, "success": 0.4}]},
    }
    head = manipulation.headline(ev, {"steps": 1000, "wall_clock_s": 12.5})
    assert head == {
        "reach": 0.9,
        "push": None,
        "chain2": 0.4,
        "chain2_first": 0.7,
        "steps": 1000,
        "wall_clock_s": 12.5,
    }


def test_budget_comes_from_the_run_logs(tmp_path):
    (tmp_path / "progress.csv").write_text("step,updates\n1000,500\n2000,1500\n")
    (tmp_path / "eval.csv").write_text("step,train/success,train_s\n2000,0.5,321.04\n")
    assert manipulation.budget(tmp_path) == {"steps": 2000, "updates": 1500, "wall_clock_s": 321.0}
    rows = manipulation.curve(tmp_path)
    assert rows == [{"step": 2000.0, "train/success": 0.5, "train_s": 321.04}]


def test_evaluating_a_run_without_checkpoints_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="has no checkpoint"):
        manipulation.main(["--work", str(tmp_path / "none"), "--eval-only"])


def test_targets_are_the_issue_targets():
    assert manipulation.TARGETS == {
        "reach": 0.90, "push": 0.80, "lift": 0.70, "put": 0.50, "stack": 0.30, "chain2": 0.60
    }  # fmt: skip


def test_a_new_run_starts_from_the_demonstrations_and_a_resumed_one_keeps_its_settings(
    tmp_path, monkeypatch
):
    calls = []
    monkeypatch.setattr(manipulation.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    args = manipulation.argparse.Namespace(
        preset="robosuite-manip", work=str(tmp_path / "run"), steps=5000, processes=1,
        demos="d.h5", extra="--sac.demo-bc 1",
    )  # fmt: skip
    manipulation.train(args)
    new = calls[-1]
    assert new[new.index("--finetune.demos") + 1] == "d.h5"
    assert new[new.index("--sac.demo-bc") + 1] == "1" and "--resume" not in new
    (tmp_path / "run" / "checkpoints" / "step_000001000").mkdir(parents=True)
    manipulation.train(args)
    again = calls[-1]
    assert "--resume" in again and "--finetune.demos" not in again and "--sac.demo-bc" not in again


def test_an_evaluation_of_the_latest_checkpoint_is_kept(tmp_path, monkeypatch):
    """A family's document for the latest checkpoint is read back, never evaluated again;
    one for an older checkpoint is evaluated again."""
    import argparse
    import json

    import benchmarks.manipulation as manip

    work = tmp_path / "run"
    work.mkdir()
    (work / "latest.json").write_text(json.dumps({"checkpoint": "checkpoints/step_000000500"}))
    assert manip.latest_step(work) == 500
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append(cmd)
        out = Path(cmd[cmd.index("--json") + 1])
        out.write_text(json.dumps({"step": 500, "sets": {}}))

        class Done:
            returncode, stderr = 0, ""

        return Done()

    monkeypatch.setattr(manip.subprocess, "run", fake_run)
    args = argparse.Namespace(work=str(work), episodes=4, processes=1)
    kept = tmp_path / "push.json"
    kept.write_text(json.dumps({"step": 500, "sets": {"train": {}}}))
    assert manip.lcrl_eval(args, kept, "--families", "push") == {"step": 500, "sets": {"train": {}}}
    assert calls == []
    old = tmp_path / "lift.json"
    old.write_text(json.dumps({"step": 400, "sets": {}}))
    assert manip.lcrl_eval(args, old, "--families", "lift") == {"step": 500, "sets": {}}
    assert len(calls) == 1
    assert manip.latest_step(tmp_path) is None


def test_compared_runs_show_their_settings_and_last_evaluations(tmp_path):
    import json

    run = tmp_path / "put"
    run.mkdir()
    cfg = {
        "env": {"families": ["put"]},
        "buffer": {"n_step": 3},
        "agent": {"net": {"slot_mode": "attributes"}, "grounding": 1.0},
        "sac": {"q_filter": True},
        "explore": {"curriculum": [], "family_weights": "uniform"},
    }
    (run / "config.json").write_text(json.dumps(cfg))
    (run / "eval.csv").write_text("step,train/put\n5000,0.1\n10000,0.2\n15000,0.4\n")
    doc = manipulation.compared(run)
    assert doc["steps"] == [10000, 15000]
    assert doc["seen"] == {"put": 0.3}
    assert doc["settings"]["n-step"] == 3 and doc["settings"]["slots"] == "attributes"
    table = "\n".join(manipulation.compared_lines([doc]))
    assert "| 3 | attributes | 1.0 | True | none | uniform |" in table and "put 0.30" in table
    with pytest.raises(SystemExit, match="no run"):
        manipulation.main(
            ["--work", str(tmp_path), "--eval-only", "--compare", str(tmp_path / "x")]
        )


def test_family_runs_are_family_equals_run_with_a_checkpoint(tmp_path):
    run = tmp_path / "stack"
    (run / "checkpoints" / "step_000001000").mkdir(parents=True)
    assert manipulation.family_runs([f"stack={run}"]) == {"stack": str(run)}
    with pytest.raises(SystemExit, match="not FAMILY=RUN"):
        manipulation.family_runs([str(run)])
    with pytest.raises(SystemExit, match="not FAMILY=RUN"):
        manipulation.family_runs([f"fly={run}"])
    with pytest.raises(SystemExit, match="has no checkpoint"):
        manipulation.family_runs([f"put={tmp_path / 'none'}"])


def test_a_family_run_gives_its_family_figure_and_the_one_policy_stays_beside(
    tmp_path, monkeypatch
):
    import argparse

    main_run, own_run = str(tmp_path / "all"), str(tmp_path / "stack")
    seen = {main_run: 0.1, own_run: 0.7}

    def fake_eval(args, out, *options, work=None):
        if "--chain" in options:
            return {"sets": {"train": {"chain": {"success": [{}, {"success": 0.2}]}}}}
        sets = {
            n: {"success": seen[work], "ci": [0, 1], "episodes": 100} for n in manipulation.SETS
        }
        return {"step": 1, "sets": sets}

    monkeypatch.setattr(manipulation, "lcrl_eval", fake_eval)
    args = argparse.Namespace(
        work=main_run, families=["reach", "stack"], family_runs={"stack": own_run}
    )
    ev = manipulation.evaluate(args)
    assert ev["families"]["stack"]["train"]["success"] == 0.7
    assert ev["families"]["reach"]["train"]["success"] == 0.1
    assert ev["one_policy"]["stack"]["train"]["success"] == 0.1
    head = manipulation.headline(ev, {"steps": 9}, {"stack": {"steps": 5, "wall_clock_s": 3.0}})
    assert head["stack"] == 0.7 and head["stack_one_policy"] == 0.1
    assert head["stack_run"] == own_run and head["stack_steps"] == 5
    assert head["reach"] == 0.1 and head["chain2"] == 0.2 and "reach_one_policy" not in head


def test_a_chain_run_gives_chain2_and_its_family_figures_beside(tmp_path, monkeypatch):
    """``--chain-run``: chain2 comes from that policy (a distilled student over every
    family), the RL policy's chain figure and the student's per-family figures beside."""
    import argparse
    import json

    rl, student = str(tmp_path / "rl"), str(tmp_path / "student")
    chains = {rl: 0.2, student: 0.5}
    seen = {rl: 0.1, student: 0.6}

    def fake_eval(args, out, *options, work=None):
        work = work or args.work
        if "--chain" in options:
            links = [{"success": 0.8}, {"success": chains[work]}]
            return {"sets": {"train": {"chain": {"success": links}}}}
        sets = {n: {"success": seen[work], "ci": [0, 1], "episodes": 9} for n in manipulation.SETS}
        return {"step": 1, "sets": sets}

    monkeypatch.setattr(manipulation, "lcrl_eval", fake_eval)
    args = argparse.Namespace(work=rl, families=["put"], family_runs={}, chain_run=student)
    ev = manipulation.evaluate(args)
    head = manipulation.headline(ev, {"steps": 9})
    assert head["chain2"] == 0.5 and head["chain2_rl_policy"] == 0.2
    assert head["put"] == 0.1 and head["put_distilled"] == 0.6

    run = tmp_path / "student"
    (run / "checkpoints" / "step_000000003").mkdir(parents=True)
    (run / "progress.csv").write_text("step,episodes,rows\n2,60,900\n3,90,1400\n")
    (run / "eval.csv").write_text("step,train/success,train_s\n3,0.5,99.94\n")
    (run / "latest.json").write_text(json.dumps({"checkpoint": "checkpoints/step_000000003"}))
    meta = {"distill": {"teacher": "runs/all", "teachers": {"put": {"path": "scripted"}}}}
    (run / "checkpoints" / "step_000000003" / "meta.json").write_text(json.dumps(meta))
    spent = manipulation.distilled(run)
    assert spent == {
        "rounds": 3,
        "episodes": 90,
        "labelled_states": 1400,
        "wall_clock_s": 99.9,
        "teachers": meta["distill"],
    }


def test_a_routed_run_gives_chain2_with_the_student_and_rl_policy_beside(tmp_path, monkeypatch):
    """``--routed-run``: chain2 comes from the routed policy (each instruction acted by its
    family's expert), the distilled student's and the RL policy's chain figures beside,
    and its budget is the sum over the runs it is made of."""
    import argparse
    import json

    rl, student, routed = (str(tmp_path / n) for n in ("rl", "student", "routed"))
    chains = {rl: 0.2, student: 0.3, routed: 0.45}
    seen = {rl: 0.1, student: 0.6, routed: 0.8}

    def fake_eval(args, out, *options, work=None):
        work = work or args.work
        if "--chain" in options:
            links = [{"success": 0.9}, {"success": chains[work]}]
            return {"sets": {"train": {"chain": {"success": links}}}}
        sets = {n: {"success": seen[work], "ci": [0, 1], "episodes": 9} for n in manipulation.SETS}
        return {"step": 1, "sets": sets}

    monkeypatch.setattr(manipulation, "lcrl_eval", fake_eval)
    args = argparse.Namespace(
        work=rl, families=["put"], family_runs={}, chain_run=student, routed_run=routed
    )
    ev = manipulation.evaluate(args)
    head = manipulation.headline(ev, {"steps": 9})
    assert head["chain2"] == 0.45 and head["chain2_first"] == 0.9
    assert head["chain2_distilled"] == 0.3 and head["chain2_rl_policy"] == 0.2
    assert head["put_routed"] == 0.8 and head["put_distilled"] == 0.6 and head["put"] == 0.1

    # the routed folder's budget: its base and experts, each from its run's logs
    for name, steps, secs in (("base", 100, 10.0), ("put", 50, 5.5)):
        run = tmp_path / name
        (run / "checkpoints" / f"step_{steps:09d}").mkdir(parents=True)
        (run / "progress.csv").write_text(f"step,updates\n{steps},{steps}\n")
        (run / "eval.csv").write_text(f"step,train_s\n{steps},{secs}\n")
    # a distilled student counts the states its rounds visited, not its rounds
    run = tmp_path / "student"
    (run / "checkpoints" / "step_000000003").mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps({"distill": {"teacher": "runs/t"}}))
    (run / "progress.csv").write_text("step,episodes,rows\n3,90,4000\n")
    (run / "eval.csv").write_text("step,train_s\n3,7.0\n")
    folder = tmp_path / "routed"  # made by evaluate(), which writes its evals there
    meta = {
        "step": 100,
        "router": {
            "base": str(tmp_path / "base" / "checkpoints" / "step_000000100"),
            "sources": {
                "put": str(tmp_path / "put" / "checkpoints" / "step_000000050"),
                "reach": str(tmp_path / "student" / "checkpoints" / "step_000000003"),
            },
        },
    }
    (folder / "meta.json").write_text(json.dumps(meta))
    assert manipulation.latest_step(folder) == 100
    spent = manipulation.routed_budget(folder)
    assert spent["steps"] == 4150 and spent["wall_clock_s"] == 22.5
    assert spent["runs"]["reach"]["distilled"] is True
    assert spent["runs"]["put"]["run"] == str(tmp_path / "put")
    with pytest.raises(SystemExit, match="not a folder of lcrl route"):
        manipulation.main(["--work", str(tmp_path / "base"), "--eval-only", "--routed-run", rl])

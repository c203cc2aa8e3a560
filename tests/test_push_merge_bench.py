"""Benchmarks that add push to a reach result (``--push-only``): reach's figures stay as
the result file has them, push's are added, and the file's command reproduces both."""

from __future__ import annotations

import json
import shutil
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def results(tmp_path, monkeypatch):
    import benchmarks.common as common

    out = tmp_path / "results"
    out.mkdir()
    monkeypatch.setattr(common, "RESULTS_DIR", out)
    return out


def test_distill_push_only_keeps_reach_and_adds_push(results, tmp_path, monkeypatch):
    import benchmarks.distill as distill

    shutil.copy(ROOT / "benchmarks/results/distill-robosuite.json", results)
    before = json.loads((results / "distill-robosuite.json").read_text())
    rounds = [{"step": 1.0, "teacher_share": 1.0, "loss": 0.1, "success": 0.5, "rows": 90.0}]
    fake = {
        "teacher": "runs/push-teacher",
        "student_distill_s": 12.0,
        "final": {
            "teacher": {"success": 0.98, "ci": [0.93, 0.99]},
            "student": {"success": 0.9, "ci": [0.83, 0.94]},
        },
        "rounds": rounds,
        "student_evals": [{"step": 5.0, "train/success": 0.5}],
        "state_student": {
            "run": "runs/state-student",
            "distill_s": 300.0,
            "final": {"success": 0.94, "ci": [0.88, 0.97]},
            "rounds": rounds,
            "evals": [{"step": 5.0, "train/success": 0.6}],
        },
    }
    monkeypatch.setattr(distill, "push_stage", lambda args: dict(fake))
    argv = ["--perception", "p", "--push-teacher", "runs/push-teacher", "--push-only"]
    monkeypatch.setattr("sys.argv", ["benchmarks/distill.py", *argv])
    # run as a script, however pytest itself was started (python -m pytest has a spec)
    monkeypatch.setitem(sys.modules, "__main__", types.ModuleType("__main__"))
    assert distill.main(argv) == 0
    after = json.loads((results / "distill-robosuite.json").read_text())
    h = after["headline"]
    assert h["student_seen"] == before["headline"]["student_seen"]  # reach kept
    assert (h["push_teacher_seen"], h["push_student_seen"], h["push_gap"]) == (0.98, 0.9, 0.08)
    assert after["reached"]["push_within_5_points"] is False
    push_cmd = "python benchmarks/distill.py " + " ".join(argv)
    reach_cmd = before["command"].split(" && ")[0]
    assert after["command"] == f"{reach_cmd} && {push_cmd}"
    assert distill.main(argv) == 0  # a second push replaces the first push's command
    again = json.loads((results / "distill-robosuite.json").read_text())
    assert again["command"] == f"{reach_cmd} && {push_cmd}"
    md = (results / "distill-robosuite.md").read_text()
    assert "| push, train | 0.98 [0.93, 0.99] | 0.90 [0.83, 0.94] |" in md
    assert "NOT reached (gap +0.08)" in md and (results / "distill-robosuite.png").is_file()
    assert "| push, train: a student reading the true state | | 0.94 [0.88, 0.97] |" in md
    assert "Push student's seen success after rounds 5: 0.50." in md
    assert "the student acts through the same perception model as for reach" in md
    fake["perception"] = "data/push-perception"
    fake["settings"] = {"rounds": 1, "updates_per_round": 5, "hidden": [512, 512, 512]}
    after["push_perception_command"] = "lcrl perception train --out data/push-perception"
    after["push_older"] = {"summary": "0.31 after 10 rounds.", "build": {}}
    distill.render({**after, "push": fake}, after["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert (
        "the student acts through the perception model `data/push-perception`, with hidden "
        "layers 512x512x512)" in md
    )
    assert "Its perception model: `lcrl perception train --out data/push-perception`." in md
    assert "Another build (`push_older`): 0.31 after 10 rounds." in md
    bands = [
        {"from_cm": 0, "to_cm": 6, "object_steps": 40, "mean_cm": 3.5, "p90_cm": 9.0},
        {"from_cm": 6, "to_cm": 10, "object_steps": 0, "mean_cm": None, "p90_cm": None},
        {"from_cm": 20, "to_cm": 1000, "object_steps": 9, "mean_cm": 2.5, "p90_cm": 6.3},
    ]
    fake["teacher_on_estimates"] = {
        "episodes": 4,
        "true_state": {"success": 1.0, "ci": [0.51, 1.0]},
        "estimate": {"success": 0.5, "ci": [0.15, 0.85]},
        "action_gap": 0.2,
        "error_by_gripper_distance": bands,
    }
    distill.render({**after, "push": fake}, after["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert "0.50 [0.15, 0.85] against 1.00 [0.51, 1.00]" in md
    assert (
        "| 0-6 cm | 40 | 3.50 cm | 9.00 cm |" in md and "| 20+ cm | 9 | 2.50 cm | 6.30 cm |" in md
    )
    assert "| 6-10 cm |" not in md  # a band without a step has no row
    fake["settings"]["init_from_teacher"], fake["settings"]["lr"] = True, 3e-4
    kept = {"step": 10.0, "train/success": 0.7}
    after["push_kept"] = {"summary": "kept.", "build": {"student_evals": [kept]}}
    distill.render({**after, "push": fake}, after["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert "started as a copy of the teacher's policy (`--init-from-teacher`)" in md
    assert "learning rate 0.0003" in md
    # the periodic evaluations of the result's push student and of each kept build
    curves = distill.push_curves({**after, "push": fake})
    assert curves["push (this result)"] == [(5.0, 0.5)] and curves["push_kept"] == [(10.0, 0.7)]
    assert "push_older" not in curves  # a build without evaluations draws nothing
    fake["recheck"] = {
        "seed": 1,
        "episodes": 200,
        "teacher": {"success": 0.92, "ci": [0.88, 0.95]},
        "student": {"success": 0.9, "ci": [0.85, 0.93]},
        "commands": ["lcrl eval t --seed 1", "lcrl eval s --seed 1"],
    }
    distill.render({**after, "push": fake}, after["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert (
        "Again on 200 other episodes (evaluation seed 1: other layouts and instructions): "
        "teacher 0.92 [0.88, 0.95], student 0.90 [0.85, 0.93] (gap +0.02, within 0.05); "
        "`lcrl eval t --seed 1`, `lcrl eval s --seed 1`." in md
    )

    fake["recheck"]["student"]["success"] = 0.865  # 173 of 200: 3 decimals, not rounded up
    distill.render({**after, "push": fake}, after["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert "student 0.865 [0.85, 0.93] (gap +0.055, NOT within 0.05)" in md
    payload = {**after, "push": fake}
    distill.add_push(payload)
    assert payload["reached"]["push_within_5_points_recheck"] is False

    with pytest.raises(SystemExit):  # push-only needs the push teacher
        distill.main(["--perception", "p", "--push-only"])


def test_push_students_of_several_seeds_are_averaged(results, tmp_path, monkeypatch):
    """``--push-seeds 0 1``: one student per seed (the first at --push-student, the next
    beside it as NAME-s1), each evaluated alone, then their ensemble evaluated as the push
    student, with the command that writes it."""
    import benchmarks.distill as distill

    made, ran = [], []

    def fake_distill(args, teacher, student, *, rounds, updates, how, resume, seed):
        student.mkdir(parents=True, exist_ok=True)
        (student / "progress.csv").write_text(
            "step,teacher_share,loss,success,rows\n1,1.0,0.5,0.5,90\n"
        )
        (student / "eval.csv").write_text("step,train/success\n1,0.8\n")
        made.append((student.name, seed, how))
        return 10.0 + seed

    scores = {"s": 0.9, "s-s1": 0.91, "s-ensemble": 0.95, "teacher": 0.99}

    def fake_evaluate(run, episodes, sets, seed=0):
        return {"train": {"success": scores[Path(run).name], "ci": [0.8, 1.0]}}

    monkeypatch.setattr(distill, "distill", fake_distill)
    monkeypatch.setattr(distill, "evaluate", fake_evaluate)
    monkeypatch.setattr(distill.subprocess, "run", lambda cmd, **kw: ran.append(cmd))
    argv = ["--perception", "p", "--push-teacher", str(tmp_path / "teacher"), "--push-only"]
    argv += ["--push-student", str(tmp_path / "s"), "--push-seeds", "0", "1"]
    argv += ["--push-eval-sets", "train", "--push-hold-radius", "0.03"]
    out = distill.push_stage(distill.build_parser().parse_args(argv))
    assert [(n, s) for n, s, _ in made] == [("s", 0), ("s-s1", 1)]
    assert made[0][2][-4:] == ("--hold-radius", "0.03", "--eval-sets", "train")
    assert [m["success"] for m in out["members"]] == [0.9, 0.91]
    assert out["student"] == str(tmp_path / "s-ensemble") and out["student_distill_s"] == 21.0
    assert out["final"]["student"]["success"] == 0.95 and out["settings"]["seeds"] == [0, 1]
    assert ran[0][-4:] == [str(tmp_path / "s-ensemble"), str(tmp_path / "s"),
                           str(tmp_path / "s-s1"), "--overwrite"]  # fmt: skip
    assert out["ensemble_command"].startswith(f"lcrl ensemble {tmp_path / 's-ensemble'} ")
    payload = json.loads((ROOT / "benchmarks/results/distill-robosuite.json").read_text())
    payload["push"] = out
    distill.render(payload, payload["machine"])
    md = (results / "distill-robosuite.md").read_text()
    assert "the mean of the actions of 2 students distilled the same way" in md
    assert f"seed 1 (`{tmp_path / 's-s1'}`, 11 s) 0.91 [0.80, 1.00]" in md


def test_image_policy_renders_push_from_demonstrations(results):
    import benchmarks.image_policy as ip

    payload = json.loads((ROOT / "benchmarks/results/robosuite-image-reach.json").read_text())
    payload["headline"].update(
        push_seen=0.9,
        push_demo_episodes=600,
        push_wall_clock_s=5000.0,
        push_seen_without_demos=0.05,
    )
    payload["times"].update(push_demos_record_s=544.0, push_train_s=2000.0)
    payload["command"] = "python a.py && python b.py --push-only"
    payload["push_command"] = "python b.py --push-only"
    payload["reach_machine"] = payload["machine"]
    ip.render(payload, payload["machine"])
    md = (results / "robosuite-image-reach.md").read_text()
    assert "Command: `python a.py && python b.py --push-only`" in md
    assert "| push: record 600 demonstrations through perception | 544 |" in md
    assert "| **to a push policy** | **5000** |" in md
    assert "Push without demonstrations: 0.05." in md


def test_distill_resumes_a_push_student_and_counts_its_own_seconds(tmp_path, monkeypatch):
    """--resume-push continues a student already there (lcrl distill --resume) and takes
    its seconds from its eval.csv, which counts every session; a new student overwrites."""
    import argparse

    import benchmarks.distill as distill

    calls = []
    monkeypatch.setattr(distill.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    args = argparse.Namespace(
        rounds=10,
        updates_per_round=500,
        episodes_per_round=20,
        seed=0,
        beta_decay=0.5,
        eval_every=5,
        eval_episodes=20,
        perception="p",
    )
    student = tmp_path / "student"
    student.mkdir()
    (student / "eval.csv").write_text("step,train/success,train_s\n5,0.5,100.0\n30,0.9,2345.6\n")
    distill.distill(args, Path("t"), student, rounds=30, updates=2000, resume=True)
    assert "--overwrite" in calls[-1] and "--resume" not in calls[-1]  # nothing to resume
    (student / "latest.json").write_text("{}")
    seconds = distill.distill(args, Path("t"), student, rounds=30, updates=2000, resume=True)
    cmd = calls[-1]
    assert "--resume" in cmd and "--overwrite" not in cmd and seconds == 2345.6
    assert cmd[cmd.index("--rounds") + 1] == "30" and cmd[cmd.index("--perception") + 1] == "p"
    assert cmd[cmd.index("--updates-per-round") + 1] == "2000"
    distill.distill(args, Path("t"), student, how=("--state",))
    assert "--state" in calls[-1] and "--perception" not in calls[-1]
    assert calls[-1][calls[-1].index("--rounds") + 1] == "10"


@pytest.fixture
def push_stage(tmp_path, monkeypatch):
    """``(extra args) -> (lcrl distill's student arguments, push section)`` of the distill
    benchmark's push stage, with distillation and evaluation stubbed out."""
    import benchmarks.distill as distill

    seen = []
    monkeypatch.setattr(distill, "distill", lambda *a, **kw: seen.append(kw["how"]) or 1.0)
    final = {"train": {"success": 0.5, "ci": [0.4, 0.6]}}
    monkeypatch.setattr(distill, "evaluate", lambda *a, **kw: final)
    monkeypatch.setattr(distill, "rows", lambda path: [{"step": 1.0}])
    base = ["--perception", "p", "--push-teacher", str(tmp_path / "t"), "--push-only"]

    def run(*extra: str) -> tuple[tuple[str, ...], dict]:
        out = distill.push_stage(distill.build_parser().parse_args([*base, *extra]))
        return seen[-1], out

    return run


def test_distill_push_stage_passes_the_student_s_hidden_layers(push_stage):
    """--push-hidden sizes the push student through perception (lcrl distill --hidden),
    and the push section records them."""
    how, out = push_stage("--push-hidden", "512", "512")
    assert how == ("--perception", "p", "--hidden", "512", "512")
    assert out["settings"]["hidden"] == [512, 512]
    how, out = push_stage()
    assert how == ("--perception", "p") and out["settings"]["hidden"] == []


def test_distill_push_stage_can_start_the_student_from_the_teacher(push_stage):
    """--push-init-teacher and --push-lr reach lcrl distill (--init-from-teacher, --lr)
    and the push section records both."""
    how, out = push_stage("--push-init-teacher", "--push-lr", "3e-4")
    assert how == ("--perception", "p", "--init-from-teacher", "--lr", "0.0003")
    assert out["settings"]["init_from_teacher"] is True and out["settings"]["lr"] == 3e-4
    _, plain = push_stage()
    assert plain["settings"]["init_from_teacher"] is False and plain["settings"]["lr"] is None


def test_distill_push_stage_rechecks_on_other_episodes(push_stage, tmp_path, monkeypatch):
    """--push-recheck N evaluates teacher and student again on N episodes at evaluation
    seed 1 with lcrl eval, and the push section keeps both results and the commands."""
    import benchmarks.distill as distill
    import benchmarks.image_policy as image_policy

    calls = []

    def fake_run(cmd, **kw):
        calls.append(cmd)
        path = Path(cmd[cmd.index("--json") + 1])
        path.parent.mkdir(parents=True, exist_ok=True)
        rate = 0.9 if path.parent.name == "student" else 0.95
        path.write_text(json.dumps({"sets": {"train": {"success": rate, "ci": [0.8, 0.99]}}}))

    monkeypatch.setattr(distill.subprocess, "run", fake_run)
    stubbed = distill.evaluate  # the final evaluations stay stubbed; the recheck runs lcrl eval
    monkeypatch.setattr(
        distill,
        "evaluate",
        lambda *a, seed=0: image_policy.evaluate(*a, seed=seed) if seed else stubbed(*a),
    )
    _, out = push_stage("--push-recheck", "200", "--push-student", str(tmp_path / "student"))
    again = out["recheck"]
    assert again["seed"] == 1 and again["episodes"] == 200 and len(calls) == 2
    assert again["teacher"]["success"] == 0.95 and again["student"]["success"] == 0.9
    for cmd in calls:
        assert cmd[cmd.index("--seed") + 1] == "1" and cmd[cmd.index("--episodes") + 1] == "200"
    assert again["commands"][1].startswith(f"lcrl eval {tmp_path / 'student'} --episodes 200")
    _, plain = push_stage()
    assert "recheck" not in plain


def test_distill_push_stage_measures_at_a_test_seed(tmp_path, monkeypatch):
    """--push-test-seed T evaluates the push teacher and student at T (refused for the
    choice seeds 0 to 3), and the push section records it."""
    import benchmarks.distill as distill
    from lcrl.errors import LcrlError

    seeds = []
    monkeypatch.setattr(distill, "distill", lambda *a, **kw: 1.0)
    monkeypatch.setattr(distill, "rows", lambda path: [{"step": 1.0}])

    def fake_evaluate(run, episodes, sets, seed=0):
        seeds.append(seed)
        return {"train": {"success": 0.5, "ci": [0.4, 0.6]}}

    monkeypatch.setattr(distill, "evaluate", fake_evaluate)
    base = ["--perception", "p", "--push-teacher", str(tmp_path / "t"), "--push-only"]
    out = distill.push_stage(distill.build_parser().parse_args([*base, "--push-test-seed", "17"]))
    assert seeds == [17, 17] and out["final_seed"] == 17
    with pytest.raises(LcrlError, match="used for choices"):
        distill.push_stage(distill.build_parser().parse_args([*base, "--push-test-seed", "1"]))

"""``lcrl train lang2d-camera``: the camera-policy pipeline of ``robosuite-camera`` on the
2D tabletop's camera frames, at a size for CI. Every stage runs as the real command; the
student learns its teacher's actions from the camera; the kept policy loads and acts;
finished stages are kept, ``--stages`` reruns some, and the stages' names are checked."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import cli, error_line

from lcrl.checkpoint import verify_checkpoint
from lcrl.errors import LcrlError

SMALL = [
    "--perception-episodes", "80",
    "--perception-steps", "100",
    "--teacher-steps", "1000",
    "--rounds", "3",
    "--episodes-per-round", "6",
    "--updates-per-round", "100",
    "--student-frames", "8",
    "--perception-ft-steps", "30",
    "--rounds-ft", "1",
    "--eval-episodes", "4",
    "--no-reader",
    "--threads", "1",
]  # fmt: skip


def test_the_2d_camera_pipeline_builds_a_kept_student_stage_by_stage(tmp_path, capsys):
    out = tmp_path / "camera"
    assert cli("train", "lang2d-camera", "--out", str(out), *SMALL) == 0
    names = [
        "perception-data", "perception", "teacher-reach", "student", "student-frames",
        "perception-ft", "student-ft", "eval", "keep",
    ]  # fmt: skip
    for name in names:
        record = json.loads((out / "stages" / f"{name}.json").read_text())
        assert record["seconds"] >= 0 and record["stage"] == name
    # the student learned the teacher's actions from the camera: its loss on the
    # teacher's labels fell well below where it started (an untrained student)
    with open(out / "student" / "progress.csv") as f:
        rows = [{k: float(v) for k, v in r.items() if v} for r in csv.DictReader(f)]
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]  # 3 rounds, then 1 through the new model
    assert rows[-1]["loss"] < 0.5 * rows[0]["loss_first"]
    # the kept policy: weights and configs only, sealed, acting through its perception
    kept = out / "kept"
    ckpt = verify_checkpoint(kept)
    assert not (kept / "arrays.npz").exists() and not (kept / "state.json").exists()
    assert "perception" in ckpt.meta
    import lcrl

    policy = lcrl.load(kept)
    env = policy.make_env()
    obs, _ = env.reset(seed=0)
    policy.reset()
    assert policy.act(obs, "reach the red cube").shape == (2,)
    evaluated = json.loads((out / "eval" / "eval.json").read_text())
    assert "train" in evaluated["sets"]
    # the same policy on the true state: the cost of perception, side by side
    doc = tmp_path / "true.json"
    assert cli("eval", str(kept), "--true-state", "--episodes", "2", "--json", str(doc)) == 0
    assert json.loads(doc.read_text())["settings"]["true_state"] is True
    capsys.readouterr()
    # run again: every stage is kept, nothing is rebuilt
    assert cli("train", "lang2d-camera", "--out", str(out), *SMALL) == 0
    said = capsys.readouterr().out
    assert said.count("-- done") == len(names) and "$ lcrl" not in said
    # --stages reruns one stage; an unknown one is named
    assert cli("train", "lang2d-camera", "--out", str(out), *SMALL, "--stages", "keep") == 0
    assert "[9/9] keep" in capsys.readouterr().out
    assert cli("train", "lang2d-camera", "--out", str(out), "--stages", "teachers") == 2
    line = error_line(capsys.readouterr().err)
    assert "--stages teachers: the stages are perception-data perception teacher-reach" in line
    assert np.isfinite(rows[-1]["loss"])


def test_scripted_families_have_no_teacher_stage_and_a_trained_teacher_is_the_base(tmp_path):
    from train.commands.pipeline import SCRIPTED, robosuite_camera, stages

    # the student of every teacher (no state student between them)
    p = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "camera"), state_rounds=0)
    names = [s.name for s in stages(p)]
    assert "teacher-put" in names and "teacher-stack" in names
    assert not any(n in names for n in ("teacher-reach", "teacher-push", "teacher-lift"))
    (student,) = [s for s in stages(p) if s.name == "student"]
    args = student.commands[0]
    assert args[1].endswith("teachers/put")  # the first trained teacher is the base
    given = args[args.index("--teacher-for") + 1 : args.index("--chain")]
    assert given == [
        "reach=scripted", "push=scripted", "lift=scripted", f"stack={p.out}/teachers/stack"
    ]  # fmt: skip
    assert args[args.index("--families") + 1 : args.index("--max-episode-steps")] == [
        "reach", "push", "lift", "put", "stack"
    ]  # fmt: skip
    threaded = dataclasses.replace(p, threads=1)  # every training stage on one thread
    for stage in stages(threaded):
        for cmd in stage.commands:
            if cmd[0] in ("train", "distill") or stage.name == "student-frames":
                assert cmd[cmd.index("--torch-threads") + 1] == "1", stage.name
            if cmd[:2] == ["perception", "collect"]:  # a stopped collection goes on
                assert "--resume" in cmd, stage.name
    # put and stack share one file of demonstrations of every family, recorded by a stage
    # of its own before them
    assert names[names.index("teacher-put") - 1] == "demos-robosuite-manip"
    (demos,) = [s for s in stages(p) if s.name == "demos-robosuite-manip"]
    assert demos.commands[0][:4] == ["demos", "record", "--preset", "robosuite-manip"]
    made = demos.outputs[0]
    for name in ("teacher-put", "teacher-stack"):
        (teacher,) = [s for s in stages(p) if s.name == name]
        assert teacher.needs == (f"{made}<demos-robosuite-manip",)
        assert [c[0] for c in teacher.commands] == ["train"]
        assert teacher.commands[0][teacher.commands[0].index("--finetune.demos") + 1] == made
    every_family_scripted = dataclasses.replace(
        p, teachers=tuple(dataclasses.replace(t, preset=SCRIPTED) for t in p.teachers)
    )
    with pytest.raises(LcrlError, match="needs one trained teacher at least"):
        stages(every_family_scripted)
    # the shipped student reads initial as its teachers do; --no-initial reaches lcrl distill
    assert "--no-initial" not in args
    (current,) = [s for s in stages(dataclasses.replace(p, initial=False)) if s.name == "student"]
    assert "--no-initial" in current.commands[0]


def test_no_pipeline_takes_the_name_of_a_preset():
    """``lcrl train NAME`` runs a pipeline before a preset: a shared name would hide one."""
    from train.commands.pipeline import PIPELINES
    from train.configs.presets import PRESETS

    assert not set(PIPELINES) & set(PRESETS)


def test_a_student_of_the_state_has_no_perception_stage(tmp_path):
    """``lcrl train robosuite-privileged``: the camera build's teachers, one student that reads
    the privileged state (``--state`` in every distill command), no perception stage."""
    from train.commands.pipeline import CAMERA_ONLY, robosuite_privileged, stages

    p = dataclasses.replace(robosuite_privileged(), out=str(tmp_path / "state"))
    names = [s.name for s in stages(p)]
    assert names == [
        "demos-robosuite-manip", "teacher-put", "teacher-stack", "student", "eval", "keep"
    ]  # fmt: skip
    assert not set(names) & set(CAMERA_ONLY)
    (student,) = [s for s in stages(p) if s.name == "student"]
    args = student.commands[0]
    assert "--state" in args and "--perception" not in args
    assert args[args.index("--rounds") + 1] == "100"
    assert student.needs == tuple(
        f"{p.out}/teachers/{f}<teacher-{f}" for f in ("put", "stack")
    )  # no perception model to wait for
    more = dataclasses.replace(p, rounds_aug=5)
    (aug,) = [s for s in stages(more) if s.name == "student-aug"]
    cmd = aug.commands[0]
    assert "--state" in cmd and "--new-perception" not in cmd
    assert cmd[cmd.index("--rounds") + 1] == "105" and aug.needs[0].endswith("<student")
    with pytest.raises(LcrlError, match="--state and --perception"):
        stages(dataclasses.replace(p, perception="some/model"))


def test_a_camera_student_of_the_state_student_has_it_as_its_one_teacher(tmp_path):
    """``--state-rounds N``: a stage ``state-student`` (the robosuite-privileged student,
    from every teacher) before the camera student, which it alone teaches, every
    instruction of a chain included, the camera student starting as its copy;
    ``--state-student MODEL`` takes a kept one instead of building it."""
    from train.commands.pipeline import (
        FINE_TUNE,
        STATE_STUDENT,
        _without_chain_teacher,
        robosuite_camera,
        stages,
    )

    p = dataclasses.replace(
        robosuite_camera(), out=str(tmp_path / "camera"), state_rounds=100, state_student=""
    )
    every = {s.name: s for s in stages(p)}
    names = list(every)
    assert names[names.index("student") - 1] == STATE_STUDENT
    state = every[STATE_STUDENT].commands[0]
    assert state[:4] == ["distill", f"{p.out}/teachers/put", "--out", f"{p.out}/{STATE_STUDENT}"]
    assert "--state" in state and state[state.index("--rounds") + 1] == "100"
    assert "--teacher-for" in state and state[state.index("--chain-teacher") + 1] == "scripted"
    assert every[STATE_STUDENT].needs == tuple(
        f"{p.out}/teachers/{f}<teacher-{f}" for f in ("put", "stack")
    )
    camera = every["student"].commands[0]
    assert camera[:2] == ["distill", f"{p.out}/{STATE_STUDENT}"]
    assert "--init-from-teacher" in camera and "--perception" in camera
    assert "--teacher-for" not in camera and "--chain-teacher" not in camera
    assert camera[camera.index("--chain-length") + 1] == "3"  # the other options stay
    assert f"{p.out}/{STATE_STUDENT}<{STATE_STUDENT}" in every["student"].needs
    assert every["student-ft"].commands[0][1] == f"{p.out}/{STATE_STUDENT}"
    # a kept state student: no stage builds one, the camera student waits on no teacher
    kept = dataclasses.replace(p, state_rounds=0, state_student="kept/state")
    every = {s.name: s for s in stages(kept)}
    assert STATE_STUDENT not in every
    assert every["student"].commands[0][1] == "kept/state"
    assert not any("<teacher-" in n for n in every["student"].needs)
    # no rounds through a fine-tuned perception: no stage fine-tunes it
    plain = dataclasses.replace(kept, rounds_ft=0, rounds_aug=5)
    every = {s.name: s for s in stages(plain)}
    assert not set(FINE_TUNE) & set(every)
    aug = every["student-aug"].commands[0]
    assert aug[aug.index("--rounds") + 1] == str(p.rounds + 5)
    assert aug[aug.index("--perception") + 1] == f"{p.out}/perception/model"
    assert "--new-perception" not in aug
    assert every["student-aug"].needs[0].endswith("<student")
    with pytest.raises(LcrlError, match="--state and --state-student"):
        stages(dataclasses.replace(kept, state=True, perception=""))
    assert _without_chain_teacher(["--a", "1", "--chain-teacher", "x", "--chain-teacher=y"]) == [
        "--a", "1"
    ]  # fmt: skip


def test_stages_writing_to_a_log_update_their_bars_twice_a_minute(monkeypatch):
    from train.commands.pipeline_steps import LOG_BAR_INTERVAL, child_env

    monkeypatch.delenv("TQDM_MININTERVAL", raising=False)
    assert "TQDM_MININTERVAL" not in child_env(terminal=True)
    assert child_env(terminal=False)["TQDM_MININTERVAL"] == str(LOG_BAR_INTERVAL)
    monkeypatch.setenv("TQDM_MININTERVAL", "2")  # a user's own setting stays
    assert child_env(terminal=False)["TQDM_MININTERVAL"] == "2"


def test_a_signal_stops_the_pipeline_with_its_own_status():
    """A stage's command ended by SIGTERM stops the pipeline as SIGTERM (status 143),
    not as a Ctrl-C."""
    import signal

    from train.commands.pipeline_steps import Signals, run_command
    from train.training.trainer import RunInterrupted

    signals = Signals()
    signals.signum = signal.SIGTERM  # as the handler records it while a stage runs
    with pytest.raises(RunInterrupted) as stopped:
        run_command(["--help"], signals)
    assert stopped.value.exit_status == 143 and stopped.value.args[0] == "SIGTERM"


def test_stopping_the_camera_benchmark_stops_its_build(monkeypatch):
    """The benchmark's build runs as a child that receives SIGTERM when the benchmark dies
    (it then saves and goes on next time), never training on alone."""
    import subprocess

    from benchmarks import robosuite_camera
    from benchmarks.common import die_with_parent

    seen = {}

    def run(cmd, **kwargs):
        seen.update(cmd=cmd, **kwargs)
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(robosuite_camera.subprocess, "run", run)
    robosuite_camera.lcrl("train", "robosuite-camera", "--out", "W")
    assert seen["cmd"][-4:] == ["train", "robosuite-camera", "--out", "W"]
    assert seen["preexec_fn"] is die_with_parent


def test_the_camera_benchmarks_wall_clock_counts_the_models_it_took_built_before(
    tmp_path, monkeypatch
):
    """A build that took a perception model with ``--perception`` adds the seconds its
    ``build.json`` records (the kept ``perception-80x3`` has one), and one that took a
    state student with ``--state-student`` the seconds of the student stage of the result
    file that keeps it; a model without such a record is refused in one line; a build
    that made its own adds nothing."""
    from benchmarks.robosuite_camera import perception_build, state_student_build

    root = Path(__file__).resolve().parent.parent
    monkeypatch.chdir(root)  # the model's path is the repository's, as the pipeline took it
    work = tmp_path / "work"
    work.mkdir()
    assert perception_build(work) == {}  # no pipeline.json: nothing to add
    (work / "pipeline.json").write_text(json.dumps({"perception": ""}))
    assert perception_build(work) == {}
    kept = "benchmarks/models/perception-80x3/model"
    (work / "pipeline.json").write_text(json.dumps({"perception": kept}))
    record = json.loads((root / "benchmarks/models/perception-80x3/build.json").read_text())
    assert record["seconds"] == sum(s["seconds"] for s in record["stages"]) > 0
    got = perception_build(work)
    assert got["seconds"] == record["seconds"] and got["model"] == kept
    bare = tmp_path / "bare" / "model"
    (work / "pipeline.json").write_text(json.dumps({"perception": str(bare)}))
    with pytest.raises(SystemExit, match=r"no .*build\.json says how long"):
        perception_build(work)
    # a kept privileged-state student: the student stage of the result file that keeps it
    state = "benchmarks/models/robosuite-privileged"
    (work / "pipeline.json").write_text(json.dumps({"state_student": state}))
    result = json.loads((root / "benchmarks/results/robosuite-manipulation.json").read_text())
    got = state_student_build(work)
    assert got["seconds"] == result["stages"]["student"]["seconds"] > 0
    assert got["record"] == "benchmarks/results/robosuite-manipulation.json"
    (work / "pipeline.json").write_text(json.dumps({"state_student": "elsewhere/model"}))
    with pytest.raises(SystemExit, match="no result file in benchmarks/results keeps it"):
        state_student_build(work)


def test_the_camera_benchmark_summarises_an_evaluation_with_intervals():
    """Seen success per family, chain2 and the pooled ratios come with 95% intervals; a
    ratio's interval holds its value and narrows with more episodes."""
    from benchmarks.robosuite_camera import FAMILIES, ratio_interval, summarise

    fams = {f: {"success": 0.5, "ci": [0.4, 0.6]} for f in FAMILIES}

    def doc(seen: float, held: float, para: float) -> dict:
        return {
            "sets": {
                "train": {"success": seen, "episodes": 500, "families": fams},
                "heldout": {"success": held, "episodes": 500, "families": fams},
                "paraphrase": {"success": para, "episodes": 500, "families": fams},
            }
        }

    chain = {"sets": {"train": {"chain": {"success": [
        {"length": 1, "success": 0.7, "ci": [0.6, 0.8]},
        {"length": 2, "success": 0.45, "ci": [0.35, 0.55]},
    ]}}}}  # fmt: skip
    ev = {"sets": doc(0.8, 0.6, 0.7), "chain2": chain, "true_state": doc(0.9, 0.9, 0.9)}
    s = summarise(ev)
    assert s["chain2"] == 0.45 and s["intervals"]["chain2"] == [0.35, 0.55]
    assert abs(s["heldout_ratio"] - 0.75) < 1e-9 and s["intervals"]["push"] == [0.4, 0.6]
    low, high = s["intervals"]["heldout_ratio"]
    assert low < 0.75 < high
    # a policy of the state is evaluated without --true-state: the same summary, no column
    state = summarise({"sets": ev["sets"], "chain2": chain})
    assert state["chain2"] == s["chain2"] and state["heldout_ratio"] == s["heldout_ratio"]
    assert all(state["per_family"][f]["true_state_seen"] is None for f in FAMILIES)
    wide = ratio_interval((0.6, 50), (0.8, 50))
    narrow = ratio_interval((0.6, 5000), (0.8, 5000))
    assert wide[1] - wide[0] > 3 * (narrow[1] - narrow[0])


def _fake_stages(monkeypatch, fail: str = "", seconds: float = 0.15):
    """Stage commands that sleep a moment and make their ``--out`` (and its ``model``),
    logging when each ran; ``fail`` names a command word that fails."""
    import threading
    import time
    from pathlib import Path

    from train.commands import pipeline

    log, lock = [], threading.Lock()
    active = {"now": 0, "most": 0}

    def run_command(args, signals):
        t0 = time.monotonic()
        with lock:
            active["now"] += 1
            active["most"] = max(active["most"], active["now"])
        time.sleep(seconds)
        with lock:
            active["now"] -= 1
        if fail and fail in args:
            raise LcrlError(f"the command `lcrl {args[0]}` failed (status 1)")
        out = Path(args[args.index("--out") + 1])
        if out.suffix == ".h5":  # a data file
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(b"data")
        else:
            (out / "model").mkdir(parents=True, exist_ok=True)
            (out / "model" / "weights.safetensors").write_bytes(b"w")
            (out / "model" / "state.json").write_text("{}")
        if args[0] == "train":  # a run: two checkpoints, the latest named
            for step in ("step_1", "step_2"):
                ckpt = out / "checkpoints" / step
                ckpt.mkdir(parents=True, exist_ok=True)
                (ckpt / "weights.safetensors").write_bytes(b"w")
                (ckpt / "arrays.npz").write_bytes(b"replay")
                (ckpt / "state.json").write_text("{}")
            (out / "latest.json").write_text('{"checkpoint": "checkpoints/step_2"}')
            (out / "tb").mkdir(exist_ok=True)
        with lock:
            log.append((args, t0, time.monotonic()))
        return seconds

    monkeypatch.setattr(pipeline, "run_command", run_command)
    monkeypatch.setattr(pipeline, "keep_policy", lambda p, signals: 0.0)
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 4)
    return log, active


def test_jobs_run_stages_side_by_side_where_none_needs_another(tmp_path, monkeypatch, capsys):
    from train.commands.pipeline import robosuite_camera, run_pipeline, stages, wall_clock

    log, active = _fake_stages(monkeypatch, seconds=0.4)
    p = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "camera"), jobs=2)
    records = run_pipeline(p)
    names = [s.name for s in stages(p)]
    assert all(records[n] is not None for n in names)
    span = {n: records[n]["span"] for n in names if n != "keep"}
    overlap = lambda a, b: span[a][0] < span[b][1] and span[b][0] < span[a][1]  # noqa: E731
    # the perception lane beside the teachers' lane, never more than two at once
    assert overlap("perception-data", "demos-robosuite-manip")
    assert any(overlap("perception", t) for t in ("teacher-put", "teacher-stack"))
    assert active["most"] == 2
    # a stage starts after the stages that make what it needs
    assert span["teacher-put"][0] >= span["demos-robosuite-manip"][1]
    assert span["teacher-stack"][0] >= span["demos-robosuite-manip"][1]
    assert span["perception"][0] >= span["perception-data"][1]
    last_maker = max(span[n][1] for n in ("perception", "teacher-put", "teacher-stack"))
    assert span["student"][0] >= last_maker
    # each training stage on its share of the (four) cores: the teachers beside another
    # stage on two, the student alone on all four
    threads = {a[0]: a[a.index("--torch-threads") + 1] for a, _, _ in log if "--torch-threads" in a}
    assert threads == {"train": "2", "distill": "4", "perception": "4"}  # student-frames alone
    # stages that write one folder never run at once, even when named alone
    active["most"] = 0
    run_pipeline(dataclasses.replace(p, stages=("student", "student-frames", "student-ft")))
    assert active["most"] == 1
    # side by side, the clock counts less than the sum of the stages
    kept = list(records.values())
    assert wall_clock(kept) < sum(r["span"][1] - r["span"][0] for r in kept) - 0.5
    assert "s on the clock" in capsys.readouterr().out


def test_a_failed_stage_stops_the_pipeline_and_starts_nothing_after_it(tmp_path, monkeypatch):
    from train.commands.pipeline import finished, robosuite_camera, run_pipeline

    log, _ = _fake_stages(monkeypatch, fail="record")
    p = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "camera"), jobs=2)
    with pytest.raises(LcrlError, match=r"lcrl demos. failed"):
        run_pipeline(p)
    ran = {args[0] for args, _, _ in log}
    assert "distill" not in ran and "train" not in ran  # no teacher without its demos
    assert finished(p, "demos-robosuite-manip") is None


def test_the_clock_counts_stages_side_by_side_once():
    from train.commands.pipeline import wall_clock

    records = [
        {"seconds": 10, "span": [0, 10]},
        {"seconds": 6, "span": [4, 10]},  # beside the first
        {"seconds": 5, "span": [12, 17]},
        {"seconds": 7},  # from before spans were recorded: its seconds
    ]
    assert wall_clock(records) == 10 + 5 + 7


def test_a_stage_stopped_and_run_again_counts_the_time_of_both_runs(tmp_path, monkeypatch):
    """The time a stage spent before an interrupt or a failure stopped it is in its record
    once it finishes (its seconds and the clock time), not lost with the stopped run."""
    from train.commands.pipeline import robosuite_camera, run_pipeline, wall_clock

    _fake_stages(monkeypatch, fail="collect", seconds=0.2)
    p = dataclasses.replace(
        robosuite_camera(), out=str(tmp_path / "c"), stages=("perception-data",)
    )
    with pytest.raises(LcrlError, match="failed"):
        run_pipeline(p)
    assert not (tmp_path / "c" / "stages" / "perception-data.json").exists()
    _fake_stages(monkeypatch, seconds=0.2)
    record = run_pipeline(p)["perception-data"]
    assert len(record["earlier_spans"]) == 1 and record["seconds"] >= 0.4
    assert wall_clock([record]) >= 0.4 - 1e-6
    assert not list((tmp_path / "c" / "stages").glob(".*partial*"))  # folded into it


def test_parts_of_a_build_are_kept_and_taken_up_by_another(tmp_path, monkeypatch, capsys):
    """--export-parts keeps perception and the teachers (weights, configs and records, no
    data); --parts starts a new build from them: only perception's data (read again by
    perception-ft) and the student's stages run."""
    from train.commands.pipeline import robosuite_camera, run_pipeline, wall_clock

    log, _ = _fake_stages(monkeypatch)
    before = (
        "perception-data", "perception", "demos-robosuite-manip", "teacher-put", "teacher-stack"
    )  # fmt: skip
    first = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "a"), stages=before)
    run_pipeline(first)
    with pytest.raises(LcrlError, match="no finished stage before the student"):
        run_pipeline(dataclasses.replace(first, out=str(tmp_path / "x"), export_parts="p"))
    with pytest.raises(LcrlError, match="give a folder outside the build"):
        run_pipeline(dataclasses.replace(first, export_parts=str(tmp_path / "a" / "parts")))
    parts = tmp_path / "parts"
    run_pipeline(dataclasses.replace(first, stages=(), export_parts=str(parts)))
    assert sorted(f.stem for f in (parts / "stages").glob("*.json")) == sorted(before)
    put = parts / "teachers" / "put"
    assert (put / "latest.json").is_file()
    assert (put / "checkpoints" / "step_2" / "weights.safetensors").is_file()
    assert not (put / "checkpoints" / "step_1").exists() and not (put / "tb").exists()
    assert not list(parts.rglob("*.npz")) and not list(parts.rglob("*.h5"))
    assert (parts / "perception" / "model" / "state.json").is_file()  # a model keeps it
    assert not (put / "checkpoints" / "step_2" / "state.json").exists()  # a run does not
    del log[:]
    second = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "b"), parts=str(parts))
    records = run_pipeline(second)
    ran = [args[0] + " " + args[1] for args, _, _ in log]
    assert ran[0] == "perception collect" and "train robosuite-put" not in ran
    assert "demos record" not in ran and "perception train" in ran  # perception-ft only
    assert ran.count("perception train") == 1
    for name in before[1:]:
        assert records[name]["from_parts"] == str(parts)
    assert "from_parts" not in records["perception-data"]
    assert (tmp_path / "b" / "teachers" / "stack" / "latest.json").is_file()
    assert wall_clock([r for r in records.values() if r]) > 0
    assert "from " + str(parts) in capsys.readouterr().out
    # with another perception model the parts' perception stages are left unused
    del log[:]
    model = tmp_path / "a" / "perception" / "model"
    third = dataclasses.replace(second, out=str(tmp_path / "d"), perception=str(model))
    records = run_pipeline(third)
    assert "perception" not in records and "perception-data" not in records
    assert records["teacher-put"]["from_parts"] == str(parts)
    assert not (tmp_path / "d" / "perception").exists()
    ran = [args[0] + " " + args[1] for args, _, _ in log]
    assert "train robosuite-put" not in ran and ran.count("perception train") == 1
    # a folder that is no parts is refused in one line
    bad = dataclasses.replace(second, out=str(tmp_path / "c"), parts=str(tmp_path))
    with pytest.raises(LcrlError, match="no stages/ folder"):
        run_pipeline(bad)


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--jobs", "0"], "--jobs 0: run one stage at a time at least"),
        (["--parts", "P", "--export-parts", "Q"], "take parts up or write them, not both"),
        (["--parts", "nowhere"], "--parts nowhere: no stages/ folder"),
    ],
)
def test_bad_pipeline_options_are_refused_in_one_line(tmp_path, capsys, args, said):
    out = tmp_path / "camera"
    assert cli("train", "lang2d-camera", "--out", str(out), *args) == 2
    assert said in error_line(capsys.readouterr().err)
    assert not out.exists()  # a refused build leaves nothing behind


def test_a_missing_input_stops_the_stages_beside_it(tmp_path, monkeypatch):
    from train.commands.pipeline import robosuite_camera, run_pipeline

    log, _ = _fake_stages(monkeypatch)
    p = dataclasses.replace(
        robosuite_camera(), out=str(tmp_path / "camera"), jobs=2, stages=("perception-data", "eval")
    )
    with pytest.raises(LcrlError, match=r"the stage eval needs .*student: run the stage student"):
        run_pipeline(p)
    assert [a[0] for a, _, _ in log] == ["perception"]  # it ran to its end, and no more


def test_the_camera_benchmark_evaluates_side_by_side_and_reads_what_is_done(tmp_path, monkeypatch):
    from benchmarks import robosuite_camera

    seen = []

    def run_jobs(jobs, parallel):
        seen.append((jobs, parallel))
        for _, argv, _ in jobs:
            path = argv[argv.index("--json") + 1]
            with open(path, "w") as f:
                json.dump({"argv": argv}, f)

    monkeypatch.setattr(robosuite_camera, "run_jobs", run_jobs)
    (tmp_path / "test-seed7-sets.json").write_text('{"kept": true}')
    out = robosuite_camera.evaluate("M", 7, 100, tmp_path)
    ((jobs, parallel),) = seen
    assert parallel == 2 and [name for name, _, _ in jobs] == ["eval chain2", "eval true_state"]
    assert out["sets"] == {"kept": True}
    chain = out["chain2"]["argv"]
    assert chain[chain.index("eval") + 1 :][:5] == ["M", "--episodes", "100", "--seed", "7"]
    assert "--chain" in chain and "--true-state" in out["true_state"]["argv"]


def test_augmented_rounds_are_a_stage_of_their_own_before_the_evaluation(tmp_path):
    from train.commands.pipeline import _waits_for, robosuite_camera, stages

    p = dataclasses.replace(robosuite_camera(), out=str(tmp_path / "camera"), rounds_aug=0)
    assert "student-aug" not in [s.name for s in stages(p)]
    p = dataclasses.replace(p, rounds_aug=40)
    every = stages(p)
    names = [s.name for s in every]
    assert names[names.index("student-ft") + 1] == "student-aug"
    (aug,) = [s for s in every if s.name == "student-aug"]
    cmd = aug.commands[0]
    assert cmd[:4] == ["distill", f"{p.out}/state-student", "--out", f"{p.out}/student"]
    assert "--resume" in cmd and cmd[cmd.index("--augment") + 1] == "colours"
    assert cmd[cmd.index("--rounds") + 1] == str(p.rounds + p.rounds_ft + 40)
    assert cmd[cmd.index("--perception") + 1] == f"{p.out}/perception-ft/model"
    waits = _waits_for(every)
    assert "student-ft" in waits["student-aug"]
    assert "student-aug" in waits["eval"] and "student-aug" in waits["keep"]

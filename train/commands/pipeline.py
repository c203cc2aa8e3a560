"""One command that builds a camera policy from nothing: ``lcrl train robosuite-camera``.

The stages, each a command of its own run in a child process (its progress shown as it
goes), each writing into the pipeline's folder (``--out``)::

    perception-data   lcrl perception collect: random and scripted frames, labelled
    perception        lcrl perception train: frames -> object slots
    demos-PRESET      scripted demonstrations (lcrl demos record), shared by the teachers
                      that start from them
    teacher-FAMILY    per family: a privileged-state SAC teacher (lcrl train), fine-tuned
                      from the demonstrations where its recipe has them
    student           lcrl distill: one student of every teacher (DAgger over chains),
                      acting from the camera through perception, slots picked by colour
                      and shape
    student-frames    lcrl perception collect: the student's own episodes
    perception-ft     lcrl perception train --init: perception fine-tuned on them
    student-ft        lcrl distill --resume --new-perception: more DAgger rounds with it
    student-aug       lcrl distill --resume --augment colours: more rounds, the colours of
                      every update's rows renamed in scene and instruction (--rounds-aug)
    eval              lcrl eval: every instruction set, and chains of two
    keep              the final policy (weights and configs), its perception model and its
                      canonical reader copied to --keep, with checksums

A stage that finished is recorded in ``OUT/stages/STAGE.json`` and skipped the next time:
the artefact is there. A stage that was stopped goes on where it stopped (``--resume``
for the training and collection stages, which keep what they finished; the perception
stages start again, writing their files atomically). ``--stages`` runs some of them
only; a stage whose inputs are missing says which stage makes them. Ctrl-C and SIGTERM
stop the stage in hand (it saves what it can) and the pipeline, with the status of the
signal.

``--jobs 2`` runs stages side by side where neither needs what the other makes (the
perception stages beside the teachers), each on its share of the cores: on two cores the
build from nothing takes the longer of the two lanes instead of their sum. A stage that
fails stops the others (they save, as on SIGTERM).
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import shlex
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcrl.errors import LcrlError
from train.commands.pipeline_parts import check_parts, export_parts, import_parts
from train.commands.pipeline_settings import CameraPipeline, TeacherRecipe
from train.commands.pipeline_steps import (
    Signals,
    keep_policy,
    run_command,
)
from train.configs.sections import SCRIPTED
from train.runtime.run_lock import lock_run, unlock_run

STAGE_DIR = "stages"
#: The privileged-state student that teaches the camera student (``--state-rounds``).
STATE_STUDENT = "state-student"
#: The stages that fine-tune perception on the student's frames (left out with
#: ``--rounds-ft 0``).
FINE_TUNE = ("student-frames", "perception-ft", "student-ft")
#: The stages of a student that acts through perception (left out with ``--state``).
CAMERA_ONLY = ("perception-data", "perception", STATE_STUDENT, *FINE_TUNE)
#: The stages that build a perception model (left out with ``--perception MODEL``).
PERCEPTION_BUILD = ("perception-data", "perception")


@dataclass
class Stage:
    name: str
    what: str
    commands: list[list[str]]
    needs: tuple[str, ...] = ()
    """Files the stage reads, each with the stage that makes it (``path<stage``)."""
    outputs: tuple[str, ...] = ()
    """What the stage leaves (recorded when it finishes)."""


def _teacher_dir(p: CameraPipeline, family: str) -> Path:
    return Path(p.out) / "teachers" / family


def _teacher_source(p: CameraPipeline, t: TeacherRecipe) -> str:
    """What ``--teacher-for`` names for a family: its run, or ``scripted``."""
    return SCRIPTED if t.preset == SCRIPTED else str(_teacher_dir(p, t.family))


def _perception_model(p: CameraPipeline) -> str:
    return p.perception or str(Path(p.out) / "perception" / "model")


def _running(path: Path) -> bool:
    return (path / "latest.json").is_file()


def _without_chain_teacher(options: Sequence[str]) -> list[str]:
    """``options`` less ``--chain-teacher X``: a student of one teacher has it teach every
    instruction of a chain."""
    kept: list[str] = []
    skip = False
    for o in options:
        if skip:
            skip = False
        elif o == "--chain-teacher":
            skip = True
        elif not o.startswith("--chain-teacher="):
            kept.append(o)
    return kept


def stages(p: CameraPipeline) -> list[Stage]:
    """The pipeline's stages, in order, with their commands as they would run now."""
    out = Path(p.out)
    data = out / "data"
    threads = ["--threads", str(p.threads)] if p.threads else []
    torch_threads = ["--torch-threads", str(p.threads)] if p.threads else []
    found: list[Stage] = []
    if p.state and p.perception:
        raise LcrlError("--state and --perception: a student of the privileged state reads none")
    if p.state and p.state_student:
        raise LcrlError("--state and --state-student: a student of the state has the teachers")
    camera = not p.state
    if camera and not p.perception:
        found.append(
            Stage(
                "perception-data",
                "random and scripted camera frames, labelled with the true object slots",
                [
                    [
                        "perception", "collect", "--env", p.env,
                        "--episodes", str(p.perception_episodes),
                        "--max-episode-steps", str(p.perception_episode_steps),
                        "--image-size", str(p.image_size), "--seed", str(p.seed),
                        "--out", str(data / "perception.h5"), "--resume", "--overwrite",
                    ]
                ],
                outputs=(str(data / "perception.h5"),),
            )
        )  # fmt: skip
        found.append(
            Stage(
                "perception",
                "the perception model: camera frame and proprioception -> object slots",
                [
                    [
                        "perception", "train", "--data", str(data / "perception.h5"),
                        "--steps", str(p.perception_steps), "--seed", str(p.seed),
                        "--out", str(out / "perception"), *threads,
                    ]
                ],
                needs=(f"{data / 'perception.h5'}<perception-data",),
                outputs=(_perception_model(p),),
            )
        )  # fmt: skip
    if not p.trained:
        raise LcrlError(
            "the pipeline needs one trained teacher at least (the student's networks and "
            "instruction table start from it): every family is scripted"
        )
    recorded: set[str] = set()
    for t in p.trained:
        if p.teacher_steps:
            t = dataclasses.replace(t, steps=p.teacher_steps)
        run = _teacher_dir(p, t.family)
        train = ["train", t.preset, "--out", str(run), "--no-progress", *torch_threads]
        needs: tuple[str, ...] = ()
        if t.demos:
            source = t.demo_preset or t.family
            demos = data / f"demos-{source}-{t.demos}.h5"
            maker = f"demos-{source}"
            if maker not in recorded:  # one stage per file, before its first teacher
                recorded.add(maker)
                which = (
                    ["--preset", t.demo_preset]
                    if t.demo_preset
                    else ["--preset", t.preset, "--families", t.family]
                )
                found.append(
                    Stage(
                        maker,
                        f"{t.demos:,} scripted demonstrations ({which[1]}) for the teachers",
                        [
                            [
                                "demos", "record", *which,
                                "--episodes", str(t.demos), "--seed", str(p.seed),
                                "--out", str(demos), "--overwrite",
                            ]
                        ],
                        outputs=(str(demos),),
                    )
                )  # fmt: skip
            needs = (f"{demos}<{maker}",)
            train += ["--finetune.demos", str(demos), "--sac.demo-bc", "1.0"]
        if _running(run):
            train += ["--resume", "--total-steps", str(t.steps)]
        else:
            train += [
                "--env.families", t.family, "--total-steps", str(t.steps),
                "--seed", str(p.seed), "--agent.seed", str(p.seed), *t.extra,
            ]  # fmt: skip
        found.append(
            Stage(
                f"teacher-{t.family}",
                f"the privileged-state teacher of {t.family} ({t.preset}, {t.steps:,} steps"
                + (f", from {t.demos} scripted demonstrations)" if t.demos else ")"),
                [train],
                needs=needs,
                outputs=(str(run),),
            )
        )
    base = p.trained[0]
    others = [t for t in p.teachers if t is not base]
    student = out / "student"
    teacher_needs = tuple(f"{_teacher_dir(p, t.family)}<teacher-{t.family}" for t in p.trained)
    perception_need = () if p.perception or not camera else (f"{_perception_model(p)}<perception",)
    common = [
        "--episodes-per-round", str(p.episodes_per_round),
        "--updates-per-round", str(p.updates_per_round),
        "--hidden", *map(str, p.student_hidden), "--slot-mode", "attributes",
        "--grounding", "1.0", "--seed", str(p.seed), "--overwrite",
        "--families", *p.families, "--max-episode-steps", str(p.max_episode_steps),
    ]  # fmt: skip
    chains = [
        *(["--chain", str(p.chain)] if p.chain else []),
        *([] if p.initial else ["--no-initial"]),
    ]
    of_teachers = [
        *(["--teacher-for", *(f"{t.family}={_teacher_source(p, t)}" for t in others)]
          if others else []),
    ]  # fmt: skip
    head = ["--no-progress", "--eval-every", "0", "--eval-sets", "train", *torch_threads]

    def distill(
        source: str,
        run: Path,
        rounds: int,
        reads: list[str],
        teachers: Sequence[str],
        extra: Sequence[str],
    ) -> list[str]:
        """``lcrl distill`` of ``source`` into ``run``: resumed where it has a checkpoint,
        else from the start with the shared options, ``teachers`` and ``extra``."""
        cmd = ["distill", source, "--out", str(run), *head]
        if _running(run):
            return [*cmd, "--resume", "--rounds", str(rounds), *reads]
        return [*cmd, *reads, "--rounds", str(rounds), *common, *teachers, *chains, *extra]

    through_state = camera and bool(p.state_rounds or p.state_student)
    if through_state and not p.state_student:
        state_run = out / STATE_STUDENT
        state = distill(
            str(_teacher_dir(p, base.family)), state_run, p.state_rounds, ["--state"],
            of_teachers, p.extra_student,
        )  # fmt: skip
        found.append(
            Stage(
                STATE_STUDENT,
                "one student of every teacher (DAgger), acting from the privileged state: "
                "the camera student's one teacher",
                [state],
                needs=teacher_needs,
                outputs=(str(state_run),),
            )
        )
    # the camera student's teacher: the state student (it alone), or the teachers
    teacher = (p.state_student or str(out / STATE_STUDENT)) if through_state else None
    reads = ["--perception", _perception_model(p)] if camera else ["--state"]
    if teacher:
        one = ["--init-from-teacher", *_without_chain_teacher(p.extra_student)]
        student_cmd = distill(teacher, student, p.rounds, reads, (), one)
    else:
        base_dir = str(_teacher_dir(p, base.family))
        student_cmd = distill(base_dir, student, p.rounds, reads, of_teachers, p.extra_student)
    if teacher is None:
        student_needs = teacher_needs
    elif p.state_student:
        student_needs = ()
    else:
        student_needs = (f"{out / STATE_STUDENT}<{STATE_STUDENT}",)
    found.append(
        Stage(
            "student",
            ("one student of the privileged-state student (DAgger), acting from the camera "
             "through perception" if teacher else
             "one student of every teacher (DAgger), acting from the camera through perception")
            if camera
            else "one student of every teacher (DAgger), acting from the privileged state",
            [student_cmd],
            needs=(*student_needs, *perception_need),
            outputs=(str(student),),
        )
    )  # fmt: skip
    frames = data / "student-frames.h5"
    found.append(
        Stage(
            "student-frames",
            "the student's own episodes, labelled with the true object slots",
            [
                [
                    "perception", "collect", "--env", p.env, "--sources", "policy",
                    "--policy", str(student), "--families", *p.families,
                    "--episodes", str(p.student_frames),
                    "--max-episode-steps", str(p.max_episode_steps),
                    "--image-size", str(p.image_size), "--seed", str(p.seed + 101),
                    "--out", str(frames), "--resume", "--overwrite", *torch_threads,
                ]
            ],
            needs=(f"{student}<student",),
            outputs=(str(frames),),
        )
    )  # fmt: skip
    base_data = (
        ["--data", str(data / "perception.h5"), "--extra-data", str(frames)]
        if not p.perception
        else ["--data", str(frames)]
    )
    found.append(
        Stage(
            "perception-ft",
            "perception fine-tuned on the student's own frames",
            [
                [
                    "perception", "train", *base_data, "--init", _perception_model(p),
                    "--steps", str(p.perception_ft_steps), "--lr", "5e-4",
                    "--seed", str(p.seed), "--out", str(out / "perception-ft"), *threads,
                ]
            ],
            needs=(
                f"{frames}<student-frames",
                *(
                    ()
                    if p.perception
                    else (
                        f"{data / 'perception.h5'}<perception-data",
                        f"{_perception_model(p)}<perception",
                    )
                ),
            ),
            outputs=(str(out / "perception-ft" / "model"),),
        )
    )  # fmt: skip
    total = p.rounds + (p.rounds_ft if camera else 0)
    reader = ["--canonical-reader"] if p.reader else []
    tuned = str(out / "perception-ft" / "model") if p.rounds_ft else _perception_model(p)

    def more_rounds(rounds: int, *extra: str) -> list[str]:
        """The student resumed to ``rounds`` rounds, acting through the tuned perception."""
        return [
            "distill", teacher or str(_teacher_dir(p, base.family)), "--out", str(student),
            "--resume",
            "--rounds", str(rounds), "--no-progress", *torch_threads, *extra,
            *(["--perception", tuned, *(["--new-perception", tuned] if p.rounds_ft else [])]
              if camera else ["--state"]),
        ]  # fmt: skip

    found.append(
        Stage(
            "student-ft",
            "more DAgger rounds, the student acting through the fine-tuned perception",
            [more_rounds(total)],
            needs=(f"{tuned}<perception-ft",),
            outputs=(str(student),),
        )
    )
    if p.rounds_aug:
        found.append(
            Stage(
                "student-aug",
                f"more DAgger rounds, every update's rows augmented ({p.augment})",
                [more_rounds(total + p.rounds_aug, "--augment", p.augment)],
                needs=(f"{student}<{'student-ft' if camera and p.rounds_ft else 'student'}",),
                outputs=(str(student),),
            )
        )
    found.append(
        Stage(
            "eval",
            "the final student on every instruction set and on chains of two",
            [
                [
                    "eval", str(student), "--episodes", str(p.eval_episodes),
                    "--seed", str(p.eval_seed), *reader,
                    "--out", str(out / "eval"), "--no-progress",
                ],
                [
                    "eval", str(student), "--episodes", str(p.eval_episodes),
                    "--seed", str(p.eval_seed), *reader, "--chain", "2",
                    "--sets", "train", "--out", str(out / "eval-chain2"), "--no-progress",
                ],
            ],
            needs=(f"{student}<student",),
            outputs=(str(out / "eval"), str(out / "eval-chain2")),
        )
    )  # fmt: skip
    found.append(
        Stage(
            "keep",
            "the final policy, its perception model and its reader, weights and configs only"
            if camera
            else "the final policy and its reader, weights and configs only",
            [],
            needs=(f"{student}<student",),
            outputs=(p.keep or str(out / "kept"),),
        )
    )
    if not camera:  # the student reads the state: nothing to fine-tune perception on
        found = [s for s in found if s.name not in CAMERA_ONLY]
    elif not p.rounds_ft:  # no rounds through a fine-tuned perception: none to fine-tune
        found = [s for s in found if s.name not in FINE_TUNE]
    return found


def wall_clock(records: Sequence[dict[str, Any]]) -> float:
    """Seconds the stages of ``records`` took on the clock: stages that ran side by side
    count once (their spans, and those of their earlier stopped runs, are merged); a
    record without a span counts its seconds."""
    spans = sorted(
        tuple(s) for r in records if r.get("span") for s in (*r.get("earlier_spans", ()), r["span"])
    )
    total = sum(float(r["seconds"]) for r in records if not r.get("span"))
    end = float("-inf")
    for a, b in spans:
        total += max(0.0, b - max(a, end))
        end = max(end, b)
    return total


def stage_names(p: CameraPipeline) -> list[str]:
    return [s.name for s in stages(p)]


def _record(p: CameraPipeline) -> Path:
    return Path(p.out) / STAGE_DIR


def finished(p: CameraPipeline, name: str) -> dict[str, Any] | None:
    """The record of a finished stage (None: not finished)."""
    path = _record(p) / f"{name}.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _stage_threads(p: CameraPipeline, beside: int) -> CameraPipeline:
    """``p`` with the torch threads of a stage that starts with ``beside`` stages running
    (itself included): its share of the cores, unless ``--threads`` names a count. A
    stage that runs alone (``--jobs 1``) chooses its own."""
    if p.jobs <= 1 or p.threads:
        return p
    return dataclasses.replace(p, threads=max(1, (os.cpu_count() or 1) // max(1, beside)))


def _run_stage(p: CameraPipeline, stage: Stage, signals: Signals) -> None:
    """Run one stage's commands and record it as finished, with the time of its earlier
    runs that were stopped (an interrupt, a failure) before it finished."""
    seconds, started = 0.0, time.time()
    partial = _record(p) / f".{stage.name}.partial.json"
    try:
        for args in stage.commands:
            seconds += run_command(args, signals)
        if stage.name == "keep":
            seconds += keep_policy(p, signals)
        signals.check()  # stopped after its last command: not finished
    except BaseException:
        earlier = _earlier_runs(partial)
        earlier.append([round(started, 1), round(time.time(), 1)])
        partial.write_text(json.dumps(earlier))
        raise
    earlier = _earlier_runs(partial)
    record = {
        "stage": stage.name,
        "seconds": round(seconds + sum(b - a for a, b in earlier), 1),
        "commands": ["lcrl " + shlex.join(a) for a in stage.commands],
        "outputs": list(stage.outputs),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "span": [round(started, 1), round(time.time(), 1)],  # wall clock, side by side
    }
    if earlier:
        record["earlier_spans"] = earlier  # runs stopped before it finished
    (_record(p) / f"{stage.name}.json").write_text(json.dumps(record, indent=1))
    partial.unlink(missing_ok=True)


def _earlier_runs(partial: Path) -> list[list[float]]:
    try:
        return [list(map(float, s)) for s in json.loads(partial.read_text())]
    except (OSError, ValueError, TypeError):
        return []


def _makers(stage: Stage) -> list[tuple[str, str]]:
    return [(path, maker) for path, _, maker in (n.rpartition("<") for n in stage.needs)]


def _waits_for(every: list[Stage]) -> dict[str, set[str]]:
    """For each stage, the earlier stages it waits for, directly or through others: those
    that make what it needs, and those that write what it reads or writes (the student's
    later rounds before its evaluation; two runs of one folder never at once)."""
    before: dict[str, set[str]] = {}
    for i, stage in enumerate(every):
        needs = _makers(stage)
        reads = {path for path, _ in needs}
        touched = reads | set(stage.outputs)
        makers = {maker for _, maker in needs}
        direct = {e.name for e in every[:i] if e.name in makers or touched & set(e.outputs)}
        before[stage.name] = direct.union(*(before[d] for d in direct))
    return before


def _schedule(p: CameraPipeline, names: list[str], wanted: list[str], signals: Signals) -> None:
    """Run the wanted stages not done yet in order, up to ``p.jobs`` at once: a stage
    starts when every earlier stage it waits for (:func:`_waits_for`) has finished."""
    todo: list[str] = []
    for i, stage in enumerate(stages(p), 1):
        if stage.name not in wanted:
            continue
        done = finished(p, stage.name)
        if done is not None and not p.stages:
            took = f"done ({done['seconds']:.0f} s), kept"
            print(f"[{i}/{len(names)}] {stage.name}: {stage.what} -- {took}")
            continue
        todo.append(stage.name)
    sys.stdout.flush()
    waits = _waits_for(stages(p))
    running: dict[str, threading.Thread] = {}
    ended: queue.Queue[tuple[str, BaseException | None]] = queue.Queue()
    failure: BaseException | None = None

    def work(stage: Stage, run: CameraPipeline) -> None:
        try:
            _run_stage(run, stage, signals)
        except BaseException as e:  # handed to the main thread
            ended.put((stage.name, e))
        else:
            ended.put((stage.name, None))

    def fail(error: BaseException) -> None:
        nonlocal failure
        if failure is None:
            failure = error
            with signals.lock:  # the stages beside it save and stop, and start nothing
                signals.stopping = True
                signals.stop(signal.SIGTERM)

    while todo or running:
        if failure is None and signals.signum is None:
            ready = [n for n in todo if not waits[n] & {*todo, *running}]
            if p.jobs <= 1:  # in order, one at a time
                ready = ready[:1] if todo and ready and ready[0] == todo[0] else []
            ready = ready[: max(0, p.jobs - len(running))]
            try:
                for name in ready:
                    stage = next(s for s in stages(p) if s.name == name)
                    for path, maker in _makers(stage):
                        if not Path(path).exists():
                            raise LcrlError(
                                f"the stage {name} needs {path}: run the stage {maker} first"
                            )
            except LcrlError as e:
                fail(e)
                ready = []
            run = _stage_threads(p, len(running) + len(ready))
            for name in ready:
                stage = next(s for s in stages(run) if s.name == name)  # commands as of now
                todo.remove(name)
                print(f"[{names.index(name) + 1}/{len(names)}] {name}: {stage.what}", flush=True)
                thread = threading.Thread(target=work, args=(stage, run), name=name, daemon=True)
                running[name] = thread
                thread.start()
        if not running:
            break
        try:
            name, error = ended.get(timeout=0.5)
        except queue.Empty:
            continue
        running.pop(name).join()
        if error is None:
            if p.jobs > 1:
                print(f"{name}: done ({finished(p, name)['seconds']:.0f} s)", flush=True)
            continue
        if isinstance(error, KeyboardInterrupt) and failure is None:  # RunInterrupted
            error.reported = True  # type: ignore[attr-defined]
            print(
                f"lcrl: the pipeline stopped in the stage {name} "
                f"({error.args[0] if error.args else 'interrupted'}): the same command "
                "goes on from there",
                file=sys.stderr,
                flush=True,
            )
        fail(error)
    if failure is not None:
        raise failure
    if signals.signum is not None:  # between two stages: nothing was running to stop
        from train.training.trainer import RunInterrupted

        raise RunInterrupted(signals.signum)


def run_pipeline(p: CameraPipeline) -> dict[str, Any]:
    """Run the stages not done yet (or ``p.stages``); returns the stage records."""
    if p.jobs < 1:
        raise LcrlError(f"--jobs {p.jobs}: run one stage at a time at least (--jobs 1)")
    if p.parts and p.export_parts:
        raise LcrlError("--parts and --export-parts: take parts up or write them, not both")
    if p.parts:
        check_parts(Path(p.parts))
    every = stages(p)
    names = [s.name for s in every]
    unknown = [s for s in p.stages if s not in names]
    if unknown:
        raise LcrlError(f"--stages {' '.join(unknown)}: the stages are {' '.join(names)}")
    out = Path(p.out)
    if p.dry_run:
        for i, stage in enumerate(every, 1):
            done = finished(p, stage.name)
            state = f"done ({done['seconds']:.0f} s)" if done else "to run"
            print(f"[{i}/{len(every)}] {stage.name}: {stage.what} -- {state}")
            for args in stage.commands:
                print(f"  $ lcrl {shlex.join(args)}")
        return {s.name: finished(p, s.name) for s in every}
    if p.export_parts:
        written = export_parts(out, every, Path(p.export_parts))
        print(f"parts of {out} written to {p.export_parts}: {' '.join(written)}")
        return {s.name: finished(p, s.name) for s in every}
    if not p.resume and _record(p).is_dir() and any(_record(p).iterdir()):
        raise LcrlError(f"{out} holds a pipeline already: leave out --no-resume to continue it")
    # one pipeline per folder: its stage records are locked (the stages lock their own
    # folders, and write elsewhere inside OUT)
    note = lock_run(_record(p), "--out")
    if note:
        print(f"lcrl: {note}", file=sys.stderr)
    (out / "pipeline.json").write_text(json.dumps(dataclasses.asdict(p), indent=1))
    if p.parts:
        unused = CAMERA_ONLY if p.state else PERCEPTION_BUILD if p.perception else ()
        taken = import_parts(out, every, Path(p.parts), unused)
        print(f"from {p.parts}: {' '.join(taken) or 'nothing new'}", flush=True)
    signals = Signals()
    previous = {sig: signal.signal(sig, signals.handle) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        _schedule(p, names, list(p.stages) or names, signals)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        unlock_run(_record(p))
    records = {n: finished(p, n) for n in names}
    kept = [r for r in records.values() if r]
    total = sum(r["seconds"] for r in kept)
    print(
        f"pipeline {out}: {len(kept)}/{len(names)} stages done, {total:.0f} s of stages, "
        f"{wall_clock(kept):.0f} s on the clock"
    )
    return records


def robosuite_camera() -> CameraPipeline:
    """The robosuite tabletop's five families from the agentview camera.

    The teachers are those of the best privileged-state student measured
    (``docs/training.md``, one policy from per-family teachers): the memoryless scripted
    controller for reach, push and lift and for every chained instruction, SAC teachers
    for put and stack (grounded slots, from 2,000 scripted demonstrations). They teach a
    student of the privileged state (``state-student``, 100 DAgger rounds over chains of up
    to three instructions, the teacher acting the first instruction of half the episodes,
    as ``lcrl train robosuite-privileged``), and it alone teaches the camera student, which
    starts as its copy: 30 rounds, 10 through perception fine-tuned on its own frames, then
    20 with the colours of every update's rows renamed (``student-aug``). Chosen on
    validation seed 1 over the student of every teacher (110 rounds) and over the same
    student stopped at round 30 or 40:
    ``benchmarks/results/robosuite-camera-privileged-teacher.md``."""
    bf16 = ("--agent.precision", "bf16")
    return CameraPipeline(
        env="robosuite",
        out="runs/robosuite-camera",
        teachers=(
            TeacherRecipe("reach", SCRIPTED, 0),
            TeacherRecipe("push", SCRIPTED, 0),
            TeacherRecipe("lift", SCRIPTED, 0),
            TeacherRecipe("put", "robosuite-put", 150_000, 2000, bf16, "robosuite-manip"),
            TeacherRecipe("stack", "robosuite-stack", 40_000, 2000, bf16, "robosuite-manip"),
        ),
        state_rounds=100,
        rounds=30,
        episodes_per_round=30,
        updates_per_round=1000,
        chain=1.0,
        rounds_aug=20,
        extra_student=(
            "--chain-length", "3", "--chain-teacher", SCRIPTED, "--roll-in", "0.5",
            "--batch-size", "512", "--lr", "3e-4", "--beta-decay", "0.7",
        ),
    )  # fmt: skip


def robosuite_privileged() -> CameraPipeline:
    """One privileged-state policy for the robosuite tabletop's five families: the
    teachers of ``robosuite-camera``, and one student that reads the simulator's state
    (``lcrl distill --state``) instead of the camera, 100 DAgger rounds over chains of
    up to three instructions (the rounds of the best such student measured, chosen on
    validation seed 1: ``docs/training.md``). The put and stack teachers are the parts
    ``--parts benchmarks/models/robosuite-camera-parts`` holds."""
    return dataclasses.replace(
        robosuite_camera(), state=True, out="runs/robosuite-privileged", rounds=100, rounds_aug=0
    )


def lang2d_camera() -> CameraPipeline:
    """The same pipeline on the 2D tabletop's camera frames, sized for minutes (CI)."""
    return CameraPipeline(
        env="lang2d",
        out="runs/lang2d-camera",
        teachers=(
            TeacherRecipe(
                "reach",
                "lang2d-quick",
                3000,
                extra=("--eval-every", "0", "--eval-episodes", "20"),
            ),
        ),
        image_size=64,
        perception_episodes=200,
        perception_episode_steps=5,
        perception_steps=600,
        rounds=4,
        episodes_per_round=10,
        updates_per_round=300,
        student_hidden=(128, 128),
        chain=0.0,
        student_frames=20,
        max_episode_steps=30,
        perception_ft_steps=200,
        rounds_ft=2,
        eval_episodes=30,
    )


#: ``lcrl train NAME`` builds these instead of training one preset.
PIPELINES = {
    "robosuite-camera": robosuite_camera,
    "robosuite-privileged": robosuite_privileged,
    "lang2d-camera": lang2d_camera,
}


def pipeline_cli(name: str, argv: Sequence[str]) -> CameraPipeline:
    """The pipeline ``name`` with the options of ``argv`` (``--out``, ``--stages`` ...)."""
    import tyro

    base = PIPELINES[name]()
    return tyro.cli(
        CameraPipeline,
        default=base,
        args=list(argv),
        prog=f"lcrl train {name}",
        description=(PIPELINES[name].__doc__ or "") + "\n\n" + (__doc__ or "").split("\n\n")[1],
    )


__all__ = [
    "PIPELINES",
    "CameraPipeline",
    "TeacherRecipe",
    "pipeline_cli",
    "run_pipeline",
    "stages",
    "wall_clock",
]

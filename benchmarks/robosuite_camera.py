"""One policy for every robosuite instruction family, built by one command.

    python -m benchmarks.robosuite_camera                 # build (resumable), then evaluate
    python -m benchmarks.robosuite_camera --analyse       # evaluate the kept model only
    python -m benchmarks.robosuite_camera --jobs 2        # two stages at a time where they can
    python -m benchmarks.robosuite_camera --parts benchmarks/models/robosuite-camera-parts
                                                          # from the kept perception and teachers
    python -m benchmarks.robosuite_camera --build robosuite-privileged \
        --parts benchmarks/models/robosuite-camera-parts  # the same teachers, a student of
                                                          # the privileged state

Builds the policy with ``lcrl train BUILD --out WORK --keep MODEL`` (every stage, from
nothing; a stopped build goes on where it stopped), then evaluates the kept model once on
the test seed (``--eval-seed``, which no choice used: the pipeline's own evaluation, on
seed 1, is the validation one) with ``lcrl eval MODEL --episodes 100 --seed S``: every
instruction set, chains of two, and (for the camera policy) the same policy on the true
state.

Writes ``benchmarks/results/robosuite-camera.{json,md,png}`` (``--build robosuite-camera``,
the default) or ``robosuite-manipulation.{json,md,png}`` (``robosuite-privileged``); the
headline holds the seen success of each family, ``chain2``, ``heldout_ratio`` and
``paraphrase_ratio`` (pooled over families), ``wall_clock_s`` (every stage, the teachers
included), ``model`` and ``eval_seed``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.common import (
    LCRL,
    die_with_parent,
    machine,
    run_jobs,
    save_figure,
    save_json,
    save_markdown,
)
from benchmarks.protocol import check_single_policy, check_test_seed
from train.commands.pipeline import wall_clock

FAMILIES = ("reach", "push", "lift", "put", "stack")
WALL_AIM_S = 8 * 3600
#: The camera policy's targets; those of the privileged-state policy (seen success per
#: family and chains of two, as the RL runs before it were held to).
CAMERA_TARGETS = {
    "reach": 0.95, "push": 0.85, "lift": 0.80, "put": 0.60, "stack": 0.40,
    "chain2": 0.50, "heldout_ratio": 0.75, "paraphrase_ratio": 0.85,
}  # fmt: skip
STATE_TARGETS = {
    "reach": 0.90, "push": 0.80, "lift": 0.70, "put": 0.50, "stack": 0.30, "chain2": 0.60,
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Build:
    """One ``lcrl train`` pipeline this benchmark builds and measures."""

    name: str
    """The result file's name."""
    title: str
    reads: str
    """What the policy acts from, in words."""
    targets: dict[str, float]
    work: str
    model: str
    eval_seed: int
    """The test seed (chosen before any evaluation on it)."""
    true_state: bool
    """Also evaluate the same network on the simulator's true state (what perception costs)."""
    tried: tuple[str, ...]
    beside: str = ""
    """A result file of composite systems reported beside this headline."""
    note: str = ""
    """What changed from the file's earlier figures."""


BUILDS = {
    "robosuite-camera": Build(
        name="robosuite-camera",
        title="One camera policy for every robosuite family",
        reads="the camera",
        targets=CAMERA_TARGETS,
        work="runs/robosuite-camera",
        model="benchmarks/models/robosuite-camera",
        eval_seed=7,
        true_state=True,
        tried=(
            "the robosuite-camera pipeline as shipped (train/commands/pipeline.py), one build",
            "its student chosen on validation seed 1 among: the build stopped after student-ft "
            "(round 60), 50 more DAgger rounds as gathered (round 110), and 50 more rounds with "
            "the colours of every update's rows renamed (student-aug, round 110, chosen): "
            "benchmarks/results/robosuite-camera-choice.json",
            "the kept model's canonical reader refitted with the wide vocabulary of training-"
            "only phrasings (chosen on the reader's own validation words, no grammar word and "
            "no evaluation seed: benchmarks/results/reader-robosuite-manip.json); the kept "
            "policy unchanged, seed 7 evaluated again for the new reader (the seen and held-out "
            "sets and chains of two gave the same episodes as with the narrow reader; the "
            "paraphrase set succeeded 38 of 100 times with either, 24 episodes ending "
            "otherwise: paraphrase_ratio 0.69 both)",
            "that build, kept until 2026-12-07, on test seed 7: reach 1.00, push 0.61, lift 0.61, "
            "put 0.38, stack 0.28, chain2 0.08, heldout_ratio 0.98, paraphrase_ratio 0.69",
            "the camera student of the kept privileged-state student alone (state-student; "
            "benchmarks/models/robosuite-privileged, --state-student), from its copy, chosen on "
            "validation seed 1 (pooled over seen, held-out and chains of two; rule fixed before "
            "looking) among: the student of every teacher as kept before (0.39), the new one at "
            "round 30 (0.45), at round 40 after 10 rounds through perception fine-tuned on its "
            "frames (0.40), and at round 60 after 20 more with colours renamed (0.45, chain2 "
            "0.13, chosen): benchmarks/results/robosuite-camera-privileged-teacher.json",
            "the chosen build's student stage is the DAgger run runs/rc-priv/student (the same "
            "options as the stage's command), taken up by the pipeline with --resume; its "
            "record counts that run's span (earlier_spans)",
        ),
    ),
    "robosuite-privileged": Build(
        name="robosuite-manipulation",
        title="One privileged-state policy for every robosuite family",
        reads="the simulator's privileged state",
        targets=STATE_TARGETS,
        work="runs/robosuite-privileged",
        model="benchmarks/models/robosuite-privileged",
        eval_seed=17,
        true_state=False,
        tried=(
            "the robosuite-privileged pipeline as shipped (train/commands/pipeline.py), one build "
            "from the kept put and stack teachers of robosuite-camera-parts; its settings are "
            "those of the best distilled state student measured before (100 rounds, chosen on "
            "validation seed 1: docs/training.md); no choice was made on this build",
            "before it, the distilled one policy of robosuite-manipulation-rl.json (lcrl distill "
            "--state by hand, 100 rounds, from other put and stack teachers: put 0.77 and stack "
            "0.57 alone), on seed 0, where its rounds were chosen beside seed 1: put 0.67, "
            "stack 0.31, chain2 0.44",
        ),
        beside="robosuite-manipulation-rl",
        note="Re-measured as one policy: until 2026-12-05 this file's headline was composite "
        "(put and stack from runs of their own, chains of two from a router over experts, "
        "on seed 0, its wall clock without the experts); those figures are now "
        "robosuite-manipulation-rl.json, beside this one. The headline is the single network "
        "lcrl train robosuite-privileged builds, evaluated once on test seed 17, and wall_clock_s "
        "counts every stage, the teachers included.",
    ),
}


def lcrl(*args: str) -> None:
    """Run ``lcrl ARGS`` as a user would; stop the benchmark if it fails."""
    # stopping the benchmark stops the build too (SIGTERM: it saves and resumes later)
    cmd = [sys.executable, "-m", "train.commands.entry", *args]
    done = subprocess.run(cmd, preexec_fn=die_with_parent)
    if done.returncode != 0:
        raise SystemExit(f"lcrl {' '.join(args)} failed ({done.returncode})")


EVALUATIONS = (
    ("sets", []),
    ("chain2", ["--chain", "2", "--sets", "train"]),
    ("true_state", ["--true-state"]),
)


def evaluate(
    model: str,
    seed: int,
    episodes: int,
    work: Path,
    parallel: int = 2,
    true_state: bool = True,
    extra: Sequence[str] = (),
) -> dict[str, Any]:
    """The kept model's evaluations on ``seed``: sets, chains of two, the true state (with
    ``true_state``); run ``parallel`` at a time, each on its share of the cores (an
    evaluation already done is read). ``extra``: more ``lcrl eval`` options for each."""
    base = [*LCRL, "eval", model, "--episodes", str(episodes), "--seed", str(seed), *extra]
    wanted = [(n, e) for n, e in EVALUATIONS if true_state or n != "true_state"]
    jobs = []
    for name, extra in wanted:
        path = work / f"test-seed{seed}-{name}.json"
        if not path.is_file():
            argv = [*base, "--no-progress", *extra, "--json", str(path)]
            jobs.append((f"eval {name}", argv, work / f"test-seed{seed}-{name}.log"))
    run_jobs(jobs, parallel=parallel)
    return {
        name: json.loads((work / f"test-seed{seed}-{name}.json").read_text()) for name, _ in wanted
    }


def pooled(doc: dict[str, Any], name: str) -> tuple[float, int]:
    s = doc["sets"].get(name)
    return (float(s["success"]), int(s["episodes"])) if s else (float("nan"), 0)


def ratio_interval(
    num: tuple[float, int], den: tuple[float, int], draws: int = 20_000, seed: int = 0
) -> list[float]:
    """95% interval of ``num`` / ``den`` (each a success rate and its episodes), from
    binomial draws of both rates (a parametric bootstrap)."""
    import numpy as np

    (a, n), (b, m) = num, den
    if not n or not m or a != a or b != b:
        return [float("nan"), float("nan")]
    rng = np.random.default_rng(seed)
    top = rng.binomial(n, a, draws) / n
    bottom = rng.binomial(m, b, draws) / m
    ok = bottom > 0
    ratio = top[ok] / bottom[ok]
    return [float(np.quantile(ratio, 0.025)), float(np.quantile(ratio, 0.975))]


def summarise(ev: dict[str, Any]) -> dict[str, Any]:
    sets = ev["sets"]
    seen = sets["sets"]["train"]["families"]
    held = sets["sets"].get("heldout", {}).get("families", {})
    para = sets["sets"].get("paraphrase", {}).get("families", {})
    true = ev["true_state"]["sets"]["train"]["families"] if "true_state" in ev else {}
    chain = ev["chain2"]["sets"]["train"]["chain"]["success"]
    two = next((c["success"] for c in chain if c["length"] == 2), float("nan"))
    seen_all, n_seen = pooled(sets, "train")
    held_all, n_held = pooled(sets, "heldout")
    para_all, n_para = pooled(sets, "paraphrase")
    pair = next((c["ci"] for c in chain if c["length"] == 2), [float("nan")] * 2)
    intervals = {
        **{f: seen.get(f, {}).get("ci") for f in FAMILIES},
        "chain2": pair,
        "heldout_ratio": ratio_interval((held_all, n_held), (seen_all, n_seen)),
        "paraphrase_ratio": ratio_interval((para_all, n_para), (seen_all, n_seen)),
    }
    return {
        "intervals": intervals,
        **{f: seen.get(f, {}).get("success", float("nan")) for f in FAMILIES},
        "chain2": two,
        "heldout_ratio": held_all / seen_all if seen_all else float("nan"),
        "paraphrase_ratio": para_all / seen_all if seen_all else float("nan"),
        "per_family": {
            f: {
                "seen": seen.get(f, {}).get("success"),
                "heldout": held.get(f, {}).get("success"),
                "paraphrase": para.get(f, {}).get("success"),
                "true_state_seen": true.get(f, {}).get("success"),
            }
            for f in FAMILIES
        },
        "pooled": {"seen": seen_all, "heldout": held_all, "paraphrase": para_all},
    }


def validation(work: Path) -> dict[str, Any]:
    """The pipeline's own evaluation (seed 1, the one choices may look at), per family."""
    out: dict[str, Any] = {}
    sets_path, chain_path = work / "eval" / "eval.json", work / "eval-chain2" / "eval.json"
    if sets_path.is_file():
        doc = json.loads(sets_path.read_text())
        for name, s in doc.get("sets", {}).items():
            fams = s.get("families", {})
            out[name] = {f: fams.get(f, {}).get("success") for f in FAMILIES}
    if chain_path.is_file():
        chain = json.loads(chain_path.read_text())["sets"]["train"]["chain"]["success"]
        out["chain2"] = next((c["success"] for c in chain if c["length"] == 2), None)
    return out


def findings(
    summary: dict[str, Any],
    ev: dict[str, Any],
    validation_figures: dict[str, Any],
    stages: dict[str, Any],
    targets: dict[str, float] | None = None,
    seed: int = 0,
) -> list[str]:
    """What the figures say, in words drawn from them: episodes per family, what
    perception costs (the same network on the true state), the validation seed, stages."""
    targets = targets or {}
    seen_all = summary["pooled"]["seen"]
    fams = ev["sets"]["sets"]["train"]["families"]
    counts = ", ".join(f"{f} {fams.get(f, {}).get('episodes', 0)}" for f in FAMILIES)
    total = sum(int(fams.get(f, {}).get("episodes", 0)) for f in FAMILIES)
    lines = [
        f"Episodes per family among the seen set's {total}: {counts}; hence the wide "
        "per-family intervals (Wilson).",
    ]
    if "true_state" in ev:
        true_all, _ = pooled(ev["true_state"], "train")
        lines += [
            "",
            f"The same network on the simulator's true state (`--true-state`) succeeds on "
            f"{true_all:.2f} of seen instructions against {seen_all:.2f} from the camera: "
            f"perception costs {true_all - seen_all:.2f}; what is left is the student's "
            "imitation of its teachers (the scripted controllers and the put and stack "
            "teachers).",
        ]
    lines += [
        "",
        "The paraphrase set reaches the policy through the kept canonical reader, fitted on "
        "training-only phrasings from the wide vocabulary; how many sentences it reads "
        "right is in `reader-robosuite-manip.md`.",
    ]
    shaky = [
        f"{f} {summary[f]:.2f} on seed {seed} against {validation_figures['train'][f]:.2f}"
        for f in FAMILIES
        if f in targets
        and summary[f] >= targets[f]
        and (validation_figures.get("train") or {}).get(f) is not None
        and validation_figures["train"][f] < targets[f]
    ]
    if shaky:
        lines += [
            "",
            f"Reached on the test seed but not on validation seed 1: {'; '.join(shaky)}. "
            "Each family has about 20 of the seen set's episodes, and the intervals are wide: "
            "these figures do not show the target held.",
        ]
    if validation_figures.get("train"):
        per = ", ".join(
            f"{f} {v:.2f}" for f, v in validation_figures["train"].items() if v is not None
        )
        lines += ["", f"Validation seed 1 (the pipeline's eval stage), seen: {per}; "
                  f"chain2 {validation_figures.get('chain2')}."]  # fmt: skip
    lines += ["", "| stage | seconds |", "|---|---:|"]
    lines += [f"| {k} | {v['seconds']:.0f} |" for k, v in stages.items()]
    return lines


def perception_build(work: Path) -> dict[str, Any]:
    """How a perception model the build took with ``--perception`` was built (``build.json``
    beside its ``model/`` folder: its stages and their seconds), so that ``wall_clock_s``
    counts every stage from nothing; nothing when the build made its own. A model without
    that record is refused in one line."""
    settings = work / "pipeline.json"
    model = json.loads(settings.read_text()).get("perception") if settings.is_file() else ""
    if not model:
        return {}
    record = Path(model).parent / "build.json"
    if not record.is_file():
        raise SystemExit(
            f"--perception {model}: no {record} says how long it took to build, and "
            "wall_clock_s counts every stage from nothing"
        )
    doc = json.loads(record.read_text())
    return {"model": model, "record": str(record), "seconds": float(doc["seconds"])}


def state_student_build(work: Path) -> dict[str, Any]:
    """How a privileged-state student the build took with ``--state-student`` was built:
    the ``student`` stage of the result file whose headline keeps that model (its
    teachers are the build's own, counted with its stages), so that ``wall_clock_s``
    counts every stage from nothing; nothing when the build made its own or has none. A
    model no result file records is refused in one line."""
    settings = work / "pipeline.json"
    model = json.loads(settings.read_text()).get("state_student") if settings.is_file() else ""
    if not model:
        return {}
    for path in sorted((Path(__file__).resolve().parent / "results").glob("*.json")):
        doc = json.loads(path.read_text())
        student = doc.get("stages", {}).get("student")
        if doc.get("headline", {}).get("model") == model and student:
            record = f"benchmarks/results/{path.name}"
            return {"model": model, "record": record, "seconds": float(student["seconds"])}
    raise SystemExit(
        f"--state-student {model}: no result file in benchmarks/results keeps it with the "
        "seconds of its student stage, and wall_clock_s counts every stage from nothing"
    )


def taken_lines(taken: dict[str, Any], what: str, option: str) -> list[str]:
    """A model the build took instead of building it, counted in ``wall_clock_s``."""
    if not taken:
        return []
    return [
        "",
        f"The build took the {what} `{taken['model']}` (`{option}`); building it took "
        f"{taken['seconds']:.0f} s (`{taken['record']}`), counted in wall_clock_s.",
    ]


def beside(name: str) -> dict[str, Any]:
    """The headline of the result file ``name`` (composite systems reported beside), or
    nothing where it is missing."""
    path = Path(__file__).resolve().parent / "results" / f"{name}.json"
    if not name or not path.is_file():
        return {}
    doc = json.loads(path.read_text())
    return {"file": f"benchmarks/results/{name}.json", "headline": doc["headline"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--build", choices=sorted(BUILDS), default="robosuite-camera",
                   help="the lcrl train pipeline to build and measure")  # fmt: skip
    p.add_argument("--work", help="the pipeline's folder (default: the build's)")
    p.add_argument("--model", help="kept model (default: the build's)")
    p.add_argument("--eval-seed", type=int, help="the test seed (no choice used it)")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--analyse", action="store_true", help="evaluate the kept model only")
    p.add_argument("--parallel", type=int, default=2, help="evaluations run at once")
    # any other option is passed on to lcrl train BUILD (--threads 1 ...)
    args, pipeline = p.parse_known_args()
    build = BUILDS[args.build]
    work = Path(args.work or build.work)
    model = args.model or build.model
    seed = check_test_seed(build.eval_seed if args.eval_seed is None else args.eval_seed)
    targets = build.targets
    if not args.analyse:
        lcrl("train", args.build, "--out", str(work), "--keep", model, *pipeline)
    stages = {f.stem: json.loads(f.read_text()) for f in sorted((work / "stages").glob("*.json"))}
    ev = evaluate(
        str(check_single_policy(model)),
        seed,
        args.episodes,
        work,
        parallel=args.parallel,
        true_state=build.true_state,
    )
    summary = summarise(ev)
    wall = wall_clock(list(stages.values()))  # stages side by side count once
    perception = perception_build(work)
    state_student = state_student_build(work)
    wall += perception.get("seconds", 0.0) + state_student.get("seconds", 0.0)
    headline = {
        **{k: summary[k] for k in (*FAMILIES, "chain2", "heldout_ratio", "paraphrase_ratio")},
        "wall_clock_s": round(wall, 1),
        "model": model,
        "eval_seed": seed,
    }
    reached = {k: bool(headline[k] >= t) for k, t in targets.items()}
    reached["wall_clock_s"] = wall <= WALL_AIM_S
    info = machine()
    # the figures are what the build command gives (--analyse only re-reads its evaluations)
    argv = drop_options(sys.argv[1:], flags=("--analyse",), valued=("--parallel",))
    cmd = " ".join(["python -m benchmarks.robosuite_camera", *argv])
    payload = {
        "command": cmd,
        "headline": headline,
        "machine": info,
        "targets": {**targets, "wall_clock_s": WALL_AIM_S},
        "reached": reached,
        "intervals": summary["intervals"],
        "per_family": summary["per_family"],
        "pooled": summary["pooled"],
        "validation_seed1": validation(work),
        "stages": {
            k: {"seconds": v["seconds"], "commands": v["commands"]} for k, v in stages.items()
        },
        **({"perception_build": perception} if perception else {}),
        **({"state_student_build": state_student} if state_student else {}),
        "validation": "the pipeline's eval stage (lcrl eval ... --seed 1) is the validation "
        f"evaluation; seed {seed} was evaluated once, for this file",
        "tried": list(build.tried),
    }
    if build.note:
        payload["note"] = build.note
    composite = beside(build.beside)
    if composite:
        payload["beside"] = composite
    save_json(build.name, payload)
    pf = summary["per_family"]

    def cell(x: Any) -> str:
        return "n/a" if x is None else f"{x:.2f}"

    true = build.true_state
    rows = [
        f"| {f} | {cell(pf[f]['seen'])} | {cell(pf[f]['heldout'])} | "
        f"{cell(pf[f]['paraphrase'])} |" + (f" {cell(pf[f]['true_state_seen'])} |" if true else "")
        for f in FAMILIES
    ]
    missed = [k for k, ok in reached.items() if not ok]
    ci = {k: v if v else [float("nan")] * 2 for k, v in summary["intervals"].items()}
    extra = [f"| {k} | {headline[k]:.3f} | |" for k in ("heldout_ratio", "paraphrase_ratio")
             if k not in targets]  # fmt: skip
    body = "\n".join(
        [
            f"One network acting from {build.reads}, kept in `{model}`. Test seed {seed}, "
            f"{args.episodes} episodes per set. Targets "
            + ("all reached." if not missed else f"NOT reached: {', '.join(missed)}."),
            "",
            "| key | value [95% interval] | target |",
            "|---|---:|---:|",
            *(
                f"| {k} | {headline[k]:.3f} [{ci[k][0]:.2f}, {ci[k][1]:.2f}] | {targets[k]} |"
                for k in targets
            ),
            *extra,
            f"| wall_clock_s | {wall:.0f} | aim {WALL_AIM_S} |",
            "",
            "| family | seen | held-out | paraphrase |" + (" true state (seen) |" if true else ""),
            "|---|---:|---:|---:|" + ("---:|" if true else ""),
            *rows,
            "",
            *findings(summary, ev, payload["validation_seed1"], stages, targets, seed),
            *taken_lines(perception, "perception model", "--perception"),
            *taken_lines(state_student, "privileged-state student", "--state-student"),
            *composite_lines(composite),
        ]
    )
    save_markdown(build.name, build.title, body, info, cmd)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.6))
    keys = ("seen", "heldout", "paraphrase", *(("true_state_seen",) if true else ()))
    width = 0.8 / len(keys)
    for i, key in enumerate(keys):
        vals = [summary["per_family"][f][key] or 0 for f in FAMILIES]
        shift = (i - (len(keys) - 1) / 2) * width
        ax.bar([x + shift for x in range(len(FAMILIES))], vals, width, label=key)
    ax.set_xticks(range(len(FAMILIES)), FAMILIES)
    ax.set(ylim=(0, 1.02), ylabel="success", title=build.title)
    ax.legend(fontsize=7)
    save_figure(build.name, fig, info, cmd)
    print(json.dumps(headline, indent=1))


def drop_options(argv: list[str], flags: tuple[str, ...], valued: tuple[str, ...]) -> list[str]:
    """``argv`` without the options that change how, not what, is measured."""
    out: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a in flags or a.split("=")[0] in valued:
            skip = a in valued
        else:
            out.append(a)
    return out


def composite_lines(composite: dict[str, Any]) -> list[str]:
    """The composite systems' figures, beside the headline (never instead of it)."""
    if not composite:
        return []
    h = composite["headline"]
    figures = ", ".join(
        f"{k} {h[k]:.2f}" for k in (*FAMILIES, "chain2") if isinstance(h.get(k), (int, float))
    )
    name = Path(composite["file"]).stem
    return [
        "",
        f"Beside it, composite systems ([{name}.md]({name}.md): an RL policy, put and stack "
        f"from runs of their own, chains of two from experts routed by family): {figures}.",
    ]


if __name__ == "__main__":
    main()

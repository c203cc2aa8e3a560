"""Teacher -> student distillation on the robosuite tabletop: a privileged-state reach policy
taught, with DAgger, to a student that acts from the agentview camera through perception.

    python benchmarks/distill.py --teacher runs/bench/robosuite-reach \
        --perception data/bench-perception-3k/model

Without ``--teacher`` the teacher is trained here first (preset ``robosuite-reach``).
Teacher and student are evaluated with ``lcrl eval`` on the same 100 layouts per
instruction set. Writes ``benchmarks/results/distill-robosuite.{json,md,png}``; target: the
student's seen-instruction success within 5 points of the teacher's.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks import common
from benchmarks.common import (
    LCRL,
    child_env,
    command,
    die_with_parent,
    evaluate,
    machine,
    save_figure,
    save_json,
    save_markdown,
    success_bars,
)
from benchmarks.protocol import VALIDATION_SEEDS, check_test_seed

NAME = "distill-robosuite"
TARGET_GAP = 0.05
SETS = ("train", "heldout", "paraphrase")


def distill(
    args: argparse.Namespace,
    teacher: Path,
    student: Path,
    *,
    rounds: int | None = None,
    updates: int | None = None,
    how: tuple[str, ...] = (),
    resume: bool = False,
    seed: int | None = None,
) -> float:
    """``lcrl distill`` of ``teacher`` into ``student`` (through ``--perception`` unless
    ``how`` says otherwise); the seconds it took. With ``resume`` a student already in
    ``student`` is continued to ``rounds`` (``lcrl distill --resume``) and the seconds are
    its own count over every session (collection and updates, evaluations excluded)."""
    t0 = time.perf_counter()
    rounds = args.rounds if rounds is None else rounds
    updates = args.updates_per_round if updates is None else updates
    how = how or ("--perception", args.perception)
    cmd = [*LCRL, "distill", str(teacher), *how, "--out", str(student)]
    cmd += ["--rounds", str(rounds), "--episodes-per-round", str(args.episodes_per_round)]
    seed = args.seed if seed is None else seed
    cmd += ["--updates-per-round", str(updates), "--seed", str(seed)]
    cmd += ["--beta-decay", str(args.beta_decay), "--eval-every", str(args.eval_every)]
    cmd += ["--eval-episodes", str(args.eval_episodes)]
    resumed = resume and (student / "latest.json").is_file()
    cmd.append("--resume" if resumed else "--overwrite")
    subprocess.run([*cmd, "--no-progress"], check=True, env=child_env(), preexec_fn=die_with_parent)
    evals = rows(student / "eval.csv") if resumed and (student / "eval.csv").is_file() else []
    if evals and "train_s" in evals[-1]:
        return round(evals[-1]["train_s"], 1)
    return round(time.perf_counter() - t0, 1)


def rows(path: Path) -> list[dict[str, float]]:
    with open(path) as f:
        return [{k: float(v) for k, v in r.items() if v != ""} for r in csv.DictReader(f)]


def teacher_on_estimates(
    teacher: Path, perception: str, episodes: int, hold_radius: float | None = None
) -> dict:
    """The teacher acting on perception's estimate of its state instead of the true state,
    on the same ``episodes`` layouts and instructions (seen push instructions) each way:
    how much of the teacher's skill survives perception's errors, whatever the student
    learns. Also the mean absolute difference of its actions on the two, over the steps
    of the true-state episodes, and perception's position error over those steps by the
    object's distance from the gripper (:data:`ERROR_BANDS`). ``hold_radius`` replaces the
    model's own object permanence (``--env.perception-hold-radius``)."""
    import numpy as np

    from envs.features import slot_layout
    from train.environments.tasks import make_env
    from train.evaluation.eval_suite import rate_stats
    from train.evaluation.evaluate import resolve_checkpoint
    from train.policies.loading import load_policy
    from train.training.distill import student_config

    policy = load_policy(resolve_checkpoint(str(teacher)))
    env_cfg = student_config(policy.cfg, perception=perception).env
    env_cfg.perception_hold_radius = hold_radius
    env = make_env(env_cfg, "train")
    task, gaps = policy.task, []
    out: dict = {"hold_radius": env.get_wrapper_attr("held").radius}
    start, count, width, dims = slot_layout(env)
    errors: list[tuple[float, float]] = []  # (distance from the gripper, error), metres

    def slots(x: np.ndarray) -> np.ndarray:
        return x[start : start + count * width].reshape(count, width)

    try:
        for source in ("privileged", "observation"):
            wins = []
            for i in range(episodes):
                obs, _ = env.reset(seed=500_000 + i)
                first, goal = obs, np.asarray([task.goal(obs, env)])
                done, won = False, False
                while not done:
                    acts = {}
                    for s in ("privileged", "observation"):
                        view = task.storage_obs({"observation": obs[s]}, {"observation": first[s]})
                        batch = {k: v[None] for k, v in view.items()}
                        acts[s] = policy.agent.act(batch, goal, deterministic=True)[0]
                    if source == "privileged":
                        gaps.append(float(np.abs(acts["privileged"] - acts["observation"]).mean()))
                        true, seen = slots(obs["privileged"]), slots(obs["observation"])
                        here = true[:, dims] > 0.5  # present kinds (flag after the position)
                        pos = true[here, :dims]
                        near = np.linalg.norm(pos - obs["privileged"][None, :dims], axis=1)
                        wrong = np.linalg.norm(pos - seen[here, :dims], axis=1)
                        errors += zip(near.tolist(), wrong.tolist(), strict=True)
                    obs, _, term, trunc, info = env.step(task.scale_action(acts[source]))
                    won = won or bool(info.get("is_success", False))
                    done = term or trunc
                wins.append(won)
            stats = rate_stats(wins)
            out["true_state" if source == "privileged" else "estimate"] = {
                "success": stats["success"],
                "ci": stats["ci"],
            }
    finally:
        env.close()
        policy.env.close()
    out["episodes"] = episodes
    out["action_gap"] = float(np.mean(gaps))
    out["error_by_gripper_distance"] = error_bands(np.asarray(errors).reshape(-1, 2))
    return out


#: Bands of an object's distance from the gripper (cm) for perception's error in
#: :func:`teacher_on_estimates`: in contact, near, approaching, far.
ERROR_BANDS = ((0, 6), (6, 10), (10, 20), (20, 1000))


def error_bands(errors) -> list[dict]:
    """``(distance, error)`` rows (metres) -> per :data:`ERROR_BANDS` band the steps, the
    mean and the 90th percentile of the error (cm)."""
    import numpy as np

    out = []
    distance = errors[:, 0] * 100
    for lo, hi in ERROR_BANDS:
        inside = (distance >= lo) & (distance < hi)
        e = errors[inside, 1] * 100
        out.append(
            {
                "from_cm": lo,
                "to_cm": hi,
                "object_steps": int(inside.sum()),
                "mean_cm": round(float(e.mean()), 2) if len(e) else None,
                "p90_cm": round(float(np.quantile(e, 0.9)), 2) if len(e) else None,
            }
        )
    return out


#: The evaluation seed of :func:`recheck` (the final evaluations use seed 0).
RECHECK_SEED = 1


def evaluate_all(jobs: dict[str, tuple[Path, int, int]]) -> dict[str, dict]:
    """``{key: (run, episodes, evaluation seed)}`` evaluated on seen instructions, two
    ``lcrl eval`` at a time: ``{key: its train-set result}``."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        futures = {
            key: pool.submit(evaluate, run, episodes, ("train",), seed=seed)
            for key, (run, episodes, seed) in jobs.items()
        }
        return {key: f.result()["train"] for key, f in futures.items()}


def push_stage(args: argparse.Namespace) -> dict:
    """The push teacher distilled too: both evaluated on seen push instructions. With
    ``--push-state-check`` a second student that reads the teacher's own privileged
    state is distilled the same way: what DAgger gives without perception's errors."""
    teacher = Path(args.push_teacher)
    student = Path(args.push_student or Path(args.work) / "push-student")
    rounds = args.push_rounds or args.rounds
    updates = args.push_updates_per_round or args.updates_per_round
    student_args = ("--hidden", *map(str, args.push_hidden)) if args.push_hidden else ()
    if args.push_init_teacher:
        student_args += ("--init-from-teacher",)
    if args.push_lr:
        student_args += ("--lr", str(args.push_lr))
    if args.push_ema:
        student_args += ("--ema", str(args.push_ema))
    if args.push_hold_radius is not None:
        student_args += ("--hold-radius", str(args.push_hold_radius))
    if args.push_eval_sets:
        student_args += ("--eval-sets", *args.push_eval_sets)
    seeds = args.push_seeds or [args.seed]
    members, times = [], []
    for i, seed in enumerate(seeds):
        run = student if i == 0 else student.with_name(f"{student.name}-s{seed}")
        times.append(
            distill(
                args,
                teacher,
                run,
                rounds=rounds,
                updates=updates,
                how=("--perception", args.perception, *student_args),
                resume=args.resume_push,
                seed=seed,
            )
        )
        members.append(run)
    seconds = round(sum(times), 1)
    ensemble = student.with_name(f"{student.name}-ensemble") if len(members) > 1 else None
    if ensemble is not None:
        cmd = [*LCRL, "ensemble", str(ensemble), *map(str, members), "--overwrite"]
        subprocess.run(cmd, check=True, env=child_env(), preexec_fn=die_with_parent)
    acting = ensemble or student
    # every evaluation, two at a time (one torch thread each)
    final_seed = args.push_test_seed
    if final_seed:
        check_test_seed(final_seed, (0, *VALIDATION_SEEDS))
    jobs = {"teacher": (teacher, final_seed), "student": (acting, final_seed)}
    if ensemble is not None:
        jobs.update({f"member-{i}": (run, final_seed) for i, run in enumerate(members)})
    if args.push_recheck:
        jobs.update(
            {"recheck-teacher": (teacher, RECHECK_SEED), "recheck-student": (acting, RECHECK_SEED)}
        )
    results = evaluate_all(
        {
            key: (
                run,
                args.push_recheck if key.startswith("recheck") else args.final_episodes,
                seed,
            )
            for key, (run, seed) in jobs.items()
        }
    )
    t, s = results["teacher"], results["student"]
    member_finals = [
        {"run": str(run), "seed": seed, "distill_s": took,
         "success": results[f"member-{i}"]["success"], "ci": results[f"member-{i}"]["ci"],
         "rounds": rows(run / "progress.csv"), "student_evals": rows(run / "eval.csv")}
        for i, (run, seed, took) in enumerate(zip(members, seeds, times, strict=True))
        if ensemble is not None
    ]  # fmt: skip
    student = acting
    config = teacher / "config.json"
    teacher_cfg = json.loads(config.read_text()) if config.is_file() else {}
    out = {
        "teacher": str(teacher),
        "teacher_config": {
            k: teacher_cfg[k]
            for k in ("env", "total_steps", "seed", "finetune", "sac")
            if k in teacher_cfg
        },
        "student": str(student),
        "perception": args.perception,
        "settings": {
            "rounds": rounds,
            "updates_per_round": updates,
            "hidden": args.push_hidden,
            "init_from_teacher": args.push_init_teacher,
            "lr": args.push_lr or None,
            "ema": args.push_ema or None,
            "hold_radius": args.push_hold_radius,
            "seeds": seeds,
        },
        "student_distill_s": seconds,
        "final_seed": final_seed,
        "final": {
            "teacher": {"success": t["success"], "ci": t["ci"]},
            "student": {"success": s["success"], "ci": s["ci"]},
        },
        "rounds": rows(members[0] / "progress.csv"),
        "student_evals": rows(members[0] / "eval.csv"),
    }
    if member_finals:
        out["members"] = member_finals
        out["ensemble_command"] = f"lcrl ensemble {student} " + " ".join(map(str, members))
    if args.push_recheck:
        out["recheck"] = {
            "seed": RECHECK_SEED,
            "episodes": args.push_recheck,
            "commands": [
                f"lcrl eval {run} --episodes {args.push_recheck} --sets train --seed {RECHECK_SEED}"
                for run in (teacher, student)
            ],
            **{
                who: {k: results[f"recheck-{who}"][k] for k in ("success", "ci")}
                for who in ("teacher", "student")
            },
        }
    if args.keep_push:
        from train.policies.loading import keep_checkpoint

        kept = keep_checkpoint(members[0], Path(args.keep_push), acting_only=True)
        out["kept"] = str(kept)
    if args.push_noise_check:
        out["teacher_on_estimates"] = teacher_on_estimates(
            teacher, args.perception, args.push_noise_check, args.push_hold_radius
        )
    if args.push_state_check:
        check = Path(args.push_state_student or Path(args.work) / "push-state-student")
        check_s = distill(
            args,
            teacher,
            check,
            rounds=rounds,
            updates=updates,
            how=("--state",),
            resume=args.resume_push,
        )
        c = evaluate(check, args.final_episodes, ("train",))["train"]
        out["state_student"] = {
            "run": str(check),
            "distill_s": check_s,
            "final": {"success": c["success"], "ci": c["ci"]},
            "rounds": rows(check / "progress.csv"),
            "evals": rows(check / "eval.csv"),
        }
    return out


def build_parser() -> argparse.ArgumentParser:
    """The benchmark's options."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--teacher", default="", help="a privileged-state reach run")
    parser.add_argument("--teacher-steps", type=int, default=30_000)
    parser.add_argument("--perception", required=True, help="the student's perception model")
    parser.add_argument("--work", default="runs/bench/distill")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--episodes-per-round", type=int, default=20)
    parser.add_argument("--updates-per-round", type=int, default=500)
    parser.add_argument("--beta-decay", type=float, default=0.5)
    parser.add_argument("--final-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--push-teacher", default="", help="a privileged-state push run, distilled the same way"
    )
    parser.add_argument("--eval-every", type=int, default=2, help="rounds between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=50, help="per set, in them")
    parser.add_argument("--push-rounds", type=int, default=0, help="push's rounds (--rounds)")
    parser.add_argument(
        "--push-updates-per-round", type=int, default=0, help="push's (--updates-per-round)"
    )
    parser.add_argument("--push-student", default="", help="default: WORK/push-student")
    parser.add_argument(
        "--push-hidden",
        type=int,
        nargs="+",
        default=[],
        metavar="N",
        help="hidden layer sizes of the push student through perception (default: the teacher's)",
    )
    parser.add_argument(
        "--push-init-teacher",
        action="store_true",
        help="the push student through perception starts as a copy of the teacher "
        "(lcrl distill --init-from-teacher; with --push-hidden, the teacher's layers grown "
        "to those sizes)",
    )
    parser.add_argument(
        "--push-recheck",
        type=int,
        default=0,
        metavar="N",
        help="also evaluate the push teacher and student on N other episodes (evaluation "
        f"seed {RECHECK_SEED})",
    )
    parser.add_argument(
        "--push-test-seed",
        type=int,
        default=0,
        metavar="T",
        help="evaluate the push teacher and student at this test seed (one no choice used; "
        "default 0: the seed the push variants were chosen on)",
    )
    parser.add_argument(
        "--keep-push",
        default="",
        metavar="DIR",
        help="keep the push student (weights, configs and its perception model; acting "
        "only) in DIR",
    )
    parser.add_argument(
        "--push-lr",
        type=float,
        default=0.0,
        help="the push student's learning rate (default: lcrl distill's)",
    )
    parser.add_argument(
        "--push-ema",
        type=float,
        default=0.0,
        help="the push student acts with the Polyak average of its weights (lcrl distill "
        "--ema; default: off)",
    )
    parser.add_argument(
        "--push-seeds",
        type=int,
        nargs="+",
        default=[],
        metavar="S",
        help="distil one push student per seed (the first in --push-student, the others "
        "beside it as NAME-sS) and evaluate the mean of their actions (lcrl ensemble, "
        "NAME-ensemble); default: one student, of --seed",
    )
    parser.add_argument(
        "--push-eval-sets",
        nargs="+",
        default=[],
        metavar="SET",
        help="instruction sets of the push students' periodic evaluations (lcrl distill "
        "--eval-sets; default: every set)",
    )
    parser.add_argument(
        "--push-hold-radius",
        type=float,
        default=None,
        metavar="R",
        help="the push student holds each object's estimate while the gripper is farther "
        "than R from it (lcrl distill --hold-radius; default: the perception model's own)",
    )
    parser.add_argument(
        "--resume-push",
        action="store_true",
        help="continue the push student(s) already there to --push-rounds (lcrl distill "
        "--resume: a distillation carried over several sessions)",
    )
    parser.add_argument(
        "--push-state-check",
        action="store_true",
        help="also distil push into a student reading the teacher's privileged state",
    )
    parser.add_argument("--push-state-student", default="", help="default: WORK/push-state-student")
    parser.add_argument(
        "--push-noise-check",
        type=int,
        default=0,
        metavar="N",
        help="also run the push teacher on N episodes acting on perception's estimate, and on "
        "the same N acting on the true state",
    )
    parser.add_argument(
        "--push-only",
        action="store_true",
        help="distil the push teacher alone; reach's figures stay those of the result file",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.push_only and not args.push_teacher:
        parser.error("--push-only distils --push-teacher RUN")

    info = machine()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.push_only:
        path = common.RESULTS_DIR / f"{NAME}.json"
        if not path.is_file():
            parser.error(f"--push-only keeps reach's figures from {path}, which is missing")
        payload = json.loads(path.read_text())
        earlier = payload.get("push")
        payload["push"] = {**push_stage(args), "command": command(), "machine": info}
        if args.push_test_seed and earlier and not earlier.get("final_seed"):
            # the build chosen on seed 0's episodes, measured again at a test seed
            payload["push_seed0_choice"] = {
                "summary": "the push headline before it was measured at a test seed: "
                "chosen on, and reported from, the same seed-0 episodes",
                "build": earlier,
            }
        if args.push_test_seed:
            payload["headline_note"] = (
                f"The push headline is one network (the student of seed {args.seed}), "
                f"rebuilt by the command and evaluated once, with its teacher, at test seed "
                f"{args.push_test_seed}, which no choice used; its variant was chosen on "
                "seed 0 (push_seed0_choice). It is kept in "
                f"{args.keep_push or 'no folder (no --keep-push)'}."
            )
        # reach's command, then this one (an earlier push command is replaced)
        reach = payload.setdefault("reach_command", payload["command"].split(" && ")[0])
        payload["command"] = f"{reach} && {command()}"
        add_push(payload)
        save_json(NAME, payload)
        render(payload, info)
        print(json.dumps(payload["headline"], indent=1))
        return 0
    times = {}
    teacher = Path(args.teacher) if args.teacher else work / "teacher"
    if not args.teacher:
        t0 = time.perf_counter()
        cmd = [*LCRL, "train", "robosuite-reach", "--out", str(teacher), "--overwrite"]
        cmd += ["--total-steps", str(args.teacher_steps), "--seed", str(args.seed)]
        subprocess.run(
            [*cmd, "--no-progress"], check=True, env=child_env(), preexec_fn=die_with_parent
        )
        times["teacher_train_s"] = round(time.perf_counter() - t0, 1)
    student = work / "student"
    times["student_distill_s"] = distill(args, teacher, student)

    results = {
        name: evaluate(run, args.final_episodes, SETS)
        for name, run in (("teacher", teacher), ("student", student))
    }
    rounds, evals = rows(student / "progress.csv"), rows(student / "eval.csv")
    t, s = results["teacher"], results["student"]
    headline = {
        "teacher_seen": round(t["train"]["success"], 3),
        "student_seen": round(s["train"]["success"], 3),
        "gap": round(t["train"]["success"] - s["train"]["success"], 3),
        "teacher_heldout": round(t["heldout"]["success"], 3),
        "student_heldout": round(s["heldout"]["success"], 3),
        "teacher_paraphrase": round(t["paraphrase"]["success"], 3),
        "student_paraphrase": round(s["paraphrase"]["success"], 3),
        "labelled_states": int(rounds[-1]["rows"]),
        "student_distill_s": times["student_distill_s"],
    }
    teacher_cfg = json.loads((teacher / "config.json").read_text())
    payload = {
        "headline": headline,
        "target": f"student_seen >= teacher_seen - {TARGET_GAP}",
        "reached": {"within_5_points": headline["gap"] <= TARGET_GAP},
        "machine": info,
        "settings": vars(args),
        "teacher_config": {k: teacher_cfg[k] for k in ("env", "total_steps", "seed")},
        "times": times,
        "final": {
            who: {k: {"success": v["success"], "ci": v["ci"]} for k, v in r.items()}
            for who, r in results.items()
        },
        "rounds": rounds,
        "student_evals": evals,
    }
    if args.push_teacher:
        payload["push"] = push_stage(args)
        add_push(payload)
    save_json(NAME, payload)
    render(payload, info)
    print(json.dumps(headline, indent=1))
    return 0


def add_push(payload: dict) -> None:
    """The push figures into the headline and the verdicts."""
    push = payload["push"]
    final = push["final"]
    teacher, student = final["teacher"]["success"], final["student"]["success"]
    members = push.get("members", [])
    # the headline is one network: the command's own seed where several were averaged
    # (the mean of their actions is a composite, reported beside it)
    single = members[0]["success"] if members else student
    payload["headline"].update(
        push_teacher_seen=round(teacher, 3),
        push_student_seen=round(single, 3),
        push_gap=round(teacher - single, 3),
    )
    payload["reached"]["push_within_5_points"] = round(teacher - single, 9) <= TARGET_GAP
    for key in ("push_ensemble_seen", "push_ensemble_gap", "push_ensemble_members"):
        payload["headline"].pop(key, None)
    payload["reached"].pop("push_ensemble_within_5_points", None)
    if members:
        payload["headline"].update(
            push_ensemble_seen=round(student, 3),
            push_ensemble_gap=round(teacher - student, 3),
            push_ensemble_members=len(members),
        )
        payload["reached"]["push_ensemble_within_5_points"] = (
            round(teacher - student, 9) <= TARGET_GAP
        )
    again = push.get("recheck")
    payload["reached"].pop("push_within_5_points_recheck", None)
    payload["reached"].pop("push_ensemble_within_5_points_recheck", None)
    if again:  # the same verdict on the other episodes, for the policy rechecked
        gap = again["teacher"]["success"] - again["student"]["success"]
        key = "push_ensemble_within_5_points_recheck" if members else "push_within_5_points_recheck"
        payload["reached"][key] = round(gap, 9) <= TARGET_GAP


def push_curves(payload: dict) -> dict[str, list[tuple[float, float]]]:
    """``{build: [(round, seen success), ...]}`` of the push student's periodic evaluations:
    the result's own push student, then every build kept beside it that has some."""
    out = {}
    push = payload.get("push")
    builds = [("push (this result)", push)] if push else []
    builds += [
        (key, value.get("build"))
        for key, value in payload.items()
        if key.startswith("push_") and isinstance(value, dict) and "summary" in value
    ]
    for label, build in builds:
        evals = [
            (r["step"], r["train/success"])
            for r in (build or {}).get("student_evals", [])
            if "train/success" in r
        ]
        if evals:
            out[label] = evals
    return out


def render(payload: dict, info: dict) -> None:
    """The Markdown table and the figure of a result payload."""
    final, rounds, headline = payload["final"], payload["rounds"], payload["headline"]
    t, s = final["teacher"], final["student"]
    episodes = payload["settings"]["final_episodes"]

    def rate(x: float) -> str:  # 2 decimals, 3 where 2 would round (0.895 of 200)
        return f"{x:.2f}" if abs(x - round(x, 2)) < 1e-9 else f"{x:.3f}"

    def cell(v: dict) -> str:
        return f"{rate(v['success'])} [{v['ci'][0]:.2f}, {v['ci'][1]:.2f}]"

    lines = [
        "| set | teacher (privileged state) | student (camera, perception) |",
        "|---|---:|---:|",
        *(f"| reach, {k} | {cell(t[k])} | {cell(s[k])} |" for k in SETS),
    ]
    push = payload.get("push")
    if push is not None:
        pt, ps = push["final"]["teacher"], push["final"]["student"]
        members = push.get("members", [])
        if members:  # one network in the headline row, their average beside it
            lines.append(f"| push, train | {cell(pt)} | {cell(members[0])} |")
            lines.append(
                f"| push, train: the mean of {len(members)} students' actions (a composite) "
                f"| | {cell(ps)} |"
            )
        else:
            lines.append(f"| push, train | {cell(pt)} | {cell(ps)} |")
        if push.get("state_student"):
            cs = push["state_student"]["final"]
            lines.append(f"| push, train: a student reading the true state | | {cell(cs)} |")

    def along(evals: list[dict]) -> str:
        """``after rounds 10, 20: 0.25, 0.55`` from a student's eval.csv rows."""
        evals = [r for r in evals if "train/success" in r]
        at = ", ".join(str(int(r["step"])) for r in evals)
        return f"after rounds {at}: " + ", ".join(f"{r['train/success']:.2f}" for r in evals)

    def round_table(rounds: list[dict]) -> list[str]:
        return [
            "| round | teacher's share | student loss | mixed-policy success | labelled states |",
            "|---:|---:|---:|---:|---:|",
            *(
                f"| {int(r['step'])} | {r['teacher_share']:.2f} | {r['loss']:.4f} | "
                f"{r['success']:.2f} | {int(r['rows'])} |"
                for r in rounds
            ),
        ]

    gap, reached = headline["gap"], payload["reached"]
    lines += [
        "",
        "Reach:",
        "",
        *round_table(rounds),
        "",
        f"Target: student within {TARGET_GAP:.2f} of the teacher on seen instructions: "
        f"{'reached' if reached['within_5_points'] else 'NOT reached'} (gap {gap:+.2f}). "
        f"Distillation took {headline['student_distill_s']:.0f} s.",
    ]
    if push is not None:
        model = push.get("perception", payload["settings"]["perception"])
        through = (
            "the same perception model as for reach"
            if model == payload["settings"]["perception"]
            else f"the perception model `{model}`"
        )
        settings = push.get("settings", {})
        hidden = settings.get("hidden")
        layers = f", with hidden layers {'x'.join(map(str, hidden))}" if hidden else ""
        if settings.get("init_from_teacher"):
            layers += ", started as a copy of the teacher's policy (`--init-from-teacher`)"
        if settings.get("lr"):
            layers += f", learning rate {settings['lr']:g}"
        if settings.get("ema"):
            layers += f", acting with the average of its weights (`--ema {settings['ema']:g}`)"
        lines += [
            "",
            f"Push (teacher `{push['teacher']}`, privileged state, started from scripted "
            f"demonstrations; the student acts through {through}{layers}):",
            "",
            *round_table(push["rounds"]),
            "",
            f"Push: student (one network) within {TARGET_GAP:.2f} of the teacher: "
            f"{'reached' if reached['push_within_5_points'] else 'NOT reached'} (gap "
            f"{headline['push_gap']:+.2f}). Distillation took {push['student_distill_s']:.0f} s"
            " (collection and updates).",
        ]
        if "push_ensemble_gap" in headline:
            ensemble_ok = reached.get("push_ensemble_within_5_points")
            lines += [
                "",
                f"The mean of the {headline['push_ensemble_members']} students' actions, a "
                f"composite and not the headline: {headline['push_ensemble_seen']:.2f} (gap "
                f"{headline['push_ensemble_gap']:+.2f}, "
                f"{'within' if ensemble_ok else 'NOT within'} {TARGET_GAP:.2f}).",
            ]
        if payload.get("headline_note"):
            lines += ["", payload["headline_note"]]
        members = push.get("members", [])
        if members:
            alone = "; ".join(
                f"seed {m['seed']} (`{m['run']}`, {m['distill_s']:.0f} s) {cell(m)}"
                for m in members
            )
            lines += [
                "",
                f"The composite is the mean of the actions of {len(members)} students "
                f"distilled the same way with other seeds (`{push.get('ensemble_command', '')}`"
                f"; the distillation time above is theirs together). Alone: {alone}.",
            ]
        if push.get("student_evals"):
            which = "The first of them" if members else "Push student"
            lines += ["", f"{which}'s seen success {along(push['student_evals'])}."]
        again = push.get("recheck")
        if again:
            gap = again["teacher"]["success"] - again["student"]["success"]
            within = "within" if round(gap, 9) <= TARGET_GAP else "NOT within"
            lines += [
                "",
                f"Again on {again['episodes']} other episodes (evaluation seed "
                f"{again['seed']}: other layouts and instructions): teacher "
                f"{cell(again['teacher'])}, "
                f"{'the composite' if members else 'student'} {cell(again['student'])} (gap "
                f"{'+' if gap >= 0 else '-'}{rate(abs(gap))}, {within} {TARGET_GAP:.2f}); "
                f"`{'`, `'.join(again['commands'])}`.",
            ]
        check = push.get("state_student")
        if check:
            lines += [
                "",
                "The same DAgger with a student that reads the teacher's own privileged state "
                f"(`{check['run']}`, no perception): {cell(check['final'])}; its seen success "
                f"{along(check['evals'])} ({check['distill_s']:.0f} s).",
            ]
        if payload.get("push_perception_command") and model != payload["settings"]["perception"]:
            lines += ["", f"Its perception model: `{payload['push_perception_command']}`."]
        if payload.get("push_teacher_command"):
            lines += ["", f"The push teacher was trained by `{payload['push_teacher_command']}`."]
        noise = push.get("teacher_on_estimates")
        if noise:
            lines += [
                "",
                "The push teacher acting on perception's estimate of its state instead of the "
                f"true state ({noise['episodes']} episodes each way, the same layouts and "
                f"instructions): {cell(noise['estimate'])} against {cell(noise['true_state'])}; "
                f"its actions on the two differ by {noise['action_gap']:.3f} on average (mean "
                "absolute difference per action dimension, actions in [-1, 1]).",
            ]
            bands = [b for b in noise.get("error_by_gripper_distance", []) if b["object_steps"]]
            if bands:
                lines += [
                    "",
                    "Perception's position error over the steps of those true-state "
                    "episodes, by the object's distance from the gripper:",
                    "",
                    "| distance from the gripper | object-steps | mean error | 90th percentile |",
                    "|---|---:|---:|---:|",
                ]
                for b in bands:
                    upper = f"-{b['to_cm']}" if b["to_cm"] < 1000 else "+"
                    band = f"{b['from_cm']}{upper} cm"
                    lines.append(
                        f"| {band} | {b['object_steps']} | {b['mean_cm']:.2f} cm "
                        f"| {b['p90_cm']:.2f} cm |"
                    )
        for key, build in payload.items():  # other push builds kept beside this one
            if key.startswith("push_") and isinstance(build, dict) and "summary" in build:
                lines += ["", f"Another build (`{key}`): {build['summary']}"]
        if push.get("command"):
            lines += [
                "",
                f"Push was distilled by `{push['command']}` (on {push['machine']['date']}); "
                f"reach's figures are those of the first command (on "
                f"{payload['machine']['date']}).",
            ]
        if push.get("student_command"):  # a student distilled apart, then resumed here
            lines += [
                "",
                f"The push student's rounds ran as `{push['student_command']}`; the command "
                "above resumed the finished run (`--resume-push`) and evaluated it.",
            ]
    title = "Teacher -> student distillation (DAgger), robosuite reach" + (
        " and push" if push else ""
    )
    save_markdown(NAME, title, "\n".join(lines), payload["machine"], payload["command"])

    import matplotlib.pyplot as plt

    builds = push_curves(payload)
    if builds:
        fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(17, 4.5))
    else:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    steps = [r["step"] for r in rounds]
    ax1.plot(steps, [r["loss"] for r in rounds], "o-", label="reach: student loss")
    if push is not None:
        ax1.plot(
            [r["step"] for r in push["rounds"]],
            [r["loss"] for r in push["rounds"]],
            "^-",
            c="tab:red",
            label="push: student loss",
        )
    ax1.set(xlabel="DAgger round", ylabel="squared action error (teacher labels)", yscale="log")
    ax1b = ax1.twinx()
    ax1b.plot(
        steps, [r["teacher_share"] for r in rounds], "s--", c="tab:orange", label="teacher share"
    )
    ax1b.set(ylabel="teacher's share of the actions", ylim=(0, 1.05))
    ax1.legend(loc="upper right")
    names = [f"{who}\n{k}" for k in SETS for who in ("teacher", "student")]
    vals = [final[who][k] for k in SETS for who in ("teacher", "student")]
    if push is not None:
        names += ["teacher\npush", "student\npush"]
        vals += [push["final"]["teacher"], push["final"]["student"]]
        if push.get("state_student"):
            names += ["state\nstudent\npush"]
            vals += [push["state_student"]["final"]]
    colors = (["tab:grey", "tab:blue"] * len(names))[: len(names)]
    if push is not None and push.get("state_student"):
        colors[-1] = "tab:green"
    success_bars(ax2, names, vals, episodes, color=colors)
    ax2.tick_params(axis="x", labelsize=7)
    if builds:
        for label, evals in builds.items():
            ax3.plot(*zip(*evals, strict=True), "o-", label=label, ms=4)
        teacher = push["final"]["teacher"]["success"]
        ax3.axhline(teacher, c="k", lw=1, label="push teacher (100 episodes)")
        ax3.axhline(teacher - TARGET_GAP, c="k", ls=":", lw=1, label="target: teacher - 0.05")
        ax3.set(xlabel="DAgger round", ylabel="push student's seen success", ylim=(0, 1.02))
        ax3.set_title("push students, 20-episode evaluations along the rounds", fontsize=9)
        ax3.legend(fontsize=6, loc="lower right")
    save_figure(NAME, fig, info, payload["command"], rect=(0, 0.06, 1, 1))


if __name__ == "__main__":
    sys.exit(main())

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

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import (
    command,
    die_with_parent,
    machine,
    save_figure,
    save_json,
    save_markdown,
    success_bars,
)
from benchmarks.image_policy import LCRL, child_env, evaluate

NAME = "distill-robosuite"
TARGET_GAP = 0.05
SETS = ("train", "heldout", "paraphrase")


def main(argv: list[str] | None = None) -> int:
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
    args = parser.parse_args(argv)

    info = machine()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
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
    t0 = time.perf_counter()
    cmd = [*LCRL, "distill", str(teacher), "--perception", args.perception, "--out", str(student)]
    cmd += ["--rounds", str(args.rounds), "--episodes-per-round", str(args.episodes_per_round)]
    cmd += ["--updates-per-round", str(args.updates_per_round), "--seed", str(args.seed)]
    cmd += ["--beta-decay", str(args.beta_decay), "--eval-every", "2", "--overwrite"]
    subprocess.run([*cmd, "--no-progress"], check=True, env=child_env(), preexec_fn=die_with_parent)
    times["student_distill_s"] = round(time.perf_counter() - t0, 1)

    results = {
        name: evaluate(run, args.final_episodes, SETS)
        for name, run in (("teacher", teacher), ("student", student))
    }
    with open(student / "progress.csv") as f:
        rounds = [{k: float(v) for k, v in r.items() if v != ""} for r in csv.DictReader(f)]
    with open(student / "eval.csv") as f:
        evals = [{k: float(v) for k, v in r.items() if v != ""} for r in csv.DictReader(f)]
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
    reached = {"within_5_points": headline["gap"] <= TARGET_GAP}
    teacher_cfg = json.loads((teacher / "config.json").read_text())
    save_json(
        NAME,
        {
            "headline": headline,
            "target": f"student_seen >= teacher_seen - {TARGET_GAP}",
            "reached": reached,
            "command": command(),
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
        },
    )
    lines = [
        "| set | teacher (privileged state) | student (camera, perception) |",
        "|---|---:|---:|",
    ]
    for k in SETS:
        a, b = t[k], s[k]
        lines.append(
            f"| {k} | {a['success']:.2f} [{a['ci'][0]:.2f}, {a['ci'][1]:.2f}] | "
            f"{b['success']:.2f} [{b['ci'][0]:.2f}, {b['ci'][1]:.2f}] |"
        )
    lines += [
        "",
        "| round | teacher's share | student loss | mixed-policy success | labelled states |",
        "|---:|---:|---:|---:|---:|",
        *(
            f"| {int(r['step'])} | {r['teacher_share']:.2f} | {r['loss']:.4f} | "
            f"{r['success']:.2f} | {int(r['rows'])} |"
            for r in rounds
        ),
        "",
        f"Target: student within {TARGET_GAP:.2f} of the teacher on seen instructions: "
        f"{'reached' if reached['within_5_points'] else 'NOT reached'} (gap "
        f"{headline['gap']:+.2f}). Distillation took {times['student_distill_s']:.0f} s.",
    ]
    save_markdown(
        NAME, "Teacher -> student distillation (DAgger), robosuite reach", "\n".join(lines), info
    )

    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    steps = [r["step"] for r in rounds]
    ax1.plot(steps, [r["loss"] for r in rounds], "o-", label="student loss (teacher labels)")
    ax1.set(xlabel="DAgger round", ylabel="squared action error", yscale="log")
    ax1b = ax1.twinx()
    ax1b.plot(
        steps, [r["teacher_share"] for r in rounds], "s--", c="tab:orange", label="teacher share"
    )
    ax1b.set(ylabel="teacher's share of the actions", ylim=(0, 1.05))
    ax1.legend(loc="upper right")
    names = [f"{who}\n{k}" for k in SETS for who in ("teacher", "student")]
    vals = [results[who][k] for k in SETS for who in ("teacher", "student")]
    colors = ["tab:grey", "tab:blue"] * len(SETS)
    success_bars(ax2, names, vals, args.final_episodes, color=colors)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    save_figure(NAME, fig, info)
    print(json.dumps(headline, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

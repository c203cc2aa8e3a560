"""Robosuite reach (and push) acting from the agentview camera: perception, then language HER.

    python benchmarks/image_policy.py --perception-work data/bench-perception-3k --parallel

The actor reads one 84 px camera frame and the gripper's state per step: a frozen
perception model (``benchmarks/perception.py``) estimates the object slots, and the policy
reads positions relative to the gripper and displacements computed from the estimate
(preset ``robosuite-image-reach``; the critic reads the true state in training). Rewards
and relabelling come from the rule captioner, as in every language-HER run.

The wall clock counts everything a user waits for on this machine: collecting the labelled
frames and training perception (measured by ``benchmarks/perception.py`` in the folder
given, read from its ``times.json``; or run here when no folder is given), then training
the reach policy. Reach and push train side by side with one torch thread each
(``--parallel``), so the reach run shares the two cores with the push run. The final
figures are ``lcrl eval`` with 100 episodes per instruction set.

Writes ``benchmarks/results/robosuite-image-reach.{json,md,png}``; targets: seen
instructions >= 0.80 within 5,400 s (3,600 s beyond it).
"""

from __future__ import annotations

import argparse
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
    curve,
    die_with_parent,
    evaluate,
    machine,
    run_seconds,
    save_figure,
    save_json,
    save_markdown,
    success_bars,
)

NAME = "robosuite-image-reach"
TARGETS = {"seen": 0.80, "wall_clock_s": 5400.0}
GOAL_WALL_CLOCK_S = 3600.0


def perception_stage(args: argparse.Namespace) -> tuple[Path, dict[str, float]]:
    """The perception model and the seconds its collection and training took."""
    if args.perception_work:
        work = Path(args.perception_work)
        times_file = work / "times.json"
        if not times_file.is_file():
            raise SystemExit(
                f"{times_file} is missing: run python benchmarks/perception.py --work {work}"
            )
        times = json.loads(times_file.read_text())
        return work / "model", {k: float(v) for k, v in times.items()}
    from benchmarks.perception import main as perception_main

    work = Path(args.work) / "perception"
    perception_main(["--work", str(work), "--no-results"])
    times = json.loads((work / "times.json").read_text())
    return work / "model", {k: float(v) for k, v in times.items()}


#: How push starts from demonstrations (docs/training.md): episodes as long as the
#: scripted ones, starts along them, a BC term on the demonstrators' actions (chains of
#: instructions are not available through perception).
PUSH_DEMO_RECIPE = [
    "--env.max-episode-steps",
    "100",
    "--explore.handover",
    "0.3",
    "--explore.handover-steps",
    "60",
    "--sac.demo-bc",
    "1.0",
    "--sac.target-clip",
    "1.0",
]


def push_demos(args: argparse.Namespace, model: Path) -> tuple[Path, float]:
    """``--push-demos N`` scripted push episodes recorded through the perception model
    (what the image policy reads), and the seconds the recording took (reused from
    ``WORK/push-demos.h5`` when it is there: its meta keeps the time)."""
    path = Path(args.work) / "push-demos.h5"
    if not path.is_file():
        cmd = [*LCRL, "demos", "record", "--preset", "robosuite-image-reach"]
        cmd += ["--perception", str(model), "--families", "push", "--max-episode-steps", "100"]
        cmd += ["--episodes", str(args.push_demos), "--seed", "5", "--out", str(path)]
        subprocess.run(
            [*cmd, "--no-progress"], check=True, env=child_env(), preexec_fn=die_with_parent
        )
    from lcrl.demos import DemoDataset

    with DemoDataset(path) as data:
        seconds = data.meta.get("record_s")
    if seconds is None:
        raise SystemExit(f"{path} does not say how long it took to record: delete it")
    return path, float(seconds)


def train_args(
    args: argparse.Namespace, model: Path, family: str, demos: Path | None = None
) -> list[str]:
    out = Path(args.work) / family
    recipe = [*PUSH_DEMO_RECIPE, "--finetune.demos", str(demos)] if demos else []
    return [
        *LCRL,
        "train",
        "robosuite-image-reach",
        "--env.perception",
        str(model),
        "--env.families",
        family,
        "--out",
        str(out),
        "--total-steps",
        str(args.steps),
        "--eval-every",
        str(args.eval_every),
        "--eval-episodes",
        str(args.eval_episodes),
        "--seed",
        str(args.seed),
        "--overwrite",
        "--no-progress",
        *recipe,
    ]


def reached_word(ok: bool) -> str:
    return "reached" if ok else "NOT reached"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--perception-work", default="", help="benchmarks/perception.py --work")
    parser.add_argument("--work", default="runs/bench/image-policy")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--eval-every", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--final-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--parallel", action="store_true", help="reach and push side by side")
    parser.add_argument("--no-push", action="store_true")
    parser.add_argument(
        "--push-demos",
        type=int,
        default=0,
        metavar="N",
        help="push starts from N scripted episodes recorded through the perception model "
        "(timed; kept in WORK/push-demos.h5)",
    )
    parser.add_argument(
        "--push-only",
        action="store_true",
        help="train and evaluate push alone; reach's figures stay those of the result file",
    )
    parser.add_argument(
        "--eval-only",
        action="store_true",
        help="evaluate the runs already in --work (their training time: from the run "
        "folder's config.json to its report.md)",
    )
    args = parser.parse_args(argv)
    if args.push_only and args.no_push:
        parser.error("--push-only and --no-push exclude each other")
    previous = None
    if args.push_only:
        path = common.RESULTS_DIR / f"{NAME}.json"
        if not path.is_file():
            parser.error(f"--push-only keeps reach's figures from {path}, which is missing")
        previous = json.loads(path.read_text())

    info = machine()
    model, ptimes = perception_stage(args)
    demos, demos_s = push_demos(args, model) if args.push_demos else (None, 0.0)
    families = ["push"] if args.push_only else ["reach"] if args.no_push else ["reach", "push"]
    seconds: dict[str, float] = {}
    procs: dict[str, tuple[subprocess.Popen, float]] = {}
    logs = {}
    Path(args.work).mkdir(parents=True, exist_ok=True)
    if args.eval_only:
        seconds = {family: run_seconds(Path(args.work) / family) for family in families}
    for family in families if not args.eval_only else []:
        logs[family] = open(Path(args.work) / f"{family}.log", "w")  # noqa: SIM115
        cmd = train_args(args, model, family, demos if family == "push" else None)
        procs[family] = (
            subprocess.Popen(
                cmd,
                stdout=logs[family],
                stderr=subprocess.STDOUT,
                env=child_env(),
                preexec_fn=die_with_parent,
            ),
            time.perf_counter(),
        )
        if not args.parallel:
            proc, t0 = procs[family]
            if proc.wait() != 0:
                raise SystemExit(f"the {family} run failed: see {logs[family].name}")
            seconds[family] = time.perf_counter() - t0
    if args.parallel and not args.eval_only:
        for family, (proc, t0) in procs.items():
            if proc.wait() != 0:
                raise SystemExit(f"the {family} run failed: see {logs[family].name}")
            seconds[family] = time.perf_counter() - t0
    for f in logs.values():
        f.close()

    final: dict[str, dict | None] = {"reach": None, "push": None}
    times: dict[str, float | None] = {}
    curves: dict[str, list[dict[str, float]]] = {}
    if previous is not None:  # reach as the result file has it
        final["reach"], curves["reach"] = previous["final"]["reach"], previous["curves"]["reach"]
        times = {k: v for k, v in previous["times"].items() if not k.startswith("push")}
        steps = int(previous["headline"]["steps"])
        if steps != args.steps:
            raise SystemExit(
                f"reach in the result file trained {steps} steps; pass --steps {steps}"
            )
    else:
        t0 = time.perf_counter()
        reach = evaluate(
            Path(args.work) / "reach", args.final_episodes, ("train", "heldout", "paraphrase")
        )
        times = {
            "perception_collect_s": ptimes.get("collect_s"),
            "perception_train_s": ptimes.get("train_s"),
            "reach_train_s": round(seconds["reach"], 1),
            "final_eval_s": round(time.perf_counter() - t0, 1),
        }
        final["reach"] = {
            k: {"success": v["success"], "ci": v["ci"], "episodes": v["episodes"]}
            for k, v in reach.items()
        }
        curves["reach"] = curve(Path(args.work) / "reach")
    if "push" in families:
        push = evaluate(Path(args.work) / "push", args.final_episodes, ("train",))
        final["push"] = {k: {"success": v["success"], "ci": v["ci"]} for k, v in push.items()}
        times["push_train_s"] = round(seconds["push"], 1)
        if demos is not None:
            times["push_demos_record_s"] = round(demos_s, 1)
        curves["push"] = curve(Path(args.work) / "push")
    reach = final["reach"]
    assert reach is not None
    perception_s = float(times.get("perception_collect_s") or 0) + float(
        times.get("perception_train_s") or 0
    )
    wall = perception_s + float(times["reach_train_s"] or 0)
    push_final = final["push"]
    headline = {
        "seen": round(reach["train"]["success"], 3),
        "heldout": round(reach["heldout"]["success"], 3),
        "paraphrase": round(reach["paraphrase"]["success"], 3),
        "wall_clock_s": round(wall, 1),
        "push_seen": None if push_final is None else round(push_final["train"]["success"], 3),
        "steps": args.steps,
    }
    if previous is not None and "push_demo_episodes" not in previous["headline"]:
        headline["push_seen_without_demos"] = previous["headline"]["push_seen"]
    if demos is not None:
        with_demos = perception_s + demos_s + float(times["push_train_s"] or 0)
        headline["push_demo_episodes"] = args.push_demos
        headline["push_wall_clock_s"] = round(with_demos, 1)
    reached = {
        "seen": headline["seen"] >= TARGETS["seen"],
        "wall_clock_s": wall <= TARGETS["wall_clock_s"],
        "wall_clock_goal_3600_s": wall <= GOAL_WALL_CLOCK_S,
    }
    settings = {**vars(args), "preset": "robosuite-image-reach", "perception": str(model)}
    if previous is not None:
        settings = {**previous["settings"], "push": settings}
        settings["push"]["command"] = command()
    payload = {
        "headline": headline,
        "targets": TARGETS,
        "reached": reached,
        # merged: the command that made reach's figures, then the one that made push's
        "command": command() if previous is None else f"{previous['command']} && {command()}",
        "machine": info,
        "settings": settings,
        "times": times,
        "final": final,
        "curves": curves,
    }
    if previous is not None:
        payload["push_command"] = command()
        payload["reach_machine"] = previous["machine"]
    save_json(NAME, payload)
    render(payload, info)
    print(json.dumps(headline, indent=1))
    return 0


def render(payload: dict, info: dict) -> None:
    """The Markdown table and the figure of a result payload."""
    headline, times, final = payload["headline"], payload["times"], payload["final"]
    curves, settings, reached = payload["curves"], payload["settings"], payload["reached"]
    reach, push = final["reach"], final["push"]
    wall = headline["wall_clock_s"]
    episodes = settings["final_episodes"]
    merged = bool(payload.get("push_command"))  # sentences on settings: the first command

    def row(name: str, v: dict) -> str:
        return f"| {name} | {v['success']:.2f} | [{v['ci'][0]:.2f}, {v['ci'][1]:.2f}] |"

    lines = [
        "| set | success | 95% CI |",
        "|---|---:|---|",
        *(row(f"reach, {name}", v) for name, v in reach.items()),
    ]
    if push is not None:
        demos = headline.get("push_demo_episodes")
        lines.append(
            row(f"push, train{f' (from {demos} demonstrations)' if demos else ''}", push["train"])
        )
    lines += [
        "",
        "| stage | seconds |",
        "|---|---:|",
        f"| perception: collect labelled frames | {times.get('perception_collect_s') or 0:.0f} |",
        f"| perception: train | {times.get('perception_train_s') or 0:.0f} |",
        f"| reach policy: train ({headline['steps']} steps) | {times['reach_train_s']:.0f} |",
    ]
    if times.get("push_demos_record_s") is not None:
        lines.append(
            f"| push: record {headline['push_demo_episodes']} demonstrations through "
            f"perception | {times['push_demos_record_s']:.0f} |"
        )
    if times.get("push_train_s") is not None:
        lines.append(
            f"| push policy: train ({headline['steps']} steps) | {times['push_train_s']:.0f} |"
        )
    lines.append(f"| **to a reach policy** | **{wall:.0f}** |")
    if headline.get("push_wall_clock_s") is not None:
        lines.append(f"| **to a push policy** | **{headline['push_wall_clock_s']:.0f}** |")
    lines += [
        "",
        f"Learning curves (seen instructions, {settings['eval_episodes']} episodes per "
        "evaluation):",
        "",
        *(
            f"- {family}: " + ", ".join(f"{int(r['step'])}: {r['train/success']:.2f}" for r in rows)
            for family, rows in curves.items()
        ),
        "",
        f"Targets: seen >= {TARGETS['seen']} ({reached_word(reached['seen'])}); wall clock <= "
        f"{TARGETS['wall_clock_s']:.0f} s ({reached_word(reached['wall_clock_s'])}; "
        f"{GOAL_WALL_CLOCK_S:.0f} s: {reached_word(reached['wall_clock_goal_3600_s'])})."
        + (
            (
                " The first command trained reach and push (without demonstrations) side by "
                "side, one torch thread each."
                if merged
                else " Reach and push trained side by side, one torch thread each."
            )
            if settings.get("parallel")
            else ""
        )
        + (
            (
                " The runs were trained without --eval-only; its pass evaluated "
                if merged
                else " The runs were trained by this command without --eval-only; this pass "
                "evaluated "
            )
            + "them (training time: from each run's config.json to its report.md)."
            if settings.get("eval_only")
            else ""
        ),
    ]
    if payload.get("push_command"):
        lines += [
            "",
            f"Push was trained and evaluated again by `{payload['push_command']}` "
            f"(on {info['date']}); reach's figures are those of the first command "
            f"(on {payload['reach_machine']['date']}).",
        ]
    if headline.get("push_seen_without_demos") is not None:
        lines += ["", f"Push without demonstrations: {headline['push_seen_without_demos']:.2f}."]
    if headline.get("push_demo_episodes"):
        lines += [
            "",
            f"Push starts from {headline['push_demo_episodes']} scripted episodes recorded "
            "through the same perception model (`lcrl demos record --perception`), with a BC "
            "term on their actions and starts along them (`--finetune.demos`, "
            "`--sac.demo-bc 1.0`; docs/training.md). The push wall clock counts perception, "
            "the recording and the training.",
        ]
    title = "Robosuite tabletop from camera images: reach (and push)"
    save_markdown(NAME, title, "\n".join(lines), info, payload["command"])

    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for family, rows in curves.items():
        ax1.plot([r["step"] for r in rows], [r["train/success"] for r in rows], "o-", label=family)
    ax1.axhline(TARGETS["seen"], ls="--", c="grey", lw=0.8)
    ax1.set(xlabel="environment steps", ylabel="success (seen instructions)", ylim=(0, 1.02))
    ax1.set_title("acting from the agentview camera")
    ax1.legend()
    names = list(reach) + ([f"push {k}" for k in push] if push else [])
    values = list(reach.values()) + (list(push.values()) if push else [])
    success_bars(ax2, names, values, episodes, color="tab:blue")
    ax2.set_title(f"final policy; {wall:.0f} s to the reach policy")
    save_figure(NAME, fig, info, payload["command"], rect=(0, 0.06, 1, 1))


if __name__ == "__main__":
    sys.exit(main())

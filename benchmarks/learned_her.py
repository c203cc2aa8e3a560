"""Language HER relabelled by the learned captioner and reward model over perception,
beside the rule captioner's, same preset, seed and budget.

    python benchmarks/learned_her.py --env robosuite --perception data/perception-3k/model \
        --captioner runs/bench/captioner-robosuite-perception --target-clip 1.0
    python benchmarks/learned_her.py --env lang2d --captioner runs/bench/captioner-lang2d-perception

robosuite: the image policy of ``robosuite-image-reach`` (it acts through ``--perception``);
relabelling candidates and rewards come from the learned models (``--relabel.captioner
learned --relabel.reward learned``), which read the frames through their own perception
model, or from the rule captioner. lang2d: the ``lang2d`` preset (privileged-state policy,
reach and push), relabelled the same two ways. The two runs train side by side, one
torch thread each; the final figures are ``lcrl eval`` with 100 episodes per set.

Writes ``benchmarks/results/learned-her-<env>.{json,md,png}`` and adds
``learned_her_seen`` and ``rule_her_seen`` to the ``headline`` of
``benchmarks/results/captioner-<env>.json``; target: learned within 10 points of rule.
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
    RESULTS_DIR,
    command,
    die_with_parent,
    machine,
    save_figure,
    save_json,
    save_markdown,
)
from benchmarks.image_policy import LCRL, child_env, evaluate

TARGET_GAP = 0.10
PRESETS = {"robosuite": "robosuite-image-reach", "lang2d": "lang2d"}


def run_args(args: argparse.Namespace, name: str) -> list[str]:
    cmd = [*LCRL, "train", PRESETS[args.env], "--out", str(Path(args.work) / name)]
    cmd += ["--total-steps", str(args.steps), "--eval-every", str(args.eval_every)]
    cmd += ["--eval-episodes", str(args.eval_episodes), "--seed", str(args.seed)]
    cmd += ["--overwrite", "--no-progress"]
    if args.perception:
        cmd += ["--env.perception", args.perception]
    if args.target_clip:
        cmd += ["--sac.target-clip", str(args.target_clip)]
    if name == "learned":
        cmd += ["--relabel.captioner", "learned", "--relabel.reward", "learned"]
        cmd += ["--relabel.checkpoint", args.captioner]
        cmd += ["--relabel.threshold", str(args.threshold)]
        if getattr(args, "family_thresholds", None):
            cmd += ["--relabel.family-thresholds", *args.family_thresholds]
        if getattr(args, "agree", False):
            cmd += ["--relabel.agree"]
        if getattr(args, "confirm", False):
            cmd += ["--relabel.confirm"]
        if getattr(args, "end", "limit") != "limit":
            cmd += ["--relabel.end", args.end]
    return cmd


def reuse(run: Path, into: Path, args: argparse.Namespace, name: str = "rule") -> float:
    """Take a finished run whose config is this benchmark's ``name`` run's (all but
    ``out``), copied to ``into`` unless it is there already; returns its training seconds
    (config.json to report.md).

    Raises:
        SystemExit: the run is unfinished or was trained with another config.
    """
    import shutil

    from benchmarks.learning_curves import same_config
    from train.cli import parse_train_args

    if not (run / "report.md").is_file():
        raise SystemExit(f"{run}: not a finished run (no report.md)")
    cmd = run_args(args, name)
    wanted = parse_train_args(cmd[cmd.index("train") + 1 :])
    saved_steps = json.loads((run / "config.json").read_text()).get("total_steps")
    # options added since the run was saved count as the defaults it ran with
    if not same_config(wanted, run) or saved_steps != wanted.total_steps:
        raise SystemExit(f"{run}: its config differs from the {name} run's")
    if run.resolve() != into.resolve():
        if into.exists():
            shutil.rmtree(into)
        shutil.copytree(run, into, symlinks=True)
    return round((run / "report.md").stat().st_mtime - (run / "config.json").stat().st_mtime, 1)


def update_captioner_markdown(path: Path, headline: dict) -> None:
    """Rewrite the relabelling lines of the captioner's Markdown (its command and the rest
    stay the captioner benchmark's)."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    for key in ("learned_her_seen", "rule_her_seen"):
        line = f"- {key}: {headline[key]:.2f} (see learned-relabelling results)."
        at = [i for i, x in enumerate(lines) if x.startswith(f"- {key}:")]
        if at:
            lines[at[0]] = line
        else:
            lines.append(line)
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", choices=tuple(PRESETS), required=True)
    parser.add_argument("--captioner", required=True, help="lcrl caption train --out")
    parser.add_argument("--perception", default="", help="the policy's (robosuite)")
    parser.add_argument("--work", default="")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--eval-every", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--final-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threshold",
        type=float,
        default=0.5,
        help="reward-model probability that counts as satisfied (--relabel.threshold)",
    )
    parser.add_argument(
        "--family-thresholds",
        nargs="+",
        default=[],
        metavar="FAMILY=P",
        help="per-family reward thresholds (--relabel.family-thresholds), e.g. push=0.9",
    )
    parser.add_argument(
        "--confirm",
        action="store_true",
        help="the learned run relabels with a caption only where the reward model judges it "
        "achieved too (--relabel.confirm)",
    )
    parser.add_argument(
        "--end",
        choices=("limit", "learned"),
        default="limit",
        help="where the learned run's training episodes end (--relabel.end): the time limit, "
        "or also where the learned reward model judges the instruction achieved",
    )
    parser.add_argument(
        "--agree",
        action="store_true",
        help="the learned run counts a reward only where the captioner reads the "
        "instruction too (--relabel.agree)",
    )
    parser.add_argument(
        "--target-clip",
        type=float,
        default=0.0,
        help="--sac.target-clip for both runs (0: none); 1.0 keeps the critics of sparse "
        "success rewards within their bound",
    )
    parser.add_argument(
        "--commands",
        action="store_true",
        help="print the two lcrl train commands (to start them one by one) and exit",
    )
    parser.add_argument(
        "--existing",
        action="store_true",
        help="both runs are in WORK already, finished by the commands this benchmark would "
        "run (started one by one, e.g. the rule run before the captioner is trained): only "
        "evaluate and report them",
    )
    parser.add_argument(
        "--reuse-rule",
        default="",
        help="a finished run of the same preset, seed, budget and perception (e.g. the "
        "image_policy.py reach run) to take as the rule run instead of training it again",
    )
    args = parser.parse_args(argv)
    if args.env == "robosuite" and not args.perception:
        parser.error("--env robosuite trains the image policy: pass --perception MODEL")
    args.work = args.work or f"runs/bench/learned-her-{args.env}"

    if args.commands:
        for name in ("rule", "learned"):
            print(" ".join(run_args(args, name)))
        return 0
    info = machine()
    Path(args.work).mkdir(parents=True, exist_ok=True)
    procs, seconds = {}, {}
    names = ("rule", "learned")
    if args.reuse_rule:
        seconds["rule"] = reuse(Path(args.reuse_rule), Path(args.work) / "rule", args)
        names = ("learned",)
    if args.existing:
        for name in names:
            seconds[name] = reuse(Path(args.work) / name, Path(args.work) / name, args, name)
        names = ()
    for name in names:
        log = open(Path(args.work) / f"{name}.log", "w")  # noqa: SIM115
        proc = subprocess.Popen(
            run_args(args, name),
            stdout=log,
            stderr=subprocess.STDOUT,
            env=child_env(),
            preexec_fn=die_with_parent,
        )
        procs[name] = (proc, log, time.perf_counter())
    for name, (proc, log, t0) in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"the {name} run failed: see {log.name}")
        seconds[name] = round(time.perf_counter() - t0, 1)
        log.close()
    sets = ("train", "heldout", "paraphrase")
    runs = ("rule", "learned")
    final = {name: evaluate(Path(args.work) / name, args.final_episodes, sets) for name in runs}
    curves = {}
    for name in runs:
        with open(Path(args.work) / name / "eval.csv") as f:
            curves[name] = [{k: float(v) for k, v in r.items() if v} for r in csv.DictReader(f)]
    agreement = {}
    with open(Path(args.work) / "learned" / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    keys = [  # over all instructions, then per family (labels_push_precision, ...)
        k
        for k in (rows[0] if rows else {})
        if k.startswith(("labels_", "rewards_")) and k.endswith(("_precision", "_recall"))
    ]
    for key in keys:
        values = [float(r[key]) for r in rows[-5:] if r.get(key) not in (None, "", "nan")]
        if values:
            agreement[key] = round(sum(values) / len(values), 3)
    learned, rule = final["learned"]["train"]["success"], final["rule"]["train"]["success"]
    headline = {
        "learned_her_seen": round(learned, 3),
        "rule_her_seen": round(rule, 3),
        "gap": round(rule - learned, 3),
        "learned_her_heldout": round(final["learned"]["heldout"]["success"], 3),
        "rule_her_heldout": round(final["rule"]["heldout"]["success"], 3),
        "steps": args.steps,
    }
    reached = {"within_10_points": headline["gap"] <= TARGET_GAP}
    name = f"learned-her-{args.env}"
    save_json(
        name,
        {
            "headline": headline,
            "target": f"learned_her_seen >= rule_her_seen - {TARGET_GAP}",
            "reached": reached,
            "command": command(),
            "machine": info,
            "settings": {**vars(args), "preset": PRESETS[args.env]},
            "seconds": seconds,
            "agreement_with_rule_last_rows": agreement,
            "final": {
                n: {k: {"success": v["success"], "ci": v["ci"]} for k, v in r.items()}
                for n, r in final.items()
            },
            "curves": curves,
        },
    )
    captioner_file = RESULTS_DIR / f"captioner-{args.env}.json"
    if captioner_file.exists():  # the captioner's results carry the relabelling figures too
        doc = json.loads(captioner_file.read_text())
        doc.setdefault("headline", {}).update(
            learned_her_seen=headline["learned_her_seen"], rule_her_seen=headline["rule_her_seen"]
        )
        doc.setdefault("reached", {})["learned_her_within_10_points"] = reached["within_10_points"]
        doc["learned_her"] = {"command": command(), "file": f"{name}.json"}
        captioner_file.write_text(json.dumps(doc, indent=1))
        update_captioner_markdown(captioner_file.with_suffix(".md"), headline)

    lines = [
        "| relabelling | seen | held-out combinations | paraphrases | train time (s) |",
        "|---|---:|---:|---:|---:|",
    ]
    for n, r in final.items():
        cells = [f"{r[k]['success']:.2f} [{r[k]['ci'][0]:.2f}, {r[k]['ci'][1]:.2f}]" for k in sets]
        lines.append(f"| {n} | {' | '.join(cells)} | {seconds[n]:.0f} |")
    lines += [
        "",
        "Learning curves (seen instructions):",
        "",
        "| run | " + " | ".join(str(int(r["step"])) for r in curves["rule"]) + " |",
        "|---|" + "---:|" * len(curves["rule"]),
        *(
            f"| {n} | " + " | ".join(f"{r['train/success']:.2f}" for r in rows) + " |"
            for n, rows in curves.items()
        ),
        "",
        "Agreement of the learned run's labels and rewards with the rule captioner (mean of "
        "the last progress rows): " + ", ".join(f"{k} {v:.2f}" for k, v in agreement.items()),
        "",
        f"Target: learned within {TARGET_GAP:.2f} of rule on seen instructions: "
        f"{'reached' if reached['within_10_points'] else 'NOT reached'} (gap "
        f"{headline['gap']:+.2f}).",
    ]
    title = f"Learned relabelling over perception vs the rule captioner ({args.env})"
    save_markdown(name, title, "\n".join(lines), info)

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for n, rows in curves.items():
        ax.plot([r["step"] for r in rows], [r["train/success"] for r in rows], "o-", label=n)
    ax.set(xlabel="environment steps", ylabel="success (seen instructions)", ylim=(0, 1.02))
    ax.set_title(f"{PRESETS[args.env]}: relabelled by rule or learned models")
    ax.legend()
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    save_figure(name, fig, info)
    print(json.dumps(headline, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

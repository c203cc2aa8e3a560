"""Language HER relabelled by the learned captioner and reward model over perception,
beside the rule captioner's, same preset, seed and budget.

    python benchmarks/learned_her.py --env robosuite --perception data/perception-3k/model \
        --captioner runs/bench/captioner-robosuite-perception --target-clip 1.0
    python benchmarks/learned_her.py --env lang2d --captioner runs/bench/captioner-lang2d-perception

    python -m benchmarks.learned_her --env robosuite \
        --perception benchmarks/models/perception-3k/model \
        --captioner 'benchmarks/models/captioner-factored-robosuite-policy/seed{seed}/model' \
        --families reach push lift --max-episode-steps 100 --steps 30000 \
        --eval-every 10000 --eval-episodes 30 --target-clip 1.0 --seeds 0 1 2 \
        --extra "--finetune.demos data/demos-image-rpl-600i.h5 --sac.demo-bc 1.0" \
        --threshold 0.9 --labels reward --end learned --eval-seed 1002 \
        --keep benchmarks/models/learned-her-robosuite

(the demonstrations, with their camera frames for the learned models to read: ``lcrl demos
record --preset robosuite-image-reach --families reach push lift --max-episode-steps 100
--episodes 600 --seed 11 --images --out data/demos-image-rpl-600i.h5``)

robosuite: the image policy of ``robosuite-image-reach`` (it acts through ``--perception``;
``--families`` widens it beyond reach);
relabelling candidates and rewards come from the learned models (``--relabel.captioner
learned --relabel.reward learned``), which read the frames through their own perception
model, or from the rule captioner. lang2d: the ``lang2d`` preset (privileged-state policy,
reach and push), relabelled the same two ways. The two runs train side by side, one
torch thread each; the final figures are ``lcrl eval`` with 100 episodes per set.

With ``--keep DIR`` every seed's policies are kept in ``DIR/<rule|learned>/seedS`` and its
evaluations in ``DIR/seedS.json``; a later invocation with the same settings reads those
seeds back instead of training them, so the seeds of a long benchmark can be trained in
different sessions (``--seeds 0 1`` now, ``--seeds 0 1 2`` later).

Writes ``benchmarks/results/learned-her-<env>.{json,md,png}`` and adds
``learned_her_seen`` and ``rule_her_seen`` to the ``headline`` of
``benchmarks/results/captioner-<env>.json``; target: rule minus learned success, seen and
held-out combinations pooled over the seeds, at most 0.05 (lang2d) or 0.08 (robosuite).
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import (
    LCRL,
    RESULTS_DIR,
    child_env,
    command,
    curve,
    die_with_parent,
    evaluate,
    keep_to_act,
    machine,
    save_figure,
    save_json,
    save_markdown,
)

#: Rule minus learned success, seen and held-out combinations, pooled over the seeds.
TARGET_GAP = {"lang2d": 0.05, "robosuite": 0.08}
#: The evaluation seed of the final figures: no choice used it (the runs' periodic
#: evaluations, at the training seed, are the validation ones).
TEST_SEED = 1000
PRESETS = {"robosuite": "robosuite-image-reach", "lang2d": "lang2d"}


def run_args(args: argparse.Namespace, name: str) -> list[str]:
    cmd = [*LCRL, "train", PRESETS[args.env], "--out", str(Path(args.work) / name)]
    cmd += ["--total-steps", str(args.steps), "--eval-every", str(args.eval_every)]
    cmd += ["--eval-episodes", str(args.eval_episodes), "--seed", str(args.seed)]
    cmd += ["--overwrite", "--no-progress"]
    if getattr(args, "families", None):
        cmd += ["--env.families", *args.families]
    if getattr(args, "max_episode_steps", 0):
        cmd += ["--env.max-episode-steps", str(args.max_episode_steps)]
    if args.perception:
        cmd += ["--env.perception", args.perception]
    if args.target_clip:
        cmd += ["--sac.target-clip", str(args.target_clip)]
    if getattr(args, "extra", ""):
        cmd += shlex.split(args.extra)
    if name == "learned":
        labels = getattr(args, "labels", "learned")
        cmd += ["--relabel.captioner", labels, "--relabel.reward", "learned"]
        cmd += ["--relabel.checkpoint", args.captioner.format(seed=args.seed)]
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
    from train.commands.cli import parse_train_args

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
    parser.add_argument(
        "--captioner",
        required=True,
        help="lcrl caption train --out; {seed} in it is the seed of each pair of runs, so "
        "each training seed has a captioner of its own",
    )
    parser.add_argument("--perception", default="", help="the policy's (robosuite)")
    parser.add_argument("--work", default="")
    parser.add_argument(
        "--families",
        nargs="+",
        default=[],
        help="instruction families of both runs (--env.families; default the preset's: "
        "robosuite-image-reach reach alone, lang2d reach and push)",
    )
    parser.add_argument(
        "--max-episode-steps",
        type=int,
        default=0,
        help="--env.max-episode-steps of both runs (0: the preset's)",
    )
    parser.add_argument(
        "--extra",
        default="",
        help='more lcrl train options for both runs, e.g. "--finetune.demos FILE '
        '--sac.demo-bc 1.0" (scripted demonstrations in the replay buffer from the start)',
    )
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--eval-every", type=int, default=5_000)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--final-episodes", type=int, default=100)
    parser.add_argument(
        "--push-episodes",
        type=int,
        default=60,
        help="lang2d: push episodes per run whose failures are sorted by how far the object "
        "got (benchmarks/push_misses.py; 0: none)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--eval-seed",
        type=int,
        default=TEST_SEED,
        help="evaluation seed of the final figures (a test seed: choose on the runs' "
        "periodic evaluations instead)",
    )
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
        "--labels",
        choices=("learned", "reward", "both"),
        default="learned",
        help="the learned run's relabelling candidates (--relabel.captioner): the learned "
        "captioner's captions, every training instruction the reward model judges achieved, "
        "or both together",
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
        nargs="+",
        default=[],
        metavar="RUN",
        help="finished runs of the same preset, budget and perception, one per seed (e.g. "
        "the image_policy.py reach run), to take as the rule runs instead of training them",
    )
    parser.add_argument(
        "--rule-from",
        default="",
        metavar="DIR",
        help="the rule runs of an earlier invocation's --keep DIR, trained by this "
        "invocation's rule command: each seed's kept rule policy (DIR/rule/seedS) is "
        "evaluated again at --eval-seed, its curve and seconds read from DIR/seedS.json; "
        "only the learned runs train",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[],
        help="several seeds, one pair of runs each under WORK/seedS, one pair at a time; the "
        "headline pools their evaluations (default: --seed alone, runs under WORK)",
    )
    parser.add_argument(
        "--note",
        default="",
        help="what changed since the file's earlier figures and why (into the JSON's note "
        "and the Markdown)",
    )
    parser.add_argument(
        "--tried",
        nargs="+",
        default=[],
        metavar="TEXT",
        help="variants screened before this command (each a sentence: what, on which seeds, "
        "what it gave), listed in the JSON's tried",
    )
    parser.add_argument(
        "--validation-only",
        action="store_true",
        help="train the runs and report their last periodic evaluations (at the training "
        "seed: the validation figures variants are chosen on) in WORK/validation.json; no "
        "evaluation at --eval-seed",
    )
    parser.add_argument(
        "--keep",
        default="",
        metavar="DIR",
        help="keep every evaluated run to act in DIR/<rule|learned>/seedS (weights and "
        "configs, no critics or replay), named in the JSON under kept, and each seed's "
        "evaluations in DIR/seedS.json: a later invocation reads those seeds back",
    )
    args = parser.parse_args(argv)
    if args.env == "robosuite" and not args.perception:
        parser.error("--env robosuite trains the image policy: pass --perception MODEL")
    args.work = args.work or f"runs/bench/learned-her-{args.env}"
    seeds = list(dict.fromkeys(args.seeds or [args.seed]))
    if args.reuse_rule and len(args.reuse_rule) != len(seeds):
        parser.error(f"--reuse-rule takes one run per seed ({len(seeds)}: {seeds})")
    if args.rule_from and args.reuse_rule:
        parser.error("--rule-from and --reuse-rule both name the rule runs: give one")
    per_seed = [seed_args(args, s, multi=len(seeds) > 1) for s in seeds]
    for ns in per_seed if args.rule_from and not args.commands else ():
        ns.rule_record = rule_record(args.rule_from, ns)

    if args.commands:
        for ns in per_seed:
            for name in ("rule", "learned"):
                print(" ".join(run_args(ns, name)))
        return 0
    info = machine()
    seconds: dict[str, dict[str, float]] = {}
    sets = ("train", "heldout", "paraphrase")
    runs = ("rule", "learned")
    records = {str(ns.seed): read_record(args.keep, ns) for ns in per_seed}
    fresh = [ns for ns in per_seed if records[str(ns.seed)] is None]
    for i, ns in enumerate(per_seed):
        if records[str(ns.seed)] is None:
            reused = args.reuse_rule[i] if args.reuse_rule else ""
            seconds[str(ns.seed)] = train_pair(ns, reused)
    if args.validation_only:
        report_validation(args, fresh, runs, sets)
        return 0
    final = evaluate_pairs(fresh, runs, sets, args.final_episodes, args.eval_seed)
    kept = keep_runs(args.keep, fresh, runs) if args.keep else {}
    curves = {str(ns.seed): {n: run_curve(ns, n) for n in runs} for ns in fresh}
    agreement = {str(ns.seed): last_agreement(Path(ns.work) / "learned") for ns in fresh}
    for ns in fresh if args.keep else ():
        s = str(ns.seed)
        write_record(args.keep, ns, final[s], curves[s], seconds[s], agreement[s], kept[s])
    for s, record in records.items():  # seeds trained and evaluated by an earlier invocation
        if record is not None:
            final[s], curves[s], seconds[s] = record["final"], record["curves"], record["seconds"]
            agreement[s], kept[s] = record["agreement"], record["kept"]
    order = [str(ns.seed) for ns in per_seed]
    final, curves, seconds, agreement = (
        {s: d[s] for s in order} for d in (final, curves, seconds, agreement)
    )
    kept = {s: kept[s] for s in order if s in kept}
    misses = push_failures(fresh, runs, args.push_episodes) if args.env == "lang2d" else {}
    pooled = {n: {k: pool([final[s][n][k] for s in final]) for k in sets} for n in runs}
    gaps = [final[s]["rule"]["train"]["success"] - final[s]["learned"]["train"]["success"]
            for s in final]  # fmt: skip
    target = TARGET_GAP[args.env]
    headline = {
        "gap_seen": round(
            pooled["rule"]["train"]["success"] - pooled["learned"]["train"]["success"], 3
        ),
        "gap_heldout": round(
            pooled["rule"]["heldout"]["success"] - pooled["learned"]["heldout"]["success"], 3
        ),
        "learned_her_seen": round(pooled["learned"]["train"]["success"], 3),
        "rule_her_seen": round(pooled["rule"]["train"]["success"], 3),
        "gap": round(sum(gaps) / len(gaps), 3),
        "learned_her_heldout": round(pooled["learned"]["heldout"]["success"], 3),
        "rule_her_heldout": round(pooled["rule"]["heldout"]["success"], 3),
        "steps": args.steps,
        "seeds": len(seeds),
        "eval_seed": args.eval_seed,
    }
    if len(seeds) > 1:
        headline["gap_interval"] = [round(x, 3) for x in mean_interval(gaps)]
    reached = {
        "gap_seen": headline["gap_seen"] <= target,
        "gap_heldout": headline["gap_heldout"] <= target,
    }
    name = f"learned-her-{args.env}"
    old = RESULTS_DIR / f"{name}.json"
    previous = {}
    if old.is_file():  # the figures this run replaces, kept beside it
        before = json.loads(old.read_text())
        previous = {k: before.get(k) for k in ("headline", "command", "git", "date")}
    save_json(
        name,
        {
            "headline": headline,
            "target": f"gap_seen <= {target} and gap_heldout <= {target} (rule minus learned, "
            f"pooled over the seeds, at evaluation seed {args.eval_seed})",
            "previous": previous,
            **({"kept": kept} if kept else {}),
            **({"note": args.note} if args.note else {}),
            **({"tried": args.tried} if args.tried else {}),
            "reached": reached,
            "machine": info,
            "settings": {**vars(args), "preset": PRESETS[args.env]},
            "seconds": seconds,
            "gaps": {s: round(g, 3) for s, g in zip(final, gaps, strict=True)},
            "agreement_with_rule_last_rows": agreement,
            "pooled": pooled,
            "final": {
                s: {
                    n: {
                        k: {"success": v["success"], "ci": v["ci"], **by_family(v)}
                        for k, v in r.items()
                    }
                    for n, r in runs_of_seed.items()
                }
                for s, runs_of_seed in final.items()
            },
            "curve_gaps": curve_gaps(curves),
            "push_failures": misses,
            "curves": curves,
        },
    )
    captioner_file = RESULTS_DIR / f"captioner-{args.env}.json"
    if captioner_file.exists():  # the captioner's results carry the relabelling figures too
        doc = json.loads(captioner_file.read_text())
        doc.setdefault("headline", {}).update(
            learned_her_seen=headline["learned_her_seen"], rule_her_seen=headline["rule_her_seen"]
        )
        doc.setdefault("reached", {}).pop("learned_her_within_10_points", None)
        doc["reached"]["learned_her_gaps"] = reached["gap_seen"] and reached["gap_heldout"]
        doc["learned_her"] = {"command": command(), "file": f"{name}.json"}
        captioner_file.write_text(json.dumps(doc, indent=1))
        update_captioner_markdown(captioner_file.with_suffix(".md"), headline)

    seed_word = "seed" if len(seeds) == 1 else "seeds"
    # the families the runs train on (robosuite-image-reach: reach alone, unless --families)
    trained = {f for n in runs for f in pooled[n]["train"]["families"]}
    fams = [f for f in ("reach", "push", "lift") if f in trained]
    lines = [
        f"{seed_word.capitalize()} {', '.join(map(str, seeds))}; `lcrl eval` with "
        f"{args.final_episodes} episodes per set and seed at evaluation seed "
        f"{args.eval_seed}, which no choice used; figures pooled over the seeds "
        "(95% Wilson intervals).",
        "",
        f"The learned run: `--relabel.captioner {args.labels} --relabel.reward learned "
        f"--relabel.checkpoint {args.captioner}` with reward threshold {args.threshold}"
        + (f", per family {' '.join(args.family_thresholds)}" if args.family_thresholds else "")
        + (
            ", a caption kept only where the reward model agrees (`--relabel.confirm`)"
            if args.confirm
            else ""
        )
        + "; the rule captioner judges the evaluations only.",
        *(["", args.note] if args.note else []),
        "",
        f"| relabelling | seen | {' | '.join(fams)} | held-out combinations | paraphrases |",
        "|---|---:|" + "---:|" * len(fams) + "---:|---:|",
    ]
    for n in runs:
        cells = [fmt(pooled[n]["train"])]
        cells += [fmt(pooled[n]["train"]["families"].get(f, {})) for f in fams]
        cells += [fmt(pooled[n][k]) for k in ("heldout", "paraphrase")]
        lines.append(f"| {n} | {' | '.join(cells)} |")
    lines += [
        "",
        f"Per seed, seen success ({' / '.join(fams)}) and training seconds:",
        "",
        "| seed | rule | learned | gap |",
        "|---|---:|---:|---:|",
    ]
    for s, gap in zip(final, gaps, strict=True):
        cells = []
        for n in runs:
            fam = by_family(final[s][n]["train"])["families"]
            per = " / ".join(f"{fam.get(f, float('nan')):.2f}" for f in fams)
            cells.append(
                f"{final[s][n]['train']['success']:.2f} ({per}), "
                f"{seconds[s].get(n, float('nan')):.0f} s"
            )
        lines.append(f"| {s} | {' | '.join(cells)} | {gap:+.2f} |")
    first = next(iter(curves.values()))
    lines += [
        "",
        f"Learning curves (seen instructions, {args.eval_episodes} episodes per point at the "
        "training seed: the validation evaluations), mean over seeds:",
        "",
        "| run | " + " | ".join(str(int(r["step"])) for r in first["rule"]) + " |",
        "|---|" + "---:|" * len(first["rule"]),
        *(f"| {n} | " + " | ".join(f"{v:.2f}" for v in mean_curve(curves, n)) + " |" for n in runs),
        "| gap | " + " | ".join(f"{g['gap']:+.2f}" for g in curve_gaps(curves)) + " |",
        *(
            f"| {n} push | "
            + " | ".join(f"{v:.2f}" for v in mean_curve(curves, n, "train/push"))
            + " |"
            for n in runs
            if "push" in fams
        ),
        "",
        *push_failure_lines(misses),
        "Agreement of the learned run's labels and rewards with the rule captioner (mean of "
        "the last progress rows, mean over seeds): "
        + ", ".join(f"{k} {v:.2f}" for k, v in mean_dicts(list(agreement.values())).items()),
        "",
        f"Targets: rule minus learned at most {target:.2f}, pooled over the seeds. Seen "
        f"instructions {headline['gap_seen']:+.3f}: "
        f"{'reached' if reached['gap_seen'] else 'NOT reached'}; held-out combinations "
        f"{headline['gap_heldout']:+.3f}: "
        f"{'reached' if reached['gap_heldout'] else 'NOT reached'}. Mean of the seeds' "
        f"seen gaps {headline['gap']:+.2f}"
        + (
            f", 95% interval over seeds [{headline['gap_interval'][0]:+.2f}, "
            f"{headline['gap_interval'][1]:+.2f}]"
            if "gap_interval" in headline
            else ""
        )
        + ".",
    ]
    title = f"Learned relabelling over perception vs the rule captioner ({args.env})"
    save_markdown(name, title, "\n".join(lines), info)

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for k, n in enumerate(runs):
        colour = f"C{k}"
        for by_run in curves.values():
            rows = by_run[n]
            ax.plot([r["step"] for r in rows], [r["train/success"] for r in rows], "-",
                    color=colour, alpha=0.3, lw=1)  # fmt: skip
        steps = [r["step"] for r in first[n]]
        ax.plot(steps, mean_curve(curves, n), "o-", color=colour, label=f"{n} (mean)")
    ax.set(xlabel="environment steps", ylabel="success (seen instructions)", ylim=(0, 1.02))
    ax.set_title(f"{PRESETS[args.env]}: relabelled by rule or learned models,\n{seed_word} "
                 f"{', '.join(map(str, seeds))}", fontsize="medium")  # fmt: skip
    ax.legend()
    save_figure(name, fig, info)
    print(json.dumps(headline, indent=1))
    return 0


def evaluate_pairs(
    per_seed: list[argparse.Namespace],
    runs: tuple[str, ...],
    sets: tuple[str, ...],
    episodes: int,
    seed: int,
) -> dict[str, dict[str, dict]]:
    """``lcrl eval`` of every seed's runs at evaluation ``seed``, two at a time (one torch
    thread each): per seed, per run, per set. An evaluation already written after the run
    finished, of the same sets and episodes (``lcrl eval RUN --episodes N --seed S --json
    RUN/eval-seedS.json``, started by hand while other runs trained), is read back."""
    from concurrent.futures import ThreadPoolExecutor

    def one(run: Path) -> dict:
        done, report = run / f"eval-seed{seed}.json", run / "report.md"
        if (
            seed
            and done.is_file()
            and (not report.is_file() or done.stat().st_mtime > report.stat().st_mtime)
        ):
            got = json.loads(done.read_text())["sets"]
            if set(got) == set(sets) and all(got[k]["episodes"] == episodes for k in sets):
                return got
        return evaluate(run, episodes, sets, seed)

    with ThreadPoolExecutor(max_workers=2) as pool_:
        jobs = {
            (str(ns.seed), n): pool_.submit(one, run_path(ns, n)) for ns in per_seed for n in runs
        }
        return {str(ns.seed): {n: jobs[str(ns.seed), n].result() for n in runs} for ns in per_seed}


def record_commands(ns: argparse.Namespace) -> dict[str, list[str]]:
    """The two lcrl train commands of a seed, without where they were written (``--out``)."""
    out = {}
    for name in ("rule", "learned"):
        cmd = run_args(ns, name)
        at = cmd.index("--out")
        out[name] = cmd[cmd.index("train") : at] + cmd[at + 2 :]
    return out


def read_record(folder: str, ns: argparse.Namespace) -> dict | None:
    """The evaluations of a seed's pair of runs that an earlier invocation kept in
    ``folder/seedS.json`` (:func:`write_record`), when they were trained by the same
    commands; None otherwise (the seed is trained and evaluated now)."""
    path = Path(folder, f"seed{ns.seed}.json") if folder else None
    if path is None or not path.is_file():
        return None
    record = json.loads(path.read_text())
    wanted = {"commands": record_commands(ns), "eval_seed": ns.eval_seed}
    wanted["final_episodes"] = ns.final_episodes
    alike = {k: record.get(k) for k in wanted} == wanted
    if (
        not alike
        and getattr(ns, "rule_record", None) is not None
        and path.resolve() == Path(ns.rule_from, f"seed{ns.seed}.json").resolve()
    ):
        return None  # the rule runs' source, which this invocation's record replaces
    if not alike:
        raise SystemExit(
            f"{path}: kept by runs of other settings; remove it to train seed {ns.seed} again"
        )
    print(f"seed {ns.seed}: evaluations read from {path}")
    return record


def rule_record(folder: str, ns: argparse.Namespace) -> dict:
    """The record of a seed's kept runs in ``folder`` (``--rule-from``) whose rule run
    this invocation's rule command trained.

    Raises:
        SystemExit: no such record or policy, or one of another rule command.
    """
    path = Path(folder, f"seed{ns.seed}.json")
    if not path.is_file() or not Path(folder, "rule", f"seed{ns.seed}").is_dir():
        raise SystemExit(f"--rule-from {folder}: no kept rule run of seed {ns.seed} there")
    record = json.loads(path.read_text())
    if record.get("commands", {}).get("rule") != record_commands(ns)["rule"]:
        raise SystemExit(f"{path}: its rule run was trained by another command than this one's")
    return record


def kept_rule(ns: argparse.Namespace) -> Path:
    """The kept rule policy of ``--rule-from`` for a seed."""
    return Path(ns.rule_from, "rule", f"seed{ns.seed}")


def run_path(ns: argparse.Namespace, name: str) -> Path:
    """Where a seed's ``name`` run is: its folder in WORK. With ``--rule-from`` the rule
    run's folder is a copy of the kept policy, made here (an evaluation writes beside the
    policy, and the kept folder's files are sealed by their checksums)."""
    path = Path(ns.work) / name
    if name == "rule" and getattr(ns, "rule_record", None) is not None and not path.exists():
        import shutil

        shutil.copytree(kept_rule(ns), path)
    return path


def run_curve(ns: argparse.Namespace, name: str) -> list[dict]:
    """A seed's ``name`` run's periodic evaluations (those ``--rule-from`` recorded for a
    kept rule run)."""
    if name == "rule" and getattr(ns, "rule_record", None) is not None:
        return ns.rule_record["curves"]["rule"]
    return curve(Path(ns.work) / name)


def write_record(
    folder: str,
    ns: argparse.Namespace,
    final: dict,
    curves: dict,
    seconds: dict,
    agreement: dict,
    kept: dict,
) -> None:
    """Keep a seed's evaluations beside its kept policies (``folder/seedS.json``), so that
    a later invocation with more seeds pools them without training them again: a benchmark
    of several seeds spans sessions."""
    record = {
        "commands": record_commands(ns),
        "eval_seed": ns.eval_seed,
        "final_episodes": ns.final_episodes,
        # every figure of the evaluations but the episode-by-episode rows
        "final": {
            run: {
                k: {x: y for x, y in res.items() if x != "episode_results"}
                for k, res in sets.items()
            }
            for run, sets in final.items()
        },
        "curves": curves,
        "seconds": seconds,
        "agreement": agreement,
        "kept": kept,
    }
    Path(folder).mkdir(parents=True, exist_ok=True)
    Path(folder, f"seed{ns.seed}.json").write_text(json.dumps(record, indent=1))


def keep_runs(
    folder: str, per_seed: list[argparse.Namespace], runs: tuple[str, ...]
) -> dict[str, dict[str, str]]:
    """Keep each seed's runs to act in ``folder/<run>/seedS`` (:func:`keep_to_act`, no
    critics); returns the folders, per seed and run."""
    import shutil

    kept: dict[str, dict[str, str]] = {}
    for ns in per_seed:
        kept[str(ns.seed)] = {}
        for n in runs:
            run, dest = run_path(ns, n), Path(folder) / n / f"seed{ns.seed}"
            if n == "rule" and getattr(ns, "rule_record", None) is not None:  # --rule-from
                if kept_rule(ns).resolve() != dest.resolve():
                    shutil.rmtree(dest, ignore_errors=True)
                    shutil.copytree(kept_rule(ns), dest)
                kept[str(ns.seed)][n] = str(dest)
            else:
                kept[str(ns.seed)][n] = keep_to_act(run, dest)
    return kept


def report_validation(
    args: argparse.Namespace, per_seed: list, runs: tuple[str, ...], sets: tuple[str, ...]
) -> dict:
    """The runs' last periodic evaluations (validation: the training seed's episodes),
    per seed and as the mean over seeds; written to ``WORK/validation.json``."""
    last = {str(ns.seed): {n: run_curve(ns, n)[-1] for n in runs} for ns in per_seed}
    mean = {
        n: {k: sum(r[n][f"{k}/success"] for r in last.values()) / len(last) for k in sets}
        for n in runs
    }
    doc = {"settings": vars(args), "last_evaluation": last, "mean": mean}
    Path(args.work, "validation.json").write_text(json.dumps(doc, indent=1))
    for n in runs:
        print(f"validation {n}: " + ", ".join(f"{k} {v:.3f}" for k, v in mean[n].items()))
    return doc


def seed_args(args: argparse.Namespace, seed: int, multi: bool) -> argparse.Namespace:
    """The settings of one seed's pair of runs (under ``WORK/seedS`` with several seeds)."""
    ns = argparse.Namespace(**vars(args))
    ns.seed = seed
    if multi:
        ns.work = str(Path(args.work) / f"seed{seed}")
    return ns


def train_pair(args: argparse.Namespace, reuse_rule: str) -> dict[str, float]:
    """Train (or take) one seed's rule and learned runs side by side; their seconds."""
    Path(args.work).mkdir(parents=True, exist_ok=True)
    procs, seconds = {}, {}
    names: tuple[str, ...] = ("rule", "learned")
    if reuse_rule:
        seconds["rule"] = reuse(Path(reuse_rule), Path(args.work) / "rule", args)
        names = ("learned",)
    if getattr(args, "rule_record", None) is not None:
        seconds["rule"] = args.rule_record["seconds"]["rule"]
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
    return seconds


def last_agreement(run: Path, last: int = 5) -> dict[str, float]:
    """Mean of the last ``last`` progress rows' agreement columns (``labels_push_precision``,
    ...: over all instructions, then per family)."""
    with open(run / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    out = {}
    for key in rows[0] if rows else {}:
        if not (
            key.startswith(("labels_", "rewards_")) and key.endswith(("_precision", "_recall"))
        ):
            continue
        values = [float(r[key]) for r in rows[-last:] if r.get(key) not in (None, "", "nan")]
        if values:
            out[key] = round(sum(values) / len(values), 3)
    return out


def by_family(result: dict) -> dict:
    """A set's success per family (``{"families": {"push": 0.4, ...}}``)."""
    fams = result.get("families") or {}
    return {"families": {f: round(v["success"], 3) for f, v in fams.items()}}


def pool(results: list[dict]) -> dict:
    """Sets of several seeds' evaluations as one: successes over episodes with a 95% Wilson
    interval, overall and per family."""
    from train.evaluation.eval_suite import wilson_interval

    def one(rows: list[dict]) -> dict:
        n = sum(int(r["episodes"]) for r in rows)
        k = sum(int(r["successes"]) for r in rows)
        low, high = wilson_interval(k, n) if n else (float("nan"), float("nan"))
        return {"success": k / n if n else float("nan"), "ci": [low, high], "episodes": n}

    out = one(results)
    families = sorted({f for r in results for f in (r.get("families") or {})})
    out["families"] = {
        f: one([r["families"][f] for r in results if f in (r.get("families") or {})])
        for f in families
    }
    return out


def fmt(result: dict) -> str:
    if not result:
        return "-"
    low, high = result["ci"]
    return f"{result['success']:.2f} [{low:.2f}, {high:.2f}]"


def mean_interval(values: list[float]) -> tuple[float, float]:
    """95% Student-t interval of the mean of ``values`` (over seeds)."""
    import numpy as np

    v = np.asarray(values, float)
    t = {2: 12.706, 3: 4.303, 4: 3.182, 5: 2.776, 6: 2.571, 7: 2.447, 8: 2.365, 9: 2.306}
    half = t.get(len(v), 1.96) * v.std(ddof=1) / np.sqrt(len(v))
    return float(v.mean() - half), float(v.mean() + half)


def push_failures(per_seed: list, runs: tuple[str, ...], episodes: int) -> dict:
    """How each run's failed push episodes fail (:mod:`benchmarks.push_misses`), per run
    over all seeds (``episodes`` per seed and run)."""
    if episodes <= 0:
        return {}
    from benchmarks.push_misses import run_pushes, summarise

    out = {}
    for n in runs:
        eps = [e for ns in per_seed for e in run_pushes(Path(ns.work) / n, episodes)]
        out[n] = {k: round(v, 3) if isinstance(v, float) else v for k, v in summarise(eps).items()}
    return out


def push_failure_lines(misses: dict) -> list[str]:
    """The Markdown table of :func:`push_failures` (nothing without it)."""
    if not misses:
        return []
    lines = [
        "How the failed push episodes fail (seen push instructions, deterministic policy, "
        "`benchmarks/push_misses.py`; fractions of the failures): the object never moved "
        "(untouched), moved less than the push distance (short), or far enough but off its "
        "direction (drift); the pusher came within reach distance of it (reached):",
        "",
        "| run | push episodes | success | untouched | short | drift | reached |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for n, m in misses.items():
        cells = [m["episodes"], *(f"{m[k]:.2f}" for k in BINS_SHOWN)]
        lines.append(f"| {n} | " + " | ".join(str(c) for c in cells) + " |")
    return [*lines, ""]


BINS_SHOWN = ("success", "untouched", "short", "drift", "reached")


def mean_curve(curves: dict, name: str, key: str = "train/success") -> list[float]:
    """Seen success (or another ``key`` of the curve rows) at each evaluation point, mean
    over seeds (the points all seeds have)."""
    rows = [by_run[name] for by_run in curves.values()]
    n = min(len(r) for r in rows)
    return [sum(r[i].get(key, float("nan")) for r in rows) / len(rows) for i in range(n)]


def curve_gaps(curves: dict) -> list[dict[str, float]]:
    """At each evaluation point all runs have: the step, the mean over seeds of the rule
    and learned runs' seen success and of push's, and the gap (rule - learned)."""
    rule, learned = mean_curve(curves, "rule"), mean_curve(curves, "learned")
    push = {n: mean_curve(curves, n, "train/push") for n in ("rule", "learned")}
    steps = [r["step"] for r in next(iter(curves.values()))["rule"]]
    return [
        {
            "step": int(steps[i]),
            "rule": round(rule[i], 3),
            "learned": round(learned[i], 3),
            "gap": round(rule[i] - learned[i], 3),
            "rule_push": round(push["rule"][i], 3),
            "learned_push": round(push["learned"][i], 3),
        }
        for i in range(min(len(rule), len(learned)))
    ]


def mean_dicts(dicts: list[dict[str, float]]) -> dict[str, float]:
    keys = [k for k in dicts[0]] if dicts else []
    return {k: sum(d[k] for d in dicts if k in d) / sum(k in d for d in dicts) for k in keys}


if __name__ == "__main__":
    sys.exit(main())

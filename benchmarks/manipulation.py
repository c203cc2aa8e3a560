"""Robosuite manipulation beyond reach: push, lift, put and stack learned with language HER.

Run from the repository root::

    python benchmarks/manipulation.py                  # train robosuite-manip to 300k, evaluate
    python benchmarks/manipulation.py --steps 60000    # train up to 60k steps now, evaluate
    python benchmarks/manipulation.py --eval-only      # evaluate the run as it stands
    python benchmarks/manipulation.py --work runs/bench/robosuite-manip-demos \
        --demos data/demos-robosuite-manip.h5 --extra "--sac.demo-bc 1.0"

The last starts from scripted demonstrations of all five families (``lcrl demos record
--preset robosuite-manip --episodes 2000 --out data/demos-robosuite-manip.h5``): the
actor is cloned from them and the critic pretrained on them before the first episode, and
they stay in the replay buffer with a Q-filtered BC loss on them.

The run (``lcrl train robosuite-manip``, privileged state: all five families in one policy,
starts handed over by the scripted controller, chains of instructions, a curriculum over
families; see docs/training.md) lives in ``--work``. When that folder has a checkpoint the
run goes on from it with ``--resume``: a run spans sessions, and its checkpoints keep the
replay buffer. Then its latest checkpoint is evaluated:

- per family, ``--episodes`` episodes of each instruction set (seen, held-out
  combinations, paraphrases): ``lcrl eval RUN --families F``;
- two instructions in a row (``lcrl eval RUN --chain 2``): ``chain2`` is the fraction of
  chains whose first two instructions both succeed;
- the scripted controllers on the same number of episodes per family, with the same
  100-step limit (``captioner.scripted3d.evaluate``);
- one ``lcrl act`` GIF per family (``--gifs``);
- with ``--chain-run RUN``: ``chain2`` and every family's figures of that run too: one
  policy over all five families that another route gave (a student of ``lcrl distill
  --state``, which merges per-family teachers over chains); the one RL policy's chain
  figure stays beside as ``chain2_rl_policy``;
- with ``--routed-run FOLDER`` (written by ``lcrl route``: each instruction acted by its
  family's expert): ``chain2`` and every family's figures of that policy; a distilled
  student's chain figure stays beside as ``chain2_distilled``, and the routed policy's
  budget is the sum over the runs it is made of.

Writes ``benchmarks/results/robosuite-manipulation-rl.{json,md,png}``. Headline: seen
success per family (``reach`` ... ``stack``, targets 0.90, 0.80, 0.70, 0.50, 0.30),
``chain2`` (target 0.60), ``steps``, ``updates`` and ``wall_clock_s`` (training seconds of
the whole run on this machine, over all its sessions).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import subprocess
from pathlib import Path
from typing import Any

from benchmarks.common import (
    LCRL,
    RESULTS_DIR,
    curve,
    die_with_parent,
    machine,
    save_figure,
    save_json,
    save_markdown,
    side_by_side_env,
)
from train.configs.presets import MANIPULATION_FAMILIES

NAME = "robosuite-manipulation-rl"
PRESET = "robosuite-manip"
SETS = ("train", "heldout", "paraphrase")
#: Seen-instruction success per family, and two instructions in a row.
TARGETS = {"reach": 0.90, "push": 0.80, "lift": 0.70, "put": 0.50, "stack": 0.30, "chain2": 0.60}
#: The episode limit of the preset, also given to the scripted controllers.
MAX_STEPS = 100


def has_checkpoint(work: Path) -> bool:
    return any((work / "checkpoints").glob("step_*"))


def routed_meta(folder: Path) -> dict[str, Any] | None:
    """The ``meta.json`` of a folder written by ``lcrl route`` (None for anything else)."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and "router" in meta else None


def child_env(args: argparse.Namespace) -> dict[str, str]:
    """The environment of a child lcrl process: its share of the cores, offscreen MuJoCo."""
    return side_by_side_env(args.processes, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))


def train(args: argparse.Namespace) -> None:
    """Train (or go on training) the run up to ``--steps``."""
    work = Path(args.work)
    cmd = [*LCRL, "train", args.preset, "--out", str(work), "--total-steps", str(args.steps)]
    if has_checkpoint(work):
        cmd += ["--resume"]  # the run's own settings, its demonstrations included
    else:
        if args.demos:
            cmd += ["--finetune.demos", args.demos]
        cmd += shlex.split(args.extra)
    cmd += ["--no-progress"]
    print("== " + shlex.join(cmd), flush=True)
    env = child_env(args)
    subprocess.run(cmd, check=True, env=env, preexec_fn=die_with_parent)


def latest_step(work: Path) -> int | None:
    """The step of the run's latest checkpoint (``latest.json``; a routed folder: its
    base's step), or None."""
    routed = routed_meta(work)
    if routed is not None:
        return int(routed.get("step", 0))
    try:
        name = json.loads((work / "latest.json").read_text())["checkpoint"]
        return int(Path(name).name.removeprefix("step_"))
    except (OSError, ValueError, KeyError):
        return None


def lcrl_eval(
    args: argparse.Namespace, out: Path, *options: str, work: str | None = None
) -> dict[str, Any] | None:
    """``lcrl eval`` of the run with ``options``; its JSON document (None when it fails,
    e.g. a set without an instruction of the family). A document already at ``out`` for
    the run's latest checkpoint is kept, so an evaluation cut short (the machine shut
    down) goes on with the families it had not finished."""
    if out.is_file():
        try:
            doc = json.loads(out.read_text())
        except ValueError:
            doc = {}
        step = latest_step(Path(work or args.work))
        if step is not None and doc.get("step") == step:
            print(f"== keeping {out} (step {step})", flush=True)
            return doc
    cmd = [*LCRL, "eval", work or args.work, "--episodes", str(args.episodes), "--num-envs", "1"]
    cmd += [*options, "--no-progress", "--json", str(out)]
    print("== " + shlex.join(cmd), flush=True)
    env = child_env(args)
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, preexec_fn=die_with_parent)
    if done.returncode != 0:
        print(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed")
        return None
    return json.loads(out.read_text())


def evaluate_family(args: argparse.Namespace, work: str, family: str) -> dict[str, Any]:
    """One family's success per set (with its interval) for the run at ``work``."""
    folder = Path(work) / "evals" / "manipulation"
    folder.mkdir(parents=True, exist_ok=True)
    # one process for the three sets; set by set when one has no instruction of it
    options = ("--families", family, "--sets")
    doc = lcrl_eval(args, folder / f"{family}.json", *options, *SETS, work=work)
    docs = {name: doc for name in SETS}
    if doc is None:
        docs = {
            name: lcrl_eval(args, folder / f"{family}-{name}.json", *options, name, work=work)
            for name in SETS
        }
    per_set: dict[str, Any] = {}
    for name, d in docs.items():
        s = d["sets"][name] if d else None
        per_set[name] = None if s is None else {k: s[k] for k in ("success", "ci", "episodes")}
    return per_set


def evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """Per family and set: success with its interval, from the family's own run where
    ``--family-runs`` names one (the one policy's figures then kept beside); the chain
    figures of the one policy."""
    out: dict[str, Any] = {
        "families": {},
        "one_policy": {},
        "runs": {},
        "chain": None,
        "chain_run": {},
        "rl_chain": None,
        "routed": {},
        "distilled_chain": None,
    }
    for family in args.families:
        out["one_policy"][family] = evaluate_family(args, args.work, family)
        own = args.family_runs.get(family)
        out["families"][family] = (
            out["one_policy"][family] if own is None else evaluate_family(args, own, family)
        )
        out["runs"][family] = own or args.work
    out["step"] = latest_step(Path(args.work))
    folder = Path(args.work) / "evals" / "manipulation"
    doc = lcrl_eval(args, folder / "chain2.json", "--chain", "2", "--sets", "train")
    if doc is not None:
        out["chain"] = doc["sets"]["train"].get("chain")
    if getattr(args, "chain_run", ""):
        out["rl_chain"] = out["chain"]
        out["chain_run"], out["chain"] = evaluate_policy(args, args.chain_run)
    if getattr(args, "routed_run", ""):
        if getattr(args, "chain_run", ""):
            out["distilled_chain"] = out["chain"]
        else:
            out["rl_chain"] = out["chain"]
        out["routed"], out["chain"] = evaluate_policy(args, args.routed_run)
    return out


def evaluate_policy(args: argparse.Namespace, work: str) -> tuple[dict[str, Any], Any]:
    """Every family's figures and the two-instruction chain figure of the policy at
    ``work`` (a run, or a folder of ``lcrl route``)."""
    families = {family: evaluate_family(args, work, family) for family in args.families}
    folder = Path(work) / "evals" / "manipulation"
    folder.mkdir(parents=True, exist_ok=True)
    doc = lcrl_eval(args, folder / "chain2.json", "--chain", "2", "--sets", "train", work=work)
    return families, None if doc is None else doc["sets"]["train"].get("chain")


def is_distilled(run: Path) -> bool:
    """Whether ``run`` is a student of ``lcrl distill`` (its config names a teacher)."""
    try:
        cfg = json.loads((run / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return bool((cfg.get("distill") or {}).get("teacher")) and (run / "progress.csv").is_file()


def routed_budget(folder: Path) -> dict[str, Any]:
    """The runs a routed policy is made of (base and experts, from its ``meta.json``) with
    each one's budget, and their sum: the cost of the routed policy. A distilled run
    counts the states its DAgger rounds visited and its seconds (its teachers' own
    training not counted)."""
    meta = routed_meta(folder) or {}
    router = meta.get("router", {})
    sources = {"base": router.get("base", ""), **router.get("sources", {})}
    runs: dict[str, Any] = {}
    for who, ckpt in sources.items():
        run = Path(ckpt).parent.parent  # RUN/checkpoints/step_N
        spent: dict[str, Any] = {}
        if is_distilled(run):  # DAgger rounds: the states it visited, its seconds
            student = distilled(run)
            spent = {
                "steps": student.get("labelled_states", 0),
                "wall_clock_s": student.get("wall_clock_s", 0.0),
                "distilled": True,
            }
        elif (run / "progress.csv").is_file():
            spent = budget(run)
        runs[who] = {"run": str(run), "checkpoint": ckpt, **spent}
    total = {
        key: round(sum(float(r.get(key, 0)) for r in runs.values()), 1)
        for key in ("steps", "wall_clock_s")
    }
    return {"runs": runs, **total}


def distilled(run: Path) -> dict[str, Any]:
    """A distilled run's budget (rounds, episodes, labelled states, training seconds) and
    its teachers, from its logs and checkpoint."""
    out: dict[str, Any] = {}
    with (run / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    if rows:
        last = rows[-1]
        out.update(
            rounds=int(float(last["step"])),
            episodes=int(float(last["episodes"])),
            labelled_states=int(float(last["rows"])),
        )
    if (run / "eval.csv").is_file():
        with (run / "eval.csv").open() as f:
            evals = list(csv.DictReader(f))
        if evals and evals[-1].get("train_s"):
            out["wall_clock_s"] = round(float(evals[-1]["train_s"]), 1)
    try:
        ckpt = json.loads((run / "latest.json").read_text())["checkpoint"]
        meta = json.loads((run / ckpt / "meta.json").read_text())
        out["teachers"] = meta.get("distill", {})
    except (OSError, ValueError, KeyError):
        pass
    return out


def family_runs(pairs: list[str]) -> dict[str, str]:
    """``FAMILY=RUN`` pairs as a dict, with a one-line error for a bad pair."""
    out: dict[str, str] = {}
    for pair in pairs:
        family, sep, run = pair.partition("=")
        if not sep or family not in MANIPULATION_FAMILIES or not run:
            raise SystemExit(
                f"--family-runs: {pair!r} is not FAMILY=RUN with a family of "
                f"{', '.join(MANIPULATION_FAMILIES)}"
            )
        if not has_checkpoint(Path(run)):
            raise SystemExit(f"--family-runs: {run} has no checkpoint")
        out[family] = run
    return out


def scripted(args: argparse.Namespace) -> dict[str, float]:
    """The scripted controller's success per family, same limit and number of episodes."""
    from captioner.scripted3d import evaluate as run_scripted
    from train.configs.presets import PRESETS

    cfg = PRESETS[args.preset][1].env
    steps = run_scripted(
        args.families,
        range(args.episodes),
        MAX_STEPS,
        num_objects=(cfg.min_objects, cfg.max_objects),
    )
    return {f: sum(n is not None for n in s.values()) / len(s) for f, s in steps.items()}


def budget(work: Path) -> dict[str, float]:
    """Steps, updates and training seconds of the run so far (from its logs)."""
    out: dict[str, float] = {}
    with (work / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    if rows:
        out.update(steps=int(float(rows[-1]["step"])), updates=int(float(rows[-1]["updates"])))
    if (work / "eval.csv").is_file():
        with (work / "eval.csv").open() as f:
            evals = list(csv.DictReader(f))
        if evals and evals[-1].get("train_s"):
            out["wall_clock_s"] = round(float(evals[-1]["train_s"]), 1)
    return out


#: The settings that tell compared runs apart (``config.json`` paths) and the value of
#: each in a config written before it existed.
COMPARED_SETTINGS = (
    ("families", ("env", "families"), None),
    ("demonstrations", ("finetune", "demos"), ""),
    ("demo BC", ("sac", "demo_bc"), 0.0),
    ("target clip", ("sac", "target_clip"), None),
    ("n-step", ("buffer", "n_step"), 1),
    ("slots", ("agent", "net", "slot_mode"), None),
    ("grounding", ("agent", "grounding"), 0.0),
    ("q-filter", ("sac", "q_filter"), True),
    ("curriculum", ("explore", "curriculum"), ()),
    ("family weights", ("explore", "family_weights"), "uniform"),
)


def compared(work: Path, last: int = 2) -> dict[str, Any]:
    """Another run's settings (:data:`COMPARED_SETTINGS`) and its seen success per family,
    the mean of its last ``last`` periodic evaluations (``eval.csv``)."""
    cfg = json.loads((work / "config.json").read_text())
    settings: dict[str, Any] = {}
    for name, path, default in COMPARED_SETTINGS:
        value: Any = cfg
        for key in path:
            value = value.get(key) if isinstance(value, dict) else None
        settings[name] = default if value is None else value
    rows = curve(work)[-last:]
    fams = settings["families"] or []
    seen = {
        f: round(sum(r[f"train/{f}"] for r in rows) / len(rows), 3)
        for f in fams
        if rows and all(f"train/{f}" in r for r in rows)
    }
    steps = [int(r["step"]) for r in rows]
    return {"run": str(work), "settings": settings, "steps": steps, "seen": seen}


def compared_lines(runs: list[dict[str, Any]]) -> list[str]:
    """A Markdown table of :func:`compared` runs."""
    names = [n for n, _, _ in COMPARED_SETTINGS]
    lines = [
        "| run | " + " | ".join(names) + " | evaluated at | seen success per family |",
        "|---|" + "---|" * len(names) + "---|---|",
    ]
    for r in runs:
        cells = []
        for n in names:
            v = r["settings"].get(n)
            if isinstance(v, list | tuple):
                cells.append(" ".join(map(str, v)) or "none")
            else:
                cells.append("none" if v == "" else str(v))
        seen = ", ".join(f"{f} {v:.2f}" for f, v in r["seen"].items())
        steps = " and ".join(f"{s:,}" for s in r["steps"])
        lines.append(f"| `{r['run']}` | " + " | ".join(cells) + f" | {steps} | {seen} |")
    return lines


def seen_instruction(run: str, family: str) -> str:
    """A seen (training) instruction of ``family`` that the run's training env draws on
    its first layout (seed 0), so ``lcrl act`` finds it feasible there."""
    import lcrl
    from train.environments.tasks import find_language_wrapper

    env = lcrl.load(run).make_env("train")
    try:
        wrapper = find_language_wrapper(env)
        wrapper.draw_from((family,))
        env.reset(seed=0)
        return wrapper.instruction
    finally:
        env.close()


def gifs(args: argparse.Namespace) -> dict[str, str]:
    """One ``lcrl act`` GIF per family, a seen instruction of the run that gives the
    family's figure, in the results folder."""
    out = {}
    for family in args.families:
        path = RESULTS_DIR / f"{NAME}-{family}.gif"
        run = args.family_runs.get(family, args.work)
        text = seen_instruction(run, family)
        cmd = [*LCRL, "act", run, "--instruction", text, "--episodes", "1"]
        cmd += ["--video", str(path), "--fps", "8"]
        env = child_env(args)
        if (
            subprocess.run(cmd, env=env, capture_output=True, preexec_fn=die_with_parent).returncode
            == 0
        ):
            out[family] = path.name
    return out


def headline(
    ev: dict[str, Any], spent: dict[str, float], own: dict[str, dict[str, float]] | None = None
) -> dict[str, Any]:
    """Seen success per family, ``chain2`` and the one policy's budget; for a family
    trained in a run of its own (``own``: its budget): ``<family>_one_policy`` (the one
    policy's figure), ``<family>_run``, ``<family>_steps`` and ``<family>_wall_clock_s``."""
    head: dict[str, Any] = {}
    for family, sets in ev["families"].items():
        seen = sets.get("train")
        head[family] = None if seen is None else seen["success"]
    chain = ev.get("chain")
    head["chain2"] = chain["success"][1].get("success") if chain else None
    head["chain2_first"] = chain["success"][0].get("success") if chain else None
    if ev.get("chain_run") or ev.get("routed"):
        rl = ev.get("rl_chain")
        head["chain2_rl_policy"] = rl["success"][1].get("success") if rl else None
        for family, sets in ev.get("chain_run", {}).items():
            seen = sets.get("train")
            head[f"{family}_distilled"] = None if seen is None else seen["success"]
    if ev.get("routed"):
        dist = ev.get("distilled_chain")
        if dist is not None:
            head["chain2_distilled"] = dist["success"][1].get("success")
        for family, sets in ev["routed"].items():
            seen = sets.get("train")
            head[f"{family}_routed"] = None if seen is None else seen["success"]
    head.update(spent)
    for family, budget_ in (own or {}).items():
        one = (ev.get("one_policy", {}).get(family) or {}).get("train")
        head[f"{family}_one_policy"] = None if one is None else one["success"]
        head[f"{family}_run"] = ev["runs"][family]
        head[f"{family}_steps"] = budget_.get("steps")
        head[f"{family}_wall_clock_s"] = budget_.get("wall_clock_s")
    return head


def figure(
    name: str,
    ev: dict[str, Any],
    script: dict[str, float],
    rows: list,
    info: dict,
    own_rows: dict[str, list] | None = None,
):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fams = list(ev["families"])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.6))
    x = np.arange(len(fams))
    bars = [
        (ev["families"], "train", "policy, seen"),
        (ev["families"], "heldout", "policy, held-out"),
    ]
    if ev.get("chain_run"):
        bars.append((ev["chain_run"], "train", "one distilled policy, seen"))
    if ev.get("routed"):
        bars.append((ev["routed"], "train", "experts routed by family, seen"))
    w = 0.8 / (len(bars) + 1)
    for i, (sets, key, label) in enumerate(bars):
        vals = [((sets.get(f) or {}).get(key) or {}).get("success") or 0.0 for f in fams]
        ax.bar(x + (i - len(bars) / 2) * w, vals, w, label=label)
    ax.bar(
        x + len(bars) / 2 * w, [script.get(f, 0.0) for f in fams], w, label="scripted controller"
    )
    for i, f in enumerate(fams):
        ax.plot([i - 0.45, i + 0.45], [TARGETS[f]] * 2, "k--", lw=1)
    # two instructions in a row: the headline policy and the ones it improved on
    chains = [
        (ev.get("rl_chain"), "one RL policy"),
        (
            ev.get("distilled_chain") or (ev.get("chain_run") and ev.get("chain")),
            "one distilled policy",
        ),
        (ev.get("chain") if ev.get("routed") else None, "experts routed by family"),
    ]
    chains = [(c, label) for c, label in chains if c and len(c.get("success", [])) > 1]
    if ev.get("chain") and not chains:
        chains = [(ev["chain"], "one RL policy")]
    c0 = len(fams)
    for j, (c, label) in enumerate(chains):
        cw = 0.8 / len(chains)
        ax.bar(c0 - 0.4 + (j + 0.5) * cw, c["success"][1]["success"], cw * 0.9, color=f"C{j + 6}")
        ax.text(c0 - 0.4 + (j + 0.5) * cw, 0.02, label, rotation=90, fontsize=6, ha="center")
    if chains:
        ax.plot([c0 - 0.45, c0 + 0.45], [TARGETS["chain2"]] * 2, "k--", lw=1)
        fams_ticks = [*fams, "2 in a row"]
    else:
        fams_ticks = fams
    ax.set_xticks(np.arange(len(fams_ticks)), fams_ticks)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success (dashed: target)")
    ax.legend(fontsize=7)
    ax.set_title("per family, privileged state")
    for i, f in enumerate(fams):
        pts = [(r["step"], r[f"train/{f}"]) for r in rows if f"train/{f}" in r]
        if pts:
            bx.plot(*zip(*pts, strict=True), marker="o", color=f"C{i}", label=f)
        mine = [(r["step"], r[f"train/{f}"]) for r in (own_rows or {}).get(f, [])]
        if mine:  # the family's own run
            bx.plot(*zip(*mine, strict=True), "--", marker="s", color=f"C{i}", label=f"{f} alone")
    bx.set_xlabel("environment steps")
    bx.set_ylabel("seen success (periodic evaluation)")
    bx.set_ylim(0, 1.05)
    bx.legend(fontsize=7)
    bx.set_title("learning curve")
    save_figure(name, fig, info, rect=(0, 0.12, 1, 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default=PRESET)
    parser.add_argument("--work", default="runs/bench/robosuite-manip")
    parser.add_argument("--steps", type=int, default=300_000, help="train up to this step")
    parser.add_argument("--episodes", type=int, default=100, help="per family and set")
    parser.add_argument(
        "--families", nargs="+", default=list(MANIPULATION_FAMILIES), choices=MANIPULATION_FAMILIES
    )
    parser.add_argument(
        "--demos",
        default="",
        help="start from these scripted demonstrations (lcrl demos record): BC-pretrained "
        "actor and critic, then online language HER (--finetune.demos)",
    )
    parser.add_argument(
        "--extra", default="", help="more lcrl train options for a new run, as one string"
    )
    parser.add_argument("--eval-only", action="store_true", help="evaluate without training")
    parser.add_argument("--gifs", action="store_true", help="an lcrl act GIF per family")
    parser.add_argument(
        "--processes", type=int, default=1, help="lcrl processes running beside this one"
    )
    parser.add_argument(
        "--family-runs",
        nargs="*",
        default=[],
        metavar="FAMILY=RUN",
        help="families whose figures come from a run of their own (a per-family preset, "
        "e.g. stack=runs/bench/robosuite-stack); the one policy's figures stay beside",
    )
    parser.add_argument(
        "--chain-run",
        default="",
        metavar="RUN",
        help="take chain2 from this run (one policy over every family, e.g. a student of "
        "lcrl distill --state) and report its per-family figures beside",
    )
    parser.add_argument(
        "--routed-run",
        default="",
        metavar="FOLDER",
        help="take chain2 from this routed policy (lcrl route: each instruction acted by "
        "its family's expert) and report its per-family figures beside",
    )
    parser.add_argument(
        "--compare",
        nargs="*",
        default=[],
        metavar="RUN",
        help="other runs (e.g. one family alone) to tabulate beside: their settings and "
        "the mean of their last two periodic evaluations",
    )
    args = parser.parse_args(argv)
    args.family_runs = family_runs(args.family_runs)
    if args.chain_run and not has_checkpoint(Path(args.chain_run)):
        raise SystemExit(f"--chain-run: {args.chain_run} has no checkpoint")
    if args.routed_run and routed_meta(Path(args.routed_run)) is None:
        raise SystemExit(f"--routed-run: {args.routed_run} is not a folder of lcrl route")
    missing = [r for r in args.compare if not (Path(r) / "config.json").is_file()]
    if missing:
        raise SystemExit(f"--compare: no run (config.json) at {', '.join(missing)}")
    work = Path(args.work)
    if not args.eval_only:
        train(args)
    if not has_checkpoint(work):
        raise SystemExit(f"{work} has no checkpoint: train it first (without --eval-only)")
    info = machine()
    ev = evaluate(args)
    script = scripted(args)
    spent = budget(work)
    own = {f: budget(Path(r)) for f, r in args.family_runs.items()}
    head = headline(ev, spent, own)
    student = distilled(Path(args.chain_run)) if args.chain_run else {}
    if student:
        head["chain2_run"] = args.chain_run
        for key in ("rounds", "labelled_states", "wall_clock_s"):
            head[f"distilled_{key}"] = student.get(key)
    routed = routed_budget(Path(args.routed_run)) if args.routed_run else {}
    if routed:
        head["chain2_run"] = args.routed_run
        head["routed_steps"] = routed["steps"]
        head["routed_wall_clock_s"] = routed["wall_clock_s"]
    reached = {
        k: (head.get(k) is not None and head[k] >= t) for k, t in TARGETS.items() if k in head
    }
    videos = gifs(args) if args.gifs else {}
    rows = curve(work)
    others = [compared(Path(r)) for r in args.compare]
    save_json(
        NAME,
        {
            "headline": head,
            "targets": TARGETS,
            "reached": reached,
            "machine": info,
            "settings": vars(args),
            "families": ev["families"],
            "chain": ev["chain"],
            "rl_chain": ev["rl_chain"],
            "distilled": {"run": args.chain_run, **student, "families": ev["chain_run"]}
            if student
            else None,
            "distilled_chain": ev["distilled_chain"],
            "routed": {"folder": args.routed_run, **routed, "families": ev["routed"]}
            if routed
            else None,
            "scripted": script,
            "curve": rows,
            "gifs": videos,
            "compared": others,
        },
    )

    def cells(sets: dict[str, Any]) -> list[str]:
        return [
            "n/a" if r is None else f"{r['success']:.2f} [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}]"
            for r in (sets.get(k) for k in SETS)
        ]

    lines = [
        "| family | run | seen | held-out combinations | paraphrases | scripted controller "
        "| target (seen) |",
        "|---|---|---|---|---|---:|---:|",
    ]
    for f, sets in ev["families"].items():
        ok = "reached" if reached.get(f) else "NOT reached"
        run = ev["runs"][f]
        lines.append(
            f"| {f} | `{run}` | {' | '.join(cells(sets))} | {script.get(f, 0):.2f} "
            f"| {TARGETS[f]} ({ok}) |"
        )
    if args.family_runs:
        lines.append(
            f"\nThe one policy of `{args.work}` (all five families) on the families above "
            "that come from a run of their own:\n"
        )
        lines += ["| family | seen | held-out combinations | paraphrases |", "|---|---|---|---|"]
        for f in args.family_runs:
            lines.append(f"| {f} | {' | '.join(cells(ev['one_policy'][f]))} |")
        for f, r in args.family_runs.items():
            b = own[f]
            lines.append(
                f"\n{f}: `{r}`, {b.get('steps', 0):,} environment steps, "
                f"{b.get('wall_clock_s', 0) / 3600:.2f} h of training."
            )
    c2 = head.get("chain2")
    if student:
        t = student.get("teachers", {})
        who = ", ".join(f"{f}: `{v['path']}`" for f, v in t.get("teachers", {}).items())
        chain_t = (t.get("chain_teacher") or {}).get("path")
        lines.append(
            f"\nOne policy over all five families, distilled with DAgger (`{args.chain_run}`, "
            f"`lcrl distill --state`): teacher `{t.get('teacher')}`"
            + (f", per family {who}" if who else "")
            + (f"; after the first instruction of a chain: `{chain_t}`" if chain_t else "")
            + f". {student.get('rounds', 0)} rounds, {student.get('labelled_states', 0):,} "
            f"labelled states, {student.get('wall_clock_s', 0) / 3600:.2f} h of DAgger (the "
            "teachers' own training not counted):\n"
        )
        lines += ["| family | seen | held-out combinations | paraphrases |", "|---|---|---|---|"]
        for f, sets in ev["chain_run"].items():
            lines.append(f"| {f} | {' | '.join(cells(sets))} |")
    if routed:
        who = ", ".join(
            f"{w}: `{r['run']}` ({r.get('steps', 0):,} steps, "
            f"{r.get('wall_clock_s', 0) / 3600:.2f} h)"
            for w, r in routed["runs"].items()
        )
        lines.append(
            f"\nExperts routed by instruction family (`{args.routed_run}`, `lcrl route`): "
            f"{who}; together {routed['steps']:,.0f} steps and "
            f"{routed['wall_clock_s'] / 3600:.2f} h of training (a distilled run: the "
            "states its DAgger rounds visited and its seconds, its teachers not counted):\n"
        )
        lines += ["| family | seen | held-out combinations | paraphrases |", "|---|---|---|---|"]
        for f, sets in ev["routed"].items():
            lines.append(f"| {f} | {' | '.join(cells(sets))} |")
    chain_policy = args.routed_run if routed else args.chain_run if student else ""
    lines.append(
        f"\nTwo instructions in a row (`lcrl eval --chain 2`, {args.episodes} chains"
        + (f", the policy of `{chain_policy}`" if chain_policy else "")
        + "): "
        + ("n/a" if c2 is None else f"{c2:.2f}")
        + ("" if head.get("chain2_first") is None else f" (first {head['chain2_first']:.2f})")
        + f", target {TARGETS['chain2']} ({'reached' if reached.get('chain2') else 'NOT reached'})."
    )
    if head.get("chain2_distilled") is not None:
        dist = head["chain2_distilled"]
        lines.append(f"The distilled student of `{args.chain_run}`: {dist:.2f}.")
    if student or routed:
        rl = head.get("chain2_rl_policy")
        lines.append(
            f"The RL policy of `{args.work}`: " + ("n/a" if rl is None else f"{rl:.2f}") + "."
        )
    lines.append(
        f"\nBudget: {spent.get('steps', 0):,} environment steps, {spent.get('updates', 0):,} "
        f"updates, {spent.get('wall_clock_s', 0) / 3600:.2f} h of training on this machine."
    )
    if others:
        lines.append(
            "\nOther runs, seed 0 (their settings from their config.json; seen success: the "
            "mean of their last two periodic evaluations, 50 episodes each):\n"
        )
        lines += compared_lines(others)
    if videos:
        lines.append("\n" + " ".join(f"![{f}]({p})" for f, p in videos.items()))
    save_markdown(
        NAME,
        "Robosuite manipulation with language HER (privileged state)",
        "\n".join(lines),
        info,
    )
    figure(NAME, ev, script, rows, info, {f: curve(Path(r)) for f, r in args.family_runs.items()})
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except subprocess.CalledProcessError as e:  # its log says why; a stopped run is kept
        raise SystemExit(f"the lcrl run stopped (exit status {e.returncode})") from None

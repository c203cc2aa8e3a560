"""Compositional generalisation over seeds: slots selected by position from the pooled
sentence vector, beside slots selected through their colour and shape with the auxiliary
grounding loss, with and without instruction augmentation; same presets, seeds and
budget.

    python benchmarks/compositional.py --env lang2d --arms pooled phrased --also grounded
    python benchmarks/compositional.py --env robosuite --steps 30000 --arms pooled clipped \
        --also grounded  # reach, privileged state
    python benchmarks/compositional.py --env lang2d --preset lang2d-quick --steps 8000
    python benchmarks/compositional.py --env lang2d --arms pooled phrased --canonical phrased \
        --headline-arm phrased-canonical  # the phrased policies behind a canonical reader

Arms (``--arms``): ``pooled`` (``--agent.net.slot-mode select``, no grounding loss),
``attributes`` (``--agent.net.slot-mode attributes``), ``grounded`` (attributes and
``--agent.grounding W``), ``phrased`` (grounded, and ``--env.phrasings N``: updates
also read training-only phrasings of the instructions, whose words the paraphrase set
never uses) and ``reader`` (phrased, and ``--env.text-reader``: the goal vector adds a
token-level reader's parse of the instruction); ``clipped`` is grounded with the critic's
TD targets clipped to the value bound of success rewards (``--sac.target-clip 1.0``),
which keeps a critic from diverging past it; ``canonical`` is grounded with
``--env.canonical-reader`` (a token-level reader turns each instruction into the canonical
sentence of the meaning it reads, and the policy reads that); ``preset`` adds nothing to
the preset (``--preset lang2d-grounded --arms preset``: the policy a user gets from it).
``--canonical ARM`` evaluates an arm's finished runs again with
``lcrl eval --canonical-reader``, reported as ``ARM-canonical`` (the same policies, a
reader fitted in front of them; its figures go to ``canonical-eval.json`` beside
``final-eval.json``). Each arm trains one run per seed
(``lcrl train PRESET --seed S``), two runs at a time with one torch thread each, and is
evaluated with ``lcrl eval`` (100 episodes per set: seen, held-out combinations,
paraphrases). Finished runs (their ``final-eval.json``) are kept, so an interrupted
benchmark goes on where it stopped.
``--also ARM`` adds an arm's finished runs to the report without training more.

``--test-seed T`` evaluates the headline arm's runs once more on evaluation seed ``T``
(``lcrl eval --seed T``, through the canonical reader for an ``ARM-canonical`` headline),
a seed that no choice used (``benchmarks.protocol``): the headline is that evaluation,
and the arms' own evaluations (seed 0, where arms were compared) stand beside it.

    python -m benchmarks.compositional --env lang2d --preset lang2d-grounded --arms preset \
        --canonical preset --headline-arm preset-canonical --test-seed 13 \
        --name compositional-lang2d --keep benchmarks/models/lang2d-grounded
        # the shipped preset, re-measured on a test seed; its three policies kept

Writes ``benchmarks/results/compositional-<env>.{json,md,png}`` (``compositional-<preset>``
with another ``--preset``). The headline is that of the last of ``--arms`` (or
``--headline-arm``): ``seen`` (mean over seeds), ``heldout_ratio`` and ``paraphrase_ratio``
(mean held-out or paraphrase success over mean seen success), with the spread over seeds;
the pooled arm's figures stand beside them. Targets: lang2d seen >= 0.90, held-out ratio
>= 0.70, paraphrase ratio >= 0.90; robosuite seen >= 0.85, held-out ratio >= 0.70.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import benchmarks.common as common
from benchmarks.common import (
    LCRL,
    child_env,
    die_with_parent,
    machine,
    save_figure,
    save_json,
    save_markdown,
)
from benchmarks.protocol import VALIDATION_SEEDS, check_test_seed
from lcrl.errors import LcrlError
from train.evaluation.report import spread

PRESETS = {"lang2d": "lang2d", "robosuite": "robosuite-reach"}
#: Collection options every run of a preset adds (but those of the ``preset`` arm, the
#: preset as shipped): the settings its earlier results were measured with, where the
#: preset ships others since (robosuite-reach: 8 environments at batch 128, docs/scale.md).
COLLECTION = {"robosuite-reach": ["--collect.envs", "1", "--batch-size", "256"]}
TARGETS = {
    "lang2d": {"seen": 0.90, "heldout_ratio": 0.70, "paraphrase_ratio": 0.90},
    "robosuite": {"seen": 0.85, "heldout_ratio": 0.70},
}
SETS = ("train", "heldout", "paraphrase")
ARMS = ("pooled", "attributes", "grounded", "phrased", "reader", "clipped", "canonical", "preset")
#: The suffix of an arm's runs evaluated through a canonical reader (``--canonical``).
READ = "-canonical"
#: Between an arm and its test seed in the name of its evaluation there (``ARM@seedT``).
TEST = "@seed"


def arm_args(arm: str, grounding: float, phrasings: int = 16) -> list[str]:
    """The ``lcrl train`` options of an arm."""
    from train.configs.presets import SLOT_ATTRIBUTES

    # only the clipped arm clips its TD targets, whatever the preset does
    attributes = ["--agent.net.slot-mode", "attributes", "--agent.net.slot-attributes"]
    attributes += [str(v) for v in SLOT_ATTRIBUTES]
    unclipped = ["--sac.target-clip", "None"]
    if arm == "pooled":
        return ["--agent.net.slot-mode", "select", "--agent.grounding", "0", *unclipped]
    if arm == "attributes":
        return [*attributes, "--agent.grounding", "0", *unclipped]
    if arm == "grounded":
        return [*attributes, "--agent.grounding", str(grounding), *unclipped]
    if arm == "clipped":
        return [*attributes, "--agent.grounding", str(grounding), "--sac.target-clip", "1.0"]
    if arm in ("phrased", "reader"):
        grounded = [*attributes, "--agent.grounding", str(grounding), *unclipped]
        phrased = [*grounded, "--env.phrasings", str(phrasings)]
        return phrased if arm == "phrased" else [*phrased, "--env.text-reader"]
    if arm == "canonical":
        return [*attributes, "--agent.grounding", str(grounding), *unclipped]
    if arm == "preset":  # the preset as shipped: what a user who names it gets
        return []
    if arm.endswith(READ):  # the same training; the reader comes in at evaluation
        return arm_args(arm.removesuffix(READ), grounding, phrasings)
    raise SystemExit(f"unknown arm {arm!r}; choose from {ARMS}")


def summarise(per_seed: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """An arm's figures over seeds from each seed's ``lcrl eval`` sets: per set the mean,
    spread and per-seed success; the held-out and paraphrase ratios (mean over mean) and
    the spread of the per-seed ratios."""
    out: dict[str, Any] = {"seeds": sorted(per_seed)}
    for s in SETS:
        values = [per_seed[k][s]["success"] for k in sorted(per_seed)]
        out[s] = spread(values)
    seen = out["train"]["mean"]
    for s, key in (("heldout", "heldout_ratio"), ("paraphrase", "paraphrase_ratio")):
        out[key] = out[s]["mean"] / seen if seen > 0 else 0.0
        ratios = [
            per_seed[k][s]["success"] / per_seed[k]["train"]["success"]
            for k in sorted(per_seed)
            if per_seed[k]["train"]["success"] > 0
        ]
        out[f"{key}_per_seed"] = spread(ratios) if ratios else None
    return out


def headline(env: str, arms: dict[str, dict[str, Any]], new: str = "grounded") -> dict:
    """The issue's headline keys (the new arm's), and the baseline's beside them."""
    a = arms[new]
    h = {
        "seen": round(a["train"]["mean"], 3),
        "seen_std": round(a["train"]["std"], 3),
        "heldout": round(a["heldout"]["mean"], 3),
        "heldout_ratio": round(a["heldout_ratio"], 3),
        "paraphrase": round(a["paraphrase"]["mean"], 3),
        "paraphrase_ratio": round(a["paraphrase_ratio"], 3),
        "seeds": len(a["seeds"]),
    }
    if "pooled" in arms and new != "pooled":
        b = arms["pooled"]
        h.update(
            pooled_seen=round(b["train"]["mean"], 3),
            pooled_heldout_ratio=round(b["heldout_ratio"], 3),
            pooled_paraphrase_ratio=round(b["paraphrase_ratio"], 3),
        )
    return h


def reached(env: str, h: dict[str, Any]) -> dict[str, bool]:
    return {k: h[k] >= v for k, v in TARGETS[env].items()}


def slot_selection(run: Path, canonical: bool = False) -> dict[str, Any] | None:
    """What the trained actor's slot reader picks for each instruction of the run's split
    (its first head's top slot against the object the instruction names), per set: the
    fraction right and the sentences it gets wrong; with ``canonical``, through a
    canonical reader. None for a run without checkpoints or without a ``select`` or
    ``attributes`` slot reader (those pick from the goal alone)."""
    if not (run / "checkpoints").is_dir():
        return None
    import numpy as np
    import torch

    import lcrl
    from captioner.grammar import try_parse
    from envs.scene import OBJECT_KINDS

    policy = lcrl.load(run, env_overrides={"canonical_reader": True} if canonical else None)
    agent, task = policy.agent, policy.task
    if not agent.options.net.slots or agent.options.net.slot_mode == "attention":
        return None
    out: dict[str, Any] = {}
    for name in SETS:
        texts = [t for t in task.split.texts(name) if try_parse(t).family in task.families]
        meanings = [try_parse(t) for t in texts]
        named = np.array([OBJECT_KINDS.index((m.colour, m.shape)) for m in meanings])
        obs = {k: np.zeros((len(texts), *v), np.float32) for k, v in task.obs_shapes.items()}
        with torch.no_grad():
            goal = agent.goal_tensor(torch.as_tensor(policy.embed(texts)), embedded=True)
            logits = agent.actor.selection_logits(agent.obs_tensors(obs), goal)
        picked = logits.reshape(-1, *logits.shape[-3:])[0, :, 0].argmax(-1).cpu().numpy()
        right = picked == named
        out[name] = {
            "accuracy": float(right.mean()) if len(texts) else None,
            "instructions": len(texts),
            "wrong": [t for t, ok in zip(texts, right, strict=True) if not ok],
        }
    return out


def combination_success(
    per_arm: dict[str, dict[int, dict[str, Any]]], set_name: str
) -> dict[str, dict[str, float]]:
    """Per family x object of a set, each arm's success pooled over its seeds (successes
    over episodes): ``{"push blue cube": {arm: success}}``."""
    out: dict[str, dict[str, float]] = {}
    for arm, runs in per_arm.items():
        totals: dict[str, list[int]] = {}
        for r in runs.values():
            for fam, objects in r[set_name].get("family_object", {}).items():
                for obj, v in objects.items():
                    t = totals.setdefault(f"{fam} {obj}", [0, 0])
                    t[0] += int(v.get("successes", round(v["success"] * v.get("episodes", 1))))
                    t[1] += int(v.get("episodes", 1))
        for combo, (hits, n) in totals.items():
            out.setdefault(combo, {})[arm] = hits / n if n else 0.0
    return dict(sorted(out.items()))


def selection_table(selection: dict[str, dict[str, dict[str, Any] | None]]) -> str:
    """Markdown: per run, the fraction of each set's instructions whose object the actor's
    slot reader picks (:func:`slot_selection`)."""
    rows = []
    for arm, runs in selection.items():
        for seed, sel in runs.items():
            if sel is None:
                continue
            cells = [
                "" if sel[k]["accuracy"] is None else f"{sel[k]['accuracy']:.2f}" for k in SETS
            ]
            rows.append(f"| {arm} | {seed} | {' | '.join(cells)} |")
    if not rows:
        return ""
    return (
        "\nThe object the actor's slot reader picks, against the one each instruction names "
        "(fraction of the set's instructions):\n\n"
        "| arm | seed | seen | held-out combinations | paraphrases |\n|---|---:|---:|---:|---:|\n"
        + "\n".join(rows)
        + "\n"
    )


def eval_options(arm: str) -> list[str]:
    """The ``lcrl eval`` options of an arm's figures beyond episodes and sets."""
    base, _, seed = arm.partition(TEST)
    reader = ["--canonical-reader"] if base.endswith(READ) else []
    return [*reader, *(["--seed", seed] if seed else [])]


def selection_note(arms: dict[str, Any], chosen: str, test_seed: int | None = None) -> str:
    """How the headline arm was chosen, with its margin over the best other arm (empty
    with one arm); with ``test_seed``, that it was evaluated once more there."""
    if test_seed is not None:
        base = chosen.split(TEST)[0]
        return (
            f"Selection: the headline arm ({base}) is named on the command line "
            f"(`--headline-arm`), fixed before these runs; its runs were evaluated once on "
            f"test seed {test_seed}, which no choice used, and that evaluation is the "
            f"headline ({chosen}). The arms' own evaluations (evaluation seed 0, where arms "
            "were compared) stand beside it."
        )
    others = {a: v for a, v in arms.items() if a != chosen}
    if not others:
        return ""
    best = max(others, key=lambda a: others[a]["heldout_ratio"])

    def figures(arm: str) -> str:
        a = arms[arm]
        return f"seen {a['train']['mean']:.2f}, held-out / seen {a['heldout_ratio']:.2f}"

    return (
        f"Selection: the headline arm ({chosen}) is named on the command line "
        "(`--headline-arm`) after every arm was evaluated on these same episodes (each "
        f"run's final evaluation); no test seed evaluated it again. It has {figures(chosen)}; "
        f"the other arm with the highest ratio ({best}) has {figures(best)}."
    )


def combination_tables(per_combo: dict[str, dict[str, dict[str, float]]]) -> str:
    """Markdown: every held-out combination, and the seen ones that fail (below 0.50) in
    some arm, with each arm's success over its seeds."""
    arms = sorted({a for table in per_combo.values() for row in table.values() for a in row})
    head = f"| combination | {' | '.join(arms)} |\n|---|{'---:|' * len(arms)}\n"

    def rows(table: dict[str, dict[str, float]]) -> str:
        cells = [
            f"| {combo} | " + " | ".join(f"{row[a]:.2f}" if a in row else "" for a in arms) + " |"
            for combo, row in table.items()
        ]
        return "\n".join(cells) + "\n"

    text = "Held-out combinations (success over each arm's seeds):\n\n"
    text += head + rows(per_combo.get("heldout", {}))
    failing = {c: r for c, r in per_combo.get("train", {}).items() if min(r.values()) < 0.5}
    text += "\nSeen combinations below 0.50 in some arm: "
    text += ("\n\n" + head + rows(failing)) if failing else "none.\n"
    return text


def run_all(args: argparse.Namespace) -> dict[str, float]:
    """Train and evaluate every (arm, seed) that has no ``final-eval.json`` yet, ``--parallel``
    at a time; returns the seconds each took."""
    todo = [(arm, seed) for seed in args.seeds for arm in args.arms]
    todo = [(a, s) for a, s in todo if not (run_dir(args, a, s) / "final-eval.json").is_file()]
    seconds: dict[str, float] = {}
    # each running (arm, seed): its name, the process now running, the start, the log, and
    # the commands still to run after it (training, then lcrl eval)
    running: list[tuple[str, subprocess.Popen, float, Any, list[list[str]]]] = []

    def start(cmd: list[str], log: Any) -> subprocess.Popen:
        return subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=child_env(), preexec_fn=die_with_parent
        )

    while todo or running:
        while todo and len(running) < args.parallel:
            arm, seed = todo.pop(0)
            out = run_dir(args, arm, seed)
            out.parent.mkdir(parents=True, exist_ok=True)
            train = train_command(args, arm, seed)
            ev = [*LCRL, "eval", str(out), "--episodes", str(args.episodes), "--num-envs", "1"]
            ev += ["--sets", *SETS, "--no-progress", "--json", str(out / "final-eval.json")]
            log = open(out.parent / f"{out.name}.log", "w")  # noqa: SIM115
            running.append((f"{arm}-s{seed}", start(train, log), time.perf_counter(), log, [ev]))
        time.sleep(5)
        for item in list(running):
            name, proc, t0, log, rest = item
            if proc.poll() is None:
                continue
            running.remove(item)
            if proc.returncode != 0:
                log.close()
                raise SystemExit(f"{name} failed: see {log.name}")
            if rest:  # its next command
                log.flush()
                running.append((name, start(rest[0], log), t0, log, rest[1:]))
                continue
            log.close()
            seconds[name] = round(time.perf_counter() - t0, 1)
            print(f"{name} done in {seconds[name]:.0f} s", flush=True)
    return seconds


def train_command(args: argparse.Namespace, arm: str, seed: int) -> list[str]:
    """The ``lcrl train`` command of an (arm, seed)."""
    out = run_dir(args, arm, seed)
    train = [*LCRL, "train", args.preset, "--out", str(out), "--seed", str(seed)]
    train += ["--total-steps", str(args.steps), "--overwrite", "--no-progress"]
    pinned = [] if arm == "preset" else COLLECTION.get(args.preset, [])
    return [*train, *pinned, *arm_args(arm, args.grounding, args.phrasings)]


def run_dir(args: argparse.Namespace, arm: str, seed: int) -> Path:
    """The run folder of an (arm, seed); an arm's evaluation on a test seed (``ARM@seedT``)
    is of the same runs."""
    return Path(args.work) / f"{arm.split(TEST)[0].removesuffix(READ)}-s{seed}"


def eval_test(args: argparse.Namespace, arm: str) -> dict[int, Path]:
    """Evaluate the finished runs of ``arm`` once on ``--test-seed`` (through a canonical
    reader for an ``ARM-canonical``); their files by seed."""
    seed = str(args.test_seed)
    reader = ["--canonical-reader"] if arm.endswith(READ) else []
    return evaluate_again(
        args, arm, f"test-eval-{seed}.json", ["--seed", seed, *reader], f"{arm}{TEST}{seed}"
    )


def eval_file(args: argparse.Namespace, arm: str, seed: int) -> Path:
    """An (arm, seed)'s evaluation: ``final-eval.json``, or ``canonical-eval.json`` for
    an arm's runs read through a canonical reader."""
    name = "canonical-eval.json" if arm.endswith(READ) else "final-eval.json"
    return run_dir(args, arm, seed) / name


def eval_canonical(args: argparse.Namespace, arm: str) -> dict[int, Path]:
    """Evaluate the finished runs of ``arm`` with ``lcrl eval --canonical-reader``; their
    files by seed."""
    name = eval_file(args, arm + READ, 0).name
    return evaluate_again(args, arm, name, ["--canonical-reader"], f"{arm}{READ}")


def evaluate_again(
    args: argparse.Namespace, arm: str, name: str, options: list[str], label: str
) -> dict[int, Path]:
    """Evaluate the finished runs of ``arm`` again with ``lcrl eval ... OPTIONS`` into
    ``name`` in each run (those without the file yet, one after another), logging to
    ``RUN-LABEL.log`` beside the run; the files by seed."""
    found: dict[int, Path] = {}
    for seed in args.seeds:
        run = run_dir(args, arm, seed)
        if not (run / "final-eval.json").is_file():
            continue
        out = run / name
        if not out.is_file():
            ev = [*LCRL, "eval", str(run), "--episodes", str(args.episodes), "--num-envs", "1"]
            ev += ["--sets", *SETS, "--no-progress", *options, "--json", str(out)]
            print(f"== {label}-s{seed}: {' '.join(ev[2:])}", flush=True)
            with open(run.parent / f"{run.name}-{label}.log", "w") as log:
                done = subprocess.run(
                    ev, stdout=log, stderr=subprocess.STDOUT, env=child_env(),
                    preexec_fn=die_with_parent, check=False,
                )  # fmt: skip
            if done.returncode != 0:
                raise SystemExit(f"{label}-s{seed} failed: see {log.name}")
        found[seed] = out
    return found


def keep_models(args: argparse.Namespace, arm: str, seeds: list[int]) -> dict[str, str]:
    """Keep the runs of ``arm`` in ``--keep``/seedS to act (:func:`keep_checkpoint`:
    weights and configs without critics), reading through the canonical reader by default,
    fitted and kept beside them, where the arm's figures do; their folders by seed."""
    from train.policies.loading import keep_checkpoint

    reader = arm.split(TEST)[0].endswith(READ)
    kept = {}
    for seed in seeds:
        folder, source = Path(args.keep) / f"seed{seed}", run_dir(args, arm, seed)
        dest = keep_checkpoint(source, folder, reader, acting_only=True, reader_cache=reader)
        kept[str(seed)] = str(dest)
    return kept


#: The per-arm entries of a result file that :func:`carry_over` keeps for arms not rerun.
PER_ARM_KEYS = ("arms", "per_seed", "heldout_family_object", "slot_selection", "arm_options")


def carry_over(payload: dict[str, Any], path: Path) -> list[str]:
    """Arms of the previous result file at ``path`` that this invocation neither trained nor
    evaluated stay in ``payload`` (every per-arm entry), each marked in ``kept_from`` with
    the command and date that produced it, so that rerunning one arm never drops the
    figures of the others (the pooled baseline beside the new arm); returns their names."""
    if not path.is_file():
        return []
    old = json.loads(path.read_text())
    source = {"command": old.get("command"), "date": old.get("machine", {}).get("date")}
    kept = [a for a in old.get("arms", {}) if a not in payload["arms"]]
    for arm in kept:
        for key in PER_ARM_KEYS:
            if arm in old.get(key, {}):
                payload[key][arm] = old[key][arm]
        if arm in old.get("eval_options", {}):
            payload["eval_options"][arm] = old["eval_options"][arm]
        payload.setdefault("kept_from", {})[arm] = old.get("kept_from", {}).get(arm, source)
    return kept


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", choices=tuple(PRESETS), default="lang2d")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--preset", default="", help="default: the env's (see PRESETS)")
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=["pooled", "grounded"])
    parser.add_argument(
        "--also",
        nargs="+",
        choices=ARMS,
        default=[],
        help="arms reported with the seeds they have finished, never trained",
    )
    parser.add_argument(
        "--canonical",
        nargs="+",
        choices=ARMS,
        default=[],
        help="evaluate these arms' finished runs again through a canonical reader (lcrl eval "
        f"--canonical-reader), reported as ARM{READ}",
    )
    parser.add_argument(
        "--headline-arm",
        choices=(*ARMS, *(a + READ for a in ARMS)),
        default="",
        help="the arm the headline reports (default: the last of --arms)",
    )
    parser.add_argument("--phrasings", type=int, default=16, help="the phrased arm's count")
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--grounding", type=float, default=1.0, help="the grounded arm's weight")
    parser.add_argument("--episodes", type=int, default=100, help="lcrl eval episodes per set")
    parser.add_argument("--parallel", type=int, default=2, help="runs at a time")
    parser.add_argument("--work", default="")
    parser.add_argument(
        "--test-seed",
        type=int,
        default=None,
        help="evaluate the headline arm once more on this evaluation seed, one no choice "
        "used, and report that as the headline",
    )
    parser.add_argument("--name", default="", help="the result's name (default: from --env)")
    parser.add_argument("--note", default="", help="what changed since the file's last run")
    parser.add_argument(
        "--keep",
        default="",
        help="keep the headline arm's policies here (DIR/seedS: weights and configs, the "
        "canonical reader on for an ARM-canonical headline)",
    )
    args = parser.parse_args(argv)
    if args.steps <= 0 or args.episodes <= 0 or args.parallel <= 0:
        parser.error("--steps, --episodes and --parallel must be positive")
    args.preset = args.preset or PRESETS[args.env]
    tag = args.env if args.preset == PRESETS[args.env] else args.preset
    args.work = args.work or f"runs/bench/compositional-{tag}"
    if args.test_seed is not None:  # seed 0: where arms were compared (lcrl eval's default)
        try:
            check_test_seed(args.test_seed, (0, *VALIDATION_SEEDS))
        except LcrlError as e:
            parser.error(str(e))
    info = machine()
    seconds = run_all(args)
    per_arm: dict[str, dict[int, dict[str, Any]]] = {}
    for arm in args.arms:
        per_arm[arm] = {
            s: json.loads((run_dir(args, arm, s) / "final-eval.json").read_text())["sets"]
            for s in args.seeds
        }
    for arm in args.also:
        found = Path(args.work).glob(f"{arm}-s*/final-eval.json")
        runs = {int(f.parent.name.rsplit("-s", 1)[1]): f for f in found}
        if runs and arm not in per_arm:
            per_arm[arm] = {s: json.loads(runs[s].read_text())["sets"] for s in sorted(runs)}
    for arm in args.canonical:
        runs = eval_canonical(args, arm)
        if runs:
            per_arm[arm + READ] = {s: json.loads(f.read_text())["sets"] for s, f in runs.items()}
    new = args.headline_arm or args.arms[-1]
    if args.test_seed is not None:
        runs = eval_test(args, new)
        if not runs:
            raise SystemExit(f"the headline arm {new!r} has no finished runs to test")
        new = f"{new}{TEST}{args.test_seed}"
        per_arm[new] = {s: json.loads(f.read_text())["sets"] for s, f in runs.items()}
    arms = {arm: summarise(runs) for arm, runs in per_arm.items()}
    name = args.name or f"compositional-{tag}"
    kept_models = keep_models(args, new, sorted(per_arm[new])) if args.keep else {}
    per_seed = {
        arm: {
            str(s): {k: {"success": r[k]["success"], "ci": r[k]["ci"]} for k in SETS}
            for s, r in runs.items()
        }
        for arm, runs in per_arm.items()
    }
    combos = {
        arm: {str(s): r["heldout"].get("family_object", {}) for s, r in runs.items()}
        for arm, runs in per_arm.items()
    }
    per_combo = {k: combination_success(per_arm, k) for k in ("heldout", "train")}
    selection = {
        arm: {
            str(s): slot_selection(run_dir(args, arm, s), arm.split(TEST)[0].endswith(READ))
            for s in runs
        }
        for arm, runs in per_arm.items()
        if TEST not in arm  # the same policies and reader as the arm's own evaluation
    }
    payload: dict[str, Any] = {
        "headline": {},
        "targets": TARGETS[args.env],
        "reached": {},
        "machine": info,
        "settings": vars(args),
        "arm_options": {
            arm: arm_args(arm.split(TEST)[0], args.grounding, args.phrasings) for arm in arms
        },
        "eval_options": {arm: eval_options(arm) for arm in arms if eval_options(arm)},
        "arms": arms,
        "per_seed": per_seed,
        "heldout_family_object": combos,
        "combination_success": per_combo,
        "slot_selection": selection,
        "seconds": seconds,
    }
    if kept_models:
        payload["models"] = kept_models
    if args.note:
        payload["note"] = args.note
    kept = carry_over(payload, common.RESULTS_DIR / f"{name}.json")
    if new not in arms:
        raise SystemExit(f"the headline arm {new!r} has no runs here nor in the previous file")
    head = headline(args.env, arms, new)
    ok = reached(args.env, head)
    payload["headline"], payload["reached"] = head, ok
    payload["selection"] = selection_note(arms, new, args.test_seed)
    save_json(name, payload)
    lines = [
        "| arm | seed | seen | held-out combinations | paraphrases | held-out / seen |",
        "|---|---:|---|---|---|---:|",
    ]
    for arm in arms:
        for s, r in sorted(per_seed[arm].items(), key=lambda kv: int(kv[0])):
            cells = [
                f"{r[k]['success']:.2f} [{r[k]['ci'][0]:.2f}, {r[k]['ci'][1]:.2f}]" for k in SETS
            ]
            seen = r["train"]["success"]
            ratio = f"{r['heldout']['success'] / seen:.2f}" if seen else "n/a"
            lines.append(f"| {arm} | {s} | {' | '.join(cells)} | {ratio} |")
        a = arms[arm]
        mean = [f"{a[k]['mean']:.2f} ± {a[k]['std']:.2f}" for k in SETS]
        lines.append(f"| **{arm}** | mean ± sd | {' | '.join(mean)} | {a['heldout_ratio']:.2f} |")
    verdict = ", ".join(
        f"{k} {head[k]:.2f} {'reached' if v else 'NOT reached'} (target {TARGETS[args.env][k]})"
        for k, v in ok.items()
    )
    body = (
        f"Preset `{args.preset}`, {args.steps:,} steps, seeds {args.seeds}; "
        f"`lcrl eval` with {args.episodes} episodes per set (95% Wilson intervals per run).\n\n"
        + "\n".join(lines)
        + f"\n\nHeadline ({new}): {verdict}.\n\n"
        + (f"{note}\n\n" if (note := selection_note(arms, new, args.test_seed)) else "")
        + (f"{args.note}\n\n" if args.note else "")
        + (f"Policies kept (to act): {', '.join(kept_models.values())}.\n\n" if kept_models else "")
        + combination_tables(per_combo)
        + selection_table(selection)
    )
    if kept:
        body += (
            f"\n\nArms kept from the previous file (not rerun by this command): "
            f"{', '.join(kept)}; `kept_from` in the JSON names the command that produced them.\n"
        )
    save_markdown(name, f"Compositional generalisation ({args.env})", body, info)

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / len(arms)
    for j, (arm, a) in enumerate(arms.items()):
        xs = [i + (j - (len(arms) - 1) / 2) * width for i in range(len(SETS))]
        ax.bar(xs, [a[k]["mean"] for k in SETS], width, yerr=[a[k]["std"] for k in SETS],
               capsize=3, label=arm, alpha=0.8)  # fmt: skip
        for x, k in zip(xs, SETS, strict=True):
            ys = [r[k]["success"] for r in per_seed[arm].values()]
            ax.plot([x] * len(ys), ys, "k.", ms=4)
    ax.set_xticks(range(len(SETS)), ["seen", "held-out combinations", "paraphrases"])
    ax.set(ylim=(0, 1.02), ylabel="success (mean ± sd over seeds; dots: seeds)")
    ax.set_title(f"{args.preset}, {args.steps:,} steps, seeds {args.seeds}")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # beside the bars
    save_figure(name, fig, info)
    print(json.dumps(head, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

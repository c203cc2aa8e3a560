"""Does the learned captioner read the episodes of the policies it relabels? Trained
without and with them.

    python -m benchmarks.captioner_policy

On robosuite, the factored captioner and reward model of ``captioner-robosuite.json``
(``--model.head factored`` over the kept ``perception-3k``, the settings of
:mod:`benchmarks.captioner_heads`) are trained two ways, 3 training seeds each:

* ``scripted``: on the random and scripted episodes of ``captioner_heads``' training set
  (1,200 episodes of 80 steps, collection seed 0), as the kept captioner was;
* ``with-policy``: on the same episodes and those of the kept camera policy
  (``benchmarks/models/robosuite-camera``: 300 episodes of 100 steps, every family) and
  of its put and stack teachers (``benchmarks/models/robosuite-camera-parts/teachers``:
  100 episodes each), every frame labelled by the rule captioner with all five families.

Each model is evaluated once on three test sets that no choice used: the random and
scripted episodes of ``captioner_heads`` (seed 1000, ``test``), episodes of the camera
policy (seed 1001, ``camera``) and of the two teachers (seeds 1002 and 1003,
``teachers``). No setting is chosen here: steps, loss and thresholds are those
``captioner_heads`` chose on its validation episodes.

``--perception MODEL`` trains and evaluates the same arms over another perception model
(``--arms with-policy``: that arm alone), in folders and a result file named after the
model's folder (``captioner-robosuite-policy-perception-80x3``).

Datasets and checkpoints go to ``--work`` (default ``data/captioner-policy``); a stage
whose output is there is not run again. Writes
``benchmarks/results/captioner-robosuite-policy.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from benchmarks.captioner_heads import (
    COLLECT,
    KEPT_PERCEPTION,
    TARGETS,
    TEST_SEED,
    by_family,
    datasets,
    evaluate,
    judged_headline,
    summary,
    train_heads,
)
from benchmarks.common import (
    LCRL,
    RESULTS_DIR,
    add_report_only,
    new_figure,
    publish,
    record_once,
    run_jobs,
)

CAMERA = "benchmarks/models/robosuite-camera"
TEACHERS = "benchmarks/models/robosuite-camera-parts/teachers"
#: Policy episodes: name -> (policy, training episodes and seed, test episodes and seed).
POLICIES = {
    "camera-policy": (CAMERA, (300, 5), (100, TEST_SEED + 1)),
    "put-teacher": (f"{TEACHERS}/put", (100, 6), (30, TEST_SEED + 2)),
    "stack-teacher": (f"{TEACHERS}/stack", (100, 7), (30, TEST_SEED + 3)),
}
#: The policies' episode length (the camera policy's own).
POLICY_STEPS = 100
ARMS = ("scripted", "with-policy")
SPLITS = ("test", "camera", "teachers")
KEYS = ("seen_exact_match", "heldout_combinations_exact_match", "seen_reward_auc",
        "heldout_combinations_reward_auc")  # fmt: skip


def policy_sets(work: Path) -> dict[str, dict[str, Path]]:
    """Each policy's training and test episodes, collected when they are not there."""
    out: dict[str, dict[str, Path]] = {}
    c = COLLECT["robosuite"]
    for name, (policy, *sizes) in POLICIES.items():
        for split, (episodes, seed) in zip(("train", "test"), sizes, strict=True):
            argv = ["caption", "collect", "--env", "robosuite", "--sources", "policy"]
            argv += ["--policy", policy, "--episodes", str(episodes), "--seed", str(seed)]
            argv += ["--image-size", str(c["image_size"])]
            argv += ["--max-episode-steps", str(POLICY_STEPS)]
            out.setdefault(name, {})[split] = record_once(work / f"{name}-{split}.h5", argv)
    return out


def merged(path: Path, parts: list[Path]) -> Path:
    """``lcrl caption merge`` of ``parts`` into ``path``, when it is not there."""
    if not path.is_file():
        cmd = [*LCRL, "caption", "merge", *map(str, parts), "--out", str(path)]
        run_jobs([("merge", [*cmd, "--no-progress"], path.with_suffix(".log"))], 1)
    return path


def perception_tag(model: str) -> str:
    """How the folders and the result of a run over another perception model than the kept
    ``perception-3k`` are named: that model's folder (``perception-80x3``); empty for
    ``perception-3k``."""
    path = Path(model)
    if path == Path(KEPT_PERCEPTION["robosuite"]):
        return ""
    return (path.parent if path.name == "model" else path).name


def perception_beside(head: dict[str, Any]) -> list[str]:
    """A table of the with-policy arm's headline beside the kept (``perception-3k``)
    captioner-robosuite-policy.json's, key by key; empty without that file."""
    path = RESULTS_DIR / "captioner-robosuite-policy.json"
    if not path.is_file():
        return []
    kept = json.loads(path.read_text())["headline"]
    rows = ["| figure (seed means) | perception-3k | this perception |", "|---|---:|---:|"]
    for key, value in head.items():
        if isinstance(value, float) and isinstance(kept.get(key), float):
            rows.append(f"| {key} | {kept[key]:.3f} | {value:.3f} |")
    return ["\n".join(rows)]


def arm_args(args: argparse.Namespace, arm: str) -> argparse.Namespace:
    """The ``captioner_heads`` arguments of one arm: the factored head, its own folder
    (``ARM-TAG`` over another perception model, :func:`perception_tag`)."""
    tag = perception_tag(args.perception)
    return argparse.Namespace(
        env="robosuite", heads=["factored"], seeds=args.seeds, steps=args.steps,
        parallel=args.parallel, work=str(Path(args.work) / (f"{arm}-{tag}" if tag else arm)),
    )  # fmt: skip


def headline_of(results: dict[str, Any]) -> dict[str, Any]:
    """The with-policy arm's figures on each test set (means over seeds), the scripted
    arm's beside them."""
    head: dict[str, Any] = {}
    for arm, prefix in (("with-policy", ""), ("scripted", "scripted_")):
        if arm not in results:
            continue
        for split in SPLITS:
            s = summary(results[arm]["factored"][split])
            for key in KEYS:
                name = key.removeprefix("seen_")
                where = "" if split == "test" else f"{split}_"
                if key in s:
                    head[f"{prefix}{where}{name}"] = round(s[key]["mean"], 3)
    return head


def table(results: dict[str, Any]) -> str:
    """One row per arm and test set: means over seeds with their range."""
    rows = [
        "| trained on | test set | seen exact match | held-out exact match | seen reward AUC "
        "| held-out reward AUC |",
        "|---|---|---|---|---|---|",
    ]
    for arm in results:
        for split in ("val", *SPLITS):
            s = summary(results[arm]["factored"][split])
            cells = [
                f"{s[k]['mean']:.3f} [{s[k]['range'][0]:.3f}, {s[k]['range'][1]:.3f}]"
                if k in s
                else "-"
                for k in KEYS
            ]
            rows.append(f"| {arm} | {split} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def family_table(results: dict[str, Any]) -> str:
    """Seen and held-out exact match per family on the policy test sets, pooled over
    seeds."""
    rows = ["| trained on | test set | family | seen | held-out combinations |"]
    rows.append("|---|---|---|---|---|")
    for arm in results:
        for split in ("camera", "teachers"):
            per = results[arm]["factored"][split]
            seen, held = by_family(per, "seen"), by_family(per, "heldout_combinations")
            for fam in sorted(set(seen) | set(held)):
                cells = [
                    f"{g[fam]['exact_match']:.2f} ({g[fam]['observations']})" if fam in g else "-"
                    for g in (seen, held)
                ]
                rows.append(f"| {arm} | {split} | {fam} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def figure(results: dict[str, Any]) -> Any:
    """Held-out exact match and reward AUC per test set, both arms (seed means and
    ranges)."""
    import numpy as np

    fig, axes = new_figure(ncols=2, figsize=(10, 3.8))
    x = np.arange(len(SPLITS))
    for ax, key in zip(axes, KEYS[1::2], strict=True):
        for i, arm in enumerate(results):
            s = [summary(results[arm]["factored"][split])[key] for split in SPLITS]
            mean = np.array([v["mean"] for v in s])
            err = np.array(
                [[m - v["range"][0], v["range"][1] - m] for m, v in zip(mean, s, strict=True)]
            ).T
            ax.bar(x + (i - 0.5) * 0.38, mean, 0.38, yerr=err, capsize=3, label=arm)
        ax.set_xticks(x, SPLITS)
        ax.set_ylim(0, 1.05)
        ax.set_title(key.replace("_", " "))
        ax.legend(loc="lower right")
    return fig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=3000, help="training steps per model")
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--work", default="data/captioner-policy")
    parser.add_argument(
        "--perception",
        default=KEPT_PERCEPTION["robosuite"],
        help="the perception model the captioners read (a model other than the kept "
        "perception-3k trains in ARM-NAME folders and writes "
        "captioner-robosuite-policy-NAME, NAME its folder)",
    )
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS))
    add_report_only(parser, "the checkpoints' evaluations in --work")
    args = parser.parse_args(argv)
    if "with-policy" not in args.arms:
        parser.error("--arms: the headline is the with-policy arm's; name it")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    base = argparse.Namespace(env="robosuite", work=args.work)
    train, test = datasets(base)
    sets = policy_sets(work)
    tests = {
        "camera": sets["camera-policy"]["test"],
        "teachers": merged(
            work / "teachers-test.h5", [sets["put-teacher"]["test"], sets["stack-teacher"]["test"]]
        ),
    }
    data = {
        "scripted": train,
        "with-policy": merged(
            work / "robosuite-train-policy.h5", [train, *(s["train"] for s in sets.values())]
        ),
    }
    model = Path(args.perception)
    if not (model / "meta.json").is_file():
        raise SystemExit(f"captioner_policy: --perception {model} holds no perception model")
    tag = perception_tag(args.perception)
    results: dict[str, Any] = {}
    for arm in args.arms:
        a = arm_args(args, arm)
        if not args.report_only:
            train_heads(a, data[arm], model)
        results[arm] = evaluate(a, data[arm], test, **tests)
    payload = {
        **judged_headline(headline_of(results), TARGETS["robosuite"]),
        "protocol": (
            "3 training seeds per arm; every test set evaluated once; no setting chosen here "
            "(captioner_heads' steps, loss and thresholds); val: the episodes each training "
            "run held out of its own training set"
        ),
        "datasets": {
            "train": str(train),
            "test": str(test),
            **{k: str(v) for k, v in tests.items()},
            "with_policy": str(data["with-policy"]),
        },
        "policies": {k: {"policy": v[0], "train": v[1], "test": v[2]} for k, v in POLICIES.items()},
        "summary": {
            arm: {s: summary(results[arm]["factored"][s]) for s in results[arm]["factored"]}
            for arm in results
        },
        "perception": str(model),
        "results": results,
    }
    beside = perception_beside(payload["headline"]) if tag else []
    body = "\n\n".join(
        [
            *(
                [
                    f"The captioners read perception `{model}`; `perception-3k`'s (the kept "
                    "captioner-robosuite-policy.json) beside them:",
                    *beside,
                ]
                if beside
                else []
            ),
            f"**{payload['verdict']}** (the with-policy arm on the random and scripted test "
            "set). Targets: " + ", ".join(f"`{k}` >= {v}" for k, v in payload["targets"].items()),
            payload["protocol"] + ".",
            table(results),
            "Exact match per family on the policies' test sets, pooled over seeds "
            "(observations in brackets):",
            family_table(results),
        ]
    )
    publish(
        f"captioner-robosuite-policy-{tag}" if tag else "captioner-robosuite-policy", payload,
        f"Learned captioner on robosuite over {model.parent.name}: trained with the policies' "
        "episodes" if tag else
        "Learned captioner on robosuite: trained with and without the policies' episodes",
        body, figure(results),
    )  # fmt: skip
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

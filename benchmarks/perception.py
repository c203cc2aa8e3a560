"""Perception on the robosuite tabletop: collect labelled camera episodes, train, evaluate
on held-out episodes and on new layouts of another seed.

    python benchmarks/perception.py --episodes 3000 --steps 10000 --work data/bench-perception-3k

Short episodes (``--episode-steps 20``) seldom bring the gripper down to the objects, where
reach and push are judged and where it hides them from the camera. A second stage trains
on a caption dataset of 80-step episodes (random, scripted and policy) from the first
model, and is evaluated on more datasets as well, e.g. episodes of policies::

    python benchmarks/perception.py --data data/captions-robosuite-1500.h5 \
        --init data/perception-3k/model --steps 8000 --lr 5e-4 --work data/perception-80 \
        --layouts data/perception-3k/layouts.h5 \
        --eval-data data/captions-robosuite-policy.h5 data/captions-robosuite-learnedpolicy.h5

Writes ``benchmarks/results/perception-robosuite.{json,md,png}``; the headline is the mean
position error of present objects in cm (target <= 1.0) and the presence accuracy
(target >= 0.99; the flags of each episode's first frame, as policies read them, with each
frame's own beside as ``*_per_frame``), on held-out episodes, with the same figures for
the objects the gripper is within 5 cm of (``near_*``) and the fraction of frames whose
every presence flag is right. Wall-clock of each phase is recorded, also in
``WORK/times.json`` (what ``benchmarks/image_policy.py`` counts when it reuses the model).
``--eval-only`` evaluates ``WORK/model`` again and writes the results.

The held-out episodes of ``--data`` chose the build (its data, steps and start); with
``--test-data FILE`` (episodes of a seed no choice used) the headline is the figures on
those, the held-out episodes' beside as ``validation_*``, and ``--test-models MODEL ...``
are evaluated on the same test episodes beside. ``--keep DIR`` copies the model (weights
and settings, a few hundred KB) into the repository, e.g. ``benchmarks/models/``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.common import (
    RESULTS_DIR,
    machine,
    new_figure,
    save_figure,
    save_json,
    save_markdown,
)
from lcrl.perception import PerceptionConfig

NAME = "perception-robosuite"
TARGETS = {"position_error_cm": 1.0, "presence_accuracy": 0.99}


def _round(x: float | None, digits: int) -> float | None:
    return None if x is None else round(x, digits)


def _figures(res: dict[str, Any], layouts: dict[str, Any] | None) -> dict[str, Any]:
    """The headline figures of one evaluation (and of the new layouts, when given)."""
    out = {
        "position_error_cm": round(res["position_error_cm"], 3),
        "presence_accuracy": round(res["presence_accuracy"], 4),
        "position_error_cm_without_hold": _round(res.get("position_error_cm_without_hold"), 3),
        "hold_radius": res.get("hold_radius", 0.0),
        "presence_accuracy_per_frame": _round(res.get("presence_accuracy_per_frame"), 4),
        "within_reach_margin": round(res["within_reach_margin"], 3),
        "within_push_distance": round(res["within_push_distance"], 3),
        "frames_all_present_right": _round(res.get("frames_all_present_right"), 4),
        "near_position_error_cm": _round(res.get("near_position_error_cm"), 3),
        "near_frames_all_present_right": _round(res.get("near_frames_all_present_right"), 4),
        "frames_all_present_right_per_frame": _round(
            res.get("frames_all_present_right_per_frame"), 4
        ),
    }
    if layouts is not None:
        out["position_error_cm_new_layouts"] = round(layouts["position_error_cm"], 3)
        out["presence_accuracy_new_layouts"] = round(layouts["presence_accuracy"], 4)
    return out


def _collected_by(paths: list[str]) -> dict[str, str]:
    """How each caption dataset was collected, from the settings its file records."""
    from captioner.caption_files import CaptionDataset

    out = {}
    for path in dict.fromkeys(p for p in paths if p):
        with CaptionDataset(path) as ds:
            c = ds.meta.get("collect", {})
            frames = ds.num_observations
        out[path] = (
            f"{c.get('episodes')} episodes ({' and '.join(c.get('sources', []))}) of up to "
            f"{c.get('max_episode_steps')} steps, seed {c.get('seed')}, {frames} frames"
        )
    return out


def _previous(path: Path) -> dict[str, Any] | None:
    """The headline, date and commit of the result file this run replaces."""
    if not path.is_file():
        return None
    old = json.loads(path.read_text())
    if "headline" not in old:
        return None
    return {
        "headline": old["headline"],
        "date": old.get("date", old.get("machine", {}).get("date", "unknown")),
        "git": old.get("git", "unknown"),
        "command": old.get("command", ""),
    }


def _model_name(model: str, work: Path) -> str:
    return "this model" if model == str(work / "model") else model


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--episode-steps", type=int, default=20)
    parser.add_argument("--layout-episodes", type=int, default=60, help="new-layout set")
    parser.add_argument("--steps", type=int, default=10000, help="training steps")
    parser.add_argument("--image-size", type=int, default=84)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--work", default="data/bench-perception")
    parser.add_argument(
        "--data", default="", help="train on this caption dataset instead of collecting one"
    )
    parser.add_argument("--init", default="", help="start from this perception model")
    parser.add_argument(
        "--extra-data",
        nargs="*",
        default=[],
        help="more caption datasets whose every episode trains too (held out: --data's)",
    )
    parser.add_argument(
        "--hold-radius",
        type=float,
        default=PerceptionConfig.hold_radius,
        help="object permanence while acting (lcrl.perception.HeldSlots); 0: off",
    )
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument(
        "--layouts", default="", help="the new-layout set (default: collect WORK/layouts.h5)"
    )
    parser.add_argument(
        "--eval-data", nargs="*", default=[], help="more caption datasets to evaluate on"
    )
    parser.add_argument(
        "--no-results",
        action="store_true",
        help="only the model and WORK/times.json (a stage of benchmarks/image_policy.py)",
    )
    parser.add_argument(
        "--eval-only",
        action="store_true",
        help="evaluate WORK/model again (trained by an earlier run of this command) and "
        "write the results; its training times come from WORK/times.json",
    )
    parser.add_argument(
        "--test-data",
        default="",
        help="a caption dataset of a seed no choice used: the headline's episodes",
    )
    parser.add_argument(
        "--test-models",
        nargs="*",
        default=[],
        help="more perception models evaluated on --test-data beside",
    )
    parser.add_argument("--keep", default="", help="copy the model into this folder")
    args = parser.parse_args(argv)
    if args.test_models and not args.test_data:
        parser.error("--test-models needs --test-data")
    if not args.hold_radius >= 0:
        parser.error(f"--hold-radius must be >= 0, got {args.hold_radius}")

    import torch

    torch.set_num_threads(args.threads)
    from captioner.dataset import CollectConfig
    from train.commands.captions import collect
    from train.environments.perception import (
        PerceptionEvalCommand,
        PerceptionTrainConfig,
        train,
    )

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    times = {}
    t0 = time.perf_counter()
    common = dict(
        env="robosuite",
        max_episode_steps=args.episode_steps,
        image_size=args.image_size,
        overwrite=True,
        progress=False,
    )
    for path in [
        args.data,
        args.init,
        args.layouts,
        args.test_data,
        *args.eval_data,
        *args.extra_data,
        *args.test_models,
    ]:
        if path and not Path(path).exists():
            parser.error(f"no such file or folder: {path}")
    data = args.data or str(work / "train.h5")
    layouts_path = args.layouts or str(work / "layouts.h5")
    if args.eval_only:
        if not (work / "times.json").is_file() or not (work / "model").is_dir():
            parser.error(f"--eval-only: no model trained by this command in {work}")
        times = json.loads((work / "times.json").read_text())
        heldout = PerceptionEvalCommand(str(work / "model")).run()
    if not args.data and not args.eval_only:
        collect(CollectConfig(out=data, episodes=args.episodes, seed=0, **common))
    if not args.layouts and not args.eval_only:
        collect(CollectConfig(out=layouts_path, episodes=args.layout_episodes, seed=1, **common))
    if not args.eval_only:
        times["collect_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        cfg = PerceptionTrainConfig(
            data=data,
            out=str(work / "model"),
            steps=args.steps,
            lr=args.lr,
            init=args.init,
            extra_data=tuple(args.extra_data),
            model=PerceptionConfig(hold_radius=args.hold_radius),
            threads=args.threads,
            progress=False,
        )
        heldout = train(cfg)
        times["train_s"] = time.perf_counter() - t0
        (work / "times.json").write_text(json.dumps(times, indent=1))
    if args.keep:
        shutil.copytree(work / "model", args.keep, dirs_exist_ok=True)
        print(f"kept the model in {args.keep}")
    if args.no_results:
        return 0
    layouts = PerceptionEvalCommand(str(work / "model"), data=layouts_path).run()
    extra = {
        path: PerceptionEvalCommand(str(work / "model"), data=path).run() for path in args.eval_data
    }
    history = json.loads((work / "model" / "model" / "history.json").read_text())

    test = {}
    if args.test_data:  # the headline's episodes; each model judged held and frame by frame
        for model in [str(work / "model"), *args.test_models]:
            test[model] = {
                "held": PerceptionEvalCommand(model, data=args.test_data).run(),
                "each_frame_alone": PerceptionEvalCommand(
                    model, data=args.test_data, hold_radius=0.0
                ).run(),
            }
    headline = _figures(heldout, layouts)
    if test:
        mine = test[str(work / "model")]
        validation = headline
        headline = _figures(mine["held"], None)
        headline["test_data"] = args.test_data
        headline.update({f"validation_{k}": v for k, v in validation.items()})
    headline["wall_clock_s"] = round(times["collect_s"] + times["train_s"], 1)
    for path, res in extra.items():
        name = Path(path).stem
        headline[f"position_error_cm_{name}"] = _round(res.get("position_error_cm"), 3)
        headline[f"near_position_error_cm_{name}"] = _round(res.get("near_position_error_cm"), 3)
        headline[f"frames_all_present_right_{name}"] = _round(
            res.get("frames_all_present_right"), 4
        )
    reached = {
        "position_error_cm": headline["position_error_cm"] <= TARGETS["position_error_cm"],
        "presence_accuracy": headline["presence_accuracy"] >= TARGETS["presence_accuracy"],
    }
    info = machine()
    sources = _collected_by([data, *args.extra_data, args.test_data, layouts_path])
    previous = _previous(RESULTS_DIR / f"{NAME}.json")
    save_json(
        NAME,
        {
            "headline": headline,
            "targets": TARGETS,
            "reached": reached,
            "machine": info,
            "settings": vars(args),
            "times": times,
            "heldout_episodes": heldout,
            "test_episodes": test,
            "new_layouts": layouts,
            "more_datasets": extra,
            "history": history,
            "datasets": sources,
            **({"previous": previous} if previous else {}),
        },
    )
    rows = [
        *(
            (f"test: {args.test_data}, {_model_name(m, work)}{how}", r[key])
            for m, r in test.items()
            for key, how in (("held", ""), ("each_frame_alone", ", each frame alone"))
        ),
        ("held-out episodes" + (" (validation)" if test else ""), heldout),
        (f"new layouts ({Path(layouts_path).name})", layouts),
        *((Path(path).name, res) for path, res in extra.items()),
    ]
    lines = [
        "| set | position error (cm) | each frame alone | median | 90% | within 2 cm | "
        "within 5 cm | presence | frames with every presence right | gripper within 5 cm of "
        "an object: frames, its error (cm), every presence right |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name, r in rows:
        near = (
            f"{r['near_frames']}, {r['near_position_error_cm']:.2f}, "
            f"{r['near_frames_all_present_right']:.3f}"
            if r.get("near_position_error_cm") is not None
            else "none"
        )
        lines.append(
            f"| {name} | {r['position_error_cm']:.2f} | "
            f"{r['position_error_cm_without_hold']:.2f} | "
            f"{r['position_error_cm_median']:.2f} | "
            f"{r['position_error_cm_p90']:.2f} | {r['within_reach_margin']:.2f} | "
            f"{r['within_push_distance']:.2f} | {r['presence_accuracy']:.3f} | "
            f"{r['frames_all_present_right']:.3f} | {near} |"
        )
    verdict = ", ".join(
        f"{k} {'reached' if ok else 'NOT reached'} (target {TARGETS[k]})"
        for k, ok in reached.items()
    )
    source = (
        f"the caption dataset {args.data}"
        if args.data
        else f"{args.episodes} robosuite episodes of {args.episode_steps} steps (random and "
        "scripted)"
    )
    if args.extra_data:
        source += " and every episode of " + ", ".join(args.extra_data)
    start = f" from {args.init}" if args.init else ""
    body = (
        f"Trained on {source}, {args.image_size} px agentview frames, {args.steps} training "
        f"steps{start} (learning rate {args.lr}); "
        f"collection {times['collect_s']:.0f} s, training {times['train_s']:.0f} s"
        + (" (the datasets given were collected before)" if args.data else "")
        + ".\n\n"
        + "\n".join(lines)
        + "\n\nPositions are judged as policies read them: an object's position is held "
        f"while the gripper stays farther than {heldout.get('hold_radius', 0.0) * 100:.0f} cm "
        "from it (object permanence, `lcrl.perception.HeldSlots`; 0 cm: every frame alone); "
        "'each frame alone' judges every frame's own estimate."
        + (
            f" The headline is this model on {args.test_data}, episodes of a seed no choice "
            "used; the held-out episodes of the training dataset chose the build."
            if test
            else ""
        )
        + f"\n\nTargets: {verdict}.\n\nThe datasets, as their files record them:\n\n"
        + "".join(f"- {path}: {how}\n" for path, how in sources.items())
        + (
            f"\nThe file's previous headline ({previous['date']}, git {previous['git']}): "
            + ", ".join(f"{k} {v}" for k, v in previous["headline"].items() if k in TARGETS)
            + ".\n"
            if previous
            else ""
        )
    )
    save_markdown(NAME, "Perception on the robosuite tabletop", body, info)

    fig, axes = new_figure(ncols=2, figsize=(9, 3.6))
    axes[0].plot([h["step"] for h in history], [h["position_loss"] for h in history])
    axes[0].set_yscale("log")
    axes[0].set_xlabel("step")
    axes[0].set_ylabel("position loss (normalised)")
    kinds = sorted(heldout["per_kind"], key=int)
    errs = [heldout["per_kind"][k]["position_error_cm"] or 0 for k in kinds]
    axes[1].bar(kinds, errs)
    axes[1].axhline(TARGETS["position_error_cm"], color="k", ls="--", lw=1, label="target")
    axes[1].set_xlabel("object kind (slot)")
    axes[1].set_ylabel("held-out position error (cm)")
    axes[1].legend()
    save_figure(NAME, fig, info)
    print(f"wrote benchmarks/results/{NAME}.{{json,md,png}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

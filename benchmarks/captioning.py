"""Learned captioner and reward model on camera frames: how well do they read the scene?

Collects a caption dataset (random and scripted episodes labelled by the rule captioner),
trains the learned captioner and reward model on 80% of its episodes, and evaluates on
the other 20%: captioner exact match, per-slot accuracy (verb, object, direction,
relation, reference object), BLEU-4, the reward model's precision / recall / ROC AUC, and
the same on observations that achieved a held-out word combination (never a training
target). Run from the repository root::

    python benchmarks/captioning.py                      # 2D tabletop, 64x64 frames
    python benchmarks/captioning.py --episodes 300 --steps 500   # a quick look
    python benchmarks/captioning.py --encoder flatten --augment-pad 0   # the plain CNN
    python benchmarks/captioning.py --env robosuite --episodes 400 --steps 3000
    python benchmarks/captioning.py --env robosuite --encoder perception \
        --perception data/bench-perception-3k/model --data data/bench-perception-3k/train.h5

With ``--encoder perception`` both models read the object slots a frozen perception model
estimates in the first and the current frame (``benchmarks/perception.py`` trains it; its
dataset serves here too, ``--data``). The results file then keeps the figures of the
frame encoder's earlier run under ``frame_encoder`` and carries a ``headline`` (exact
match and reward AUC on held-out episodes; targets 0.80 and 0.95).

The two models train side by side, one process and one thread each (``--serial``: one
after the other in this process).

Writes ``benchmarks/results/captioner-<env>.{json,md,png}``; the dataset and the
checkpoint go to ``runs/bench/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from benchmarks.common import (
    RESULTS_DIR,
    die_with_parent,
    machine,
    save_figure,
    save_json,
    save_markdown,
)
from captioner.dataset import CaptionDataset, CollectConfig
from captioner.learned import (
    CaptionModelConfig,
    CaptionTrainConfig,
    LearnedCaptioner,
    evaluate_models,
    format_results,
    train_models,
)
from train.commands.captions import collect


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="lang2d", choices=("lang2d", "robosuite"))
    parser.add_argument("--episodes", type=int, default=3000)
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument(
        "--max-episode-steps",
        type=int,
        default=0,
        help="steps per collected episode at most (0: 50 on lang2d, 80 on robosuite, where "
        "the scripted stack takes up to 70)",
    )
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument(
        "--encoder", default="spatial", choices=("spatial", "flatten", "perception")
    )
    parser.add_argument("--perception", default="", help="with --encoder perception")
    parser.add_argument("--data", default="", help="an existing caption dataset to use")
    parser.add_argument(
        "--out",
        default="",
        help="checkpoint folder (default: runs/bench/captioner-<env>[-perception])",
    )
    parser.add_argument("--augment-pad", type=int, default=4)
    parser.add_argument(
        "--near-negatives",
        type=float,
        default=0.0,
        help="fraction of near misses among the reward model's negatives and the "
        "captioner's <none> targets (CaptionTrainConfig.near_negative_fraction)",
    )
    parser.add_argument(
        "--strides",
        type=int,
        nargs="*",
        default=[],
        help="convolution strides of the frame encoder (default: 2 1 2 1)",
    )
    parser.add_argument("--serial", action="store_true", help="train the models one by one")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--beam", type=int, default=3, help="beam width of a second pass")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--recollect", action="store_true", help="collect even if cached")
    parser.add_argument(
        "--eval-only",
        action="store_true",
        help="evaluate the checkpoint of a previous run again (no collection, no training)",
    )
    args = parser.parse_args(argv)
    info = machine()
    name = f"captioner-{args.env}"
    if (args.encoder == "perception") != bool(args.perception):
        parser.error("--encoder perception and --perception MODEL go together")
    data_path = Path(
        args.data or f"runs/bench/captions-{args.env}-{args.episodes}-{args.image_size}.h5"
    )
    ckpt = Path(args.out or f"runs/bench/{name}" + ("-perception" if args.perception else ""))
    previous = RESULTS_DIR / f"{name}.json"
    timings = {}
    if args.eval_only:
        if not (ckpt / "meta.json").exists() or not previous.exists():
            parser.error(f"--eval-only needs a previous run ({ckpt}, {previous})")
        old = json.loads(previous.read_text())
        timings = {k: v for k, v in old["timings_s"].items() if k != "eval_s"}
        for key in ("steps", "batch_size", "encoder", "augment_pad", "strides"):
            setattr(args, key, old["settings"].get(key, getattr(args, key)))
    t0 = time.perf_counter()
    if args.eval_only:
        pass
    elif args.data:
        if not data_path.is_file():
            parser.error(f"no dataset at {data_path}")
    elif args.recollect or not data_path.exists():
        collect(
            CollectConfig(
                out=str(data_path),
                env=args.env,
                episodes=args.episodes,
                image_size=args.image_size,
                max_episode_steps=args.max_episode_steps or (80 if args.env == "robosuite" else 50),
                overwrite=True,
            )
        )
    if not args.eval_only:
        timings["collect_s"] = time.perf_counter() - t0
    with CaptionDataset(data_path) as data:
        print(data.summary())
        counts = data.counts()
    if not args.eval_only:
        t0 = time.perf_counter()
        cfg = CaptionTrainConfig(
            data=str(data_path),
            out=str(ckpt),
            steps=args.steps,
            batch_size=args.batch_size,
            augment_pad=args.augment_pad,
            near_negative_fraction=args.near_negatives,
            model=CaptionModelConfig(encoder=args.encoder, strides=tuple(args.strides)),
            perception=args.perception,
            threads=args.threads,
            device=args.device,
            overwrite=True,
        )
        if args.serial:
            train_models(cfg)
        else:
            train_side_by_side(cfg)
        timings["train_s"] = time.perf_counter() - t0
    lc = LearnedCaptioner.load(ckpt, device=args.device)
    results = {}
    with CaptionDataset(data_path) as data:
        t0 = time.perf_counter()
        results["greedy"] = evaluate_models(lc, data)
        timings["eval_s"] = time.perf_counter() - t0
        if args.beam > 1:
            results[f"beam{args.beam}"] = evaluate_models(lc, data, beam=args.beam)
        # the same figures on training episodes: the gap is how much the models memorise
        val = set(lc.meta["val_episodes"])
        train_eps = np.asarray([e for e in range(data.num_episodes) if e not in val])
        sample = np.sort(np.random.default_rng(0).choice(train_eps, len(val), replace=False))
        results["greedy, training episodes"] = evaluate_models(lc, data, episodes=sample)
    for k, v in results.items():
        print(f"[{k}]\n{format_results(v)}")
    payload = {
        "env": args.env,
        "machine": info,
        "settings": vars(args),
        "dataset": counts,
        "timings_s": timings,
        "results": results,
        "history": lc.meta.get("history", {}),
    }
    if args.encoder == "perception":
        payload = perception_payload(payload, previous)
    save_json(name, payload)
    save_markdown(name, f"Learned captioner and reward model ({args.env})", _table(payload), info)
    _figure(name, payload, info)
    print(f"results in benchmarks/results/{name}.md")
    return 0


#: Targets of the models over perception, on held-out episodes.
PERCEPTION_TARGETS = {"exact_match": 0.80, "reward_auc": 0.95}


def perception_payload(payload: dict, previous: Path) -> dict:
    """The results of the models over perception, with a ``headline``; the figures of the
    frame encoder's earlier run (and any learned-relabelling figures) are kept."""

    old = json.loads(previous.read_text()) if previous.exists() else {}
    frames = old.get("frame_encoder") or {k: v for k, v in old.items() if k != "headline"}
    seen = payload["results"]["greedy"]["seen"]
    combos = payload["results"]["greedy"].get("heldout_combinations", {})
    headline = {
        **old.get("headline", {}),
        "exact_match": round(seen["exact_match"], 3),
        "reward_auc": round(seen["auc"], 3),
        "heldout_combinations_exact_match": round(combos.get("exact_match", float("nan")), 3),
        "heldout_combinations_reward_auc": round(combos.get("auc", float("nan")), 3),
    }
    reached = {k: headline[k] >= v for k, v in PERCEPTION_TARGETS.items()}
    return {
        "headline": headline,
        "targets": {**old.get("targets", {}), **PERCEPTION_TARGETS},
        "reached": {**old.get("reached", {}), **reached},
        **payload,
        "frame_encoder": frames or None,
    }


def _train_one(cfg: CaptionTrainConfig) -> str:
    return str(train_models(cfg))


def side_by_side_parts(cfg: CaptionTrainConfig) -> dict[str, CaptionTrainConfig]:
    """One config per model, each trained apart at one thread; the first model's process
    shows its progress bar (one bar keeps the log readable while both train)."""
    return {
        m: dataclasses.replace(
            cfg,
            models=(m,),
            out=f"{cfg.out}-{m}",
            progress=cfg.progress and m == cfg.models[0],
            threads=1,
        )
        for m in cfg.models
    }


def train_side_by_side(cfg: CaptionTrainConfig) -> Path:
    """Train each model in its own process (one thread each), then save them together."""
    ctx = multiprocessing.get_context("spawn")
    parts = side_by_side_parts(cfg)
    with ProcessPoolExecutor(len(parts), mp_context=ctx, initializer=die_with_parent) as pool:
        done = dict(zip(parts, pool.map(_train_one, parts.values()), strict=True))
    return merge_checkpoints(done, cfg)


def merge_checkpoints(done: dict[str, str], cfg: CaptionTrainConfig) -> Path:
    """Save the models trained apart (``{model: checkpoint}``) as one checkpoint."""
    models = {m: LearnedCaptioner.load(path) for m, path in done.items()}
    merged = models[cfg.models[0]]
    for m, lc in models.items():
        if m == "reward":
            merged.reward = lc.reward
            merged.meta["text_dim"] = lc.meta["text_dim"]
        else:
            merged.captioner = lc.captioner
        merged.meta["history"].update(lc.meta["history"])
    merged.meta["train"]["models"] = list(cfg.models)
    out = merged.save(cfg.out)
    for path in done.values():
        shutil.rmtree(path, ignore_errors=True)
    return out


def _row(group: str, decoding: str, r: dict) -> str:
    slots = r.get("slot_accuracy", {})
    cells = [
        f"{slots[g]:.2f}" if g in slots else "-"
        for g in ("verb", "object", "colour", "shape", "direction", "relation", "reference")
    ]
    auc = f"{r['auc']:.3f}" if "auc" in r else "-"
    pr = f"{r['precision']:.2f} / {r['recall']:.2f}" if "precision" in r else "-"
    return (
        f"| {group} | {decoding} | {r['observations']} | "
        f"{r.get('exact_match', float('nan')):.2f} | "
        f"{' | '.join(cells)} | {r.get('bleu4', float('nan')):.2f} | {auc} | {pr} |"
    )


def _encoder_text(settings: dict) -> str:
    """How the models read the frames, in words."""
    if settings.get("encoder") == "perception":
        return f"over the slots of the frozen perception model {settings.get('perception')}"
    return (
        f"{settings.get('encoder', 'flatten')} encoder, random-shift augmentation pad "
        f"{settings.get('augment_pad', 0)}"
    )


def _table(p: dict) -> str:
    d = p["dataset"]
    lines = [
        f"Dataset: {d['episodes']} episodes ({d['episodes_per_source']}), "
        f"{d['observations']} frames, {d['labelled_observations']} with labels. Models "
        f"trained {p['settings']['steps']} steps each at batch {p['settings']['batch_size']} "
        f"({_encoder_text(p['settings'])}) on 80% of the episodes; figures on the "
        "other 20% (and, to show what the models memorise, on as many training episodes).",
        "",
        "| observations | decoding | n | exact match | verb | object | colour | shape | direction "
        "| relation | reference | BLEU-4 | reward AUC | reward precision / recall |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for decoding, res in p["results"].items():
        for group in ("seen", "heldout_combinations"):
            if group in res and res[group].get("observations"):
                lines.append(_row(group.replace("_", " "), decoding, res[group]))
    lines.append("")
    if p["settings"].get("eval_only"):
        lines.append(
            "- The models were trained by an earlier `python benchmarks/captioning.py` run "
            "with these settings; this pass evaluated them again."
        )
    for decoding, res in p["results"].items():
        seen = res.get("seen", {})
        if "auc_near" in seen:
            lines.append(
                f"- {decoding}: reward AUC against near misses (the same instruction a few "
                f"steps before or after, not satisfied) {seen['auc_near']:.3f}; near misses "
                f"scored as satisfied {seen['near_false_positive_rate']:.2f}."
            )
        if "none_accuracy" in res:
            lines.append(
                f"- {decoding}: the captioner says `<none>` on {res['none_accuracy']:.2f} of "
                "observations that achieved nothing."
            )
    if p.get("headline"):
        h = p["headline"]
        for key, target in PERCEPTION_TARGETS.items():
            ok = "reached" if h[key] >= target else "NOT reached"
            lines.append(f"- Target {key} >= {target} on held-out episodes: {h[key]:.3f} ({ok}).")
        for key in ("learned_her_seen", "rule_her_seen"):
            if key in h:
                lines.append(f"- {key}: {h[key]:.2f} (see learned-relabelling results).")
    old = p.get("frame_encoder")
    if old and old.get("results"):
        greedy = old["results"].get("greedy", {}).get("seen", {})
        lines.append(
            f"- The frame encoder's earlier run ({old['settings'].get('encoder')} encoder, "
            f"{old['dataset']['episodes']} episodes, {old['settings'].get('image_size')} px "
            f"frames): exact match {greedy.get('exact_match', float('nan')):.2f}, reward AUC "
            f"{greedy.get('auc', float('nan')):.3f} on held-out episodes (kept under "
            "`frame_encoder` in the JSON)."
        )
    t = p["timings_s"]
    names = {"collect_s": "collect", "train_s": "train", "eval_s": "evaluate"}
    if p["settings"].get("data"):  # a dataset collected before, by its own command
        names.pop("collect_s")
        lines.append(f"- Dataset: {p['settings']['data']} (given with --data).")
    parts = [f"{names[k]} {t[k]:.0f} s" for k in names if t.get(k) is not None]
    lines.append(f"- Time: {', '.join(parts)}.")
    return "\n".join(lines)


def _figure(name: str, p: dict, info: dict) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for k, v in p["history"].items():
        ax.plot(np.arange(len(v)) * 50, v, label=k.replace("_", " "))
    ax.set_xlabel("gradient step")
    ax.set_ylabel("training loss (mean of 50 steps)")
    ax.legend()
    ax.set_title("training")
    ax = axes[1]
    res = p["results"]["greedy"]
    metrics = ["exact_match", "verb", "object", "direction", "relation", "reference", "auc"]
    width = 0.38
    for i, group in enumerate(("seen", "heldout_combinations")):
        r = res.get(group, {})
        vals = []
        for m in metrics:
            if m in ("exact_match", "auc"):
                vals.append(r.get(m, np.nan))
            else:
                vals.append(r.get("slot_accuracy", {}).get(m, np.nan))
        ax.bar(np.arange(len(metrics)) + (i - 0.5) * width, vals, width,
               label=group.replace("_", " "))  # fmt: skip
    ax.set_xticks(np.arange(len(metrics)), [m.replace("_", " ") for m in metrics], rotation=20)
    ax.set_ylim(0, 1)
    ax.set_title("held-out episodes (greedy captions; reward-model AUC)")
    ax.legend()
    save_figure(name, fig, info)


if __name__ == "__main__":
    raise SystemExit(main())

"""``lcrl demo``: build scenes, run scripted and random episodes, caption what they achieved.

The demo exercises the whole foundation on its defaults, with no server and no download:

1. makes a compositional instruction split for the 2D families and saves it;
2. embeds every instruction with the frozen text encoder and checks how often a paraphrase's
   nearest training instruction (by cosine similarity) has the same meaning;
3. runs episodes on the language-goal 2D tabletop, half with the scripted controller and
   half with random actions, and captions every step with the rule captioner: the scripted
   success rate per family shows the families are achievable and recognised, the random
   episodes' captions show what hindsight relabelling has to work with;
4. writes ``summary.json``, ``report.md``, ``episodes.png`` (filmstrips with instruction
   and captions) and ``families.png`` into the output folder, with the resolved config.
"""

from __future__ import annotations

import json
import textwrap
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from gymnasium.wrappers import TimeLimit
from tqdm import tqdm

from captioner.grammar import FAMILIES_2D
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner
from captioner.scripted import ScriptedController2D
from captioner.splits import SPLIT_SETS, make_split
from envs.tabletop2d import Tabletop2DEnv
from lcrl.errors import LcrlError
from lcrl.text_encoder import FrozenTextEncoder, TextEncoderConfig


@dataclass
class DemoConfig:
    """Caption scripted and random episodes on the fast 2D tabletop and write a report."""

    out: str = "runs/demo"
    """Output folder (created; existing files in it are overwritten)."""
    episodes: int = 200
    """Episodes to run, alternating scripted controller and random actions."""
    max_steps: int = 50
    """Steps per episode."""
    seed: int = 0
    """Seed of the episode layouts and random actions."""
    split_seed: int = 0
    """Seed of the instruction split."""
    image_size: int = 96
    """Side of the rendered frames in the filmstrip figure."""
    text_encoder: TextEncoderConfig = field(default_factory=TextEncoderConfig)
    """Frozen text encoder."""


def _validate(cfg: DemoConfig) -> None:
    if cfg.episodes < 2:
        raise LcrlError(
            f"--episodes must be at least 2 (one scripted, one random), got {cfg.episodes}"
        )
    if cfg.max_steps < 1:
        raise LcrlError(f"--max-steps must be positive, got {cfg.max_steps}")
    if not 32 <= cfg.image_size <= 512:
        raise LcrlError(f"--image-size must be between 32 and 512, got {cfg.image_size}")


def _paraphrase_check(encoder: FrozenTextEncoder, split) -> dict:
    """Nearest training instruction of each paraphrase / held-out instruction by cosine."""
    train = list(split.texts("train"))
    train_meanings = split.instructions("train")
    emb_train = encoder.encode(train)
    result: dict = {}
    for name in ("paraphrase", "heldout"):
        texts = list(split.texts(name))
        emb = encoder.encode(texts)
        nearest = np.argmax(emb @ emb_train.T, axis=1)
        meanings = split.instructions(name)
        same_meaning = [train_meanings[k] == m for k, m in zip(nearest, meanings, strict=True)]
        same_family = [
            train_meanings[k].family == m.family for k, m in zip(nearest, meanings, strict=True)
        ]
        result[name] = {
            "count": len(texts),
            "nearest_same_meaning": float(np.mean(same_meaning)),
            "nearest_same_family": float(np.mean(same_family)),
            "examples": [
                {"text": texts[k], "nearest_train": train[int(nearest[k])]}
                for k in range(0, len(texts), max(1, len(texts) // 5))
            ][:5],
        }
    return result


def _run_episodes(cfg: DemoConfig, split) -> tuple[list[dict], list[list[np.ndarray]]]:
    base = Tabletop2DEnv(image=True, image_size=cfg.image_size)
    wrapper = LanguageGoalWrapper(base, split=split, families=FAMILIES_2D)
    env = TimeLimit(wrapper, max_episode_steps=cfg.max_steps)
    captioner = RuleCaptioner(FAMILIES_2D)
    scripted = ScriptedController2D()
    env.action_space.seed(cfg.seed)
    records, films = [], []
    for ep in tqdm(range(cfg.episodes), desc="episodes", unit="ep"):
        policy = "scripted" if ep % 2 == 0 else "random"
        obs, _ = env.reset(seed=cfg.seed + ep)
        s0, meaning = wrapper.s0, wrapper.meaning
        frames = [obs["image"]]
        achieved: set[str] = set()
        success, steps, done = False, 0, False
        while not done:
            if policy == "scripted":
                action = scripted.act(meaning, s0, base.scene())
            else:
                action = env.action_space.sample()
            obs, _, terminated, truncated, info = env.step(action)
            steps += 1
            frames.append(obs["image"])
            achieved |= {i.text for i in captioner.caption(s0, base.scene())}
            success = success or bool(info["is_success"])
            done = terminated or truncated
        records.append(
            {
                "episode": ep,
                "policy": policy,
                "instruction": wrapper.instruction,
                "family": meaning.family,
                "success": success,
                "steps": steps,
                "achieved": sorted(achieved),
            }
        )
        if policy == "scripted" and len(films) < 4:
            films.append(frames)
    return records, films


def _summarise(records: list[dict]) -> dict:
    out: dict = {}
    for policy in ("scripted", "random"):
        recs = [r for r in records if r["policy"] == policy]
        by_family = defaultdict(list)
        for r in recs:
            by_family[r["family"]].append(r["success"])
        caption_families = Counter(a.split()[0] for r in recs for a in r["achieved"])
        out[policy] = {
            "episodes": len(recs),
            "success_rate": float(np.mean([r["success"] for r in recs])) if recs else 0.0,
            "success_by_family": {
                f: {"episodes": len(v), "success_rate": float(np.mean(v))}
                for f, v in sorted(by_family.items())
            },
            "episodes_with_any_caption": float(np.mean([bool(r["achieved"]) for r in recs])),
            "mean_captions_per_episode": float(np.mean([len(r["achieved"]) for r in recs])),
            "captions_by_family": dict(sorted(caption_families.items())),
        }
    return out


def _figures(out: Path, records: list[dict], films: list[list[np.ndarray]], summary: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scripted = [r for r in records if r["policy"] == "scripted"]
    n_cols = 6
    fig, axes = plt.subplots(
        len(films), n_cols, figsize=(2.0 * n_cols, 2.8 * len(films)), squeeze=False
    )
    for row, (frames, rec) in enumerate(zip(films, scripted, strict=False)):
        picks = np.linspace(0, len(frames) - 1, n_cols).round().astype(int)
        for col, k in enumerate(picks):
            ax = axes[row, col]
            ax.imshow(frames[k])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"t={k}", fontsize=8)
        status = "success" if rec["success"] else "failure"
        achieved = "; ".join(rec["achieved"][:3]) or "nothing"
        if len(rec["achieved"]) > 3:
            achieved += f" (+{len(rec['achieved']) - 3} more)"
        axes[row, 0].set_ylabel(f"ep {rec['episode']}", fontsize=8)
        text = f'"{rec["instruction"]}" ({status}). Captioned: {achieved}'
        axes[row, 0].annotate(
            "\n".join(textwrap.wrap(text, 110)),
            xy=(0, 1.2),
            xycoords="axes fraction",
            fontsize=8,
            va="bottom",
            annotation_clip=False,
        )
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.02, top=0.9, hspace=0.8, wspace=0.08)
    fig.savefig(out / "episodes.png", dpi=90)
    plt.close(fig)

    fams = list(FAMILIES_2D)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.5))
    width = 0.38
    for k, policy in enumerate(("scripted", "random")):
        rates = [
            summary[policy]["success_by_family"].get(f, {}).get("success_rate", 0.0) for f in fams
        ]
        a1.bar(np.arange(len(fams)) + (k - 0.5) * width, rates, width, label=policy)
        counts = [summary[policy]["captions_by_family"].get(f, 0) for f in fams]
        a2.bar(np.arange(len(fams)) + (k - 0.5) * width, counts, width, label=policy)
    a1.set_xticks(range(len(fams)), fams)
    a1.set_ylim(0, 1)
    a1.set_ylabel("success rate on the given instruction")
    a1.legend()
    a2.set_xticks(range(len(fams)), fams)
    a2.set_ylabel("distinct captions (all episodes)")
    a2.set_title("what hindsight relabelling can use")
    fig.tight_layout()
    fig.savefig(out / "families.png", dpi=90)
    plt.close(fig)


def _report(cfg: DemoConfig, split, para: dict, summary: dict, elapsed: float) -> str:
    lines = [
        "# lcrl demo report",
        "",
        f"{cfg.episodes} episodes of {cfg.max_steps} steps on the 2D tabletop "
        f"(seed {cfg.seed}), {elapsed:.1f} s.",
        "",
        "## Instruction split",
        "",
        "```",
        split.summary(),
        "```",
        "",
        "## Episodes",
        "",
        "| policy | family | episodes | success rate |",
        "|---|---|---|---|",
    ]
    for policy in ("scripted", "random"):
        for fam, v in summary[policy]["success_by_family"].items():
            lines.append(f"| {policy} | {fam} | {v['episodes']} | {v['success_rate']:.2f} |")
    lines += [
        "",
        "Captions (instructions the rule captioner found achieved at some step):",
        "",
    ]
    for policy in ("scripted", "random"):
        s = summary[policy]
        lines.append(
            f"- {policy}: {s['mean_captions_per_episode']:.1f} distinct captions per episode, "
            f"{100 * s['episodes_with_any_caption']:.0f}% of episodes achieved something; "
            f"by family {s['captions_by_family']}"
        )
    lines += ["", "## Frozen text encoder", ""]
    for name, v in para.items():
        lines.append(
            f"- {name}: nearest training instruction has the same meaning for "
            f"{100 * v['nearest_same_meaning']:.0f}% and the same family for "
            f"{100 * v['nearest_same_family']:.0f}% of {v['count']}"
        )
        for ex in v["examples"][:3]:
            lines.append(f'  - "{ex["text"]}" -> "{ex["nearest_train"]}"')
    lines += ["", "![episodes](episodes.png)", "", "![families](families.png)", ""]
    return "\n".join(lines)


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo and write its outputs; returns the summary dictionary."""
    _validate(cfg)
    start = time.perf_counter()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(asdict(cfg), indent=1) + "\n")
    split = make_split(cfg.split_seed, FAMILIES_2D)
    split.save(out / "split.json")
    print(split.summary())

    print(f"loading text encoder {cfg.text_encoder.model} ...")
    encoder = FrozenTextEncoder(cfg.text_encoder)
    all_texts = [t for name in SPLIT_SETS for t in split.texts(name)]
    encoder.encode(all_texts)
    para = _paraphrase_check(encoder, split)

    records, films = _run_episodes(cfg, split)
    summary = _summarise(records)
    elapsed = time.perf_counter() - start
    result = {
        "split_fingerprint": split.fingerprint(),
        "text_encoder": {
            "model": cfg.text_encoder.model,
            "dim": encoder.dim,
            "texts_encoded": encoder.num_encoded,
        },
        "paraphrase_check": para,
        "episodes": summary,
        "elapsed_s": elapsed,
    }
    (out / "summary.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "episodes.json").write_text(json.dumps(records, indent=1) + "\n")
    _figures(out, records, films, summary)
    (out / "report.md").write_text(_report(cfg, split, para, summary, elapsed))

    for policy in ("scripted", "random"):
        s = summary[policy]
        per = ", ".join(f"{f} {v['success_rate']:.2f}" for f, v in s["success_by_family"].items())
        print(
            f"{policy:>8}: success {s['success_rate']:.2f} ({per}); "
            f"{s['mean_captions_per_episode']:.1f} captions/episode"
        )
    p = para["paraphrase"]
    print(
        f"paraphrases whose nearest training instruction means the same: "
        f"{100 * p['nearest_same_meaning']:.0f}%"
    )
    print(
        f"outputs in {out}/: report.md, summary.json, episodes.json, episodes.png, "
        f"families.png, split.json, config.json"
    )
    return result

"""Relabelling demonstrations in hindsight with the rule captioner or the learned models
(``lcrl demos relabel``)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from envs.scene import SceneState
from lcrl.demos import GIVEN, HINDSIGHT, DemoDataset, append_segments
from lcrl.errors import LcrlError
from train.training.demo_episodes import family_of, scenes_from_arrays


def _split_of(meta: Mapping[str, Any], path: Path) -> Any:
    """The compositional split a dataset was recorded with (from its meta)."""
    from captioner.splits import make_split
    from train.environments.simulators import ENVS, canonical_kind

    env = meta.get("env")
    kind = canonical_kind(str(env.get("kind"))) if isinstance(env, dict) else ""
    if kind not in ENVS or not ENVS[kind].families:
        raise LcrlError(
            f"{path} does not say which tabletop it was recorded on (no env in its meta): "
            "relabel needs a file written by lcrl demos record"
        )
    families = meta.get("split_families") or ENVS[kind].families
    split = make_split(int(meta.get("split_seed", env.get("split_seed", 0))), tuple(families))
    want = meta.get("split_fingerprint")
    if want and split.fingerprint() != want:
        raise LcrlError(
            f"{path} was recorded with split {want}, but this lcrl makes "
            f"{split.fingerprint()} from its seed: the split code changed since"
        )
    return split


def relabel(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    captioner: str = "rule",
    starts_every: int = 0,
    train_only: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    beam: int = 3,
    min_logprob: float = -1.0,
    device: str = "cpu",
) -> dict[str, Any]:
    """Add hindsight segments for everything each episode achieved (DIAL-style).

    For every episode and every segment start (0, and every ``starts_every`` steps when
    positive) the captioner reads the change from the start to each later step; each
    instruction it finds gives the segment ``[start, t]`` with ``t`` the first step where
    it holds (instructions that already hold at the start are skipped, and so is a
    segment identical to a given one). Existing hindsight segments of ``src`` are
    replaced. The result is written atomically to ``dst`` (which may be ``src``).

    Args:
        src: a dataset recorded by :func:`record`.
        dst: where to write the relabelled dataset.
        captioner: ``rule`` (the rule captioner on the stored privileged scene) or the
            path of a learned-captioner checkpoint (``lcrl caption train``), which reads
            the stored camera frames and proprioception.
        starts_every: also start segments every this many steps (0: only at step 0).
            Later starts judge the instruction against that step's observation (the
            displacement features of the observation still count from the reset).
        train_only: only add instructions of the split's training set for the recorded
            families, so that held-out combinations never enter training data.
        overwrite: replace an existing ``dst`` (other than ``src``).
        progress: show a progress bar.
        beam: beam width of the learned captioner.
        min_logprob: learned captions less likely than this are skipped.
        device: torch device of the learned captioner.

    Returns:
        Counts (also printed by the CLI): episodes, given and added hindsight segments,
        distinct instructions before and after, per-family segments, segments per
        episode, and how many failed episodes gained at least one instruction.
    """
    from tqdm import tqdm

    from captioner.rule import RuleCaptioner

    src, dst = Path(src), Path(dst)
    if starts_every < 0:
        raise LcrlError(f"--starts-every must be >= 0, got {starts_every}")
    same = dst.exists() and src.exists() and os.path.samefile(src, dst)
    if dst.exists() and not same and not overwrite:
        raise LcrlError(f"{dst} exists; pass --overwrite to replace it")
    with DemoDataset(src) as data:
        meta = data.meta
        split = _split_of(meta, src)
        families = tuple(meta.get("families") or meta["env"].get("families", ()))
        pairs = [(t, m) for t, m in zip(split.train, split.instructions("train"), strict=True)]
        if not train_only:
            pairs += list(zip(split.heldout, split.instructions("heldout"), strict=True))
        allowed = {t for t, m in pairs if m.family in families}
        heldout = set(split.heldout)
        learned = captioner != "rule"
        labeller = None
        if learned:
            labeller = _learned_labeller(
                captioner, data, sorted(allowed), beam, min_logprob, device
            )
        if not learned and "positions" not in data.scene_keys:
            raise LcrlError(
                f"{src} stores no privileged scene (it was not recorded by lcrl demos "
                "record): the rule captioner cannot run; use a learned captioner on its images"
            )
        rule = RuleCaptioner(families)
        given = data.segments(hindsight=False)
        given_keys = {tuple(r[:4]) for r in given.tolist()}
        rows: list[tuple[int, int, int, str]] = []
        gained = np.zeros(data.num_episodes, bool)
        bar = tqdm(range(data.num_episodes), disable=not progress, desc="relabel", unit="ep")
        for e in bar:
            ep = data.episode(e)
            t_len = int(ep["length"])
            starts = [0]
            if starts_every > 0:
                starts += list(range(starts_every, t_len, starts_every))
            if labeller is None:
                found = _rule_segments(rule, scenes_from_arrays(ep["scene"]), starts, allowed)
            else:
                found = _learned_segments(labeller, ep["obs"], starts)
            for start, end, text in found:
                iid = data.instructions.index(text) if text in data.instructions else -1
                if (e, start, end, iid) in given_keys:
                    continue  # the given segment, found again
                rows.append((e, start, end, text))
                gained[e] = True
        failed = data.episode_success == 0
        before = data.counts()
        table = list(data.instructions)
    leaked = sorted({t for _, _, _, t in rows if t in heldout}) if train_only else []
    if leaked:  # pragma: no cover - a bug, never a user mistake
        raise RuntimeError(f"held-out instructions in a train-only relabelling: {leaked[:3]}")
    settings = {
        "captioner": captioner,
        "starts_every": starts_every,
        "train_only": train_only,
        "source": str(src),
    }
    out = append_segments(src, rows, dst, drop_hindsight=True, meta={"relabel": settings})
    with DemoDataset(out) as result:
        seg = result.segments()
        after = result.counts()
        texts = result.instructions
    per_family: dict[str, dict[str, int]] = {}
    for iid, origin in seg[:, 3:5].tolist():
        row = per_family.setdefault(family_of(texts[iid]), {"given": 0, "hindsight": 0})
        row["given" if origin == GIVEN else "hindsight"] += 1
    n_eps = int(before["episodes"])
    counts = {
        "episodes": n_eps,
        "failed_episodes": int(failed.sum()),
        "failed_with_hindsight": int((failed & gained).sum()),
        "given_segments": int(np.sum(seg[:, 4] == GIVEN)),
        "hindsight_segments": int(np.sum(seg[:, 4] == HINDSIGHT)),
        "instructions_before": int(before["distinct_instructions"]["given"]),
        "instructions_after": int(after["distinct_instructions"]["all"]),
        "new_instructions": len(set(texts) - set(table)),
        "segments_per_episode": len(seg) / max(1, n_eps),
        "per_family": dict(sorted(per_family.items())),
        **settings,
        "out": str(out),
    }
    return counts


def _rule_segments(
    rule: Any, scenes: Sequence[SceneState], starts: Sequence[int], allowed: set[str]
) -> list[tuple[int, int, str]]:
    """(start, first step, text) of every allowed instruction the scenes achieve."""
    out = []
    for start in starts:
        s0 = scenes[start]
        already = {i.text for i in rule.caption(s0, s0)}
        first: dict[str, int] = {}
        for t in range(start + 1, len(scenes)):
            for ins in rule.caption(s0, scenes[t]):
                text = ins.text
                if text in allowed and text not in already and text not in first:
                    first[text] = t
        out.extend((start, t, text) for text, t in sorted(first.items(), key=lambda x: x[1]))
    return out


def _learned_labeller(
    path: str, data: DemoDataset, table: list[str], beam: int, min_logprob: float, device: str
) -> Any:
    from captioner.learned import LearnedCaptioner, LearnedLabeller

    if "image" not in data.obs_shapes:
        raise LcrlError(
            f"a learned captioner reads camera frames and {data.path} has none: record with "
            "--images, or relabel with --captioner rule"
        )
    if not Path(path).exists():
        raise LcrlError(
            f"--captioner must be 'rule' or a learned-captioner checkpoint; {path} does not exist"
        )
    models = LearnedCaptioner.load(path, device=device)
    shape = data.obs_shapes["image"]
    if tuple(shape) != tuple(models.frame_shape):
        raise LcrlError(
            f"the captioner reads {'x'.join(map(str, models.frame_shape))} frames; {data.path} "
            f"has {'x'.join(map(str, shape))} (record with --image-size {models.frame_shape[0]})"
        )
    if "proprio" not in data.obs_shapes and "observation" not in data.obs_shapes:
        raise LcrlError(f"{data.path} stores no proprioception for the learned captioner")
    return LearnedLabeller(
        models,
        table,
        len(table),
        captioner=True,
        reward=False,
        min_logprob=min_logprob,
        beam=beam,
    )


def _learned_segments(
    labeller: Any, obs: Mapping[str, np.ndarray], starts: Sequence[int]
) -> list[tuple[int, int, str]]:
    frames = np.asarray(obs["image"], np.uint8)
    dim = labeller.models.proprio_dim
    proprio = obs["proprio"] if "proprio" in obs else obs["observation"][:, :dim]
    proprio = np.asarray(proprio, np.float32)
    if proprio.shape[1] != dim:
        raise LcrlError(
            f"the captioner reads {dim} proprioception values; the file stores {proprio.shape[1]}"
        )
    out = []
    for start in starts:
        labels = labeller.labels(frames[start:], proprio[start:])
        first: dict[str, int] = {}
        for k, ids in enumerate(labels):
            for i in ids:
                text = labeller.table[i]
                first.setdefault(text, start + k)
        out.extend((start, t, text) for text, t in first.items() if t > start)
    return out


def format_relabel(counts: Mapping[str, Any]) -> str:
    """The counts of :func:`relabel` for the terminal."""
    n = counts["starts_every"]
    every = f" and every {n} steps" if n else ""
    lines = [
        f"relabelled {counts['episodes']} episodes with the {counts['captioner']} captioner "
        f"(segments from step 0{every}; "
        f"{'training instructions only' if counts['train_only'] else 'held-out ones included'})",
        f"  segments: {counts['given_segments']} given + {counts['hindsight_segments']} "
        f"hindsight ({counts['segments_per_episode']:.2f} per episode)",
        f"  distinct instructions: {counts['instructions_before']} before, "
        f"{counts['instructions_after']} after",
        f"  failed episodes that gained an instruction: {counts['failed_with_hindsight']} of "
        f"{counts['failed_episodes']}",
        "  per family (given / hindsight):",
    ]
    for fam, row in counts["per_family"].items():
        lines.append(f"    {fam:<6} {row['given']:>6} / {row['hindsight']}")
    lines.append(f"saved {counts['out']}")
    return "\n".join(lines)

"""Training the models a config asks for (:func:`train_models`, ``lcrl caption train``)."""

from __future__ import annotations

import functools
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from captioner.dataset import CaptionDataset
from captioner.grammar import Instruction, try_parse
from captioner.learned.data import CaptionTrainConfig, _Pairs, _Sampler, onset_delays
from captioner.learned.factored import SlotPredicates, train_factored
from captioner.learned.models import Captioner, RewardModel, SlotPairEncoder
from captioner.learned.saved import LearnedCaptioner
from captioner.learned.vocabulary import NONE_TEXT, PAD, Vocabulary
from lcrl.errors import LcrlError
from lcrl.perception import Perception, load_model


def train_models(cfg: CaptionTrainConfig) -> Path:
    """Train the models a config asks for and save them; returns the checkpoint path."""
    cfg.validate()
    from tqdm import tqdm

    out = Path(cfg.out)
    if (out / "meta.json").exists() and not cfg.overwrite:
        raise LcrlError(f"{out} already holds a checkpoint; pass --overwrite to replace it")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator(device=cfg.device).manual_seed(cfg.seed)
    device = torch.device(cfg.device)
    mcfg = cfg.model
    perception = _perception(cfg)
    data = CaptionDataset(cfg.data)
    try:
        if perception is not None:
            _check_perception(perception, data)
        lc = LearnedCaptioner(
            Vocabulary.from_grammar(),
            data.instructions,
            data.instruction_set,
            data.frame_shape,
            data.proprio.shape[1],
            mcfg,
            np.zeros(data.proprio.shape[1], np.float32),  # set from the training pairs below
            np.ones(data.proprio.shape[1], np.float32),
            cfg.text_model,
            {"dataset": str(cfg.data), "dataset_meta": data.meta, "train": asdict(cfg)},
            cfg.device,
        )
        lc.perception = perception
        vocab = lc.vocab
        perceive = (
            functools.partial(_perceive_dataset, lc, data, progress=cfg.progress)
            if perception
            else None
        )
        pairs = _Pairs(data, cfg.val_fraction, cfg.seed, perceive)
        lc.meta["val_episodes"] = pairs.val_episodes.tolist()
        lc.p_mean, lc.p_std = pairs.p_mean, pairs.p_std
        table = [_parse(t) for t in data.instructions]
        sampler = _Sampler(pairs, table, rng, cfg.near_window, onset_delays(cfg.onset_delay))
        pad = 0 if perception is not None else cfg.augment_pad  # slots are not shifted
        history: dict[str, list[float]] = {}
        if mcfg.head == "factored":
            assert perception is not None  # validated: the head needs encoder=perception
            model_f = SlotPredicates(perception, lc.proprio_dim, mcfg.hidden, mcfg.use_proprio)
            _fit_encoder(model_f, pairs, sampler, device)
            model_f.to(device)
            history["factored_loss"] = train_factored(
                model_f,
                pairs,
                sampler,
                table,
                pairs.seen,
                cfg.steps,
                cfg.batch_size,
                cfg.lr,
                cfg.none_fraction,
                cfg.near_negative_fraction,
                device,
                cfg.progress,
            )
            lc.factored = model_f
        if "captioner" in cfg.models and mcfg.head == "sequence":
            tokens = torch.as_tensor(
                [vocab.encode(t, mcfg.max_len) for t in data.instructions]
                + [vocab.encode(NONE_TEXT, mcfg.max_len)],
                device=device,
            )
            none_row = len(data.instructions)
            model = Captioner(data.frame_shape, lc.proprio_dim, len(vocab), mcfg, perception)
            _fit_encoder(model.encoder, pairs, sampler, device)
            model.to(device)
            opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], cfg.lr)
            losses = []
            bar = tqdm(range(cfg.steps), disable=not cfg.progress, desc="captioner")
            for _ in bar:
                idx, targets = sampler.caption_batch(
                    cfg.batch_size, cfg.none_fraction, cfg.near_negative_fraction
                )
                rows = torch.as_tensor(
                    [none_row if t is None else t for t in targets], device=device
                )
                seq = tokens[rows]
                ctx = model.encoder(*_augment(pairs.tensors(idx, device), pad, gen))
                logits = model(ctx, seq[:, :-1])
                loss = F.cross_entropy(
                    logits.reshape(-1, logits.shape[-1]), seq[:, 1:].reshape(-1), ignore_index=PAD
                )
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(loss.item())
                bar.set_postfix_str(f"loss {np.mean(losses[-50:]):.3f}", refresh=False)
            lc.captioner = model
            history["captioner_loss"] = losses
        if "reward" in cfg.models and mcfg.head == "sequence":
            seen_texts = [
                t
                for t, s in zip(data.instructions, data.instruction_set, strict=True)
                if s == "train"
            ]
            emb = lc.encode_texts(data.instructions)
            model_r = RewardModel(data.frame_shape, lc.proprio_dim, emb.shape[1], mcfg, perception)
            model_r.set_text_stats(lc.encode_texts(seen_texts).cpu().numpy())
            _fit_encoder(model_r.encoder, pairs, sampler, device)
            model_r.to(device)
            lc.meta["text_dim"] = int(emb.shape[1])
            opt = torch.optim.Adam([q for q in model_r.parameters() if q.requires_grad], cfg.lr)
            losses = []
            bar = tqdm(range(cfg.steps), disable=not cfg.progress, desc="reward model")
            for _ in bar:
                idx, ids, y = sampler.reward_batch(
                    cfg.batch_size, cfg.hard_negative_fraction, cfg.near_negative_fraction
                )
                ctx = model_r.context(*_augment(pairs.tensors(idx, device), pad, gen))
                logit = model_r(ctx, emb[torch.as_tensor(ids, device=device)])
                loss = F.binary_cross_entropy_with_logits(logit, torch.as_tensor(y, device=device))
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(loss.item())
                bar.set_postfix_str(f"loss {np.mean(losses[-50:]):.3f}", refresh=False)
            lc.reward = model_r
            history["reward_loss"] = losses
        lc.meta["history"] = {
            k: [float(np.mean(v[i : i + 50])) for i in range(0, len(v), 50)]
            for k, v in history.items()
        }
        return lc.save(out)
    finally:
        data.close()


def _perceive_dataset(
    lc: LearnedCaptioner, data: CaptionDataset, frames: Any, proprio: np.ndarray, progress: bool
) -> np.ndarray:
    """Perception's estimates of every frame of a dataset, as the models read them (with
    ``first_presence``, each frame with its episode's first-frame presence flags)."""
    if not lc.cfg.first_presence:
        return lc.perceive(frames, proprio, progress=progress)
    starts = np.asarray(data.episode_start[:-1], np.int64)
    assert lc.perception is not None
    present = lc.perception.presence(lc.perceive(data.read_frames(starts), proprio[starts]))
    episode = data.episode_of(np.arange(data.num_observations))
    return lc.perceive(frames, proprio, progress=progress, present=present[episode])


def _perception(cfg: CaptionTrainConfig) -> Perception | None:
    """The frozen perception model of ``model.encoder=perception`` (None otherwise)."""
    if cfg.model.encoder != "perception":
        if cfg.perception:
            raise LcrlError("--perception is read by --model.encoder perception only")
        return None
    if not cfg.perception:
        raise LcrlError(
            "--model.encoder perception reads a perception model: pass --perception MODEL "
            "(lcrl perception train --out)"
        )
    model = load_model(cfg.perception, cfg.device)[0]
    model.eval()
    return model


def _check_perception(model: Perception, data: CaptionDataset) -> None:
    """Refuse a perception model of another camera or object set than the dataset's."""
    layout = data.meta.get("slot_layout")
    if tuple(data.frame_shape) != tuple(model.frame_shape):
        raise LcrlError(
            f"the perception model reads {model.frame_shape} frames; {data.path} has "
            f"{tuple(data.frame_shape)} frames (collect at --image-size {model.frame_shape[0]})"
        )
    if layout is not None and list(map(int, layout)) != model.layout.to_list():
        raise LcrlError(
            f"the perception model reads the object slots {model.layout.to_list()}; "
            f"{data.path} was collected with {list(layout)} (another simulator or object set)"
        )


def _fit_encoder(encoder: nn.Module, pairs: _Pairs, sampler: _Sampler, device: Any) -> None:
    """Fit the input standardisation of a model over perception's slots on training
    pairs (frame encoders need nothing)."""
    if not isinstance(encoder, SlotPairEncoder | SlotPredicates):
        return
    idx = np.concatenate([sampler.labelled_arr, sampler.empty_arr])
    if len(idx) > 20_000:
        idx = np.sort(sampler.rng.choice(idx, 20_000, replace=False))
    with torch.no_grad():
        encoder.fit(*pairs.tensors(idx, torch.device("cpu"))[:2])


def _augment(
    inputs: tuple[torch.Tensor, ...], pad: int, gen: torch.Generator
) -> tuple[torch.Tensor, ...]:
    """Shift both frames of each pair by one random offset (DrQ's random shift)."""
    if pad <= 0:
        return inputs
    from lcrl.nets import random_shift

    first, current, p0, p = inputs
    both = random_shift(torch.cat([first, current], -1), pad, gen)
    c = first.shape[-1]
    return both[..., :c], both[..., c:], p0, p


def _parse(text: str) -> Instruction:
    ins = try_parse(text)
    if ins is None:
        raise LcrlError(f"dataset instruction {text!r} does not parse")
    return ins

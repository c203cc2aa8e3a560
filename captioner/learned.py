"""Learned captioner and learned reward model over camera frames.

Both read a pair of camera frames, the episode's first frame and the current one, and
optionally the robot's proprioception at both; they learn from a caption dataset
(:mod:`captioner.dataset`) labelled by the rule captioner, so that relabelling can later
run where no privileged state exists.

* :class:`FramePairEncoder`: by default (``spatial``) convolutions over the first frame,
  the current frame, their difference and two coordinate channels, pooled by each
  channel's maximum and its spatial-softmax keypoint. Pooling instead of a flattened map
  makes "the red cube moved left" read the same wherever on the table it happens; on the
  2D tabletop it halved the gap between training and held-out episodes (see the README).
* :class:`Captioner`: the encoder, then a GRU that writes the instruction word by word
  over the grammar's vocabulary (so it can produce word combinations it never saw as a
  whole). An observation that achieved
  nothing is captioned ``<none>``. Greedy and beam decoding; a caption's log-likelihood is
  returned with it, so unsure captions can be dropped by a threshold.
* :class:`RewardModel`: the probability that an instruction is satisfied by the change
  from the first frame to the current one. The instruction enters as the frozen text
  encoder's embedding (standardised over the training instructions), so any free text
  can be scored; it scales and shifts the channels of the late convolutions (FiLM), so it
  chooses what to look for before the map is pooled.

Training (:func:`train_models`) uses the dataset's training episodes; held-out
instructions (the split's held-out word combinations) are never used as targets, positives
or negatives. :func:`evaluate_models` reports, on held-out episodes and separately on
observations that achieved a held-out combination: exact match, per-slot accuracy (verb,
object, direction, relation, reference object), BLEU-4, and the reward model's precision,
recall and ROC AUC.
"""

from __future__ import annotations

import functools
import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from captioner.dataset import CaptionDataset
from captioner.grammar import FAMILIES, Instruction, all_instructions, try_parse
from lcrl.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from lcrl.errors import LcrlError
from lcrl.nets import spatial_softmax
from lcrl.perception import Perception, embedded_meta, load_model

SPECIALS: tuple[str, ...] = ("<pad>", "<bos>", "<eos>", "<none>")
#: Steps around an achievement whose observations count as near misses in evaluation.
NEAR_WINDOW = 10
PAD, BOS, EOS, NONE = 0, 1, 2, 3
NONE_TEXT = "<none>"
CHECKPOINT_KIND = "lcrl-learned-captioner"
MODELS: tuple[str, ...] = ("captioner", "reward")

__all__ = [
    "MODELS",
    "NONE_TEXT",
    "CaptionModelConfig",
    "CaptionTrainConfig",
    "Captioner",
    "LearnedCaptioner",
    "RewardModel",
    "Vocabulary",
    "bleu4",
    "evaluate_models",
    "roc_auc",
    "train_models",
]


# --------------------------------------------------------------------------- vocabulary


class Vocabulary:
    """Words of the grammar's canonical instructions, after the special tokens."""

    def __init__(self, words: Sequence[str]) -> None:
        words = [w for w in words if w not in SPECIALS]
        self.words: list[str] = list(SPECIALS) + sorted(set(words))
        self.index = {w: i for i, w in enumerate(self.words)}

    @classmethod
    def from_grammar(cls, families: Sequence[str] = FAMILIES) -> Vocabulary:
        """Every word of every canonical instruction of ``families``."""
        return cls([w for ins in all_instructions(families) for w in ins.text.split()])

    def __len__(self) -> int:
        return len(self.words)

    def encode(self, text: str, max_len: int) -> list[int]:
        """``<bos> words <eos>`` (``<bos> <none> <eos>`` for :data:`NONE_TEXT`), padded to
        ``max_len`` tokens."""
        words = [NONE_TEXT] if text == NONE_TEXT else text.split()
        unknown = [w for w in words if w not in self.index]
        if unknown:
            raise LcrlError(f"words outside the captioner's vocabulary: {unknown}")
        ids = [BOS, *(self.index[w] for w in words), EOS]
        if len(ids) > max_len:
            raise LcrlError(f"{text!r} is longer than {max_len - 2} words")
        return ids + [PAD] * (max_len - len(ids))

    def decode(self, ids: Sequence[int]) -> str:
        """Text of a generated id sequence (up to ``<eos>``; ``<bos>`` skipped)."""
        out = []
        for i in ids:
            i = int(i)
            if i in (EOS, PAD):
                break
            if i == BOS:
                continue
            out.append(self.words[i])
        return " ".join(out)


# --------------------------------------------------------------------------- models


@dataclass
class CaptionModelConfig:
    """Sizes of the captioner and the reward model."""

    encoder: str = "spatial"
    """Frame-pair encoder: ``spatial`` (convolutions over the first frame, the current
    frame, their difference and two coordinate channels, pooled by a per-channel maximum
    and a spatial softmax, so that what moved is read the same wherever it is) or
    ``flatten`` (the feature map flattened into a linear layer: more parameters, tends to
    memorise its training episodes) or ``perception`` (a frozen perception model,
    ``lcrl perception train``, estimates the object slots of both frames; an MLP reads
    them with each object's position relative to the gripper and its displacement between
    the frames: what the policy reads, learned once)."""
    channels: tuple[int, ...] = (32, 32, 64, 64)
    """Channels of the 3x3 convolutions. ``spatial``: strides 2, 1, 2, 1, ...; the reward
    model conditions the second half of them on the instruction (FiLM). ``flatten``: the
    first three have stride 2."""
    strides: tuple[int, ...] = ()
    """``spatial``: stride of each convolution (empty: 2, 1, 2, 1, ...). A first stride of
    1 keeps every pixel of small objects for the first layer (their shape)."""
    features: int = 256
    """Width of the frame-pair features."""
    use_proprio: bool = True
    """Also read the robot's proprioception at the first and the current frame."""
    embed: int = 64
    """Captioner word-embedding width."""
    hidden: int = 256
    """Captioner GRU width, and the reward model's MLP width."""
    text_features: int = 128
    """Reward model: width of the projection of the frozen text embedding."""
    max_len: int = 12
    """Captions are at most ``max_len - 2`` words."""
    slot_query: bool = True
    """Reward model over ``perception``: the instruction also picks the object slot it
    names (attention with the instruction as the query) and the model reads that slot's
    own inputs, not only the frame pair's features pooled the same way for every
    instruction (which follow whatever object moved, so that "reach the red cube" could
    be read into a pushed blue one). Checkpoints saved before the option read without."""
    first_presence: bool = True
    """Over ``perception``: the current frame's presence flags are those perception reads
    in the episode's first frame (the tabletops place their objects at reset, and the arm
    over the table can hide one later), as the policy acting through perception reads
    them. Without it an object the arm hides is estimated absent, at position 0, and the
    models read a change that did not happen. Checkpoints saved before the option read
    without."""

    def validate(self) -> None:
        if self.encoder not in ENCODERS:
            raise LcrlError(f"model.encoder must be one of {ENCODERS}, got {self.encoder!r}")
        if not self.channels or any(int(c) <= 0 for c in self.channels):
            raise LcrlError(f"model.channels must be positive widths, got {self.channels}")
        if self.encoder == "spatial" and len(self.channels) < 2:
            raise LcrlError("the spatial encoder needs at least two convolutions")
        if self.strides and (
            len(self.strides) != len(self.channels) or any(int(v) < 1 for v in self.strides)
        ):
            raise LcrlError(
                f"model.strides must give one stride >= 1 per convolution ({len(self.channels)}), "
                f"got {self.strides}"
            )


ENCODERS: tuple[str, ...] = ("spatial", "flatten", "perception")


class FramePairEncoder(nn.Module):
    """(first frame, current frame) plus proprioception -> frame-pair features.

    ``spatial``: the two frames, their difference and two coordinate channels go through
    :meth:`early` (text-independent) and :meth:`late` convolutions (which the reward model
    modulates with the instruction), then :meth:`pool` takes each channel's maximum and its
    spatial-softmax keypoint. ``flatten``: the stacked frames' feature map is flattened
    into a linear layer.
    """

    def __init__(self, frame_shape: Sequence[int], proprio_dim: int, cfg: CaptionModelConfig):
        super().__init__()
        cfg.validate()
        h, w, c = (int(v) for v in frame_shape)
        self.kind = cfg.encoder
        self.proprio_dim = proprio_dim if cfg.use_proprio else 0
        chans = [int(v) for v in cfg.channels]
        if self.kind == "flatten":
            layers: list[nn.Module] = []
            ch = 2 * c
            for i, out in enumerate(chans):
                layers += [nn.Conv2d(ch, out, 3, stride=2 if i < 3 else 1, padding=1), nn.ReLU()]
                ch = out
            self.convs = nn.Sequential(*layers)
            with torch.no_grad():
                flat = self.convs(torch.zeros(1, 2 * c, h, w)).numel()
        else:
            self.split = len(chans) // 2
            ch = 3 * c + 2
            convs = []
            strides = [int(v) for v in cfg.strides] or [
                2 if i % 2 == 0 else 1 for i in range(len(chans))
            ]
            for out, stride in zip(chans, strides, strict=True):
                convs.append(nn.Conv2d(ch, out, 3, stride=stride, padding=1))
                ch = out
            self.convs = nn.ModuleList(convs)
            self.late_channels = chans[self.split :]
            self.log_temperature = nn.Parameter(torch.zeros(()))
            with torch.no_grad():
                z = torch.zeros(1, h, w, c, dtype=torch.uint8)
                e = self.early(z, z)
                self.early_shape = tuple(e.shape[1:])
                self.map_shape = tuple(self.late(e).shape[1:])
            flat = 3 * self.map_shape[0]
        self.head = nn.Sequential(
            nn.Linear(flat + 2 * self.proprio_dim, cfg.features),
            nn.LayerNorm(cfg.features),
            nn.ReLU(),
        )
        self.out_dim = cfg.features

    def early(self, first: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
        """Spatial encoder: the text-independent first half of the convolutions."""
        a = first.permute(0, 3, 1, 2).float() / 255.0
        b = current.permute(0, 3, 1, 2).float() / 255.0
        n, _, hh, ww = a.shape
        ys = torch.linspace(-1.0, 1.0, hh, device=a.device).view(1, 1, hh, 1).expand(n, 1, hh, ww)
        xs = torch.linspace(-1.0, 1.0, ww, device=a.device).view(1, 1, 1, ww).expand(n, 1, hh, ww)
        x = torch.cat([a - 0.5, b - 0.5, 2.0 * (b - a), ys, xs], 1)
        for conv in self.convs[: self.split]:
            x = F.relu(conv(x))
        return x

    def late(self, x: torch.Tensor, film: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
        """Spatial encoder: the second half of the convolutions, each output optionally
        scaled and shifted per channel (``film``: one ``(B, 2C)`` tensor per layer); the
        last output is left before its ReLU (the pooling applies it)."""
        late = self.convs[self.split :]
        for i, conv in enumerate(late):
            x = conv(x)
            if film is not None:
                gamma, beta = film[i].chunk(2, -1)
                x = x * (1.0 + gamma[:, :, None, None]) + beta[:, :, None, None]
            if i < len(late) - 1:
                x = F.relu(x)
        return x

    def pool(self, h: torch.Tensor, p0: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Spatial encoder: per-channel maximum and keypoint of the last map, then the head."""
        temp = self.log_temperature.exp()
        z = torch.cat([F.relu(h.amax((2, 3))), spatial_softmax(h, temp)], -1)
        if self.proprio_dim:
            z = torch.cat([z, p0, p], -1)
        return self.head(z)

    def forward(
        self, first: torch.Tensor, current: torch.Tensor, p0: torch.Tensor, p: torch.Tensor
    ) -> torch.Tensor:
        if self.kind == "spatial":
            return self.pool(self.late(self.early(first, current)), p0, p)
        x = torch.cat([first, current], -1).permute(0, 3, 1, 2).float() / 255.0 - 0.5
        z = self.convs(x).flatten(1)
        if self.proprio_dim:
            z = torch.cat([z, p0, p], -1)
        return self.head(z)


class SlotPairEncoder(nn.Module):
    """(first, current) object slots estimated by a frozen perception model -> features.

    Inputs are perception's estimated observations ``(B, dim)`` of the first and the
    current frame (:meth:`LearnedCaptioner.perceive` computes them from frames; training
    computes them once per dataset frame). Every object slot is read by the same MLP:
    whether the object is on the table, its position relative to the gripper and its
    displacement since the first frame (what a
    reach, a push, a lift is judged on), so what one object teaches serves every other.
    Attention heads pick the slots that matter (a learned embedding of each slot, which
    names its colour and shape, is added to what is picked); the difference between the
    positions the first two heads pick carries the relation of put and stack. With the
    max over slots and the proprioception at both frames, a linear layer gives the
    features. Inputs are standardised with statistics of the training pairs (:meth:`fit`).

    Args:
        perception: the frozen perception model (kept outside this module's parameters:
            the checkpoint saves it once, as ``perception``).
        proprio_dim: proprioception values per frame.
        cfg: sizes (``hidden``, ``features``, ``use_proprio``).
    """

    kind = "perception"
    #: Attention heads over the object slots (put and stack name two objects).
    HEADS = 2
    #: The smallest spread an input is divided by (the units of positions: a feature that
    #: is nearly always 0 in training, such as a displacement, must not blow up when it is
    #: not).
    MIN_STD = 0.02

    def __init__(self, perception: Perception, proprio_dim: int, cfg: CaptionModelConfig):
        super().__init__()
        self._perception = [perception]
        for param in perception.parameters():
            param.requires_grad_(False)
        self.layout = lay = perception.layout
        self.proprio_dim = proprio_dim if cfg.use_proprio else 0
        d, width = lay.position_dims, cfg.hidden
        self.slot_dim = 1 + 2 * d
        self.register_buffer("feat_mean", torch.zeros(self.slot_dim))
        self.register_buffer("feat_std", torch.ones(self.slot_dim))
        self.slot = nn.Sequential(
            nn.Linear(self.slot_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU()
        )
        self.identity = nn.Parameter(torch.randn(lay.count, width) * 0.1)
        self.score = nn.Linear(width, self.HEADS)
        out_in = (self.HEADS + 1) * width + d + 2 * self.proprio_dim
        self.head = nn.Sequential(
            nn.Linear(out_in, cfg.features), nn.LayerNorm(cfg.features), nn.ReLU()
        )
        self.out_dim = cfg.features

    @property
    def perception(self) -> Perception:
        """The frozen perception model."""
        return self._perception[0]

    def slot_features(
        self, first: torch.Tensor, current: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-slot inputs ``(B, count, 1 + 2d)`` (unstandardised) of estimated observation
        pairs, and which slots hold an object in either frame ``(B, count)``."""
        lay, d = self.layout, self.layout.position_dims

        def split(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            slots = x[:, lay.start : lay.dim].reshape(-1, lay.count, lay.width)
            return x[:, :d], slots[..., :d], slots[..., d]

        _, pos0, on0 = split(first.float())
        g, pos, on = split(current.float())
        rel = (pos - g[:, None]) * on[..., None]
        disp = (pos - pos0) * (on * on0)[..., None]
        x = torch.cat([on[..., None], rel, disp], -1)
        return x, (on + on0) > 0

    def fit(self, first: torch.Tensor, current: torch.Tensor) -> None:
        """Standardise the per-slot inputs with their mean and spread over the slots that
        hold an object in these pairs."""
        x, present = self.slot_features(first, current)
        x = x[present]
        self.feat_mean.copy_(x.mean(0))
        self.feat_std.copy_(x.std(0).clamp_min(self.MIN_STD))

    def forward(
        self, first: torch.Tensor, current: torch.Tensor, p0: torch.Tensor, p: torch.Tensor
    ) -> torch.Tensor:
        return self.features_and_slots(first, current, p0, p)[0]

    def features_and_slots(
        self, first: torch.Tensor, current: torch.Tensor, p0: torch.Tensor, p: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The features, with the standardised per-slot inputs ``(B, K, 1 + 2d)`` and the
        presence ``(B, K)`` they were computed from."""
        x, present = self.slot_features(first, current)
        xs = (x - self.feat_mean) / self.feat_std
        h = self.slot(xs)  # (B, K, W)
        z = h + self.identity
        score = self.score(h).masked_fill(~present[..., None], -1e4)  # (B, K, heads)
        attn = torch.softmax(score, 1)
        picked = torch.einsum("bkh,bkw->bhw", attn, z).flatten(1)
        d = self.layout.position_dims
        where = torch.einsum("bkh,bkd->bhd", attn, x[..., 1 : 1 + d])  # relative positions
        parts = [picked, h.masked_fill(~present[..., None], 0.0).amax(1), where[:, 0] - where[:, 1]]
        if self.proprio_dim:
            parts += [p0, p]
        return self.head(torch.cat(parts, -1)), xs, present


def make_encoder(
    frame_shape: Sequence[int],
    proprio_dim: int,
    cfg: CaptionModelConfig,
    perception: Perception | None = None,
) -> FramePairEncoder | SlotPairEncoder:
    """The encoder ``cfg.encoder`` names (``perception`` needs the perception model)."""
    if cfg.encoder == "perception":
        if perception is None:
            raise LcrlError("model.encoder=perception needs a perception model (--perception)")
        return SlotPairEncoder(perception, proprio_dim, cfg)
    return FramePairEncoder(frame_shape, proprio_dim, cfg)


class Captioner(nn.Module):
    """Frame pair -> instruction, word by word (GRU decoder over the vocabulary)."""

    def __init__(
        self,
        frame_shape: Sequence[int],
        proprio_dim: int,
        vocab_size: int,
        cfg: CaptionModelConfig,
        perception: Perception | None = None,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = make_encoder(frame_shape, proprio_dim, cfg, perception)
        self.embed = nn.Embedding(vocab_size, cfg.embed, padding_idx=PAD)
        self.init = nn.Linear(cfg.features, cfg.hidden)
        self.gru = nn.GRU(cfg.embed + cfg.features, cfg.hidden, batch_first=True)
        self.out = nn.Linear(cfg.hidden, vocab_size)

    def forward(self, ctx: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
        """Logits ``(B, L, V)`` for the next token after each of ``tokens`` ``(B, L)``."""
        h0 = torch.tanh(self.init(ctx)).unsqueeze(0)
        e = self.embed(tokens)
        x = torch.cat([e, ctx.unsqueeze(1).expand(-1, e.shape[1], -1)], -1)
        y, _ = self.gru(x, h0)
        return self.out(y)

    def _step(
        self, ctx: torch.Tensor, token: torch.Tensor, h: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([self.embed(token), ctx], -1).unsqueeze(1)
        y, h = self.gru(x, h)
        return F.log_softmax(self.out(y[:, 0]), -1), h

    @torch.no_grad()
    def greedy(self, ctx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Most likely word at every step: token ids ``(B, max_len - 1)`` and the
        caption's log-likelihood ``(B,)``."""
        b = ctx.shape[0]
        h = torch.tanh(self.init(ctx)).unsqueeze(0)
        token = torch.full((b,), BOS, dtype=torch.long, device=ctx.device)
        done = torch.zeros(b, dtype=torch.bool, device=ctx.device)
        total = torch.zeros(b, device=ctx.device)
        out = []
        for _ in range(self.cfg.max_len - 1):
            logp, h = self._step(ctx, token, h)
            lp, token = logp.max(-1)
            total = total + torch.where(done, torch.zeros_like(lp), lp)
            token = torch.where(done, torch.full_like(token, PAD), token)
            out.append(token)
            done = done | (token == EOS)
            if bool(done.all()):
                break
        return torch.stack(out, 1), total

    @torch.no_grad()
    def beam(self, ctx: torch.Tensor, width: int = 4) -> list[list[tuple[list[int], float]]]:
        """Beam search: for each row, up to ``width`` finished captions (token ids,
        log-likelihood), best first."""
        results = []
        for i in range(ctx.shape[0]):
            c = ctx[i : i + 1]
            h = torch.tanh(self.init(c)).unsqueeze(0)
            beams: list[tuple[list[int], float, torch.Tensor]] = [([BOS], 0.0, h)]
            finished: list[tuple[list[int], float]] = []
            for _ in range(self.cfg.max_len - 1):
                if not beams:
                    break
                tokens = torch.tensor([b[0][-1] for b in beams], device=ctx.device)
                hs = torch.cat([b[2] for b in beams], 1)
                logp, hs = self._step(c.expand(len(beams), -1), tokens, hs)
                cand = []
                top_lp, top_id = logp.topk(min(width, logp.shape[-1]), -1)
                for k, (seq, score, _) in enumerate(beams):
                    for lp, t in zip(top_lp[k].tolist(), top_id[k].tolist(), strict=True):
                        cand.append(([*seq, t], score + lp, hs[:, k : k + 1]))
                cand.sort(key=lambda x: -x[1])
                beams = []
                for seq, score, hk in cand:
                    if seq[-1] == EOS:
                        finished.append((seq[1:], score))
                    elif len(beams) < width:
                        beams.append((seq, score, hk))
                    if len(beams) >= width and len(finished) >= width:
                        break
            finished.sort(key=lambda x: -x[1])
            results.append(finished[:width])
        return results


class RewardModel(nn.Module):
    """(instruction embedding, frame pair) -> logit of "the instruction is satisfied".

    With the ``spatial`` encoder the instruction modulates the late convolutions (FiLM,
    per channel), so it picks what to look for before the map is pooled; the frame pair's
    "context" is then the early feature map and the proprioception, flattened, which
    :meth:`context` computes once per frame pair for any number of instructions. With
    ``flatten`` the pooled frame features are modulated instead.
    """

    def __init__(
        self,
        frame_shape: Sequence[int],
        proprio_dim: int,
        text_dim: int,
        cfg: CaptionModelConfig,
        perception: Perception | None = None,
    ) -> None:
        super().__init__()
        self.encoder = make_encoder(frame_shape, proprio_dim, cfg, perception)
        self.register_buffer("text_mean", torch.zeros(text_dim))
        self.register_buffer("text_std", torch.ones(text_dim))
        self.text = nn.Linear(text_dim, cfg.text_features)
        if self.encoder.kind == "spatial":
            widths = [2 * c for c in self.encoder.late_channels]
        else:
            widths = [2 * cfg.features]
        self.film = nn.Linear(cfg.text_features, sum(widths))
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)
        self.widths = widths
        self.out_features = cfg.features
        mlp_in = cfg.features + cfg.text_features
        enc = self.encoder
        self.slot_query = enc.kind == "perception" and cfg.slot_query
        if self.slot_query:  # the instruction picks its slot: its features and inputs
            self.query = nn.Linear(cfg.text_features, cfg.hidden)
            mlp_in += cfg.hidden + enc.slot_dim
        self.mlp = nn.Sequential(
            nn.Linear(mlp_in, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, 1),
        )

    def set_text_stats(self, embeddings: np.ndarray) -> None:
        """Standardise text embeddings with the statistics of the training instructions."""
        e = torch.as_tensor(np.asarray(embeddings, np.float32))
        self.text_mean.copy_(e.mean(0))
        self.text_std.copy_(e.std(0).clamp_min(1e-3))

    def context(
        self, first: torch.Tensor, current: torch.Tensor, p0: torch.Tensor, p: torch.Tensor
    ) -> torch.Tensor:
        """What :meth:`forward` needs of a frame pair, as one ``(B, D)`` tensor."""
        enc = self.encoder
        if self.slot_query:  # pooled features, then each slot's inputs and presence
            z, x, present = enc.features_and_slots(first, current, p0, p)
            return torch.cat([z, x.flatten(1), present.float()], -1)
        if enc.kind != "spatial":
            return enc(first, current, p0, p)
        parts = [enc.early(first, current).flatten(1)]
        if enc.proprio_dim:
            parts += [p0, p]
        return torch.cat(parts, -1)

    def pick(
        self, ctx: torch.Tensor, t: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """With ``slot_query``: how much the instruction (projected text ``t``) attends to
        each object slot ``(B, K)`` (absent slots get none), the slots' features
        ``(B, K, W)`` and their standardised inputs ``(B, K, 1 + 2d)``."""
        enc = self.encoder
        n, k, d = self.out_features, enc.layout.count, enc.slot_dim
        x = ctx[:, n : n + k * d].view(-1, k, d)
        present = ctx[:, n + k * d :] > 0.5
        h = enc.slot(x)
        q = self.query(t)
        score = ((h + enc.identity) * q[:, None]).sum(-1) / float(q.shape[-1]) ** 0.5
        return torch.softmax(score.masked_fill(~present, -1e4), 1), h, x

    def text_features(self, text: torch.Tensor) -> torch.Tensor:
        """The projected instruction embedding the model is conditioned on."""
        return F.relu(self.text((text - self.text_mean) / self.text_std))

    def forward(self, ctx: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        t = self.text_features(text)
        film = list(self.film(t).split(self.widths, -1))
        enc = self.encoder
        if enc.kind == "spatial":
            n = int(np.prod(enc.early_shape))
            x = ctx[:, :n].view(-1, *enc.early_shape)
            pd = enc.proprio_dim
            p0, p = ctx[:, n : n + pd], ctx[:, n + pd :]
            z = enc.pool(enc.late(x, film), p0, p)
        elif self.slot_query:
            gamma, beta = film[0].chunk(2, -1)
            z = ctx[:, : self.out_features] * (1.0 + gamma) + beta
            attn, h, x = self.pick(ctx, t)
            parts = [z, t, (attn[..., None] * h).sum(1), (attn[..., None] * x).sum(1)]
            return self.mlp(torch.cat(parts, -1)).squeeze(-1)
        else:  # the instruction picks which frame features matter
            gamma, beta = film[0].chunk(2, -1)
            z = ctx * (1.0 + gamma) + beta
        return self.mlp(torch.cat([z, t], -1)).squeeze(-1)


# --------------------------------------------------------------------------- metrics


def bleu4(candidate: str, references: Sequence[str]) -> float:
    """Sentence BLEU-4 against several references (uniform weights, brevity penalty, +1
    smoothing of the higher n-gram precisions as in Lin and Och 2004)."""
    cand = candidate.split()
    refs = [r.split() for r in references]
    if not cand or not refs:
        return 0.0
    logs = []
    for n in range(1, 5):
        grams = Counter(tuple(cand[i : i + n]) for i in range(len(cand) - n + 1))
        if not grams:
            logs.append(math.log(1.0 / (1.0 + 1.0)))  # smoothed empty order
            continue
        best: Counter = Counter()
        for r in refs:
            rg = Counter(tuple(r[i : i + n]) for i in range(len(r) - n + 1))
            for g in grams:
                best[g] = max(best[g], rg[g])
        hit = sum(min(c, best[g]) for g, c in grams.items())
        total = sum(grams.values())
        if n == 1:
            if hit == 0:
                return 0.0
            logs.append(math.log(hit / total))
        else:
            logs.append(math.log((hit + 1.0) / (total + 1.0)))
    ref_len = min((abs(len(r) - len(cand)), len(r)) for r in refs)[1]
    bp = 1.0 if len(cand) > ref_len else math.exp(1.0 - ref_len / len(cand))
    return bp * math.exp(sum(logs) / 4.0)


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (ties count one half); NaN without both classes."""
    scores = np.asarray(scores, np.float64)
    labels = np.asarray(labels, bool)
    pos, neg = labels.sum(), (~labels).sum()
    if pos == 0 or neg == 0:
        return float("nan")
    order = np.argsort(scores, kind="mergesort")
    ranks = np.empty(len(scores), np.float64)
    sorted_scores = scores[order]
    i = 0
    while i < len(scores):  # average ranks over ties
        j = i
        while j + 1 < len(scores) and sorted_scores[j + 1] == sorted_scores[i]:
            j += 1
        ranks[order[i : j + 1]] = 0.5 * (i + j) + 1.0
        i = j + 1
    return float((ranks[labels].sum() - pos * (pos + 1) / 2.0) / (pos * neg))


SLOT_GROUPS: dict[str, tuple[str, ...]] = {
    "verb": ("family",),
    "object": ("colour", "shape"),
    "colour": ("colour",),
    "shape": ("shape",),
    "direction": ("direction",),
    "relation": ("relation",),
    "reference": ("target_colour", "target_shape"),
}


def slot_matches(generated: Instruction | None, label: Instruction) -> dict[str, bool]:
    """For each slot group the label has, whether the generated instruction agrees."""
    want = label.slots()
    got = generated.slots() if generated is not None else {}
    out = {}
    for group, keys in SLOT_GROUPS.items():
        if all(k in want for k in keys):
            out[group] = all(got.get(k) == want[k] for k in keys)
    return out


# --------------------------------------------------------------------------- data


def _observations(data: CaptionDataset, episodes: np.ndarray) -> np.ndarray:
    """Observation indices of the given episodes."""
    if len(episodes) == 0:
        return np.zeros(0, np.int64)
    starts, ends = data.episode_start[episodes], data.episode_start[episodes + 1]
    return np.concatenate([np.arange(a, b) for a, b in zip(starts, ends, strict=True)])


class _Pairs:
    """Frame pairs of a caption dataset, in memory, with the episode split."""

    def __init__(
        self,
        data: CaptionDataset,
        val_fraction: float,
        seed: int,
        perceive: Any = None,
    ) -> None:
        self.data = data
        self.proprio = data.proprio.astype(np.float32)
        # uint8 frames (N, H, W, 3), or perception's estimates of them, computed once (read
        # from the file a batch at a time)
        self.frames = data.frames[:] if perceive is None else perceive(data.frames, self.proprio)
        n_ep = data.num_episodes
        perm = np.random.default_rng(seed).permutation(n_ep)
        n_val = max(1, round(val_fraction * n_ep)) if n_ep > 1 else 0
        self.val_episodes = np.sort(perm[:n_val])
        self.train_episodes = np.sort(perm[n_val:])
        self.seen = np.asarray([s == "train" for s in data.instruction_set])
        self.first = data.first_of(np.arange(data.num_observations))
        p = self.proprio
        self.p_mean = p.mean(0) if len(p) else np.zeros(p.shape[1], np.float32)
        self.p_std = p.std(0).clip(1e-3) if len(p) else np.ones(p.shape[1], np.float32)

    def observations(self, episodes: np.ndarray) -> np.ndarray:
        return _observations(self.data, episodes)

    def tensors(self, idx: np.ndarray, device: torch.device) -> tuple[torch.Tensor, ...]:
        first = self.first[idx]
        p0 = (self.proprio[first] - self.p_mean) / self.p_std
        p = (self.proprio[idx] - self.p_mean) / self.p_std
        return (
            torch.as_tensor(self.frames[first], device=device),
            torch.as_tensor(self.frames[idx], device=device),
            torch.as_tensor(p0, device=device),
            torch.as_tensor(p, device=device),
        )


# --------------------------------------------------------------------------- training


@dataclass
class CaptionTrainConfig:
    """Train the learned captioner and reward model on a caption dataset
    (``lcrl caption train``)."""

    data: str = "data/captions-lang2d.h5"
    """The caption dataset (``lcrl caption collect``)."""
    out: str = "runs/captioner"
    """Checkpoint folder to write."""
    models: tuple[str, ...] = MODELS
    """Which models to train: ``captioner``, ``reward`` or both."""
    steps: int = 3000
    """Gradient steps per model."""
    batch_size: int = 64
    """Frame pairs per step."""
    lr: float = 3e-4
    """Adam learning rate."""
    none_fraction: float = 0.25
    """Captioner: fraction of each batch drawn from observations that achieved nothing
    (target ``<none>``)."""
    augment_pad: int = 4
    """Random-shift augmentation of training frame pairs: pad by this many edge pixels and
    crop back at a random offset, the same for both frames of a pair (0: off)."""
    hard_negative_fraction: float = 0.5
    """Reward model: fraction of the negatives that share the object or the family of an
    instruction the observation satisfies (the rest are any other instruction)."""
    near_negative_fraction: float = 0.0
    """Reward model: fraction of the negatives that are near misses: the same instruction
    on an observation of the same episode, within ``near_window`` steps, that does not
    satisfy it (where the achievement begins or ends). Captioner: the same fraction of its
    ``<none>`` targets are observations that achieved nothing within ``near_window``
    steps of one that did. They teach the boundary of an achievement, where relabelling
    in a training loop asks most."""
    near_window: int = 10
    """Steps around an achievement that count as near (``near_negative_fraction``)."""
    onset_delay: tuple[str, ...] = ()
    """``FAMILY=STEPS`` entries (e.g. ``push=1``): an instruction of the family counts as
    achieved, for both models, only from STEPS steps after the rule captioner first accepts
    it (its first accepted steps become near misses). A model whose boundary is blurred by
    perception error then judges the achievement a little after the rule does, not before:
    a push it rewards has moved its object far enough."""
    val_fraction: float = 0.2
    """Episodes held out of training for evaluation."""
    model: CaptionModelConfig = field(default_factory=CaptionModelConfig)
    """Network sizes."""
    text_model: str = ""
    """Frozen text encoder for the reward model (empty: the packaged all-MiniLM-L6-v2)."""
    perception: str = ""
    """With ``--model.encoder perception``: the perception model (``lcrl perception
    train --out``) whose estimated object slots both models read (frozen; saved with
    them)."""
    device: str = "cpu"
    """``cpu`` or ``cuda``."""
    seed: int = 0
    """Seed of the episode split, sampling and initialisation."""
    threads: int = 0
    """Torch CPU threads (0: leave torch's default)."""
    overwrite: bool = False
    """Replace an existing checkpoint in ``out``."""
    progress: bool = True
    """Show progress bars."""

    def validate(self) -> None:
        bad = [m for m in self.models if m not in MODELS]
        if bad or not self.models:
            raise LcrlError(f"models must be among {MODELS}, got {self.models}")
        self.model.validate()
        for name in ("steps", "batch_size"):
            if getattr(self, name) <= 0:
                raise LcrlError(f"{name} must be positive")
        if self.augment_pad < 0:
            raise LcrlError("augment_pad must be >= 0")
        if self.near_window < 1:
            raise LcrlError("near_window must be at least 1")
        onset_delays(self.onset_delay)  # raises on a bad entry
        for name in ("none_fraction", "hard_negative_fraction", "near_negative_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise LcrlError(f"{name} must be in [0, 1]")
        if not 0.0 < self.val_fraction < 1.0:
            raise LcrlError("val_fraction must be in (0, 1)")
        if self.device not in ("cpu", "cuda") and not self.device.startswith("cuda:"):
            raise LcrlError(f"device must be cpu or cuda, got {self.device!r}")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise LcrlError("device cuda was asked for but torch sees no CUDA device")


def onset_delays(entries: Sequence[str]) -> dict[str, int]:
    """``("push=1", ...)`` as ``{"push": 1}``.

    Raises:
        LcrlError: an entry that is not ``FAMILY=STEPS`` with a known family and STEPS >= 0.
    """
    out: dict[str, int] = {}
    for entry in entries:
        family, sep, value = str(entry).partition("=")
        steps = int(value) if sep and value.strip().isdigit() else -1
        if family not in FAMILIES or steps < 0:
            raise LcrlError(
                f"onset_delay entry {entry!r}: give FAMILY=STEPS with a family of {FAMILIES} "
                "and STEPS a whole number >= 0 (e.g. push=1)"
            )
        out[family] = steps
    return out


def delayed_labels(
    data: Any, observations: np.ndarray, delays: dict[str, int], families: Sequence[str]
) -> dict[int, np.ndarray]:
    """Each of ``observations``' labels (instruction ids) whose family has a delay ``d`` in
    ``delays``, kept only where the same instruction was also accepted at each of the ``d``
    steps before, in the same episode; labels of other families as they are."""
    out: dict[int, np.ndarray] = {}
    for j in observations:
        j = int(j)
        lab = data.labels(j).astype(np.int64)
        if lab.size and delays:
            start = int(data.first_of(j))
            keep = []
            for i in lab:
                d = delays.get(families[int(i)], 0)
                ok = j - d > start and all(int(i) in data.labels(j - m) for m in range(1, d + 1))
                keep.append(d == 0 or ok)
            lab = lab[np.asarray(keep, bool)]
        out[j] = lab
    return out


def _text_encoder(name: str) -> Any:
    from lcrl.text_encoder import FrozenTextEncoder, TextEncoderConfig

    cfg = TextEncoderConfig() if not name else TextEncoderConfig(model=name)
    return FrozenTextEncoder(cfg)


class _Sampler:
    """Training batches for both models from the training episodes."""

    def __init__(
        self,
        pairs: _Pairs,
        table: list[Instruction],
        rng: np.random.Generator,
        near_window: int = 10,
        onset_delay: dict[str, int] | None = None,
    ):
        self.pairs, self.rng, self.table = pairs, rng, table
        self.near_window = int(near_window)
        data = pairs.data
        obs = pairs.observations(pairs.train_episodes)
        seen = pairs.seen
        #: Each training observation's labels, after the families' onset delays.
        self._labels = delayed_labels(
            data, obs, dict(onset_delay or {}), [ins.family for ins in table]
        )
        self.labelled: list[int] = []
        self.targets: list[np.ndarray] = []
        self.empty: list[int] = []
        for j in obs:
            lab = self.labels(int(j))
            if lab.size == 0:
                self.empty.append(int(j))
            elif seen[lab].any():
                self.labelled.append(int(j))
                self.targets.append(lab[seen[lab]])
            # observations whose labels are all held-out never enter training
        self.labelled_arr = np.asarray(self.labelled, np.int64)
        self.empty_arr = np.asarray(self.empty, np.int64)
        # near misses: observations that achieved nothing within near_window steps of one
        # that achieved something, in the same episode (where an achievement begins or ends)
        ep = data.episode_of(self.empty_arr) if len(self.empty_arr) else self.empty_arr
        lab_ep = data.episode_of(self.labelled_arr)
        near = []
        for j, e in zip(self.empty_arr, ep, strict=True):
            lo = np.searchsorted(self.labelled_arr, j - self.near_window)
            hi = np.searchsorted(self.labelled_arr, j + self.near_window, side="right")
            if np.any(lab_ep[lo:hi] == e):
                near.append(int(j))
        self.near_empty_arr = np.asarray(near, np.int64)
        self.seen_ids = np.flatnonzero(seen)
        if not self.labelled:
            raise LcrlError("no training observation carries a training instruction label")
        # hard negatives: seen instructions sharing the object or the family
        self.related: list[np.ndarray] = []
        for ins in table:
            rel = [
                k
                for k in self.seen_ids
                if table[k] != ins and (table[k].obj == ins.obj or table[k].family == ins.family)
            ]
            self.related.append(np.asarray(rel, np.int64))

    def labels(self, j: int) -> np.ndarray:
        """Instruction ids that training observation ``j`` counts as achieved."""
        return self._labels[int(j)]

    def caption_batch(
        self, n: int, none_fraction: float, near: float = 0.0
    ) -> tuple[np.ndarray, list[int | None]]:
        """Observation indices and target instruction ids (None: ``<none>``); a fraction
        ``near`` of the ``<none>`` rows are near misses."""
        n_none = int(self.rng.binomial(n, none_fraction)) if self.empty else 0
        k = self.rng.integers(len(self.labelled), size=n - n_none)
        idx = list(self.labelled_arr[k])
        texts: list[int | None] = [
            int(self.targets[i][self.rng.integers(len(self.targets[i]))]) for i in k
        ]
        if n_none:
            n_near = int(self.rng.binomial(n_none, near)) if len(self.near_empty_arr) else 0
            pools = ((self.empty_arr, n_none - n_near), (self.near_empty_arr, n_near))
            for pool, m in pools:
                idx += list(pool[self.rng.integers(len(pool), size=m)])
            texts += [None] * n_none
        return np.asarray(idx, np.int64), texts

    def near_negative(self, j: int, instruction: int) -> int:
        """An observation of ``j``'s episode, within ``near_window`` steps, where
        ``instruction`` is not satisfied (-1: none): the boundary of an achievement."""
        data = self.pairs.data
        e = int(data.episode_of(np.asarray([j]))[0])
        lo = max(int(data.episode_start[e]) + 1, j - self.near_window)
        hi = min(int(data.episode_start[e + 1]), j + self.near_window + 1)
        for _ in range(8):
            c = int(self.rng.integers(lo, hi)) if hi > lo else -1
            if c >= 0 and instruction not in self.labels(c):
                return c
        return -1

    def reward_batch(
        self, n: int, hard: float, near: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Observation indices, instruction ids and 0/1 targets, half positives; a
        fraction ``near`` of the negatives are near misses (:meth:`near_negative`)."""
        n_pos = n // 2
        k = self.rng.integers(len(self.labelled), size=n)
        idx = self.labelled_arr[k].copy()
        ids = np.empty(n, np.int64)
        y = np.zeros(n, np.float32)
        for r in range(n):
            sat = self.targets[k[r]]
            if r < n_pos:
                ids[r] = sat[self.rng.integers(len(sat))]
                y[r] = 1.0
                continue
            if near and self.rng.random() < near:  # the same instruction, just before or after
                i = int(sat[self.rng.integers(len(sat))])
                c = self.near_negative(int(idx[r]), i)
                if c >= 0:
                    idx[r], ids[r] = c, i
                    continue
            if self.empty and self.rng.random() < 0.3:  # nothing achieved: any instruction
                idx[r] = self.empty_arr[self.rng.integers(len(self.empty))]
                ids[r] = self.seen_ids[self.rng.integers(len(self.seen_ids))]
                continue
            all_labels = self.labels(int(idx[r]))
            pool = self.related[int(sat[self.rng.integers(len(sat))])]
            if self.rng.random() >= hard or pool.size == 0:
                pool = self.seen_ids
            for _ in range(10):
                cand = int(pool[self.rng.integers(len(pool))])
                if cand not in all_labels:
                    break
            else:
                cand = -1
            if cand < 0:  # every candidate was satisfied: fall back to a positive
                ids[r] = sat[0]
                y[r] = 1.0
            else:
                ids[r] = cand
        return idx, ids, y


class LearnedCaptioner:
    """A trained captioner and/or reward model with what they need to run.

    Load one with :meth:`load`; :meth:`caption` and :meth:`score` take uint8 frames.
    """

    def __init__(
        self,
        vocab: Vocabulary,
        instructions: list[str],
        instruction_set: list[str],
        frame_shape: tuple[int, ...],
        proprio_dim: int,
        cfg: CaptionModelConfig,
        p_mean: np.ndarray,
        p_std: np.ndarray,
        text_model: str,
        meta: dict[str, Any],
        device: str = "cpu",
    ) -> None:
        self.vocab = vocab
        self.instructions = instructions
        self.instruction_set = instruction_set
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self.proprio_dim = int(proprio_dim)
        self.cfg = cfg
        self.p_mean = np.asarray(p_mean, np.float32)
        self.p_std = np.asarray(p_std, np.float32)
        self.text_model = text_model
        self.meta = meta
        self.device = torch.device(device)
        self.captioner: Captioner | None = None
        self.reward: RewardModel | None = None
        self._encoder: Any = None
        #: The frozen perception model both models read through (``encoder=perception``).
        self.perception: Perception | None = None

    # -- inputs
    def _inputs(
        self, first: np.ndarray, current: np.ndarray, p0: np.ndarray | None, p: np.ndarray | None
    ) -> tuple[torch.Tensor, ...]:
        first = np.asarray(first, np.uint8)
        current = np.asarray(current, np.uint8)
        if first.shape[1:] != self.frame_shape or current.shape != first.shape:
            raise LcrlError(
                f"frames must be (B, {', '.join(map(str, self.frame_shape))}) uint8 pairs; got "
                f"{first.shape} and {current.shape}"
            )
        b = first.shape[0]
        if p0 is None or p is None:
            if self.cfg.use_proprio:
                raise LcrlError("this model reads proprioception: pass p0 and p")
            p0 = p = np.zeros((b, self.proprio_dim), np.float32)
        if self.perception is not None:  # what the models read: the estimated slots
            first = self.perceive(first, np.asarray(p0, np.float32))
            present = self.perception.presence(first) if self.cfg.first_presence else None
            current = self.perceive(current, np.asarray(p, np.float32), present=present)
        p0 = (np.asarray(p0, np.float32) - self.p_mean) / self.p_std
        p = (np.asarray(p, np.float32) - self.p_mean) / self.p_std
        dev = self.device
        return (
            torch.as_tensor(first, device=dev),
            torch.as_tensor(current, device=dev),
            torch.as_tensor(p0, device=dev),
            torch.as_tensor(p, device=dev),
        )

    def perceive(
        self,
        frames: Any,
        proprio: np.ndarray,
        batch: int = 256,
        progress: bool = False,
        present: np.ndarray | None = None,
    ) -> np.ndarray:
        """Perception's estimated observations ``(N, dim)`` of frames (an array, or any
        sequence that slices into arrays, such as a file's dataset) and their robot state
        (``encoder=perception``), with presence flags ``(N, count)`` to use instead of the
        estimated ones if given; ``progress`` shows a bar."""
        if self.perception is None:
            raise LcrlError("these models read camera frames, not a perception model's slots")
        from tqdm import tqdm

        start = self.perception.layout.start
        n = len(frames)
        bar = tqdm(total=n, desc="perception", unit="frame", disable=not progress or n == 0)
        out = []
        for i in range(0, n, batch):
            x = np.asarray(frames[i : i + batch])
            flags = None if present is None else present[i : i + batch]
            out.append(self.perception.observation(x, proprio[i : i + batch, :start], flags))
            bar.update(len(x))
        bar.close()
        return np.concatenate(out).astype(np.float32) if out else np.zeros((0, 0), np.float32)

    def encode_texts(self, texts: Sequence[str]) -> torch.Tensor:
        """Frozen text embeddings of instructions (any free text)."""
        if self._encoder is None:
            self._encoder = _text_encoder(self.text_model)
        return torch.as_tensor(self._encoder.encode(list(texts)), device=self.device)

    # -- inference
    def _context(self, model: str, *frames: Any) -> torch.Tensor:
        net = self.captioner if model == "captioner" else self.reward
        if net is None:
            other = "reward" if model == "captioner" else "captioner"
            raise LcrlError(
                f"this checkpoint has no {model} (it was trained with --models {other})"
            )
        net.eval()
        inputs = self._inputs(*frames)
        return net.encoder(*inputs) if isinstance(net, Captioner) else net.context(*inputs)

    @torch.no_grad()
    def captions(
        self,
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
        beam: int = 0,
    ) -> list[list[tuple[str, float]]]:
        """Captions and their log-likelihoods per frame pair, best first: one greedy
        caption, or up to ``beam`` from a beam search (``beam > 1``). ``<none>``: nothing
        achieved."""
        ctx = self._context("captioner", first, current, p0, p)
        assert self.captioner is not None
        if beam > 1:
            return [
                [(self.vocab.decode(ids), float(sc)) for ids, sc in beams]
                for beams in self.captioner.beam(ctx, beam)
            ]
        ids, logp = self.captioner.greedy(ctx)
        return [
            [(self.vocab.decode(row), float(lp))]
            for row, lp in zip(ids.tolist(), logp.tolist(), strict=True)
        ]

    def caption(
        self,
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
        beam: int = 0,
    ) -> list[tuple[str, float]]:
        """The best caption and its log-likelihood per frame pair (see :meth:`captions`)."""
        return [
            c[0] if c else ("", float("-inf")) for c in self.captions(first, current, p0, p, beam)
        ]

    @torch.no_grad()
    def score(
        self,
        texts: Sequence[str],
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
    ) -> np.ndarray:
        """Probability that each ``texts[i]`` is satisfied by the change from
        ``first[i]`` to ``current[i]``."""
        if len(texts) != len(first):
            raise LcrlError(f"{len(texts)} instructions for {len(first)} frame pairs")
        ctx = self._context("reward model", first, current, p0, p)
        return torch.sigmoid(self.reward(ctx, self.encode_texts(texts))).cpu().numpy()

    @torch.no_grad()
    def score_matrix(
        self,
        texts: Sequence[str],
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
    ) -> np.ndarray:
        """``(len(current), len(texts))`` probabilities: every instruction against every
        frame pair (the frames are encoded once)."""
        ctx = self._context("reward model", first, current, p0, p)
        emb = self.encode_texts(texts)
        n, m = ctx.shape[0], emb.shape[0]
        # row-major: frame i against text k at i * m + k
        logits = self.reward(ctx.repeat_interleave(m, 0), emb.repeat(n, 1))
        return torch.sigmoid(logits).view(n, m).cpu().numpy()

    # -- saving
    def save(self, directory: str | Path) -> Path:
        modules: dict[str, nn.Module] = {}
        if self.captioner is not None:
            modules["captioner"] = self.captioner
        if self.reward is not None:
            modules["reward"] = self.reward
        if self.perception is not None:
            modules["perception"] = self.perception
        meta = {
            "kind": CHECKPOINT_KIND,
            "models": sorted(modules),
            "frame_shape": list(self.frame_shape),
            "proprio_dim": self.proprio_dim,
            "model": asdict(self.cfg),
            "text_model": self.text_model,
            "proprio_mean": self.p_mean.tolist(),
            "proprio_std": self.p_std.tolist(),
            **self.meta,
        }
        if self.perception is not None:  # rebuilt from here when loading
            meta["perception"] = embedded_meta(
                self.perception, str(self.meta.get("train", {}).get("perception", ""))
            )
        json_files = {
            "vocabulary": {"words": self.vocab.words},
            "instructions": {"texts": self.instructions, "sets": self.instruction_set},
        }
        return save_checkpoint(directory, modules=modules, meta=meta, json_files=json_files)

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> LearnedCaptioner:
        """Load a checkpoint written by :meth:`save` (or ``lcrl caption train``)."""
        try:
            ckpt = load_checkpoint(path)
        except CheckpointError as e:
            raise LcrlError(str(e)) from None
        meta = ckpt.meta
        if meta.get("kind") != CHECKPOINT_KIND:
            raise LcrlError(
                f"{path} is not a learned-captioner checkpoint (kind {meta.get('kind')!r}); "
                "policy checkpoints go to lcrl eval / act"
            )
        words = ckpt.json("vocabulary")["words"]
        vocab = Vocabulary([])
        vocab.words = list(words)
        vocab.index = {w: i for i, w in enumerate(words)}
        table = ckpt.json("instructions")
        # checkpoints from before an option read as they were trained
        saved = {
            "encoder": "flatten",
            "slot_query": False,
            "first_presence": False,
            **meta["model"],
        }
        mcfg = CaptionModelConfig(
            **{
                **saved,
                "channels": tuple(saved["channels"]),
                "strides": tuple(saved.get("strides", ())),
            }
        )
        known = {"kind", "models", "frame_shape", "proprio_dim", "model", "text_model",
                 "proprio_mean", "proprio_std", "format_version", "perception"}  # fmt: skip
        lc = cls(
            vocab,
            list(table["texts"]),
            list(table["sets"]),
            tuple(meta["frame_shape"]),
            int(meta["proprio_dim"]),
            mcfg,
            np.asarray(meta["proprio_mean"], np.float32),
            np.asarray(meta["proprio_std"], np.float32),
            meta.get("text_model", ""),
            {k: v for k, v in meta.items() if k not in known},
            device,
        )
        try:
            if mcfg.encoder == "perception":
                lc.perception = load_model(path, device)[0]
            if "captioner" in meta["models"]:
                lc.captioner = Captioner(
                    lc.frame_shape, lc.proprio_dim, len(vocab), mcfg, lc.perception
                )
                ckpt.load_module("captioner", lc.captioner)
                lc.captioner.to(lc.device)
            if "reward" in meta["models"]:
                dim = int(meta["text_dim"])
                lc.reward = RewardModel(lc.frame_shape, lc.proprio_dim, dim, mcfg, lc.perception)
                ckpt.load_module("reward", lc.reward)
                lc.reward.to(lc.device)
        except CheckpointError as e:
            raise LcrlError(str(e)) from None
        return lc

    def check_dataset(self, data: CaptionDataset) -> None:
        """Refuse a dataset whose frames or robot state differ from the training data's."""
        if data.frame_shape != self.frame_shape or data.proprio.shape[1] != self.proprio_dim:
            raise LcrlError(
                f"the models read {'x'.join(map(str, self.frame_shape))} frames and "
                f"{self.proprio_dim} proprioception values; {data.path} has "
                f"{'x'.join(map(str, data.frame_shape))} frames and {data.proprio.shape[1]}"
            )


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
        if "captioner" in cfg.models:
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
        if "reward" in cfg.models:
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
    """Fit a slot-pair encoder's input standardisation on training pairs (frame
    encoders need nothing)."""
    if not isinstance(encoder, SlotPairEncoder):
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


# --------------------------------------------------------------------------- evaluation


def evaluate_models(
    lc: LearnedCaptioner,
    data: CaptionDataset,
    episodes: np.ndarray | None = None,
    max_pairs: int = 2000,
    batch_size: int = 128,
    beam: int = 0,
    seed: int = 0,
) -> dict[str, Any]:
    """Captioner and reward-model figures on ``episodes`` (default: the checkpoint's
    held-out episodes when it was trained on ``data``, else every episode).

    Returns a dict with ``seen`` (observations that achieved a training instruction) and
    ``heldout_combinations`` (observations that achieved a held-out combination), each
    with captioner ``exact_match``, ``slot_accuracy`` per slot group, ``bleu4``, and the
    reward model's ``precision``, ``recall`` and ``auc``; plus ``none_accuracy`` (the
    captioner says ``<none>`` where nothing was achieved). The reward model's ``auc``
    ranks each satisfied instruction against an unsatisfied one of the same family on the
    same frames (about the same object where the family allows: the instruction alone
    decides); ``auc_with_idle`` adds observations that achieved nothing, paired with any
    instruction, to the negatives; ``auc_near`` ranks each satisfied instruction against
    the same instruction a few steps before or after in the same episode, where it is not
    satisfied (near misses: the boundary a training loop's relabelling asks about most),
    and ``near_false_positive_rate`` is how often those score as satisfied.
    """
    lc.check_dataset(data)
    if episodes is None:
        same = lc.meta.get("dataset_meta") == data.meta and "val_episodes" in lc.meta
        episodes = (
            np.asarray(lc.meta["val_episodes"], np.int64) if same else np.arange(data.num_episodes)
        )
    rng = np.random.default_rng(seed)
    obs = _observations(data, np.asarray(episodes, np.int64))
    names = data.instructions  # matched to the models by text, never by id
    heldout_names = {t for t, s in zip(names, data.instruction_set, strict=True) if s == "heldout"}
    groups: dict[str, list[tuple[int, list[str]]]] = {"seen": [], "heldout_combinations": []}
    empty: list[int] = []
    for j in obs:
        lab = [names[i] for i in data.labels(int(j))]
        if not lab:
            empty.append(int(j))
            continue
        if any(t in heldout_names for t in lab):
            groups["heldout_combinations"].append((int(j), lab))
        if any(t not in heldout_names for t in lab):
            groups["seen"].append((int(j), lab))
    first_of = data.first_of

    def batches(idx: list[int]) -> Any:
        for s in range(0, len(idx), batch_size):
            sl = np.asarray(idx[s : s + batch_size], np.int64)
            f = data.read_frames(first_of(sl))
            c = data.read_frames(sl)
            yield sl, f, c, data.proprio[first_of(sl)], data.proprio[sl]

    results: dict[str, Any] = {"episodes": len(episodes)}
    for name, items in groups.items():
        if len(items) > max_pairs:
            items = [items[i] for i in np.sort(rng.choice(len(items), max_pairs, replace=False))]
        res: dict[str, Any] = {"observations": len(items)}
        if lc.captioner is not None and items:
            idx = [j for j, _ in items]
            captions = []
            for _, f, c, p0, p in batches(idx):
                captions += lc.caption(f, c, p0, p, beam=beam)
            exact, bleu, slots = [], [], {g: [] for g in SLOT_GROUPS}
            made_heldout = []
            for (_, lab), (text, _) in zip(items, captions, strict=True):
                # the references: the labels of the group's kind (seen or held-out)
                refs = [t for t in lab if (t in heldout_names) == (name != "seen")]
                exact.append(text in lab)
                made_heldout.append(text in heldout_names and text in lab)
                bleu.append(bleu4(text, refs))
                gen = try_parse(text) if text != NONE_TEXT else None
                best = max(
                    (slot_matches(gen, _parse(r)) for r in refs),
                    key=lambda m: sum(m.values()),
                )
                for g, ok in best.items():
                    slots[g].append(ok)
            res["exact_match"] = float(np.mean(exact))
            res["bleu4"] = float(np.mean(bleu))
            res["slot_accuracy"] = {g: float(np.mean(v)) for g, v in slots.items() if v}
            if name != "seen":
                res["heldout_caption_rate"] = float(np.mean(made_heldout))
            res["examples"] = [
                {"labels": lab[:4], "caption": text}
                for (_, lab), (text, _) in list(zip(items, captions, strict=True))[:5]
            ]
        if lc.reward is not None and items:
            pos_idx, pos_txt, neg_idx, neg_txt = [], [], [], []
            pool = (
                sorted(heldout_names)
                if name != "seen"
                else [t for t in names if t not in heldout_names]
            )
            by_family: dict[str, list[str]] = {}
            for t in pool:
                by_family.setdefault(t.split()[0], []).append(t)
            for j, lab in items:
                mine = [t for t in lab if (t in heldout_names) == (name != "seen")]
                if not mine:
                    continue
                pos_idx.append(j)
                pos_txt.append(mine[rng.integers(len(mine))])
                # A hard negative for the same frames: an unsatisfied instruction of the
                # same family, about the same object when the family allows (push the red
                # cube right, not left), so that the instruction alone decides.
                pos = _parse(pos_txt[-1])
                same = [t for t in by_family[pos.family] if t not in lab]
                close = [t for t in same if _parse(t).obj == pos.obj]
                cands = close or same
                if cands:
                    neg_idx.append(j)
                    neg_txt.append(cands[rng.integers(len(cands))])
            n_hard = len(neg_idx)
            # near misses: the positive's instruction a few steps before or after, in the
            # same episode, where it is not satisfied (the boundary of the achievement)
            near_pos, near_idx, near_txt = [], [], []
            for k, (j, text) in enumerate(zip(pos_idx, pos_txt, strict=True)):
                e = int(data.episode_of(np.asarray([j]))[0])
                lo, hi = int(data.episode_start[e]) + 1, int(data.episode_start[e + 1])
                cands = [
                    c
                    for c in range(max(lo, j - NEAR_WINDOW), min(hi, j + NEAR_WINDOW + 1))
                    if text not in {names[i] for i in data.labels(c)}
                ]
                if cands:
                    near_pos.append(k)
                    near_idx.append(cands[rng.integers(len(cands))])
                    near_txt.append(text)
            for j in (
                rng.choice(empty, min(len(empty), len(pos_idx) // 2), replace=False)
                if empty
                else []
            ):  # observations that achieved nothing, with any instruction
                neg_idx.append(int(j))
                neg_txt.append(pool[rng.integers(len(pool))])
            all_idx = pos_idx + neg_idx + near_idx
            all_txt = pos_txt + neg_txt + near_txt
            y = np.asarray([1] * len(pos_idx) + [0] * len(neg_idx), bool)
            scores = []
            for s in range(0, len(all_idx), batch_size):
                sl = np.asarray(all_idx[s : s + batch_size], np.int64)
                f = data.read_frames(first_of(sl))
                c = data.read_frames(sl)
                scores.append(
                    lc.score(
                        all_txt[s : s + batch_size],
                        f,
                        c,
                        data.proprio[first_of(sl)],
                        data.proprio[sl],
                    )
                )
            sc = np.concatenate(scores) if scores else np.zeros(0)
            near_sc = sc[len(pos_idx) + len(neg_idx) :]
            sc = sc[: len(pos_idx) + len(neg_idx)]
            if near_pos:
                pos_sc = sc[np.asarray(near_pos)]
                res["auc_near"] = roc_auc(
                    np.concatenate([pos_sc, near_sc]),
                    np.concatenate([np.ones(len(pos_sc), bool), np.zeros(len(near_sc), bool)]),
                )
                res["near_false_positive_rate"] = float(np.mean(near_sc >= 0.5))
            pred = sc >= 0.5
            tp = int(np.sum(pred & y))
            res["reward_pairs"] = len(y)
            res["precision"] = float(tp / max(int(pred.sum()), 1))
            res["recall"] = float(tp / max(int(y.sum()), 1))
            hard = np.concatenate([np.ones(len(pos_idx), bool), np.arange(len(neg_idx)) < n_hard])
            res["auc"] = roc_auc(sc[hard], y[hard])
            res["auc_with_idle"] = roc_auc(sc, y)
        results[name] = res
    if lc.captioner is not None and empty:
        sample = (
            empty if len(empty) <= max_pairs else list(rng.choice(empty, max_pairs, replace=False))
        )
        said = []
        for _, f, c, p0, p in batches(sorted(int(j) for j in sample)):
            said += [t == NONE_TEXT for t, _ in lc.caption(f, c, p0, p, beam=beam)]
        results["none_accuracy"] = float(np.mean(said))
    return results


def relabel_agreement(
    lc: LearnedCaptioner,
    data: CaptionDataset,
    thresholds: Sequence[float],
    families: Sequence[str] = (),
    episodes: np.ndarray | None = None,
    beam: int = 3,
    min_logprob: float = -1.0,
) -> dict[str, Any]:
    """How learned relabelling agrees with the rule captioner on whole episodes, scored as
    a training loop's :class:`LearnedLabeller` scores them: the candidates of an episode are
    the captioner's beam captions among the training instructions (of ``families``, if
    given) plus the episode's own instruction; the reward model judges every candidate at
    every step. Precision and recall count (step, candidate) pairs against the dataset's
    rule labels, at each reward threshold; the labels' precision and recall need none.
    Far more pairs are negative here than in :func:`evaluate_models`' balanced pairs, so
    this is the figure a threshold for ``--relabel.threshold`` is chosen on.

    Returns:
        ``{"episodes", "labels": {precision, recall}, "rewards": [{threshold, precision,
        recall, f1}, ...], "best_threshold"}`` (best: the highest F1).
    """
    lc.check_dataset(data)
    if lc.captioner is None or lc.reward is None:
        raise LcrlError(
            "relabelling agreement needs a checkpoint with a captioner and a reward model"
        )
    if episodes is None:
        same = lc.meta.get("dataset_meta") == data.meta and "val_episodes" in lc.meta
        episodes = (
            np.asarray(lc.meta["val_episodes"], np.int64) if same else np.arange(data.num_episodes)
        )
    texts = list(data.instructions)
    known = sorted({t.split()[0] for t in texts})
    unknown = [f for f in families if f not in known]
    if unknown:
        raise LcrlError(f"no instruction of family {unknown[0]!r} in the dataset; it has {known}")
    train = [
        t
        for t, kind in zip(texts, data.instruction_set, strict=True)
        if kind == "train" and (not families or t.split()[0] in families)
    ]
    # the loop's table: its training instructions first, the rest after
    in_train = set(train)
    table = train + [t for t in texts if t not in in_train]
    at = {t: i for i, t in enumerate(table)}
    to_table = [at[t] for t in texts]  # dataset instruction id -> table id
    lab = LearnedLabeller(lc, table, len(train), min_logprob=min_logprob, beam=beam)
    thresholds = sorted(float(x) for x in thresholds)
    counts = np.zeros((len(thresholds), 3), np.int64)  # tp, fp, fn per threshold
    for e in episodes:
        ep = data.episode(int(e))
        frames, proprio = ep["frames"], ep["proprio"]
        labels = lab.labels(frames, proprio)
        rule = [[to_table[i] for i in ids if to_table[i] < len(train)] for ids in ep["labels"]]
        lab.compare("labels", labels, rule)
        own = [to_table[ep["instruction"]]] if ep["instruction"] >= 0 else []
        cands = sorted({i for ids in labels for i in ids} | {i for i in own if i < len(train)})
        if not cands:
            continue
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        probs = lc.score_matrix([table[c] for c in cands], first, frames, p0, proprio)
        column = {c: k for k, c in enumerate(cands)}
        truth = np.zeros_like(probs, bool)
        for t, ids in enumerate(rule):
            for i in ids:
                if i in column:
                    truth[t, column[i]] = True
        truth[0] = False
        for k, thr in enumerate(thresholds):
            hit = probs >= thr
            hit[0] = False
            counts[k] += [(hit & truth).sum(), (hit & ~truth).sum(), (~hit & truth).sum()]
    agreement = lab.agreement()
    rows = []
    for thr, (tp, fp, fn) in zip(thresholds, counts, strict=True):
        precision = tp / (tp + fp) if tp + fp else float("nan")
        recall = tp / (tp + fn) if tp + fn else float("nan")
        f1 = 2 * precision * recall / (precision + recall) if tp else 0.0
        rows.append({"threshold": thr, "precision": precision, "recall": recall, "f1": f1})
    best = max(rows, key=lambda r: r["f1"])["threshold"] if rows else None
    return {
        "episodes": len(episodes),
        "families": list(families),
        "labels": {
            "precision": agreement["labels_precision"],
            "recall": agreement["labels_recall"],
        },
        "rewards": rows,
        "best_threshold": best,
    }


def format_agreement(result: dict[str, Any]) -> str:
    """:func:`relabel_agreement` as a few lines of text."""
    lab = result["labels"]
    lines = [
        f"learned relabelling against the rule captioner, {result['episodes']} whole episodes"
        + (f" ({', '.join(result['families'])})" if result["families"] else ""),
        f"labels: precision {lab['precision']:.2f}, recall {lab['recall']:.2f}",
        "rewards (every candidate at every step):",
    ]
    for r in result["rewards"]:
        lines.append(
            f"  threshold {r['threshold']:.2f}: precision {r['precision']:.2f}, recall "
            f"{r['recall']:.2f}, F1 {r['f1']:.2f}"
        )
    if result["best_threshold"] is not None:
        lines.append(f"best F1 at --relabel.threshold {result['best_threshold']:.2f}")
    return "\n".join(lines)


def format_results(results: dict[str, Any]) -> str:
    """A few lines for the terminal."""
    lines = [f"episodes evaluated: {results['episodes']}"]
    for name in ("seen", "heldout_combinations"):
        r = results.get(name)
        if not r:
            continue
        parts = [f"{name}: {r['observations']} observations"]
        if "exact_match" in r:
            slots = ", ".join(f"{g} {v:.2f}" for g, v in r["slot_accuracy"].items())
            parts.append(
                f"exact match {r['exact_match']:.2f}, BLEU-4 {r['bleu4']:.2f}, slots: {slots}"
            )
        if "auc" in r:
            parts.append(
                f"reward model AUC {r['auc']:.3f}, precision {r['precision']:.2f}, "
                f"recall {r['recall']:.2f} ({r['reward_pairs']} pairs)"
            )
        lines.append("; ".join(parts))
    if "none_accuracy" in results:
        lines.append(f"'<none>' where nothing was achieved: {results['none_accuracy']:.2f}")
    return "\n".join(lines)


def save_results(results: dict[str, Any], path: str | Path) -> Path:
    """Write evaluation results as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
    return path


# --------------------------------------------------------------------------- relabelling


class LearnedLabeller:
    """Labels a stored episode with the learned models, once per episode.

    ``labels`` are the relabelling candidates of each observation (what the learned
    captioner says the change since the first frame achieved, every beam caption whose
    log-likelihood is at least ``min_logprob``, restricted to the training instructions);
    ``achieved`` are the instructions the learned reward model judges satisfied at each
    observation (probability at least ``threshold``), scored for every candidate of the
    episode and its own instruction in one batch.

    Args:
        models: the loaded checkpoint.
        table: the run's instruction table; ids ``< num_train`` may be labels.
        num_train: number of training instructions at the front of ``table``.
        captioner: use the learned captioner for ``labels`` (else the caller's rule
            labels are kept).
        reward: use the learned reward model for ``achieved``.
        captioner_rewards: the captions are the rewards too (no reward model; the caller
            stores no separate ``achieved``).
        min_logprob: captions less likely than this are skipped.
        beam: beam width (0 or 1: greedy, one caption per observation).
        threshold: reward-model probability that counts as satisfied.
        family_thresholds: per-family overrides of ``threshold`` (``{"push": 0.9}``).
        agree: count an instruction as achieved at an observation only where the
            captioner's labels of that observation hold it too (both models agree).
        confirm: keep a caption as a relabelling candidate of an observation only where
            the reward model judges it achieved there (:meth:`confirmed`).
        reward_labels: the relabelling candidates of each observation are the training
            instructions the reward model judges achieved there, every one of them scored
            (no captioner).
    """

    def __init__(
        self,
        models: LearnedCaptioner,
        table: Sequence[str],
        num_train: int,
        captioner: bool = True,
        reward: bool = True,
        captioner_rewards: bool = False,
        min_logprob: float = -1.0,
        beam: int = 3,
        threshold: float = 0.5,
        agree: bool = False,
        family_thresholds: dict[str, float] | None = None,
        confirm: bool = False,
        reward_labels: bool = False,
    ) -> None:
        if captioner and models.captioner is None:
            raise LcrlError("learned relabelling needs a checkpoint with a captioner")
        if reward and models.reward is None:
            raise LcrlError("learned rewards need a checkpoint with a reward model")
        self.models = models
        self.table = list(table)
        self.train_ids = {t: i for i, t in enumerate(self.table[:num_train])}
        if captioner_rewards and (reward or not captioner):
            raise LcrlError("captioner rewards need the learned captioner and no reward model")
        self.use_captioner, self.use_reward = captioner, reward
        self.captioner_rewards = captioner_rewards
        self.min_logprob, self.beam, self.threshold = float(min_logprob), int(beam), threshold
        if agree and not (captioner and reward):
            raise LcrlError("agreement needs both the learned captioner and the reward model")
        self.agree = bool(agree)
        if confirm and not (captioner and reward):
            raise LcrlError("confirmation needs both the learned captioner and the reward model")
        self.confirm = bool(confirm)
        if reward_labels and (captioner or not reward):
            raise LcrlError("reward-model labels need the reward model and no learned captioner")
        self.reward_labels = bool(reward_labels)
        self.num_train = int(num_train)
        self.skipped = 0  # captions dropped by the threshold
        self.kept = 0
        # each instruction's family (its first word), for the agreement of each family
        self.families = [t.split()[0] if t.split() else "" for t in self.table]
        self.family_names = sorted(set(self.families[:num_train]) - {""})
        self.family_thresholds = dict(family_thresholds or {})
        self._agreement: dict[str, dict[str, int]] = {}

    def compare(self, kind: str, learned: Sequence[Sequence[int]], rule: Sequence[Sequence[int]],
                among: Sequence[int] | None = None) -> None:  # fmt: skip
        """Count how the learned ``kind`` (``labels`` or ``rewards``) agree with the rule
        captioner's, observation by observation (only ids in ``among``, if given)."""
        keep = None if among is None else set(int(i) for i in among)
        for pred, true in zip(learned, rule, strict=True):
            a, b = set(int(i) for i in pred), set(int(i) for i in true)
            if keep is not None:
                a, b = a & keep, b & keep
            for key, ids in (("tp", a & b), ("fp", a - b), ("fn", b - a)):
                for i in ids:
                    for name in (kind, f"{kind}_{self.families[i]}"):
                        self._agreement.setdefault(name, {"tp": 0, "fp": 0, "fn": 0})[key] += 1

    def agreement(self) -> dict[str, float]:
        """Precision and recall of the learned labels / rewards against the rule captioner
        since the last call (``nan`` where there was nothing to count), then reset: over
        all instructions (``labels_precision``, ...) and per family of the training
        instructions (``labels_push_precision``, ``rewards_reach_recall``, ...)."""
        out = {}
        for kind in ("labels", "rewards"):
            for name in (kind, *(f"{kind}_{f}" for f in self.family_names)):
                n = self._agreement.get(name, {"tp": 0, "fp": 0, "fn": 0})
                tp, fp, fn = n["tp"], n["fp"], n["fn"]
                out[f"{name}_precision"] = tp / (tp + fp) if tp + fp else float("nan")
                out[f"{name}_recall"] = tp / (tp + fn) if tp + fn else float("nan")
        self._agreement = {}
        return out

    def labels(self, frames: np.ndarray, proprio: np.ndarray) -> list[list[int]]:
        """Training-instruction ids the captioner reads in each observation."""
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        per_obs = self.models.captions(first, frames, p0, proprio, beam=self.beam)
        out = []
        for caps in per_obs:
            ids = []
            for text, score in caps:
                if text == NONE_TEXT or text not in self.train_ids:
                    continue
                if score < self.min_logprob:
                    self.skipped += 1
                    continue
                self.kept += 1
                ids.append(self.train_ids[text])
            out.append(sorted(set(ids)))
        out[0] = []  # nothing is achieved by the first observation relative to itself
        return out

    def satisfied(
        self,
        goals: Sequence[int],
        first: np.ndarray,
        frames: np.ndarray,
        p0: np.ndarray,
        proprio: np.ndarray,
    ) -> np.ndarray:
        """Whether the reward model judges each pair's instruction ``goals[i]`` achieved
        between ``first[i]`` and ``frames[i]`` (its family's threshold), ``(N,)`` bool: the
        online check that ends a training episode where the learned reward says so."""
        goals = [int(g) for g in goals]
        if not goals:
            return np.zeros(0, bool)
        cands = sorted(set(goals))
        col = {c: k for k, c in enumerate(cands)}
        probs = self.models.score_matrix([self.table[c] for c in cands], first, frames, p0, proprio)
        p = probs[np.arange(len(goals)), [col[g] for g in goals]]
        bar = [self.family_thresholds.get(self.families[g], self.threshold) for g in goals]
        return p >= np.asarray(bar, np.float32)

    def confirmed(
        self, labels: Sequence[Sequence[int]], achieved: Sequence[Sequence[int]]
    ) -> list[list[int]]:
        """With ``confirm``, each observation's labels that the reward model judges achieved
        there too (else the labels as they are)."""
        if not self.confirm:
            return [list(ids) for ids in labels]
        kept = []
        for ids, hit in zip(labels, achieved, strict=True):
            rewarded = set(hit)
            kept.append([i for i in ids if i in rewarded])
        return kept

    def achieved(
        self,
        frames: np.ndarray,
        proprio: np.ndarray,
        candidates: Sequence[int],
        labels: Sequence[Sequence[int]] | None = None,
    ) -> list[list[int]]:
        """For each observation, the candidate ids the reward model judges satisfied
        (with ``agree``, only those among that observation's ``labels`` too)."""
        cands = sorted(set(int(c) for c in candidates))
        if not cands:
            return [[] for _ in range(len(frames))]
        first = np.repeat(frames[:1], len(frames), 0)
        p0 = np.repeat(proprio[:1], len(proprio), 0)
        probs = self.models.score_matrix([self.table[c] for c in cands], first, frames, p0, proprio)
        bar = [self.family_thresholds.get(self.families[c], self.threshold) for c in cands]
        hit = probs >= np.asarray(bar, np.float32)
        hit[0] = False
        out = [[cands[k] for k in np.flatnonzero(row)] for row in hit]
        if self.agree:
            if labels is None:
                raise LcrlError("agreement needs each observation's captioner labels")
            out = [
                [c for c in row if c in keep]
                for row, keep in zip(out, map(set, labels), strict=True)
            ]
        return out

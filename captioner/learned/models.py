"""The networks: frame-pair and slot-pair encoders, the captioner (a GRU over the
vocabulary) and the reward model (FiLM by the instruction's embedding)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from captioner.learned.vocabulary import BOS, EOS, PAD
from lcrl.errors import LcrlError
from lcrl.nets import spatial_softmax
from lcrl.perception import Perception

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

    head: str = "sequence"
    """``sequence``: a GRU captioner writes the caption word by word and a reward model
    reads the instruction's text embedding. ``factored`` (needs ``encoder=perception``):
    one network scores every instruction of the grammar by its slots, a network shared by
    every object for reach, push and lift and one shared by every pair of objects for put
    and stack, so that a new combination of known words is read as a seen one
    (:mod:`captioner.learned.factored`); ``hidden`` is its width."""

    def validate(self) -> None:
        if self.head not in HEADS:
            raise LcrlError(f"model.head must be one of {HEADS}, got {self.head!r}")
        if self.head == "factored" and self.encoder != "perception":
            raise LcrlError(
                "model.head factored reads perception's object slots: pass "
                "--model.encoder perception and --perception MODEL"
            )
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
HEADS: tuple[str, ...] = ("sequence", "factored")


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


def split_slots(x: torch.Tensor, layout: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gripper's position ``(B, d)``, the objects' positions ``(B, K, d)`` and their
    presence ``(B, K)`` in perception's estimated observations ``(B, dim)``."""
    d = layout.position_dims
    slots = x[:, layout.start : layout.dim].reshape(-1, layout.count, layout.width)
    return x[:, :d], slots[..., :d], slots[..., d]


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
        _, pos0, on0 = split_slots(first.float(), self.layout)
        g, pos, on = split_slots(current.float(), self.layout)
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

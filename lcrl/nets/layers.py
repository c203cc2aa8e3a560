"""The network config and the layers everything else is made of: MLPs, the CNN, batched linear
layers, spatial softmax and random-shift augmentation."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

FUSIONS = ("concat", "film")


SLOT_MODES = ("attention", "select", "attributes")


@dataclass
class NetConfig:
    """Network sizes and fusion."""

    hidden: tuple[int, ...] = (256, 256)
    """Hidden layer widths of the fused MLP (actor and critics)."""
    state_layers: tuple[int, ...] = ()
    """Hidden widths of the vector-observation encoder; empty means the identity."""
    goal_layers: tuple[int, ...] = ()
    """Hidden widths of the vector-goal encoder; empty means the identity."""
    text_dim: int = 64
    """Width of the learned projection of a frozen text embedding (or one-hot task id)."""
    fusion: str = "concat"
    """How goal and observation features meet: ``concat`` or ``film``."""
    cnn_channels: tuple[int, ...] = (32, 32, 32, 32)
    """Channels of the image encoder's 3x3 convolutions (the first has stride 2)."""
    cnn_features: int = 50
    """Output width of the image encoder (linear + layer norm after the convolutions)."""
    slots: tuple[int, ...] = ()
    """``(start, count, width)`` of per-object slots inside vector observations (e.g.
    ``(2, 8, 3)`` for the 2D tabletop: after the pusher's x, y, 8 object kinds of x, y,
    present). When set, those observations are read by goal-conditioned attention over
    objects: a shared MLP encodes each slot (plus a learned embedding of which slot it
    is), the goal picks slots by attention, and the picked features go to the fused MLP.
    Empty: plain concatenation."""
    slot_mode: str = "attention"
    """How the goal reads the object slots: ``attention`` (each slot encoded by a shared
    MLP, picked by query-key attention), ``select`` (the goal alone picks slots by
    position, a softmax over slot indices per head, and the picked slots' raw values
    are added to the full observation: cheap, and enough wherever a slot's position
    says which object it holds, as in both tabletops) or ``attributes`` (``select``
    with each slot's logit the sum of the goal's scores of its attribute values,
    ``slot_attributes``)."""
    slot_attributes: tuple[int, ...] = ()
    """With ``slot_mode="attributes"``: for each attribute the slots have (colour, then
    shape on both tabletops), the value of that attribute in every slot, ``count``
    numbers per attribute, attributes one after another. The goal then scores each
    attribute value, and a slot's logit is the sum of its values' scores, so that
    "blue" and "cylinder" each select what they name, also in combinations never
    trained on."""
    slot_dim: int = 64
    """Width of the per-slot features of the object attention."""
    slot_heads: int = 2
    """Attention heads over objects (put and stack name two objects)."""
    share_cnn: bool = False
    """Image goals are read by the same CNN as the image observation of the same shape
    (one encoder per network instead of two)."""
    task_heads: int = 0
    """Per-task output heads (multi-task RL with one-hot task ids): the last layer of the
    actor and of each critic is one linear head per task over the shared trunk, picked by
    the task id (the argmax of the one-hot goal). Set it to the number of tasks; 0: one
    shared output layer."""


def mlp(sizes: Sequence[int], out_act: bool = False) -> nn.Sequential:
    """``Linear-ReLU`` stack through ``sizes``; ReLU after the last layer if ``out_act``."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or out_act:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class ConvEncoder(nn.Module):
    """CNN for uint8 ``(B, H, W, C)`` images: conv stack, linear, layer norm, tanh."""

    def __init__(self, shape: Sequence[int], channels: Sequence[int], features: int) -> None:
        super().__init__()
        h, w, c = shape
        convs: list[nn.Module] = []
        for i, ch in enumerate(channels):
            convs += [nn.Conv2d(c, ch, 3, stride=2 if i == 0 else 1), nn.ReLU()]
            c = ch
        self.convs = nn.Sequential(*convs)
        with torch.no_grad():
            n = self.convs(torch.zeros(1, shape[2], h, w)).numel()
        self.head = nn.Sequential(nn.Linear(n, features), nn.LayerNorm(features), nn.Tanh())
        self.out_dim = features

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = image.permute(0, 3, 1, 2).float() / 255.0 - 0.5
        return self.head(self.convs(x).flatten(1))


def spatial_softmax(h: torch.Tensor, temperature: torch.Tensor) -> torch.Tensor:
    """Expected image coordinates ``(B, 2C)`` in [-1, 1] of each channel's softmax over
    the positions of ``h`` ``(B, C, H, W)`` (rows first, then columns)."""
    b, c, hh, ww = h.shape
    attn = torch.softmax(h.flatten(2) / temperature, -1).view(b, c, hh, ww)
    ys = torch.linspace(-1.0, 1.0, hh, device=h.device, dtype=h.dtype)
    xs = torch.linspace(-1.0, 1.0, ww, device=h.device, dtype=h.dtype)
    return torch.cat([(attn.sum(3) * ys).sum(2), (attn.sum(2) * xs).sum(2)], -1)


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator) -> torch.Tensor:
    """DrQ's random shift: pad ``(B, H, W, C)`` images by ``pad`` edge pixels and crop each
    back to ``(H, W)`` at a random offset; returns float images on the same 0-255 scale."""
    b, h, w, _ = images.shape
    x = F.pad(images.permute(0, 3, 1, 2).float(), (pad, pad, pad, pad), mode="replicate")
    dev = images.device
    oy = torch.randint(0, 2 * pad + 1, (b, 1), generator=generator, device=dev)
    ox = torch.randint(0, 2 * pad + 1, (b, 1), generator=generator, device=dev)
    rows = (oy + torch.arange(h, device=dev))[:, None, :, None].expand(
        -1, x.shape[1], -1, x.shape[3]
    )
    x = x.gather(2, rows)
    cols = (ox + torch.arange(w, device=dev))[:, None, None, :].expand(-1, x.shape[1], h, -1)
    return x.gather(3, cols).permute(0, 2, 3, 1)


class BatchedLinear(nn.Module):
    """``n`` independent linear layers applied at once: ``(n, B, in) -> (n, B, out)``.

    Each member is initialised like :class:`torch.nn.Linear`.
    """

    def __init__(self, n: int, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(n, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(n, 1, out_dim))
        bound = 1.0 / math.sqrt(in_dim)
        with torch.no_grad():
            for i in range(n):
                w = torch.empty(out_dim, in_dim)
                nn.init.kaiming_uniform_(w, a=math.sqrt(5))
                self.weight[i].copy_(w.T)
            self.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.shape[2] == 1:
            # one output per member (the critics' values): a batched matrix-vector product,
            # which bmm runs about 6x slower on the CPU than a product and a sum, forward
            # and backward
            w = self.weight.transpose(1, 2).to(x.dtype)
            return (x * w).sum(-1, keepdim=True) + self.bias.to(x.dtype)
        if x.dim() == 2:
            x = x.expand(self.weight.shape[0], *x.shape)
        return torch.baddbmm(self.bias, x, self.weight)

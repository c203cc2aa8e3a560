"""Encoders and universal value function approximators (UVFA) for goal-conditioned RL.

A network sees an observation and a goal through *separate* encoders, then fuses them:

* the observation encoder concatenates one encoder per observation key: an MLP (or the
  identity) for vector keys, a CNN for uint8 image keys (``(H, W, C)``);
* the goal encoder is an MLP (or the identity) for vector goals, a learned projection of
  the frozen text embedding for language goals, a linear layer for one-hot task ids, or a
  CNN for image goals: :data:`GOAL_ENCODERS` names the encoder of each goal kind;
* fusion is concatenation followed by an MLP (default), or FiLM: the goal produces a
  per-unit scale and shift for every hidden layer of the MLP that reads the observation.

Parameters of each network are packed into one flat buffer (:func:`flatten_parameters`)
so that :class:`FlatAdam` updates them with a handful of vectorised operations.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from lcrl.errors import LcrlError

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


class _SlotReader(nn.Module):
    """Shared part of the slot readers: the ``(start, count, width)`` layout and the
    slots of every key side by side, ``(B, count, keys * width)``."""

    def __init__(self, layout: Sequence[int]) -> None:
        super().__init__()
        start, count, width = (int(v) for v in layout)
        self.start, self.count, self.width = start, count, width
        self.end = start + count * width

    def _slots(self, xs: Sequence[torch.Tensor]) -> torch.Tensor:
        b = xs[0].shape[0]
        return torch.cat(
            [x[:, self.start : self.end].reshape(b, self.count, self.width) for x in xs], -1
        )


class SlotAttention(_SlotReader):
    """Goal-conditioned attention over object slots of vector observations.

    Every key's vector is ``[global (start values), count slots of width values,
    rest]``. Slot ``i`` is encoded by a shared MLP from its values in every key, the
    global and rest values, and a learned embedding of ``i`` (which object kind the slot
    holds); each head's query comes from the goal features. Output: the attended slot
    features of every head, then the global and rest values.

    Args:
        dims: vector width of each key (all keys share the slot layout).
        layout: ``(start, count, width)``.
        goal_dim: width of the goal features.
        cfg: network config (``slot_dim``, ``slot_heads``).
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(layout)
        count, width = self.count, self.width
        self.extra = sum(d - count * width for d in dims)  # global + rest values, all keys
        d, heads = cfg.slot_dim, cfg.slot_heads
        self.identity = nn.Parameter(torch.randn(count, d) * 0.1)
        self.slot_mlp = mlp([len(dims) * width + self.extra + d, d, d], out_act=True)
        self.query = nn.Linear(goal_dim, heads * d)
        self.key = nn.Linear(d, heads * d)
        self.heads, self.d = heads, d
        self.out_dim = heads * d + self.extra

    def _encode(self, xs: Sequence[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-slot features ``(B, count, d)`` and the global and rest values."""
        b = xs[0].shape[0]
        slots = self._slots(xs)
        extra = torch.cat([torch.cat([x[:, : self.start], x[:, self.end :]], -1) for x in xs], -1)
        per_slot = torch.cat(
            [
                slots,
                extra.unsqueeze(1).expand(b, self.count, self.extra),
                self.identity.expand(b, -1, -1),
            ],
            -1,
        )
        return self.slot_mlp(per_slot), extra

    def _scores(self, h: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        b = h.shape[0]
        q = self.query(goal).view(b, self.heads, 1, self.d)
        k = self.key(h).view(b, self.count, self.heads, self.d).transpose(1, 2)
        return (q * k).sum(-1) / math.sqrt(self.d)  # (B, heads, count)

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each head's attention logits over the slots, ``(B, heads, count)``."""
        return self._scores(self._encode(xs)[0], goal)

    def forward(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = xs[0].shape[0]
        h, extra = self._encode(xs)
        w = torch.softmax(self._scores(h, goal), -1)  # (B, heads, count)
        picked = torch.einsum("bhc,bcd->bhd", w, h).reshape(b, self.heads * self.d)
        return torch.cat([picked, extra], -1)


class SlotSelect(_SlotReader):
    """Goal-conditioned selection of object slots by position.

    Every key's vector is ``[global (start values), count slots of width values,
    rest]``, and slot ``i`` always holds the same object kind. Each head turns the goal
    features into softmax weights over the ``count`` slot positions and picks the
    weighted sum of the slots' raw values (from every key); the output is the picked
    values of every head followed by every key's full vector, so that nothing is lost.

    Args:
        dims: vector width of each key (all keys share the slot layout).
        layout: ``(start, count, width)``.
        goal_dim: width of the goal features.
        cfg: network config (``slot_heads``).
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(layout)
        self.heads = cfg.slot_heads
        self.logits = nn.Linear(goal_dim, self.heads * self.count)
        self.out_dim = self.heads * len(dims) * self.width + sum(dims)

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each head's logits over the slot positions, ``(B, heads, count)``."""
        return self.logits(goal).view(goal.shape[0], self.heads, self.count)

    def forward(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = xs[0].shape[0]
        slots = self._slots(xs)
        w = torch.softmax(self.selection_logits(xs, goal), -1)
        picked = torch.bmm(w, slots).reshape(b, -1)  # (B, heads * keys * width)
        return torch.cat([picked, *xs], -1)


def grounding_loss(logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of slot selection against the slots an instruction names.

    Args:
        logits: ``(n, B, heads, count)`` selection logits of ``n`` networks.
        targets: ``(B, T)`` slot index named for head ``t`` (the object acted on, then
            the reference object of two-object families), -1 where none is.

    Returns:
        The mean over networks of the summed per-head cross-entropies (each averaged over
        its rows with a target); 0 where no row has one.
    """
    n, b, heads, count = logits.shape
    total = logits.new_zeros(())
    for t in range(min(heads, targets.shape[1])):
        y = targets[:, t]
        if not bool((y >= 0).any()):
            continue
        flat = logits[:, :, t].reshape(n * b, count)
        total = total + F.cross_entropy(flat, y.repeat(n), ignore_index=-1)
    return total


class SlotAttributes(SlotSelect):
    """:class:`SlotSelect` whose logits go through the slots' attributes: per head and
    attribute the goal features score every value of the attribute, and a slot's logit
    is the sum of the scores of its values (``cfg.slot_attributes``).

    Raises:
        LcrlError: ``slot_attributes`` is not ``count`` non-negative values per attribute.
    """

    def __init__(
        self, dims: Sequence[int], layout: Sequence[int], goal_dim: int, cfg: NetConfig
    ) -> None:
        super().__init__(dims, layout, goal_dim, cfg)
        del self.logits
        values = [int(v) for v in cfg.slot_attributes]
        if not values or len(values) % self.count or min(values) < 0:
            raise LcrlError(
                f"slot_mode attributes needs slot_attributes: {self.count} values (one per "
                f"slot) for each attribute, got {tuple(values)}"
            )
        table = torch.tensor(values).view(-1, self.count)  # (attributes, count)
        self.scores = nn.ModuleList()
        for a, row in enumerate(table):
            onehot = F.one_hot(row, int(row.max()) + 1).float()  # (count, values)
            self.register_buffer(f"onehot{a}", onehot, persistent=False)
            self.scores.append(nn.Linear(goal_dim, self.heads * onehot.shape[1]))

    def selection_logits(self, xs: Sequence[torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        b = goal.shape[0]
        out = goal.new_zeros(b, self.heads, self.count)
        for a, score in enumerate(self.scores):
            onehot = getattr(self, f"onehot{a}")
            out = out + score(goal).view(b, self.heads, -1) @ onehot.T
        return out


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


class ObsEncoder(nn.Module):
    """One encoder per observation key, outputs concatenated (keys in sorted order).

    With ``cfg.slots`` set, the vector keys that hold that slot layout are read together by
    :class:`SlotAttention` (which needs the goal features).

    Args:
        obs_shapes: ``{key: shape}``; 1-D shapes are vectors, 3-D ``(H, W, C)`` images.
        cfg: network config.
        goal_dim: width of the goal features (for object attention).
    """

    def __init__(
        self, obs_shapes: Mapping[str, Sequence[int]], cfg: NetConfig, goal_dim: int = 0
    ) -> None:
        super().__init__()
        self.keys = sorted(obs_shapes)
        self.encoders = nn.ModuleDict()
        self.slot_keys: list[str] = []
        self.slots: SlotAttention | SlotSelect | None = None
        dim = 0
        if cfg.slots:
            if len(cfg.slots) != 3:
                raise LcrlError(f"slots must be (start, count, width), got {cfg.slots}")
            start, count, width = cfg.slots
            self.slot_keys = [
                k
                for k in self.keys
                if len(obs_shapes[k]) == 1 and obs_shapes[k][0] >= start + count * width
            ]
            if not self.slot_keys:
                raise LcrlError(
                    f"no vector observation holds the slot layout {tuple(cfg.slots)}: "
                    f"shapes {dict(obs_shapes)}"
                )
            if cfg.slot_mode not in SLOT_MODES:
                raise LcrlError(f"unknown slot_mode {cfg.slot_mode!r}; choose one of {SLOT_MODES}")
            reader = {
                "attention": SlotAttention,
                "select": SlotSelect,
                "attributes": SlotAttributes,
            }[cfg.slot_mode]
            self.slots = reader(
                [obs_shapes[k][0] for k in self.slot_keys], cfg.slots, goal_dim, cfg
            )
            dim += self.slots.out_dim
        for key in self.keys:
            shape = tuple(obs_shapes[key])
            if key in self.slot_keys:
                continue
            if len(shape) == 1:
                if cfg.state_layers:
                    enc: nn.Module = mlp([shape[0], *cfg.state_layers], out_act=True)
                    dim += cfg.state_layers[-1]
                else:
                    enc = nn.Identity()
                    dim += shape[0]
            elif len(shape) == 3:
                enc = ConvEncoder(shape, cfg.cnn_channels, cfg.cnn_features)
                dim += enc.out_dim
            else:
                raise LcrlError(
                    f"observation {key!r} has shape {shape}: expected (d,) or (H, W, C)"
                )
            self.encoders[key] = enc
        self.out_dim = dim

    def selection_logits(self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """The slot reader's logits over object slots per head, ``(B, heads, count)``,
        from the goal features.

        Raises:
            LcrlError: the encoder reads no object slots.
        """
        if self.slots is None:
            raise LcrlError("grounding needs networks that read object slots (net.slots)")
        return self.slots.selection_logits([obs[k] for k in self.slot_keys], goal)

    def forward(
        self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor | None = None
    ) -> torch.Tensor:
        feats = [self.encoders[k](obs[k]) for k in self.keys if k in self.encoders]
        if self.slots is not None:
            if goal is None:
                raise LcrlError("object attention needs the goal features")
            feats.insert(0, self.slots([obs[k] for k in self.slot_keys], goal))
        return feats[0] if len(feats) == 1 else torch.cat(feats, -1)


#: ``(goal shape, network config, shared CNN or None) -> (module, output width)``.
GoalEncoderFactory = Callable[[tuple[int, ...], NetConfig, nn.Module | None], tuple[nn.Module, int]]


@dataclass(frozen=True)
class GoalEncoderSpec:
    """One goal kind of :data:`GOAL_ENCODERS`.

    Attributes:
        make: builds the encoder's module and gives its output width. It is stored as
            the :class:`GoalEncoder`'s ``net`` (so its parameters are saved as
            ``net.*``). With ``share_cnn`` and an image-shaped goal ``(H, W, C)`` it gets
            the observation encoder's CNN, which reads the goal instead (the module it
            returns then holds no parameters of its own).
        task_ids: goals are one-hot task ids: per-task output heads
            (:attr:`NetConfig.task_heads`) may pick a head by them.
    """

    make: GoalEncoderFactory
    task_ids: bool = False


def vector_goal_encoder(
    shape: tuple[int, ...], cfg: NetConfig, shared: nn.Module | None = None
) -> tuple[nn.Module, int]:
    """Goal vectors (positions): an MLP of ``cfg.goal_layers``, or the identity."""
    if cfg.goal_layers:
        return mlp([shape[0], *cfg.goal_layers], out_act=True), cfg.goal_layers[-1]
    return nn.Identity(), shape[0]


def projected_goal_encoder(
    shape: tuple[int, ...], cfg: NetConfig, shared: nn.Module | None = None
) -> tuple[nn.Module, int]:
    """Frozen text embeddings and one-hot task ids: a learned linear projection to
    ``cfg.text_dim`` with layer norm."""
    net = nn.Sequential(nn.Linear(shape[0], cfg.text_dim), nn.LayerNorm(cfg.text_dim))
    return net, cfg.text_dim


def image_goal_encoder(
    shape: tuple[int, ...], cfg: NetConfig, shared: nn.Module | None = None
) -> tuple[nn.Module, int]:
    """Goal camera frames: a CNN of their own, or the identity when the observation's CNN
    (``shared``) reads them."""
    if shared is not None:
        return nn.Identity(), cfg.cnn_features
    return ConvEncoder(shape, cfg.cnn_channels, cfg.cnn_features), cfg.cnn_features


#: Every goal kind (:attr:`lcrl.algos.Problem.goal_kind`, set by a task's ``goal_kind``):
#: how the networks encode its goals. A new kind is one entry here (and, for a goal
#: normaliser, one in :data:`lcrl.algos.base.GOAL_NORMALISERS`).
GOAL_ENCODERS: dict[str, GoalEncoderSpec] = {
    "vector": GoalEncoderSpec(vector_goal_encoder),
    "text": GoalEncoderSpec(projected_goal_encoder),
    "onehot": GoalEncoderSpec(projected_goal_encoder, task_ids=True),
    "image": GoalEncoderSpec(image_goal_encoder),
}


def goal_encoder_spec(kind: str) -> GoalEncoderSpec:
    """The registry entry of a goal kind.

    Raises:
        LcrlError: no goal kind of that name.
    """
    spec = GOAL_ENCODERS.get(kind)
    if spec is None:
        raise LcrlError(f"unknown goal kind {kind!r}; choose one of {tuple(GOAL_ENCODERS)}")
    return spec


class GoalEncoder(nn.Module):
    """Encodes embedded goals with the module of their kind (:data:`GOAL_ENCODERS`):
    identity/MLP, text projection, one-hot projection or CNN.

    Args:
        kind: a key of :data:`GOAL_ENCODERS` (``vector``, ``text``, ``onehot``, ``image``).
        shape: shape of one embedded goal.
        cfg: network config.
        shared: the observation encoder's CNN, which reads image goals too.
    """

    def __init__(
        self, kind: str, shape: Sequence[int], cfg: NetConfig, shared: nn.Module | None = None
    ) -> None:
        super().__init__()
        spec = goal_encoder_spec(kind)
        self.kind = kind
        # A shared CNN belongs to the observation encoder: kept out of this module's
        # parameters so that it is saved and optimised once.
        self._shared = [shared] if shared is not None else []
        self.net, self.out_dim = spec.make(tuple(shape), cfg, shared)

    def forward(self, goal: torch.Tensor) -> torch.Tensor:
        if self._shared:
            return self._shared[0](goal)
        return self.net(goal)


def build_encoders(
    obs_shapes: Mapping[str, Sequence[int]],
    goal_kind: str,
    goal_shape: Sequence[int],
    cfg: NetConfig,
) -> tuple[ObsEncoder, GoalEncoder]:
    """The observation and goal encoders of one network (sharing a CNN if configured and
    the goals are images, ``(H, W, C)``)."""
    if cfg.share_cnn and len(goal_shape) == 3:
        matches = sorted(k for k, v in obs_shapes.items() if tuple(v) == tuple(goal_shape))
        if not matches:
            raise LcrlError(
                f"share_cnn needs an image observation of the goal's shape {tuple(goal_shape)}; "
                f"observations are {dict(obs_shapes)}"
            )
        obs_encoder = ObsEncoder(obs_shapes, cfg, cfg.cnn_features)
        return obs_encoder, GoalEncoder(
            goal_kind, goal_shape, cfg, shared=obs_encoder.encoders[matches[0]]
        )
    goal_encoder = GoalEncoder(goal_kind, goal_shape, cfg)
    return ObsEncoder(obs_shapes, cfg, goal_encoder.out_dim), goal_encoder


class TaskHeads(nn.Module):
    """One linear layer per task; row ``b`` of the input goes through head ``task[b]``.

    Each head is initialised like :class:`torch.nn.Linear`. With ``members`` > 0 the heads
    belong to an ensemble: inputs ``(members, B, in)`` (or ``(B, in)``, shared), outputs
    ``(members, B, out)``.

    Args:
        num_tasks: heads.
        in_dim: input width (the trunk's last hidden layer).
        out_dim: output width.
        members: ensemble members (0: a single network).
    """

    def __init__(self, num_tasks: int, in_dim: int, out_dim: int, members: int = 0) -> None:
        super().__init__()
        self.members = members
        lead = (members,) if members else ()
        self.weight = nn.Parameter(torch.empty(*lead, num_tasks, in_dim, out_dim))
        self.bias = nn.Parameter(torch.empty(*lead, num_tasks, out_dim))
        bound = 1.0 / math.sqrt(in_dim)
        with torch.no_grad():
            w = self.weight.view(-1, in_dim, out_dim)
            for i in range(w.shape[0]):
                layer = torch.empty(out_dim, in_dim)
                nn.init.kaiming_uniform_(layer, a=math.sqrt(5))
                w[i].copy_(layer.T)
            self.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
        rows = torch.arange(task.shape[0], device=task.device)
        if not self.members:
            out = torch.einsum("bi,kio->bko", x, self.weight) + self.bias
            return out[rows, task]
        if x.dim() == 2:
            x = x.expand(self.members, *x.shape)
        out = torch.einsum("nbi,nkio->nbko", x, self.weight) + self.bias[:, None]
        return out[:, rows, task]


def check_task_heads(cfg: NetConfig, goal_kind: str, goal_shape: Sequence[int]) -> int:
    """The number of per-task heads of a network (0 for none).

    Raises:
        LcrlError: heads asked for with goals that are not one-hot task ids, or a number of
            heads other than the number of tasks.
    """
    heads = int(cfg.task_heads)
    if heads < 0:
        raise LcrlError(f"net.task_heads must be >= 0, got {heads}")
    if not heads:
        return 0
    if not goal_encoder_spec(goal_kind).task_ids:
        raise LcrlError(
            f"net.task_heads picks a head by one-hot task id, but this network's goals are "
            f"{goal_kind!r}: use --env.goal-type task, or set net.task_heads=0"
        )
    if heads != int(goal_shape[0]):
        raise LcrlError(
            f"net.task_heads is {heads} but there are {goal_shape[0]} tasks: set "
            f"--agent.net.task-heads {goal_shape[0]}"
        )
    return heads


class FusedMLP(nn.Module):
    """MLP over (features, goal features [, extra input]) with concat or FiLM fusion.

    ``concat``: ``MLP([x, g, extra])``. ``film``: ``h_l = relu(W_l h_{l-1}) * (1 + gamma_l(g))
    + beta_l(g)`` for every hidden layer, the first reading ``[x, extra]``. With
    ``task_heads`` the output layer is a :class:`TaskHeads` picked by ``task``.
    """

    def __init__(
        self,
        in_dim: int,
        goal_dim: int,
        out_dim: int,
        hidden: Sequence[int],
        fusion: str,
        task_heads: int = 0,
    ) -> None:
        super().__init__()
        if fusion not in FUSIONS:
            raise LcrlError(f"unknown fusion {fusion!r}; choose one of {FUSIONS}")
        if not hidden:
            raise LcrlError("the fused MLP needs at least one hidden layer")
        self.fusion = fusion
        self.task_heads = task_heads
        if fusion == "concat" and task_heads:
            self.net = mlp([in_dim + goal_dim, *hidden], out_act=True)
            self.heads = TaskHeads(task_heads, hidden[-1], out_dim)
        elif fusion == "concat":
            self.net = mlp([in_dim + goal_dim, *hidden, out_dim])
        else:
            sizes = [in_dim, *hidden]
            self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(sizes))
            self.film = nn.Linear(goal_dim, 2 * sum(hidden))
            nn.init.zeros_(self.film.weight)
            nn.init.zeros_(self.film.bias)
            self.out: nn.Module = (
                TaskHeads(task_heads, hidden[-1], out_dim)
                if task_heads
                else nn.Linear(hidden[-1], out_dim)
            )
            self.hidden = tuple(hidden)

    def forward(
        self, x: torch.Tensor, g: torch.Tensor, task: torch.Tensor | None = None
    ) -> torch.Tensor:
        if self.fusion == "concat":
            h = self.net(torch.cat([x, g], -1))
            return self.heads(h, task) if self.task_heads else h
        params = self.film(g).split([h for h in self.hidden for _ in range(2)], -1)
        h = x
        for i, layer in enumerate(self.layers):
            h = F.relu(layer(h)) * (1 + params[2 * i]) + params[2 * i + 1]
        return self.out(h, task) if self.task_heads else self.out(h)


class GoalConditionedNet(nn.Module):
    """Observation encoder + goal encoder + fused MLP: ``f(obs, goal[, action])``.

    Args:
        obs_shapes: ``{key: shape}`` of the observation.
        goal_kind: goal encoder kind (see :class:`GoalEncoder`).
        goal_shape: shape of one embedded goal.
        out_dim: output width.
        cfg: network config.
        action_dim: width of an action input (critics), 0 for none.
    """

    def __init__(
        self,
        obs_shapes: Mapping[str, Sequence[int]],
        goal_kind: str,
        goal_shape: Sequence[int],
        out_dim: int,
        cfg: NetConfig,
        action_dim: int = 0,
    ) -> None:
        super().__init__()
        obs_encoder, goal_encoder = build_encoders(obs_shapes, goal_kind, goal_shape, cfg)
        self.goal_encoder = goal_encoder  # registered first: parameter order as before
        self.obs_encoder = obs_encoder
        self.task_heads = check_task_heads(cfg, goal_kind, goal_shape)
        self.head = FusedMLP(
            self.obs_encoder.out_dim + action_dim,
            self.goal_encoder.out_dim,
            out_dim,
            cfg.hidden,
            cfg.fusion,
            self.task_heads,
        )

    def forward(
        self,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        g = self.goal_encoder(goal)
        x = self.obs_encoder(obs, g)
        if action is not None:
            x = torch.cat([x, action], -1)
        # float32 out, also where the update runs under bf16 autocast (agent precision)
        if self.task_heads:
            return self.head(x, g, goal.argmax(-1)).float()
        return self.head(x, g).float()

    def selection_logits(self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Logits of the object slots the goal picks, ``(1, B, heads, count)``."""
        return self.obs_encoder.selection_logits(obs, self.goal_encoder(goal)).unsqueeze(0).float()


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
        if x.dim() == 2:
            x = x.expand(self.weight.shape[0], *x.shape)
        return torch.baddbmm(self.bias, x, self.weight)


class GoalConditionedEnsemble(nn.Module):
    """``n`` independent :class:`GoalConditionedNet` s evaluated together: ``(n, B, out)``.

    With concatenation fusion the members' MLPs run as batched matrix products (one call
    per layer for all members), and members whose encoders have no parameters (vector
    inputs) share the encoding work; FiLM heads and learned encoders run per member.

    Args:
        n: number of members (2 for twin critics).
        obs_shapes, goal_kind, goal_shape, out_dim, cfg, action_dim: as for
            :class:`GoalConditionedNet`.
    """

    def __init__(
        self,
        n: int,
        obs_shapes: Mapping[str, Sequence[int]],
        goal_kind: str,
        goal_shape: Sequence[int],
        out_dim: int,
        cfg: NetConfig,
        action_dim: int = 0,
    ) -> None:
        super().__init__()
        self.n = n
        pairs = [build_encoders(obs_shapes, goal_kind, goal_shape, cfg) for _ in range(n)]
        self.goal_encoders = nn.ModuleList(goal for _, goal in pairs)
        self.obs_encoders = nn.ModuleList(obs for obs, _ in pairs)
        self.shared = not any(
            p.numel()
            for enc in (self.obs_encoders[0], self.goal_encoders[0])
            for p in enc.parameters()
        )
        in_dim = self.obs_encoders[0].out_dim + action_dim
        goal_dim = self.goal_encoders[0].out_dim
        self.batched = cfg.fusion == "concat"
        self.task_heads = check_task_heads(cfg, goal_kind, goal_shape)
        if self.batched:
            sizes = [in_dim + goal_dim, *cfg.hidden, out_dim]
            if self.task_heads:
                sizes = sizes[:-1]
            self.layers = nn.ModuleList(
                BatchedLinear(n, a, b) for a, b in itertools.pairwise(sizes)
            )
            if self.task_heads:
                self.out_heads = TaskHeads(self.task_heads, cfg.hidden[-1], out_dim, members=n)
        else:
            self.heads = nn.ModuleList(
                FusedMLP(in_dim, goal_dim, out_dim, cfg.hidden, cfg.fusion, self.task_heads)
                for _ in range(n)
            )

    def _features(
        self,
        i: int,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.goal_encoders[i](goal)
        x = self.obs_encoders[i](obs, g)
        if action is not None:
            x = torch.cat([x, action], -1)
        return x, g

    def selection_logits(self, obs: Mapping[str, torch.Tensor], goal: torch.Tensor) -> torch.Tensor:
        """Each member's logits of the object slots the goal picks, ``(n, B, heads,
        count)``."""
        return torch.stack(
            [
                enc.selection_logits(obs, goal_enc(goal))
                for enc, goal_enc in zip(self.obs_encoders, self.goal_encoders, strict=True)
            ]
        ).float()

    def forward(
        self,
        obs: Mapping[str, torch.Tensor],
        goal: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        task = goal.argmax(-1) if self.task_heads else None
        if not self.batched:
            outs = []
            for i in range(self.n):
                x, g = self._features(i, obs, goal, action)
                outs.append(self.heads[i](x, g, task))
            return torch.stack(outs).float()
        if self.shared:
            h = torch.cat(self._features(0, obs, goal, action), -1)
        else:
            h = torch.stack(
                [torch.cat(self._features(i, obs, goal, action), -1) for i in range(self.n)]
            )
        last = len(self.layers) - (0 if self.task_heads else 1)
        for k, layer in enumerate(self.layers):
            h = layer(h)
            if k < last:
                h = F.relu(h)
        if self.task_heads:
            return self.out_heads(h, task).float()
        return h.float()


class RunningNorm(nn.Module):
    """Running mean / std normaliser with clipping; statistics are saved as buffers.

    Args:
        dim: feature width.
        clip: clip normalised values to ``[-clip, clip]``.
        eps: floor of the standard deviation.
    """

    def __init__(self, dim: int, clip: float = 5.0, eps: float = 1e-2) -> None:
        super().__init__()
        self.clip = clip
        self.eps = eps
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("var", torch.ones(dim))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self._inv_std: torch.Tensor | None = None

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Fold a ``(N, dim)`` batch into the statistics (parallel Welford)."""
        x = x.reshape(-1, self.mean.shape[0]).to(self.mean.device, torch.float32)
        n = x.shape[0]
        if n == 0:
            return
        mean, var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        new_mean = self.mean + delta * (n / total)
        m2 = self.var * self.count + var * n + delta.pow(2) * (self.count * n / total)
        self.mean.copy_(new_mean)
        self.var.copy_((m2 / total).float())
        self.count.fill_(total)
        self._inv_std = None

    def _scale(self) -> torch.Tensor:
        if self._inv_std is None:
            inv = self.var.sqrt().clamp_min(self.eps).reciprocal()
            if torch.is_inference_mode_enabled():  # not cached: autograd cannot save it
                return inv
            self._inv_std = inv
        return self._inv_std

    def _load_from_state_dict(self, *args: object, **kwargs: object) -> None:
        self._inv_std = None
        super()._load_from_state_dict(*args, **kwargs)  # type: ignore[arg-type]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) * self._scale()).clamp_(-self.clip, self.clip)


class WhiteningNorm(nn.Module):
    """Regularised PCA whitening of a fixed set of vectors (frozen text embeddings).

    Sentence embeddings of instructions that differ in one word are nearly parallel
    (cosine 0.98 between "push the red cube left" and "... right" with all-MiniLM-L6-v2):
    the words that tell goals apart live in directions of tiny variance, which a network
    reading the raw or per-dimension standardised embedding learns to use only slowly.
    :meth:`fit` centres the vectors and rescales each principal direction of their
    covariance by ``1 / sqrt(var_i + eps * total_var)``, so every direction the training
    instructions vary along carries comparable weight; directions they never vary along
    are dropped, so an unseen phrasing is read through the words training instructions
    share with it. Output width equals input width; statistics are buffers (saved with
    the weights).

    Args:
        dim: vector width.
        eps: ridge added to each direction's variance, as a fraction of the total variance
            (smaller whitens harder).
        clip: clip outputs to ``[-clip, clip]``.
    """

    def __init__(self, dim: int, eps: float = 1e-2, clip: float = 5.0) -> None:
        super().__init__()
        self.eps = eps
        self.clip = clip
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("transform", torch.eye(dim))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def fit(self, x: torch.Tensor) -> None:
        """Set the statistics from ``(N, dim)`` vectors (replacing earlier ones)."""
        x = x.reshape(-1, self.mean.shape[0]).to(self.mean.device, torch.float64)
        n = x.shape[0]
        if n == 0:
            return
        mean = x.mean(0)
        z = x - mean
        _, s, vt = torch.linalg.svd(z, full_matrices=False)
        var = s.pow(2) / n
        total = var.sum()
        keep = var > total * 1e-9  # directions the vectors vary along (none for one vector)
        v = vt[keep]
        scale = (var[keep] + self.eps * total).rsqrt()
        transform = v.T @ (scale[:, None] * v)
        self.mean.copy_(mean.float())
        self.transform.copy_(transform.float())
        self.count.fill_(float(n))

    def update(self, x: torch.Tensor) -> None:
        """Same as :meth:`fit` (the interface of :class:`RunningNorm`)."""
        self.fit(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) @ self.transform).clamp_(-self.clip, self.clip)


# --- flat parameters and a fast Adam ---------------------------------------------------
def flatten_parameters(params: Sequence[nn.Parameter]) -> tuple[torch.Tensor, torch.Tensor]:
    """Make ``params`` views of one flat buffer, and their grads views of another.

    After this, ``backward`` accumulates every gradient into the flat gradient buffer, so an
    optimiser steps all parameters with a few vectorised operations. Call it after moving
    the module to its device.

    Returns:
        ``(flat_params, flat_grads)``.
    """
    if not params:
        raise LcrlError("no parameters to flatten")
    device, dtype = params[0].device, params[0].dtype
    total = sum(p.numel() for p in params)
    flat = torch.zeros(total, device=device, dtype=dtype)
    grads = torch.zeros(total, device=device, dtype=dtype)
    offset = 0
    for p in params:
        n = p.numel()
        flat[offset : offset + n].copy_(p.data.reshape(-1))
        p.data = flat[offset : offset + n].view_as(p)
        p.grad = grads[offset : offset + n].view_as(p)
        offset += n
    return flat, grads


class FlatAdam:
    """Adam over parameters packed by :func:`flatten_parameters` (optional grad clipping).

    Args:
        params: the parameters (flattened here, in place).
        lr: learning rate.
        betas: Adam's moment decay rates.
        eps: Adam's epsilon.
        max_grad_norm: clip the global gradient norm to this (the gradient buffer is
            scaled in place); ``None`` for no clipping.
    """

    def __init__(
        self,
        params: Iterable[nn.Parameter],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        max_grad_norm: float | None = None,
    ) -> None:
        self.params = [p for p in params if p.requires_grad]
        self.flat, self.grad = flatten_parameters(self.params)
        self.lr = lr
        self.betas = betas
        self.eps = eps
        self.max_grad_norm = max_grad_norm
        self.step_count = 0
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        # torch's fused Adam kernel updates the flat buffer in one pass.
        self._fused = hasattr(torch, "_fused_adam_")
        self._step_t = torch.zeros((), dtype=torch.float32, device=self.flat.device)

    def zero_grad(self) -> None:
        """Zero the flat gradient buffer (in place, keeping the views)."""
        self.grad.zero_()

    @torch.no_grad()
    def step(self) -> float:
        """One Adam step; returns the gradient norm before clipping (0.0 if not computed)."""
        norm = 0.0
        g = self.grad
        if self.max_grad_norm is not None:
            norm = float(torch.linalg.vector_norm(g))
            if norm > self.max_grad_norm:
                g.mul_(self.max_grad_norm / (norm + 1e-6))
        self.step_count += 1
        b1, b2 = self.betas
        if self._fused:
            self._step_t.fill_(self.step_count)
            try:
                torch._fused_adam_(
                    [self.flat],
                    [g],
                    [self.exp_avg],
                    [self.exp_avg_sq],
                    [],
                    [self._step_t],
                    lr=self.lr,
                    beta1=b1,
                    beta2=b2,
                    weight_decay=0.0,
                    eps=self.eps,
                    amsgrad=False,
                    maximize=False,
                )
                return norm
            except (RuntimeError, NotImplementedError):
                self._fused = False  # no fused kernel for this device: vectorised ops
        self.exp_avg.lerp_(g, 1 - b1)
        self.exp_avg_sq.mul_(b2).addcmul_(g, g, value=1 - b2)
        bc1 = 1 - b1**self.step_count
        bc2 = 1 - b2**self.step_count
        denom = (self.exp_avg_sq / bc2).sqrt_().add_(self.eps)
        self.flat.addcdiv_(self.exp_avg, denom, value=-self.lr / bc1)
        return norm

    def state_dict(self) -> dict[str, object]:
        """Moments and step count (tensors and plain numbers)."""
        return {
            "step": self.step_count,
            "exp_avg": self.exp_avg,
            "exp_avg_sq": self.exp_avg_sq,
            "lr": self.lr,
        }

    def load_state_dict(self, state: Mapping[str, object]) -> None:
        """Restore :meth:`state_dict` (shapes must match)."""
        exp_avg = torch.as_tensor(state["exp_avg"])
        if exp_avg.shape != self.exp_avg.shape:
            raise LcrlError(
                f"optimiser state has {exp_avg.numel()} values; this model has "
                f"{self.exp_avg.numel()} parameters"
            )
        self.step_count = int(state["step"])  # type: ignore[arg-type]
        self.exp_avg.copy_(exp_avg)
        self.exp_avg_sq.copy_(torch.as_tensor(state["exp_avg_sq"]))


def polyak(target: Sequence[torch.Tensor], source: Sequence[torch.Tensor], tau: float) -> None:
    """``target <- (1 - tau) target + tau source`` for every pair, in place."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target), list(source), tau)


def gaussian_log_prob_tanh(
    mean: torch.Tensor, log_std: torch.Tensor, noise: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample ``tanh(mean + std * noise)`` and its log-probability (tanh-corrected)."""
    u = mean + log_std.exp() * noise
    action = torch.tanh(u)
    log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    log_prob = log_prob - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
    return action, log_prob

"""Observation and goal encoders, and the registry of goal kinds (:data:`GOAL_ENCODERS`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from lcrl.errors import LcrlError
from lcrl.nets.layers import SLOT_MODES, ConvEncoder, NetConfig, mlp
from lcrl.nets.slots import SlotAttention, SlotAttributes, SlotSelect


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

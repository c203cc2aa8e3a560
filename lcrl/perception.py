"""Perception: camera frames and proprioception -> the object slots of the privileged state.

A tabletop's privileged ``observation`` is the robot's own state followed by one slot per
object kind, ``[position (d values), present]`` (``slot_layout = (start, count, width)``
and ``position_dims = d`` on the env class). :class:`Perception` reads a camera frame and
the proprioception (the first ``start`` values, which the robot always knows) and
estimates every slot: the positions, in the env's units (metres), and whether the object
is on the table. :meth:`Perception.observation` assembles the estimate in the same layout,
so relative positions and displacements are computed from it exactly as from the true
state, and a state policy's features apply unchanged.

The network: the frame with two coordinate channels goes through a small convolution
stack; each channel of the last map gives its maximum and its spatial-softmax keypoint
(expected image coordinates), which with the normalised proprioception feed an MLP that
outputs, per slot, the normalised position and a presence logit. It is trained by
regression on frames the simulator labels for free (``train/environments/perception.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from lcrl.checkpoint import CheckpointError, load_checkpoint
from lcrl.errors import LcrlError
from lcrl.nets import random_shift, spatial_softmax

#: The ``format`` of a perception checkpoint's meta (``lcrl perception train``).
FORMAT = "lcrl-perception"


@dataclass
class PerceptionConfig:
    """The perception network."""

    channels: tuple[int, ...] = (32, 32, 64, 64)
    """Output channels of each convolution (3x3 kernels)."""
    strides: tuple[int, ...] = (2, 1, 2, 1)
    """Stride of each convolution."""
    hidden: int = 256
    """Width of the two hidden layers of the head."""
    augment_pad: int = 2
    """Random-shift augmentation in training: pixels of padding (0: off)."""
    hold_radius: float = 0.06
    """Object permanence when acting (:class:`HeldSlots`): an object's estimated position
    is held from frame to frame while the gripper is farther than this from it on the
    table (in the env's units, metres); 0: every frame's own estimate. Models saved
    before this setting existed hold nothing."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for inconsistent settings."""
        if not self.channels or len(self.channels) != len(self.strides):
            raise LcrlError("perception channels and strides need one value per convolution")
        if min(self.channels) < 1 or min(self.strides) < 1 or self.hidden < 1:
            raise LcrlError("perception channels, strides and hidden must be positive")
        if self.augment_pad < 0:
            raise LcrlError("augment_pad must be >= 0")
        if not self.hold_radius >= 0:
            raise LcrlError(f"hold_radius must be >= 0, got {self.hold_radius}")


@dataclass(frozen=True)
class SlotLayout:
    """Where the object slots are in a privileged observation.

    Attributes:
        start: values before the first slot (the robot's state: the proprioception).
        count: slots (object kinds).
        width: values per slot: ``position_dims`` positions, then presence.
        position_dims: position values per slot (2 on the 2D tabletop, 3 on robosuite).
    """

    start: int
    count: int
    width: int
    position_dims: int

    @classmethod
    def of(cls, values: Sequence[int]) -> SlotLayout:
        """From ``(start, count, width, position_dims)``."""
        start, count, width, dims = (int(v) for v in values)
        if width != dims + 1:
            raise LcrlError(
                f"a slot of width {width} with {dims} position values: perception expects "
                "[positions, present] slots"
            )
        return cls(start, count, width, dims)

    @property
    def dim(self) -> int:
        """Width of the whole observation."""
        return self.start + self.count * self.width

    def split(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(proprio (N, start), positions (N, count, d), present (N, count))`` of
        privileged observations ``(N, dim)``."""
        state = np.asarray(state, np.float32)
        if state.ndim != 2 or state.shape[1] != self.dim:
            raise LcrlError(
                f"privileged observations of shape {state.shape}: this slot layout needs "
                f"(N, {self.dim})"
            )
        slots = state[:, self.start :].reshape(-1, self.count, self.width)
        return state[:, : self.start], slots[..., : self.position_dims], slots[..., -1] > 0.5

    def to_list(self) -> list[int]:
        """``[start, count, width, position_dims]``."""
        return [self.start, self.count, self.width, self.position_dims]


class Perception(nn.Module):
    """Frames ``(B, H, W, 3)`` uint8 and proprioception ``(B, start)`` -> object slots.

    Args:
        frame_shape: ``(H, W, 3)``.
        layout: the env's slot layout.
        cfg: network settings.
        stats: normalisers fitted on training data: ``pos_mean``/``pos_std``
            ``(count, d)`` and ``proprio_mean``/``proprio_std`` ``(start,)``; defaults
            0 and 1 (a loaded checkpoint restores them with the weights).
    """

    def __init__(
        self,
        frame_shape: Sequence[int],
        layout: SlotLayout,
        cfg: PerceptionConfig | None = None,
        stats: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        super().__init__()
        self.cfg = cfg = cfg or PerceptionConfig()
        cfg.validate()
        self.frame_shape = tuple(int(v) for v in frame_shape)
        if len(self.frame_shape) != 3 or self.frame_shape[2] != 3:
            raise LcrlError(f"perception reads RGB frames (H, W, 3), not {self.frame_shape}")
        self.layout = layout
        convs, c_in = [], 5  # RGB and two coordinate channels
        for c, s in zip(cfg.channels, cfg.strides, strict=True):
            convs.append(nn.Conv2d(c_in, c, 3, stride=s, padding=1))
            c_in = c
        self.convs = nn.ModuleList(convs)
        self.temperature = nn.Parameter(torch.ones(()))
        k, d = layout.count, layout.position_dims
        self.head = nn.Sequential(
            nn.Linear(3 * c_in + layout.start, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, cfg.hidden),
            nn.ReLU(),
            nn.Linear(cfg.hidden, k * (d + 1)),
        )
        stats = dict(stats or {})
        self.register_buffer("pos_mean", _stat(stats, "pos_mean", (k, d), 0.0))
        self.register_buffer("pos_std", _stat(stats, "pos_std", (k, d), 1.0))
        self.register_buffer("proprio_mean", _stat(stats, "proprio_mean", (layout.start,), 0.0))
        self.register_buffer("proprio_std", _stat(stats, "proprio_std", (layout.start,), 1.0))

    def check_frames(self, frames: torch.Tensor) -> None:
        """Refuse frames of another size, naming both."""
        if tuple(frames.shape[1:]) != self.frame_shape:
            raise LcrlError(
                f"frames of shape {tuple(frames.shape[1:])}: this perception model was trained "
                f"on {self.frame_shape} frames (another camera size?)"
            )

    def forward(
        self,
        frames: torch.Tensor,
        proprio: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised positions ``(B, count, d)`` and presence logits ``(B, count)``;
        with ``generator``, frames are randomly shifted (training augmentation)."""
        self.check_frames(frames)
        if generator is not None and self.cfg.augment_pad:
            x = random_shift(frames, self.cfg.augment_pad, generator)
        else:
            x = frames.float()
        x = x.permute(0, 3, 1, 2) / 255.0 - 0.5
        b, _, h, w = x.shape
        ys = torch.linspace(-1.0, 1.0, h, device=x.device).view(1, 1, h, 1).expand(b, 1, h, w)
        xs = torch.linspace(-1.0, 1.0, w, device=x.device).view(1, 1, 1, w).expand(b, 1, h, w)
        x = torch.cat([x, ys, xs], 1)
        for conv in self.convs:
            x = F.relu(conv(x))
        temp = self.temperature.abs() + 1e-2
        z = torch.cat(
            [
                x.amax((2, 3)),
                spatial_softmax(x, temp),
                (proprio - self.proprio_mean) / self.proprio_std,
            ],
            -1,
        )
        out = self.head(z).view(b, self.layout.count, self.layout.position_dims + 1)
        return out[..., :-1], out[..., -1]

    def positions(self, normalised: torch.Tensor) -> torch.Tensor:
        """Positions in the env's units from normalised ones."""
        return normalised * self.pos_std + self.pos_mean

    def estimate(
        self, frames: torch.Tensor, proprio: torch.Tensor, present: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The estimated privileged observation ``(B, dim)`` as a tensor (differentiable in
        the positions): the proprioception, then per slot the estimated position and
        presence (1 or 0; an absent object's position is 0, as the envs write it).

        With ``present`` ``(B, count)`` (bool or 0/1), those flags replace the thresholded
        presence logits. The tabletops place their objects at reset and an object's
        ``present`` flag holds for the whole episode, so the flags estimated in the
        episode's first frame, where the robot hides nothing, serve its later frames,
        where the gripper can cover an object (see :meth:`presence`)."""
        pos, logit = self(frames, proprio)
        if present is None:
            present = (logit > 0).float()
        else:
            present = present.to(device=pos.device, dtype=pos.dtype)
        pos = self.positions(pos) * present[..., None]
        slots = torch.cat([pos, present[..., None]], -1).flatten(1)
        return torch.cat([proprio, slots], -1)

    @torch.no_grad()
    def observation(
        self, frames: np.ndarray, proprio: np.ndarray, present: np.ndarray | None = None
    ) -> np.ndarray:
        """:meth:`estimate` of numpy frames ``(B, H, W, 3)`` uint8 and proprioception (and
        presence flags ``(B, count)`` to use instead of the estimated ones)."""
        device = self.pos_mean.device
        f = torch.as_tensor(np.asarray(frames, np.uint8), device=device)
        p = torch.as_tensor(np.asarray(proprio, np.float32), device=device)
        flags = None if present is None else torch.as_tensor(np.asarray(present, np.float32))
        return self.estimate(f, p, flags).cpu().numpy()

    def held_slots(self, radius: float | None = None) -> HeldSlots:
        """Object permanence for this model's estimates (:class:`HeldSlots`), at ``radius``
        or, by default, the model's own ``hold_radius``."""
        return HeldSlots(self.layout, self.cfg.hold_radius if radius is None else radius)

    def presence(self, observation: np.ndarray) -> np.ndarray:
        """The presence flags ``(..., count)`` of observations as :meth:`observation`
        assembles them: what :meth:`observation` takes as ``present`` for the later frames
        of the episode whose first frame gave ``observation``."""
        lay = self.layout
        x = np.asarray(observation, np.float32)
        slots = x[..., lay.start : lay.dim].reshape(*x.shape[:-1], lay.count, lay.width)
        return slots[..., -1] > 0.5


class HeldSlots:
    """Object permanence for perception's estimates, frame after frame of one episode.

    Objects move only when the robot moves them, and a frame with the arm over the table
    reads every object less well than the episode's first frame, where the arm is away.
    So each object's estimated position is held while the gripper (the first two values of
    the proprioception: its place on the table) is farther than ``radius`` from it, in
    this frame and in the one before; near it, the frame's own estimate is taken, and held
    from then on. Near means that the position held or the frame's own estimate is within
    ``radius``: an object the gripper carried off while its estimate lagged behind (it is
    hidden under the gripper) is taken again where the frame sees it by the gripper,
    instead of staying held where the estimate was left. Presence flags and the
    proprioception pass through unchanged.

    Args:
        layout: the slot layout of the estimates.
        radius: in the env's units; 0 passes every estimate through.
    """

    def __init__(self, layout: SlotLayout, radius: float) -> None:
        if not radius >= 0:
            raise LcrlError(f"the hold radius must be >= 0, got {radius}")
        self.layout, self.radius = layout, float(radius)
        self.reset()

    def reset(self) -> None:
        """A new episode: the next estimate is taken whole."""
        self._held: np.ndarray | None = None
        self._agent: np.ndarray | None = None

    def __call__(self, estimate: np.ndarray) -> np.ndarray:
        """The estimates ``(B, dim)`` (one row per episode in parallel) with the
        positions of objects the gripper is away from held; a new number of rows starts
        new episodes."""
        x = np.array(estimate, np.float32, copy=True)
        if not self.radius:
            return x
        lay = self.layout
        agent = x[:, :2]
        if self._held is None or self._held.shape != x.shape:
            self._held, self._agent = x, agent
            return x.copy()
        d = lay.position_dims
        slots = x[:, lay.start : lay.dim].reshape(len(x), lay.count, lay.width)
        held = self._held[:, lay.start : lay.dim].reshape(len(x), lay.count, lay.width)
        near = np.zeros(slots.shape[:2], bool)
        for where in (agent, self._agent):
            for seen in (held, slots):  # the position held, or this frame's own estimate
                near |= np.linalg.norm(seen[..., :2] - where[:, None, :], axis=-1) < self.radius
        slots[..., :d] = np.where(near[..., None], slots[..., :d], held[..., :d])
        slots[..., :d] *= slots[..., d:]  # an object absent has the position 0
        x[:, lay.start : lay.dim] = slots.reshape(len(x), -1)
        self._held, self._agent = x, agent
        return x.copy()


class PerceivedSlots(nn.Module):
    """Camera frames -> the observation a policy reads, as a differentiable module: for
    fine-tuning perception end to end with the policy's losses.

    The output is :meth:`Perception.estimate` extended as :class:`envs.features.SlotFeatures`
    extends the simulator's observation: each slot ``[position, present]`` followed by the
    position relative to the agent (``relative``) and the displacement from the episode's
    first estimate (``displacement``), both 0 for absent objects.

    Args:
        perception: the model to fine-tune.
        relative: add positions relative to the agent (its first ``d`` values).
        displacement: add displacements from ``origin``.
    """

    #: The stored observation keys it reads: the frame, the proprioception and the slot
    #: positions estimated in the episode's first frame.
    KEYS = ("image", "proprio", "origin")

    def __init__(self, perception: Perception, relative: bool, displacement: bool) -> None:
        super().__init__()
        self.perception = perception
        self.relative, self.displacement = bool(relative), bool(displacement)
        lay = perception.layout
        d = lay.position_dims
        self.width = lay.width + d * (int(self.relative) + int(self.displacement))
        self.out_dim = lay.start + lay.count * self.width

    def forward(
        self, image: torch.Tensor, proprio: torch.Tensor, origin: torch.Tensor
    ) -> torch.Tensor:
        """``(B, out_dim)`` observations of frames ``(B, H, W, 3)``, proprioception
        ``(B, start)`` and first-frame slot positions ``(B, count * d)``. The presence
        flags are the first frame's (an object absent there has the origin 0, as the
        envs write it), as :class:`train.environments.perception.PerceptionObservation` gives
        them."""
        lay = self.perception.layout
        d = lay.position_dims
        present = (origin.view(-1, lay.count, d) != 0).any(-1)
        x = self.perception.estimate(image, proprio, present)
        slots = x[:, lay.start :].reshape(-1, lay.count, lay.width)
        present = slots[..., -1:]
        parts = [slots]
        if self.relative:
            parts.append((slots[..., :d] - x[:, None, :d]) * present)
        if self.displacement:
            parts.append((slots[..., :d] - origin.view(-1, lay.count, d)) * present)
        return torch.cat([x[:, : lay.start], torch.cat(parts, -1).flatten(1)], -1)

    def origin(self, observation: np.ndarray) -> np.ndarray:
        """The slot positions ``(..., count * d)`` of observations in this layout (what
        ``origin`` takes, from the episode's first observation)."""
        lay = self.perception.layout
        x = np.asarray(observation, np.float32)
        slots = x[..., lay.start : self.out_dim].reshape(*x.shape[:-1], lay.count, self.width)
        return slots[..., : lay.position_dims].reshape(*x.shape[:-1], -1).copy()


def _stat(stats: Mapping[str, Any], name: str, shape: tuple[int, ...], fill: float) -> torch.Tensor:
    value = stats.get(name)
    if value is None:
        return torch.full(shape, fill)
    arr = torch.as_tensor(np.asarray(value, np.float32))
    if tuple(arr.shape) != shape:
        raise LcrlError(f"perception statistic {name} has shape {tuple(arr.shape)}, not {shape}")
    return arr


#: Smallest position spread a normaliser divides by (metres). Objects resting on the table
#: barely vary in height over short episodes; dividing by that spread would turn a lifted
#: object's 10 cm into a hundred standard deviations and swamp the loss.
MIN_POSITION_STD = 0.01


def fit_stats(layout: SlotLayout, state: np.ndarray) -> dict[str, np.ndarray]:
    """Normalisers of positions (over frames where each object is present; spreads at
    least :data:`MIN_POSITION_STD`) and of the proprioception, from privileged
    observations ``(N, dim)``."""
    proprio, pos, present = layout.split(state)
    counts = present.sum(0)[:, None]
    mean = np.where(counts > 0, (pos * present[..., None]).sum(0) / np.maximum(counts, 1), 0.0)
    var = (((pos - mean) ** 2) * present[..., None]).sum(0) / np.maximum(counts, 1)
    return {
        "pos_mean": mean.astype(np.float32),
        "pos_std": np.maximum(np.sqrt(var), MIN_POSITION_STD).astype(np.float32),
        "proprio_mean": proprio.mean(0).astype(np.float32),
        "proprio_std": np.maximum(proprio.std(0), 1e-3).astype(np.float32),
    }


def perception_loss(
    model: Perception,
    frames: torch.Tensor,
    proprio: torch.Tensor,
    positions: torch.Tensor,
    present: torch.Tensor,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Squared error of the normalised positions of present objects plus the presence
    cross-entropy; returns the loss and its parts."""
    pos, logit = model(frames, proprio, generator)
    target = (positions - model.pos_mean) / model.pos_std
    mask = present.float()
    err = ((pos - target) ** 2).sum(-1)
    pos_loss = (err * mask).sum() / mask.sum().clamp_min(1.0)
    presence = F.binary_cross_entropy_with_logits(logit, mask)
    loss = pos_loss + presence
    parts = {"loss": loss, "position_loss": pos_loss, "presence": presence}
    return loss, {k: float(v.detach()) for k, v in parts.items()}


# --- checkpoints ---------------------------------------------------------------------------
#: The repository's folder of kept models: a relative path under it that is not found from
#: the working folder is looked up in the repository (the camera presets' default
#: perception model works from any folder of an editable install).
KEPT_MODELS = Path("benchmarks/models")
_REPOSITORY = Path(__file__).resolve().parent.parent


def _checkpoint_dir(path: str | Path) -> Path:
    """The checkpoint folder of a perception model: ``lcrl perception train --out`` (the
    folder or its ``model`` checkpoint), or a policy checkpoint that carries one."""
    p = Path(path)
    kept = _REPOSITORY / p
    if not p.exists() and p.parts[:2] == KEPT_MODELS.parts and kept.exists():
        p = kept  # a model kept in the repository, named from another folder
    if (p / "model" / "meta.json").is_file():
        p = p / "model"
    if not (p / "meta.json").is_file():
        raise LcrlError(f"no perception model at {path} (train one with lcrl perception train)")
    return p


def model_meta(path: str | Path) -> dict[str, Any]:
    """The meta of a perception model: of ``lcrl perception train --out`` (the folder or
    its ``model`` checkpoint), or the ``perception`` entry of a policy checkpoint that
    acts through one (its copy of the model it was trained with).

    Raises:
        LcrlError: no perception model there.
    """
    p = _checkpoint_dir(path)
    meta = load_checkpoint(p).meta
    if meta.get("format") == FORMAT:
        return meta
    embedded = meta.get("perception")
    if isinstance(embedded, dict) and embedded.get("format") == FORMAT:
        return embedded
    raise CheckpointError(
        f"{p} is neither a perception checkpoint nor a policy that carries one "
        f"(format {meta.get('format')!r})"
    )


def load_model(path: str | Path, device: str = "cpu") -> tuple[Perception, dict[str, Any]]:
    """A perception model and its meta from ``lcrl perception train --out`` (the folder or
    its ``model`` checkpoint), or from a policy checkpoint that carries one.

    Raises:
        CheckpointError: not a perception checkpoint, or a field missing.
    """
    meta = model_meta(path)  # a perception model, or a clear error
    p = _checkpoint_dir(path)
    ckpt = load_checkpoint(p)
    try:
        layout = SlotLayout.of(meta["slot_layout"])
        settings = {"hold_radius": 0.0, **meta["model"]}  # older models hold nothing
        model = Perception(meta["frame_shape"], layout, PerceptionConfig(**settings))
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(
            f"{p / 'meta.json'}: a perception field is missing or wrong: {e}"
        ) from None
    ckpt.load_module("perception", model)
    model.to(torch.device(device)).eval()
    return model, meta


def embedded_meta(model: Perception, source: str) -> dict[str, Any]:
    """What a policy checkpoint records of the perception model it acts through (its
    weights go beside, as the module ``perception``): enough to rebuild it without the
    folder it was trained into."""
    return {
        "format": FORMAT,
        "frame_shape": list(model.frame_shape),
        "slot_layout": model.layout.to_list(),
        "model": asdict(model.cfg),
        "source": str(source),
    }

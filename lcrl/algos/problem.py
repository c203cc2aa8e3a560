"""What a learner is built for and with: the :class:`Problem` (observation shapes, goal
encoding, action space, rewards' range), the :class:`AgentOptions`, the return's bounds,
the device, and the goal normalisers of each goal kind."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from lcrl.errors import LcrlError
from lcrl.multitask import MultiTaskOptions
from lcrl.nets import (
    NetConfig,
    RunningNorm,
    WhiteningNorm,
)

GoalEmbedder = Callable[[np.ndarray, torch.device], torch.Tensor]


#: Normalisations of text goals (:attr:`AgentOptions.text_goal_norm`).
TEXT_GOAL_NORMS = ("whiten", "standardize")


#: The arithmetic of updates (:attr:`AgentOptions.precision`).
PRECISIONS = ("fp32", "bf16")


#: Action spaces an algorithm can take (:attr:`AlgoSpec.actions`).
ACTION_KINDS = ("continuous", "discrete", "any")


#: Where an algorithm's data comes from (:attr:`AlgoSpec.learns_from`): ``env`` for
#: online RL, ``demos`` for learning from demonstrations.
DATA_SOURCES = ("env", "demos")


@dataclass
class Problem:
    """What a learner must know about the task.

    Attributes:
        obs_shapes: ``{key: shape}`` of the stored observation (vectors ``(d,)``, uint8
            images ``(H, W, C)``).
        goal_kind: how the networks read the goals: a key of :data:`lcrl.nets.GOAL_ENCODERS`
            (``vector``, ``text``, ``onehot`` or ``image``).
        goal_shape: shape of one embedded goal.
        action_dim: continuous action width (actions in ``[-1, 1]``), or the number of
            discrete actions.
        discrete: whether actions are discrete.
        num_tasks: the size of a fixed task set whose goal ids are batch goals (one-hot
            task ids, or instruction ids of a table of exactly those tasks); 0 for none.
        privileged: observation keys that only the critics read (an asymmetric
            actor-critic: the simulator's true state, stored in training, which acting
            never needs). When set, the critics read exactly these keys and the actor
            every other key; empty: every network reads every key.
        perceived: stored observation keys that a perception module attached to the agent
            (:meth:`Agent.attach_perception`, fine-tuned with the losses) turns into one
            vector, the networks' ``observation`` of width ``perceived_dim``; empty: none.
        perceived_dim: the width of that ``observation``.
        reward_range: the lowest and highest reward a transition can earn (sparse success
            rewards: ``(0, 1)``; gymnasium-robotics: ``(-1, 0)``); ``None``: unknown.
        success_ends: whether earning the highest reward ends the episode (no bootstrap
            past it), which bounds the return by one such reward.
    """

    obs_shapes: dict[str, tuple[int, ...]]
    goal_kind: str
    goal_shape: tuple[int, ...]
    action_dim: int
    discrete: bool = False
    num_tasks: int = 0
    privileged: tuple[str, ...] = ()
    perceived: tuple[str, ...] = ()
    perceived_dim: int = 0
    # what the task's rewards allow, not what the networks read: two problems that differ
    # only here take the same weights (a checkpoint's saved problem has neither)
    reward_range: tuple[float, float] | None = field(default=None, compare=False)
    success_ends: bool = field(default=False, compare=False)

    def __post_init__(self) -> None:
        self.privileged = tuple(self.privileged)
        if self.reward_range is not None:
            lo, hi = (float(x) for x in self.reward_range)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
                raise LcrlError(f"reward_range must be finite (low, high), got {self.reward_range}")
            self.reward_range = (lo, hi)
        self.perceived = tuple(self.perceived)
        missing = [k for k in self.perceived if k not in self.obs_shapes]
        if missing or (self.perceived and self.perceived_dim <= 0):
            raise LcrlError(
                f"perceived observation keys {list(self.perceived)} must be observation keys "
                f"(of {sorted(self.obs_shapes)}) with a positive perceived_dim"
            )
        if set(self.perceived) & set(self.privileged):
            raise LcrlError("an observation key cannot be both perceived and privileged")
        unknown = [k for k in self.privileged if k not in self.obs_shapes]
        if unknown:
            raise LcrlError(
                f"privileged observation keys {unknown} are not among the observation keys "
                f"{sorted(self.obs_shapes)}"
            )
        if self.privileged and not self.actor_shapes:
            raise LcrlError("every observation key is privileged: the actor would read nothing")

    def _network(self, shapes: dict[str, tuple[int, ...]]) -> dict[str, tuple[int, ...]]:
        """Stored keys -> what the networks read: perceived keys become ``observation``."""
        if not self.perceived or not set(self.perceived) & set(shapes):
            return shapes
        out = {k: v for k, v in shapes.items() if k not in self.perceived}
        out["observation"] = (self.perceived_dim,)
        return out

    @property
    def network_shapes(self) -> dict[str, tuple[int, ...]]:
        """Every observation input of the networks, after perception."""
        return self._network(dict(self.obs_shapes))

    @property
    def actor_shapes(self) -> dict[str, tuple[int, ...]]:
        """The observation inputs of the actor (the acting network)."""
        return self._network({k: v for k, v in self.obs_shapes.items() if k not in self.privileged})

    @property
    def critic_shapes(self) -> dict[str, tuple[int, ...]]:
        """The observation inputs of the critics."""
        if not self.privileged:
            return self.network_shapes
        return {k: self.obs_shapes[k] for k in self.privileged}

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return {
            "obs_shapes": {k: list(v) for k, v in self.obs_shapes.items()},
            "goal_kind": self.goal_kind,
            "goal_shape": list(self.goal_shape),
            "action_dim": self.action_dim,
            "discrete": self.discrete,
            "num_tasks": self.num_tasks,
            "privileged": list(self.privileged),
            "perceived": list(self.perceived),
            "perceived_dim": self.perceived_dim,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Problem:
        """Inverse of :meth:`to_dict`."""
        return cls(
            obs_shapes={k: tuple(v) for k, v in d["obs_shapes"].items()},
            goal_kind=d["goal_kind"],
            goal_shape=tuple(d["goal_shape"]),
            action_dim=int(d["action_dim"]),
            discrete=bool(d["discrete"]),
            num_tasks=int(d.get("num_tasks", 0)),
            privileged=tuple(d.get("privileged", ())),
            perceived=tuple(d.get("perceived", ())),
            perceived_dim=int(d.get("perceived_dim", 0)),
        )


@dataclass
class AgentOptions:
    """Options shared by every learner."""

    net: NetConfig = field(default_factory=NetConfig)
    """Network sizes and fusion."""
    normalize_obs: bool = True
    """Normalise vector observations with running statistics."""
    normalize_goal: bool = True
    """Normalise goals: state goals with running statistics of achieved goals, text goals
    with the statistics of the training instructions' embeddings (see
    ``text_goal_norm``)."""
    text_goal_norm: str = "standardize"
    """How text goals are normalised: ``standardize`` (each dimension on its own) or
    ``whiten`` (regularised PCA whitening over the training instructions, so that the one
    word telling two instructions apart, such as left and right, is as visible as the
    rest: cosine 0.61 instead of 0.91 between those two). Whitening did not learn faster
    in the runs measured so far (see docs/design.md), so it is not the default."""
    text_whiten_eps: float = 0.01
    """Ridge of the whitening, as a fraction of the embeddings' total variance (smaller
    whitens harder)."""
    reward_shift: float = 0.0
    """Added to every reward the learner sees. -1 turns 0/1 success rewards into -1/0 ones
    (as in gymnasium-robotics): every step that does not reach the goal then costs
    something, which pins down the value of goals the policy does not reach far faster
    than discounting alone."""
    augment_pad: int = 0
    """Random-shift augmentation of image inputs in updates (DrQ): each image (observation,
    next observation, image goal) is padded by this many edge pixels and cropped back at a
    random offset. 0 turns it off; 4 is DrQ's value for 84x84 images."""
    perception_lr: float = 0.0
    """Fine-tune the perception model the policy acts through (``--env.perception``) end
    to end with the SAC losses, at this learning rate: the replay buffer then stores the
    camera frames and the networks read them through the model at every update (its
    critic loss, or its actor loss where the critic reads privileged state). 0: frozen,
    its estimates computed once per frame. On a CPU core an update at batch 256 then costs
    seconds instead of milliseconds: a GPU option."""
    privileged_critic: bool = False
    """An asymmetric actor-critic: the critics read the simulator's true state (stored in
    training only) while the actor reads what it acts from: a perception model's estimate
    from camera frames (``--env.perception``) or the frames themselves
    (``--env.image-obs``). Acting and evaluation never need the true state. SAC and
    TD3."""
    bound_targets: bool = True
    """Clip TD targets to the bounds of the return that the task's rewards allow
    (:func:`value_bounds`: ``[0, 1]`` for sparse success rewards that end the episode,
    ``[-1 / (1 - gamma), 0]`` for -1/0 rewards that do not), in every learner with a TD
    target (SAC, TD3, DQN). A critic that overestimates then cannot feed on its own
    estimates beyond what any episode could return, the drift that precedes the collapse
    of off-policy critics on hindsight goals. Off: targets as computed (SAC's
    ``target_clip`` still applies)."""
    grounding: float = 0.0
    """Weight of an auxiliary grounding loss (SAC, language goals, networks that read object
    slots): every network's selection of object slots is trained by cross-entropy to pick
    the object each training instruction names (its first head; the second head picks the
    reference object of put and stack), as the grammar parses the instruction. The goal's
    choice of object then no longer has to be discovered through the reward, and it
    carries over to word combinations never trained on. Off for goals that are not
    instructions. 0: off."""
    device: str = "cpu"
    """``cpu``, ``cuda`` or ``cuda:N``."""
    compile: bool = False
    """``torch.compile`` the networks (their forward and backward passes; the weights,
    checkpoints and optimisers are unchanged). The first updates then take a minute or two
    to compile. On a 2-core CPU it gave no speed-up for the 2x256 networks of ``lang2d``
    (``benchmarks/results/compiled_update.json``): their updates are matrix products
    already; a GPU option."""
    precision: str = "fp32"
    """Arithmetic of the networks in updates: ``fp32``, or ``bf16``: every update runs
    under ``torch.autocast`` with bfloat16, so matrix products and convolutions take
    bfloat16 inputs while weights, optimiser state, network outputs, losses and targets
    stay float32. Acting, evaluation and checkpoints are unchanged. On CPUs with bfloat16
    instructions (AVX512-BF16, AMX) the ``lang2d`` SAC update takes about half the float32
    time at one thread and 0.7 of it at two (``benchmarks/results/compiled_update.json``);
    on other CPUs it is slower. On CUDA it is the usual mixed precision."""
    seed: int = 0
    """Seed of the network initialisation and of the agent's noise."""
    multitask: MultiTaskOptions = field(default_factory=MultiTaskOptions)
    """Multi-task training over a fixed task set (``env.tasks``): PCGrad, task weights,
    gradient-conflict measurement (SAC) and how training tasks are drawn."""


def value_bounds(
    reward_range: tuple[float, float], gamma: float, success_ends: bool
) -> tuple[float, float]:
    """The lowest and highest discounted return of rewards in ``reward_range``.

    Every return is a discounted sum of per-step rewards in ``[lo, hi]``, so it lies in
    ``[min(lo, 0), max(hi, 0)] / (1 - gamma)``. Where earning ``hi`` ends the episode and
    every other reward is at most 0 (sparse success rewards), the return is at most
    ``max(hi, 0)``: the rewards before the success add nothing positive and nothing
    follows it. Multi-step rows (n-step returns) are such sums too, so the same bounds hold.

    Args:
        reward_range: ``(lo, hi)``, the lowest and highest per-step reward.
        gamma: the discount, in ``[0, 1)``.
        success_ends: whether earning ``hi`` ends the episode.
    """
    lo, hi = float(reward_range[0]), float(reward_range[1])
    horizon = 1.0 / (1.0 - gamma)
    low = min(lo, 0.0) * horizon
    high = max(hi, 0.0) if success_ends and lo <= 0.0 else max(hi, 0.0) * horizon
    return low, high


def resolve_device(name: str) -> torch.device:
    """The torch device for a config string, with a clear error when it is unavailable.

    Args:
        name: ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        LcrlError: an unknown device, or CUDA asked for on a machine without it.
    """
    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise LcrlError(f"unknown device {name!r}: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise LcrlError(f"device {name!r} requested but CUDA is not available on this machine")
    return device


def text_goal_normaliser(problem: Problem, options: AgentOptions) -> nn.Module:
    """Language goals (frozen text embeddings): standardised per dimension, or whitened
    over the instruction table (``options.text_goal_norm``)."""
    # Frozen sentence embeddings of instructions are close to each other (cosine 0.98
    # between "push the red cube left" and "... right"); whitening over the instruction
    # table spreads them apart (cosine 0.61), standardising each dimension much less
    # (0.91).
    if options.text_goal_norm == "whiten":
        return WhiteningNorm(problem.goal_shape[0], eps=options.text_whiten_eps)
    return RunningNorm(problem.goal_shape[0], eps=1e-3)


def vector_goal_normaliser(problem: Problem, options: AgentOptions) -> nn.Module:
    """Goal vectors: running statistics of the achieved goals."""
    return RunningNorm(problem.goal_shape[0], eps=1e-2)


#: ``(problem, options) -> module``: the goal normaliser of each goal kind
#: (:data:`lcrl.nets.GOAL_ENCODERS`), saved as ``norms.goal.*`` and used when
#: ``options.normalize_goal`` is on. Kinds without an entry (one-hot task ids, image
#: goals) are not normalised.
GOAL_NORMALISERS: dict[str, Callable[[Problem, AgentOptions], nn.Module]] = {
    "text": text_goal_normaliser,
    "vector": vector_goal_normaliser,
}

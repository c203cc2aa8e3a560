"""What every learner shares: the problem description, the agent options, the :class:`Agent`
base class (device, normalisers, batch tensors, checkpoint state) and :class:`AlgoSpec`, the
registry entry each algorithm module ends with.

Targets bootstrap through time limits: only ``terminated`` transitions (goal reached,
failure) stop the bootstrap, truncations do not (the buffer never marks a truncation as
terminated). Runs are deterministic on the CPU under a seed: each agent draws its noise
from its own ``torch.Generator``.
"""

from __future__ import annotations

import copy
import functools
import math
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from lcrl.algos.problem import (
    ACTION_KINDS as ACTION_KINDS,
    DATA_SOURCES as DATA_SOURCES,
    GOAL_NORMALISERS as GOAL_NORMALISERS,
    PRECISIONS as PRECISIONS,
    TEXT_GOAL_NORMS as TEXT_GOAL_NORMS,
    AgentOptions as AgentOptions,
    GoalEmbedder as GoalEmbedder,
    Problem as Problem,
    resolve_device as resolve_device,
    text_goal_normaliser as text_goal_normaliser,
    value_bounds as value_bounds,
    vector_goal_normaliser as vector_goal_normaliser,
)
from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from lcrl.multitask import MultiTaskOptions
from lcrl.nets import (
    FlatAdam,
    GoalConditionedEnsemble,
    GoalConditionedNet,
    RunningNorm,
    flatten_parameters,
    random_shift,
)

#: Learners with the auxiliary grounding loss (:attr:`AgentOptions.grounding`).
GROUNDED_ALGOS = ("sac", "td3", "bc")


def _cpu_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (oneDNN's check)."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def _in_precision(update: Callable[..., dict[str, float]]) -> Callable[..., dict[str, float]]:
    """``update`` run under bf16 autocast when the agent's ``precision`` is ``bf16``."""

    @functools.wraps(update)
    def run(self: Agent, *args: Any, **kwargs: Any) -> dict[str, float]:
        if self.options.precision != "bf16":
            return update(self, *args, **kwargs)
        with torch.autocast(self.device.type, dtype=torch.bfloat16):
            return update(self, *args, **kwargs)

    return run


class Agent:
    """Shared machinery: device, normalisers, tensors from batches, saving.

    Every subclass's :meth:`update` runs in the options' ``precision`` (bf16 autocast or
    plain float32) without doing anything itself.

    On construction an agent whose :attr:`name` is registered in :data:`lcrl.algos.ALGOS`
    refuses an action space its :class:`AlgoSpec` does not take, and every agent refuses
    active multi-task options unless its spec supports them.

    Args:
        problem: observation shapes, goal encoding, action space.
        options: networks, normalisation, augmentation, device, seed, multi-task options.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
    """

    name = "agent"
    #: The algorithm's config; subclasses set it in ``__init__``.
    cfg: Any

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "update" in cls.__dict__:
            cls.update = _in_precision(cls.__dict__["update"])  # type: ignore[method-assign]

    def __deepcopy__(self, memo: dict[int, Any]) -> Agent:
        """An independent copy that learns on its own (a benchmark's second arm, say).

        The networks' parameters are views of flat buffers (:func:`flatten_parameters`:
        the optimisers' and the target networks'), and ``copy.deepcopy`` clones each
        parameter on its own; the copies are made views of the copied buffers again, so
        that the copy's optimisers and target steps move the copy's networks.
        """
        cls = type(self)
        new = cls.__new__(cls)
        memo[id(self)] = new
        for key, value in self.__dict__.items():
            setattr(new, key, copy.deepcopy(value, memo))
        buffers: list[tuple[torch.Tensor, torch.Tensor | None]] = []
        params: dict[int, torch.Tensor] = {}
        for value in self.__dict__.values():
            if isinstance(value, FlatAdam):
                buffers.append((value.flat, value.grad))
                params.update((id(p), p) for p in value.params)
            elif isinstance(value, torch.Tensor) and value.dim() == 1:
                buffers.append((value, None))
            elif isinstance(value, nn.Module):
                params.update((id(p), p) for p in value.parameters())
        for flat, grad in buffers:
            storage = flat.untyped_storage().data_ptr()
            new_flat = memo[id(flat)]
            new_grad = None if grad is None else memo[id(grad)]
            for key, p in params.items():
                if p.untyped_storage().data_ptr() != storage or key not in memo:
                    continue
                start = (p.data_ptr() - flat.data_ptr()) // p.element_size()
                rows = slice(start, start + p.numel())
                copied = memo[key]
                copied.data = new_flat[rows].view_as(p)
                if new_grad is not None:
                    copied.grad = new_grad[rows].view_as(p)
        return new

    def __init__(self, problem: Problem, options: AgentOptions, goal_embed: GoalEmbedder) -> None:
        self.problem = problem
        self.options = options
        self.device = resolve_device(options.device)
        self.goal_embed = goal_embed
        torch.manual_seed(options.seed)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(options.seed)
        self.np_rng = np.random.default_rng(options.seed)
        self.norms = nn.ModuleDict()
        if options.normalize_obs:
            for key, shape in problem.network_shapes.items():
                if len(shape) == 1:
                    self.norms[f"obs_{key}"] = RunningNorm(shape[0])
        if options.text_goal_norm not in TEXT_GOAL_NORMS:
            raise LcrlError(
                f"unknown text_goal_norm {options.text_goal_norm!r}; choose one of "
                f"{TEXT_GOAL_NORMS}"
            )
        if options.precision not in PRECISIONS:
            raise LcrlError(f"unknown precision {options.precision!r}; choose one of {PRECISIONS}")
        if options.precision == "bf16" and self.device.type == "cpu" and not _cpu_bf16():
            warnings.warn(
                "precision bf16 on a CPU without bfloat16 instructions: updates will be "
                "slower than in fp32",
                stacklevel=2,
            )
        if options.text_whiten_eps <= 0:
            raise LcrlError(f"text_whiten_eps must be positive, got {options.text_whiten_eps}")
        goal_norm = GOAL_NORMALISERS.get(problem.goal_kind)
        if options.normalize_goal and goal_norm is not None:
            self.norms["goal"] = goal_norm(problem, options)
        self.norms.to(self.device)
        self.updates = 0
        self.acts = 0
        options.multitask.validate(problem.num_tasks)
        if self.name in ALGOS:
            check_algo(self.name, problem.discrete)
            if problem.privileged and not ALGOS[self.name].privileged_critic:
                able = [n for n, spec in ALGOS.items() if spec.privileged_critic]
                raise LcrlError(
                    f"{self.name} has no critic that could read privileged state apart from "
                    f"its actor: the asymmetric actor-critic needs one of {able}"
                )
        check_multitask(self.name, options.multitask)
        if options.grounding < 0:
            raise LcrlError(f"grounding must be 0 (off) or positive, got {options.grounding}")
        if options.grounding and self.name not in GROUNDED_ALGOS:
            raise LcrlError(
                f"the grounding loss is implemented for {', '.join(GROUNDED_ALGOS)}, not "
                f"{self.name}"
            )
        if options.grounding and not options.net.slots:
            raise LcrlError("the grounding loss needs networks that read object slots (net.slots)")

    def value_bounds(self) -> tuple[float, float] | None:
        """The bounds of the return the learner's TD targets are clipped to
        (:attr:`AgentOptions.bound_targets`, the rewards as the learner sees them, with
        ``reward_shift``); ``None`` where the targets are not clipped or the task's rewards
        are unknown."""
        p = self.problem
        gamma = getattr(self.cfg, "gamma", None)
        if not self.options.bound_targets or p.reward_range is None or gamma is None:
            return None
        shift = float(self.options.reward_shift)
        lo, hi = p.reward_range
        return value_bounds((lo + shift, hi + shift), float(gamma), p.success_ends)

    def bound_targets(self, y: torch.Tensor) -> torch.Tensor:
        """TD targets clipped to :meth:`value_bounds` (unchanged where there are none)."""
        bounds = self.value_bounds()
        return y if bounds is None else y.clamp(bounds[0], bounds[1])

    #: Per goal id, the slots its instruction names (:meth:`set_grounding`).
    grounding_targets: torch.Tensor | None = None

    def set_grounding(self, targets: np.ndarray) -> None:
        """Turn on the grounding loss (:attr:`AgentOptions.grounding`) with, per goal id,
        the object slots its instruction names: an ``(ids, 2)`` integer array of the slot
        of the object acted on and of the reference object, -1 where there is none.

        Raises:
            LcrlError: grounding is off, or the array has the wrong shape or slot indices
                outside the networks' slots.
        """
        if not self.options.grounding:
            raise LcrlError("set_grounding: the grounding loss is off (agent.grounding is 0)")
        t = np.asarray(targets)
        count = int(self.options.net.slots[1])
        if t.ndim != 2 or t.shape[1] != 2 or t.dtype.kind not in "iu":
            raise LcrlError(f"grounding targets must be an (ids, 2) integer array, got {t.shape}")
        if t.size and (t.min() < -1 or t.max() >= count):
            raise LcrlError(f"grounding targets must be -1 or slot indices below {count}")
        self.grounding_targets = torch.as_tensor(t.astype(np.int64), device=self.device)

    def grounding_rows(self, goal_ids: np.ndarray) -> torch.Tensor | None:
        """The named slots of a batch's goals, ``(B, 2)``; None when grounding is off."""
        if self.grounding_targets is None:
            return None
        ids = torch.as_tensor(np.asarray(goal_ids, np.int64), device=self.device)
        return self.grounding_targets[ids]

    #: Per goal id, other phrasings of its instruction (:meth:`set_phrasings`).
    phrasings: torch.Tensor | None = None
    phrasing_counts: torch.Tensor | None = None
    phrasing_share: float = 0.5

    def set_phrasings(self, variants: np.ndarray, counts: np.ndarray, share: float = 0.5) -> None:
        """Train on other phrasings of the instructions: in every update a ``share`` of
        the rows whose goal id has phrasings reads one of them, drawn uniformly, instead
        of the instruction's own embedding. Acting and evaluation are unchanged.

        Args:
            variants: ``(ids, P, d)`` embeddings of up to ``P`` phrasings per goal id (ids
                beyond the first axis have none).
            counts: ``(ids,)`` how many of the ``P`` are filled for each id.
            share: fraction of such rows that read a phrasing, in (0, 1].

        Raises:
            LcrlError: shapes that disagree, or a share outside (0, 1].
        """
        v = np.asarray(variants, np.float32)
        c = np.asarray(counts)
        if v.ndim != 3 or c.shape != v.shape[:1] or c.dtype.kind not in "iu":
            raise LcrlError(
                f"phrasings must be (ids, P, d) embeddings with (ids,) integer counts, got "
                f"{v.shape} and {c.shape}"
            )
        if c.size and (c.min() < 0 or c.max() > v.shape[1]):
            raise LcrlError(f"phrasing counts must be between 0 and {v.shape[1]}")
        if not 0.0 < share <= 1.0:
            raise LcrlError(f"the share of rows reading a phrasing must be in (0, 1], not {share}")
        self.phrasings = torch.as_tensor(v, device=self.device)
        self.phrasing_counts = torch.as_tensor(c.astype(np.int64), device=self.device)
        self.phrasing_share = float(share)

    def batch_goal(self, goal: np.ndarray) -> torch.Tensor:
        """A batch's goals as network input (:meth:`goal_tensor`), with other phrasings of
        the instructions in a share of the rows when :meth:`set_phrasings` gave some."""
        g = np.asarray(goal)
        if self.phrasings is None or g.ndim != 1 or g.dtype.kind not in "iu":
            return self.goal_tensor(g)
        vectors = self.goal_embed(g, self.device).clone()
        ids = torch.as_tensor(g.astype(np.int64), device=self.device)
        known = ids < self.phrasings.shape[0]
        safe = torch.where(known, ids, torch.zeros_like(ids))
        n = torch.where(known, self.phrasing_counts[safe], torch.zeros_like(ids))
        u = torch.rand(len(g), generator=self.gen, device=self.device)
        pick = (n > 0) & (u < self.phrasing_share)
        if bool(pick.any()):
            r = torch.rand(len(g), generator=self.gen, device=self.device)
            k = torch.minimum((r * n).long(), (n - 1).clamp(min=0))
            vectors[pick] = self.phrasings[safe[pick], k[pick]]
        return self.goal_tensor(vectors, embedded=True)

    #: The perception module fine-tuned with the losses (:meth:`attach_perception`).
    perceiver: nn.Module | None = None
    perceiver_opt: FlatAdam | None = None

    def attach_perception(self, module: nn.Module, lr: float) -> None:
        """Read the :attr:`Problem.perceived` keys through ``module`` (frames -> the
        networks' ``observation``, e.g. :class:`lcrl.perception.PerceivedSlots`) and
        fine-tune it at learning rate ``lr`` with the critic loss, or with the actor loss
        when the critics read privileged state instead.

        Raises:
            LcrlError: the problem has no perceived keys, or the module's output width
                differs from ``perceived_dim``.
        """
        p = self.problem
        if not p.perceived:
            raise LcrlError("attach_perception: the problem has no perceived observation keys")
        width = getattr(module, "out_dim", p.perceived_dim)
        if width != p.perceived_dim:
            raise LcrlError(
                f"the perception module gives {width} values; the networks read {p.perceived_dim}"
            )
        if lr <= 0:
            raise LcrlError(f"the perception learning rate must be positive, got {lr}")
        self.perceiver = module.to(self.device)
        for param in module.parameters():
            param.requires_grad_(True)
        self.perceiver_opt = FlatAdam(list(module.parameters()), lr)

    def _perceive(self, obs: Mapping[str, Any], grad: bool = True) -> dict[str, Any]:
        """Observations with the perceived keys replaced by the module's ``observation``
        (unnormalised)."""
        if self.perceiver is None or not all(k in obs for k in self.problem.perceived):
            return dict(obs)
        keys = self.problem.perceived
        tensors = [to_device(obs[k], self.device) for k in keys]
        tensors = [t if t.dtype == torch.uint8 else t.float() for t in tensors]
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            x = self.perceiver(*tensors)
        out = {k: v for k, v in obs.items() if k not in keys}
        out["observation"] = x
        return out

    # --- inputs ----------------------------------------------------------------------
    def observe(self, obs: Mapping[str, np.ndarray], goals: np.ndarray | None = None) -> None:
        """Update the running normalisers with observations and goal vectors (achieved state
        goals, or the embeddings of the training instructions)."""
        if self.perceiver is not None:
            with torch.no_grad():
                obs = {k: _numpy(v) for k, v in self._perceive(obs, grad=False).items()}
        for key, arr in obs.items():
            if f"obs_{key}" in self.norms:
                self.norms[f"obs_{key}"].update(torch.as_tensor(np.asarray(arr, np.float32)))
        if goals is not None and "goal" in self.norms:
            g = np.asarray(goals)
            if g.dtype.kind in "iu":  # ids: embed them first
                t = self.goal_embed(g, self.device)
            else:
                t = torch.as_tensor(g, dtype=torch.float32)
            self.norms["goal"].update(t)

    def obs_tensors(self, obs: Mapping[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """Observation arrays as (normalised) tensors on the device (frames read by an
        attached perception module become the ``observation`` it computes)."""
        out = {}
        for key, arr in self._perceive(obs).items():
            t = to_device(arr, self.device)
            if t.dtype != torch.uint8:
                t = t.float()
                if f"obs_{key}" in self.norms:
                    t = self.norms[f"obs_{key}"](t)
            out[key] = t
        return out

    def goal_tensor(self, goal: np.ndarray | torch.Tensor, embedded: bool = False) -> torch.Tensor:
        """Goals as network input: embedded by the goal space (unless already) and normalised."""
        if embedded:
            g = torch.as_tensor(goal, device=self.device)
            g = g.float() if g.dtype != torch.uint8 else g
        else:
            g = self.goal_embed(np.asarray(goal), self.device)
        if "goal" in self.norms:
            g = self.norms["goal"](g)
        return g

    def batch_tensors(self, batch: Batch) -> tuple[Any, ...]:
        """``obs, next_obs, goal, action, reward, bootstrap`` tensors of a batch.

        ``bootstrap`` multiplies the next state's value in the target: the discount
        (``gamma``, or :attr:`Batch.discount` for multi-step rows) where the row did not
        terminate, 0 where it did.
        """
        obs = self.obs_tensors(batch.obs)
        with torch.set_grad_enabled(self.perceiver is None and torch.is_grad_enabled()):
            nobs = self.obs_tensors(batch.next_obs)  # targets only: no gradient
        goal = self.batch_goal(batch.goal)
        pad = self.options.augment_pad
        if pad:
            for d in (obs, nobs):
                for key, t in d.items():
                    if t.dim() == 4:
                        d[key] = random_shift(t, pad, self.gen)
            if goal.dim() == 4:
                goal = random_shift(goal, pad, self.gen)
        act = to_device(batch.action, self.device)
        act = act.long() if self.problem.discrete else act.float()
        rew = to_device(batch.reward, self.device, torch.float32)
        gamma = float(self.cfg.gamma)
        if batch.discount is None:
            disc = torch.full_like(rew, gamma)
        else:
            disc = to_device(batch.discount, self.device, torch.float32)
        if self.options.reward_shift:
            # a shift per step: sum_j gamma**j over the row's m rewards, gamma**m = disc
            per_row = 1.0 if batch.discount is None else (1.0 - disc) / (1.0 - gamma)
            rew = rew + self.options.reward_shift * per_row
        term = to_device(batch.terminated, self.device, torch.float32)
        return obs, nobs, goal, act, rew, (1.0 - term) * disc

    def _critics(self, action_dim: int, n: int = 2) -> GoalConditionedEnsemble:
        p = self.problem
        return GoalConditionedEnsemble(
            n, p.critic_shapes, p.goal_kind, p.goal_shape, 1, self.options.net, action_dim
        ).to(self.device)

    def _net(self, out_dim: int, action_dim: int = 0) -> GoalConditionedNet:
        p = self.problem
        return GoalConditionedNet(
            p.actor_shapes, p.goal_kind, p.goal_shape, out_dim, self.options.net, action_dim
        ).to(self.device)

    # --- acting ----------------------------------------------------------------------
    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: np.ndarray | torch.Tensor,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Actions for a batch of observations and goals (continuous in ``[-1, 1]``)."""
        raise NotImplementedError

    # --- learning --------------------------------------------------------------------
    def update(self, batch: Any) -> dict[str, float]:
        """One learning step on a batch; returns losses and diagnostics by name."""
        raise NotImplementedError

    # --- saving ----------------------------------------------------------------------
    def compile_networks(self) -> None:
        """``torch.compile`` every network in place (``nn.Module.compile``, so parameter
        names and checkpoints stay as they are), as CUDA graphs on CUDA
        (:func:`compile_mode`); the perception model is left alone.

        Raises:
            LcrlError: on CUDA, where it does not work yet: replaying a compiled network's
                CUDA graph overwrites an output still in use (measured on an H100,
                docs/scale.md).
        """
        if self.device.type == "cuda":
            raise LcrlError(
                "--agent.compile does not work on CUDA yet (replaying a compiled network's "
                "CUDA graph overwrites an output still in use; docs/scale.md): train on "
                "CUDA without --agent.compile"
            )
        mode = compile_mode(self.device)
        for name, module in self.modules().items():
            if name != "perceiver":
                module.compile(dynamic=False, mode=mode)

    #: Modules of :meth:`modules` that only learning reads (critics, target networks):
    #: a policy kept to act (``lcrl export``) leaves them out, and loading it skips them.
    LEARNING_ONLY: tuple[str, ...] = ()

    def modules(self) -> dict[str, nn.Module]:
        """Weights to checkpoint, by name."""
        out: dict[str, nn.Module] = {"norms": self.norms}
        if self.perceiver is not None:
            out["perceiver"] = self.perceiver
        return out

    def states(self) -> dict[str, Any]:
        """Optimiser moments, noise generator and counters to checkpoint."""
        out = {
            "generator": self.gen.get_state(),
            "np_rng": self.np_rng.bit_generator.state,
            "counters": {"updates": self.updates, "acts": self.acts},
        }
        if self.perceiver_opt is not None:
            out["perceiver_opt"] = self.perceiver_opt.state_dict()
        return out

    def load_states(self, states: Mapping[str, Any]) -> None:
        """Restore :meth:`states`."""
        if self.perceiver_opt is not None and "perceiver_opt" in states:
            self.perceiver_opt.load_state_dict(states["perceiver_opt"])
        self.gen.set_state(torch.as_tensor(states["generator"], dtype=torch.uint8).cpu())
        self.np_rng.bit_generator.state = states["np_rng"]
        self.updates = int(states["counters"]["updates"])
        self.acts = int(states["counters"]["acts"])


# --- shared helpers -------------------------------------------------------------------------
def _numpy(x: Any) -> np.ndarray:
    """A tensor or array as a numpy array."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def to_device(x: Any, device: torch.device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """An array (or tensor) as a tensor on ``device``.

    On CUDA a host array goes through page-locked (pinned) memory and is copied
    asynchronously (``non_blocking``), so the copy of one batch overlaps the work queued
    before it; on the CPU it is ``torch.as_tensor`` (no copy where none is needed).
    """
    if isinstance(x, torch.Tensor) and x.device.type != "cpu":
        return x.to(device=device, dtype=dtype)
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
    if dtype is not None and t.dtype != dtype:
        t = t.to(dtype)
    if device.type != "cuda":
        return t.to(device)
    return t.pin_memory().to(device, non_blocking=True)


def compile_mode(device: torch.device) -> str:
    """The ``torch.compile`` mode of the networks on ``device``: ``reduce-overhead`` on
    CUDA, which records each compiled forward and backward pass as a CUDA graph and
    replays it (one launch for the whole network, as LeanRL does for its updates);
    ``default`` elsewhere, where there are no graphs to record."""
    return "reduce-overhead" if device.type == "cuda" else "default"


def flat_target(module: nn.Module) -> tuple[nn.Module, torch.Tensor]:
    """A frozen copy of ``module`` for a target network, and one flat tensor that its
    parameters are views of (so a Polyak step is one ``lerp_``).

    Args:
        module: the online network (its parameters are copied, not shared).

    Returns:
        ``(target, flat)``: the copy, with ``requires_grad`` off, and its flat parameters.
    """
    target = copy.deepcopy(module)
    for p in target.parameters():
        p.requires_grad_(False)
    flat, _ = flatten_parameters(list(target.parameters()))
    return target, flat


def check_fields(
    cfg: Any,
    prefix: str,
    *,
    unit: Iterable[str] = (),
    probability: Iterable[str] = (),
    positive: Iterable[str] = (),
    non_negative: Iterable[str] = (),
    positive_or_none: Iterable[str] = (),
    finite_or_none: Iterable[str] = (),
) -> None:
    """Check ranges of a config's fields, for ``validate`` methods.

    Args:
        cfg: the config.
        prefix: its name in messages (``sac`` gives ``sac.gamma must be ...``).
        unit: fields in ``(0, 1]`` (discounts, Polyak rates).
        probability: fields in ``[0, 1]``.
        positive: fields ``> 0`` (learning rates, counts).
        non_negative: fields ``>= 0``.
        positive_or_none: fields ``> 0`` or ``None`` (gradient clipping).
        finite_or_none: finite numbers or ``None``.

    Raises:
        LcrlError: the first field outside its range (NaN is outside every range).
    """
    checks: tuple[tuple[Iterable[str], Callable[[Any], bool], str], ...] = (
        (unit, lambda v: 0.0 < v <= 1.0, "must be in (0, 1]"),
        (probability, lambda v: 0.0 <= v <= 1.0, "must be in [0, 1]"),
        (positive, lambda v: v > 0, "must be positive"),
        (non_negative, lambda v: v >= 0, "must be >= 0"),
        (positive_or_none, lambda v: v is None or v > 0, "must be positive (or None)"),
        (finite_or_none, lambda v: v is None or math.isfinite(v), "must be finite (or None)"),
    )
    for names, ok, what in checks:
        for name in names:
            value = getattr(cfg, name)
            if not ok(value):
                raise LcrlError(f"{prefix}.{name} {what}, got {value}")


class AlgoConfig(Protocol):
    """What an algorithm's config provides: a check of its own settings."""

    def validate(self) -> None:
        """Raise :class:`LcrlError` for settings the algorithm cannot train with."""


@dataclass(frozen=True)
class AlgoSpec:
    """One algorithm, as listed in :data:`lcrl.algos.ALGOS`.

    Attributes:
        name: the key in ``ALGOS``, ``--algo`` on the command line, the ``TrainConfig``
            field holding the config, and the agent class's ``name``.
        agent: the learner class, built as ``agent(problem, options, goal_embed, config)``.
        config: its config dataclass (with a ``validate()`` method).
        actions: the action spaces it takes: ``continuous``, ``discrete`` or ``any``.
        multitask: whether it implements the multi-task options (PCGrad, task weights,
            gradient-conflict measurement).
        learns_from: ``env`` (online RL on a replay buffer) or ``demos`` (demonstrations).
        summary: one line for listings.
        privileged_critic: whether its critics can read privileged observation keys that
            its actor does not (:attr:`Problem.privileged`: an asymmetric actor-critic).
        title: how it learns, in a few words for reports (``behavioural cloning``);
            empty: its name.
    """

    name: str
    agent: type[Agent]
    config: type[AlgoConfig]
    actions: str
    multitask: bool = False
    learns_from: str = "env"
    summary: str = ""
    privileged_critic: bool = False
    title: str = ""

    def __post_init__(self) -> None:
        if self.actions not in ACTION_KINDS:
            raise LcrlError(f"AlgoSpec {self.name!r}: actions must be one of {ACTION_KINDS}")
        if self.learns_from not in DATA_SOURCES:
            raise LcrlError(f"AlgoSpec {self.name!r}: learns_from must be one of {DATA_SOURCES}")
        if self.agent.name != self.name:
            raise LcrlError(
                f"AlgoSpec {self.name!r} names agent class {self.agent.__name__} whose name is "
                f"{self.agent.name!r}"
            )

    @property
    def unit(self) -> str:
        """What ``total_steps`` and the ``*_every`` settings of its runs count: ``step``
        (environment steps, online RL) or ``update`` (gradient updates on
        demonstrations)."""
        return "update" if self.learns_from == "demos" else "step"

    def takes(self, discrete: bool) -> bool:
        """Whether the algorithm takes discrete (or continuous) actions."""
        return self.actions in ("any", "discrete" if discrete else "continuous")


#: Every algorithm, by name (:data:`lcrl.algos.ALGOS`, the same dict): filled by
#: :mod:`lcrl.algos`, the one place an algorithm is listed, when the package is imported,
#: which happens before any of its modules (so before any agent is built).
ALGOS: dict[str, AlgoSpec] = {}

#: What ``auto`` stands for, by action space.
AUTO_ALGOS = {"continuous": "sac", "discrete": "dqn"}


def _one_of(names: list[str] | tuple[str, ...], word: str = "or") -> str:
    """``a, b or c``."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} {word} {names[-1]}"


def algo_choices() -> tuple[str, ...]:
    """The values ``--algo`` takes: ``auto`` and every name in :data:`ALGOS`."""
    return ("auto", *ALGOS)


def resolve_algo(name: str, discrete: bool) -> str:
    """The algorithm ``name`` stands for: ``auto`` is DQN for discrete actions and SAC for
    continuous ones (:data:`AUTO_ALGOS`), any other name itself.

    Args:
        name: ``auto`` or a name in :data:`ALGOS` (not checked here: see
            :func:`check_algo`).
        discrete: whether the environment's actions are discrete.
    """
    if name == "auto":
        return AUTO_ALGOS["discrete" if discrete else "continuous"]
    return name


def check_algo(name: str, discrete: bool | None = None) -> None:
    """Refuse an unknown algorithm, or one that does not take the environment's actions.

    Args:
        name: ``auto`` or a name in :data:`ALGOS`.
        discrete: whether the environment's actions are discrete; ``None`` (not known
            yet) checks the name only.

    Raises:
        LcrlError: an unknown name (the message lists :func:`algo_choices`), or an
            algorithm for the other kind of actions (the message names one that fits).
    """
    choices = algo_choices()
    if name not in choices:
        raise LcrlError(f"unknown algo {name!r}; choose {_one_of(choices)}")
    if discrete is None:
        return
    spec = ALGOS[resolve_algo(name, discrete)]
    if not spec.takes(discrete):
        have, need = ("discrete", "continuous") if discrete else ("continuous", "discrete")
        raise LcrlError(
            f"{spec.name} needs {need} actions; this env has {have} actions: use "
            f"{resolve_algo('auto', discrete)}"
        )


def check_multitask(name: str, options: MultiTaskOptions) -> None:
    """Refuse active multi-task options (PCGrad, task weights, conflict measurement) for an
    algorithm whose spec does not implement them.

    Args:
        name: the algorithm (``auto`` is not resolved: it passes).
        options: the multi-task options.

    Raises:
        LcrlError: the options are active and ``name`` is not a multi-task algorithm.
    """
    if not options.active or name == "auto":
        return
    spec = ALGOS.get(name)
    if spec is not None and spec.multitask:
        return
    able = [n for n, s in ALGOS.items() if s.multitask]
    what = "PCGrad, task weights and gradient-conflict measurement"
    if not able:
        raise LcrlError(f"{what} are not implemented by any algorithm: turn them off")
    raise LcrlError(
        f"{what} are implemented for {_one_of([n.upper() for n in able], 'and')}, not {name}: "
        f"use --algo {_one_of(able)} or turn the multitask options off"
    )

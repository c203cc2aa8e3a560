"""Normalisers of observations and goals, the flat-buffer Adam, Polyak averaging and the
tanh-Gaussian log-probability."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from lcrl.errors import LcrlError


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


#: Adam moments below this are set to zero every :data:`FLUSH_EVERY` steps (see FlatAdam).
FLUSH_BELOW = 1e-30
FLUSH_EVERY = 64


class FlatAdam:
    """Adam over parameters packed by :func:`flatten_parameters` (optional grad clipping).

    The first moment of a parameter whose gradient stays zero (a unit that ReLU keeps
    off) shrinks by ``beta1`` each step until it is subnormal, and arithmetic on subnormal
    floats is many times slower on x86 CPUs: after 2,500 steps on FetchReach the critics'
    Adam step took 0.70 ms instead of 0.08. Every :data:`FLUSH_EVERY` steps the
    moments below :data:`FLUSH_BELOW` are set to zero, before any of them can reach the
    subnormal range (1.2e-38) at ``beta1 = 0.9``; the parameter change this drops is
    below ``lr * 1e-30 / eps``.

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
        if self.step_count % FLUSH_EVERY == 0:
            for moment in (self.exp_avg, self.exp_avg_sq):
                moment.masked_fill_(moment.abs() < FLUSH_BELOW, 0.0)
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

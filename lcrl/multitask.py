"""Multi-task RL: task sampling, task weights, PCGrad and gradient-conflict statistics.

A multi-task run trains one policy on a fixed set of ``K`` tasks, each with its own reward
function; the policy is told which task to do by a task id (a one-hot vector) or by the
task's instruction. The objective is ``sum_i w_i L_i`` over the tasks' losses. This module
holds the parts of it that know nothing about environments:

:class:`MultiTaskOptions`
    the options of a multi-task learner (PCGrad, task weights, how often gradient conflict
    is measured, how training tasks are drawn).
:class:`TaskSampler`
    draws the task of each training episode: ``uniform``, ``success`` (tasks with lower
    recent success more often) or ``progress`` (tasks whose success is changing fastest
    more often, as in teacher-student curricula).
:func:`project_conflicting`
    PCGrad (Yu et al. 2020, "Gradient surgery for multi-task learning"): each task's
    gradient loses its component along every other task's gradient it conflicts with.
:func:`conflict_stats`
    pairwise cosine similarity of task gradients (mean, minimum, fraction of conflicting
    pairs), the measure of how much tasks pull a shared network apart.
:class:`TaskGradients`
    an optimiser wrapper: per-task losses in, per-task gradients of one network out,
    projected (PCGrad) or not, and their weighted sum written into the flat gradient
    buffer of a :class:`~lcrl.nets.FlatAdam` before its step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from lcrl.errors import LcrlError
from lcrl.nets import FlatAdam

#: Strategies of :class:`TaskSampler`.
SAMPLING_STRATEGIES = ("uniform", "success", "progress")
#: Task loss weightings (:attr:`MultiTaskOptions.weighting`).
WEIGHTINGS = ("fixed", "gradnorm")

#: Names of the gradient-conflict statistics (:func:`conflict_stats`).
CONFLICT_KEYS = ("cos_mean", "cos_min", "conflict_fraction")


@dataclass
class MultiTaskOptions:
    """Options of multi-task training over a fixed task set (``env.tasks``)."""

    pcgrad: bool = False
    """Project conflicting task gradients (PCGrad) in the critic and actor updates (SAC):
    each task's gradient loses its component along every other task's gradient that it
    has a negative dot product with, before the gradients are summed."""
    task_weights: tuple[float, ...] = ()
    """Weight ``w_i`` of each task's loss in the objective ``sum_i w_i L_i`` (one per task;
    empty: all equal). Batch rows of task ``i`` weigh ``w_i / mean(w)``, so equal weights
    give the usual loss."""
    conflict_every: int = 0
    """Measure the cosine similarity between the tasks' critic and actor gradients every
    this many updates (0: never, unless PCGrad is on, which measures it every update).
    Runs with and without PCGrad report the same statistic: the cosines of the gradients
    before projection."""
    sampling: str = "uniform"
    """How each training episode's task is drawn: ``uniform``, ``success`` (tasks with
    lower recent success more often: ``p_i ~ 1 - s_i + eps``) or ``progress`` (tasks whose
    success changes fastest more often: ``p_i ~ |fast EMA - slow EMA| + eps`` of the task's
    episode successes)."""
    window: int = 50
    """Recent episodes per task behind its success rate (``success`` sampling and the
    per-task live success in progress.csv)."""
    eps: float = 0.05
    """Added to every task's score before normalising (``success``, ``progress``)."""
    uniform_mix: float = 0.2
    """Share of the uniform distribution mixed into ``success`` and ``progress``
    sampling: no task is drawn with probability below ``uniform_mix / K``."""
    weighting: str = "fixed"
    """How task losses are weighted: ``fixed`` (``task_weights``, or all equal) or
    ``gradnorm`` (SAC: weights learned so that the tasks' gradient norms balance, as in
    GradNorm, Chen et al. 2018; every update then splits the batch by task, as PCGrad does,
    and the weights are logged per task as ``task_weight/i``)."""
    gradnorm_alpha: float = 1.5
    """GradNorm's asymmetry: tasks whose loss fell least, relative to their first loss, get
    larger target gradient norms (0: equal norms for every task)."""
    gradnorm_lr: float = 0.025
    """Learning rate of GradNorm's task weights."""
    fast_rate: float = 0.1
    """Rate of the fast moving average of a task's success (``progress``)."""
    slow_rate: float = 0.01
    """Rate of the slow moving average of a task's success (``progress``)."""

    @property
    def measures_conflict(self) -> bool:
        """Whether gradient conflict between tasks is measured at all."""
        return self.pcgrad or self.conflict_every > 0

    @property
    def gradnorm(self) -> bool:
        """Whether task weights are learned by GradNorm."""
        return self.weighting == "gradnorm"

    @property
    def active(self) -> bool:
        """Whether the learner's update differs from the single-task one."""
        weights = np.asarray(self.task_weights, np.float64)
        uneven = weights.size > 0 and not np.allclose(weights, weights[0])
        return self.measures_conflict or uneven or self.gradnorm

    def validate(self, num_tasks: int) -> None:
        """Raise :class:`LcrlError` for inconsistent options, given the number of tasks
        (0: the run has no task set)."""
        if self.sampling not in SAMPLING_STRATEGIES:
            raise LcrlError(
                f"unknown task sampling {self.sampling!r}; choose one of {SAMPLING_STRATEGIES}"
            )
        if self.weighting not in WEIGHTINGS:
            raise LcrlError(
                f"unknown task weighting {self.weighting!r}; choose one of {WEIGHTINGS}"
            )
        if self.gradnorm and self.task_weights:
            raise LcrlError(
                "multitask.task_weights are fixed weights; multitask.weighting gradnorm "
                "learns them: give one or the other"
            )
        if self.gradnorm_alpha < 0 or self.gradnorm_lr <= 0:
            raise LcrlError(
                "multitask.gradnorm_alpha must be >= 0 and multitask.gradnorm_lr positive"
            )
        if self.conflict_every < 0:
            raise LcrlError(f"multitask.conflict_every must be >= 0, got {self.conflict_every}")
        if self.window < 1:
            raise LcrlError(f"multitask.window must be at least 1, got {self.window}")
        if self.eps <= 0:
            raise LcrlError(f"multitask.eps must be positive, got {self.eps}")
        if not 0.0 <= self.uniform_mix <= 1.0:
            raise LcrlError(f"multitask.uniform_mix must be in [0, 1], got {self.uniform_mix}")
        for name in ("fast_rate", "slow_rate"):
            rate = getattr(self, name)
            if not 0.0 < rate <= 1.0:
                raise LcrlError(f"multitask.{name} must be in (0, 1], got {rate}")
        if num_tasks == 0:
            asked = [
                name
                for name, on in (
                    ("pcgrad", self.pcgrad),
                    ("task_weights", bool(self.task_weights)),
                    ("conflict_every", self.conflict_every > 0),
                    ("sampling", self.sampling != "uniform"),
                    ("weighting", self.gradnorm),
                )
                if on
            ]
            if asked:
                raise LcrlError(
                    f"multitask.{asked[0]} needs a task set: list the tasks with --env.tasks "
                    "(and --env.goal-type task for one-hot task ids)"
                )
            return
        task_weights(self.task_weights, num_tasks)


def task_weights(weights: Sequence[float], num_tasks: int) -> np.ndarray:
    """Per-task row weights ``w_i / mean(w)`` (all ones for empty ``weights``).

    Raises:
        LcrlError: a weight count other than ``num_tasks``, a negative weight, or all zero.
    """
    if not weights:
        return np.ones(num_tasks, np.float64)
    w = np.asarray(weights, np.float64)
    if w.shape != (num_tasks,):
        raise LcrlError(
            f"multitask.task_weights has {w.size} values for {num_tasks} tasks: give one "
            "weight per task (or none for equal weights)"
        )
    if not np.all(np.isfinite(w)) or (w < 0).any() or w.sum() <= 0:
        raise LcrlError(
            f"multitask.task_weights must be finite, non-negative and not all zero, got "
            f"{tuple(weights)}"
        )
    return w / w.mean()


class GradNorm:
    """Task loss weights that balance the tasks' gradient norms (GradNorm, Chen et al. 2018).

    With ``G_i = w_i ||grad L_i||`` the weighted gradient norm of task ``i``, ``r_i`` its
    inverse training rate (``L_i / L_i(0)`` over the mean of that ratio) and ``alpha`` the
    asymmetry, each update moves the weights down the gradient of
    ``sum_i |G_i - mean(G) r_i^alpha|`` (the target treated as a constant, as in the paper),
    then keeps them positive and renormalises them to sum to ``K``. Tasks whose gradients
    are small, or whose loss has fallen least, gain weight.

    Args:
        num_tasks: ``K``.
        alpha: the asymmetry (0: equal weighted norms are the target).
        lr: the weights' learning rate.
    """

    def __init__(self, num_tasks: int, alpha: float = 1.5, lr: float = 0.025) -> None:
        self.weights = np.ones(num_tasks, np.float64)
        self.initial = np.full(num_tasks, np.nan)
        self.alpha, self.lr = float(alpha), float(lr)

    def update(self, norms: np.ndarray, losses: np.ndarray) -> np.ndarray:
        """One step of the weights from the tasks' unweighted gradient norms and losses
        (NaN for tasks absent from the batch, which keep their weight); returns them."""
        norms = np.asarray(norms, np.float64)
        losses = np.asarray(losses, np.float64)
        seen = np.isfinite(norms) & np.isfinite(losses)
        if seen.sum() < 2:
            return self.weights
        first = seen & ~np.isfinite(self.initial)
        self.initial[first] = np.maximum(np.abs(losses[first]), 1e-8)
        ratio = np.abs(losses[seen]) / self.initial[seen]
        r = ratio / max(ratio.mean(), 1e-12)
        g = self.weights[seen] * norms[seen]
        target = g.mean() * r**self.alpha
        w = self.weights.copy()
        w[seen] -= self.lr * np.sign(g - target) * norms[seen] / max(norms[seen].mean(), 1e-12)
        w = np.maximum(w, 1e-3)
        self.weights = w * len(w) / w.sum()
        return self.weights

    def state_dict(self) -> dict[str, Any]:
        """The weights and first losses (NaN: not seen yet, saved as None)."""
        return {
            "weights": self.weights.tolist(),
            "initial": [None if not np.isfinite(x) else float(x) for x in self.initial],
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.weights = np.asarray(state["weights"], np.float64)
        self.initial = np.asarray(
            [np.nan if x is None else x for x in state["initial"]], np.float64
        )


# --- task sampling ---------------------------------------------------------------------------
class TaskSampler:
    """Draws the task of each training episode and tracks every task's recent success.

    Strategies:

    ``uniform``
        every task with probability ``1 / K``.
    ``success``
        performance-based: ``p_i ~ (1 - s_i) + eps``, ``s_i`` the task's success rate over
        its last ``window`` episodes (0 before its first episode), so tasks the policy
        fails at are practised more.
    ``progress``
        learning progress, as in teacher-student curricula (Matiisen et al. 2017):
        ``p_i ~ |f_i - s_i| + eps`` where ``f_i`` and ``s_i`` are fast and slow moving
        averages (rates ``fast_rate`` and ``slow_rate``, bias-corrected) of the task's
        episode successes. A task the policy is getting better (or worse) at is drawn
        more often; one it has mastered or cannot do at all falls back to ``eps``.

    ``success`` and ``progress`` mix in ``uniform_mix`` of the uniform distribution, so
    every task keeps a probability of at least ``uniform_mix / K``: none starves.

    Args:
        num_tasks: ``K``.
        strategy: ``uniform``, ``success`` or ``progress``.
        window: recent episodes per task behind :meth:`success_rates`.
        eps: added to every score before normalising.
        uniform_mix: share of the uniform distribution in the probabilities.
        fast_rate: rate of the fast moving average (``progress``).
        slow_rate: rate of the slow moving average (``progress``).
    """

    def __init__(
        self,
        num_tasks: int,
        strategy: str = "uniform",
        window: int = 50,
        eps: float = 0.05,
        uniform_mix: float = 0.2,
        fast_rate: float = 0.1,
        slow_rate: float = 0.01,
    ) -> None:
        if num_tasks < 1:
            raise LcrlError(f"a task sampler needs at least one task, got {num_tasks}")
        MultiTaskOptions(
            sampling=strategy,
            window=window,
            eps=eps,
            uniform_mix=uniform_mix,
            fast_rate=fast_rate,
            slow_rate=slow_rate,
        ).validate(num_tasks)
        self.num_tasks = int(num_tasks)
        self.strategy = strategy
        self.window = int(window)
        self.eps = float(eps)
        self.uniform_mix = float(uniform_mix)
        self.fast_rate = float(fast_rate)
        self.slow_rate = float(slow_rate)
        self._history = np.zeros((self.num_tasks, self.window), np.float64)
        self._count = np.zeros(self.num_tasks, np.int64)  # episodes per task, all time
        self._fast = np.zeros(self.num_tasks, np.float64)
        self._slow = np.zeros(self.num_tasks, np.float64)

    @classmethod
    def from_options(cls, num_tasks: int, options: MultiTaskOptions) -> TaskSampler:
        """The sampler a :class:`MultiTaskOptions` describes."""
        return cls(
            num_tasks,
            options.sampling,
            window=options.window,
            eps=options.eps,
            uniform_mix=options.uniform_mix,
            fast_rate=options.fast_rate,
            slow_rate=options.slow_rate,
        )

    def update(self, task: int, success: bool | float) -> None:
        """Record the outcome of one episode of ``task``."""
        if not 0 <= task < self.num_tasks:
            raise LcrlError(f"task {task} is outside [0, {self.num_tasks})")
        s = float(success)
        self._history[task, self._count[task] % self.window] = s
        self._count[task] += 1
        self._fast[task] += self.fast_rate * (s - self._fast[task])
        self._slow[task] += self.slow_rate * (s - self._slow[task])

    @property
    def episodes(self) -> np.ndarray:
        """Episodes recorded per task, ``(K,)``."""
        return self._count.copy()

    def success_rates(self) -> np.ndarray:
        """Success over each task's last ``window`` episodes, ``(K,)``; NaN before a
        task's first episode."""
        n = np.minimum(self._count, self.window)
        total = self._history.sum(1)  # unfilled entries are 0
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, total / np.maximum(n, 1), np.nan)

    def progress(self) -> np.ndarray:
        """Learning progress ``|fast - slow|`` of each task's bias-corrected moving
        averages of success, ``(K,)`` (0 before a task's first episode)."""
        n = self._count.astype(np.float64)
        fast = self._fast / np.maximum(1.0 - (1.0 - self.fast_rate) ** n, 1e-12)
        slow = self._slow / np.maximum(1.0 - (1.0 - self.slow_rate) ** n, 1e-12)
        return np.where(n > 0, np.abs(fast - slow), 0.0)

    def probs(self) -> np.ndarray:
        """The probability of drawing each task next, ``(K,)``."""
        k = self.num_tasks
        if self.strategy == "uniform":
            return np.full(k, 1.0 / k)
        if self.strategy == "success":
            score = 1.0 - np.nan_to_num(self.success_rates(), nan=0.0) + self.eps
        else:
            score = self.progress() + self.eps
        p = score / score.sum()
        return (1.0 - self.uniform_mix) * p + self.uniform_mix / k

    def sample(self, rng: np.random.Generator) -> int:
        """Draw a task id with :meth:`probs` (one uniform number from ``rng``)."""
        cdf = np.cumsum(self.probs())
        return int(min(np.searchsorted(cdf, rng.random() * cdf[-1], side="right"), len(cdf) - 1))

    def state_dict(self) -> dict[str, Any]:
        """Everything the sampler has recorded (plain lists and numbers, for checkpoints)."""
        return {
            "num_tasks": self.num_tasks,
            "strategy": self.strategy,
            "window": self.window,
            "history": self._history.tolist(),
            "count": self._count.tolist(),
            "fast": self._fast.tolist(),
            "slow": self._slow.tolist(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises:
            LcrlError: the state belongs to a sampler over another number of tasks or with
                another window.
        """
        if int(state["num_tasks"]) != self.num_tasks or int(state["window"]) != self.window:
            raise LcrlError(
                f"saved task sampler has {state['num_tasks']} tasks and a window of "
                f"{state['window']}; this one has {self.num_tasks} and {self.window}"
            )
        self._history = np.asarray(state["history"], np.float64).reshape(
            self.num_tasks, self.window
        )
        self._count = np.asarray(state["count"], np.int64).reshape(self.num_tasks)
        self._fast = np.asarray(state["fast"], np.float64).reshape(self.num_tasks)
        self._slow = np.asarray(state["slow"], np.float64).reshape(self.num_tasks)


# --- PCGrad and gradient conflict ----------------------------------------------------------
def gram_matrix(grads: torch.Tensor) -> np.ndarray:
    """``(K, K)`` dot products of the rows of ``grads`` (computed in their dtype, returned as
    float64 numpy)."""
    g = grads.detach()
    return (g @ g.T).double().cpu().numpy()


def pcgrad_coefficients(
    gram: np.ndarray,
    order: Sequence[Sequence[int]] | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """PCGrad's projection as coefficients: ``C`` with ``projected = g - C @ g``.

    Task ``i`` visits the other tasks in turn; where its gradient as projected so far has a
    negative dot product with task ``j``'s original gradient, ``C[i, j]`` takes
    ``(g_i . g_j) / ||g_j||^2``. The dot products of the projected gradients follow from
    the Gram matrix of the original ones, so no ``D``-sized vector is touched here.

    Args:
        gram: ``(K, K)`` dot products of the original gradients (:func:`gram_matrix`).
        order: ``order[i]`` lists the other tasks in the order task ``i`` visits them.
        rng: draws a random order per task when ``order`` is not given; without either,
            tasks are visited in increasing index order.
    """
    gram = np.asarray(gram, np.float64)
    k = gram.shape[0]
    coef = np.zeros((k, k), np.float64)
    for i in range(k):
        others = [j for j in range(k) if j != i]
        if order is not None:
            visit = [int(j) for j in order[i]]
            if sorted(visit) != others:
                raise LcrlError(f"order[{i}] must list every task but {i} once, got {visit}")
        elif rng is not None:
            visit = [others[j] for j in rng.permutation(len(others))]
        else:
            visit = others
        for j in visit:
            if gram[j, j] <= 0.0:
                continue
            dot = gram[i, j] - coef[i] @ gram[:, j]  # (projected g_i) . g_j
            if dot < 0.0:
                coef[i, j] += dot / gram[j, j]
    return coef


def project_conflicting(
    grads: torch.Tensor,
    order: Sequence[Sequence[int]] | None = None,
    rng: np.random.Generator | None = None,
) -> torch.Tensor:
    """PCGrad's projection of conflicting task gradients (Yu et al. 2020).

    For each task ``i`` and each other task ``j`` in turn, if ``g_i . g_j < 0`` then
    ``g_i <- g_i - (g_i . g_j) / ||g_j||^2 g_j``, where ``g_i`` is task ``i``'s gradient as
    projected so far and ``g_j`` task ``j``'s *original* gradient. With two tasks the
    projected ``g_i`` is orthogonal to ``g_j``; with more, the result depends on the order
    in which the other tasks are visited, which PCGrad randomises.

    The dot products are tracked through the ``K x K`` Gram matrix of the original
    gradients (:func:`pcgrad_coefficients`), so the whole projection costs two matrix
    products however large ``D`` is.

    Args:
        grads: ``(K, D)`` per-task gradients (rows of zeros are tasks without data: they
            neither change nor are changed).
        order: ``order[i]`` lists the other tasks in the order task ``i`` visits them.
        rng: draws a random order per task when ``order`` is not given; without either,
            tasks are visited in increasing index order.

    Returns:
        ``(K, D)`` projected gradients, same dtype and device as ``grads``.
    """
    if grads.dim() != 2:
        raise LcrlError(f"grads must be (K, D), got shape {tuple(grads.shape)}")
    coef = pcgrad_coefficients(gram_matrix(grads), order, rng)
    g = grads.detach()
    return g - torch.as_tensor(coef, dtype=g.dtype, device=g.device) @ g


def conflict_stats(grads: torch.Tensor, gram: np.ndarray | None = None) -> dict[str, float]:
    """How much task gradients disagree: over the pairs of tasks with non-zero gradients,
    the mean and minimum cosine similarity and the fraction of pairs with a negative dot
    product (NaN when fewer than two tasks have a gradient).

    Args:
        grads: ``(K, D)`` per-task gradients.
        gram: their Gram matrix, when already computed (:func:`gram_matrix`).

    Returns:
        ``{"cos_mean", "cos_min", "conflict_fraction", "pairs"}``.
    """
    gram = gram_matrix(grads) if gram is None else np.asarray(gram, np.float64)
    norms = np.sqrt(np.maximum(np.diag(gram), 0.0))
    live = np.flatnonzero(norms > 0)
    if live.size < 2:
        nan = float("nan")
        return {"cos_mean": nan, "cos_min": nan, "conflict_fraction": nan, "pairs": 0.0}
    i, j = np.triu_indices(live.size, 1)
    a, b = live[i], live[j]
    cos = np.clip(gram[a, b] / (norms[a] * norms[b]), -1.0, 1.0)
    return {
        "cos_mean": float(cos.mean()),
        "cos_min": float(cos.min()),
        "conflict_fraction": float((gram[a, b] < 0).mean()),
        "pairs": float(cos.size),
    }


class TaskGradients:
    """Per-task losses of one network into its :class:`~lcrl.nets.FlatAdam` step.

    :meth:`backward` back-propagates each task's loss on its own into the optimiser's flat
    gradient buffer, collects the ``(K, D)`` task gradients, measures their conflict,
    projects them with :func:`project_conflicting` when ``pcgrad`` is on, and writes
    ``sum_i c_i g_i`` back into the buffer; :meth:`step` then steps the optimiser. With
    coefficients ``c_i`` and no conflicting pair the result is exactly the gradient of
    ``sum_i c_i L_i``.

    Each loss should come from its own forward pass (e.g. the task's rows of a batch), so
    that the backward passes together cost about one backward pass over the whole batch.

    Args:
        optimizer: the network's optimiser (its ``grad`` buffer is written).
        pcgrad: project conflicting gradients before summing them.
    """

    def __init__(self, optimizer: FlatAdam, pcgrad: bool = True) -> None:
        self.optimizer = optimizer
        self.pcgrad = pcgrad

    def task_gradients(self, losses: Sequence[torch.Tensor | None]) -> torch.Tensor:
        """``(K, D)`` gradients of each loss (zeros for ``None``: a task without rows)."""
        opt = self.optimizer
        grads = torch.zeros(len(losses), opt.grad.numel(), device=opt.grad.device)
        for i, loss in enumerate(losses):
            if loss is None:
                continue
            opt.zero_grad()
            loss.backward()
            grads[i] = opt.grad
        return grads

    def backward(
        self,
        losses: Sequence[torch.Tensor | None],
        coefs: Sequence[float] | np.ndarray | torch.Tensor,
        rng: np.random.Generator | None = None,
    ) -> dict[str, float]:
        """Write the combined gradient into the optimiser's buffer.

        Args:
            losses: one scalar loss per task (``None`` for a task without data).
            coefs: ``c_i``, the weight of each task's gradient in the sum.
            rng: randomises PCGrad's visiting order (fixed order without it).

        Returns:
            :func:`conflict_stats` of the gradients before projection.
        """
        if len(losses) != len(coefs):
            raise LcrlError(f"{len(losses)} losses but {len(coefs)} coefficients")
        grads = self.task_gradients(losses)
        gram = gram_matrix(grads)
        stats: dict[str, Any] = dict(conflict_stats(grads, gram))
        # each task's gradient norm (NaN for a task without data), for GradNorm
        stats["norms"] = np.where(
            [loss is None for loss in losses], np.nan, np.sqrt(np.maximum(np.diag(gram), 0.0))
        )
        c = np.asarray(coefs, np.float64)
        if self.pcgrad:  # sum_i c_i (g_i - sum_j C_ij g_j) = (c (I - C)) @ g
            c = c @ (np.eye(len(c)) - pcgrad_coefficients(gram, rng=rng))
        w = torch.as_tensor(c, dtype=grads.dtype, device=grads.device)
        with torch.no_grad():
            self.optimizer.grad.copy_(w @ grads)
        return stats

    def step(
        self,
        losses: Sequence[torch.Tensor | None],
        coefs: Sequence[float] | np.ndarray | torch.Tensor,
        rng: np.random.Generator | None = None,
    ) -> dict[str, float]:
        """:meth:`backward`, then one optimiser step; returns the conflict statistics."""
        stats = self.backward(losses, coefs, rng)
        self.optimizer.step()
        return stats


def rows_by_task(tasks: np.ndarray, num_tasks: int) -> list[np.ndarray]:
    """Indices of the batch rows of each task (empty arrays for absent tasks).

    Raises:
        LcrlError: a task id outside ``[0, num_tasks)``.
    """
    tasks = np.asarray(tasks, np.int64).reshape(-1)
    if tasks.size and (tasks.min() < 0 or tasks.max() >= num_tasks):
        raise LcrlError(f"batch task ids must be in [0, {num_tasks}), got {np.unique(tasks)}")
    order = np.argsort(tasks, kind="stable")
    bounds = np.searchsorted(tasks[order], np.arange(num_tasks + 1))
    return [order[bounds[i] : bounds[i + 1]] for i in range(num_tasks)]

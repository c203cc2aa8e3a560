"""Ensemble MLPs with a hand-written backward pass: the same values and gradients as
autograd through :class:`lcrl.nets.layers.BatchedLinear` layers and ReLUs, in fewer and
cheaper kernels.

Autograd takes a one-output layer's weight gradient as a product and a sum over an
``(n, B, H)`` temporary, and runs each layer's backward node by node. :class:`EnsembleMLP`
takes that weight gradient as one batched product, each ReLU's gradient as one kernel, and
skips what no input asks for. ``benchmarks/update_floor.py`` times the whole update.

:class:`EnsembleMin` is the actor's view of frozen critics, ``min_k Q_k``: the gradient of
a row flows through the member that is smallest there only, so its backward pass runs
each row through one member instead of all (half the work for twin critics). Its
parameters must not require gradients.

Both take the input ``x`` as ``(B, in)`` (shared by all members) or ``(n, B, in)``, then
the layers' weights ``(n, in, out)`` and biases ``(n, 1, out)`` in order; ReLU follows
every layer but the last. They are for float32 outside autocast and compilation; the
caller (:meth:`lcrl.nets.heads.GoalConditionedEnsemble.forward`) falls back to the layers
elsewhere.
"""

from __future__ import annotations

from typing import Any

import torch


def _layers(x: torch.Tensor, params: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
    """Every layer's input and the last layer's output: ``[x, h_1, ..., h_L-1, out]``."""
    n = params[0].shape[0]
    acts = [x]
    h = x
    last = len(params) // 2 - 1
    for k in range(last + 1):
        w, b = params[2 * k], params[2 * k + 1]
        if h.dim() == 2:
            h = h.expand(n, *h.shape)
        if w.shape[2] == 1:  # a one-output layer: a product and a sum beat bmm on the CPU
            h = (h * w.transpose(1, 2)).sum(-1, keepdim=True) + b
        else:
            h = torch.baddbmm(b, h, w)
        if k < last:
            h = h.relu_()
        acts.append(h)
    return acts


def _back(gh: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The gradient of a layer's input from that of its output ``gh`` ``(n, B, out)``."""
    if w.shape[2] == 1:
        return gh * w.transpose(1, 2)
    return torch.bmm(gh, w.transpose(1, 2))


def _relu_back(grad: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``grad`` where the ReLU's output ``out`` is positive, else 0 (one kernel; a mask of
    booleans costs several times more on the CPU)."""
    return torch.ops.aten.threshold_backward(grad, out, 0.0)


class EnsembleMLP(torch.autograd.Function):
    """``(n, B, out)`` values of the members; backward written out (see the module)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, *params: torch.Tensor) -> torch.Tensor:
        acts = _layers(x, params)
        ctx.save_for_backward(*acts[:-1], *params)
        ctx.depth = len(acts) - 1
        return acts[-1]

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        saved = ctx.saved_tensors
        depth = ctx.depth
        acts, params = saved[:depth], saved[depth:]
        needs = ctx.needs_input_grad
        grads: list[torch.Tensor | None] = [None] * (1 + len(params))
        n = params[0].shape[0]
        gh = grad.contiguous()
        for k in reversed(range(depth)):
            w = params[2 * k]
            a = acts[k] if acts[k].dim() == 3 else acts[k].expand(n, *acts[k].shape)
            if needs[1 + 2 * k]:
                if w.shape[2] == 1:  # (n, 1, B) @ (n, B, H), transposed to (n, H, 1)
                    grads[1 + 2 * k] = torch.bmm(gh.transpose(1, 2), a).transpose(1, 2)
                else:
                    grads[1 + 2 * k] = torch.bmm(a.transpose(1, 2), gh)
            if needs[2 + 2 * k]:
                grads[2 + 2 * k] = gh.sum(1, keepdim=True)
            if k == 0 and not needs[0]:
                break
            gh = _back(gh, w)
            if k > 0:
                gh = _relu_back(gh, acts[k])
        if needs[0]:
            grads[0] = gh.sum(0) if acts[0].dim() == 2 else gh
        return tuple(grads)


class EnsembleMin(torch.autograd.Function):
    """``(B, out)``: the smallest member's value per row, for frozen parameters; the
    gradient of ``x`` only (see the module)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, *params: torch.Tensor) -> torch.Tensor:
        acts = _layers(x, params)
        values, index = acts[-1].min(0)
        ctx.save_for_backward(*acts[:-1], index, *params)
        ctx.depth = len(acts) - 1
        return values

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        saved = ctx.saved_tensors
        depth = ctx.depth
        acts, index, params = saved[:depth], saved[depth], saved[depth + 1 :]
        x = acts[0]
        gx = x.new_zeros(x.shape)
        for i in range(params[0].shape[0]):
            rows = (index[:, 0] == i).nonzero().squeeze(1)
            if rows.numel() == 0:
                continue
            gh = grad.index_select(0, rows)
            for k in reversed(range(depth)):
                w = params[2 * k][i]
                gh = gh * w.transpose(0, 1) if w.shape[1] == 1 else gh @ w.transpose(0, 1)
                if k > 0:
                    gh = _relu_back(gh, acts[k][i].index_select(0, rows))
            if x.dim() == 2:
                gx.index_copy_(0, rows, gh)
            else:
                gx[i].index_copy_(0, rows, gh)
        return (gx, *([None] * len(params)))

"""GradNorm task weighting (``--agent.multitask.weighting gradnorm``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from helpers import tiny
from test_multitask import read_csv

from lcrl.errors import LcrlError
from lcrl.multitask import GradNorm, MultiTaskOptions
from train.training.loop import Trainer


def _weighted_norms(grad_norm: GradNorm, theta: torch.Tensor, scales: list[float]) -> np.ndarray:
    """One GradNorm step on hand-made losses ``s_i ||theta - c_i||^2``; returns the
    weighted gradient norms ``w_i ||grad L_i||`` before the step."""
    norms, losses = [], []
    for i, s in enumerate(scales):
        t = theta.detach().clone().requires_grad_(True)
        loss = s * (t - float(i)).pow(2).sum()
        (g,) = torch.autograd.grad(loss, t)
        norms.append(float(g.norm()))
        losses.append(float(loss.detach()))
    before = grad_norm.weights * np.asarray(norms)
    grad_norm.update(np.asarray(norms), np.asarray(losses))
    return before


def test_gradnorm_weights_move_toward_equal_gradient_norms():
    """Task 0's gradient is 10x task 1's: with alpha 0 the weighted norms converge."""
    gn = GradNorm(2, alpha=0.0, lr=0.05)
    theta = torch.full((4,), 3.0)
    first = _weighted_norms(gn, theta, [10.0, 1.0])
    for _ in range(300):
        last = _weighted_norms(gn, theta, [10.0, 1.0])
    assert abs(math.log(first[0] / first[1])) > 2.0
    assert abs(math.log(last[0] / last[1])) < 0.3
    assert gn.weights[1] > gn.weights[0] and gn.weights.sum() == pytest.approx(2.0)


def test_gradnorm_favours_the_task_whose_loss_fell_least():
    """Equal gradient norms, but task 1's loss stayed at its start while task 0's fell:
    with alpha > 0 task 1 is given the larger weight."""
    gn = GradNorm(2, alpha=1.5, lr=0.05)
    gn.update(np.array([1.0, 1.0]), np.array([1.0, 1.0]))  # the first losses
    for _ in range(50):
        gn.update(np.array([1.0, 1.0]), np.array([0.2, 1.0]))
    assert gn.weights[1] > 1.2 > gn.weights[0]


def test_gradnorm_leaves_absent_tasks_alone_and_round_trips():
    gn = GradNorm(3)
    gn.update(np.array([5.0, 1.0, np.nan]), np.array([1.0, 1.0, np.nan]))
    assert gn.weights.sum() == pytest.approx(3.0) and math.isnan(gn.initial[2])
    again = GradNorm(3)
    again.load_state_dict(gn.state_dict())
    np.testing.assert_array_equal(again.weights, gn.weights)
    assert math.isnan(again.initial[2]) and again.initial[0] == gn.initial[0]


def test_gradnorm_options_are_checked():
    with pytest.raises(LcrlError, match="unknown task weighting 'nope'"):
        MultiTaskOptions(weighting="nope").validate(8)
    with pytest.raises(LcrlError, match="give one or the other"):
        MultiTaskOptions(weighting="gradnorm", task_weights=(1.0,) * 8).validate(8)
    with pytest.raises(LcrlError, match="needs a task set"):
        MultiTaskOptions(weighting="gradnorm").validate(0)


def test_train_lang2d_tasks_with_gradnorm_logs_and_resumes_the_weights(tmp_path):
    cfg = tiny("lang2d-tasks", tmp_path / "run", total_steps=10_000, learning_starts=60)
    cfg.agent.multitask = MultiTaskOptions(weighting="gradnorm", gradnorm_lr=0.05)
    trainer = Trainer(cfg)
    trainer.open_outputs()
    for _ in range(6):
        trainer.collect_episode()
    trainer.log()
    weights = trainer.agent.learned_task_weights()
    assert weights.sum() == pytest.approx(8.0) and not np.allclose(weights, 1.0)
    fields, rows = read_csv(tmp_path / "run" / "progress.csv")
    columns = [f"tasks/{i}/weight" for i in range(8)]
    assert set(columns) <= set(fields)
    assert sum(float(rows[-1][c]) for c in columns) == pytest.approx(8.0, rel=1e-4)
    trainer.save()
    resumed = Trainer(dataclasses.replace(cfg, resume=True))
    np.testing.assert_allclose(resumed.agent.learned_task_weights(), weights)

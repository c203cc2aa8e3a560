"""Sequential stages, forgetting and EWC (``--sequential.*``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from helpers import cli, error_line, tiny

from lcrl.buffer import Batch, batch_rows
from lcrl.continual import EWC
from train.configs.config import SequentialConfig
from train.evaluation.sequential import transfer_metrics
from train.training.loop import Trainer


def test_ewc_penalty_is_zero_at_the_anchor_and_grows_away_from_it():
    ewc = EWC(weight=2.0)
    params = torch.tensor([1.0, -2.0, 0.5])
    assert ewc.penalty("critic", params) == 0.0 and ewc.grad("critic", params) is None
    ewc.consolidate("critic", params, torch.tensor([1.0, 0.0, 4.0]))
    assert ewc.penalty("critic", params) == 0.0
    assert torch.equal(ewc.grad("critic", params), torch.zeros(3))
    near, far = params + 0.1, params + 1.0
    assert 0.0 < ewc.penalty("critic", near) < ewc.penalty("critic", far)
    # quadratic: ten times further costs a hundred times more
    assert ewc.penalty("critic", far) == pytest.approx(100 * ewc.penalty("critic", near))
    # the gradient added to the optimiser's is the penalty's own
    x = far.clone().requires_grad_(True)
    ewc.penalty("critic", x).backward()
    assert torch.allclose(x.grad, ewc.grad("critic", far))
    # a weight with zero Fisher information is free to move
    moved = params.clone()
    moved[1] += 5.0
    assert ewc.penalty("critic", moved) == 0.0
    # a second stage adds its Fisher and moves the anchor
    ewc.consolidate("critic", far, torch.ones(3))
    assert ewc.penalty("critic", far) == 0.0
    assert torch.equal(ewc.fisher["critic"], torch.tensor([2.0, 1.0, 5.0]))
    again = EWC(2.0)
    again.load_state_dict(ewc.state_dict())
    assert again.penalty("critic", params) == ewc.penalty("critic", params)


def test_batch_rows_picks_the_same_rows_of_every_array():
    batch = Batch(
        obs={"x": np.arange(10).reshape(5, 2)},
        action=np.arange(5.0),
        reward=np.arange(5.0) * 2,
        next_obs={"x": np.arange(10).reshape(5, 2) + 1},
        terminated=np.zeros(5),
        goal=np.arange(5) + 10,
        relabelled=np.array([True, False, True, False, True]),
        index=np.arange(5) + 100,
    )
    row = batch_rows(batch, [3])
    assert row.obs["x"].tolist() == [[6, 7]] and row.next_obs["x"].tolist() == [[7, 8]]
    assert row.action.tolist() == [3.0] and row.goal.tolist() == [13]
    assert row.index.tolist() == [103] and row.discount is None


def test_transfer_metrics_by_hand():
    stages = [("reach",), ("push",), ("put",)]
    matrix = [
        {"reach": 0.1, "push": 0.0, "put": 0.0},  # before training
        {"reach": 0.9, "push": 0.2, "put": 0.0},  # after reach
        {"reach": 0.5, "push": 0.8, "put": 0.1},  # after push
        {"reach": 0.3, "push": 0.6, "put": 0.7},  # after put
    ]
    m = transfer_metrics(matrix, stages)
    assert m["forgetting"] == pytest.approx(((0.9 - 0.3) + (0.8 - 0.6)) / 2)
    assert m["backward_transfer"] == pytest.approx(((0.3 - 0.9) + (0.6 - 0.8)) / 2)
    assert m["forward_transfer"] == pytest.approx(((0.2 - 0.0) + (0.1 - 0.0)) / 2)
    assert m["final_mean"] == pytest.approx((0.3 + 0.6 + 0.7) / 3)
    # after one stage nothing can have been forgotten yet
    assert math.isnan(transfer_metrics(matrix[:2], stages)["forgetting"])


@pytest.mark.parametrize(("replay", "ewc"), [(0, 0.0), (150, 10.0)])
def test_sequential_run_writes_its_matrix(tmp_path, replay, ewc):
    out = tmp_path / "run"
    cfg = tiny(
        "lang2d",
        out,
        total_steps=400,
        learning_starts=100,
        eval_episodes=6,
        sequential=SequentialConfig(
            stages=("reach", "push"), replay=replay, ewc=ewc, ewc_samples=12
        ),
    )
    trainer = Trainer(cfg)
    assert trainer.envs[0].unwrapped is not None
    sizes: list[int] = []
    gradients = trainer.agent.output_gradients  # the default Fisher: of the outputs

    def per_row(batch):
        sizes.append(len(batch.action))
        return gradients(batch)

    trainer.agent.output_gradients = per_row
    trainer.run()
    payload = json.loads((out / "sequential.json").read_text())
    assert [r["after"] for r in payload["rows"]] == ["init", "reach", "push"]
    assert payload["families"] == ["reach", "push"]
    assert set(payload["metrics"]) == {
        "forgetting", "backward_transfer", "forward_transfer", "final_mean"
    }  # fmt: skip
    assert math.isfinite(payload["metrics"]["forgetting"])
    assert (out / "sequential.png").is_file()
    assert "## Sequential stages" in (out / "report.md").read_text()
    if ewc:  # the Fisher of both networks, anchored at the end of the first stage
        assert set(trainer.agent.ewc.fisher) == {"critic", "actor"}
        assert trainer.agent.ewc.fisher["critic"].sum() > 0
        assert sizes == [1] * 12  # one transition per squared gradient
    if replay:
        steps = sum(len(e["action"]) for e in trainer.memory[0])
        assert 0 < steps <= replay


def test_stages_train_only_their_families(tmp_path):
    cfg = tiny("lang2d", tmp_path / "run", sequential=SequentialConfig(stages=("push", "reach")))
    trainer = Trainer(cfg)
    try:
        from train.environments.tasks import find_language_wrapper

        assert find_language_wrapper(trainer.envs[0]).families == ("push",)
        families = {trainer.task.captioner.parse(t).family for t in trainer.task.label_ids}
        assert families == {"push"}
        assert len(trainer.task.table) > len(trainer.task.label_ids)  # the table spans both
    finally:
        trainer.close()


def test_bad_stages_are_one_line_errors(tmp_path, capsys):
    status = cli(
        "train", "lang2d", "--out", str(tmp_path / "r"), "--sequential.stages", "reach", "lift",
    )  # fmt: skip
    assert status != 0
    assert error_line(capsys.readouterr().err) == (
        "lcrl: error: sequential.stages: lift is not made of env.families ('reach', 'push')"
    )


def test_output_fisher_is_the_score_of_the_policy_and_the_q_gradient(tmp_path):
    """``ewc_fisher=output``: the actor's gradient is the score of a pre-squash action drawn
    from the policy (checked against autograd of the Gaussian log-likelihood), the
    critic's the gradient of its Q-values; neither is scaled by a loss."""
    trainer = Trainer(tiny("lang2d", tmp_path / "run", learning_starts=50))
    try:
        while trainer.buffer.size < 60:
            trainer.collect_episode()
        agent = trainer.agent
        row = batch_rows(trainer.buffer.sample(4), [0])
        state = agent.gen.get_state()
        grads = agent.output_gradients(row)
        agent.gen.set_state(state)
        obs, _, goal, act, _, _ = agent.batch_tensors(row)
        mean, log_std = agent.actor(obs, goal).chunk(2, -1)
        log_std = log_std.clamp(-20.0, 2.0)
        noise = torch.randn(mean.shape, generator=agent.gen, device=agent.device)
        u = (mean + log_std.exp() * noise).detach()
        agent.actor_opt.zero_grad()
        torch.distributions.Normal(mean, log_std.exp()).log_prob(u).sum().backward()
        assert torch.allclose(grads["actor"], agent.actor_opt.grad, atol=1e-5)
        agent.critic_opt.zero_grad()
        agent.critic(obs, goal, act).sum().backward()
        assert torch.allclose(grads["critic"], agent.critic_opt.grad, atol=1e-6)
        assert grads["critic"].abs().sum() > 0 and grads["actor"].abs().sum() > 0
        agent.actor_opt.zero_grad()
        agent.critic_opt.zero_grad()
    finally:
        trainer.close()


def test_stages_with_the_output_fisher_consolidate_both_networks(tmp_path):
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        total_steps=400,
        sequential=SequentialConfig(
            stages=("reach", "push"), ewc=1.0, ewc_samples=8, ewc_fisher="output"
        ),
    )
    trainer = Trainer(cfg)
    trainer.run()
    fisher = trainer.agent.ewc.fisher
    assert set(fisher) == {"critic", "actor"}
    assert all(f.min() >= 0 and f.sum() > 0 for f in fisher.values())


@pytest.mark.parametrize("freeze", [False, True])
def test_freeze_norm_keeps_the_first_stage_statistics(tmp_path, freeze):
    cfg = tiny(
        "lang2d",
        tmp_path / "run",
        total_steps=400,
        sequential=SequentialConfig(stages=("reach", "push"), freeze_norm=freeze),
    )
    trainer = Trainer(cfg)
    norm = trainer.agent.norms["obs_observation"]
    counts: list[float] = []
    next_stage = trainer.next_stage

    def record():
        counts.append(float(norm.count))
        next_stage()

    trainer.next_stage = record
    trainer.run()
    assert len(counts) == 1 and counts[0] > 0
    # frozen: the push stage's observations never reach the normaliser
    assert (float(norm.count) == counts[0]) is freeze

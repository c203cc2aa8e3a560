"""Tests for lcrl.nets and lcrl.algos: FlatAdam, fusion, normalisers, SAC, TD3 and DQN."""

from __future__ import annotations

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from lcrl import algos
from lcrl.algos import (
    ALGOS,
    DQN,
    SAC,
    TD3,
    AgentOptions,
    DQNConfig,
    Problem,
    SACConfig,
    TD3Config,
)
from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from lcrl.nets import ConvEncoder, FlatAdam, FusedMLP, NetConfig, RunningNorm, WhiteningNorm


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny nets are fastest (and not starved by other processes) on one intra-op thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.optim.Adam([nn.Parameter(torch.zeros(1))])  # pay torch's lazy imports here
    yield
    torch.set_num_threads(threads)


# --- helpers -----------------------------------------------------------------------------
TEXT_TABLE = torch.randn(10, 16, generator=torch.Generator().manual_seed(1234))
KEYS = {
    "sac": {"critic_loss", "actor_loss", "alpha", "q", "q_max", "entropy"},
    "td3": {"critic_loss", "actor_loss", "q"},
    "dqn": {"loss", "q", "epsilon"},
}


def vector_embed(goals, device):
    return torch.as_tensor(goals, dtype=torch.float32, device=device)


def text_embed(goals, device):
    return TEXT_TABLE[torch.as_tensor(goals, dtype=torch.long)].to(device)


def onehot_embed(goals, device):
    return torch.eye(5, device=device)[torch.as_tensor(goals, dtype=torch.long, device=device)]


def image_embed(goals, device):
    return torch.as_tensor(goals, device=device)


EMBEDS = {"vector": vector_embed, "text": text_embed, "onehot": onehot_embed, "image": image_embed}


def options(seed: int = 0, **net) -> AgentOptions:
    net.setdefault("hidden", (32, 32))
    return AgentOptions(net=NetConfig(**net), seed=seed)


def problem(discrete: bool, obs_dim: int = 3, goal_dim: int = 2, action_dim: int = 2) -> Problem:
    return Problem({"state": (obs_dim,)}, "vector", (goal_dim,), action_dim, discrete)


def make_agent(algo: str, seed: int = 0, prob: Problem | None = None, config=None, **net):
    cls = ALGOS[algo].agent
    prob = prob or problem(algo == "dqn")
    return cls(prob, options(seed, **net), EMBEDS[prob.goal_kind], config)


def make_batch(prob: Problem, rng: np.random.Generator, size: int = 16) -> Batch:
    def obs():
        out = {}
        for key, shape in prob.obs_shapes.items():
            if len(shape) == 3:
                out[key] = rng.integers(0, 256, (size, *shape), dtype=np.uint8)
            else:
                out[key] = rng.normal(size=(size, *shape)).astype(np.float32)
        return out

    if prob.discrete:
        action = rng.integers(0, prob.action_dim, size).astype(np.int64)
    else:
        action = rng.uniform(-1, 1, (size, prob.action_dim)).astype(np.float32)
    if prob.goal_kind == "vector":
        goal = rng.normal(size=(size, *prob.goal_shape)).astype(np.float32)
    elif prob.goal_kind == "image":
        goal = rng.integers(0, 256, (size, *prob.goal_shape), dtype=np.uint8)
    else:
        goal = rng.integers(0, 10 if prob.goal_kind == "text" else 5, size).astype(np.int64)
    return Batch(
        obs=obs(),
        action=action,
        reward=(rng.random(size) < 0.3).astype(np.float32),
        next_obs=obs(),
        terminated=(rng.random(size) < 0.2).astype(np.float32),
        goal=goal,
        relabelled=np.zeros(size, bool),
        index=np.arange(size),
    )


def batches(prob: Problem, n: int, seed: int = 0, size: int = 16) -> list[Batch]:
    rng = np.random.default_rng(seed)
    return [make_batch(prob, rng, size) for _ in range(n)]


def snapshot(agent) -> dict[str, torch.Tensor]:
    """Every weight and buffer of the agent (and SAC's temperature), cloned."""
    out = {
        f"{name}.{key}": value.detach().clone()
        for name, module in agent.modules().items()
        for key, value in module.state_dict().items()
    }
    if isinstance(agent, SAC):
        out["log_alpha"] = agent.log_alpha.detach().clone()
    return out


def assert_identical(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def repeated(batch: Batch, i: int, size: int, **override) -> Batch:
    """A batch of ``size`` copies of transition ``i`` of ``batch`` (fields overridable)."""

    def rep(x):
        return np.repeat(x[i : i + 1], size, axis=0)

    fields = {
        "obs": {k: rep(v) for k, v in batch.obs.items()},
        "action": rep(batch.action),
        "reward": rep(batch.reward),
        "next_obs": {k: rep(v) for k, v in batch.next_obs.items()},
        "terminated": rep(batch.terminated),
        "goal": rep(batch.goal),
        "relabelled": np.zeros(size, bool),
        "index": np.zeros(size, np.int64),
    }
    fields.update(override)
    return Batch(**fields)


class ConstCritics(nn.Module):
    """Stand-in for a target critic ensemble: every member predicts ``value``."""

    def __init__(self, value: float, members: int = 2) -> None:
        super().__init__()
        self.value = value
        self.members = members

    def forward(self, obs, goal, action=None):
        return torch.full((self.members, goal.shape[0], 1), self.value)

    def min_value(self, obs, goal, action=None):
        return self(obs, goal, action).min(0).values


class ConstQ(nn.Module):
    """Stand-in for a DQN target network: fixed per-action values."""

    def __init__(self, values: torch.Tensor) -> None:
        super().__init__()
        self.values = values

    def forward(self, obs, goal):
        return self.values.expand(goal.shape[0], -1)


def small_mlp(seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Linear(5, 16), nn.ReLU(), nn.Linear(16, 16), nn.Tanh(), nn.Linear(16, 3)
    )


def mlp_loss(model: nn.Module, gen: torch.Generator) -> torch.Tensor:
    x = torch.randn(8, 5, generator=gen)
    y = torch.randn(8, 3, generator=gen)
    return F.mse_loss(model(x), y)


def assert_views(params, flat: torch.Tensor) -> None:
    """Every tensor in ``params`` is a view of consecutive slices of ``flat``."""
    offset = 0
    base = flat.untyped_storage().data_ptr()
    size = flat.element_size()
    for p in params:
        assert p.untyped_storage().data_ptr() == base
        assert p.data_ptr() == base + size * (flat.storage_offset() + offset)
        offset += p.numel()
    assert offset == flat.numel()


# --- 1. FlatAdam -------------------------------------------------------------------------
def test_flat_adam_matches_torch_adam():
    ref, flat_model = small_mlp(0), small_mlp(0)
    kwargs = {"lr": 1e-2, "betas": (0.8, 0.99), "eps": 1e-6}
    ref_opt = torch.optim.Adam(ref.parameters(), foreach=False, **kwargs)
    opt = FlatAdam(flat_model.parameters(), **kwargs)
    gen_a, gen_b = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    for _ in range(20):
        ref_opt.zero_grad()
        mlp_loss(ref, gen_a).backward()
        ref_opt.step()
        opt.zero_grad()
        mlp_loss(flat_model, gen_b).backward()
        assert opt.step() == 0.0  # no clipping: the norm is not computed
    assert opt.step_count == 20
    moved = 0.0
    for p, q, p0 in zip(
        ref.parameters(), flat_model.parameters(), small_mlp(0).parameters(), strict=True
    ):
        torch.testing.assert_close(q, p, rtol=0, atol=1e-6)
        moved = max(moved, float((p - p0).detach().abs().max()))
    assert moved > 0.05  # the comparison is not trivially between unchanged weights
    assert_views(flat_model.parameters(), opt.flat)
    assert_views([p.grad for p in flat_model.parameters()], opt.grad)


def test_flat_adam_sets_moments_to_zero_before_they_become_subnormal():
    from lcrl.nets import optim

    w = torch.nn.Parameter(torch.zeros(3))
    opt = FlatAdam([w], lr=1e-3)
    opt.grad.copy_(torch.tensor([1e-3, 1.0, 0.0]))
    opt.step()  # then the gradient of the first entry stays zero, as a unit ReLU keeps off
    opt.grad.copy_(torch.tensor([0.0, 1.0, 0.0]))
    tiny = torch.finfo(torch.float32).tiny  # the smallest normal float32
    m = []
    for _ in range(3 * optim.FLUSH_EVERY * 4):
        opt.step()
        m.append(float(opt.exp_avg[0]))
        assert not 0.0 < abs(m[-1]) < tiny  # never subnormal
    # 1e-4 * 0.9**k falls below the threshold after about 610 steps and is zero at the
    # next multiple of FLUSH_EVERY; without the flush it would still be about 1e-33 there
    i = m.index(0.0)
    assert (i + 2) % optim.FLUSH_EVERY == 0  # m[i] is that of step i + 2
    assert 0.0 < m[i - 1] < optim.FLUSH_BELOW <= m[i - 1 - optim.FLUSH_EVERY]
    assert m[i - 1] > 1e4 * tiny  # still far from subnormal when it was flushed
    assert float(opt.exp_avg[1]) == pytest.approx(1.0)  # a live moment is untouched
    assert float(opt.exp_avg_sq[0]) > 0.0  # the second moment decays far more slowly


def test_flat_adam_state_round_trip_keeps_views():
    model = small_mlp(0)
    opt = FlatAdam(model.parameters(), lr=1e-2)
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        opt.zero_grad()
        mlp_loss(model, gen).backward()
        opt.step()
    saved_model = copy.deepcopy(model.state_dict())
    saved_opt = copy.deepcopy(opt.state_dict())

    other = small_mlp(1)
    other_opt = FlatAdam(other.parameters(), lr=1e-2)
    other.load_state_dict(saved_model)
    other_opt.load_state_dict(saved_opt)
    assert_views(other.parameters(), other_opt.flat)
    assert_views([p.grad for p in other.parameters()], other_opt.grad)
    assert torch.equal(other_opt.flat, opt.flat)
    assert other_opt.step_count == 3
    # Loading into itself is harmless too.
    opt.load_state_dict(opt.state_dict())
    assert_views(model.parameters(), opt.flat)

    gen_a, gen_b = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    for _ in range(5):
        for m, o, g in ((model, opt, gen_a), (other, other_opt, gen_b)):
            o.zero_grad()
            mlp_loss(m, g).backward()
            o.step()
    for p, q in zip(model.parameters(), other.parameters(), strict=True):
        assert torch.equal(p, q)
    assert not torch.equal(opt.flat, torch.cat([v.reshape(-1) for v in saved_model.values()]))

    wrong = FlatAdam(nn.Linear(2, 2).parameters(), lr=1e-2)
    with pytest.raises(LcrlError, match="parameters"):
        wrong.load_state_dict(saved_opt)


def test_flat_adam_clips_gradient_norm():
    def one_step(max_norm):
        model = small_mlp(0)
        opt = FlatAdam(model.parameters(), lr=1e-2, eps=1e-3, max_grad_norm=max_norm)
        before = opt.flat.clone()
        loss = mlp_loss(model, torch.Generator().manual_seed(3)) * 100.0
        loss.backward()
        grad_norm = float(torch.linalg.vector_norm(opt.grad))
        returned = opt.step()
        return returned, grad_norm, float(torch.linalg.vector_norm(opt.flat - before)), opt

    returned, grad_norm, free_step, _ = one_step(None)
    assert returned == 0.0
    assert grad_norm > 1.0

    returned, grad_norm, clipped_step, opt = one_step(1e-3)
    assert returned == pytest.approx(grad_norm, rel=1e-6)  # the norm before clipping
    # The first moment holds (1 - beta1) times the clipped gradient, of norm max_grad_norm.
    assert float(torch.linalg.vector_norm(opt.exp_avg)) == pytest.approx(0.1 * 1e-3, rel=1e-4)
    assert float(opt.grad.norm()) == pytest.approx(1e-3, rel=1e-4)  # clipped in place
    assert clipped_step < 0.1 * free_step

    returned, grad_norm, loose_step, _ = one_step(1e9)  # above the norm: no clipping
    assert returned == pytest.approx(grad_norm, rel=1e-6)
    assert loose_step == free_step


# --- 2. determinism ----------------------------------------------------------------------
@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
def test_same_seed_is_bit_identical(algo):
    prob = problem(algo == "dqn")
    data = batches(prob, 4)
    act_obs = {"state": np.linspace(-1, 1, 6, dtype=np.float32).reshape(2, 3)}
    act_goal = np.array([[0.5, -0.5], [1.0, 0.0]], np.float32)
    runs = []
    for seed in (0, 0, 1):
        agent = make_agent(algo, seed, prob)
        agent.observe(data[0].obs, data[0].goal)
        metrics = [agent.update(b) for b in data]
        actions = agent.act(act_obs, act_goal)
        runs.append((snapshot(agent), metrics, actions))
    (snap_a, metrics_a, act_a), (snap_b, metrics_b, act_b), (snap_c, metrics_c, _) = runs
    assert_identical(snap_a, snap_b)
    assert metrics_a == metrics_b
    np.testing.assert_array_equal(act_a, act_b)
    differing = [k for k in snap_a if not torch.equal(snap_a[k], snap_c[k])]
    assert len(differing) > len(snap_a) // 2
    assert metrics_a != metrics_c


# --- 3. metrics and target networks ------------------------------------------------------
@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
def test_update_returns_finite_documented_metrics(algo):
    prob = problem(algo == "dqn")
    agent = make_agent(algo, 0, prob)
    before = snapshot(agent)
    for b in batches(prob, 3):
        metrics = agent.update(b)
        assert set(metrics) == KEYS[algo]
        for value in metrics.values():
            assert type(value) is float
            assert math.isfinite(value)
    assert agent.updates == 3
    after = snapshot(agent)
    online = "critic" if algo != "dqn" else "q"
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith(f"{online}."))


def test_sac_target_critic_moves_by_tau():
    tau = 0.3
    prob = problem(False)
    agent = make_agent("sac", 0, prob, SACConfig(tau=tau))
    assert torch.equal(agent._target_flat, agent.critic_opt.flat)  # starts as a copy
    data = batches(prob, 2)
    agent.update(data[0])  # make target and online differ
    old_target = agent._target_flat.clone()
    old_state = {k: v.clone() for k, v in agent.critic_target.state_dict().items()}
    agent.update(data[1])
    new_online = agent.critic_opt.flat
    assert not torch.equal(old_target, new_online)
    assert torch.equal(agent._target_flat, torch.lerp(old_target, new_online, tau))
    online_state = agent.critic.state_dict()
    for key, value in agent.critic_target.state_dict().items():
        expected = (1 - tau) * old_state[key] + tau * online_state[key]
        torch.testing.assert_close(value, expected, rtol=0, atol=1e-6)
        assert not value.requires_grad


def test_sac_temperature_step_is_adams_step_on_the_temperature_loss():
    """The temperature's gradient, written in closed form, is autograd's gradient of
    ``-(log_alpha * (log pi + target_entropy)).mean()``: one step equals Adam's step on
    that loss."""
    prob = problem(False)
    agent = make_agent("sac", 0, prob, SACConfig(alpha_lr=0.05))
    captured = {}
    policy = agent._policy

    def spy(obs, goal, with_mean=False):
        out = policy(obs, goal, with_mean)
        if with_mean:  # the actor step's log-probabilities
            captured["logp"] = out[1].detach().clone()
        return out

    agent._policy = spy
    start = agent.log_alpha.detach().clone()
    agent.update(batches(prob, 1)[0])
    log_alpha = start.clone().requires_grad_(True)
    opt = torch.optim.Adam([log_alpha], lr=0.05)
    (-(log_alpha * (captured["logp"] + agent.target_entropy)).mean()).backward()
    opt.step()
    torch.testing.assert_close(agent.log_alpha.detach(), log_alpha.detach())


def test_sac_acting_samples_what_the_policy_samples():
    """``act`` draws its action without the log-probability, but the same action as
    ``_policy`` from the same generator state."""
    prob = problem(False)
    agent = make_agent("sac", 0, prob)
    batch = batches(prob, 1)[0]
    state = agent.gen.get_state()
    acted = agent.act(batch.obs, batch.goal)
    agent.gen.set_state(state)
    with torch.no_grad():
        o, g = agent.obs_tensors(batch.obs), agent.goal_tensor(batch.goal)
        expected = agent._policy(o, g)[0].numpy()
    np.testing.assert_array_equal(acted, expected)


def test_batched_value_layer_matches_per_member_linear_layers():
    """The ensemble's one-output layer (a product and a sum, not bmm) gives each member's
    ``x @ W_k + b_k`` and the same gradients, for shared and per-member inputs."""
    from lcrl.nets.layers import BatchedLinear

    torch.manual_seed(0)
    layer = BatchedLinear(3, 5, 1)
    for x in (torch.randn(7, 5), torch.randn(3, 7, 5)):
        x = x.requires_grad_(True)
        out = layer(x)
        xs = x if x.dim() == 3 else x.expand(3, 7, 5)
        expected = torch.baddbmm(layer.bias, xs, layer.weight)
        torch.testing.assert_close(out, expected)
        w = torch.randn_like(out)
        grads = torch.autograd.grad((out * w).sum(), (x, layer.weight, layer.bias))
        ref = torch.autograd.grad((expected * w).sum(), (x, layer.weight, layer.bias))
        for g, r in zip(grads, ref, strict=True):
            torch.testing.assert_close(g, r)


def test_td3_targets_move_with_policy_delay():
    tau = 0.25
    prob = problem(False)
    agent = make_agent("td3", 0, prob, TD3Config(tau=tau, policy_delay=2))
    data = batches(prob, 3)
    initial_actor, initial_critic = (
        agent._actor_target_flat.clone(),
        agent._critic_target_flat.clone(),
    )
    agent.update(data[0])  # critic only: targets stay
    assert not torch.equal(agent.critic_opt.flat, initial_critic)
    assert torch.equal(agent._actor_target_flat, initial_actor)
    assert torch.equal(agent._critic_target_flat, initial_critic)
    old_actor, old_critic = agent._actor_target_flat.clone(), agent._critic_target_flat.clone()
    metrics = agent.update(data[1])  # second call: actor and targets
    assert metrics["actor_loss"] != 0.0
    assert torch.equal(agent._actor_target_flat, torch.lerp(old_actor, agent.actor_opt.flat, tau))
    assert torch.equal(
        agent._critic_target_flat, torch.lerp(old_critic, agent.critic_opt.flat, tau)
    )
    old_actor, old_critic = agent._actor_target_flat.clone(), agent._critic_target_flat.clone()
    actor = agent.actor_opt.flat.clone()
    third = agent.update(data[2])  # critic only again
    assert torch.equal(agent._actor_target_flat, old_actor)
    assert torch.equal(agent._critic_target_flat, old_critic)
    assert torch.equal(agent.actor_opt.flat, actor)
    assert third["actor_loss"] == metrics["actor_loss"]


def test_dqn_target_moves_by_tau():
    tau = 0.4
    prob = problem(True)
    agent = make_agent("dqn", 0, prob, DQNConfig(tau=tau))
    data = batches(prob, 2)
    agent.update(data[0])
    old = agent._target_flat.clone()
    agent.update(data[1])
    assert not torch.equal(old, agent.opt.flat)
    assert torch.equal(agent._target_flat, torch.lerp(old, agent.opt.flat, tau))
    for p, q in zip(agent.q_target.parameters(), agent.q.parameters(), strict=True):
        assert p.shape == q.shape


# --- 4. terminated vs truncated targets ----------------------------------------------------
@pytest.mark.parametrize("algo", ["sac", "td3"])
@pytest.mark.parametrize("terminated", [1.0, 0.0])
def test_actor_critic_td_target(algo, terminated):
    """With the target critics fixed at C, ``y = 1`` when terminated, ``1 + gamma C`` if not
    (a truncated transition is stored with ``terminated = 0``, so it bootstraps)."""
    gamma, value, size = 0.9, 10.0, 8
    prob = problem(False)
    if algo == "sac":
        # A negligible temperature makes SAC's entropy bonus vanish from the target.
        config = SACConfig(gamma=gamma, init_alpha=1e-30, autotune_alpha=False)
    else:
        config = TD3Config(gamma=gamma)
    agent = make_agent(algo, 0, prob, config)
    agent.critic_target = ConstCritics(value)
    batch = repeated(
        batches(prob, 1)[0],
        0,
        size,
        reward=np.ones(size, np.float32),
        terminated=np.full(size, terminated, np.float32),
    )
    obs, _, goal, act, _, _ = agent.batch_tensors(batch)
    with torch.no_grad():
        q = agent.critic(obs, goal, act).squeeze(-1)  # (2, size)
    y = 1.0 if terminated else 1.0 + gamma * value
    expected = 0.5 * float(((q - y) ** 2).mean(-1).sum())
    metrics = agent.update(batch)
    assert metrics["critic_loss"] == pytest.approx(expected, rel=1e-5)
    wrong_y = 1.0 + gamma * value if terminated else 1.0
    wrong = 0.5 * float(((q - wrong_y) ** 2).mean(-1).sum())
    assert abs(wrong - expected) > 10.0


@pytest.mark.parametrize("terminated", [1.0, 0.0])
def test_dqn_td_target(monkeypatch, terminated):
    """Double DQN: ``y = r + gamma (1 - terminated) Q_target(s', argmax_a Q(s', a))``."""
    gamma, size = 0.9, 8
    prob = problem(True)
    agent = make_agent("dqn", 0, prob, DQNConfig(gamma=gamma))
    target_values = torch.tensor([[3.0, 5.0, 7.0, 11.0]])
    agent.q_target = ConstQ(target_values)
    captured = {}

    def spy(q, y):
        captured["y"] = y.clone()
        return F.smooth_l1_loss(q, y)

    monkeypatch.setattr(algos.dqn, "F", SimpleNamespace(smooth_l1_loss=spy))
    batch = repeated(
        batches(prob, 1)[0],
        0,
        size,
        reward=np.ones(size, np.float32),
        terminated=np.full(size, terminated, np.float32),
    )
    _, nobs, goal, _, _, _ = agent.batch_tensors(batch)
    with torch.no_grad():
        best = int(agent.q(nobs, goal)[0].argmax())
    agent.update(batch)
    y = captured["y"]
    assert y.shape == (size,)
    if terminated:
        assert torch.equal(y, torch.ones(size))
    else:
        expected = 1.0 + gamma * float(target_values[0, best])
        torch.testing.assert_close(y, torch.full((size,), expected), rtol=0, atol=1e-6)


# --- 5. tiny learning checks ---------------------------------------------------------------
def test_dqn_learns_goal_conditioned_bandit():
    prob = Problem({"state": (2,)}, "vector", (4,), 4, discrete=True)
    agent = DQN(prob, options(0), vector_embed, DQNConfig(lr=3e-3))
    rng = np.random.default_rng(0)
    eye = np.eye(4, dtype=np.float32)
    size = 64
    for _ in range(300):
        idx = rng.integers(0, 4, size)
        action = rng.integers(0, 4, size)
        obs = {"state": rng.normal(size=(size, 2)).astype(np.float32)}
        batch = Batch(
            obs=obs,
            action=action,
            reward=(action == idx).astype(np.float32),
            next_obs=obs,
            terminated=np.ones(size, np.float32),
            goal=eye[idx],
            relabelled=np.zeros(size, bool),
            index=np.arange(size),
        )
        agent.update(batch)
    obs = {"state": np.zeros((4, 2), np.float32)}
    np.testing.assert_array_equal(agent.act(obs, eye, deterministic=True), np.arange(4))
    with torch.no_grad():
        q = agent.q(agent.obs_tensors(obs), agent.goal_tensor(eye))
    np.testing.assert_allclose(q.numpy(), np.eye(4), atol=0.2)


def test_sac_moves_mean_action_to_goal():
    prob = Problem({"state": (1,)}, "vector", (1,), 1)
    agent = SAC(prob, options(0), vector_embed, SACConfig(actor_lr=3e-3, critic_lr=3e-3))
    goals = np.array([[-0.6], [0.6]], np.float32)
    obs = {"state": np.zeros((2, 1), np.float32)}
    start = agent.act(obs, goals, deterministic=True)[:, 0]
    assert np.all(np.abs(start - goals[:, 0]) > 0.4)
    rng = np.random.default_rng(0)
    size = 64
    for _ in range(300):
        goal = goals[rng.integers(0, 2, size)]
        action = rng.uniform(-1, 1, (size, 1)).astype(np.float32)
        state = {"state": np.zeros((size, 1), np.float32)}
        batch = Batch(
            obs=state,
            action=action,
            reward=(np.abs(action - goal)[:, 0] < 0.3).astype(np.float32),
            next_obs=state,
            terminated=np.ones(size, np.float32),
            goal=goal,
            relabelled=np.zeros(size, bool),
            index=np.arange(size),
        )
        agent.update(batch)
    end = agent.act(obs, goals, deterministic=True)[:, 0]
    assert np.all(np.abs(end - goals[:, 0]) < 0.2), end


# --- 6. fusion and goal/observation encoders ---------------------------------------------
def test_fused_mlp_shapes_and_film_identity():
    torch.manual_seed(0)
    x, g, g2 = torch.randn(4, 5), torch.randn(4, 3), torch.randn(4, 3)
    concat = FusedMLP(5, 3, 2, (8, 8), "concat")
    film = FusedMLP(5, 3, 2, (8, 8), "film")
    assert concat(x, g).shape == (4, 2)
    assert film(x, g).shape == (4, 2)
    assert not torch.equal(concat(x, g), concat(x, g2))

    # FiLM starts as the identity modulation: the plain layer stack, whatever the goal.
    assert torch.count_nonzero(film.film(g)) == 0
    h = x
    for layer in film.layers:
        h = F.relu(layer(h))
    plain = film.out(h)
    assert torch.equal(film(x, g), plain)
    assert torch.equal(film(x, g2), plain)

    # Once the FiLM layer is non-zero, h = relu(W h) * (1 + gamma) + beta per hidden layer.
    with torch.no_grad():
        film.film.weight.normal_()
        film.film.bias.normal_()
    gamma1, beta1, gamma2, beta2 = film.film(g).split([8, 8, 8, 8], -1)
    h = F.relu(film.layers[0](x)) * (1 + gamma1) + beta1
    h = F.relu(film.layers[1](h)) * (1 + gamma2) + beta2
    torch.testing.assert_close(film(x, g), film.out(h))
    assert not torch.equal(film(x, g), plain)


@pytest.mark.parametrize("fusion", ["concat", "film"])
@pytest.mark.parametrize(
    "prob",
    [
        Problem({"state": (3,)}, "text", (16,), 2),
        Problem({"state": (3,)}, "onehot", (5,), 2),
        Problem({"state": (3,), "image": (16, 16, 3)}, "vector", (2,), 2),
        Problem({"state": (3,)}, "image", (16, 16, 3), 2),
    ],
    ids=["text", "onehot", "image-obs", "image-goal"],
)
def test_sac_end_to_end_inputs(prob, fusion):
    agent = SAC(
        prob,
        options(0, fusion=fusion, text_dim=8, cnn_channels=(8, 8), cnn_features=16),
        EMBEDS[prob.goal_kind],
        SACConfig(),
    )
    data = batches(prob, 2, size=8)
    agent.observe(data[0].obs, data[0].goal)
    before = snapshot(agent)
    for b in data:
        metrics = agent.update(b)
        assert set(metrics) == KEYS["sac"]
        assert all(math.isfinite(v) for v in metrics.values())
    after = snapshot(agent)
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    # The goal encoder of the critics and the actor learns (text/one-hot projection, CNN).
    if prob.goal_kind != "vector":
        assert any(k.startswith("critic.goal_encoders.") for k in changed)
        assert any(k.startswith("actor.") and ".goal_encoder." in k for k in changed)
    if "image" in prob.obs_shapes:
        assert any(".obs_encoder.encoders.image.convs." in k for k in changed)
    actions = agent.act(data[0].obs, data[0].goal)
    assert actions.shape == (8, 2)
    assert np.all(np.abs(actions) <= 1.0)


# --- 7. errors ------------------------------------------------------------------------------
def test_algorithm_action_space_mismatch():
    with pytest.raises(LcrlError, match="continuous"):
        SAC(problem(True), options(), vector_embed)
    with pytest.raises(LcrlError, match="continuous"):
        TD3(problem(True), options(), vector_embed)
    with pytest.raises(LcrlError, match="discrete"):
        DQN(problem(False), options(), vector_embed)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_cuda_unavailable(device):
    opts = AgentOptions(net=NetConfig(hidden=(32, 32)), device=device)
    with pytest.raises(LcrlError, match="CUDA is not available"):
        SAC(problem(False), opts, vector_embed)


def test_unknown_device_fusion_and_goal_kind():
    with pytest.raises(LcrlError, match="unknown device"):
        SAC(problem(False), AgentOptions(device="quantum"), vector_embed)
    with pytest.raises(LcrlError, match="unknown fusion"):
        SAC(problem(False), options(fusion="sum"), vector_embed)
    with pytest.raises(LcrlError, match="unknown fusion"):
        FusedMLP(3, 2, 1, (4,), "attention")
    with pytest.raises(LcrlError, match="hidden layer"):
        FusedMLP(3, 2, 1, (), "concat")
    with pytest.raises(LcrlError, match="unknown goal kind"):
        SAC(Problem({"state": (3,)}, "audio", (4,), 2), options(), vector_embed)
    with pytest.raises(LcrlError, match="expected"):
        SAC(Problem({"state": (3, 4)}, "vector", (2,), 2), options(), vector_embed)


# --- 8. RunningNorm ---------------------------------------------------------------------------
def test_running_norm_matches_numpy_and_round_trips():
    rng = np.random.default_rng(0)
    chunks = [
        (rng.normal(size=(n, 3)) * [1.0, 5.0, 0.1] + [3.0, -2.0, 0.5]).astype(np.float32)
        for n in (1, 7, 50, 0, 200, 13)
    ]
    norm = RunningNorm(3, clip=5.0, eps=1e-2)
    seen = []
    for chunk in chunks:
        norm.update(torch.as_tensor(chunk))
        seen.append(chunk)
        data = np.concatenate(seen).astype(np.float64)
        np.testing.assert_allclose(norm.mean.numpy(), data.mean(0), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(norm.var.numpy(), data.var(0), rtol=1e-5, atol=1e-5)
        assert float(norm.count) == len(data)

    x = torch.as_tensor(rng.normal(size=(20, 3)).astype(np.float32)) * 10
    std = norm.var.sqrt().clamp_min(1e-2)
    torch.testing.assert_close(norm(x), ((x - norm.mean) / std).clamp(-5.0, 5.0))
    assert float(norm(x).abs().max()) <= 5.0

    state = copy.deepcopy(norm.state_dict())
    assert set(state) == {"mean", "var", "count"}
    restored = RunningNorm(3)
    restored.load_state_dict(state)
    for key in ("mean", "var", "count"):
        assert torch.equal(getattr(restored, key), getattr(norm, key))
    assert torch.equal(restored(x), norm(x))
    extra = torch.as_tensor(chunks[2])
    norm.update(extra)
    restored.update(extra)
    assert torch.equal(restored.mean, norm.mean) and torch.equal(restored.var, norm.var)


def test_whitening_norm_equalises_directions_and_drops_unseen_ones():
    rng = np.random.default_rng(1)
    # 40 vectors in 6-D varying along 3 orthogonal directions with variances 1, 1e-2, 1e-4.
    basis, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    raw = rng.normal(size=(40, 3))
    q, _ = np.linalg.qr(raw - raw.mean(0))  # centred, uncorrelated columns
    coef = q * np.sqrt(40 * np.array([1.0, 1e-2, 1e-4]))
    centre = rng.normal(size=6)
    x = coef @ basis[:, :3].T + centre
    norm = WhiteningNorm(6, eps=1e-3, clip=100.0)
    norm.fit(torch.as_tensor(x, dtype=torch.float32))
    np.testing.assert_allclose(norm.mean.numpy(), x.mean(0), atol=1e-5)
    y = norm(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
    np.testing.assert_allclose(y.mean(0), 0.0, atol=1e-4)
    # Each direction's variance becomes var / (var + eps * total): close to 1 for the
    # first two, and the weakest direction goes from 1e-4 of the strongest to about 1/11.
    var = coef.var(0)
    total = var.sum()
    expected = var / (var + 1e-3 * total)
    got = (y @ basis[:, :3]).var(0)
    np.testing.assert_allclose(got, expected, rtol=1e-3)
    assert got[2] / got[0] > 0.05
    # A direction the fitted vectors never vary along is dropped.
    unseen = torch.as_tensor(centre + basis[:, 4], dtype=torch.float32)
    torch.testing.assert_close(norm(unseen[None]), torch.zeros(1, 6), atol=1e-4, rtol=0)
    # Statistics are buffers: a fresh module with the state dict gives the same outputs.
    restored = WhiteningNorm(6, eps=1e-3, clip=100.0)
    restored.load_state_dict(copy.deepcopy(norm.state_dict()))
    assert set(norm.state_dict()) == {"mean", "transform", "count"}
    assert torch.equal(restored(unseen[None]), norm(unseen[None]))
    # One vector has no spread: everything maps to zero; outputs are clipped.
    norm.fit(torch.as_tensor(x[:1], dtype=torch.float32))
    assert float(norm(torch.as_tensor(x, dtype=torch.float32)).abs().max()) < 1e-5
    clipped = WhiteningNorm(6, eps=1e-6, clip=2.0)
    clipped.fit(torch.as_tensor(x, dtype=torch.float32))
    assert float(clipped(torch.as_tensor(x * 50, dtype=torch.float32)).abs().max()) <= 2.0


def test_text_goal_norm_option():
    prob = problem(False)
    text = Problem(prob.obs_shapes, "text", (8,), prob.action_dim)
    for choice, cls in (("whiten", WhiteningNorm), ("standardize", RunningNorm)):
        opts = AgentOptions(text_goal_norm=choice)
        agent = SAC(text, opts, vector_embed, SACConfig())
        assert isinstance(agent.norms["goal"], cls)
    with pytest.raises(LcrlError, match="text_goal_norm"):
        SAC(text, AgentOptions(text_goal_norm="pca"), vector_embed, SACConfig())
    with pytest.raises(LcrlError, match="text_whiten_eps"):
        SAC(text, AgentOptions(text_whiten_eps=0.0), vector_embed, SACConfig())


def test_agent_observe_feeds_normalisers():
    prob = problem(False)
    agent = make_agent("sac", 0, prob)
    data = batches(prob, 1, size=32)[0]
    agent.observe(data.obs, data.goal)
    np.testing.assert_allclose(
        agent.norms["obs_state"].mean.numpy(), data.obs["state"].mean(0), atol=1e-6
    )
    np.testing.assert_allclose(agent.norms["goal"].var.numpy(), data.goal.var(0), rtol=1e-5)
    # Already-embedded goals skip the embedder but are still normalised.
    g = torch.as_tensor(data.goal)
    assert torch.equal(agent.goal_tensor(g, embedded=True), agent.goal_tensor(data.goal))


# --- 9. states round trip -----------------------------------------------------------------------
@pytest.mark.parametrize("done", [3, 4], ids=["odd", "even"])
@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
def test_restored_agent_continues_identically(algo, done):
    prob = problem(algo == "dqn")
    data = batches(prob, 8)
    act_obs, act_goal = data[0].obs, data[0].goal
    agent = make_agent(algo, 0, prob)
    agent.observe(data[0].obs, data[0].goal)
    for b in data[:done]:
        agent.update(b)
    agent.act(act_obs, act_goal)

    # What a checkpoint holds, copied (as writing it to disk would).
    weights = {name: copy.deepcopy(m.state_dict()) for name, m in agent.modules().items()}
    states = copy.deepcopy(agent.states())
    fresh = make_agent(algo, 7, prob)  # another seed: everything must come from the copy
    assert not torch.equal(
        next(iter(fresh.modules()["critic" if algo != "dqn" else "q"].parameters())),
        next(iter(agent.modules()["critic" if algo != "dqn" else "q"].parameters())),
    )
    for name, module in fresh.modules().items():
        module.load_state_dict(weights[name])
    fresh.load_states(states)
    assert_identical(snapshot(fresh), snapshot(agent))
    assert (fresh.updates, fresh.acts) == (agent.updates, agent.acts)

    for i, b in enumerate(data[done:]):
        expected, got = agent.update(b), fresh.update(b)
        assert got == expected, i
        np.testing.assert_array_equal(fresh.act(act_obs, act_goal), agent.act(act_obs, act_goal))
    assert_identical(snapshot(fresh), snapshot(agent))
    for a, f in zip(agent.modules().values(), fresh.modules().values(), strict=True):
        for p, q in zip(a.parameters(), f.parameters(), strict=True):
            assert torch.equal(p, q)
    assert fresh.updates == agent.updates == 8


def test_object_slot_attention_reads_slots_and_learns() -> None:
    from lcrl.nets import GoalConditionedNet, SlotAttention

    cfg = NetConfig(hidden=(32, 32), slots=(2, 4, 3), slot_dim=16, slot_heads=2, text_dim=8)
    shapes = {"observation": (14,), "initial": (14,)}
    net = GoalConditionedNet(shapes, "text", (16,), 3, cfg)
    assert isinstance(net.obs_encoder.slots, SlotAttention)
    assert net.obs_encoder.slot_keys == ["initial", "observation"]
    obs = {k: torch.randn(5, 14) for k in shapes}
    goal = torch.randn(5, 16)
    assert net(obs, goal).shape == (5, 3)
    # Permuting the slots' contents changes the output (the slot identity matters) ...
    swapped = {k: v.clone() for k, v in obs.items()}
    for v in swapped.values():
        first, second = v[:, 2:5].clone(), v[:, 5:8].clone()
        v[:, 2:5], v[:, 5:8] = second, first
    assert not torch.allclose(net(obs, goal), net(swapped, goal))
    # ... and the goal picks what is read.
    assert not torch.allclose(net(obs, goal), net(obs, torch.randn(5, 16)))
    with pytest.raises(LcrlError, match="slot layout"):
        GoalConditionedNet({"observation": (5,)}, "text", (16,), 3, cfg)

    # Twin critics with object attention train end to end in SAC.
    prob = Problem({"observation": (14,)}, "vector", (2,), 2)
    agent = SAC(prob, AgentOptions(net=cfg, seed=0), vector_embed)
    rng = np.random.default_rng(0)
    batch = Batch(
        obs={"observation": rng.normal(size=(16, 14)).astype(np.float32)},
        action=rng.uniform(-1, 1, (16, 2)).astype(np.float32),
        reward=rng.random(16).astype(np.float32),
        next_obs={"observation": rng.normal(size=(16, 14)).astype(np.float32)},
        terminated=np.zeros(16, np.float32),
        goal=rng.normal(size=(16, 2)).astype(np.float32),
        relabelled=np.zeros(16, bool),
        index=np.arange(16),
    )
    before = {k: v.clone() for k, v in agent.critic.state_dict().items()}
    metrics = agent.update(batch)
    assert all(np.isfinite(v) for v in metrics.values())
    changed = [k for k, v in agent.critic.state_dict().items() if not torch.equal(v, before[k])]
    assert any(".slots." in k for k in changed)


def test_slot_select_picks_slots_by_goal_and_learns_which() -> None:
    from lcrl.nets import GoalConditionedNet, SlotSelect

    cfg = NetConfig(hidden=(32, 32), slots=(2, 4, 3), slot_heads=1, slot_mode="select")
    shapes = {"observation": (14,), "initial": (14,)}
    net = GoalConditionedNet(shapes, "onehot", (4,), 1, cfg)
    sel = net.obs_encoder.slots
    assert isinstance(sel, SlotSelect)
    assert sel.out_dim == 2 * 3 + 2 * 14  # picked slot of each key, then both full vectors
    obs = {k: torch.randn(6, 14) for k in shapes}
    # Logits that put all weight on slot 2: the picked values are slot 2 of each key.
    with torch.no_grad():
        sel.logits.weight.zero_()
        sel.logits.bias.copy_(torch.tensor([0.0, 0.0, 50.0, 0.0]))
    out = sel([obs["initial"], obs["observation"]], torch.zeros(6, cfg.text_dim))
    torch.testing.assert_close(out[:, :3], obs["initial"][:, 8:11])
    torch.testing.assert_close(out[:, 3:6], obs["observation"][:, 8:11])
    torch.testing.assert_close(out[:, 6:20], obs["initial"])
    with pytest.raises(LcrlError, match="slot_mode"):
        GoalConditionedNet(shapes, "onehot", (4,), 1, NetConfig(slots=(2, 4, 3), slot_mode="x"))

    # Regression "the first value of the slot the goal names": learned to a small error.
    torch.manual_seed(0)
    net = GoalConditionedNet({"observation": (14,)}, "onehot", (4,), 1, cfg)
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    for _ in range(600):
        x = torch.randn(128, 14)
        k = torch.randint(0, 4, (128,))
        target = x[torch.arange(128), 2 + 3 * k]
        loss = F.mse_loss(net({"observation": x}, torch.eye(4)[k]).squeeze(-1), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.05


def test_slot_attributes_score_colours_and_shapes_and_compose() -> None:
    """A slot's logit is its colour's score plus its shape's; trained to pick the named
    kind on 6 of 8 colour x shape kinds, the attribute selector picks the 2 kinds never
    named, where position-wise selection cannot."""
    from lcrl.nets import GoalConditionedNet, SlotAttributes, SlotSelect, grounding_loss
    from train.configs.presets import SLOT_ATTRIBUTES

    cfg = NetConfig(hidden=(16,), slots=(2, 8, 3), slot_heads=1, slot_mode="attributes",
                    slot_attributes=SLOT_ATTRIBUTES, text_dim=8)  # fmt: skip
    net = GoalConditionedNet({"observation": (26,)}, "text", (6,), 1, cfg)
    sel = net.obs_encoder.slots
    assert isinstance(sel, SlotAttributes)
    g = torch.randn(5, 8)
    colour = sel.scores[0](g).view(5, 1, 4)
    shape = sel.scores[1](g).view(5, 1, 2)
    expected = torch.stack([colour[..., k // 2] + shape[..., k % 2] for k in range(8)], -1)
    torch.testing.assert_close(sel.selection_logits([], g), expected)
    for bad in ((), (0, 1, 2), (0,) * 7 + (-1,)):
        with pytest.raises(LcrlError, match="slot_attributes"):
            GoalConditionedNet({"observation": (26,)}, "text", (6,), 1,
                               NetConfig(slots=(2, 8, 3), slot_mode="attributes",
                                         slot_attributes=bad))  # fmt: skip

    # goals whose words add up: one-hot colour then one-hot shape; kinds 3 and 7 held out
    def goal(k):
        return torch.cat([F.one_hot(torch.tensor(k // 2), 4), F.one_hot(torch.tensor(k % 2), 2)])

    seen, held = [0, 1, 2, 4, 5, 6], [3, 7]
    picked = {}
    for mode in ("select", "attributes"):
        torch.manual_seed(0)
        net = GoalConditionedNet(
            {"observation": (26,)},
            "text",
            (6,),
            1,
            NetConfig(
                hidden=(16,),
                slots=(2, 8, 3),
                slot_heads=1,
                slot_mode=mode,
                slot_attributes=SLOT_ATTRIBUTES,
                text_dim=8,
            ),
        )
        assert isinstance(net.obs_encoder.slots, SlotSelect)
        opt = torch.optim.Adam(net.parameters(), 1e-2)
        obs = {"observation": torch.zeros(6, 26)}
        goals = torch.stack([goal(k) for k in seen]).float()
        targets = torch.tensor([[k, -1] for k in seen])
        for _ in range(300):
            loss = grounding_loss(net.selection_logits(obs, goals), targets)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            test = torch.stack([goal(k) for k in held]).float()
            logits = net.selection_logits({"observation": torch.zeros(2, 26)}, test)
            picked[mode] = logits[0, :, 0].argmax(-1).tolist()
        assert float(loss.detach()) < 0.05
    assert picked["attributes"] == held
    assert not set(picked["select"]) & set(held)  # never-named slots are never picked


def test_grounding_loss_ignores_rows_without_a_named_slot() -> None:
    from lcrl.nets import grounding_loss

    torch.manual_seed(0)
    logits = torch.randn(2, 5, 2, 4)  # 2 networks, 5 rows, 2 heads, 4 slots
    targets = torch.tensor([[0, -1], [3, 1], [-1, -1], [2, -1], [1, 0]])
    expected = 0.0
    for t in range(2):
        rows = targets[:, t] >= 0
        per_net = [F.cross_entropy(logits[i, rows, t], targets[rows, t]) for i in range(2)]
        expected += sum(per_net) / 2
    torch.testing.assert_close(grounding_loss(logits, targets), expected)
    assert float(grounding_loss(logits, torch.full((5, 2), -1))) == 0.0


def test_grounding_trains_every_network_to_pick_the_named_slot() -> None:
    """SAC with ``grounding``: the actor's and both critics' slot selection learn which
    slot each goal id names; without it nothing reports a grounding loss."""
    rng = np.random.default_rng(0)
    table = rng.normal(size=(6, 16)).astype(np.float32)

    def embed(ids, device):
        return torch.as_tensor(table[np.asarray(ids, np.int64)], device=device)

    named = np.array([[0, -1], [1, -1], [2, -1], [3, -1], [1, 3], [2, 0]])
    cfg = NetConfig(hidden=(32, 32), slots=(2, 4, 3), slot_heads=2, slot_mode="select")
    prob = Problem({"observation": (14,), "initial": (14,)}, "text", (16,), 2)
    agent = SAC(prob, AgentOptions(net=cfg, seed=0, grounding=1.0), embed)
    agent.observe({}, table)
    agent.set_grounding(named)

    def batch(size=64):
        obs = {k: rng.normal(size=(size, 14)).astype(np.float32) for k in prob.obs_shapes}
        return Batch(
            obs=obs,
            action=rng.uniform(-1, 1, (size, 2)).astype(np.float32),
            reward=rng.random(size).astype(np.float32),
            next_obs=obs,
            terminated=np.zeros(size, np.float32),
            goal=rng.integers(0, 6, size),
            relabelled=np.zeros(size, bool),
            index=np.arange(size),
        )

    first = agent.update(batch())
    assert first["grounding_actor"] > 1.0 and first["grounding_critic"] > 1.0  # ~ 2 log 4
    for _ in range(150):
        last = agent.update(batch())
    assert last["grounding_actor"] < 0.3 and last["grounding_critic"] < 0.3
    obs = agent.obs_tensors({k: np.zeros((6, 14), np.float32) for k in prob.obs_shapes})
    goal = agent.goal_tensor(np.arange(6))
    with torch.no_grad():
        for net in (agent.actor, agent.critic):
            picked = net.selection_logits(obs, goal).argmax(-1)  # (n, ids, heads)
            assert (picked[..., 0] == torch.as_tensor(named[:, 0])).all()
            assert (picked[:, 4:, 1] == torch.as_tensor(named[4:, 1])).all()

    plain = SAC(prob, AgentOptions(net=cfg, seed=0), embed)
    assert not any(k.startswith("grounding") for k in plain.update(batch()))
    with pytest.raises(LcrlError, match="grounding loss is off"):
        plain.set_grounding(named)
    with pytest.raises(LcrlError, match=r"\(ids, 2\) integer"):
        agent.set_grounding(named[:, :1])
    with pytest.raises(LcrlError, match="slot indices below 4"):
        agent.set_grounding(named + 4)
    with pytest.raises(LcrlError, match="not dqn"):
        DQN(Problem(prob.obs_shapes, "text", (16,), 4, discrete=True),
            AgentOptions(net=cfg, grounding=1.0), embed)  # fmt: skip
    # TD3 and BC train their networks' selection the same way
    from lcrl.bc import BC

    for other in (TD3(prob, AgentOptions(net=cfg, seed=0, grounding=1.0), embed),
                  BC(prob, AgentOptions(net=cfg, seed=0, grounding=1.0), embed)):  # fmt: skip
        other.observe({}, table)
        other.set_grounding(named)
        actor = [
            m["grounding_actor"]
            for m in (other.update(batch()) for _ in range(120))
            if "grounding_actor" in m
        ]  # fmt: skip  (TD3: on its delayed actor steps)
        assert actor[0] > 1.0 > 0.3 > actor[-1]
    with pytest.raises(LcrlError, match="read object slots"):
        SAC(prob, AgentOptions(grounding=1.0), embed)
    with pytest.raises(LcrlError, match="0 \\(off\\) or positive"):
        SAC(prob, AgentOptions(net=cfg, grounding=-1.0), embed)


@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
def test_multi_step_batches_bootstrap_with_their_discount(algo: str) -> None:
    """A row's ``discount`` replaces gamma in the bootstrap; a reward shift counts once per
    summed step (sum of gamma**j over the row's m steps)."""
    prob = problem(algo == "dqn")
    agent = make_agent(algo)
    gamma = agent.cfg.gamma
    base = make_batch(prob, np.random.default_rng(3), size=6)
    term = np.array([0, 0, 1, 0, 0, 1], np.float32)
    one = base._replace(terminated=term)
    _, _, _, _, rew1, boot1 = agent.batch_tensors(one)
    np.testing.assert_allclose(boot1.numpy(), (1 - term) * gamma, rtol=1e-6)
    disc = np.array([gamma, gamma**2, gamma**3, gamma**3, 1.0, gamma], np.float32)
    multi = one._replace(discount=disc)
    _, _, _, _, rew, boot = agent.batch_tensors(multi)
    np.testing.assert_allclose(boot.numpy(), (1 - term) * disc, rtol=1e-6)
    np.testing.assert_allclose(rew.numpy(), rew1.numpy())

    agent.options.reward_shift = -1.0
    _, _, _, _, shifted, _ = agent.batch_tensors(multi)
    steps = np.round(np.log(disc) / np.log(gamma)).astype(int)
    per_row = np.array([sum(gamma**j for j in range(m)) for m in steps])
    np.testing.assert_allclose(shifted.numpy(), base.reward - per_row, rtol=1e-5, atol=1e-6)
    metrics = agent.update(multi)
    assert all(np.isfinite(v) for v in metrics.values())


def test_random_shift_moves_images_by_at_most_pad_pixels() -> None:
    from lcrl.nets import random_shift

    gen = torch.Generator().manual_seed(0)
    img = torch.zeros(64, 12, 12, 3, dtype=torch.uint8)
    img[:, 5, 7, :] = 255  # one bright pixel
    out = random_shift(img, 2, gen)
    assert out.shape == (64, 12, 12, 3) and out.dtype == torch.float32
    pos = [divmod(int(o[..., 0].argmax()), 12) for o in out]
    dy = {r - 5 for r, _ in pos}
    dx = {c - 7 for _, c in pos}
    assert dy <= set(range(-2, 3)) and dx <= set(range(-2, 3))
    assert len(dy) > 1 and len(dx) > 1  # offsets vary across the batch
    assert all(float(o.max()) == 255.0 for o in out)  # a shift, not a blur
    # edge pixels replicate: a constant image stays constant
    const = torch.full((4, 6, 6, 3), 9, dtype=torch.uint8)
    assert torch.equal(random_shift(const, 3, gen), const.float())


def image_problem() -> Problem:
    return Problem({"image": (16, 16, 3), "state": (4,)}, "image", (16, 16, 3), 2, False)


def test_shared_cnn_reads_image_goals_once_per_network() -> None:
    prob = image_problem()
    cfg = dict(hidden=(32,), cnn_channels=(8, 8), cnn_features=16)
    separate = SAC(prob, options(**cfg), image_embed)
    shared = SAC(prob, options(share_cnn=True, **cfg), image_embed)

    def count(module: nn.Module) -> int:
        return sum(p.numel() for p in module.parameters())

    cnn = count(ConvEncoder((16, 16, 3), (8, 8), 16))
    assert count(separate.actor) - count(shared.actor) == cnn
    assert count(separate.critic) - count(shared.critic) == 2 * cnn
    # the goal goes through the observation's CNN: same weights, same features
    net = shared.actor
    img = torch.randint(0, 256, (3, 16, 16, 3), dtype=torch.uint8)
    assert torch.equal(net.goal_encoder(img), net.obs_encoder.encoders["image"](img))
    # a state dict holds each weight once (safetensors refuses shared storage)
    names = list(net.state_dict())
    assert not any(n.startswith("goal_encoder.") for n in names)
    with pytest.raises(LcrlError, match="share_cnn"):
        SAC(
            Problem({"state": (4,)}, "image", (16, 16, 3), 2, False),
            options(share_cnn=True, **cfg),
            image_embed,
        )


def test_image_goal_updates_with_augmentation_are_deterministic() -> None:
    prob = image_problem()

    def run() -> dict[str, torch.Tensor]:
        opts = options(share_cnn=True, hidden=(32,), cnn_channels=(8, 8), cnn_features=16)
        opts.augment_pad = 2
        agent = SAC(prob, opts, image_embed)
        for b in batches(prob, 3, seed=5, size=8):
            metrics = agent.update(b)
            assert all(np.isfinite(v) for v in metrics.values())
        return snapshot(agent)

    first, second = run(), run()
    assert_identical(first, second)


def test_hindsight_bc_pulls_the_mean_action_to_relabelled_actions() -> None:
    """With a large weight, the actor imitates relabelled rows' actions and ignores others."""
    prob = problem(False)
    base = make_batch(prob, np.random.default_rng(7), size=32)
    target = np.tile(np.array([[0.6, -0.4]], np.float32), (32, 1))
    rel = np.arange(32) < 16
    action = np.where(rel[:, None], target, -target)  # other rows point the other way
    batch = base._replace(action=action, relabelled=rel)

    def mean_action(agent) -> np.ndarray:
        with torch.no_grad():
            o = agent.obs_tensors(batch.obs)
            g = agent.goal_tensor(batch.goal)
            return torch.tanh(agent.actor(o, g).chunk(2, -1)[0]).numpy()

    agent = make_agent("sac", config=algos.SACConfig(hindsight_bc=50.0))
    for _ in range(150):
        metrics = agent.update(batch)
    assert "bc_loss" in metrics and metrics["bc_loss"] < 0.05
    np.testing.assert_allclose(mean_action(agent)[rel], target[rel], atol=0.15)

    plain = make_agent("sac")
    assert "bc_loss" not in plain.update(batch)
    no_rel = make_agent("sac", config=algos.SACConfig(hindsight_bc=50.0))
    assert "bc_loss" not in no_rel.update(batch._replace(relabelled=np.zeros(32, bool)))


def test_demo_bc_clones_demonstration_rows_alone() -> None:
    """With a large weight and no Q-filter, the actor imitates the demonstrator's actions
    on demonstration rows; rows the policy acted are left alone."""
    prob = problem(False)
    base = make_batch(prob, np.random.default_rng(7), size=32)
    target = np.tile(np.array([[0.6, -0.4]], np.float32), (32, 1))
    demo = np.arange(32) < 16
    batch = base._replace(action=np.where(demo[:, None], target, -target), demo=demo)
    agent = make_agent("sac", config=algos.SACConfig(demo_bc=50.0, q_filter=False))
    for _ in range(150):
        metrics = agent.update(batch)
    assert metrics["demo_rows"] == 0.5 and metrics["demo_cloned"] == 1.0
    with torch.no_grad():
        o, g = agent.obs_tensors(batch.obs), agent.goal_tensor(batch.goal)
        mean = torch.tanh(agent.actor(o, g).chunk(2, -1)[0]).numpy()
    np.testing.assert_allclose(mean[demo], target[demo], atol=0.15)
    # no demonstration rows, or no flags at all: no term
    for b in (batch._replace(demo=np.zeros(32, bool)), batch._replace(demo=None)):
        assert "demo_rows" not in make_agent("sac", config=algos.SACConfig(demo_bc=50.0)).update(b)


class ValuedAround(nn.Module):
    """A critic plus ``sign * 100 * |a - centre|^2``: with ``sign`` -1 the centre is the
    best action, with +1 the worst."""

    def __init__(self, critic: nn.Module, centre: torch.Tensor, sign: float) -> None:
        super().__init__()
        self.critic, self.centre, self.sign = critic, centre, sign

    def forward(self, obs, goal, action):
        bonus = self.sign * 100.0 * (action - self.centre).pow(2).sum(-1, keepdim=True)
        return self.critic(obs, goal, action) + bonus

    def min_value(self, obs, goal, action):
        return self(obs, goal, action).min(0).values


@pytest.mark.parametrize("sign", [-1.0, 1.0])
def test_the_q_filter_clones_only_where_the_demonstration_is_valued_higher(sign) -> None:
    """Demonstrations valued above the policy's actions are all cloned; valued below,
    none is, and the update is the one without the term, bit for bit."""
    prob = problem(False)
    base = make_batch(prob, np.random.default_rng(3), size=24)
    centre = np.array([0.5, 0.5], np.float32)
    batch = base._replace(action=np.tile(centre, (24, 1)), demo=np.ones(24, bool))
    agents = []
    for weight in (10.0, 0.0):
        agent = make_agent("sac", config=algos.SACConfig(demo_bc=weight))
        agent.critic = ValuedAround(agent.critic, torch.as_tensor(centre), sign)
        agents.append(agent)
    for _ in range(3):
        metrics, plain = agents[0].update(batch), agents[1].update(batch)
    assert metrics["demo_rows"] == 1.0 and "demo_rows" not in plain
    assert metrics["demo_cloned"] == (1.0 if sign < 0 else 0.0)
    if sign > 0:
        assert_identical(snapshot(agents[0]), snapshot(agents[1]))


# --- the SAC update over per-row weights ---------------------------------------------------
def tasks_problem() -> Problem:
    """Three-dimensional observations, one-hot ids of five tasks as goals."""
    return Problem({"state": (3,)}, "onehot", (5,), 2, num_tasks=5)


def multitask_sac(seed: int = 0, config: SACConfig | None = None, **multitask) -> SAC:
    from lcrl.multitask import MultiTaskOptions

    opts = AgentOptions(
        net=NetConfig(hidden=(32, 32)), seed=seed, multitask=MultiTaskOptions(**multitask)
    )
    return SAC(tasks_problem(), opts, onehot_embed, config)


def test_sac_multitask_update_without_weights_or_measurement_is_the_plain_update() -> None:
    """Equal task weights on updates that measure nothing: the plain update, bit for bit."""
    data = batches(tasks_problem(), 3, seed=4, size=20)
    plain = multitask_sac()
    quiet = multitask_sac(conflict_every=100, task_weights=(1.0,) * 5)
    assert plain.multitask is None and quiet.multitask is not None
    plain.updates = quiet.updates = 1  # update 0 would measure
    for b in data:
        assert plain.update(b) == quiet.update(b)
    assert_identical(snapshot(plain), snapshot(quiet))


@pytest.mark.parametrize("hindsight_bc", [0.0, 3.0])
def test_sac_task_weights_weigh_rows_alike_with_and_without_measurement(hindsight_bc) -> None:
    """``sum_i w_i L_i`` from per-row weights over the batch, and from per-task losses with
    coefficients ``n_i / n * w_i`` on measured updates: the same critic gradient, losses and
    behaviour-cloning loss (the actor's noise draws differ between the two)."""
    weights = (2.0, 1.0, 0.5, 1.0, 0.0)
    cfg = SACConfig(hindsight_bc=hindsight_bc)
    batch = batches(tasks_problem(), 1, seed=6, size=40)[0]
    batch = batch._replace(relabelled=np.arange(40) % 3 == 0)
    weighted = multitask_sac(config=cfg, task_weights=weights, conflict_every=2)
    measured = multitask_sac(config=cfg, task_weights=weights, conflict_every=1)
    weighted.updates = 1  # not measured
    a, b = weighted.update(batch), measured.update(batch)
    assert not any(k.startswith("grad/") for k in a)
    assert {"grad/critic_cos_mean", "grad/actor_conflict"} <= set(b)
    torch.testing.assert_close(weighted.critic_opt.grad, measured.critic_opt.grad)
    assert a["critic_loss"] == pytest.approx(b["critic_loss"], rel=1e-5)
    assert a["q"] == pytest.approx(b["q"], rel=1e-5)
    assert ("bc_loss" in a) == ("bc_loss" in b) == (hindsight_bc > 0)
    if hindsight_bc:  # the mean action is deterministic: the same in both
        assert a["bc_loss"] == pytest.approx(b["bc_loss"], rel=1e-5)
        # by hand: sum of w_i * squared error over relabelled rows / their count
        w = torch.tensor(weights) / torch.tensor(weights).mean()
        rel = torch.as_tensor(batch.relabelled)
        agent = multitask_sac(config=cfg, task_weights=weights, conflict_every=2)
        with torch.no_grad():
            o, g = agent.obs_tensors(batch.obs), agent.goal_tensor(batch.goal)
            mean = torch.tanh(agent.actor(o, g).chunk(2, -1)[0])
            err = (mean - torch.as_tensor(batch.action)).pow(2).sum(-1)
            rw = w[torch.as_tensor(batch.goal)]
            expected = float((err[rel] * rw[rel]).sum() / rel.sum())
        assert a["bc_loss"] == pytest.approx(expected, rel=1e-5)


def test_sac_target_temperature_and_polyak_steps_are_shared_by_both_updates() -> None:
    """A measured multi-task update moves the target critics by ``tau`` and tunes the
    temperature, as the plain update does."""
    batch = batches(tasks_problem(), 1, seed=2, size=24)[0]
    for agent in (multitask_sac(), multitask_sac(pcgrad=True)):
        target = agent._target_flat.clone()
        alpha = float(agent.log_alpha.detach())
        agent.update(batch)
        expected = target + agent.cfg.tau * (agent.critic_opt.flat - target)
        torch.testing.assert_close(agent._target_flat, expected)
        assert float(agent.log_alpha.detach()) != alpha


# --- asymmetric actor-critic ------------------------------------------------------------------
@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_the_privileged_critic_reads_state_the_actor_cannot(algo):
    """With ``Problem.privileged`` the critics read exactly those keys and the actor every
    other key: changing the privileged state moves the critics' values, never the actions;
    changing what the actor reads moves the actions, never the values."""
    prob = Problem(
        {"seen": (3,), "privileged": (5,)}, "vector", (2,), 2, privileged=("privileged",)
    )
    assert prob.actor_shapes == {"seen": (3,)} and prob.critic_shapes == {"privileged": (5,)}
    assert Problem.from_dict(prob.to_dict()) == prob  # recorded in checkpoints
    agent = make_agent(algo, 0, prob)
    for batch in batches(prob, 3):
        agent.update(batch)
    rng = np.random.default_rng(1)
    obs = {"seen": rng.normal(size=(4, 3)), "privileged": rng.normal(size=(4, 5))}
    goal = rng.normal(size=(4, 2)).astype(np.float32)
    action = torch.zeros(4, 2)

    def values(o):
        with torch.no_grad():
            return agent.critic(agent.obs_tensors(o), agent.goal_tensor(goal), action)

    other_state = {**obs, "privileged": rng.normal(size=(4, 5))}
    other_view = {**obs, "seen": rng.normal(size=(4, 3))}
    acted = agent.act(obs, goal, deterministic=True)
    np.testing.assert_array_equal(acted, agent.act(other_state, goal, deterministic=True))
    assert not np.allclose(acted, agent.act(other_view, goal, deterministic=True))
    assert not torch.allclose(values(obs), values(other_state))
    torch.testing.assert_close(values(obs), values(other_view), rtol=0, atol=0)
    # acting needs no privileged entry at all
    np.testing.assert_array_equal(acted, agent.act({"seen": obs["seen"]}, goal, deterministic=True))


def test_privileged_keys_are_checked_and_refused_without_a_critic():
    with pytest.raises(LcrlError, match="not among the observation keys"):
        Problem({"seen": (3,)}, "vector", (2,), 2, privileged=("state",))
    with pytest.raises(LcrlError, match="the actor would read nothing"):
        Problem({"state": (3,)}, "vector", (2,), 2, privileged=("state",))
    prob = Problem(
        {"seen": (3,), "privileged": (5,)}, "vector", (2,), 4, True, privileged=("privileged",)
    )
    with pytest.raises(LcrlError, match="asymmetric actor-critic needs one of"):
        make_agent("dqn", 0, prob)


@pytest.mark.parametrize("clip", [None, 1.0])
def test_sac_target_clip_bounds_the_td_targets(tmp_path, clip):
    """Success rewards of 0 or 1 that end the episode bound every value by 1: with
    ``sac.target_clip`` a target critic that overestimates cannot push targets past it."""
    import dataclasses

    from helpers import tiny

    from lcrl.buffer import batch_rows
    from train.training.loop import Trainer

    cfg = tiny("lang2d", tmp_path / "run", learning_starts=50)
    cfg.sac = dataclasses.replace(cfg.sac, target_clip=clip)
    # the return's bounds (agent.bound_targets, on in every preset) off: only target_clip
    cfg.agent = dataclasses.replace(cfg.agent, bound_targets=False)
    trainer = Trainer(cfg)
    try:
        while trainer.buffer.size < 60:
            trainer.collect_episode()
        agent = trainer.agent
        with torch.no_grad():
            for p in agent.critic_target.parameters():
                p.add_(1.0)  # every target value far above 1
        batch = batch_rows(trainer.buffer.sample(32), list(range(32)))
        _, nobs, goal, _, rew, boot = agent.batch_tensors(batch)
        y = agent.td_target(nobs, goal, rew, boot, agent.log_alpha.detach().exp())
        if clip is None:
            assert y.max() > 1.0
        else:
            assert y.max() <= 1.0 and y.min() >= -1.0
            assert torch.all(y[boot > 0] == 1.0)  # the overestimates are cut at the bound
    finally:
        trainer.close()


@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
def test_a_deep_copied_agent_learns_on_its_own(algo):
    """Parameters are views of flat buffers; a deep copy's optimiser and target steps move
    the copy's networks, and never the original's."""
    agent = make_agent(algo)
    rng = np.random.default_rng(0)
    agent.update(make_batch(agent.problem, rng))
    twin = copy.deepcopy(agent)

    def weights(a):
        return {k: [p.detach().clone() for p in m.parameters()] for k, m in a.modules().items()}

    original, before = weights(agent), weights(twin)
    for _ in range(2):
        twin.update(make_batch(twin.problem, rng))
    after = weights(twin)
    for name in before:
        if name == "norms":
            continue
        assert any(not torch.equal(x, y) for x, y in zip(before[name], after[name], strict=True)), (
            name
        )
    for name, values in weights(agent).items():
        assert all(torch.equal(x, y) for x, y in zip(original[name], values, strict=True)), name

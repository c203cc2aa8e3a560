"""Tests for lcrl.buffer (HindsightReplayBuffer) and the goal spaces of lcrl.goals.

Synthetic episodes encode ``(episode id, step index)`` into every observation, action and
achieved goal, so each test can tell exactly where a sampled field came from.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from lcrl.buffer import Batch, HindsightReplayBuffer
from lcrl.errors import LcrlError
from lcrl.goals import STRATEGIES as GOAL_STRATEGIES, LabelGoals, StateGoals

OBS_DIM = 3
ACT_DIM = 2
GOAL_DIM = 3
OBS_SPEC = {"state": ((OBS_DIM,), np.float32)}
STRATEGIES = ("future", "final", "episode")


# --- helpers -----------------------------------------------------------------------------
def dense_reward(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """A dense reward, so that any mix-up of achieved goals changes the value."""
    return -np.linalg.norm(achieved - desired, axis=-1).astype(np.float32)


def sparse_reward(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """0/1 success reward."""
    return (np.linalg.norm(achieved - desired, axis=-1) < 0.5).astype(np.float32)


def state_episode(
    ep: int,
    steps: int,
    rng: np.random.Generator,
    terminated: np.ndarray | None = None,
    achieved: np.ndarray | None = None,
    desired: np.ndarray | None = None,
) -> dict[str, Any]:
    """A StateGoals episode: obs ``[ep, j, noise]``, achieved goal ``[ep, j, 0.25 * ep]``."""
    j = np.arange(steps + 1)
    state = np.stack([np.full(steps + 1, ep), j, rng.normal(size=steps + 1)], 1)
    action = np.stack([np.full(steps, 1000 * ep) + np.arange(steps), rng.normal(size=steps)], 1)
    if achieved is None:
        achieved = np.stack([np.full(steps + 1, ep), j, np.full(steps + 1, 0.25 * ep)], 1)
    if desired is None:
        desired = np.array([ep, -1.0, 0.5], np.float32)
    if terminated is None:
        terminated = np.zeros(steps, bool)
    return {
        "obs": {"state": state.astype(np.float32)},
        "action": action.astype(np.float32),
        "reward": rng.normal(size=steps).astype(np.float32),
        "terminated": np.asarray(terminated, bool),
        "achieved_goal": np.asarray(achieved, np.float32),
        "desired_goal": np.asarray(desired, np.float32),
    }


def label_episode(
    ep: int,
    labels: list[list[int]],
    goal_id: int,
    rng: np.random.Generator,
    terminated: np.ndarray | None = None,
) -> dict[str, Any]:
    """A LabelGoals episode of ``len(labels) - 1`` steps, obs ``[ep, j, noise]``."""
    steps = len(labels) - 1
    out = state_episode(ep, steps, rng, terminated)
    del out["achieved_goal"], out["desired_goal"]
    out["goal_id"] = goal_id
    out["labels"] = labels
    return out


def state_buffer(
    capacity: int,
    strategy: str = "future",
    k: int = 4,
    seed: int = 0,
    reward_fn: Any = dense_reward,
    success_reward: float = 1.0,
    terminate_on_success: bool = False,
) -> HindsightReplayBuffer:
    gs = StateGoals(GOAL_DIM, reward_fn, success_reward, terminate_on_success)
    return HindsightReplayBuffer(capacity, OBS_SPEC, (ACT_DIM,), np.float32, gs, strategy, k, seed)


def label_buffer(
    capacity: int, goal_space: LabelGoals, strategy: str = "future", k: int = 4, seed: int = 0
) -> HindsightReplayBuffer:
    return HindsightReplayBuffer(
        capacity, OBS_SPEC, (ACT_DIM,), np.float32, goal_space, strategy, k, seed
    )


def decode(batch: Batch) -> tuple[np.ndarray, np.ndarray]:
    """(episode id, step index) of each sampled transition, checked against next_obs."""
    ep = batch.obs["state"][:, 0].astype(np.int64)
    t = batch.obs["state"][:, 1].astype(np.int64)
    np.testing.assert_array_equal(batch.next_obs["state"][:, 0].astype(np.int64), ep)
    np.testing.assert_array_equal(batch.next_obs["state"][:, 1].astype(np.int64), t + 1)
    return ep, t


def random_labels(
    steps: int, rng: np.random.Generator, num_goals: int, p_empty: float = 0.4
) -> list[list[int]]:
    labels: list[list[int]] = [[]]
    for _ in range(steps):
        if rng.random() < p_empty:
            labels.append([])
        else:
            size = int(rng.integers(1, 5))
            labels.append(sorted(int(x) for x in rng.choice(num_goals, size, replace=False)))
    return labels


# --- 1. where relabelled goals come from (StateGoals) -------------------------------------
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_state_relabelled_goals_come_from_the_same_episode(strategy: str) -> None:
    rng = np.random.default_rng(1)
    lengths = [1, 3, 5, 8, 13, 2, 7]
    episodes = [state_episode(e, t, rng) for e, t in enumerate(lengths)]
    buf = state_buffer(sum(t + 1 for t in lengths), strategy, k=4, seed=2)
    for episode in episodes:
        buf.add_episode(episode)
    assert buf.size == sum(lengths)

    batch = buf.sample(60_000)
    ep, t = decode(batch)
    steps = np.array(lengths)[ep]
    goal_ep = batch.goal[:, 0].astype(np.int64)
    goal_j = batch.goal[:, 1].astype(np.int64)
    rel = batch.relabelled

    # Original goals are the episode's desired goal.
    desired = np.stack([episodes[e]["desired_goal"] for e in ep[~rel]])
    np.testing.assert_array_equal(batch.goal[~rel], desired)
    # Relabelled goals are achieved goals of the same episode, whole vectors included.
    assert rel.any()
    np.testing.assert_array_equal(goal_ep[rel], ep[rel])
    achieved = [episodes[e]["achieved_goal"][j] for e, j in zip(ep[rel], goal_j[rel], strict=True)]
    np.testing.assert_array_equal(batch.goal[rel], np.stack(achieved))
    if strategy == "future":
        assert (goal_j[rel] >= t[rel] + 1).all()
        assert (goal_j[rel] <= steps[rel]).all()
        allowed = {
            (e, s, j) for e, n in enumerate(lengths) for s in range(n) for j in range(s + 1, n + 1)
        }
    elif strategy == "final":
        np.testing.assert_array_equal(goal_j[rel], steps[rel])
        allowed = {(e, s, n) for e, n in enumerate(lengths) for s in range(n)}
    else:
        assert (goal_j[rel] >= 1).all()
        assert (goal_j[rel] <= steps[rel]).all()
        allowed = {
            (e, s, j) for e, n in enumerate(lengths) for s in range(n) for j in range(1, n + 1)
        }
    # Every allowed (episode, step, goal index) combination is drawn; nothing else is.
    seen = set(zip(ep[rel].tolist(), t[rel].tolist(), goal_j[rel].tolist(), strict=True))
    assert seen == allowed


# --- 2. rewards, next observations, actions ----------------------------------------------
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_state_rewards_obs_and_actions_match_the_episode(strategy: str) -> None:
    rng = np.random.default_rng(3)
    lengths = [4, 9, 1, 6, 12]
    episodes = [state_episode(e, t, rng) for e, t in enumerate(lengths)]
    # One episode whose desired goal is one of its own achieved goals, so that some
    # original (non-relabelled) goals are reached too.
    episodes[1]["desired_goal"] = episodes[1]["achieved_goal"][5].copy()
    buf = state_buffer(64, strategy, k=4, seed=4)
    for episode in episodes:
        buf.add_episode(episode)

    batch = buf.sample(20_000)
    assert batch.reward.dtype == np.float32 and batch.reward.shape == (20_000,)
    assert batch.terminated.dtype == np.float32 and batch.relabelled.dtype == bool
    ep, t = decode(batch)
    obs = np.stack([episodes[e]["obs"]["state"][s] for e, s in zip(ep, t, strict=True)])
    nxt = np.stack([episodes[e]["obs"]["state"][s + 1] for e, s in zip(ep, t, strict=True)])
    act = np.stack([episodes[e]["action"][s] for e, s in zip(ep, t, strict=True)])
    ach = np.stack([episodes[e]["achieved_goal"][s + 1] for e, s in zip(ep, t, strict=True)])
    np.testing.assert_array_equal(batch.obs["state"], obs)
    np.testing.assert_array_equal(batch.next_obs["state"], nxt)
    np.testing.assert_array_equal(batch.action, act)
    np.testing.assert_array_equal(batch.reward, dense_reward(ach, batch.goal))
    # The slot of every transition holds its observation.
    np.testing.assert_array_equal(buf.obs["state"][batch.index], obs)
    # Both relabelled and original goals are present, and the original goal of episode 1
    # is reached at step 4 only (reward 0 = distance 0 under the dense reward).
    assert batch.relabelled.any() and (~batch.relabelled).any()
    hit = ~batch.relabelled & (batch.reward == 0.0)
    assert hit.any()
    assert set(zip(ep[hit].tolist(), t[hit].tolist(), strict=True)) == {(1, 4)}

    # relabel=False keeps every original goal, rewards still recomputed.
    plain = buf.sample(2_000, relabel=False)
    ep, t = decode(plain)
    assert not plain.relabelled.any()
    np.testing.assert_array_equal(plain.goal, np.stack([episodes[e]["desired_goal"] for e in ep]))
    ach = np.stack([episodes[e]["achieved_goal"][s + 1] for e, s in zip(ep, t, strict=True)])
    np.testing.assert_array_equal(plain.reward, dense_reward(ach, plain.goal))


# --- 3. relabelled fraction --------------------------------------------------------------
@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize(("k", "ratio"), [(4, 0.8), (1, 0.5), (0, 0.0)])
def test_relabelled_fraction_is_k_over_k_plus_1(strategy: str, k: int, ratio: float) -> None:
    rng = np.random.default_rng(5)
    buf = state_buffer(100, strategy, k=k, seed=6)
    for e, steps in enumerate([5, 20, 11, 30]):
        buf.add_episode(state_episode(e, steps, rng))
    assert buf.relabel_ratio == pytest.approx(ratio)
    batch = buf.sample(200_000)
    frac = batch.relabelled.mean()
    assert abs(frac - ratio) < 0.01, frac
    if k == 0:
        assert not batch.relabelled.any()


# --- 4. exact positive fractions ---------------------------------------------------------
def expected_positive_fraction(strategy: str, steps: int) -> float:
    """Exact fraction of relabelled transitions rewarded, all achieved goals distinct."""
    if strategy == "future":
        return sum(1.0 / i for i in range(1, steps + 1)) / steps  # H_T / T
    return 1.0 / steps


def test_expected_positive_fraction_figures() -> None:
    assert expected_positive_fraction("future", 50) == pytest.approx(0.0900, abs=5e-5)
    assert expected_positive_fraction("final", 50) == pytest.approx(0.02)
    assert expected_positive_fraction("episode", 50) == pytest.approx(0.02)


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("steps", [50, 10])
def test_positive_fraction_of_relabelled_transitions(strategy: str, steps: int) -> None:
    rng = np.random.default_rng(7)
    achieved = np.zeros((steps + 1, GOAL_DIM), np.float32)
    achieved[:, 0] = 10.0 * np.arange(steps + 1)  # all far apart
    episode = state_episode(
        0, steps, rng, achieved=achieved, desired=np.array([-1000.0, 0.0, 0.0], np.float32)
    )
    buf = state_buffer(steps + 1, strategy, k=4, seed=8, reward_fn=sparse_reward)
    buf.add_episode(episode)
    n = 400_000
    batch = buf.sample(n)
    rel = batch.relabelled
    assert not batch.reward[~rel].any()  # the desired goal is never reached
    p = expected_positive_fraction(strategy, steps)
    m = int(rel.sum())
    frac = batch.reward[rel].mean()
    # Binomial standard error over the m relabelled transitions; 5 sigma is deterministic
    # here (fixed seed) and would be a 6e-7 false-alarm rate with a fresh one.
    tol = 5.0 * math.sqrt(p * (1.0 - p) / m)
    assert abs(frac - p) < tol, (frac, p, tol)
    # Per step, the successes are exactly where the chosen goal is the next achieved goal.
    t = batch.obs["state"][:, 1].astype(np.int64)
    nxt_goal = achieved[t + 1]
    np.testing.assert_array_equal(
        batch.reward[rel] == 1.0, (batch.goal[rel] == nxt_goal[rel]).all(axis=1)
    )
    if strategy == "final":
        np.testing.assert_array_equal(batch.reward[rel] == 1.0, t[rel] == steps - 1)
    if strategy == "future":
        # uniform over steps t' >= t: success rate 1 / (T - t) at every step t
        for step in range(steps):
            hits = batch.reward[rel & (t == step)]
            q = 1.0 / (steps - step)
            assert abs(hits.mean() - q) <= 5.0 * math.sqrt(q * (1.0 - q) / hits.size), step


# --- 5. wrap-around ----------------------------------------------------------------------
LABEL_STRIDE = 32  # label id of observation j of episode e: (e % 100) * 32 + j


def wrap_episode(kind: str, ep: int, steps: int, rng: np.random.Generator) -> dict[str, Any]:
    if kind == "state":
        return state_episode(ep, steps, rng)
    labels: list[list[int]] = [[]]
    for j in range(1, steps + 1):
        labels.append([(ep % 100) * LABEL_STRIDE + j] if rng.random() < 0.5 else [])
    return label_episode(ep, labels, 3200 + ep % 100, rng)


@pytest.mark.parametrize("kind", ["state", "label"])
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_wrap_around_never_mixes_episodes(kind: str, strategy: str) -> None:
    capacity = 23
    rng = np.random.default_rng(9)
    if kind == "state":
        buf = state_buffer(capacity, strategy, k=4, seed=10)
    else:
        buf = label_buffer(capacity, LabelGoals(4096, terminate_on_success=False), strategy)
    lengths = [*rng.integers(1, capacity, 150).tolist(), capacity - 1, 1, capacity - 1]
    count = len(lengths)
    owner = np.full(capacity, -1)  # which episode last wrote each slot
    start_of = np.zeros(count, np.int64)
    steps_of = np.array(lengths)
    actions = np.zeros((count, capacity, ACT_DIM), np.float32)
    labelled = np.zeros((count, capacity + 1), bool)  # obs j of episode e carries a label
    episodes: dict[int, dict[str, Any]] = {}
    ptr = 0
    for ep, steps in enumerate(lengths):
        episode = wrap_episode(kind, ep, steps, rng)
        buf.add_episode(episode)
        # The documented placement: consecutive slots, restarting at 0 when it does not fit.
        start = ptr if ptr + steps + 1 <= capacity else 0
        owner[start : start + steps + 1] = ep
        start_of[ep] = start
        episodes[ep] = episode
        actions[ep, :steps] = episode["action"]
        if kind == "label":
            labelled[ep, : steps + 1] = [bool(x) for x in episode["labels"]]
        ptr = (start + steps + 1) % capacity
        # Live: episodes none of whose slots was written since.
        live = {
            e
            for e in range(ep + 1)
            if (owner[start_of[e] : start_of[e] + lengths[e] + 1] == e).all()
        }
        for e in live:
            s = start_of[e]
            np.testing.assert_array_equal(
                buf.obs["state"][s : s + lengths[e] + 1], episodes[e]["obs"]["state"]
            )
        assert buf.size == len(buf) == sum(lengths[e] for e in live)

        batch = buf.sample(1_000)
        b_ep, t = decode(batch)
        assert set(b_ep.tolist()) == live  # overwritten never appear; every live one does
        assert ep in live
        n = steps_of[b_ep]
        np.testing.assert_array_equal(batch.index, start_of[b_ep] + t)
        assert (t < n).all()  # never the final observation slot
        np.testing.assert_array_equal(batch.action, actions[b_ep, t])
        rel = batch.relabelled
        if kind == "state":
            np.testing.assert_array_equal(batch.goal[:, 0].astype(np.int64), b_ep)
            goal_j = batch.goal[:, 1].astype(np.int64)
            assert (goal_j[~rel] == -1).all()
            low = {"future": t + 1, "final": n, "episode": np.ones_like(t)}[strategy]
            assert ((goal_j[rel] >= low[rel]) & (goal_j[rel] <= n[rel])).all()
        else:
            np.testing.assert_array_equal(batch.goal[~rel], 3200 + b_ep[~rel] % 100)
            goal_ep, goal_j = np.divmod(batch.goal[rel], LABEL_STRIDE)
            np.testing.assert_array_equal(goal_ep, b_ep[rel] % 100)
            assert labelled[b_ep[rel], goal_j].all()
            if strategy != "episode":
                assert (goal_j >= t[rel] + 1).all()
            if strategy == "final":
                last = capacity - np.argmax(labelled[:, ::-1], axis=1)  # last labelled obs
                np.testing.assert_array_equal(goal_j, last[b_ep[rel]])
            # rewards: the goal's label is on the next observation
            nxt_label = np.where(labelled[b_ep, t + 1], (b_ep % 100) * LABEL_STRIDE + t + 1, -2)
            np.testing.assert_array_equal(
                batch.reward, (batch.goal == nxt_label).astype(np.float32)
            )


def test_episode_longer_than_capacity_is_rejected() -> None:
    rng = np.random.default_rng(11)
    buf = state_buffer(23)
    buf.add_episode(state_episode(0, 5, rng))
    with pytest.raises(LcrlError, match="does not fit in 23 slots"):
        buf.add_episode(state_episode(1, 23, rng))
    assert buf.size == 5  # nothing dropped by the rejected episode
    buf.add_episode(state_episode(2, 22, rng))  # exactly 23 slots fits
    assert buf.size == 22


def test_rejected_episode_leaves_no_sampleable_mix() -> None:
    """A goal-space error after old episodes were dropped must not leave them sampleable."""
    rng = np.random.default_rng(12)
    gs = LabelGoals(5, terminate_on_success=False)
    buf = label_buffer(20, gs)
    buf.add_episode(label_episode(0, [[]] * 10, 1, rng))  # slots 0..9
    buf.add_episode(label_episode(1, [[]] * 4, 1, rng))  # slots 10..13
    buf.sample(4)  # caches the valid slots
    bad = label_episode(2, [[]] * 9 + [[7]], 2, rng)  # wraps to slot 0: drops episode 0
    with pytest.raises(LcrlError, match="label ids"):
        buf.add_episode(bad)
    assert buf.size == 3
    ep, _ = decode(buf.sample(500))
    assert set(ep.tolist()) == {1}


# --- 6. termination ----------------------------------------------------------------------
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_terminated_flags_are_the_stored_ones(strategy: str) -> None:
    rng = np.random.default_rng(13)
    lengths = [6, 9, 4, 12]
    flags = [rng.random(n) < 0.3 for n in lengths]
    flags[0][:] = False  # a time-limit truncated episode
    flags[1][:] = False
    flags[1][-1] = True  # an episode that ended by termination
    episodes = [
        state_episode(e, n, rng, terminated=f)
        for e, (n, f) in enumerate(zip(lengths, flags, strict=True))
    ]
    buf = state_buffer(40, strategy, k=4, seed=14, terminate_on_success=False)
    for episode in episodes:
        buf.add_episode(episode)
    batch = buf.sample(20_000)
    ep, t = decode(batch)
    expected = np.array([flags[e][s] for e, s in zip(ep, t, strict=True)], np.float32)
    np.testing.assert_array_equal(batch.terminated, expected)
    assert (batch.terminated[ep == 0] == 0.0).all()  # truncation is not termination
    last1 = (ep == 1) & (t == lengths[1] - 1)
    assert last1.any() and (batch.terminated[last1] == 1.0).all()
    # The final observation slot of each episode is never a transition.
    starts = np.cumsum([0] + [n + 1 for n in lengths[:-1]])
    finals = {int(s + n) for s, n in zip(starts, lengths, strict=True)}
    assert not finals & set(batch.index.tolist())
    assert not buf.terminated[list(finals)].any()
    assert set(batch.index.tolist()) == {
        int(s + i) for s, n in zip(starts, lengths, strict=True) for i in range(n)
    }


def test_state_terminate_on_success_uses_relabelled_success() -> None:
    """gymnasium-robotics style -1/0 rewards with success_reward 0 and goal termination."""
    rng = np.random.default_rng(15)

    def minus_one_zero(a: np.ndarray, d: np.ndarray) -> np.ndarray:
        return sparse_reward(a, d) - 1.0

    buf = state_buffer(
        40, "future", 4, 16, minus_one_zero, success_reward=0.0, terminate_on_success=True
    )
    flags = []
    for e, n in enumerate([7, 10, 5]):
        f = rng.random(n) < 0.3
        flags.append(f)
        buf.add_episode(state_episode(e, n, rng, terminated=f))
    batch = buf.sample(20_000)
    ep, t = decode(batch)
    rel = batch.relabelled
    assert set(np.unique(batch.reward).tolist()) == {-1.0, 0.0}
    np.testing.assert_array_equal(
        batch.terminated[rel], (batch.reward[rel] == 0.0).astype(np.float32)
    )
    stored = np.array([flags[e][s] for e, s in zip(ep, t, strict=True)], np.float32)
    # an original goal ends where the episode ended, or at its own success
    expected = np.maximum(stored, (batch.reward == 0.0).astype(np.float32))
    np.testing.assert_array_equal(batch.terminated[~rel], expected[~rel])


# --- 7. LabelGoals -----------------------------------------------------------------------
def label_sources(labels: list[list[int]], t: int, strategy: str, num_relabel: int) -> set[int]:
    """Ids a transition at step t may be relabelled with."""
    usable = [{x for x in lab if x < num_relabel} for lab in labels]
    labelled = [j for j, u in enumerate(usable) if u]
    if strategy == "future":
        return set().union(*(usable[j] for j in labelled if j >= t + 1))
    if strategy == "final":
        return usable[labelled[-1]] if labelled and labelled[-1] >= t + 1 else set()
    return set().union(*(usable[j] for j in labelled))


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_label_relabelling_rewards_and_fallback(strategy: str) -> None:
    rng = np.random.default_rng(17)
    num_goals, num_relabel = 40, 30
    gs = LabelGoals(num_goals, num_relabel=num_relabel, terminate_on_success=False)
    buf = label_buffer(200, gs, strategy, k=4, seed=18)
    episodes = []
    for e in range(12):
        steps = int(rng.integers(2, 14))
        labels = random_labels(steps, rng, num_goals)
        if e == 0:
            labels = [[] for _ in range(steps + 1)]  # achieves nothing
        if e == 1:
            labels = [[]] + [[35, 31]] * steps  # only held-out ids
        episodes.append(label_episode(e, labels, int(rng.integers(0, num_goals)), rng))
        buf.add_episode(episodes[-1])

    # source[e, t, g]: g may relabel step t of episode e; carried[e, j, g]: g labels obs j
    max_t = max(len(x["labels"]) for x in episodes)
    source = np.zeros((len(episodes), max_t, num_goals), bool)
    carried = np.zeros((len(episodes), max_t, num_goals), bool)
    for e, x in enumerate(episodes):
        for j, lab in enumerate(x["labels"]):
            carried[e, j, lab] = True
            if j < len(x["labels"]) - 1:
                source[e, j, list(label_sources(x["labels"], j, strategy, num_relabel))] = True
    has_source = source.any(axis=2)
    desired = np.array([x["goal_id"] for x in episodes])

    batch = buf.sample(60_000)
    ep, t = decode(batch)
    rel = batch.relabelled
    # reward == 1 iff the goal is among the labels of the next observation (all ids)
    np.testing.assert_array_equal(batch.reward, carried[ep, t + 1, batch.goal].astype(np.float32))
    assert batch.reward.any() and not batch.reward.all()
    # relabelled goals come from the allowed observations, never held-out ids
    assert source[ep[rel], t[rel], batch.goal[rel]].all()
    assert (batch.goal[rel] < num_relabel).all()
    # Rows are relabelled with probability 0.8, always drawn among transitions with a
    # source; the other rows keep their original goal.
    src = has_source[ep, t]
    assert src[rel].all()
    assert abs(rel.mean() - 0.8) < 0.01
    np.testing.assert_array_equal(batch.goal[~rel], desired[ep[~rel]])
    assert (~src).any() and src.any()
    assert not rel[ep <= 1].any()

    # only_relabelable=False: rows are drawn uniformly; those without a source keep their
    # goal, those with one are relabelled 80 % of the time (standard error 0.002).
    buf.only_relabelable = False
    batch = buf.sample(60_000)
    ep, t = decode(batch)
    rel, src = batch.relabelled, has_source[ep, t]
    assert not rel[~src].any()
    assert abs(rel[src].mean() - 0.8) < 0.01
    np.testing.assert_array_equal(batch.goal[~rel], desired[ep[~rel]])

    # The goal space itself reports exactly which transitions have a source.
    idx = np.flatnonzero(buf.valid)
    goals, ok = gs.relabel(
        idx, buf.ep_start[idx], buf.ep_end[idx], strategy, np.random.default_rng(0)
    )
    slot_ep = buf.obs["state"][idx, 0].astype(np.int64)
    slot_t = buf.obs["state"][idx, 1].astype(np.int64)
    np.testing.assert_array_equal(ok, has_source[slot_ep, slot_t])
    assert source[slot_ep[ok], slot_t[ok], goals[ok]].all()
    np.testing.assert_array_equal(goals[~ok], desired[slot_ep[~ok]])


def test_label_heldout_ids_reward_but_never_relabel() -> None:
    rng = np.random.default_rng(19)
    gs = LabelGoals(10, num_relabel=6, terminate_on_success=False)
    buf = label_buffer(30, gs, "future", k=4, seed=20)
    # desired goal 8 is held out; it is achieved at observations 3 and 4 only
    labels = [[], [1], [9], [8, 2], [8], [], [7]]
    buf.add_episode(label_episode(0, labels, 8, rng))
    batch = buf.sample(20_000)
    _, t = decode(batch)
    rel = batch.relabelled
    assert set(batch.goal[rel].tolist()) == {1, 2}  # 7, 8, 9 never; 1 only from t = 0
    assert set(batch.goal[rel & (t >= 1)].tolist()) == {2}
    assert not rel[t >= 3].any()  # observations 4..6 carry only held-out ids
    orig = ~rel
    np.testing.assert_array_equal(batch.reward[orig], np.isin(t[orig], [2, 3]).astype(np.float32))
    assert batch.reward[orig & (t == 2)].size and (batch.reward[orig & (t == 2)] == 1).all()


def test_label_future_and_final_distributions() -> None:
    rng = np.random.default_rng(21)
    labels = [[], [1], [], [2, 3], [], [4], []]
    gs = LabelGoals(6, terminate_on_success=False)
    buf = label_buffer(7, gs)
    buf.add_episode(label_episode(0, labels, 0, rng))
    n = 60_000
    for t, strategy, probs in [
        # uniform over labelled observations at or after t + 1, then over their labels
        (0, "future", {1: 1 / 3, 2: 1 / 6, 3: 1 / 6, 4: 1 / 3}),
        (1, "future", {2: 1 / 4, 3: 1 / 4, 4: 1 / 2}),
        (4, "future", {4: 1.0}),
        (0, "final", {4: 1.0}),
        (4, "final", {4: 1.0}),
        (0, "episode", {1: 1 / 3, 2: 1 / 6, 3: 1 / 6, 4: 1 / 3}),
        (5, "episode", {1: 1 / 3, 2: 1 / 6, 3: 1 / 6, 4: 1 / 3}),
    ]:
        idx = np.full(n, t)
        goals, ok = gs.relabel(
            idx, buf.ep_start[idx], buf.ep_end[idx], strategy, np.random.default_rng(t)
        )
        assert ok.all()
        assert set(goals.tolist()) == set(probs)
        for g, p in probs.items():
            assert abs((goals == g).mean() - p) < 0.01, (t, strategy, g)
    for strategy in ("future", "final"):  # observation 6 carries nothing
        goals, ok = gs.relabel(np.array([5]), np.array([0]), np.array([6]), strategy, rng)
        assert not ok.any() and goals.tolist() == [0]


def test_label_final_picks_the_last_labelled_observation() -> None:
    rng = np.random.default_rng(22)
    labels = [[], [1], [], [2, 3], [], [], []]
    gs = LabelGoals(6, terminate_on_success=False)
    buf = label_buffer(7, gs, "final", k=4, seed=23)
    buf.add_episode(label_episode(0, labels, 5, rng))
    batch = buf.sample(20_000)
    _, t = decode(batch)
    rel = batch.relabelled
    assert set(batch.goal[rel].tolist()) == {2, 3}
    assert set(t[rel].tolist()) == {0, 1, 2}
    assert not rel[t >= 3].any()
    assert abs((batch.goal[rel] == 2).mean() - 0.5) < 0.02


def test_label_max_labels_subsamples_relabel_goals_but_not_rewards() -> None:
    rng = np.random.default_rng(24)
    gs = LabelGoals(20, max_labels=2, terminate_on_success=False, seed=3)
    buf = label_buffer(4, gs, "future")
    buf.add_episode(label_episode(0, [[], [0, 1, 2, 3, 4, 5, 6, 7, 8, 9], []], 15, rng))
    idx = np.zeros(5_000, np.int64)
    goals, ok = gs.relabel(idx, idx, idx + 2, "future", rng)
    assert ok.all()
    kept = set(goals.tolist())
    assert len(kept) == 2 and kept <= set(range(10))
    ids = np.arange(20)
    reward = gs.reward(np.zeros(20, np.int64), ids)
    np.testing.assert_array_equal(reward, (ids < 10).astype(np.float32))


def test_label_terminate_on_success() -> None:
    rng = np.random.default_rng(25)
    gs = LabelGoals(12, terminate_on_success=True)
    buf = label_buffer(80, gs, "future", k=4, seed=26)
    flags = []
    for e in range(6):
        steps = int(rng.integers(3, 12))
        f = rng.random(steps) < 0.3
        flags.append(f)
        buf.add_episode(
            label_episode(e, random_labels(steps, rng, 12), int(rng.integers(12)), rng, f)
        )
    batch = buf.sample(20_000)
    ep, t = decode(batch)
    rel = batch.relabelled
    assert rel.any() and batch.reward[rel].any() and not batch.reward[rel].all()
    np.testing.assert_array_equal(batch.terminated[rel], batch.reward[rel])
    stored = np.array([flags[e][s] for e, s in zip(ep, t, strict=True)], np.float32)
    # an original goal ends where the episode ended, or at its own success (episodes that
    # went on after succeeding)
    expected = np.maximum(stored, batch.reward)
    np.testing.assert_array_equal(batch.terminated[~rel], expected[~rel])
    assert ((batch.reward[~rel] > 0) & (stored[~rel] == 0)).any()


def test_label_embed() -> None:
    table = np.random.default_rng(27).normal(size=(7, 5)).astype(np.float32)
    ids = np.array([3, 0, 6, 3])
    gs = LabelGoals(7, embeddings=table)
    assert gs.embed_dim == 5
    out = gs.embed(ids, "cpu")
    assert out.dtype == torch.float32 and tuple(out.shape) == (4, 5)
    np.testing.assert_array_equal(out.numpy(), table[ids])
    onehot = LabelGoals(7)
    assert onehot.embed_dim == 7
    np.testing.assert_array_equal(
        onehot.embed(ids, "cpu").numpy(), np.eye(7, dtype=np.float32)[ids]
    )
    state = StateGoals(GOAL_DIM, dense_reward)
    assert state.embed_dim == GOAL_DIM
    goals = np.ones((2, GOAL_DIM), np.float64)
    emb = state.embed(goals, "cpu")
    assert emb.dtype == torch.float32
    np.testing.assert_array_equal(emb.numpy(), goals)


# --- 8. save/restore and bad input -------------------------------------------------------
def fill(buf: HindsightReplayBuffer, kind: str, rng: np.random.Generator, count: int) -> None:
    for e in range(count):
        steps = int(rng.integers(1, 12))
        if kind == "state":
            buf.add_episode(state_episode(e, steps, rng))
        else:
            buf.add_episode(
                label_episode(e, random_labels(steps, rng, 9), int(rng.integers(9)), rng)
            )


def make(kind: str, strategy: str) -> HindsightReplayBuffer:
    if kind == "state":
        return state_buffer(37, strategy, k=4, seed=28)
    return label_buffer(37, LabelGoals(9, num_relabel=7), strategy, k=4, seed=28)


def assert_same_batch(a: Batch, b: Batch) -> None:
    for field in Batch._fields:
        x, y = getattr(a, field), getattr(b, field)
        if isinstance(x, dict):
            assert x.keys() == y.keys()
            for key in x:
                np.testing.assert_array_equal(x[key], y[key])
        else:
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("kind", ["state", "label"])
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_arrays_round_trip(kind: str, strategy: str) -> None:
    rng = np.random.default_rng(29)
    buf = make(kind, strategy)
    fill(buf, kind, rng, 15)  # wraps around several times
    saved = {key: arr.copy() for key, arr in buf.arrays().items()}
    assert all(isinstance(v, np.ndarray) for v in saved.values())
    fresh = make(kind, strategy)
    fresh.load_arrays(saved)
    assert (fresh.size, fresh.ptr, fresh.episodes_added, fresh.steps_added) == (
        buf.size,
        buf.ptr,
        buf.episodes_added,
        buf.steps_added,
    )
    assert buf.size < buf.steps_added  # old episodes were overwritten
    # Same seed (28), and adding episodes draws nothing from the sampling generator, so
    # both buffers draw the same batches from here on.
    for _ in range(2):
        for _ in range(3):
            assert_same_batch(buf.sample(512), fresh.sample(512))
        # both keep going identically (restored write pointer and episode bounds)
        episode_rng = np.random.default_rng(31)
        extra = (
            state_episode(99, 9, episode_rng)
            if kind == "state"
            else label_episode(99, random_labels(9, episode_rng, 9), 2, episode_rng)
        )
        buf.add_episode(extra)
        fresh.add_episode(extra)
    # the loaded buffer does not share memory with what it was loaded from
    for arr in saved.values():
        arr[...] = 0
    assert_same_batch(buf.sample(256), fresh.sample(256))


def test_load_arrays_rejects_mismatched_storage() -> None:
    rng = np.random.default_rng(33)
    buf = state_buffer(37)
    fill(buf, "state", rng, 4)
    saved = buf.arrays()
    with pytest.raises(LcrlError, match="capacity 37; this buffer has 38"):
        state_buffer(38).load_arrays(saved)
    old_layout = {k: v for k, v in buf._full_arrays().items()}
    with pytest.raises(LcrlError, match="shape"):
        state_buffer(38).load_arrays(old_layout)
    with pytest.raises(LcrlError, match="lacks"):
        state_buffer(37).load_arrays({k: v for k, v in saved.items() if k != "valid"})
    label = label_buffer(37, LabelGoals(9))
    fill(label, "label", rng, 4)
    with pytest.raises(LcrlError, match="saved goal array"):
        label_buffer(37, LabelGoals(17)).load_arrays(label.arrays())


def test_bad_input_raises_lcrl_error() -> None:
    assert GOAL_STRATEGIES == STRATEGIES
    rng = np.random.default_rng(34)
    buf = state_buffer(30)
    with pytest.raises(LcrlError, match="empty"):
        buf.sample(4)

    episode = state_episode(0, 5, rng)
    with pytest.raises(LcrlError, match="keys"):
        buf.add_episode({**episode, "obs": {"pixels": episode["obs"]["state"]}})
    with pytest.raises(LcrlError, match="keys"):
        buf.add_episode({**episode, "obs": {**episode["obs"], "extra": episode["obs"]["state"]}})
    with pytest.raises(LcrlError, match="shape"):
        buf.add_episode({**episode, "obs": {"state": episode["obs"]["state"][:-1]}})
    with pytest.raises(LcrlError, match="shape"):
        buf.add_episode({**episode, "obs": {"state": episode["obs"]["state"][:, :2]}})
    with pytest.raises(LcrlError, match="actions have shape"):
        buf.add_episode({**episode, "action": episode["action"][:, :1]})
    with pytest.raises(LcrlError, match="at least one step"):
        buf.add_episode(state_episode(0, 0, rng))
    with pytest.raises(LcrlError, match="achieved_goal"):
        buf.add_episode({**episode, "achieved_goal": episode["achieved_goal"][:, :2]})
    with pytest.raises(LcrlError, match="achieved_goal"):  # T rows instead of T + 1
        buf.add_episode({**episode, "achieved_goal": episode["achieved_goal"][:-1]})
    with pytest.raises(LcrlError, match="desired_goal"):
        buf.add_episode({**episode, "desired_goal": np.zeros(GOAL_DIM + 1, np.float32)})
    buf.add_episode(episode)
    assert buf.size == 5

    gs = StateGoals(GOAL_DIM, dense_reward)
    for kwargs, match in [
        ({"capacity": 1}, "capacity"),
        ({"strategy": "past"}, "unknown relabelling strategy"),
        ({"k": -1}, "k must be"),
    ]:
        args = {"capacity": 10, "strategy": "future", "k": 4, **kwargs}
        with pytest.raises(LcrlError, match=match):
            HindsightReplayBuffer(
                args["capacity"], OBS_SPEC, (ACT_DIM,), np.float32, gs, args["strategy"], args["k"]
            )
    idx = np.array([0])
    with pytest.raises(LcrlError, match="unknown relabelling strategy"):
        buf.goal_space.relabel(idx, idx, idx + 5, "past", rng)

    lbuf = label_buffer(30, LabelGoals(5))
    with pytest.raises(LcrlError, match="goal id 5"):
        lbuf.add_episode(label_episode(0, [[], [1]], 5, rng))
    with pytest.raises(LcrlError, match="goal id -1"):
        lbuf.add_episode(label_episode(0, [[], [1]], -1, rng))
    with pytest.raises(LcrlError, match="label ids"):
        lbuf.add_episode(label_episode(0, [[], [5]], 1, rng))
    short = label_episode(0, [[], [1], [2]], 1, rng)
    with pytest.raises(LcrlError, match="labels has 2 entries"):
        lbuf.add_episode({**short, "labels": [[], [1]]})
    with pytest.raises(LcrlError, match="at least one goal"):
        LabelGoals(0)
    with pytest.raises(LcrlError, match="embeddings must have shape"):
        LabelGoals(5, embeddings=np.zeros((4, 3)))
    lbuf.add_episode(short)
    assert lbuf.size == 2


def test_oversized_goal_fields_do_not_corrupt_the_next_episode() -> None:
    rng = np.random.default_rng(35)
    buf = state_buffer(12, seed=36)
    for e in range(3):
        buf.add_episode(state_episode(e, 3, rng))  # slots 0..3, 4..7, 8..11
    long = state_episode(3, 3, rng)
    long["achieved_goal"] = np.zeros((7, GOAL_DIM), np.float32)  # would spill into 4..6
    with pytest.raises(LcrlError, match="achieved_goal"):
        buf.add_episode(long)
    ep, _ = decode(buf.sample(2_000, relabel=False))
    assert set(ep.tolist()) == {1, 2}
    np.testing.assert_array_equal(buf.goal_space.arrays()["achieved"][5:8, 1], [1.0, 2.0, 3.0])


# --- random goals (HER's "random" strategy) ----------------------------------------------
@pytest.mark.parametrize("kind", ["state", "label"])
def test_random_goals_fraction_and_rewards(kind: str) -> None:
    rng = np.random.default_rng(31)
    if kind == "state":
        buf = state_buffer(400, k=3, seed=32)
        episodes = [state_episode(e, int(rng.integers(3, 12)), rng) for e in range(10)]
    else:
        gs = LabelGoals(20, num_relabel=12, terminate_on_success=False)
        buf = label_buffer(400, gs, k=3, seed=32)
        episodes = [
            label_episode(e, random_labels(int(rng.integers(3, 12)), rng, 20), 15, rng)
            for e in range(10)
        ]
    for x in episodes:
        buf.add_episode(x)
    buf.random_fraction = 0.2
    batch = buf.sample(100_000)
    ep, _t = decode(batch)
    rel = batch.relabelled
    if kind == "state":
        desired = np.stack([x["desired_goal"] for x in episodes])[ep]
        changed = np.any(batch.goal != desired, axis=1)
        achieved_anywhere = {tuple(g) for x in episodes for g in x["achieved_goal"][1:]}
        assert all(tuple(g) in achieved_anywhere for g in batch.goal[changed & ~rel])
    else:
        changed = batch.goal != 15
        assert (batch.goal[changed & ~rel] < 12).all()  # random ids are relabelling ids
    # 0.75 hindsight, 0.2 random, 0.05 original (standard errors about 0.0015)
    assert abs(rel.mean() - 0.75) < 0.01
    assert abs((changed & ~rel).mean() - 0.2) < 0.01
    # rewards are recomputed for every goal
    np.testing.assert_array_equal(batch.reward, buf.goal_space.reward(batch.index, batch.goal))


def test_random_fraction_is_bounded() -> None:
    gs = LabelGoals(5)
    with pytest.raises(LcrlError, match="random_fraction"):
        HindsightReplayBuffer(10, OBS_SPEC, (ACT_DIM,), np.float32, gs, k=4, random_fraction=0.3)


# --- multi-step returns -------------------------------------------------------------------
def test_one_step_batches_carry_no_discount() -> None:
    rng = np.random.default_rng(40)
    buf = state_buffer(100)
    buf.add_episode(state_episode(0, 10, rng))
    assert buf.sample(8).discount is None


@pytest.mark.parametrize("n", [2, 3, 5])
def test_n_step_returns_match_a_per_row_reference(n: int) -> None:
    """Dense rewards, no termination: each row sums min(n, steps left) rewards of its goal."""
    rng = np.random.default_rng(41)
    gamma = 0.9
    gs = StateGoals(GOAL_DIM, dense_reward)
    buf = HindsightReplayBuffer(
        200, OBS_SPEC, (ACT_DIM,), np.float32, gs, "future", 4, 42, n_step=n, gamma=gamma
    )
    episodes = [state_episode(e, int(rng.integers(2, 9)), rng) for e in range(6)]
    for e in episodes:
        buf.add_episode(e)
    batch = buf.sample(3000)
    ep = batch.obs["state"][:, 0].astype(np.int64)
    t = batch.obs["state"][:, 1].astype(np.int64)
    for i in range(batch.reward.size):
        e = episodes[ep[i]]
        steps = e["action"].shape[0]
        m = min(n, steps - t[i])
        rewards = dense_reward(e["achieved_goal"][t[i] + 1 : t[i] + 1 + m], batch.goal[i])
        expected = sum(gamma**j * r for j, r in enumerate(rewards))
        assert batch.reward[i] == pytest.approx(expected, rel=1e-5, abs=1e-6)
        assert batch.discount[i] == pytest.approx(gamma**m, rel=1e-6)
        assert batch.next_obs["state"][i, 0] == ep[i]
        assert batch.next_obs["state"][i, 1] == t[i] + m
    assert not batch.terminated.any()
    assert {round(float(d), 6) for d in batch.discount} > {round(gamma**n, 6)}


def test_n_step_stops_at_the_first_success_of_the_rows_goal() -> None:
    """Label goals ending on success: a row's sum stops at the first step whose labels hold
    its goal (relabelled or original; the stored episodes never terminated)."""
    rng = np.random.default_rng(43)
    gamma = 0.5
    gs = LabelGoals(6, terminate_on_success=True)
    buf = HindsightReplayBuffer(
        300, OBS_SPEC, (ACT_DIM,), np.float32, gs, "future", 4, 44, n_step=4, gamma=gamma
    )
    episodes = []
    for e in range(8):
        steps = int(rng.integers(3, 10))
        labels = random_labels(steps, rng, 6, p_empty=0.6)
        episodes.append(labels)
        buf.add_episode(label_episode(e, labels, int(rng.integers(6)), rng))
    batch = buf.sample(4000)
    ep = batch.obs["state"][:, 0].astype(np.int64)
    t = batch.obs["state"][:, 1].astype(np.int64)
    for i in range(batch.reward.size):
        labels = episodes[ep[i]]
        steps = len(labels) - 1
        g = int(batch.goal[i])
        ret, m, done = 0.0, 0, False
        while m < 4 and t[i] + m < steps and not done:
            r = float(g in labels[t[i] + m + 1])
            ret += gamma**m * r
            done = r > 0
            m += 1
        assert batch.reward[i] == pytest.approx(ret)
        assert batch.terminated[i] == float(done)
        assert batch.discount[i] == pytest.approx(gamma**m)
        assert batch.next_obs["state"][i, 1] == t[i] + m
    assert batch.terminated.any() and not batch.terminated.all()
    assert (batch.reward[batch.terminated > 0] > 0).all()
    assert batch.terminated[~batch.relabelled].any()


def test_n_step_arguments_are_checked() -> None:
    gs = StateGoals(GOAL_DIM, dense_reward)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(LcrlError, match="n_step"):
            HindsightReplayBuffer(10, OBS_SPEC, (ACT_DIM,), np.float32, gs, n_step=bad)
    with pytest.raises(LcrlError, match="gamma"):
        HindsightReplayBuffer(10, OBS_SPEC, (ACT_DIM,), np.float32, gs, n_step=3, gamma=1.5)


# --- image goals ----------------------------------------------------------------------------
IMG = (4, 5, 3)


def image_episode(ep: int, steps: int, rng: np.random.Generator) -> dict[str, Any]:
    """Frames encode (episode, step) in their first two pixels; desired frame is 200 + ep."""
    out = state_episode(ep, steps, rng)
    frames = np.zeros((steps + 1, *IMG), np.uint8)
    frames[:, 0, 0, 0] = ep
    frames[:, 0, 1, 0] = np.arange(steps + 1)
    out["obs"]["image"] = frames
    out["desired_image"] = np.full(IMG, 200 + ep, np.uint8)
    return out


def image_buffer(capacity: int, min_episode_steps: int = 20, **kw: Any) -> HindsightReplayBuffer:
    from lcrl.goals import ImageGoals

    gs = ImageGoals(GOAL_DIM, dense_reward, IMG, min_episode_steps=min_episode_steps)
    spec = {**OBS_SPEC, "image": (IMG, np.uint8)}
    return HindsightReplayBuffer(capacity, spec, (ACT_DIM,), np.float32, gs, **kw)


def test_image_goals_are_later_frames_of_the_episode_and_rewards_use_their_states() -> None:
    rng = np.random.default_rng(50)
    buf = image_buffer(200, k=4, seed=51)
    episodes = [image_episode(e, int(rng.integers(3, 10)), rng) for e in range(8)]
    for e in episodes:
        buf.add_episode(e)
    batch = buf.sample(4000)
    ep, t = decode(batch)
    frames = buf.goal_space.frames(batch.goal)
    rel = batch.relabelled
    assert 0.75 < rel.mean() < 0.85
    # relabelled: a frame of the same episode at index >= t + 1, stored once in the buffer
    np.testing.assert_array_equal(frames[rel, 0, 0, 0], ep[rel])
    assert (frames[rel, 0, 1, 0] >= t[rel] + 1).all()
    # original goals: the episode's desired frame
    np.testing.assert_array_equal(
        frames[~rel], np.full(((~rel).sum(), *IMG), 0) + 200 + ep[~rel, None, None, None]
    )
    # rewards: the state reward of what the step achieved against the frame's state
    for i in np.flatnonzero(rel)[:200]:
        e = episodes[ep[i]]
        goal_state = e["achieved_goal"][frames[i, 0, 1, 0]]
        expected = dense_reward(e["achieved_goal"][t[i] + 1][None], goal_state[None])[0]
        assert batch.reward[i] == pytest.approx(expected)
    for i in np.flatnonzero(~rel)[:50]:
        e = episodes[ep[i]]
        expected = dense_reward(e["achieved_goal"][t[i] + 1][None], e["desired_goal"][None])[0]
        assert batch.reward[i] == pytest.approx(expected)
    # embed: codes become uint8 frames; frames pass through unchanged
    emb = buf.goal_space.embed(batch.goal[:7], "cpu")
    assert emb.dtype == torch.uint8 and tuple(emb.shape) == (7, *IMG)
    np.testing.assert_array_equal(emb.numpy(), frames[:7])
    assert torch.equal(buf.goal_space.embed(frames[:7], "cpu"), emb)


def test_image_goals_fall_back_to_the_final_frame_when_the_ring_wrapped() -> None:
    rng = np.random.default_rng(52)
    # ring of 200 // 21 + 1 = 10 desired frames; 2-step episodes (3 slots) fill it first
    buf = image_buffer(200, min_episode_steps=20, k=0, seed=53)
    for e in range(30):
        buf.add_episode(image_episode(e, 2, rng))
    batch = buf.sample(3000)
    ep, _ = decode(batch)
    frames = buf.goal_space.frames(batch.goal)
    recent = ep >= 20
    np.testing.assert_array_equal(frames[recent, 0, 0, 0], 200 + ep[recent])
    old = ~recent
    assert old.any()
    np.testing.assert_array_equal(frames[old, 0, 0, 0], ep[old])  # the episode's own frame
    np.testing.assert_array_equal(frames[old, 0, 1, 0], 2)  # ... its final one


def test_image_goals_round_trip_and_checks() -> None:
    from lcrl.goals import ImageGoals

    rng = np.random.default_rng(54)
    buf = image_buffer(120, seed=55)
    for e in range(6):
        buf.add_episode(image_episode(e, 5, rng))
    other = image_buffer(120, seed=55)
    other.load_arrays(buf.arrays())
    a, b = buf.sample(64), other.sample(64)
    assert_same_batch(a, b)
    np.testing.assert_array_equal(buf.goal_space.frames(a.goal), other.goal_space.frames(b.goal))
    with pytest.raises(LcrlError, match="desired_image"):
        bad = image_episode(9, 3, rng)
        bad["desired_image"] = np.zeros((2, 2, 3), np.uint8)
        buf.add_episode(bad)
    gs = ImageGoals(GOAL_DIM, dense_reward, IMG)
    with pytest.raises(LcrlError, match="does not store"):
        HindsightReplayBuffer(50, OBS_SPEC, (ACT_DIM,), np.float32, gs)
    with pytest.raises(LcrlError, match="uint8"):
        spec = {"image": ((4, 5, 3), np.float32)}
        HindsightReplayBuffer(50, spec, (ACT_DIM,), np.float32, ImageGoals(3, dense_reward, IMG))


@pytest.mark.parametrize("kind", ["state", "label"])
@pytest.mark.parametrize("episodes", [2, 12])  # before and after the first wrap-around
def test_saved_arrays_hold_the_written_slots_only(kind, episodes) -> None:
    """A buffer saves the slots written so far (``extent``); loaded into a fresh buffer,
    it samples exactly as the original, before and after wrap-around. The layout of
    earlier versions (every slot) loads the same."""
    rng = np.random.default_rng(41)

    def make():
        return state_buffer(60) if kind == "state" else label_buffer(60, LabelGoals(9))

    buf = make()
    fill(buf, kind, rng, episodes)
    saved = buf.arrays()
    high, capacity = saved["extent"]
    assert capacity == 60 and high == buf.high
    if episodes == 2:
        assert high < 60 and all(
            v.shape[0] == high for k, v in saved.items() if k.startswith(("obs.", "valid"))
        )
    else:
        assert high > 50  # wrapped: nearly everything is data
    for layout in (saved, buf._full_arrays()):
        fresh = make()
        fresh.load_arrays({k: np.array(v) for k, v in layout.items()})
        state = buf.rng.bit_generator.state
        fresh.rng.bit_generator.state = state
        assert_same_batch(buf.sample(128), fresh.sample(128))
        buf.rng.bit_generator.state = state
        for a, b in zip(buf._full_arrays().values(), fresh._full_arrays().values(), strict=True):
            np.testing.assert_array_equal(a, b)


def test_checkpoint_of_a_little_used_buffer_is_small(tmp_path) -> None:
    from lcrl.checkpoint import load_checkpoint, save_checkpoint

    rng = np.random.default_rng(42)
    buf = label_buffer(100_000, LabelGoals(9))
    fill(buf, "label", rng, 3)
    path = save_checkpoint(tmp_path / "c", modules={}, arrays=buf.arrays())
    size = (path / "arrays.npz").stat().st_size
    assert size < 0.01 * sum(a.nbytes for a in buf._full_arrays().values())
    fresh = label_buffer(100_000, LabelGoals(9))
    fresh.load_arrays(load_checkpoint(path).arrays())
    assert fresh.size == buf.size and fresh.high == buf.high


def test_demonstration_flags_are_sampled_with_their_rows_and_saved() -> None:
    """Even episodes are all demonstration, odd ones only their first two steps; a batch
    row carries its transition's flag, through a save and a load; a buffer saved before
    the flags existed loads with none."""
    rng = np.random.default_rng(5)
    buf = state_buffer(200, seed=3)
    for e in range(8):
        episode = state_episode(e, 9, rng)
        episode["demo"] = np.arange(9) < (9 if e % 2 == 0 else 2)
        buf.add_episode(episode)
    buf.add_episode(state_episode(8, 9, rng))  # no flags: the policy's
    batch = buf.sample(512)
    ep, j = batch.obs["state"][:, 0], batch.obs["state"][:, 1]
    expected = (ep < 8) & ((ep % 2 == 0) | (j < 2))
    np.testing.assert_array_equal(batch.demo, expected)
    assert 0 < batch.demo.mean() < 1
    saved = buf.arrays()
    fresh = state_buffer(200, seed=3)
    fresh.load_arrays(saved)
    np.testing.assert_array_equal(fresh.demo, buf.demo)
    older = state_buffer(200, seed=3)
    older.load_arrays({k: v for k, v in saved.items() if k != "demo"})
    assert not older.demo.any() and older.size == buf.size


# --- 10. storage on the learner's device ----------------------------------------------------
def frames_buffer(device: str | None, n_step: int = 1) -> HindsightReplayBuffer:
    """State goals over observations with a state and camera frames."""
    gs = StateGoals(GOAL_DIM, dense_reward)
    spec = {**OBS_SPEC, "image": (IMG, np.uint8)}
    return HindsightReplayBuffer(
        41, spec, (ACT_DIM,), np.float32, gs, k=4, seed=7, n_step=n_step, device=device
    )


def as_numpy(batch: Batch) -> Batch:
    def conv(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: conv(v) for k, v in x.items()}
        return x.cpu().numpy() if isinstance(x, torch.Tensor) else x

    return Batch(*(conv(x) for x in batch))


@pytest.mark.parametrize("n_step", [1, 3])
def test_device_storage_samples_what_host_storage_does(n_step: int) -> None:
    host, dev = frames_buffer(None, n_step), frames_buffer("cpu", n_step)
    assert dev.device_keys == ("state", "image") and host.device_keys == ()
    rng = np.random.default_rng(60)
    for e in range(12):  # wraps around
        ep = image_episode(e, int(rng.integers(2, 9)), rng)
        host.add_episode(ep)
        dev.add_episode(ep)
    for _ in range(3):
        a, b = host.sample(64), dev.sample(64)
        assert isinstance(b.obs["image"], torch.Tensor) and b.obs["image"].dtype == torch.uint8
        assert isinstance(b.next_obs["state"], torch.Tensor)
        assert isinstance(a.obs["image"], np.ndarray)
        assert_same_batch(a, as_numpy(b))
    np.testing.assert_array_equal(
        dev.host_obs("image", slice(0, dev.high)), host.obs["image"][: host.high]
    )


def test_device_storage_checkpoints_load_into_either_storage() -> None:
    rng = np.random.default_rng(61)
    dev = frames_buffer("cpu")
    for e in range(5):
        dev.add_episode(image_episode(e, int(rng.integers(2, 6)), rng))
    saved = dev.arrays()
    first = as_numpy(dev.sample(128))  # the first batch of a buffer seeded 7
    assert all(isinstance(v, np.ndarray) for v in saved.values())
    assert saved["obs.image"].shape[0] == dev.high < dev.capacity
    for target in (frames_buffer(None), frames_buffer("cpu")):
        target.load_arrays(saved)
        assert_same_batch(first, as_numpy(target.sample(128)))
        # the rows never written stay zero, the written ones are the saved ones
        np.testing.assert_array_equal(target.host_obs("image", slice(dev.high, None)), 0)
        np.testing.assert_array_equal(
            target.host_obs("image", slice(0, dev.high)), saved["obs.image"]
        )


def test_device_storage_keeps_the_frames_image_goals_read_on_the_host() -> None:
    buf = image_buffer(120, k=4, seed=3, device="cpu")
    assert buf.device_keys == ("state",)
    assert isinstance(buf.obs["image"], np.ndarray) and isinstance(buf.obs["state"], torch.Tensor)
    rng = np.random.default_rng(62)
    for e in range(4):
        buf.add_episode(image_episode(e, 25, rng))
    batch = buf.sample(32)
    assert isinstance(batch.obs["state"], torch.Tensor)
    # relabelled goals are frames of the row's episode, read from the host frames
    frames = buf.goal_space.frames(batch.goal)
    rel = batch.relabelled
    assert rel.any()
    np.testing.assert_array_equal(frames[rel, 0, 0, 0], batch.obs["image"][rel, 0, 0, 0])


def test_device_storage_errors_are_one_line() -> None:
    for device, words in (
        ("tpu7", "unknown replay storage device 'tpu7'"),
        ("meta", "not supported"),
    ):
        with pytest.raises(LcrlError, match=words):
            frames_buffer(device)
    if not torch.cuda.is_available():
        with pytest.raises(LcrlError, match="needs CUDA, which this machine does not have"):
            frames_buffer("cuda")

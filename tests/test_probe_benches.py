"""benchmarks.chain_probe, benchmarks.dagger_fit and benchmarks.update_floor: what they
count and compute."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
import torch

from benchmarks import chain_probe, dagger_fit, update_floor


class _Recorded:
    """What a :class:`chain_probe.Probe` holds after its episodes."""

    def __init__(self) -> None:
        self.errors = {
            ("fresh", 0, "reach"): [0.1, 0.3],
            ("fresh", 0, "push"): [0.5],
            ("after teacher", 1, "reach"): [1.0, 2.0],
        }
        self.success = {
            ("fresh", 0, "reach"): [True, True],
            ("fresh", 0, "push"): [False],
            ("after teacher", 1, "reach"): [False, True],
            ("teacher twice", 1, "reach"): [True, True],
        }


def test_the_chain_probe_pools_success_and_action_error_per_instruction_of_the_chain():
    rows = chain_probe.summary(_Recorded(), ["reach", "push"])
    fresh, second, teacher = rows["fresh 1"], rows["after teacher 2"], rows["teacher twice 2"]
    assert (fresh["success"], fresh["n"]) == (2 / 3, 3)
    assert math.isclose(fresh["action_error"], 0.3)  # the mean over every step of both
    assert fresh["families"]["reach"]["success"] == 1.0
    assert math.isclose(fresh["families"]["reach"]["action_error"], 0.2)
    assert (second["success"], second["action_error"]) == (0.5, 1.5)
    push = second["families"]["push"]
    assert push["n"] == 0 and push["action_error"] is None
    assert teacher["success"] == 1.0 and teacher["action_error"] is None  # the teacher acted
    low, high = fresh["ci"]
    assert 0.0 < low < 2 / 3 < high < 1.0
    assert math.isnan(chain_probe.rate([])["success"])


def test_the_chain_probe_reads_the_reset_as_initial_in_its_last_arm(monkeypatch):
    """``reset initial``: the same second instruction from the same scene, the policy
    reading the reset's observation as its ``initial`` one; ``after teacher`` reads the
    observation its instruction started from."""
    import types

    import train.environments.tasks as tasks

    read: list[tuple[str, str]] = []  # (what the observation is, what it reads as initial)

    class Env:
        def reset(self, seed):
            return {"at": "reset"}, {}

        def step(self, action):
            return {"at": "stepped"}, 0.0, True, False, {"is_success": True}

    class Task:
        def goal(self, obs, env):
            return 0

        def storage_obs(self, obs, first):
            read.append((obs["at"], first["at"]))
            return {"x": np.zeros(1, np.float32)}

        def scale_action(self, a):
            return a

    probe = object.__new__(chain_probe.Probe)
    probe.env, probe.task = Env(), Task()
    probe.lang = types.SimpleNamespace(meaning=types.SimpleNamespace(family="reach"))
    probe.scripted = types.SimpleNamespace(act=lambda env, rng: np.zeros(1), reset=lambda: None)
    agent = types.SimpleNamespace(act=lambda batch, goal, deterministic: np.zeros((1, 1)))
    probe.policy = types.SimpleNamespace(agent=agent)
    probe.rng = np.random.default_rng(0)
    probe.errors, probe.success = defaultdict(list), defaultdict(list)
    monkeypatch.setattr(tasks, "switch_in_place", lambda env, obs: {"at": "switched"})
    probe.episode(7)
    # fresh: the reset read as itself; after teacher: the switched scene as its own start;
    # reset initial: the switched scene, the reset read as initial
    assert read == [("reset", "reset"), ("switched", "switched"), ("switched", "reset")]
    assert probe.success[("reset initial", 1, "reach")] == [True]
    assert probe.success[("teacher twice", 1, "reach")] == [True]


def _episode(gripper_start: list[float], steps: int, switch_at: int = 0) -> tuple:
    """Rows of one DAgger episode (observation, first observation; gripper x, y, z first),
    the gripper moving 1 cm a step; at step ``switch_at`` (0: never) the next instruction
    of a chain starts where the gripper is."""
    obs, initial = [], []
    g = np.asarray(gripper_start, np.float32)
    first = np.r_[g, 0.0].astype(np.float32)
    for i in range(steps):
        row = np.r_[g, float(i)].astype(np.float32)
        if switch_at and i == switch_at:
            first = row.copy()
        obs.append(row)
        initial.append(first)
        g = g + 0.01
    return np.stack(obs), np.stack(initial)


def test_dagger_fit_tells_a_switch_in_place_from_a_reset_and_rows_from_their_round(tmp_path):
    # episode 1: a link of 3 steps, then one of 3 in place; episode 2: a reset far away
    o1, i1 = _episode([0.0, 0.0, 0.9], 6, switch_at=3)
    o2, i2 = _episode([0.3, 0.3, 1.0], 4)
    links = dagger_fit.chain_links(np.concatenate([i1, i2]), np.concatenate([o1, o2]))
    assert links.tolist() == [0, 0, 0, 1, 1, 1, 0, 0, 0, 0]
    (tmp_path / "progress.csv").write_text("step,rows\n1,6\n2,10\n")
    assert dagger_fit.row_rounds(tmp_path, 10).tolist() == [1] * 6 + [2] * 4
    with pytest.raises(SystemExit, match="ends at 10 rows"):
        dagger_fit.row_rounds(tmp_path, 12)


def test_the_eager_floor_is_a_sac_update_that_moves_actor_critics_targets_and_temperature():
    torch.set_num_threads(1)
    floor = update_floor.EagerFloor(seed=0)
    before = {
        "actor": [p.detach().clone() for p in floor.actor.parameters()],
        "critic": [p.detach().clone() for p in floor.q_params],
        "target": [p.detach().clone() for p in floor.t_params],
    }
    alpha = floor.log_alpha.item()
    floor.update()
    after = {
        "actor": list(floor.actor.parameters()),
        "critic": floor.q_params,
        "target": floor.t_params,
    }
    for name, old in before.items():
        assert any(not torch.equal(o, n) for o, n in zip(old, after[name], strict=True)), name
    assert floor.log_alpha.item() != alpha
    # the critics are trainable again after the actor's step, the targets never are
    assert all(p.requires_grad for p in floor.q_params)
    assert update_floor.ms_per_call(lambda: None, 3) >= 0.0

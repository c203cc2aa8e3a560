"""Every preset does what its help text says, and keeps its critic within the return's bound.

``lcrl train --help`` describes each preset in a sentence. Each phrase below is a claim a
help text can make, with the config fields that make it true; a help text that makes a
claim its config does not keep fails here, so the two cannot drift apart.
"""

from __future__ import annotations

import re
from collections.abc import Callable

import pytest

from lcrl.algos.base import value_bounds
from train.configs.config import TrainConfig
from train.configs.presets import PRESETS


def _goal_type(cfg: TrainConfig) -> str:
    if cfg.env.goal_type:
        return cfg.env.goal_type
    return "state" if cfg.env.kind == "gym" else "language"


def _camera(cfg: TrainConfig) -> bool:
    return bool(cfg.env.perception or cfg.env.image_obs)


#: (pattern, what it claims, the check). A pattern with a group passes the number it read.
CLAIMS: list[tuple[str, str, Callable[..., bool]]] = [
    (r"(\d+)k steps", "total_steps", lambda c, n: c.total_steps == int(n) * 1000),
    (r"(\d+)k updates", "total_steps", lambda c, n: c.total_steps == int(n) * 1000),
    (
        r"(\d+)% scripted",
        "scripted_fraction",
        lambda c, n: abs(c.scripted_fraction - int(n) / 100) < 1e-9,
    ),
    (r"without scripted episodes", "no scripted episodes", lambda c: c.scripted_fraction == 0),
    (
        r"colour and shape",
        "slots picked through their attributes",
        lambda c: c.agent.net.slot_mode == "attributes",
    ),
    (
        r"picked by position",
        "slots picked by position",
        lambda c: c.agent.net.slot_mode == "select",
    ),
    (r"grounding loss", "the grounding loss", lambda c: c.agent.grounding > 0),
    (
        r"clipped",
        "TD targets clipped",
        lambda c: c.agent.bound_targets or c.sac.target_clip is not None,
    ),
    (r"(\d+)-step returns", "n-step returns", lambda c, n: c.buffer.n_step == int(n)),
    (
        r"(\d+) training-only phrasings",
        "training phrasings",
        lambda c, n: c.env.phrasings == int(n),
    ),
    (r"(\d+) objects", "objects per scene", lambda c, n: c.env.max_objects == int(n)),
    (r"language goals", "language goals", lambda c: _goal_type(c) == "language"),
    (r"state goals", "state goals", lambda c: _goal_type(c) == "state"),
    (r"image goals", "image goals", lambda c: _goal_type(c) == "image"),
    (r"one-hot task ids", "task ids", lambda c: _goal_type(c) == "task"),
    (r"privileged state", "the policy reads the true state", lambda c: not _camera(c)),
    (r"camera", "the policy reads the camera", _camera),
    (r"critic reads the true state", "privileged critic", lambda c: c.agent.privileged_critic),
    (r"(\d+)x\1 camera", "image size", lambda c, n: c.env.image_size == int(n)),
    (r"\bTD3\b", "TD3", lambda c: c.algo == "td3"),
    (r"\bDQN\b", "DQN", lambda c: c.algo in ("dqn", "auto") and c.env.discrete),
    (r"\bSAC\b", "SAC", lambda c: c.algo in ("sac", "auto") and not c.env.discrete),
    (r"behavioural cloning", "behavioural cloning", lambda c: c.algo == "bc"),
    (r"without hindsight relabelling|no relabelling", "no relabelling", lambda c: c.buffer.k == 0),
    (r"\bHER\b|(?<!without )hindsight", "hindsight relabelling", lambda c: c.buffer.k > 0),
    (r"chains of instructions", "training chains", lambda c: c.explore.chain > 0),
    (r"curriculum", "a curriculum over families", lambda c: bool(c.explore.curriculum)),
    (r"starts along scripted", "hand-overs", lambda c: c.explore.handover > 0),
    (r"reach instructions", "reach only", lambda c: tuple(c.env.families) == ("reach",)),
    (r"\(reach, push\)", "reach and push", lambda c: tuple(c.env.families) == ("reach", "push")),
    (r"small networks", "small networks", lambda c: max(c.agent.net.hidden) < 256),
    (r"(\d+) environments at once", "vector environments", lambda c, n: c.collect.envs == int(n)),
    (r"batches of (\d+)", "batch size", lambda c, n: c.batch_size == int(n)),
]


def _claims(help_text: str) -> list[tuple[str, str, tuple[str, ...], Callable[..., bool]]]:
    found = []
    for pattern, what, check in CLAIMS:
        for match in re.finditer(pattern, help_text):
            found.append((match.group(0), what, match.groups()[:1], check))
    return found


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_claim_of_a_presets_help_text_holds_in_its_config(name: str) -> None:
    help_text, cfg = PRESETS[name]
    wrong = [
        f"{phrase!r} ({what})"
        for phrase, what, groups, check in _claims(help_text)
        if not check(cfg, *groups)
    ]
    assert not wrong, f"{name}: its help says {', '.join(wrong)}, its config does not"


def test_the_claims_table_catches_a_help_text_that_lies() -> None:
    """The check can fail: a help text claiming what the config does not keep."""
    help_text, cfg = PRESETS["lang2d"]
    lying = help_text + ", slots picked through their colour and shape, 3-step returns"
    failed = [what for _, what, groups, check in _claims(lying) if not check(cfg, *groups)]
    assert failed == ["slots picked through their attributes", "n-step returns"]


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_bounds_its_td_targets(name: str) -> None:
    """Every preset with a TD learner clips its targets to the return's bound."""
    _, cfg = PRESETS[name]
    cfg.validate(files=False)
    assert cfg.agent.bound_targets, f"{name} leaves TD targets unbounded"


@pytest.mark.parametrize(
    ("rewards", "gamma", "ends", "bounds"),
    [
        ((0.0, 1.0), 0.98, True, (0.0, 1.0)),  # sparse success that ends the episode
        ((-1.0, 0.0), 0.95, False, (-20.0, 0.0)),  # gymnasium-robotics
        ((0.0, 1.0), 0.98, False, (0.0, 50.0)),  # success that does not end it
        ((-1.0, 0.0), 0.9, True, (-10.0, 0.0)),  # shifted success rewards
    ],
)
def test_value_bounds(rewards, gamma, ends, bounds) -> None:
    assert value_bounds(rewards, gamma, ends) == pytest.approx(bounds)


def _q_rows(out) -> list[tuple[float, float]]:
    import csv

    with open(out / "progress.csv", newline="") as f:
        return [(float(r["q"]), float(r["q_max"])) for r in csv.DictReader(f) if r.get("q")]


def test_a_short_runs_critic_stays_within_the_return_bound(tmp_path, one_thread):
    """Success rewards that end the episode bound every return by 1. A large fixed
    entropy bonus (alpha 1) makes soft targets climb past it within a few hundred updates;
    with the bound (the default) the critic's mean Q stays at or below 1, without it the
    same run leaves the bound, so this check fails when the bound stops holding."""
    from helpers import TINY_CLI, cli

    args = ["train", "lang2d-quick", *TINY_CLI, "--total-steps", "600"]
    args += ["--learning-starts", "200", "--eval-episodes", "2", "--eval-every", "0"]
    args += ["--sac.init-alpha", "1.0", "--sac.no-autotune-alpha", "--torch-threads", "1"]
    assert cli(*args, "--out", str(tmp_path / "bounded")) == 0
    bounded = _q_rows(tmp_path / "bounded")
    assert len(bounded) >= 3
    assert all(q <= 1.0 + 0.02 and q_max <= 1.25 for q, q_max in bounded), bounded
    assert cli(*args, "--out", str(tmp_path / "free"), "--agent.no-bound-targets") == 0
    free = _q_rows(tmp_path / "free")
    assert free[-1][0] > 1.5, free  # the same run, unbounded, drifts past the bound

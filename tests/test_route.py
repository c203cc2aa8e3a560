"""Experts routed by instruction family (``lcrl route``), at a tiny size: each instruction
is acted by its family's expert, rows of one batch by their own experts, the routed folder
evaluates on chains like any checkpoint, and experts that cannot stand in for the base
are refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import cli, error_line, train_tiny

import lcrl


@pytest.fixture(scope="module", autouse=True)
def _single_thread(one_thread):
    """Every test of this module runs on one torch thread (``one_thread`` in conftest)."""


def _train(out: Path, preset: str = "lang2d", seed: int = 0, **env) -> Path:
    return train_tiny(out, preset, seed, **env)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A base over reach and push, and a push expert trained apart (another seed)."""
    root = tmp_path_factory.mktemp("route")
    return {
        "base": _train(root / "base"),
        "push": _train(root / "push", seed=1, families=("push",)),
        "root": root,
    }


@pytest.fixture(scope="module")
def routed(runs) -> Path:
    out = runs["root"] / "routed"
    expert = f"push={runs['push']}"
    assert cli("route", str(out), "--base", str(runs["base"]), "--expert", expert) == 0
    return out


def test_each_instruction_is_acted_by_its_familys_expert(runs, routed):
    policy = lcrl.load(routed)
    base, push = lcrl.load(runs["base"]), lcrl.load(runs["push"])
    agent = policy.agent
    # every training instruction of the base is routed by its own family
    texts = agent.texts
    assert set(agent.families) == {"reach", "push"}
    vectors = policy.embed(texts)
    assert agent.route(vectors) == agent.families
    env = policy.make_env()
    obs, _ = env.reset(seed=3)
    reach_text = texts[agent.families.index("reach")]
    push_text = texts[agent.families.index("push")]
    for text, owner in ((reach_text, base), (push_text, push)):
        for p in (policy, owner):
            p.reset()
        np.testing.assert_allclose(policy.act(obs, text), owner.act(obs, text), atol=1e-6)
    # the base and the expert disagree, so the comparison above tells them apart
    base.reset()
    push.reset()
    assert not np.allclose(base.act(obs, push_text), push.act(obs, push_text), atol=1e-4)
    # one batch, rows of both families: each row by its own expert
    batch = {k: np.stack([v, v]) for k, v in obs.items() if isinstance(v, np.ndarray)}
    for p in (policy, base, push):
        p.reset()
    both = policy.act(batch, [reach_text, push_text])
    np.testing.assert_allclose(both[0], base.act(obs, reach_text), atol=1e-6)
    np.testing.assert_allclose(both[1], push.act(obs, push_text), atol=1e-6)
    env.close()
    # narrowed to one family (lcrl eval --families push), it still routes among both
    narrowed = lcrl.load(routed, env_overrides={"families": ("push",)}).agent
    assert narrowed.texts == texts and narrowed.route(vectors) == agent.families


def test_act_names_the_expert_that_acts(routed, capsys):
    policy = lcrl.load(routed)
    agent = policy.agent
    for family, who in (("push", "the push expert"), ("reach", "the base policy")):
        text = agent.texts[agent.families.index(family)]
        assert cli("act", str(routed), "--instruction", text, "--episodes", "1") == 0
        assert f"routed as {family}: {who} acts" in capsys.readouterr().out


def test_routed_folder_evaluates_chains_like_a_checkpoint(routed, tmp_path):
    out = tmp_path / "chain.json"
    args = ["eval", str(routed), "--episodes", "3", "--chain", "2", "--sets", "train"]
    args += ["--num-envs", "1", "--vector", "sync", "--no-progress", "--json", str(out)]
    assert cli(*args) == 0
    doc = json.loads(out.read_text())
    train = doc["sets"]["train"]
    assert train["chain"]["chains"] == 3
    assert set(train["families"]) <= {"reach", "push"}


def test_bad_experts_get_one_line(runs, routed, tmp_path, capsys):
    base, push = str(runs["base"]), str(runs["push"])
    reach_only = _train(runs["root"] / "reach-only", "lang2d-quick")
    other_features = _train(runs["root"] / "no-disp", families=("push",), displacements=False)
    out = str(tmp_path / "r")
    cases = [
        (["--expert", "push"], "an expert is FAMILY=RUN"),
        (["--expert", f"push={push}", f"push={push}"], "two experts for the family 'push'"),
        (["--expert", f"lift={push}"], "follows the families reach, push, not lift"),
        (["--expert", f"push={reach_only}"], "trained on the families reach, not push"),
        (["--expert", f"push={other_features}"], "must read the same observation features"),
        (["--expert", f"push={routed}"], "is itself routed"),
        ([], "name at least one expert"),
    ]
    for extra, message in cases:
        assert cli("route", out, "--base", base, *extra) == 2, extra
        line = error_line(capsys.readouterr().err)
        assert line.startswith("lcrl: error:") and message in line, line
    assert cli("route", str(routed), "--base", base, "--expert", f"push={push}") == 2
    assert "already exists" in error_line(capsys.readouterr().err)
    args = ["--base", base, "--expert", f"push={push}", "--overwrite"]
    assert cli("route", push, *args) == 2  # would delete the expert it copies
    assert "which it is made from" in error_line(capsys.readouterr().err)
    assert (Path(push) / "latest.json").is_file()
    assert not Path(out).exists()

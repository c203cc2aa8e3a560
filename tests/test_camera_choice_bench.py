"""benchmarks.camera_choice: camera students chosen on a validation seed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks import camera_choice as cc


def _doc(seen: float, held: float, n: int = 100) -> dict:
    fams = {f: {"success": seen} for f in cc.FAMILIES}
    return {
        "sets": {
            "train": {"success": seen, "episodes": n, "families": fams},
            "heldout": {"success": held, "episodes": n, "families": {}},
        }
    }


def test_the_candidate_with_the_best_pooled_success_is_chosen(tmp_path, monkeypatch):
    docs = {"plain": _doc(0.5, 0.2), "colours": _doc(0.45, 0.4), "base": _doc(0.4, 0.3)}
    calls = []

    def run_jobs(jobs, parallel):
        assert parallel == 2
        for name, argv, _log in jobs:
            calls.append(argv)
            path = Path(argv[argv.index("--json") + 1])
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(docs[name.removeprefix("eval ")]))

    monkeypatch.setattr(cc, "run_jobs", run_jobs)
    import benchmarks.common as common

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    args = [f"{n}=runs/{n}" for n in docs] + ["--work", str(tmp_path / "work")]
    assert cc.main(args) == 0
    doc = json.loads((tmp_path / "results" / "robosuite-camera-choice.json").read_text())
    assert doc["headline"]["chosen"] == "colours"  # 0.425 pooled against 0.35 and 0.35
    assert doc["headline"]["plain_pooled"] == pytest.approx(0.35)
    for argv in calls:  # the validation seed, both sets, free text through the reader
        assert argv[argv.index("--seed") + 1] == "1"
        assert argv[argv.index("--sets") + 1 : argv.index("--sets") + 3] == ["train", "heldout"]
        assert "--canonical-reader" in argv
    calls.clear()
    assert cc.main(args) == 0  # evaluations already written are read
    assert calls == []


def test_bad_candidates_and_test_seeds_are_refused():
    with pytest.raises(SystemExit, match="give NAME=RUN"):
        cc.candidates(["a=runs/a", "runs/b"])
    with pytest.raises(SystemExit, match="two candidates or more"):
        cc.candidates(["a=runs/a"])
    with pytest.raises(SystemExit, match="named twice"):
        cc.candidates(["a=runs/a", "a=runs/b"])
    with pytest.raises(SystemExit, match="validation seeds"):
        cc.main(["a=runs/a", "b=runs/b", "--seed", "7"])


def test_the_pooled_interval_covers_the_pooled_rate():
    s = cc.summary(_doc(0.6, 0.2, n=50))
    assert s["pooled"] == pytest.approx(0.4) and s["episodes"] == 100
    lo, hi = s["pooled_ci"]
    assert lo < 0.4 < hi and hi - lo < 0.25


def _chains(whole: float, n: int = 100) -> dict:
    return {
        "sets": {
            "train": {
                "chain": {
                    "length": 2,
                    "chains": n,
                    "success": [
                        {"length": 1, "success": 0.7},
                        {"length": 2, "success": whole},
                    ],
                }
            }
        }
    }


def test_chains_run_per_candidate_and_count_in_the_pooled_choice(tmp_path, monkeypatch):
    """``--chain 2``: one more evaluation per candidate, of chains of seen instructions; a
    chain achieved whole is one more success in the pooled rate that chooses."""
    docs = {"first": _doc(0.6, 0.5), "current": _doc(0.55, 0.5)}
    chains = {"first": _chains(0.1), "current": _chains(0.4)}
    calls = []

    def run_jobs(jobs, parallel):
        for name, argv, _log in jobs:
            calls.append(argv)
            path = Path(argv[argv.index("--json") + 1])
            path.parent.mkdir(parents=True, exist_ok=True)
            kind, cand = name.split(" ")
            path.write_text(json.dumps((chains if kind == "chains" else docs)[cand]))

    monkeypatch.setattr(cc, "run_jobs", run_jobs)
    import benchmarks.common as common

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    args = [f"{n}=runs/{n}" for n in docs] + ["--work", str(tmp_path / "work")]
    assert cc.main([*args, "--chain", "2", "--name", "choice"]) == 0
    chained = [a for a in calls if "--chain" in a]
    assert len(chained) == 2 and all(a[a.index("--chain") + 1] == "2" for a in chained)
    assert all(a[a.index("--sets") + 1 :][:2] == ["train", "--chain"] for a in chained)
    head = json.loads((tmp_path / "results" / "choice.json").read_text())["headline"]
    # without chains "first" pools 0.55 against 0.525; with them 0.4 against 0.483
    assert head["chosen"] == "current"
    assert head["current_chain2"] == pytest.approx(0.4)
    assert head["first_pooled"] == pytest.approx((60 + 50 + 10) / 300, abs=1e-3)


def test_chain_links_count_each_familys_first_and_later_instructions():
    """Each attempt of a chain counts for its family, as the chain's first instruction or
    as a later one; an attempt that could not be checked counts for neither."""

    def attempt(family: str, success: bool, checked: bool = True) -> dict:
        return {"slots": {"family": family}, "success": success, "checked": checked}

    doc = _chains(0.5)
    doc["sets"]["train"]["episode_results"] = [
        {"attempts": [attempt("lift", True), attempt("put", False)]},
        {"attempts": [attempt("put", True), attempt("stack", True), attempt("put", True)]},
        {"attempts": [attempt("stack", False)]},
        {"attempts": [attempt("reach", True), attempt("push", True, checked=False)]},
    ]
    links = cc.chain_links(doc)
    assert links["first"] == {"lift": [1, 1], "put": [1, 1], "stack": [0, 1], "reach": [1, 1]}
    assert links["later"] == {"put": [1, 2], "stack": [1, 1]}
    assert cc.summary(_doc(0.5, 0.5), doc)["chain_links"] == links

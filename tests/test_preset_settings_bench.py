"""benchmarks.preset_settings: how a preset's settings are chosen from time to success."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks import preset_settings as ps


def _curve(out, rows):
    out.mkdir(parents=True, exist_ok=True)
    lines = ["step,train/success,train_s"] + [f"{s},{v},{t}" for s, v, t in rows]
    (out / "eval.csv").write_text("\n".join(lines) + "\n")
    (out / "report.md").write_text("done")


def test_the_soonest_arm_that_keeps_the_final_success_is_chosen(tmp_path, monkeypatch):
    calls = []

    def run_logged(cmd, log, what):
        calls.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])
        fast = "--collect.envs" in cmd
        seed = int(cmd[cmd.index("--seed") + 1])
        # 8 environments get there in half the time; on seed 101 one environment never does
        slow_rows = [(1000, 0.5, 40), (2000, 0.9 if seed == 100 else 0.7, 80)]
        _curve(out, [(1000, 0.85, 20), (2000, 0.9, 40)] if fast else slow_rows)
        return 1.0

    monkeypatch.setattr(ps, "run_logged", run_logged)
    import benchmarks.common as common

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path / "results")
    assert ps.main(["lang2d-quick", "--work", str(tmp_path / "work")]) == 0
    doc = json.loads((tmp_path / "results" / "preset-settings-lang2d-quick.json").read_text())
    head = doc["headline"]
    assert head["chosen"] == "--collect.envs 8"
    assert head["--collect.envs 8_s"] == 20 and head["as shipped_s"] == 80
    assert doc["arms"]["as shipped"]["all_reached"] is False  # seed 101 never got there
    # the arms alternate within each seed, one thread each, the same evaluation schedule
    arms = [("--collect.envs" in c, c[c.index("--seed") + 1]) for c in calls]
    assert arms == [(False, "100"), (True, "100"), (False, "101"), (True, "101")]
    for c in calls:
        assert c[c.index("--torch-threads") + 1] == "1"
        assert c[c.index("--eval-every") + 1] == "1000"
        assert "--total-steps" not in c  # the preset's own budget unless one is given
    # a second screen of the same preset reads the same runs into a file of its own
    assert ps.main(["lang2d-quick", "--work", str(tmp_path / "work"), "--name", "second"]) == 0
    assert len(calls) == 4  # finished runs are read, not trained again
    again = json.loads((tmp_path / "results" / "second.json").read_text())
    assert again["headline"] == head


def test_every_arm_gets_the_same_budget_when_one_is_given(tmp_path):
    args = ps.argparse.Namespace(threads=1, eval_every=2000, eval_episodes=50, total_steps=40000)
    shipped = ps.run_command("lang2d-td3", "", 100, tmp_path / "run", args)
    candidate = ps.run_command("lang2d-td3", "--collect.envs 8", 100, tmp_path / "run", args)
    for cmd in (shipped, candidate):
        assert cmd[cmd.index("--total-steps") + 1] == "40000"
    # a candidate's own options come last, so they win over the shared ones
    assert candidate[-2:] == ["--collect.envs", "8"] and candidate[:-2] == shipped


def test_no_arm_is_chosen_that_ends_lower_than_the_shipped_one():
    arms = {
        "as shipped": {"seconds": 80, "final_seen": 0.95, "all_reached": True},
        "--collect.envs 8": {"seconds": 20, "final_seen": 0.90, "all_reached": True},
    }
    assert ps.choose(arms) == "as shipped"
    arms["--collect.envs 8"]["final_seen"] = 0.94
    assert ps.choose(arms) == "--collect.envs 8"


def test_time_to_success_trains_the_preset_at_every_seed_and_reports_the_median(
    tmp_path, monkeypatch
):
    from benchmarks import time_to_success as tts

    def run_logged(cmd, log, what):
        out = Path(cmd[cmd.index("--out") + 1])
        seed = int(cmd[cmd.index("--seed") + 1])
        # seed 0 gets there at 100 s, seed 1 at 350 s, seed 2 never
        hit = {0: 0.9, 1: 0.5, 2: 0.5}[seed]
        late = 0.85 if seed == 1 else 0.6
        _curve(out, [(1000, hit, 100), (2000, late, 350)])
        (out / "config.json").write_text(
            json.dumps({"collect": {"envs": 8}, "updates_per_step": 1.0, "batch_size": 128})
        )
        return 1.0

    written = {}
    monkeypatch.setattr(tts, "run_logged", run_logged)
    monkeypatch.setattr(tts, "save_json", lambda name, doc, **kw: written.update(doc))
    monkeypatch.setattr(tts, "save_markdown", lambda *a, **kw: None)
    monkeypatch.setattr(tts, "save_figure", lambda *a, **kw: None)
    work = tmp_path / "work"
    for arm in ("new", "old"):  # the arms this invocation does not train
        run_logged([*tts.run_args(tts.argparse.Namespace(
            work=str(work), steps=2000, eval_every=1000, eval_episodes=10, seed=0), arm)],
            None, arm)  # fmt: skip
    tts.main(["--arms", "preset", "--preset-seeds", "0", "1", "2", "--work", str(work),
              "--steps", "2000", "--eval-every", "1000"])  # fmt: skip
    # seed 0 (--seed) trains in the arm's folder, the others beside it
    assert {"preset", "preset-s1", "preset-s2"} <= {p.name for p in work.iterdir()}
    head = written["headline"]
    assert head["preset_s_per_seed"] == {0: 100.0, 1: 350.0, 2: None}
    assert head["preset_s"] == 350.0  # the median, the seed that never got there the slowest
    assert written["reached"]["preset_s"] is False  # the target is 300 s
    assert tts.median_or_none([None, None, 5.0]) is None

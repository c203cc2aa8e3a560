"""The multi-task benchmark keeps the runs an invocation does not train."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.multitask import carry_over


def test_carry_over_keeps_other_runs_with_their_command(tmp_path: Path) -> None:
    old = {
        "command": "python benchmarks/multitask.py --parallel",
        "machine": {"date": "2026-11-21"},
        "runs": {
            "ids": {"goal_type": "task", "final": {}},
            "lang": {"goal_type": "language", "final": {}},
            "ids-s1": {"run": "ids", "final": {}},
        },
    }
    path = tmp_path / "multitask.json"
    path.write_text(json.dumps(old))
    results = {"ids-s0": {"run": "ids", "final": {}}}
    carry_over(results, {"ids"}, path)
    # runs named as this invocation's are retrained, never carried; others stay
    assert sorted(results) == ["ids-s0", "lang"]
    kept = results["lang"]["kept_from"]
    assert kept == {"command": old["command"], "date": "2026-11-21"}
    assert results["lang"]["run"] == "lang" and "kept_from" not in results["ids-s0"]
    # a run carried twice keeps where it first came from
    path.write_text(json.dumps({"command": "later", "runs": {"lang": results["lang"]}}))
    again: dict = {}
    carry_over(again, {"ids"}, path)
    assert again["lang"]["kept_from"]["command"] == old["command"]
    # no previous file: nothing to keep
    fresh: dict = {}
    carry_over(fresh, {"ids"}, tmp_path / "missing.json")
    assert fresh == {}

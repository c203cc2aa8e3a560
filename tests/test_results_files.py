"""The benchmarks' harness and what it writes: every result file carries the keys a reader
checks (headline, command, machine, git, date, tried), the index stays short, and the
benchmark scripts share their code through the harness instead of repeating it."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"
RESULTS = BENCHMARKS / "results"


def test_every_result_file_carries_the_keys_of_the_harness():
    from benchmarks.common import REQUIRED_KEYS

    files = sorted(RESULTS.glob("*.json"))
    assert len(files) > 30
    for path in files:
        doc = json.loads(path.read_text())
        missing = [key for key in REQUIRED_KEYS if key not in doc]
        assert not missing, f"{path.name} has no {missing}"
        assert isinstance(doc["headline"], dict) and doc["headline"], path.name
        assert isinstance(doc["tried"], list) and doc["tried"], path.name
        assert doc["git"] and doc["git"] != "unknown", path.name


def test_save_json_adds_provenance_and_keeps_what_earlier_runs_tried(tmp_path, monkeypatch):
    import benchmarks.common as common
    from lcrl.errors import LcrlError

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path)
    monkeypatch.setattr(common, "git_commit", lambda: "abc123")
    with pytest.raises(LcrlError, match="no headline"):
        common.save_json("x", {"machine": {}})
    payload = {"headline": {"a": 1}, "machine": {}, "command": "python -m benchmarks.x"}
    first = json.loads(common.save_json("x", {**payload, "arms": {"p": 1, "q": 2}}).read_text())
    assert first["git"] == "abc123" and first["date"]
    run = f"python -m benchmarks.x (git abc123, {first['date']})"
    assert first["tried"] == ["arm p", "arm q", run]
    again = {**payload, "command": "python -m benchmarks.x --fast"}
    second = json.loads(common.save_json("x", again, tried=["threshold 0.5"]).read_text())
    assert second["tried"][:3] == ["arm p", "arm q", run]
    assert second["tried"][3:] == [
        "threshold 0.5",
        f"python -m benchmarks.x --fast (git abc123, {first['date']})",
    ]
    # the command of this process when the payload gives none
    assert json.loads(common.save_json("y", {"headline": {}, "machine": {}}).read_text())["command"]


def test_save_json_keeps_the_latest_figures_of_each_kind_of_machine(tmp_path, monkeypatch):
    import benchmarks.common as common

    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path)
    monkeypatch.setattr(common, "git_commit", lambda: "g1")
    amd = {"cpu": "AMD EPYC", "cpu_features": "avx2", "date": "d1"}
    intel = {"cpu": "Xeon", "cpu_features": "avx512", "date": "d2"}
    # a file from before the record: its own headline becomes its machine's entry
    old = {"headline": {"r": 1.4, "other": 0}, "machine": amd, "git": "g0", "tried": ["t"]}
    (tmp_path / "x.json").write_text(json.dumps(old))
    doc = json.loads(
        common.save_json(
            "x", {"headline": {"r": 1.6}, "machine": intel}, by_machine_keys=["r"]
        ).read_text()
    )
    assert doc["by_machine"] == {
        "AMD EPYC (avx2)": {"r": 1.4, "git": "g0", "date": "d1"},
        "Xeon (avx512)": {"r": 1.6, "git": "g1", "date": "d2"},
    }
    # a new run on one kind replaces that kind's entry only
    again = {"headline": {"r": 1.45}, "machine": {**amd, "date": "d3"}}
    doc = json.loads(common.save_json("x", again, by_machine_keys=["r"]).read_text())
    assert doc["by_machine"]["AMD EPYC (avx2)"] == {"r": 1.45, "git": "g1", "date": "d3"}
    assert doc["by_machine"]["Xeon (avx512)"]["r"] == 1.6
    # without the keys, no record is written
    assert "by_machine" not in json.loads(common.save_json("z", again).read_text())


def test_the_results_index_and_the_readme_are_short():
    index = (RESULTS / "README.md").read_text()
    assert len(index.encode()) < 12 * 1024, "benchmarks/results/README.md is 12 KB or more"
    readme = (ROOT / "README.md").read_text()
    for name, text in (("the results index", index), ("the README", readme)):
        for line in text.splitlines():
            if line.startswith("|"):
                for cell in line.strip("|").split("|"):
                    assert len(cell) <= 300, f"a cell of {name} is long: {cell[:80]}"
    assert len(readme.splitlines()) < 250


def _imports(tree: ast.Module) -> set[int]:
    """The line numbers of the module's imports (statements of several lines included)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            lines.update(range(node.lineno, (node.end_lineno or node.lineno) + 1))
    return lines


def _windows(path: Path, size: int = 6) -> dict[tuple[str, ...], int]:
    """Every run of ``size`` non-blank lines outside imports (stripped), by its first line."""
    text = path.read_text()
    skip = _imports(ast.parse(text))
    lines = [
        (n, line.strip())
        for n, line in enumerate(text.splitlines(), 1)
        if line.strip() and n not in skip and not line.strip().startswith("#")
    ]
    return {
        tuple(s for _, s in lines[i : i + size]): lines[i][0] for i in range(len(lines) - size + 1)
    }


def test_benchmark_scripts_edit_no_import_path_and_repeat_no_block():
    scripts = sorted(p for p in BENCHMARKS.glob("*.py") if p.name != "__init__.py")
    seen: dict[tuple[str, ...], str] = {}
    repeated = []
    for path in scripts:
        assert "sys.path" not in path.read_text(), f"{path.name} edits sys.path"
        for window, line in _windows(path).items():
            # closing lines alone (brackets, returns) are not a block of code
            if sum(len(s) > 12 for s in window) < 4:
                continue
            where = seen.setdefault(window, f"{path.name}:{line}")
            if not where.startswith(path.name + ":"):
                repeated.append(f"{path.name}:{line} repeats {where}")
    assert not repeated, "\n".join(repeated[:10])


def test_a_figure_caption_holds_a_long_command_in_a_few_lines():
    from benchmarks.common import CAPTION_LINES, caption, machine, new_figure

    fig, _ = new_figure(figsize=(7, 3))
    info = machine()
    long = "python -m benchmarks.camera_choice --note '" + "word " * 400 + "'"
    caption(fig, info, long)
    (text,) = fig.texts
    lines = text.get_text().split("\n")
    assert len(lines) == CAPTION_LINES + 1  # the command's lines, then the machine's
    assert "the whole command" in lines[-2]
    caption(fig, info, "python -m benchmarks.x --seed 1")
    assert fig.texts[-1].get_text().startswith("python -m benchmarks.x --seed 1\n")

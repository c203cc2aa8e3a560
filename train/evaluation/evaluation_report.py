"""An evaluation's document: its Markdown tables (sets, chains, tasks, word combinations,
slot breakdowns) and its files (``lcrl eval --out``)."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lcrl.errors import LcrlError
from train.evaluation.report_plots import (
    _bars,
    _chain_plot,
    _eval_footer,
    _heatmap,
    _task_bars,
    plot_run_curves,
)
from train.evaluation.run_logs import EVAL_FORMAT, EVAL_VERSION


# --- Markdown pieces ---------------------------------------------------------------------------
def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _ci(st: dict[str, Any]) -> str:
    return "" if st.get("success") is None else f"[{st['ci'][0]:.2f}, {st['ci'][1]:.2f}]"


def _steps(st: dict[str, Any]) -> str:
    s = st.get("mean_steps_to_success")
    return "" if s is None else f"{s:.1f}"


def _row(cells: Sequence[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _sets_table(sets: dict[str, Any]) -> list[str]:
    lines = [
        _row(["set", "success", "95% CI", "episodes", "instructions checked", "steps to success"]),
        "|---|---:|---|---:|---:|---:|",
    ]
    for name, r in sets.items():
        lines.append(
            _row([name, _pct(r["success"]), _ci(r), r["episodes"], r["attempts"], _steps(r)])
        )
    return lines


def _chain_table(sets: dict[str, Any]) -> list[str]:
    chains = {n: r["chain"] for n, r in sets.items() if r.get("chain")}
    if not chains:
        return []
    n = max(c["length"] for c in chains.values())
    lines = [
        "## Chains",
        "",
        "Fraction of chains whose first k instructions all succeeded (95% CI), and the "
        "average number of instructions completed in a row.",
        "",
        _row(["set", "chains", *[f"k={k}" for k in range(1, n + 1)], "average length"]),
        "|---|---:|" + "---:|" * n + "---:|",
    ]
    for name, c in chains.items():
        cells = [f"{_pct(x['success'])} {_ci(x)}" for x in c["success"]]
        lines.append(_row([name, c["chains"], *cells, _pct(c["average_length"])]))
    stops = {n: c["stops"] for n, c in chains.items() if c["stops"].get("no_feasible")}
    for name, s in stops.items():
        lines.append(
            f"\n`{name}`: {s['no_feasible']} chains stopped because no instruction of the "
            "set was feasible in the scene."
        )
    return [*lines, ""]


def _tasks_table(sets: dict[str, Any]) -> list[str]:
    """Success per task of each set that has a fixed task set (none without one)."""
    lines: list[str] = []
    for name, r in sets.items():
        if not r.get("tasks"):
            continue
        lines += [
            f"### {name}",
            "",
            _row(["id", "task", "family", "success", "95% CI", "episodes", "steps to success"]),
            "|---:|---|---|---:|---|---:|---:|",
        ]
        for t in r["tasks"]:
            cells = [t.get("family") or "", _pct(t["success"]), _ci(t), t["episodes"], _steps(t)]
            lines.append(_row([t["id"], t["instruction"], *cells]))
        lines.append("")
    return lines


#: A combination whose success is below this fails (the combinations table marks it).
FAILING = 0.5


def combinations(sets: dict[str, Any]) -> list[dict[str, Any]]:
    """Success of every family x colour x shape combination of every set, worst first
    within each set: ``set``, ``family``, ``object``, ``success``, ``ci``, ``episodes``
    and ``fails`` (success below :data:`FAILING`)."""
    rows = []
    for name, r in sets.items():
        found = []
        for fam, objects in r.get("family_object", {}).items():
            for obj, st in objects.items():
                if st["success"] is None:
                    continue
                found.append(
                    {
                        "set": name,
                        "family": fam,
                        "object": obj,
                        "success": st["success"],
                        "ci": st["ci"],
                        "episodes": st["episodes"],
                        "fails": st["success"] < FAILING,
                    }
                )
        rows += sorted(found, key=lambda x: (x["success"], x["family"], x["object"]))
    return rows


def _combinations_table(sets: dict[str, Any]) -> list[str]:
    """Per set, which family x colour x shape combinations fail (worst first)."""
    rows = combinations(sets)
    if not rows:
        return []
    lines = [
        "## Combinations (family x colour x shape, worst first)",
        "",
        f"A combination fails when its success is below {FAILING:.2f}.",
        "",
    ]
    for name in dict.fromkeys(r["set"] for r in rows):
        mine = [r for r in rows if r["set"] == name]
        failing = sum(r["fails"] for r in mine)
        lines += [
            f"### {name}: {failing} of {len(mine)} combinations fail",
            "",
            _row(["family", "object", "success", "95% CI", "episodes", "fails"]),
            "|---|---|---:|---|---:|---|",
        ]
        for r in mine:
            cells = [_pct(r["success"]), _ci(r), r["episodes"], "yes" if r["fails"] else ""]
            lines.append(_row([r["family"], r["object"], *cells]))
        lines.append("")
    return lines


def _breakdown(name: str, r: dict[str, Any]) -> list[str]:
    lines = [
        f"### {name}",
        "",
        _row(["group", "value", "success", "95% CI", "episodes", "steps to success"]),
        "|---|---|---:|---|---:|---:|",
    ]
    for fam, st in r["families"].items():
        cells = [_pct(st["success"]), _ci(st), st["episodes"], _steps(st)]
        lines.append(_row(["family", fam, *cells]))
    for key, values in r.get("slots", {}).items():
        for value, st in values.items():
            lines.append(
                _row([key, value, _pct(st["success"]), _ci(st), st["episodes"], _steps(st)])
            )
    if r.get("file_instructions"):
        canonical = any(x.get("canonical") for x in r["file_instructions"])
        head = ["line", "instruction", "success", "95% CI", "episodes", "steps to success"]
        if canonical:  # lines judged by the meaning of their canonical part
            head.insert(2, "judged as")
        lines += [
            "",
            "Per line of the instruction file:",
            "",
            _row(head),
            "|---:|---|" + ("---|" if canonical else "") + "---:|---|---:|---:|",
        ]
        for x in r["file_instructions"]:
            st = r["instructions"].get(x["text"])
            n = r["unchecked_instructions"].get(x["text"], 0)
            if x["checked"] and st is not None:
                cells = [_pct(st["success"]), _ci(st), st["episodes"], _steps(st)]
            elif n:
                cells = ["not checked", x["note"] or "not feasible in the layouts drawn", n, ""]
            else:
                cells = ["not run", "fewer episodes than lines", 0, ""]
            first = [x["line"], x["text"]]
            if canonical:
                first.append(x.get("canonical") or x["text"])
            lines.append(_row([*first, *cells]))
    elif r.get("unchecked_instructions"):
        lines += ["", "Not checked (the rule captioner cannot judge them here):", ""]
        for text, n in r["unchecked_instructions"].items():
            lines.append(f"- {text!r}: {n} episodes")
    return [*lines, ""]


def evaluation_markdown(doc: dict[str, Any], images: dict[str, str]) -> str:
    """The Markdown report of an evaluation document; ``images`` maps a figure name
    (``sets``, ``heatmap``, ``chain``, ``curves``) to its relative path."""
    s = doc["settings"]
    lines = [f"# Evaluation of {Path(doc['checkpoint']).name} (step {doc['step']})", ""]
    run = f"; run `{doc['run']}`." if doc.get("run") else "."
    lines.append(f"Checkpoint: `{doc['checkpoint']}`{run}")
    lines.append(f"Task: {doc.get('task', '')}.")
    per = "chains" if s.get("chain", 0) > 1 else "episodes"
    lines.append(
        f"{s['episodes']} {per} per set, seed {s['seed']}, deterministic policy; episode i "
        f"starts from reset seed {s['first_seed']} + i, so every figure is reproducible."
    )
    if s.get("chain", 0) > 1:
        lines.append(
            f"Chains of up to {s['chain']} instructions in one scene, each with the env's "
            "step budget; families, slots and instructions count every instruction attempted."
        )
    if s.get("instructions_file"):
        lines.append(f"Set `custom`: the instructions of `{s['instructions_file']}`.")
    if s.get("command"):
        lines.append(f"\nCommand: `{s['command']}`")
    if doc.get("machine"):
        from train.runtime.machine import machine_line

        lines.append(f"\nMachine: {machine_line(doc['machine'])}")
    lines += ["", "## Success per set", "", *_sets_table(doc["sets"]), ""]
    lines.append(
        "`train`: seen instructions; `heldout`: word combinations never trained on; "
        "`paraphrase`: seen meanings in unseen phrasings. Intervals are 95% Wilson score "
        "intervals; steps to success are means over the successful episodes."
    )
    tasks = _tasks_table(doc["sets"])
    if tasks:
        k = max(len(r["tasks"]) for r in doc["sets"].values() if r.get("tasks"))
        lines.append(
            f"With a fixed task set, `train` is its {k} tasks: episode i runs task i mod {k} "
            "from the first layout of its reset seed where the task is feasible (the "
            "layouts of the training loop's evaluation)."
        )
    if "sets" in images:
        lines += ["", f"![success per set]({images['sets']})"]
    if tasks:
        lines += ["", "## Success per task", "", *tasks]
        if "tasks" in images:
            lines += [f"![success per task]({images['tasks']})"]
    lines += ["", *_chain_table(doc["sets"])]
    if "chain" in images:
        lines += [f"![chains]({images['chain']})", ""]
    lines += ["## Families and slot values", ""]
    if "heatmap" in images:
        lines += [f"![success per family and object]({images['heatmap']})", ""]
    for name, r in doc["sets"].items():
        lines += _breakdown(name, r)
    lines += _combinations_table(doc["sets"])
    if "curves" in images:
        lines += ["## Learning curves", "", f"![learning curves]({images['curves']})", ""]
    return "\n".join(lines) + "\n"


def write_evaluation(doc: dict[str, Any], out: str | Path) -> dict[str, Path]:
    """Write an evaluation document (:func:`train.evaluation.eval_suite.evaluation_document`) to
    ``out``: ``eval.json``, ``eval.md`` and the PNG figures; returns the paths by name."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LcrlError(f"--out {out} is a file, not a folder")
    out.mkdir(parents=True, exist_ok=True)
    doc = {"format": EVAL_FORMAT, "version": EVAL_VERSION, **doc}
    paths: dict[str, Path] = {}
    sets = doc["sets"]
    footer = _eval_footer(doc)
    paths["sets"] = _bars(sets, out / "sets.png", footer)
    heat = _heatmap(sets, out / "heatmap.png", footer)
    if heat is not None:
        paths["heatmap"] = heat
    chain = _chain_plot(sets, out / "chain.png", footer)
    if chain is not None:
        paths["chain"] = chain
    per_task = _task_bars(sets, out / "tasks.png", footer)
    if per_task is not None:
        paths["tasks"] = per_task
    if doc.get("run"):
        paths["curves"] = plot_run_curves(doc["run"], out / "curves.png", doc.get("step"), footer)
    json_path = out / "eval.json"
    tmp = json_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, json_path)
    paths["json"] = json_path
    images = {k: p.name for k, p in paths.items() if p.suffix == ".png"}
    md = out / "eval.md"
    md.write_text(evaluation_markdown(doc, images))
    paths["md"] = md
    return paths

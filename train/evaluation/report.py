"""Reports: a run's learning curves and summary, an evaluation's figures, run comparisons.

* :func:`write_report` writes a run folder's ``curves.png`` (learning curves from its
  ``progress.csv`` and ``eval.csv``) and ``report.md`` (config, final evaluation, and the
  figures of every ``lcrl eval --out`` written inside the run folder). Training calls it at
  the end of every run; ``lcrl report RUN_DIR`` rebuilds it for a finished or interrupted
  run.
* :func:`write_evaluation` writes what ``lcrl eval --out DIR`` produces: ``eval.json``
  (every figure), ``eval.md``, ``sets.png`` (success per set and family with 95%
  confidence intervals), ``heatmap.png`` (success per family and object), ``chain.png``
  (chained evaluation), ``tasks.png`` (success per task of a fixed task set) and, when
  the checkpoint belongs to a run folder, ``curves.png``.
* :func:`compare_runs` puts several runs side by side (``lcrl report RUN_A RUN_B --out
  DIR``): ``comparison.md`` (a table) and ``comparison.png`` (overlaid curves).

Layout of evaluations inside a run: ``lcrl eval RUN_DIR --out RUN_DIR/evals/NAME`` (any
folder one or two levels below the run folder holding an ``eval.json`` is found);
``lcrl report RUN_DIR`` lists each of them with its figures.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lcrl.algos import ALGOS
from lcrl.errors import LcrlError
from train.environments.simulators import ENVS, KIND_ALIASES, describe
from train.environments.tasks import GOALS, goals_label

EVAL_FORMAT = "lcrl-eval"
EVAL_VERSION = 1
SET_STYLES = {"train": "-", "all": "-", "heldout": "--", "paraphrase": ":", "custom": "-."}
SET_LABELS = {
    "train": "seen instructions",
    "heldout": "held-out combinations",
    "paraphrase": "unseen phrasings",
    "custom": "instruction file",
    "all": "environment goals",
}


# --- reading a run ---------------------------------------------------------------------------
def _read(path: Path) -> list[dict[str, float]]:
    """Rows of a run's CSV log as floats (missing values are NaN); [] without the file."""
    if not path.exists():
        return []
    try:
        with path.open() as f:
            rows = []
            for r in csv.DictReader(f):
                rows.append(
                    {
                        k: float(v) if v not in ("", None) else float("nan")
                        for k, v in r.items()
                        if k is not None
                    }
                )
            return rows
    except (ValueError, csv.Error, UnicodeDecodeError) as e:
        raise LcrlError(f"{path} is not a valid log (CSV of numbers): {e}") from None


def _config(run: Path) -> dict[str, Any]:
    if not run.exists():
        raise LcrlError(f"{run} is not a run folder: it does not exist")
    if not run.is_dir():
        raise LcrlError(f"{run} is not a run folder: it is a file")
    path = run / "config.json"
    if not path.exists():
        raise LcrlError(f"{run} is not a run folder (no config.json)")
    try:
        config = json.loads(path.read_text())
        if not isinstance(config["env"]["kind"], str):
            raise TypeError("env.kind is not a string")
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise LcrlError(f"{path} is not a valid run config: {e!r}") from None
    return config


def run_of_checkpoint(checkpoint: str | Path) -> Path | None:
    """The run folder a checkpoint folder belongs to (``RUN/checkpoints/step_N``), if any."""
    p = Path(checkpoint).resolve()
    run = p.parent.parent
    if p.parent.name == "checkpoints" and (run / "config.json").is_file():
        try:  # as the user would type it, when it is below the working directory
            return run.relative_to(Path.cwd().resolve())
        except ValueError:
            return run
    return None


def task_name(env: dict[str, Any]) -> str:
    """A short name of a run's task from its (saved) env config: ``2D tabletop
    reach/push``, ``2D tabletop (state goals)``, ``robosuite tabletop (image goals)``, a
    gym id."""
    kind, alias_goal = KIND_ALIASES.get(str(env.get("kind", "?")), (env.get("kind", "?"), None))
    goal_type = str(alias_goal or env.get("goal_type", "language"))
    name = describe(env)
    spec = ENVS.get(kind)
    modality = GOALS.get(goal_type)
    text = modality is not None and modality.text
    if text and spec is not None and spec.families:
        name += " " + "/".join(env.get("families", ()))
    tasks = env.get("tasks") or ()
    if tasks:
        return name + f", {len(tasks)} tasks as {goals_label(goal_type)}"
    if not text:
        name += f" ({goals_label(goal_type)})"
    return name


def _sets_of(evals: list[dict[str, float]]) -> list[str]:
    return [k.split("/")[0] for k in (evals[0] if evals else {}) if k.endswith("/success")]


def final_from_log(run: str | Path) -> dict[str, Any] | None:
    """The last evaluation of a run's ``eval.csv`` in the shape of
    :func:`train.evaluation.evaluate.evaluate`'s results (None when it has no row)."""
    run = Path(run)
    evals = _read(run / "eval.csv")
    if not evals:
        return None
    config = _config(run)
    last = evals[-1]
    out = {}
    for s in _sets_of(evals):
        fams = {
            k.split("/", 1)[1]: v
            for k, v in last.items()
            if k.startswith(f"{s}/") and k != f"{s}/success" and not math.isnan(v)
        }
        out[s] = {
            "success": last[f"{s}/success"],
            "episodes": int(config.get("eval_episodes", 0)),
            "families": fams,
            "step": int(last["step"]),
        }
    tasks = config["env"].get("tasks") or ()
    if tasks and "train" in out:  # a fixed task set: success per task, run round robin
        n, k = out["train"]["episodes"], len(tasks)
        out["train"]["tasks"] = [
            {
                "id": i,
                "instruction": t,
                "success": last.get(f"tasks/{i}", float("nan")),
                "episodes": n // k + (i < n % k),
            }
            for i, t in enumerate(tasks)
        ]
    return out


def find_evaluations(run: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """Every ``eval.json`` one or two folder levels below a run folder, oldest
    checkpoint first: ``[(folder, document)]``. Files that are not evaluations are skipped."""
    run = Path(run)
    found = []
    for path in sorted([*run.glob("*/eval.json"), *run.glob("*/*/eval.json")]):
        if "checkpoints" in path.relative_to(run).parts:
            continue
        try:
            doc = load_evaluation(path)
        except LcrlError:
            continue
        found.append((path.parent, doc))
    found.sort(key=lambda x: (x[1].get("step") or 0, str(x[0])))
    return found


def load_evaluation(path: str | Path) -> dict[str, Any]:
    """Read an ``eval.json`` written by ``lcrl eval --out`` (a file or its folder)."""
    p = Path(path)
    if p.is_dir():
        p = p / "eval.json"
    if not p.is_file():
        raise LcrlError(f"no evaluation at {p}")
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise LcrlError(f"{p} is not valid JSON: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != EVAL_FORMAT or "sets" not in doc:
        raise LcrlError(f"{p} is not an evaluation written by lcrl eval")
    if doc.get("version") != EVAL_VERSION:
        raise LcrlError(f"{p}: evaluation format version {doc.get('version')} is not supported")
    return doc


# --- plots -----------------------------------------------------------------------------------
def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plot_curves(
    axes: Sequence[Any],
    progress: list[dict[str, float]],
    evals: list[dict[str, float]],
    label: str = "",
    colour: Any = None,
) -> None:
    """Training success (left) and evaluation success per set (right) of one run."""
    if progress:
        axes[0].plot(
            [r["step"] for r in progress],
            [r["success"] for r in progress],
            color=colour,
            label=label or None,
        )
    for s in _sets_of(evals):
        axes[1].plot(
            [r["step"] for r in evals],
            [r[f"{s}/success"] for r in evals],
            SET_STYLES.get(s, "-"),
            marker="o",
            ms=3,
            color=colour,
            label=f"{label} {s}".strip(),
        )


def _style_curve_axes(axes: Sequence[Any]) -> None:
    axes[0].set_title("training episodes (last 100)")
    axes[1].set_title("evaluation (deterministic policy)")
    for ax in axes:
        ax.set_xlabel("environment steps")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)


def _footer(fig: Any, footer: str) -> None:
    """The command and machine behind a figure, in small print at its bottom left."""
    if footer:
        fig.text(0.01, 0.005, footer, fontsize=6, va="bottom")


def _eval_footer(doc: dict[str, Any]) -> str:
    """``command`` and machine line of an evaluation document (older ones may lack them)."""
    from train.runtime.machine import machine_line

    lines = [doc.get("settings", {}).get("command") or ""]
    if doc.get("machine"):
        lines.append(machine_line(doc["machine"]))
    return "\n".join(x for x in lines if x)


def plot_run_curves(
    run: str | Path, path: str | Path, mark_step: int | None = None, footer: str = ""
) -> Path:
    """Learning curves of a run folder into ``path`` (PNG); ``mark_step`` draws a vertical
    line (the evaluated checkpoint); ``footer``: small print (command, machine)."""
    run = Path(run)
    config = _config(run)
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    _plot_curves(axes, _read(run / "progress.csv"), _read(run / "eval.csv"))
    if mark_step is not None:
        for ax in axes:
            ax.axvline(mark_step, color="grey", lw=0.8, ls=":")
    _style_curve_axes(axes)
    fig.suptitle(f"{run.name}: {config['env']['kind']} {config.get('resolved_algo', '')}")
    fig.tight_layout(rect=(0, 0.06 if footer else 0, 1, 1))
    _footer(fig, footer)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _bars(sets: dict[str, Any], path: Path, footer: str = "") -> Path:
    """Success per family (and overall) for each set, with Wilson 95% error bars."""
    import numpy as np

    plt = _plt()
    names = list(sets)
    groups = ["all", *sorted({f for r in sets.values() for f in r["families"]} - {"all"})]
    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(groups) * max(1, len(names)) * 0.6), 3.4))
    width = 0.8 / max(1, len(names))
    x = np.arange(len(groups))
    for k, name in enumerate(names):
        res = sets[name]
        vals, lo, hi = [], [], []
        for g in groups:
            st = res if g == "all" else res["families"].get(g)
            if st is None or st.get("success") is None:
                vals.append(np.nan)
                lo.append(0.0)
                hi.append(0.0)
                continue
            vals.append(st["success"])
            lo.append(max(0.0, st["success"] - st["ci"][0]))
            hi.append(max(0.0, st["ci"][1] - st["success"]))
        ax.bar(
            x + (k - (len(names) - 1) / 2) * width,
            vals,
            width,
            yerr=[lo, hi],
            capsize=3,
            label=SET_LABELS.get(name, name),
        )
    ax.set_xticks(x, groups)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate (95% CI)")
    ax.set_title("success per set and family")
    ax.legend(fontsize=7)
    fig.tight_layout(rect=(0, 0.08 if footer else 0, 1, 1))
    _footer(fig, footer)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _heatmap(sets: dict[str, Any], path: Path, footer: str = "") -> Path | None:
    """Success per family (rows) and object (columns), one panel per set."""
    import numpy as np

    from envs.scene import OBJECT_KINDS

    panels = [(n, r["family_object"]) for n, r in sets.items() if r.get("family_object")]
    if not panels:
        return None
    plt = _plt()
    objects = [f"{c} {s}" for c, s in OBJECT_KINDS]
    fig, axes = plt.subplots(
        1, len(panels), figsize=(4.2 * len(panels), 0.6 * max(len(p[1]) for p in panels) + 2.2)
    )
    axes = np.atleast_1d(axes)
    image = None
    for ax, (name, table) in zip(axes, panels, strict=True):
        families = sorted(table)
        grid = np.full((len(families), len(objects)), np.nan)
        for i, fam in enumerate(families):
            for j, obj in enumerate(objects):
                st = table[fam].get(obj)
                if st is not None and st["success"] is not None:
                    grid[i, j] = st["success"]
                    colour = "white" if st["success"] < 0.6 else "black"
                    label = f"{st['success']:.2f}\n{st['episodes']}"
                    ax.text(j, i, label, ha="center", va="center", fontsize=6, color=colour)
        image = ax.imshow(np.ma.masked_invalid(grid), vmin=0, vmax=1, cmap="viridis")
        ax.set_xticks(range(len(objects)), objects, rotation=60, ha="right", fontsize=7)
        ax.set_yticks(range(len(families)), families, fontsize=8)
        ax.set_facecolor("#dddddd")
        ax.set_title(SET_LABELS.get(name, name), fontsize=9)
    if image is not None:
        fig.colorbar(image, ax=list(axes), shrink=0.8, label="success (episodes below)")
    if footer:
        fig.text(0.01, -0.08, footer, fontsize=6, va="top", transform=fig.transFigure)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _task_bars(sets: dict[str, Any], path: Path, footer: str = "") -> Path | None:
    """Success per task of a fixed task set (one bar per task, Wilson 95% error bars),
    one panel per set that has tasks; None when no set has."""
    import numpy as np

    panels = [(n, r["tasks"]) for n, r in sets.items() if r.get("tasks")]
    if not panels:
        return None
    plt = _plt()
    k = max(len(t) for _, t in panels)
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 0.32 * k + 1.6))
    for ax, (name, tasks) in zip(np.atleast_1d(axes), panels, strict=True):
        y = np.arange(len(tasks))
        vals = [np.nan if t["success"] is None else t["success"] for t in tasks]
        lo = [0.0 if t["success"] is None else max(0.0, t["success"] - t["ci"][0]) for t in tasks]
        hi = [0.0 if t["success"] is None else max(0.0, t["ci"][1] - t["success"]) for t in tasks]
        ax.barh(y, vals, xerr=[lo, hi], capsize=3, color="tab:blue")
        labels = [f"{t['id']}: {t['instruction']} ({t['episodes']})" for t in tasks]
        ax.set_yticks(y, labels, fontsize=7)
        ax.invert_yaxis()
        ax.set_xlim(0, 1.05)
        ax.set_xlabel("success rate (95% CI)")
        ax.set_title(f"success per task, {name} (episodes)", fontsize=9)
    fig.tight_layout(rect=(0, 0.08 if footer else 0, 1, 1))
    _footer(fig, footer)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _chain_plot(sets: dict[str, Any], path: Path, footer: str = "") -> Path | None:
    chains = {n: r["chain"] for n, r in sets.items() if r.get("chain") and r["chain"]["chains"]}
    if not chains:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3.4))
    for name, c in chains.items():
        ks = [x["length"] for x in c["success"]]
        ax.plot(ks, [x["success"] for x in c["success"]], SET_STYLES.get(name, "-"), marker="o",
                label=f"{SET_LABELS.get(name, name)} (avg {c['average_length']:.2f})")  # fmt: skip
        ax.fill_between(ks, [x["ci"][0] for x in c["success"]], [x["ci"][1] for x in c["success"]],
                        alpha=0.15)  # fmt: skip
    ax.set_xlabel("instructions in a row")
    ax.set_ylabel("chains completed (95% CI)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xticks(ks)
    ax.legend(fontsize=7)
    ax.set_title("chained instructions")
    fig.tight_layout(rect=(0, 0.1 if footer else 0, 1, 1))
    _footer(fig, footer)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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


# --- a run's report ----------------------------------------------------------------------------
def write_report(
    run_dir: str | Path, final: dict[str, Any] | None = None, out: str | Path | None = None
) -> Path:
    """Write ``curves.png`` and ``report.md`` for a run folder; returns the report's path.

    Args:
        run_dir: the run folder (``config.json``, ``progress.csv``, ``eval.csv``).
        final: the final evaluation (:func:`train.evaluation.evaluate.evaluate`'s results); default:
            the last row of ``eval.csv``.
        out: where to write (default: the run folder).

    Raises:
        LcrlError: not a run folder, or unreadable logs.
    """
    run = Path(run_dir)
    config = _config(run)
    dest = Path(out) if out is not None else run
    if dest.exists() and not dest.is_dir():
        raise LcrlError(f"--out {dest} is a file, not a folder")
    dest.mkdir(parents=True, exist_ok=True)
    progress = _read(run / "progress.csv")
    plot_run_curves(run, dest / "curves.png")

    lines = [f"# Run {run.name}", ""]
    what = task_name(config["env"])
    algo = config.get("resolved_algo", config.get("algo", "?"))
    lines.append(
        f"{what}, {algo}, {learning_summary(config)}, "
        f"{config.get('total_steps', 0):,} {_unit(algo)}s, "
        f"seed {config.get('seed', '?')}."
    )
    if progress:
        last_step = int(progress[-1]["step"])
        if last_step < config.get("total_steps", 0):
            lines.append(
                f"\nThe logs stop at step {last_step:,} of {config['total_steps']:,} (an "
                "interrupted or running run)."
            )
    lines += ["", "![learning curves](curves.png)", ""]
    from_log = final is None
    if final is None:
        final = final_from_log(run)
    if final:
        fams = sorted({f for res in final.values() for f in res["families"]})
        lines.append("| set | success | " + " | ".join(fams) + " |")
        lines.append("|---|---:|" + "---:|" * len(fams))
        for name, res in final.items():
            cells = [f"{res['families'][f]:.2f}" if f in res["families"] else "" for f in fams]
            lines.append(f"| {name} | {res['success']:.2f} | " + " | ".join(cells) + " |")
        n = next(iter(final.values()))["episodes"]
        if from_log:
            step = next(iter(final.values())).get("step")
            lines += ["", f"Last evaluation in eval.csv (step {step:,}): {n} episodes per set."]
        else:
            lines += ["", f"Final evaluation: {n} episodes per set, deterministic policy."]
        lines.append(
            "`train`: seen instructions; `heldout`: word combinations never trained on; "
            "`paraphrase`: seen meanings in unseen phrasings."
            if "heldout" in final
            else ""
        )
        lines += _tasks_section(final)
    from train.evaluation.sequential import markdown, read

    stages = read(run)
    if stages is not None:  # sequential stages: the success matrix and forgetting
        lines += ["", markdown(stages), "![success matrix](sequential.png)", ""]
    if progress:
        last = progress[-1]
        speed = last.get("steps_per_s", float("nan"))
        updates = last.get("updates", float("nan"))
        if not (math.isnan(speed) or math.isnan(updates)):
            lines.append(f"\nTraining speed: {speed:.0f} steps/s; {int(updates):,} updates.")
    lines += _evaluations_section(run, dest)
    lines += ["", "Files: config.json, progress.csv, eval.csv, checkpoints/ (latest.json)."]
    path = dest / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _unit(algo: str) -> str:
    """What a run's steps count (``step``, or ``update`` for learning from
    demonstrations)."""
    spec = ALGOS.get(algo)
    return spec.unit if spec is not None else "step"


def learning_summary(config: dict[str, Any]) -> str:
    """How a run learns, from its config: ``behavioural cloning from FILE (hindsight
    segments on)``, ``task ids, no relabelling``, or the relabelling settings
    (``relabelling future k=4``)."""
    algo = config.get("resolved_algo", config.get("algo", "?"))
    spec = ALGOS.get(algo)
    if spec is not None and spec.learns_from == "demos":
        # configs saved before the option existed had its default
        default = getattr(spec.config(), "hindsight", None)
        hindsight = (config.get(algo) or {}).get("hindsight", default)
        on = "on" if hindsight else "off"
        segments = "" if hindsight is None else f" (hindsight segments {on})"
        return f"{spec.title or spec.name} from {config.get('demos') or '?'}{segments}"
    goal_type = str((config.get("env") or {}).get("goal_type", ""))
    modality = GOALS.get(goal_type)
    if modality is not None and not modality.relabel:
        return f"{goals_label(goal_type)}, no relabelling"
    buf = config.get("buffer", {})
    return f"relabelling {buf.get('strategy', '?')} k={buf.get('k', '?')}"


def _tasks_section(final: dict[str, Any]) -> list[str]:
    """A table of success per task of a fixed task set (none without one)."""
    lines: list[str] = []
    for name, res in final.items():
        tasks = res.get("tasks")
        if not tasks:
            continue
        lines += ["", f"Success per task ({name}):", "", "| id | task | success | episodes |"]
        lines.append("|---:|---|---:|---:|")
        for t in tasks:
            n = t.get("episodes", "")
            lines.append(f"| {t['id']} | {t['instruction']} | {_pct(t['success'])} | {n} |")
    return lines


def _evaluations_section(run: Path, dest: Path) -> list[str]:
    found = find_evaluations(run)
    if not found:
        return []
    lines = ["", "## Evaluations (lcrl eval --out)", ""]
    for folder, doc in found:
        rel = os.path.relpath(folder, dest)
        s = doc["settings"]
        chain = f", chains of {s['chain']}" if s.get("chain", 0) > 1 else ""
        lines += [
            f"### {folder.name} (checkpoint step {doc['step']})",
            "",
            f"{s['episodes']} episodes per set, seed {s['seed']}{chain}; "
            f"full report: [{rel}/eval.md]({rel}/eval.md).",
            "",
            *_sets_table(doc["sets"]),
            "",
            *_chain_table(doc["sets"]),
        ]
        if (folder / "sets.png").exists():
            lines += [f"![{folder.name}]({rel}/sets.png)", ""]
        if (folder / "tasks.png").exists() and any(r.get("tasks") for r in doc["sets"].values()):
            lines += [f"![{folder.name}: success per task]({rel}/tasks.png)", ""]
    return lines


# --- comparing runs ----------------------------------------------------------------------------
def _labels(runs: Sequence[Path]) -> list[str]:
    names = [r.name for r in runs]
    if len(set(names)) == len(names):
        return names
    return [f"{r.parent.name}/{r.name}" if names.count(r.name) > 1 else r.name for r in runs]


#: Config keys that differ between the seeds of one experiment (and where it is written).
PER_RUN_KEYS = ("out", "seed", "overwrite", "resume", "progress", "tensorboard")


def seed_groups(configs: Sequence[dict[str, Any]]) -> list[list[int]]:
    """Indices of runs whose configs are equal apart from :data:`PER_RUN_KEYS` (the
    seeds of one experiment), in order of first appearance."""
    groups: dict[str, list[int]] = {}
    for i, config in enumerate(configs):
        rest = {k: v for k, v in config.items() if k not in PER_RUN_KEYS}
        groups.setdefault(json.dumps(rest, sort_keys=True, default=str), []).append(i)
    return list(groups.values())


def spread(values: Sequence[float]) -> dict[str, Any]:
    """Mean, sample standard deviation, min and max of one figure over runs."""
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else 0.0
    return {"mean": mean, "std": std, "min": min(values), "max": max(values), "runs": n}


def _spread_cell(values: Sequence[float | None]) -> str:
    have = [v for v in values if v is not None]
    if len(have) < 2:
        return ""
    sp = spread(have)
    return f"{_pct(sp['mean'])} ± {_pct(sp['std'])} ({_pct(sp['min'])}–{_pct(sp['max'])})"


def _seeds_table(
    labels: Sequence[str],
    configs: Sequence[dict[str, Any]],
    finals: Sequence[dict[str, Any]],
    evaluations: Sequence[Any],
) -> list[str]:
    """The mean and spread over the seeds of each experiment (runs whose configs differ
    only in seed and output folder): last evaluation and latest ``lcrl eval``, with the
    ratio of held-out to seen success."""
    groups = [g for g in seed_groups(configs) if len(g) > 1]
    if not groups:
        return []
    figures: list[tuple[str, list[dict[str, Any]]]] = [("last eval", list(finals))]
    if any(e is not None for e in evaluations):
        figures.append(("lcrl eval", [e[1]["sets"] if e else {} for e in evaluations]))
    lines = [
        "## Across seeds (mean ± standard deviation over runs, min–max)",
        "",
        "Runs whose configs differ only in seed and output folder are one experiment.",
        "",
    ]
    for source, per_run in figures:
        sets = list(dict.fromkeys(s for i in range(len(per_run)) for s in per_run[i]))
        ratio = "train" in sets and "heldout" in sets
        head = ["runs", "figures", *sets, *(["held-out / seen"] if ratio else [])]
        lines += [_row(head), "|---|---|" + "---|" * (len(head) - 2)]
        for g in groups:
            rates = {
                s: [per_run[i][s]["success"] if s in per_run[i] else None for i in g] for s in sets
            }
            cells = [_spread_cell(rates[s]) for s in sets]
            if ratio:
                pairs = [
                    (t, h)
                    for t, h in zip(rates["train"], rates["heldout"], strict=True)
                    if t and h is not None
                ]
                cells.append(_spread_cell([h / t for t, h in pairs]))
            lines.append(_row([", ".join(labels[i] for i in g), source, *cells]))
        lines.append("")
    return lines


def compare_runs(runs: Sequence[str | Path], out: str | Path) -> Path:
    """Runs side by side: ``comparison.md`` (a table of their settings, last evaluation
    and latest ``lcrl eval`` figures; the mean and spread over the seeds of each
    experiment) and ``comparison.png`` (overlaid curves) in ``out``.

    Raises:
        LcrlError: fewer than two runs, the same run twice, or a folder that is not a run.
    """
    paths = [Path(r) for r in runs]
    if len(paths) < 2:
        raise LcrlError("a comparison needs two or more run folders")
    resolved = [p.resolve() for p in paths]
    if len(set(resolved)) != len(resolved):
        raise LcrlError("the same run folder is given twice")
    configs = [_config(p) for p in paths]
    dest = Path(out)
    if dest.exists() and not dest.is_dir():
        raise LcrlError(f"--out {dest} is a file, not a folder")
    dest.mkdir(parents=True, exist_ok=True)
    labels = _labels(paths)
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    finals, evaluations, steps = [], [], []
    for k, (run, label) in enumerate(zip(paths, labels, strict=True)):
        progress = _read(run / "progress.csv")
        _plot_curves(axes, progress, _read(run / "eval.csv"), label, colours[k % len(colours)])
        finals.append(final_from_log(run) or {})
        found = find_evaluations(run)
        evaluations.append(found[-1] if found else None)
        steps.append(int(progress[-1]["step"]) if progress else 0)
    _style_curve_axes(axes)
    fig.suptitle("runs compared: " + ", ".join(labels), fontsize=9)
    fig.tight_layout()
    png = dest / "comparison.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    sets = list(dict.fromkeys(s for f in finals for s in f))
    lines = ["# Runs compared", "", f"![learning curves]({png.name})", ""]
    lines.append(_row(["run", "task", "algo", "steps", *[f"{s} (last eval)" for s in sets]]))
    lines.append("|---|---|---|---:|" + "---:|" * len(sets))
    for label, config, final, step in zip(labels, configs, finals, steps, strict=True):
        task = task_name(config["env"])
        cells = [_pct(final[s]["success"]) if s in final else "" for s in sets]
        algo = config.get("resolved_algo", config.get("algo", "?"))
        lines.append(_row([label, task, algo, f"{step:,}", *cells]))
    lines += ["", "Last evaluation: the last row of each run's eval.csv.", ""]
    ev_sets = list(dict.fromkeys(s for e in evaluations if e is not None for s in e[1]["sets"]))
    if ev_sets:
        lines += [
            "## lcrl eval figures (latest evaluation of each run, success and 95% CI)",
            "",
            _row(["run", "checkpoint step", "episodes", *ev_sets, "chain average length"]),
            "|---|---:|---:|" + "---|" * len(ev_sets) + "---:|",
        ]
        for label, e in zip(labels, evaluations, strict=True):
            if e is None:
                lines.append(_row([label, "", "", *[""] * len(ev_sets), ""]))
                continue
            doc = e[1]
            cells = []
            for s in ev_sets:
                st = doc["sets"].get(s)
                cells.append(f"{_pct(st['success'])} {_ci(st)}" if st else "")
            avg = [
                f"{s}: {_pct(r['chain']['average_length'])}"
                for s, r in doc["sets"].items()
                if r.get("chain")
            ]
            lines.append(
                _row([label, doc["step"], doc["settings"]["episodes"], *cells, "; ".join(avg)])
            )
        lines.append("")
    lines += _seeds_table(labels, configs, finals, evaluations)
    lines.append("Runs: " + ", ".join(f"`{p}`" for p in paths))
    path = dest / "comparison.md"
    path.write_text("\n".join(lines) + "\n")
    return path


if __name__ == "__main__":
    print(write_report(sys.argv[1]))

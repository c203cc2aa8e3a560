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

import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lcrl.algos import ALGOS
from lcrl.errors import LcrlError
from train.environments.tasks import GOALS, goals_label
from train.evaluation.evaluation_report import (
    FAILING as FAILING,
    _breakdown as _breakdown,
    _chain_table as _chain_table,
    _ci,
    _combinations_table as _combinations_table,
    _pct,
    _row,
    _sets_table as _sets_table,
    combinations as combinations,
    evaluation_markdown as evaluation_markdown,
    write_evaluation as write_evaluation,
)
from train.evaluation.report_plots import (
    SET_LABELS as SET_LABELS,
    SET_STYLES as SET_STYLES,
    _plot_curves,
    _plt,
    _style_curve_axes,
    plot_run_curves as plot_run_curves,
)
from train.evaluation.run_logs import (
    EVAL_FORMAT as EVAL_FORMAT,
    EVAL_VERSION as EVAL_VERSION,
    _config,
    _read,
    final_from_log as final_from_log,
    find_evaluations as find_evaluations,
    load_evaluation as load_evaluation,
    run_of_checkpoint as run_of_checkpoint,
    task_name as task_name,
)


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

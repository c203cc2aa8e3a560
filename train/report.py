"""A run's report: learning curves (``curves.png``) and a summary (``report.md``).

Written at the end of every training run from its ``progress.csv`` and ``eval.csv``; run
``python -m train.report RUN_DIR`` to rewrite it for any run folder.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path
from typing import Any

from lcrl.errors import LcrlError


def _read(path: Path) -> list[dict[str, float]]:
    if not path.exists():
        return []
    with path.open() as f:
        rows = []
        for r in csv.DictReader(f):
            rows.append(
                {k: float(v) if v not in ("", None) else float("nan") for k, v in r.items()}
            )
        return rows


def write_report(run_dir: str | Path, final: dict[str, Any] | None = None) -> Path:
    """Write ``curves.png`` and ``report.md`` into ``run_dir``; returns the report's path."""
    run = Path(run_dir)
    if not (run / "config.json").exists():
        raise LcrlError(f"{run} is not a run folder (no config.json)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = json.loads((run / "config.json").read_text())
    progress = _read(run / "progress.csv")
    evals = _read(run / "eval.csv")
    sets = [k.split("/")[0] for k in (evals[0] if evals else {}) if k.endswith("/success")]

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    if progress:
        axes[0].plot([r["step"] for r in progress], [r["success"] for r in progress])
    axes[0].set_title("training episodes (last 100)")
    styles = {"train": "-", "all": "-", "heldout": "--", "paraphrase": ":"}
    for s in sets:
        axes[1].plot(
            [r["step"] for r in evals],
            [r[f"{s}/success"] for r in evals],
            styles.get(s, "-"),
            marker="o",
            ms=3,
            label=s,
        )
    axes[1].set_title("evaluation (deterministic policy)")
    if sets:
        axes[1].legend(fontsize=8)
    for ax in axes:
        ax.set_xlabel("environment steps")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
    fig.suptitle(f"{run.name}: {config['env']['kind']} {config.get('resolved_algo', '')}")
    fig.tight_layout()
    fig.savefig(run / "curves.png", dpi=110)
    plt.close(fig)

    lines = [f"# Run {run.name}", ""]
    env = config["env"]
    what = env["gym_id"] if env["kind"] == "gym" else f"{env['kind']} {tuple(env['families'])}"
    buf = config["buffer"]
    lines.append(
        f"{what}, {config.get('resolved_algo', config['algo'])}, relabelling "
        f"{buf['strategy']} k={buf['k']}, {config['total_steps']:,} steps, seed "
        f"{config['seed']}."
    )
    lines += ["", "![learning curves](curves.png)", ""]
    if final:
        fams = sorted({f for res in final.values() for f in res["families"]})
        lines.append("| set | success | " + " | ".join(fams) + " |")
        lines.append("|---|---:|" + "---:|" * len(fams))
        for name, res in final.items():
            cells = [f"{res['families'][f]:.2f}" if f in res["families"] else "" for f in fams]
            lines.append(f"| {name} | {res['success']:.2f} | " + " | ".join(cells) + " |")
        n = next(iter(final.values()))["episodes"]
        lines += ["", f"Final evaluation: {n} episodes per set, deterministic policy."]
        lines.append(
            "`train`: seen instructions; `heldout`: word combinations never trained on; "
            "`paraphrase`: seen meanings in unseen phrasings."
            if "heldout" in final
            else ""
        )
    if progress:
        last = progress[-1]
        lines.append(
            f"\nTraining speed: {last['steps_per_s']:.0f} steps/s; {int(last['updates']):,} "
            "updates."
        )
    lines += ["", "Files: config.json, progress.csv, eval.csv, checkpoints/ (latest.json)."]
    path = run / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


if __name__ == "__main__":
    print(write_report(sys.argv[1]))

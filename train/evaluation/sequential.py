"""Sequential training over task groups, with forgetting measured (``sequential.stages``).

The run trains its stages one after another, ``total_steps / len(stages)`` steps each; a
stage's training episodes draw instructions of its families only, and hindsight
relabelling names only their instructions. Every family of ``env.families`` is evaluated
(seen instructions) before the first stage and after each, which gives the success matrix
``R[s][t]`` (after stage ``s``, family ``t``) and, as in the continual-learning
literature (Lopez-Paz and Ranzato 2017; Chaudhry et al. 2018):

* **forgetting**: over the families trained before the last stage, the mean drop of their
  success from their best after any earlier stage to the end;
* **backward transfer**: the mean of ``R[last][t] - R[stage of t][t]`` over those families
  (negative: forgetting);
* **forward transfer**: the mean of ``R[s - 1][t] - R[init][t]`` over the families first
  trained in stage ``s > 0`` (what earlier stages gave a family before it was trained).

Mitigations: experience replay of earlier stages with a fixed memory budget
(``sequential.replay``) and EWC (``sequential.ewc``); per-task heads exist for task ids.
Writes ``sequential.json`` and ``sequential.png`` in the run folder (``lcrl report`` shows
the matrix).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.errors import LcrlError

FILE = "sequential.json"


def first_stage(stages: list[tuple[str, ...]], family: str) -> int | None:
    """The index of the first stage that trains ``family`` (None: none does)."""
    return next((i for i, fams in enumerate(stages) if family in fams), None)


def transfer_metrics(
    matrix: list[dict[str, float]], stages: list[tuple[str, ...]]
) -> dict[str, float]:
    """Forgetting, backward and forward transfer of a success matrix.

    Args:
        matrix: ``[init, after stage 0, after stage 1, ...]``, each ``{family: success}``.
        stages: the families of each stage.

    Returns:
        ``forgetting``, ``backward_transfer``, ``forward_transfer`` (NaN where no family
        qualifies) and ``final_mean`` (mean success over trained families at the end).
    """
    last = len(matrix) - 1  # the row after the last stage trained so far
    done = last  # stages trained
    trained = [f for f in dict.fromkeys(f for s in stages[:done] for f in s)]
    earlier = [f for f in trained if first_stage(stages, f) < done - 1]
    forgetting = [
        max(matrix[r][f] for r in range(1 + first_stage(stages, f), last)) - matrix[last][f]
        for f in earlier
    ]
    backward = [matrix[last][f] - matrix[1 + first_stage(stages, f)][f] for f in earlier]
    forward = [
        matrix[s][f] - matrix[0][f]  # row s: after stage s - 1
        for f in trained
        if (s := first_stage(stages, f)) > 0
    ]

    def mean(xs: list[float]) -> float:
        return float(np.mean(xs)) if xs else float("nan")

    return {
        "forgetting": mean(forgetting),
        "backward_transfer": mean(backward),
        "forward_transfer": mean(forward),
        "final_mean": mean([matrix[last][f] for f in trained]),
    }


def write(out: Path, payload: dict[str, Any]) -> Path:
    """``sequential.json`` and the matrix as ``sequential.png`` in the run folder."""
    path = out / FILE
    path.write_text(json.dumps(payload, indent=1))
    plot(out / "sequential.png", payload)
    return path


def plot(path: Path, payload: dict[str, Any]) -> None:
    """A heat map of the success matrix (rows: before training, after each stage)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families, rows = payload["families"], payload["rows"]
    values = np.array([[r["success"][f] for f in families] for r in rows])
    fig, ax = plt.subplots(figsize=(1.2 * len(families) + 2.5, 0.5 * len(rows) + 1.8))
    ax.imshow(values, vmin=0, vmax=1, cmap="viridis", aspect="auto")
    for i in range(len(rows)):
        for j in range(len(families)):
            v = values[i, j]
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="w" if v < 0.6 else "k")
    ax.set_xticks(range(len(families)), families)
    ax.set_yticks(range(len(rows)), [r["after"] for r in rows])
    m = payload["metrics"]
    ax.set_title(
        f"forgetting {m['forgetting']:.2f}, BWT {m['backward_transfer']:.2f}, "
        f"FWT {m['forward_transfer']:.2f}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def read(run: Path) -> dict[str, Any] | None:
    """A run's ``sequential.json`` (None when it has none)."""
    path = Path(run) / FILE
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise LcrlError(f"{path} is not valid JSON ({e})") from None


def markdown(payload: dict[str, Any]) -> str:
    """The matrix and metrics as a Markdown section of report.md."""
    families = payload["families"]
    lines = [
        "## Sequential stages",
        "",
        "Stages: "
        + " -> ".join("+".join(s) for s in payload["stages"])
        + f"; replay {payload['replay']} transitions, EWC weight {payload['ewc']}.",
        "",
        "| after | " + " | ".join(families) + " |",
        "|---|" + "---:|" * len(families),
    ]
    for r in payload["rows"]:
        lines.append(
            f"| {r['after']} | " + " | ".join(f"{r['success'][f]:.2f}" for f in families) + " |"
        )
    m = payload["metrics"]
    lines += [
        "",
        f"Forgetting {m['forgetting']:.3f}, backward transfer {m['backward_transfer']:.3f}, "
        f"forward transfer {m['forward_transfer']:.3f}, final mean {m['final_mean']:.3f}.",
        "",
    ]
    return "\n".join(lines)

"""The figures of runs and evaluations: learning curves, success bars, slot heatmaps, task
bars and chains."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from train.evaluation.run_logs import _config, _read, _sets_of

SET_STYLES = {"train": "-", "all": "-", "heldout": "--", "paraphrase": ":", "custom": "-."}


SET_LABELS = {
    "train": "seen instructions",
    "heldout": "held-out combinations",
    "paraphrase": "unseen phrasings",
    "custom": "instruction file",
    "all": "environment goals",
}


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

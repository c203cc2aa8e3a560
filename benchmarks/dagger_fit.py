"""How well a DAgger student fits its own dataset: by chain link and by the round a row came from.

    python -m benchmarks.dagger_fit                          # the robosuite-camera student
    python -m benchmarks.dagger_fit --run runs/rc-aug/student --rows 40000

``lcrl distill`` keeps every labelled state it gathered in its checkpoint. This reads the
final checkpoint of a run, acts with its student on a sample of those rows and scores the
squared distance to the teacher's label (policy units, summed over the action's
dimensions, as :mod:`benchmarks.chain_probe` does on fresh episodes). Two splits:

``link``
    the instruction of a chain the row belongs to: 0 the first after a reset, 1 the one
    after it in the same scene, and so on. The dataset stores no link; a row starts a
    later link where its episode's first observation changes and the new first
    observation's gripper is within 5 cm of the previous row's (a reset moves the arm
    home; a switch in place leaves it where it was: the two are centimetres or tens of
    centimetres apart);
``round``
    the DAgger round that gathered the row (from ``progress.csv``'s cumulative ``rows``).
    A row of an early round has been in hundreds of minibatches; one of the last round in
    about one. The error on the newest rows is the nearest the dataset gets to the error
    on states the student has not seen.

Writes ``benchmarks/results/dagger-fit.{json,md,png}``. Headline: ``error_first_link``,
``error_later_links``, ``error_oldest_rounds`` (the first tenth of the rounds),
``error_newest_round``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import machine, new_figure, publish

NAME = "dagger-fit"
RUN = "runs/rc-aug/student"
#: A later link's first gripper position is this close to the previous row's (metres).
SWITCH_DISTANCE = 0.05


def chain_links(initial: np.ndarray, observation: np.ndarray) -> np.ndarray:
    """The chain link of every row (0: the first instruction after a reset)."""
    n = len(initial)
    starts = np.flatnonzero(np.r_[True, np.any(initial[1:] != initial[:-1], axis=1)])
    moved = np.linalg.norm(initial[starts[1:], :3] - observation[starts[1:] - 1, :3], axis=1)
    in_place = np.r_[False, moved < SWITCH_DISTANCE]
    links = np.zeros(n, np.int64)
    ends = np.r_[starts[1:], n]
    link = 0
    for start, end, same_scene in zip(starts, ends, in_place, strict=True):
        link = link + 1 if same_scene else 0
        links[start:end] = link
    return links


def row_rounds(run: Path, n: int) -> np.ndarray:
    """The DAgger round (1-based) that gathered each of the ``n`` rows."""
    with (run / "progress.csv").open() as f:
        ends = {int(float(r["step"])): int(float(r["rows"])) for r in csv.DictReader(f)}
    bounds = np.array([ends[k] for k in sorted(ends)])
    if bounds[-1] != n:
        raise SystemExit(f"{run}/progress.csv ends at {bounds[-1]} rows, the checkpoint has {n}")
    return np.searchsorted(bounds, np.arange(n), side="right") + 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", default=RUN, help="an lcrl distill run with its checkpoint")
    parser.add_argument("--rows", type=int, default=40_000, help="rows sampled")
    parser.add_argument("--seed", type=int, default=0, help="the sample's seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args(argv)

    import torch

    from train.evaluation.evaluate import resolve_checkpoint
    from train.policies.loading import load_policy

    torch.set_num_threads(args.threads)
    run = Path(args.run)
    ckpt = resolve_checkpoint(str(run))
    data = np.load(Path(ckpt) / "arrays.npz")
    if "data_action" not in data.files:
        raise SystemExit(f"{ckpt} keeps no dataset: give an lcrl distill run")
    policy = load_policy(ckpt)
    obs_keys = [
        k.removeprefix("data_") for k in data.files if k not in ("data_action", "data_goal")
    ]
    initial, observation = data["data_initial"], data["data_observation"]
    n = len(initial)
    links, rounds = chain_links(initial, observation), row_rounds(run, n)
    newest = np.flatnonzero(rounds == rounds.max())  # every row of the last round
    rng = np.random.default_rng(args.seed)
    sample = rng.choice(n, min(args.rows, n), replace=False)
    idx = np.union1d(sample, newest)
    goal = data["data_goal"][idx]
    errors = []
    for lo in range(0, len(idx), 4096):
        part = idx[lo : lo + 4096]
        obs = {k: data[f"data_{k}"][part] for k in obs_keys}
        act = policy.agent.act(obs, goal[lo : lo + 4096], deterministic=True)
        errors.append(np.sum((act - data["data_action"][part]) ** 2, axis=1))
    err = np.concatenate(errors)
    family = np.array([policy.task.table[g].split()[0] for g in goal])
    link, rnd = links[idx], rounds[idx]
    last = int(rounds.max())
    # the sample alone for every split but the last round's (scored whole)
    sampled = np.isin(idx, sample)

    def stat(mask: np.ndarray, whole_round: bool = False) -> dict[str, Any]:
        mask = mask if whole_round else mask & sampled
        return {"error": float(err[mask].mean()) if mask.any() else None, "rows": int(mask.sum())}

    by_link = {int(k): stat(link == k) for k in np.unique(link)}
    by_family = {
        f: {int(k): stat((link == k) & (family == f)) for k in (0, 1)} for f in np.unique(family)
    }
    tenth = max(1, last // 10)
    by_round = {
        f"{lo}-{min(lo + tenth - 1, last)}": {
            int(k): stat((rnd >= lo) & (rnd < lo + tenth) & (link == k)) for k in (0, 1)
        }
        for lo in range(1, last + 1, tenth)
    }
    headline = {
        "error_first_link": stat(link == 0)["error"],
        "error_later_links": stat(link > 0)["error"],
        "error_oldest_rounds": stat(rnd <= tenth)["error"],
        "error_newest_round": stat(rnd == last, whole_round=True)["error"],
        "run": args.run,
        "rounds": last,
        "dataset_rows": n,
        "later_link_share": float((links > 0).mean()),
    }
    payload = {
        "headline": headline,
        "machine": machine(),
        "settings": vars(args),
        "links": by_link,
        "families": by_family,
        "rounds": by_round,
    }

    def cell(s: dict[str, Any]) -> str:
        return "-" if s["error"] is None else f"{s['error']:.3f} ({s['rows']})"

    lines = ["| rows | first instruction | later in a chain |", "|---|---|---|"]
    lines.append(f"| all | {cell(stat(link == 0))} | {cell(stat(link > 0))} |")
    for f, s in by_family.items():
        lines.append(f"| {f} | {cell(s[0])} | {cell(s[1])} |")
    for r, s in by_round.items():
        lines.append(f"| rounds {r} | {cell(s[0])} | {cell(s[1])} |")
    newest_cells = [cell(stat((rnd == last) & m, whole_round=True)) for m in (link == 0, link > 0)]
    lines.append(f"| round {last}, every row | " + " | ".join(newest_cells) + " |")
    body = (
        f"The final student of `{args.run}` ({last} rounds, {n:,} labelled states, "
        f"{headline['later_link_share']:.0%} of them later instructions of a chain) on "
        f"{len(sample):,} of its own rows drawn at random, and every row of its last round. "
        "Error: the mean squared distance between the "
        "student's action and the teacher's label (policy units, summed over the action's "
        "dimensions), with the rows scored in brackets.\n\n" + "\n".join(lines)
    )
    fig, ax = new_figure(figsize=(6, 3.5))
    mids = [int(r.split("-")[0]) for r in by_round]
    for k, label in ((0, "first instruction"), (1, "second in a chain")):
        ax.plot(mids, [s[k]["error"] for s in by_round.values()], marker="o", label=label)
    ax.set(xlabel="DAgger round that gathered the row", ylabel="action error", title=args.run)
    ax.legend(fontsize=8)
    publish(NAME, payload, "A DAgger student on its own dataset", body, fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

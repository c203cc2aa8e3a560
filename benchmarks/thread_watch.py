"""A run's torch threads when another busy run starts beside it: chosen again, or fixed.

    python -m benchmarks.thread_watch                 # lang2d, 2 cores
    python -m benchmarks.thread_watch --warmup-steps 3000 --overlap-steps 3000

A run started on an idle 2-core machine takes both cores as torch threads. When another
run starts beside it, two threads on one free core collapse (``docs/scale.md``). With
``--torch-threads 0`` (the default), :class:`train.runtime.machine.ThreadWatcher` reads
the load every 20 s and gives a core back; ``--torch-threads 2`` keeps both.

Each arm starts ``lcrl train PRESET`` alone (``main``), waits until it has trained
``--warmup-steps``, then starts a second run of the same preset with one torch thread
(``other``), as a user who starts a second run would. The main run trains
``--overlap-steps`` more with the other beside it; then the other is stopped and the
main run trains ``--after-steps`` more alone. The benchmark reads both runs'
``progress.csv`` every half second, so steps per second are measured per phase from the
wall clock. Arms:

``watched``
    the main run with ``--torch-threads 0`` and neither ``OMP_NUM_THREADS`` nor
    ``LCRL_PROCESSES`` set: it chooses its threads, and chooses them again;
``fixed``
    the main run with ``--torch-threads 2``.

Writes ``benchmarks/results/thread_watch.{json,md,png}``. Headline: ``watched_overlap``
and ``fixed_overlap`` (the main run's steps per second while the other runs),
``overlap_ratio`` (watched / fixed), ``watched_other`` and ``fixed_other`` (the other
run's), ``watched_after`` and ``fixed_after`` (the main run alone again).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from benchmarks.common import (
    LCRL,
    RESULTS_DIR,
    add_report_only,
    die_with_parent,
    machine,
    new_figure,
    publish,
)

NAME = "thread_watch"
ROOT = Path("runs/bench/thread-watch")
#: What the main run starts with, by arm.
ARMS = {"watched": "0", "fixed": "2"}


def _env() -> dict[str, str]:
    """A user's shell: nothing that fixes the threads."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "LCRL_PROCESSES")}
    env.pop("MKL_NUM_THREADS", None)
    return env


def _last(path: Path) -> dict[str, str] | None:
    """The last row of a progress.csv (None before the first)."""
    if not path.exists():
        return None
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else None


def _start(preset: str, out: Path, threads: str, steps: int, seed: int) -> subprocess.Popen:
    shutil.rmtree(out, ignore_errors=True)
    argv = [*LCRL, "train", preset, "--out", str(out), "--total-steps", str(steps)]
    argv += ["--seed", str(seed), "--torch-threads", threads, "--eval-every", "0"]
    argv += ["--log-every", "250", "--checkpoint-every", "0", "--no-progress", "--no-tensorboard"]
    with (out.parent / f"{out.name}.log").open("w") as log:  # the child keeps its own copy
        return subprocess.Popen(
            argv, stdout=log, stderr=subprocess.STDOUT, env=_env(), preexec_fn=die_with_parent
        )


def arm(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """One arm: the main run's (and the other's) steps over wall-clock time, per phase."""
    main_out, other_out = ROOT / f"{name}-main", ROOT / f"{name}-other"
    total = args.warmup_steps + args.overlap_steps + args.after_steps
    main = _start(args.preset, main_out, ARMS[name], total, 0)
    other: subprocess.Popen | None = None
    trace: list[dict[str, Any]] = []
    phase, t0, stop_at = "alone", time.monotonic(), args.warmup_steps + args.overlap_steps
    try:
        while main.poll() is None:
            time.sleep(0.5)
            row, other_row = _last(main_out / "progress.csv"), _last(other_out / "progress.csv")
            if row is None:
                continue
            step = int(float(row["step"]))
            trace.append(
                {
                    "t": time.monotonic() - t0,
                    "phase": phase,
                    "step": step,
                    "threads": int(float(row.get("torch_threads") or 0)),
                    "other_step": int(float(other_row["step"])) if other_row else 0,
                }
            )
            if phase == "alone" and step >= args.warmup_steps:
                other = _start(args.preset, other_out, "1", 10**7, 1)
                phase = "overlap"
            elif phase == "overlap" and step >= stop_at:
                other.send_signal(signal.SIGINT)
                other.wait(timeout=60)
                phase = "after"
        if main.returncode != 0:
            raise SystemExit(f"{main_out}: lcrl train failed; see {main_out}.log")
    finally:
        for p in (main, other):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                p.wait(timeout=60)

    return summarise({"main_threads": ARMS[name], "trace": trace})


def summarise(result: dict[str, Any]) -> dict[str, Any]:
    """An arm's steps per second per phase, from its trace. The main run's last phase ends
    at its last step: the final evaluation after it trains nothing."""
    trace = result["trace"]
    last = max((r["step"] for r in trace), default=0)
    end = next((i for i, r in enumerate(trace) if r["step"] >= last), len(trace) - 1)

    def rate(phase: str, key: str = "step") -> float | None:
        rows = [r for r in trace[: end + 1] if r["phase"] == phase]
        if key == "other_step":
            rows = [r for r in rows if r["other_step"] > 0]
        if len(rows) < 2 or rows[-1]["t"] <= rows[0]["t"]:
            return None
        return (rows[-1][key] - rows[0][key]) / (rows[-1]["t"] - rows[0]["t"])

    return {
        "main_threads": result["main_threads"],
        "alone": rate("alone"),
        "overlap": rate("overlap"),
        "other": rate("overlap", "other_step"),
        "after": rate("after"),
        "threads_seen": sorted({r["threads"] for r in trace if r["threads"]}),
        "trace": trace,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="lang2d")
    parser.add_argument("--warmup-steps", type=int, default=3000, help="main run alone")
    parser.add_argument("--overlap-steps", type=int, default=3000, help="the other beside it")
    parser.add_argument("--after-steps", type=int, default=2000, help="alone again")
    parser.add_argument("--arms", nargs="+", choices=sorted(ARMS), default=list(ARMS))
    add_report_only(parser, "the traces in benchmarks/results/thread_watch.json")
    args = parser.parse_args(argv)
    ROOT.mkdir(parents=True, exist_ok=True)
    results, kept = {}, {}
    if args.report_only:  # the measured traces again, with this version's arithmetic
        kept = json.loads((RESULTS_DIR / f"{NAME}.json").read_text())
        args = argparse.Namespace(**{**vars(args), **kept["settings"], "report_only": True})
    for name in args.arms:
        print(f"== {name}", flush=True)
        results[name] = summarise(kept["arms"][name]) if kept else arm(name, args)
        r = results[name]
        print(f"   alone {r['alone']}, beside another {r['overlap']} (other {r['other']}), "
              f"after {r['after']}", flush=True)  # fmt: skip

    def fig_rate(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f}"

    headline: dict[str, Any] = {"preset": args.preset}
    for name, r in results.items():
        headline[f"{name}_overlap"] = r["overlap"]
        headline[f"{name}_other"] = r["other"]
        headline[f"{name}_after"] = r["after"]
    if results.get("watched", {}).get("overlap") and results.get("fixed", {}).get("overlap"):
        headline["overlap_ratio"] = results["watched"]["overlap"] / results["fixed"]["overlap"]
    settings = {k: v for k, v in vars(args).items() if k != "report_only"}
    payload = {"headline": headline, "machine": machine(), "settings": settings, "arms": results}
    if kept:
        payload.update(machine=kept["machine"], command=kept["command"], git=kept["git"])
        payload["date"] = kept["date"]
    lines = [
        "| main run | alone | beside another run | the other run | alone again | threads it used |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} (`--torch-threads {r['main_threads']}`) | {fig_rate(r['alone'])} | "
            f"{fig_rate(r['overlap'])} | {fig_rate(r['other'])} | {fig_rate(r['after'])} | "
            f"{', '.join(map(str, r['threads_seen']))} |"
        )
    body = (
        f"`lcrl train {args.preset}` alone for {args.warmup_steps:,} steps, then beside a "
        f"second `{args.preset}` run with one torch thread for {args.overlap_steps:,} steps, "
        f"then alone for {args.after_steps:,}. Environment steps per second from the wall "
        "clock, per phase (read from both runs' progress.csv every half second).\n\n"
        + "\n".join(lines)
    )
    fig, ax = new_figure(figsize=(7, 3.8))
    for name, r in results.items():
        tr = r["trace"]
        (line,) = ax.plot([p["t"] for p in tr], [p["step"] for p in tr], label=f"main run, {name}")
        beside = [p["t"] for p in tr if p["phase"] == "overlap"]
        if beside:  # the other run's time beside it, shaded in the arm's colour
            ax.axvspan(min(beside), max(beside), color=line.get_color(), alpha=0.12)
    ax.set(xlabel="seconds", ylabel="main run's environment steps", title=args.preset)
    ax.legend(fontsize=8, title="shaded: another run beside it", title_fontsize=8)
    publish(NAME, payload, "Torch threads chosen again when another run starts", body, fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``--agent.compile`` and ``--agent.precision bf16`` on the CPU: the SAC update of
``lang2d``, eager float32 against compiled and against bfloat16 autocast.

    python benchmarks/compiled_update.py

Three agents with the same networks, seed and buffer (a ``lang2d`` trainer after its
random steps): one eager, one whose networks went through ``torch.compile``
(``Agent.compile_networks``), one eager whose updates run in bf16
(``AgentOptions.precision``). Their updates (``agent.update(buffer.sample(256))``) are
timed alternately, ``--rounds`` times, at each thread count, alone on the machine; the
compile time (the first updates) is reported apart.

Writes ``benchmarks/results/compiled_update.{json,md,png}``; ``headline.speedup_<n>_threads``
is eager ms / compiled ms, ``headline.bf16_speedup_<n>_threads`` eager ms / bf16 ms.
"""

from __future__ import annotations

import argparse
import statistics
import time

from benchmarks.common import (
    machine,
    new_figure,
    publish,
)
from benchmarks.loop_bound import discard, trainer

NAME = "compiled_update"


def update_ms(t: object, agent: object, updates: int) -> float:
    """Milliseconds per ``agent.update(buffer.sample(batch))``."""
    batch = t.cfg.batch_size
    t0 = time.perf_counter()
    for _ in range(updates):
        agent.update(t.buffer.sample(batch))
    return (time.perf_counter() - t0) / updates * 1000


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=200, help="timed updates per round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import copy
    import dataclasses

    import torch

    t = trainer(1, 0, 2000, args.seed)
    eager = t.agent
    compiled = copy.deepcopy(eager)
    t0 = time.perf_counter()
    compiled.compile_networks()
    for _ in range(3):
        compiled.update(t.buffer.sample(t.cfg.batch_size))
    compile_s = time.perf_counter() - t0
    print(f"compiled in {compile_s:.1f} s", flush=True)
    bf16 = copy.deepcopy(eager)
    bf16.options = dataclasses.replace(bf16.options, precision="bf16")

    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for agent in (eager, compiled, bf16):  # warm up at this thread count
            update_ms(t, agent, 10)
        e_ms, c_ms, b_ms = [], [], []
        for _ in range(args.rounds):
            e_ms.append(update_ms(t, eager, args.updates))
            c_ms.append(update_ms(t, compiled, args.updates))
            b_ms.append(update_ms(t, bf16, args.updates))
        row = {
            "threads": threads,
            "eager_ms": statistics.median(e_ms),
            "compiled_ms": statistics.median(c_ms),
            "bf16_ms": statistics.median(b_ms),
            "eager_rounds": e_ms,
            "compiled_rounds": c_ms,
            "bf16_rounds": b_ms,
        }
        row["speedup"] = row["eager_ms"] / row["compiled_ms"]
        row["bf16_speedup"] = row["eager_ms"] / row["bf16_ms"]
        rows.append(row)
        print(
            f"threads {threads}: eager {row['eager_ms']:.2f} ms, compiled "
            f"{row['compiled_ms']:.2f} ms (x{row['speedup']:.2f}), bf16 {row['bf16_ms']:.2f} "
            f"ms (x{row['bf16_speedup']:.2f})",
            flush=True,
        )
    discard(t)

    info = machine()
    headline = {f"speedup_{r['threads']}_threads": r["speedup"] for r in rows}
    headline.update({f"eager_ms_{r['threads']}_threads": r["eager_ms"] for r in rows})
    headline.update({f"compiled_ms_{r['threads']}_threads": r["compiled_ms"] for r in rows})
    headline.update({f"bf16_speedup_{r['threads']}_threads": r["bf16_speedup"] for r in rows})
    headline.update({f"bf16_ms_{r['threads']}_threads": r["bf16_ms"] for r in rows})
    headline["compile_s"] = compile_s
    payload = {"headline": headline, "machine": info, "settings": vars(args), "rows": rows}
    lines = [
        "| torch threads | eager ms | compiled ms | speed-up | bf16 ms | speed-up |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['threads']} | {r['eager_ms']:.2f} | {r['compiled_ms']:.2f} | "
            f"{r['speedup']:.2f}x | {r['bf16_ms']:.2f} | {r['bf16_speedup']:.2f}x |"
        )
    body = (
        "SAC update of the `lang2d` networks (batch 256), eager float32 against "
        "`--agent.compile` and against `--agent.precision bf16` (bfloat16 autocast); "
        f"compiling took {compile_s:.0f} s (the first updates).\n\n" + "\n".join(lines)
    )

    fig, ax = new_figure(figsize=(5, 3.5))
    x = range(len(rows))
    ax.bar([i - 0.27 for i in x], [r["eager_ms"] for r in rows], 0.27, label="eager fp32")
    ax.bar(list(x), [r["compiled_ms"] for r in rows], 0.27, label="compiled")
    ax.bar([i + 0.27 for i in x], [r["bf16_ms"] for r in rows], 0.27, label="bf16")
    ax.set_xticks(list(x), [f"{r['threads']} thread(s)" for r in rows])
    ax.set(ylabel="ms per update", title="lang2d SAC update, CPU")
    ax.legend()
    title = "torch.compile and bf16 on the CPU (lang2d update)"
    publish(NAME, payload, title, body, fig, rect=(0, 0.1, 1, 1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

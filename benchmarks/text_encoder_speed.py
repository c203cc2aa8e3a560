"""Speed of the frozen text encoder: model forward vs in-memory cache vs on-disk cache.

Run from the repository root:

    python benchmarks/text_encoder_speed.py

Encodes ~300 distinct instruction-like strings three ways:

* cold: every text goes through the model forward pass (no disk cache);
* warm, in memory: the same instance again, every text is a dictionary hit;
* warm, on disk: a fresh instance sharing a SQLite cache folder (in a temp dir) that another
  instance filled, so every text is read from disk and none is encoded.

Each measurement is repeated (the cold and disk ones after ``clear_cache()``) and the median
is reported. Model loading is not timed. Results go to
``benchmarks/results/text_encoder_speed.json`` and ``.md``.
"""

import datetime
import itertools
import os
import platform
import shlex
import statistics
import sys
import tempfile
import time

import numpy as np
import torch

from benchmarks.common import RESULTS_DIR, save_json
from lcrl.text_encoder import DEFAULT_TEXT_ENCODER, FrozenTextEncoder

REPEATS = 5


def make_instructions() -> list[str]:
    """About 300 distinct tabletop instructions."""
    verbs = ["push", "lift", "reach", "move"]
    colours = ["red", "green", "blue", "yellow"]
    shapes = ["cube", "cylinder"]
    directions = [
        "to the left",
        "to the right",
        "forward",
        "backward",
        "behind the red cube",
        "in front of the green cylinder",
        "next to the blue cube",
        "towards the yellow cylinder",
        "a little",
        "",
    ]
    texts = []
    for verb, colour, shape, direction in itertools.product(verbs, colours, shapes, directions):
        texts.append(" ".join(w for w in (verb, "the", colour, shape, direction) if w))
    assert len(set(texts)) == len(texts)
    return texts


def time_encode(encoder: FrozenTextEncoder, texts: list[str], clear: bool) -> list[float]:
    """Seconds for ``encoder.encode(texts)``, ``REPEATS`` times."""
    times = []
    for _ in range(REPEATS):
        if clear:
            encoder.clear_cache()
        start = time.perf_counter()
        encoder.encode(texts)
        times.append(time.perf_counter() - start)
    return times


def machine() -> dict[str, object]:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numpy": np.__version__,
        "load_average_1m_at_start": round(os.getloadavg()[0], 2)
        if hasattr(os, "getloadavg")
        else None,
    }


def main() -> None:
    texts = make_instructions()
    n = len(texts)
    rows: dict[str, dict[str, float]] = {}

    cold = FrozenTextEncoder()
    cold_times = time_encode(cold, texts, clear=True)
    assert cold.num_encoded == REPEATS * n
    reference = cold.encode(texts)
    warm_times = time_encode(cold, texts, clear=False)
    assert cold.num_encoded == REPEATS * n  # all hits

    with tempfile.TemporaryDirectory() as tmp:
        filler = FrozenTextEncoder(cache_dir=tmp)
        filler.encode(texts)
        fresh = FrozenTextEncoder(cache_dir=tmp)
        disk_times = time_encode(fresh, texts, clear=True)
        assert fresh.num_encoded == 0
        assert np.array_equal(fresh.encode(texts), reference)

    cold_s = statistics.median(cold_times)
    for name, times in [
        ("cold (model forward)", cold_times),
        ("warm, in-memory cache", warm_times),
        ("warm, on-disk cache (fresh instance)", disk_times),
    ]:
        med = statistics.median(times)
        rows[name] = {
            "seconds_total": med,
            "seconds_best": min(times),
            "seconds_all_runs": times,
            "texts_per_second": n / med,
            "microseconds_per_text": 1e6 * med / n,
            "speedup_vs_cold": cold_s / med,
        }

    header = "| mode | median total (ms) | best (ms) | texts/s | µs/text | speed-up vs cold |"
    lines = [header, "|---|---:|---:|---:|---:|---:|"]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {1e3 * r['seconds_total']:.2f} | {1e3 * r['seconds_best']:.2f} | "
            f"{r['texts_per_second']:,.0f} | "
            f"{r['microseconds_per_text']:.1f} | {r['speedup_vs_cold']:,.1f}x |"
        )
    table = "\n".join(lines)

    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    info = machine()
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    result = {
        "benchmark": "text_encoder_speed",
        "command": command,
        "date_utc": date,
        "machine": info,
        "model": DEFAULT_TEXT_ENCODER,
        "model_key": cold.model_key,
        "device": cold.config.device,
        "batch_size": cold.config.batch_size,
        "num_texts": n,
        "repeats": REPEATS,
        "statistic": "median over repeats (best also given); model loading not timed",
        "results": rows,
    }
    print(f"{n} distinct texts, median of {REPEATS} runs, {DEFAULT_TEXT_ENCODER} on cpu\n")
    print(table)

    os.makedirs(RESULTS_DIR, exist_ok=True)
    result["headline"] = {
        f"{name}_texts_per_s": round(r["texts_per_second"]) for name, r in rows.items()
    }
    save_json("text_encoder_speed", result)
    machine_lines = "\n".join(f"- {k}: {v}" for k, v in info.items())
    md = (
        "# Text encoder speed\n\n"
        f"Command: `{command}`\n\n"
        f"Date (UTC): {date}\n\n"
        f"Machine:\n\n{machine_lines}\n\n"
        f"Model: `{DEFAULT_TEXT_ENCODER}` on {cold.config.device}, "
        f"batch_size {cold.config.batch_size}. {n} distinct instruction strings, "
        f"median of {REPEATS} runs; model loading not timed. Cold: every text through the "
        "model forward pass. Warm in-memory: the same instance again. Warm on-disk: a fresh "
        "instance reading a SQLite cache another instance filled (no forward pass). "
        "texts/s, µs/text and speed-ups use the median. On a shared machine the cold time "
        "varies run to run with other load (see the load average above).\n\n"
        f"{table}\n"
    )
    with open(os.path.join(RESULTS_DIR, "text_encoder_speed.md"), "w") as fh:
        fh.write(md)
    print(f"\nwrote {RESULTS_DIR}/text_encoder_speed.json and .md")


if __name__ == "__main__":
    main()

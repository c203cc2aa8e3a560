"""Stopping a benchmark stops the runs it started: children die with their parent."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

PARENT = textwrap.dedent(
    """
    import subprocess, sys, time
    sys.path.insert(0, {root!r})
    from benchmarks.common import die_with_parent
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(60)"], preexec_fn=die_with_parent
    )
    print(child.pid, flush=True)
    time.sleep(60)
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers; its state says it is gone
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().split()[2] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_started_by_a_benchmark_dies_with_it():
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT.format(root=str(ROOT))], stdout=subprocess.PIPE, text=True
    )
    child = int(parent.stdout.readline())
    assert _alive(child)
    parent.kill()  # SIGKILL: no handler of the parent's runs
    parent.wait()
    deadline = time.monotonic() + 10
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(child)


def _trainer_threads() -> int:
    """What a trainer that is not told its threads takes (``--torch-threads 0``)."""
    from train.runtime.machine import set_threads

    return set_threads(0)


def test_a_pool_worker_that_trains_beside_others_keeps_one_thread():
    """A trainer in a benchmark's worker process keeps the worker's one thread: it no
    longer takes both cores because the other worker happened to be idle as it started."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from benchmarks.common import one_thread_worker

    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx, initializer=one_thread_worker) as pool:
        assert pool.submit(_trainer_threads).result(timeout=120) == 1


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ("fpu sse2 avx avx2 fma", "avx2"),
        ("avx2 avx512f avx512bw", "avx512"),
        ("avx2 avx512f avx512_bf16", "avx512, bf16"),
        ("fpu sse2", ""),
    ],
)
def test_result_files_name_the_cpu_s_vector_instructions(tmp_path, flags, expected):
    """The machine line says which vector instructions the figures had."""
    from train.runtime.machine import cpu_features, machine_line

    info = tmp_path / "cpuinfo"
    info.write_text(f"processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: {flags}\n")
    assert cpu_features(str(info)) == expected
    assert cpu_features(str(tmp_path / "missing")) == ""
    line = machine_line(
        {
            "cpu": "AMD EPYC",
            "cpu_features": expected,
            "cores": 2,
            "memory_gib": 23.5,
            "python": "3.11",
            "torch": "2.13.0",
            "torch_threads": 1,
            "date": "2026-12-06",
        }
    )
    assert line.startswith(f"AMD EPYC ({expected}), 2 cores" if expected else "AMD EPYC, 2 cores")

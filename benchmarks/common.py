"""Shared helpers of the learning and speed benchmarks: machine description, results files."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

import torch

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def command() -> str:
    """The command line that ran this benchmark."""
    return "python " + " ".join(shlex.quote(a) for a in sys.argv)


def machine() -> dict[str, Any]:
    """CPU, cores, memory, Python and torch versions, GPU if any."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gib = None
    try:
        with open("/proc/meminfo") as f:
            mem_gib = round(int(f.readline().split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gib,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def machine_line(info: dict[str, Any]) -> str:
    """One-line machine description for figure captions and tables."""
    gpu = f", {info['gpu']}" if "gpu" in info else ""
    return (
        f"{info['cpu']}, {info['cores']} cores, {info['memory_gib']} GiB{gpu}; "
        f"Python {info['python']}, torch {info['torch']} ({info['torch_threads']} threads); "
        f"{info['date']}"
    )


def save_json(name: str, payload: dict[str, Any]) -> Path:
    """Write ``results/<name>.json``."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    path.write_text(json.dumps(payload, indent=1))
    return path


def save_markdown(name: str, title: str, body: str, info: dict[str, Any]) -> Path:
    """Write ``results/<name>.md`` with the command and machine above ``body``."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.md"
    path.write_text(
        f"# {title}\n\nCommand: `{command()}`\n\nMachine: {machine_line(info)}\n\n{body}\n"
    )
    return path


def caption(fig: Any, info: dict[str, Any]) -> None:
    """Put the command and machine under a matplotlib figure."""
    fig.text(0.01, 0.01, f"{command()}\n{machine_line(info)}", fontsize=6, va="bottom")


def save_figure(name: str, fig: Any, info: dict[str, Any]) -> Path:
    """Caption a matplotlib figure with the command and machine, write
    ``results/<name>.png`` and close it."""
    import matplotlib.pyplot as plt

    caption(fig, info)
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path

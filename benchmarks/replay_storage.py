"""``--buffer.storage device`` against host storage: the time to sample a batch of camera
frames and have it on the learner's device.

    python benchmarks/replay_storage.py                 # the learner on this CPU
    python benchmarks/replay_storage.py --device cuda   # where a GPU is lent

Two replay buffers with the same seed and the same stored episodes (64x64 RGB frames and
a 40-dimensional state, as the robosuite image presets store them): one keeps its
observations as numpy arrays in host memory (the default), the other as torch tensors on
``--device``. Each round samples ``--batches`` batches of ``--batch-size`` from each,
alternately, and moves every observation of the batch (``obs`` and ``next_obs``) to the
learner's device as the learners do (``lcrl.algos.base.to_device``: pinned memory and an
asynchronous copy on CUDA); on CUDA the round ends with a synchronisation. Relabelling and
rewards are computed on the host by both.

Writes ``benchmarks/results/replay_storage.{json,md,png}``; ``headline.host_ms`` and
``headline.device_ms`` are the medians over rounds of the milliseconds per batch,
``headline.speedup`` their ratio.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.common import (
    machine,
    new_figure,
    publish,
)

NAME = "replay_storage"
FRAME = (64, 64, 3)
STATE = 40


def make_buffer(capacity: int, device: str | None, seed: int):
    from lcrl.buffer import HindsightReplayBuffer
    from lcrl.goals import StateGoals

    def reward(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return -(np.linalg.norm(achieved - desired, axis=-1) > 0.05).astype(np.float32)

    spec = {"observation": ((STATE,), np.float32), "image": (FRAME, np.uint8)}
    return HindsightReplayBuffer(
        capacity, spec, (7,), np.float32, StateGoals(3, reward), k=4, seed=seed, device=device
    )


def fill(buffers: list, capacity: int, steps: int, seed: int) -> int:
    """The same episodes of ``steps`` steps into every buffer, until they are full."""
    rng = np.random.default_rng(seed)
    episodes = 0
    while (episodes + 1) * (steps + 1) <= capacity:
        ep = {
            "obs": {
                "observation": rng.normal(size=(steps + 1, STATE)).astype(np.float32),
                "image": rng.integers(0, 256, (steps + 1, *FRAME), dtype=np.uint8),
            },
            "action": rng.uniform(-1, 1, (steps, 7)).astype(np.float32),
            "reward": np.zeros(steps, np.float32),
            "terminated": np.zeros(steps, bool),
            "achieved_goal": rng.normal(size=(steps + 1, 3)).astype(np.float32),
            "desired_goal": rng.normal(size=3).astype(np.float32),
        }
        for buf in buffers:
            buf.add_episode(ep)
        episodes += 1
    return episodes


def batch_ms(buf, device, batch_size: int, batches: int) -> float:
    """Milliseconds per batch sampled and moved to ``device``."""
    import torch

    from lcrl.algos.base import to_device

    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(batches):
        b = buf.sample(batch_size)
        moved = [to_device(v, device) for part in (b.obs, b.next_obs) for v in part.values()]
        moved.append(to_device(b.action, device))
    sync()
    return (time.perf_counter() - t0) / batches * 1000


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="the learner's device: cpu or cuda")
    parser.add_argument("--capacity", type=int, default=50_000, help="observation slots")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--batches", type=int, default=100, help="timed batches per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import torch

    from lcrl.algos.base import resolve_device
    from lcrl.errors import LcrlError

    try:
        device = resolve_device(args.device)
    except LcrlError as e:
        parser.error(str(e))
    torch.set_num_threads(args.threads)
    host = make_buffer(args.capacity, None, args.seed)
    dev = make_buffer(args.capacity, str(device), args.seed)
    t0 = time.perf_counter()
    episodes = fill([host, dev], args.capacity, 50, args.seed)
    print(f"filled {episodes} episodes in {time.perf_counter() - t0:.0f} s", flush=True)
    for buf in (host, dev):  # warm up
        batch_ms(buf, device, args.batch_size, 5)
    host_ms, dev_ms = [], []
    for r in range(args.rounds):
        host_ms.append(batch_ms(host, device, args.batch_size, args.batches))
        dev_ms.append(batch_ms(dev, device, args.batch_size, args.batches))
        print(f"round {r}: host {host_ms[-1]:.2f} ms, device {dev_ms[-1]:.2f} ms", flush=True)
    frames_gb = host.obs["image"].nbytes / 1e9
    headline = {
        "host_ms": statistics.median(host_ms),
        "device_ms": statistics.median(dev_ms),
        "device": str(device),
    }
    headline["speedup"] = headline["host_ms"] / headline["device_ms"]
    info = machine()
    payload = {
        "headline": headline,
        "machine": info,
        "settings": vars(args),
        "episodes": episodes,
        "frames_gb": frames_gb,
        "host_rounds_ms": host_ms,
        "device_rounds_ms": dev_ms,
    }
    where = "this CPU" if device.type == "cpu" else f"the GPU ({device})"
    body = (
        f"A batch of {args.batch_size} transitions sampled with hindsight relabelling "
        f"(k = 4) from {episodes} stored 50-step episodes ({args.capacity:,} slots; "
        f"{FRAME[0]}x{FRAME[1]} RGB frames, {frames_gb:.2f} GB of them, and a {STATE}-d "
        f"state), its observations and next observations then moved to the learner on "
        f"{where}; median of {args.rounds} alternating rounds of {args.batches} batches, "
        f"{args.threads} torch thread(s).\n\n"
        "| replay storage | ms per batch | rounds |\n|---|---:|---|\n"
        f"| host (numpy) | {headline['host_ms']:.2f} | "
        f"{', '.join(f'{x:.2f}' for x in host_ms)} |\n"
        f"| device ({device}) | {headline['device_ms']:.2f} | "
        f"{', '.join(f'{x:.2f}' for x in dev_ms)} |\n\n"
        f"Ratio host / device: {headline['speedup']:.2f}x."
    )
    if device.type == "cpu":
        body += (
            " On a CPU learner the device is host memory too, so storage on the device "
            "changes where the gather happens (torch instead of numpy) and nothing else: "
            "this row checks that the option costs nothing where it cannot help. Its gain "
            "is on CUDA, where a batch of frames is gathered in GPU memory instead of "
            "being copied over the bus; run it with `--device cuda` on a GPU machine."
        )

    fig, ax = new_figure(figsize=(5.5, 3.8))
    for i, vals in enumerate((host_ms, dev_ms)):
        ax.bar(i, statistics.median(vals), 0.6, color=f"C{i}")
        ax.scatter([i] * len(vals), vals, color="k", s=10, zorder=3)
    ax.set_xticks([0, 1], ["host (numpy)", f"device ({device})"])
    ax.set_ylabel("ms per batch (sample + move)")
    ax.set_title(f"batch {args.batch_size} of 64x64 frames, learner on {device}")
    title = "Replay storage on the learner's device"
    publish(NAME, payload, title, body, fig, rect=(0, 0.1, 1, 1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Ray rollout workers across the nodes of a real cluster: collection speed against the
8-environment local loop, learning against the local run on 3 seeds, and three faults.

    python -m benchmarks.ray_cluster

A two-node Ray cluster is started on this machine (``ray.cluster_utils.Cluster``: a head
node, where the learner runs, and a worker node with ``--worker-cpus`` CPUs). The rollout
workers are pinned to the worker node (``--collect.placement other-nodes``).

- **Collection** (``collect_speedup``): steps/s of collection alone (the policy acts;
  nothing is stored or updated) on ``lang2d``: the worker node's ``--workers`` workers
  against the local loop with 8 environments (``--collect.envs 8``).
- **Learning** (``seen_ratio``): ``lcrl train lang2d-quick`` on seeds 0, 1 and 2 (chosen
  before any run), once locally and once with the cluster's workers, same steps; each is
  evaluated with ``lcrl eval`` (``--episodes`` per set). The ratio is the mean seen
  success of the cluster runs over that of the local runs.
- **Faults** (``faults_survived``): on a ``lang2d-quick`` run with the cluster's workers,
  (1) a rollout worker's process is killed, (2) the whole worker node is removed, and
  (3) the learner (``lcrl train`` as a user runs it) gets SIGINT. Each is survived when
  nothing is lost: after (1) and (2) the run goes on and every stored episode is whole
  (the buffer holds exactly the steps counted); after (3) the run exits with its
  checkpoint saved, resumable, and no rollout worker is left running.

On two cores the learner, its workers and the cluster's processes share the same cores,
so ``collect_speedup`` is reported, not targeted (more than 1 needs cores the local loop
does not use).

Writes ``benchmarks/results/ray_cluster.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.common import LCRL, evaluate, machine, new_figure, publish, run_logged
from benchmarks.ray_collect import collection_config, local_rate, ray_rate

NAME = "ray_cluster"
SETS = ("train", "heldout", "paraphrase")
TARGETS = {"seen_ratio": 0.95, "faults_survived": 3}


def start_cluster(workers: int, worker_cpus: int) -> tuple[Any, Any]:
    """A head node (the learner's, with room for ``workers`` workers once the other node
    is gone) and a worker node of ``worker_cpus`` CPUs, on this machine."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True, head_node_args={"num_cpus": workers, "include_dashboard": False}
    )
    node = cluster.add_node(num_cpus=worker_cpus)
    cluster.wait_for_nodes()
    return cluster, node


def cluster_flags(address: str, workers: int) -> list[str]:
    """The ``lcrl train`` options of a run whose workers are the cluster's other nodes."""
    return [
        "--collect.backend", "ray", "--collect.workers", str(workers),
        "--collect.address", address, "--collect.placement", "other-nodes",
    ]  # fmt: skip


def collection(args: argparse.Namespace, address: str) -> dict[str, float]:
    """Steps/s of the 8-environment local loop and of the cluster's workers."""
    local, weights, table = local_rate(collection_config(args.seed, envs=8), args.seconds)
    cfg = collection_config(
        args.seed, backend="ray", workers=args.workers, address=address, placement="other-nodes"
    )
    remote = ray_rate(cfg, table, weights, args.seconds)
    return {"local8_steps_per_s": local, "cluster_steps_per_s": remote}


def learning(args: argparse.Namespace, address: str) -> dict[str, Any]:
    """Final success of ``lang2d-quick`` per seed, locally and with the cluster's workers."""
    work = Path(args.work)
    runs: dict[str, dict[str, Any]] = {"local": {}, "cluster": {}}
    for seed in args.seeds:
        for arm in runs:
            out = work / f"{arm}-s{seed}"
            if not (out / "final-eval.json").is_file():
                cmd = [*LCRL, "train", "lang2d-quick", "--out", str(out), "--seed", str(seed)]
                cmd += ["--agent.seed", str(seed), "--overwrite", "--no-progress"]
                cmd += ["--no-tensorboard", "--checkpoint-every", "0"]
                if arm == "cluster":
                    cmd += cluster_flags(address, args.workers)
                seconds = run_logged(cmd, out.with_suffix(".log"), f"{arm} seed {seed}")
                (work / f"{arm}-s{seed}.seconds").write_text(f"{seconds:.1f}")
                evaluate(out, args.episodes, SETS, env=dict(os.environ))
            result = json.loads((out / "final-eval.json").read_text())["sets"]
            seconds = float((work / f"{arm}-s{seed}.seconds").read_text())
            runs[arm][str(seed)] = {"sets": result, "seconds": seconds}
    return runs


def whole(trainer: Any) -> bool:
    """Every stored episode is whole: the buffer holds exactly the steps counted."""
    return trainer.buffer.size == trainer.step and trainer.episodes >= 1


def in_process_faults(cluster: Any, node: Any, args: argparse.Namespace) -> dict[str, Any]:
    """(1) a worker's process killed, then (2) the worker node removed, mid-run."""
    import ray

    from train.configs.config import CollectionConfig
    from train.configs.presets import PRESETS
    from train.training.loop import Trainer

    collect = CollectionConfig(
        backend="ray", workers=args.workers, address=cluster.address, placement="other-nodes"
    )
    cfg = dataclasses.replace(
        copy.deepcopy(PRESETS["lang2d-quick"][1]),
        out=str(Path(args.work) / "faults"),
        collect=collect,
        total_steps=3000,
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        tensorboard=False,
    )
    trainer = Trainer(cfg)
    trainer.open_outputs()
    found: dict[str, Any] = {}
    try:
        while trainer.step < 1000:
            trainer.advance()
        before = (trainer.step, trainer.episodes, trainer.remote.restarts)
        os.kill(ray.get(trainer.remote.slots[0].actor.pid.remote()), signal.SIGKILL)
        while trainer.remote.restarts == before[2]:
            trainer.advance()
        while trainer.step < 1800:
            trainer.advance()
        found["worker_killed"] = {
            "survived": whole(trainer) and trainer.episodes > before[1],
            "restarts": trainer.remote.restarts - before[2],
            "step_before": before[0],
            "step_after": trainer.step,
        }
        before = (trainer.step, trainer.episodes, trainer.remote.restarts)
        cluster.remove_node(node)
        while trainer.remote.restarts < before[2] + args.workers:
            trainer.advance()
        while trainer.step < cfg.total_steps:
            trainer.advance()
        head = ray.get_runtime_context().get_node_id()
        found["node_killed"] = {
            "survived": whole(trainer) and trainer.remote.nodes() == [head] * args.workers,
            "restarts": trainer.remote.restarts - before[2],
            "dropped_episodes": trainer.remote.dropped,
            "step_before": before[0],
            "step_after": trainer.step,
        }
    finally:
        trainer.close()
    return found


def workers_running() -> int:
    """Rollout worker processes alive on this machine."""
    out = subprocess.run(["pgrep", "-f", "RolloutWorker"], capture_output=True, text=True)
    return len(out.stdout.split())


def learner_interrupt(address: str, args: argparse.Namespace) -> dict[str, Any]:
    """(3) ``lcrl train`` with the cluster's workers gets SIGINT mid-run."""
    out = Path(args.work) / "interrupted"
    cmd = [*LCRL, "train", "lang2d-quick", "--out", str(out), "--overwrite", "--no-progress"]
    cmd += ["--total-steps", "100000", *cluster_flags(address, args.workers)]
    log = out.with_suffix(".log")
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        start = time.time()
        while time.time() - start < 600:
            if proc.poll() is not None:
                raise SystemExit(f"the interrupted run ended before its signal: see {log}")
            log_file = out / "progress.csv"
            rows = log_file.read_text().splitlines() if log_file.is_file() else []
            if len(rows) > 2 and workers_running() >= args.workers:
                break
            time.sleep(2)
        running = workers_running()
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=300)
    time.sleep(5)  # the actors' processes exit once killed
    latest = out / "latest.json"
    saved = json.loads(latest.read_text())["checkpoint"] if latest.is_file() else None
    intact = saved is not None and (out / saved / "meta.json").is_file()
    left = workers_running()
    return {
        "survived": code != 0 and intact and left == 0,
        "exit_code": code,
        "checkpoint": saved,
        "workers_before": running,
        "workers_left": left,
        "log": str(log),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=2, help="rollout workers")
    parser.add_argument("--worker-cpus", type=int, default=2, help="the worker node's CPUs")
    parser.add_argument("--seconds", type=float, default=30.0, help="per collection rate")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=100, help="evaluation, per set")
    parser.add_argument("--seed", type=int, default=0, help="of the collection timing")
    parser.add_argument("--work", default="runs/bench/ray-cluster")
    args = parser.parse_args(argv)
    import ray

    Path(args.work).mkdir(parents=True, exist_ok=True)
    cluster, node = start_cluster(args.workers, args.worker_cpus)
    try:
        faults = {"learner_interrupted": learner_interrupt(cluster.address, args)}
        print(f"learner interrupted: {faults['learner_interrupted']}", flush=True)
        ray.init(address=cluster.address)
        faults = {**in_process_faults(cluster, node, args), **faults}
        print(f"faults: {faults}", flush=True)
        cluster.add_node(num_cpus=args.worker_cpus)  # a new worker node for what follows
        cluster.wait_for_nodes()
        rates = collection(args, cluster.address)
        print(f"collection: {rates}", flush=True)
        runs = learning(args, cluster.address)
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
    seen = {arm: [r["sets"]["train"]["success"] for r in per.values()] for arm, per in runs.items()}
    local_seen = statistics.mean(seen["local"])
    headline = {
        "collect_speedup": round(rates["cluster_steps_per_s"] / rates["local8_steps_per_s"], 3),
        "seen_ratio": round(statistics.mean(seen["cluster"]) / max(local_seen, 1e-9), 3),
        "faults_survived": sum(bool(f["survived"]) for f in faults.values()),
        "local_seen": round(local_seen, 3),
        "cluster_seen": round(statistics.mean(seen["cluster"]), 3),
    }
    reached = {
        "seen_ratio": headline["seen_ratio"] >= TARGETS["seen_ratio"],
        "faults_survived": headline["faults_survived"] >= TARGETS["faults_survived"],
    }
    payload = {
        "headline": headline,
        "targets": TARGETS,
        "reached": reached,
        "machine": machine(),
        "settings": vars(args),
        "collection": rates,
        "runs": runs,
        "faults": faults,
    }
    lines = [
        f"A two-node Ray cluster on this machine (head: the learner; worker node: "
        f"{args.worker_cpus} CPUs, {args.workers} rollout workers pinned to it).",
        "",
        "| figure | value | target |",
        "|---|---:|---|",
        f"| collection, cluster workers / 8-environment local loop | "
        f"{headline['collect_speedup']:.2f}x ({rates['cluster_steps_per_s']:.0f} against "
        f"{rates['local8_steps_per_s']:.0f} steps/s) | reported |",
        f"| seen success, cluster / local (lang2d-quick, seeds {args.seeds}) | "
        f"{headline['seen_ratio']} ({headline['cluster_seen']:.2f} against "
        f"{headline['local_seen']:.2f}) | >= {TARGETS['seen_ratio']}: "
        f"{'reached' if reached['seen_ratio'] else 'NOT reached'} |",
        f"| faults survived | {headline['faults_survived']} of 3 | 3 of 3: "
        f"{'reached' if reached['faults_survived'] else 'NOT reached'} |",
    ]
    lines += [
        "",
        "Both nodes of this cluster share one machine's cores, so the collection ratio is "
        "the price of Ray's messages and of acting one episode at a time in each worker, "
        "against a local loop that steps 8 environments with one batched forward pass: "
        "more than 1 needs nodes with cores of their own.",
        "",
        "| fault | survived | what happened |",
        "|---|---|---|",
    ]
    for name, f in faults.items():
        said = ", ".join(f"{k} {v}" for k, v in f.items() if k not in ("survived", "log"))
        lines.append(f"| {name.replace('_', ' ')} | {'yes' if f['survived'] else 'NO'} | {said} |")
    lines += [
        "",
        "| arm | seed | seen | held-out | paraphrase | seconds |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for arm, per in runs.items():
        for seed, r in per.items():
            s = r["sets"]
            lines.append(
                f"| {arm} | {seed} | {s['train']['success']:.2f} | {s['heldout']['success']:.2f}"
                f" | {s['paraphrase']['success']:.2f} | {r['seconds']:.0f} |"
            )
    fig, ax = new_figure(figsize=(6, 3.6))
    for i, arm in enumerate(seen):
        ax.bar(i, statistics.mean(seen[arm]), 0.6, color=f"C{i}")
        ax.scatter([i] * len(seen[arm]), seen[arm], color="k", s=12, zorder=3)
    ax.set_xticks([0, 1], ["local", f"cluster ({args.workers} workers)"])
    ax.set(ylim=(0, 1.02), ylabel="seen success (lang2d-quick)")
    ax.set_title(f"faults survived {headline['faults_survived']} of 3")
    publish(NAME, payload, "Ray rollout workers on a two-node cluster", "\n".join(lines), fig)
    return 0


if __name__ == "__main__":
    sys.exit(main())

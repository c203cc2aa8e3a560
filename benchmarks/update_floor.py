"""How far lcrl's float32 SAC update is from the cheapest eager PyTorch update, and from SB3's.

    python -m benchmarks.update_floor

The setting of ``benchmarks/speed_vs_sb3.py`` (FetchReach-v4, SAC, two hidden layers of
256 for actor and critics, batch 256, float32), one gradient update timed three ways,
alternating ``--rounds`` times at each torch thread count in one process:

``lcrl``
    ``agent.update(batch)`` of the ``fetch-reach`` trainer that ``speed_vs_sb3`` times,
    after 1,000 random steps, on batches sampled (with hindsight relabelling) before the
    clock starts.
``eager floor``
    the fewest operations a plain PyTorch SAC update of the same networks needs, written
    out as CleanRL writes it: two ``nn.Sequential`` critics and their targets, one actor,
    fused Adam, the temperature tuned, Polyak averaging with one ``_foreach_lerp_``; on
    random tensors of FetchReach's shapes (10 observation, 3 goal and 4 action values).
``sb3``
    ``SAC.train(gradient_steps=1, batch_size=256)`` of Stable-Baselines3 with a
    ``HerReplayBuffer`` after 1,000 random steps, less the time its buffer takes to
    sample a batch (timed apart, alternating with it).

The file answers what ``speed_vs_sb3`` cannot: whether lcrl's update has overhead left to
remove, and how fast a whole training step could be against SB3's if lcrl's update cost
no more than the floor. ``headline.lcrl_over_floor_<n>`` is lcrl ms / floor ms and
``headline.sb3_over_lcrl_<n>`` SB3 ms / lcrl ms, per thread count.

Writes ``benchmarks/results/update_floor.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from benchmarks.common import machine, new_figure, publish
from benchmarks.speed_vs_sb3 import BATCH, HIDDEN, WARMUP

NAME = "update_floor"
OBS, GOAL, ACT = 10, 3, 4  # FetchReach-v4: observation, desired goal, action


def _mlp(inp: int, out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in HIDDEN:
        layers += [nn.Linear(inp, width), nn.ReLU()]
        inp = width
    return nn.Sequential(*layers, nn.Linear(inp, out))


class EagerFloor:
    """A minimal SAC update in plain PyTorch, the fewest eager operations it takes."""

    def __init__(self, seed: int) -> None:
        torch.manual_seed(seed)
        self.actor = _mlp(OBS + GOAL, 2 * ACT)
        self.q = [_mlp(OBS + GOAL + ACT, 1) for _ in range(2)]
        self.q_target = [_mlp(OBS + GOAL + ACT, 1) for _ in range(2)]
        for q, t in zip(self.q, self.q_target, strict=True):
            t.load_state_dict(q.state_dict())
        self.q_params = [p for q in self.q for p in q.parameters()]
        self.t_params = [p for q in self.q_target for p in q.parameters()]
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), 3e-4, fused=True)
        self.q_opt = torch.optim.Adam(self.q_params, 3e-4, fused=True)
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], 3e-4)
        self.batches = [
            (
                torch.randn(BATCH, OBS + GOAL),
                torch.rand(BATCH, ACT) * 2 - 1,
                -(torch.rand(BATCH) < 0.5).float(),
                torch.randn(BATCH, OBS + GOAL),
                torch.zeros(BATCH),
            )
            for _ in range(16)
        ]
        self.n = 0

    def _policy(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.actor(x).chunk(2, -1)
        log_std = log_std.clamp(-20.0, 2.0)
        u = mean + log_std.exp() * torch.randn_like(mean)
        logp = (-0.5 * ((u - mean) / log_std.exp()).pow(2) - log_std - 0.9189385).sum(-1)
        logp = logp - (2.0 * (0.6931472 - u - F.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u), logp

    def update(self) -> None:
        x, a, r, nx, done = self.batches[self.n % len(self.batches)]
        self.n += 1
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            na, nlogp = self._policy(nx)
            t_in = torch.cat([nx, na], -1)
            target_q = torch.min(self.q_target[0](t_in), self.q_target[1](t_in)).squeeze(-1)
            y = r + 0.98 * (1.0 - done) * (target_q - alpha * nlogp)
        q_in = torch.cat([x, a], -1)
        q_loss = sum(0.5 * (q(q_in).squeeze(-1) - y).pow(2).mean() for q in self.q)
        self.q_opt.zero_grad()
        q_loss.backward()
        self.q_opt.step()
        for p in self.q_params:
            p.requires_grad_(False)
        pa, logp = self._policy(x)
        p_in = torch.cat([x, pa], -1)
        q_pi = torch.min(self.q[0](p_in), self.q[1](p_in)).squeeze(-1)
        actor_loss = (alpha * logp - q_pi).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        for p in self.q_params:
            p.requires_grad_(True)
        alpha_loss = -(self.log_alpha * (logp.detach() - ACT)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()
        with torch.no_grad():
            torch._foreach_lerp_(self.t_params, self.q_params, 0.005)


class Lcrl:
    """lcrl's update on the ``fetch-reach`` trainer that ``speed_vs_sb3`` times."""

    def __init__(self, seed: int) -> None:
        from lcrl.nets import NetConfig
        from train.configs.presets import PRESETS
        from train.training.loop import Trainer

        base = PRESETS["fetch-reach"][1]
        self.out = Path(tempfile.mkdtemp(prefix="lcrl-floor-"))
        cfg = dataclasses.replace(
            base,
            out=str(self.out),
            total_steps=10**9,
            learning_starts=WARMUP,
            batch_size=BATCH,
            collect=dataclasses.replace(base.collect, envs=1),
            progress=False,
            tensorboard=False,
            eval_every=0,
            checkpoint_every=0,
            seed=seed,
        )
        cfg.agent = dataclasses.replace(
            cfg.agent, net=NetConfig(hidden=HIDDEN), seed=seed, precision="fp32"
        )
        self.trainer = Trainer(cfg)
        while self.trainer.step < WARMUP:
            self.trainer.collect_episode()
        self.batches = [self.trainer.buffer.sample(BATCH) for _ in range(16)]
        self.n = 0

    def update(self) -> None:
        self.trainer.agent.update(self.batches[self.n % len(self.batches)])
        self.n += 1

    def close(self) -> None:
        self.trainer.close()
        shutil.rmtree(self.out, ignore_errors=True)


class Sb3:
    """SB3 SAC + ``HerReplayBuffer``: one ``train`` step, and its buffer's sampling alone."""

    def __init__(self, seed: int) -> None:
        import gymnasium as gym
        import gymnasium_robotics
        from stable_baselines3 import SAC, HerReplayBuffer

        gym.register_envs(gymnasium_robotics)
        self.model = SAC(
            "MultiInputPolicy",
            gym.make("FetchReach-v4"),
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
            learning_starts=WARMUP,
            batch_size=BATCH,
            policy_kwargs={"net_arch": list(HIDDEN)},
            seed=seed,
            verbose=0,
        )
        self.model.learn(WARMUP)

    def train(self) -> None:
        self.model.train(gradient_steps=1, batch_size=BATCH)

    def sample(self) -> None:
        self.model.replay_buffer.sample(BATCH, env=self.model._vec_normalize_env)


def ms_per_call(fn: Callable[[], None], calls: int) -> float:
    t0 = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - t0) / calls * 1000


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=300, help="timed updates per round")
    parser.add_argument(
        "--rounds",
        type=int,
        default=7,
        help="alternating rounds per thread count (3 were too few on a noisy AVX2 machine: "
        "one such run put lcrl above the floor at one thread, a 7-round run below it)",
    )
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    lcrl, floor, sb3 = Lcrl(args.seed), EagerFloor(args.seed), Sb3(args.seed)
    arms: dict[str, Callable[[], None]] = {
        "lcrl": lcrl.update,
        "eager floor": floor.update,
        "sb3 train": sb3.train,
        "sb3 sample": sb3.sample,
    }
    rows: list[dict[str, Any]] = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for fn in arms.values():  # warm up at this thread count
            ms_per_call(fn, 20)
        rounds: dict[str, list[float]] = {k: [] for k in arms}
        for _ in range(args.rounds):
            for k, fn in arms.items():
                rounds[k].append(ms_per_call(fn, args.updates))
        med = {k: statistics.median(v) for k, v in rounds.items()}
        row = {
            "threads": threads,
            "lcrl_ms": med["lcrl"],
            "floor_ms": med["eager floor"],
            "sb3_ms": med["sb3 train"] - med["sb3 sample"],
            "sb3_sample_ms": med["sb3 sample"],
            "rounds": rounds,
        }
        rows.append(row)
        print(
            f"threads {threads}: lcrl {row['lcrl_ms']:.2f} ms, eager floor "
            f"{row['floor_ms']:.2f} ms, SB3 {row['sb3_ms']:.2f} ms (+{row['sb3_sample_ms']:.2f} "
            "ms sampling)",
            flush=True,
        )
    lcrl.close()

    headline: dict[str, Any] = {}
    for r in rows:
        n = r["threads"]
        headline[f"lcrl_ms_{n}"] = round(r["lcrl_ms"], 3)
        headline[f"floor_ms_{n}"] = round(r["floor_ms"], 3)
        headline[f"sb3_ms_{n}"] = round(r["sb3_ms"], 3)
        headline[f"lcrl_over_floor_{n}"] = round(r["lcrl_ms"] / r["floor_ms"], 3)
        headline[f"sb3_over_lcrl_{n}"] = round(r["sb3_ms"] / r["lcrl_ms"], 3)
    info = machine()
    payload = {
        "headline": headline,
        "machine": info,
        "settings": {**vars(args), "batch": BATCH, "hidden": list(HIDDEN), "precision": "fp32"},
        "rows": rows,
    }
    lines = [
        "| torch threads | lcrl ms | eager floor ms | lcrl / floor | SB3 ms (sampling apart) "
        "| SB3 / lcrl |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['threads']} | {r['lcrl_ms']:.2f} | {r['floor_ms']:.2f} | "
            f"{r['lcrl_ms'] / r['floor_ms']:.2f} | {r['sb3_ms']:.2f} "
            f"(+{r['sb3_sample_ms']:.2f}) | {r['sb3_ms'] / r['lcrl_ms']:.2f} |"
        )
    body = (
        "One float32 SAC update in the setting of `speed_vs_sb3` (FetchReach-v4, hidden "
        f"{HIDDEN[0]}x{HIDDEN[1]}, batch {BATCH}), medians of {args.rounds} alternating rounds "
        f"of {args.updates} updates. The eager floor is a minimal plain-PyTorch SAC update of "
        "the same networks (CleanRL's way, fused Adam); SB3's figure is its `train` step less "
        "its buffer's sampling, timed apart.\n\n" + "\n".join(lines)
    )
    fig, ax = new_figure(figsize=(5.5, 3.5))
    x = range(len(rows))
    for i, (key, label) in enumerate(
        (("lcrl_ms", "lcrl"), ("floor_ms", "eager floor"), ("sb3_ms", "SB3"))
    ):
        ax.bar([j + (i - 1) * 0.27 for j in x], [r[key] for r in rows], 0.27, label=label)
    ax.set_xticks(list(x), [f"{r['threads']} thread(s)" for r in rows])
    ax.set(ylabel="ms per update", title="float32 SAC update, FetchReach shapes")
    ax.legend()
    publish(NAME, payload, "lcrl's float32 update against the eager floor and SB3", body, fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

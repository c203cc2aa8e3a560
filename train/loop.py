"""The training loop: collect an episode, label it, store it, update, evaluate, checkpoint.

Reads top to bottom in :meth:`Trainer.run`. One environment steps at a time; after
``learning_starts`` steps of random actions every step is followed by
``updates_per_step`` gradient updates on relabelled batches. Every ``eval_every`` steps
the policy is evaluated (deterministically) on each instruction set; every
``checkpoint_every`` steps, at the end, and on Ctrl-C the run is checkpointed (the
unfinished episode of an interrupted run is discarded and collected again on resume).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import shutil
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.algos import Agent
from lcrl.buffer import HindsightReplayBuffer
from lcrl.checkpoint import find_latest, load_checkpoint, save_checkpoint, write_latest
from lcrl.errors import LcrlError
from train.config import TrainConfig, config_from_dict, config_to_dict
from train.evaluate import build_agent, build_task, evaluate, format_results
from train.report import write_report
from train.tasks import ScriptedActor, make_env


class CsvLog:
    """Append rows to a CSV file; the header is fixed by the first row (or the file)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fields: list[str] | None = None
        if path.exists():
            with path.open() as f:
                header = f.readline().strip()
            self.fields = header.split(",") if header else None

    def write(self, row: Mapping[str, Any]) -> None:
        """Write one row (keys outside the header are dropped)."""
        new = self.fields is None
        if new:
            self.fields = list(row)
        with self.path.open("a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow({k: _fmt(v) for k, v in row.items()})


def _fmt(v: Any) -> Any:
    return f"{v:.6g}" if isinstance(v, float) else v


class Trainer:
    """Builds everything a run needs from a :class:`TrainConfig` and runs it.

    Args:
        cfg: the run's configuration. With ``cfg.resume`` the latest checkpoint in
            ``cfg.out`` is loaded, with the config saved there (and ``cfg.total_steps``).
    """

    def __init__(self, cfg: TrainConfig) -> None:
        cfg.validate()
        self.out = Path(cfg.out)
        ckpt = None
        if cfg.resume:
            latest = find_latest(self.out)
            if latest is None:
                raise LcrlError(f"--resume: no checkpoint in {self.out} (no latest.json)")
            ckpt = load_checkpoint(latest)
            saved = config_from_dict(ckpt.meta["config"])
            saved.total_steps = cfg.total_steps
            saved.resume = True
            saved.out = cfg.out
            cfg = saved
        elif (self.out / "latest.json").exists():
            if not cfg.overwrite:
                raise LcrlError(
                    f"{self.out} already holds a run; pass --resume to continue it, "
                    "--overwrite to replace it, or choose another --out"
                )
            for name in ("checkpoints", "tb"):
                shutil.rmtree(self.out / name, ignore_errors=True)
            for name in ("latest.json", "progress.csv", "eval.csv", "report.md", "curves.png"):
                (self.out / name).unlink(missing_ok=True)
        self.cfg = cfg
        models = _learned_models(cfg)
        env_cfg = cfg.env
        if models is not None:  # the training env renders the frames the models read
            size = models.frame_shape[0]
            env_cfg = dataclasses.replace(
                cfg.env, extra={**cfg.env.extra, "image": True, "image_size": size}
            )
        self.env = make_env(env_cfg, "train", training=True)
        self.task = build_task(cfg, self.env, ckpt)
        if models is not None:
            from captioner.learned import LearnedLabeller

            r = cfg.relabel
            self.task.labeller = LearnedLabeller(
                models,
                self.task.table,
                self.task.num_train,
                captioner=r.captioner == "learned",
                reward=r.reward == "learned",
                captioner_rewards=r.reward == "captioner",
                min_logprob=r.min_logprob,
                beam=r.beam,
                threshold=r.threshold,
            )
        self.problem = self.task.problem()
        self.algo = cfg.resolved_algo(self.problem.discrete)
        self.agent: Agent = build_agent(self.algo, self.problem, cfg, self.task.goal_space.embed)
        p = self.problem
        self.buffer = HindsightReplayBuffer(
            cfg.buffer.capacity,
            {
                k: (shape, np.uint8 if len(shape) == 3 else np.float32)
                for k, shape in p.obs_shapes.items()
            },
            () if p.discrete else (p.action_dim,),
            np.int64 if p.discrete else np.float32,
            self.task.goal_space,
            strategy=cfg.buffer.strategy,
            k=cfg.buffer.k,
            seed=cfg.seed,
            random_fraction=cfg.buffer.random_fraction,
            n_step=cfg.buffer.n_step,
            gamma=self.agent.cfg.gamma,
        )
        self.rng = np.random.default_rng(cfg.seed)
        self.scripted = (
            ScriptedActor(cfg.env, self.task, cfg.scripted_noise)
            if cfg.scripted_fraction > 0
            else None
        )
        self.scripted_rng = np.random.default_rng([cfg.seed, 1])
        self.step = 0
        self.episodes = 0
        self.sim_errors = 0  # episodes a simulator error ended (the env reports them)
        self.scripted_episodes = 0  # episodes acted by the scripted controller
        self.recent: deque[float] = deque(maxlen=100)
        self._credit = 0.0
        self._metrics: dict[str, float] = {}
        self._metric_count = 0
        self.last_eval: dict[str, Any] | None = None
        self._last_logged = -1
        if ckpt is not None:
            self._restore(ckpt)
        elif self.problem.goal_kind == "text":
            self.agent.observe({}, self.task.embeddings[: self.task.num_train])

    # --- the loop --------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        """Train to ``total_steps``; returns the final evaluation."""
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(
            json.dumps({**config_to_dict(cfg), "resolved_algo": self.algo}, indent=1)
        )
        self.progress_log = CsvLog(self.out / "progress.csv")
        self.eval_log = CsvLog(self.out / "eval.csv")
        self.tb = _tensorboard(self.out / "tb") if cfg.tensorboard else None
        bar = _progress(cfg.total_steps, self.step, cfg.progress)
        self._t0, self._step0 = time.perf_counter(), self.step
        next_eval = _next(self.step, cfg.eval_every)
        next_ckpt = _next(self.step, cfg.checkpoint_every)
        next_log = _next(self.step, cfg.log_every)
        try:
            while self.step < cfg.total_steps:
                before = self.step
                self.collect_episode()
                bar.update(self.step - before)
                if self.step >= next_log:
                    self._log()
                    next_log = _next(self.step, cfg.log_every)
                if cfg.eval_every and self.step >= next_eval and self.step < cfg.total_steps:
                    self.evaluate()
                    next_eval = _next(self.step, cfg.eval_every)
                if cfg.checkpoint_every and self.step >= next_ckpt and self.step < cfg.total_steps:
                    self.save()
                    next_ckpt = _next(self.step, cfg.checkpoint_every)
                bar.set_postfix_str(self._postfix(), refresh=False)
        except KeyboardInterrupt:
            bar.close()
            path = self.save()
            print(f"interrupted at step {self.step}: saved {path}; continue with --resume")
            self.close()
            raise
        bar.close()
        if self._last_logged != self.step:
            self._log()
        results = self.evaluate()
        path = self.save()
        report = write_report(self.out, results)
        print(f"final checkpoint: {path}")
        print(f"report: {report}")
        self.close()
        return results

    def close(self) -> None:
        """Close the TensorBoard writer."""
        if getattr(self, "tb", None) is not None:
            self.tb.close()
            self.tb = None

    def collect_episode(self) -> None:
        """Run one episode (acting, stepping, updating) and store it in the buffer."""
        cfg, task, env = self.cfg, self.task, self.env
        obs, info = env.reset(seed=int(cfg.seed * 1_000_003 + self.episodes))
        first = obs
        goal = task.goal(obs, env)
        goal_batch = np.asarray([goal])
        stored = [task.storage_obs(obs, first)]
        records = [task.step_record(obs, env)]
        actions, rewards, terms = [], [], []
        succeeded = False  # at any step (episodes may go on after success)
        start_step = self.step
        scripted = self.scripted is not None and self.scripted_rng.random() < cfg.scripted_fraction
        if scripted:
            self.scripted.reset()
        try:
            while True:
                if scripted:
                    a = self.scripted.act(env, self.scripted_rng)
                elif self.step < cfg.learning_starts:
                    if (self.step - start_step) % cfg.random_action_repeat == 0:
                        random_a = task.random_action(self.rng)
                    a = random_a
                else:
                    batch_obs = {k: v[None] for k, v in stored[-1].items()}
                    a = self.agent.act(batch_obs, goal_batch)[0]
                obs, reward, terminated, truncated, info = env.step(task.scale_action(a))
                self.step += 1
                stored.append(task.storage_obs(obs, first))
                records.append(task.step_record(obs, env))
                actions.append(a)
                rewards.append(reward)
                terms.append(terminated)
                succeeded = succeeded or bool(info.get("is_success", False))
                self._update(self._updates_due())
                if terminated or truncated:
                    break
                if self.step >= cfg.total_steps and self.step - start_step >= 1:
                    break  # the budget ends mid-episode: store what was collected
        except BaseException:
            self.step = start_step  # the unfinished episode is dropped: count it again
            raise
        episode_obs = {k: np.stack([s[k] for s in stored]) for k in stored[0]}
        episode = {
            "obs": episode_obs,
            "action": np.asarray(actions),
            "reward": np.asarray(rewards, np.float32),
            "terminated": np.asarray(terms, bool),
            **task.episode_fields(records, goal, env),
        }
        self.buffer.add_episode(episode)
        self.agent.observe(episode_obs, episode.get("achieved_goal"))
        self.episodes += 1
        if scripted:
            self.scripted_episodes += 1
        else:  # the live success rate is the policy's
            self.recent.append(float(succeeded))
        if info.get("sim_error"):
            self.sim_errors += 1

    def _updates_due(self) -> int:
        """Gradient updates due after this env step."""
        cfg = self.cfg
        if self.step < cfg.learning_starts or self.buffer.size == 0:
            return 0
        self._credit += cfg.updates_per_step
        n = int(self._credit)
        self._credit -= n
        return n

    def _update(self, n: int) -> None:
        for _ in range(n):
            metrics = self.agent.update(self.buffer.sample(self.cfg.batch_size))
            for k, v in metrics.items():
                self._metrics[k] = self._metrics.get(k, 0.0) + v
            self._metric_count += 1

    # --- evaluation, logging ---------------------------------------------------------
    def evaluate(self) -> dict[str, Any]:
        """Evaluate on every instruction set; log and return the results."""
        cfg = self.cfg
        results = evaluate(self.agent, self.task, cfg, episodes=cfg.eval_episodes, seed=cfg.seed)
        self.last_eval = results
        row: dict[str, Any] = {"step": self.step, "episodes": self.episodes}
        families = tuple(getattr(self.task, "families", ()))
        for name, res in results.items():
            row[f"{name}/success"] = res["success"]
            # every family gets a column, even one that no episode of this round drew
            for fam in dict.fromkeys((*families, *res["families"])):
                row[f"{name}/{fam}"] = res["families"].get(fam, float("nan"))
        self.eval_log.write(row)
        if self.tb is not None:
            for k, v in row.items():
                if k not in ("step", "episodes"):
                    self.tb.add_scalar(f"eval/{k}", v, self.step)
        print(f"[step {self.step}] " + format_results(results).replace("\n", " | "))
        return results

    def _postfix(self) -> str:
        sr = np.mean(self.recent) if self.recent else 0.0
        text = f"ep {self.episodes} success {sr:.2f}"
        if self.last_eval:
            text += " eval " + " ".join(
                f"{k} {v['success']:.2f}" for k, v in self.last_eval.items()
            )
        return text

    def _log(self) -> None:
        elapsed = time.perf_counter() - self._t0
        row: dict[str, Any] = {
            "step": self.step,
            "episodes": self.episodes,
            "success": float(np.mean(self.recent)) if self.recent else 0.0,
            "steps_per_s": (self.step - self._step0) / max(elapsed, 1e-9),
            "updates": self.agent.updates,
            "buffer": self.buffer.size,
            "sim_errors": self.sim_errors,
            "scripted_episodes": self.scripted_episodes,
        }
        labeller = getattr(self.task, "labeller", None)
        if labeller is not None:  # learned relabelling, against the rule captioner
            row.update(labeller.agreement())
        n = max(self._metric_count, 1)
        row.update({k: v / n for k, v in sorted(self._metrics.items())})
        self._metrics, self._metric_count = {}, 0
        self.progress_log.write(row)
        self._last_logged = self.step
        if self.tb is not None:
            for k, v in row.items():
                if k != "step":
                    self.tb.add_scalar(f"train/{k}", v, self.step)

    # --- checkpoints -----------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint the run (weights, optimiser and RNG state, buffer, tables)."""
        cfg = self.cfg
        directory = self.out / "checkpoints" / f"step_{self.step:09d}"
        json_files: dict[str, Any] = {}
        meta = {
            "config": config_to_dict(cfg),
            "algo": self.algo,
            "problem": self.problem.to_dict(),
            "step": self.step,
            "episodes": self.episodes,
            "env": {
                "kind": cfg.env.kind,
                "observation_space": str(self.env.observation_space),
                "action_space": str(self.env.action_space),
            },
        }
        table = getattr(self.task, "table", None)
        if table is not None:
            json_files["instructions"] = {"texts": table, "num_train": self.task.num_train}
            json_files["split"] = self.task.split.to_dict()
            meta["text_encoder"] = {
                "model": cfg.text_encoder.model,
                "dim": int(self.task.embeddings.shape[1]),
            }
        states = {
            **self.agent.states(),
            "buffer_rng": self.buffer.rng.bit_generator.state,
            "trainer_rng": self.rng.bit_generator.state,
            "scripted_rng": self.scripted_rng.bit_generator.state,
            "trainer": {
                "step": self.step,
                "episodes": self.episodes,
                "sim_errors": self.sim_errors,
                "scripted_episodes": self.scripted_episodes,
                "recent": list(self.recent),
                "credit": self._credit,
            },
        }
        arrays = self.buffer.arrays() if cfg.save_buffer else None
        path = save_checkpoint(
            directory,
            modules=self.agent.modules(),
            states=states,
            meta=meta,
            json_files=json_files,
            arrays=arrays,
        )
        write_latest(self.out, path)
        kept = sorted((self.out / "checkpoints").glob("step_*"))
        for old in kept[: -cfg.keep_checkpoints]:
            shutil.rmtree(old, ignore_errors=True)
        return path

    def _restore(self, ckpt: Any) -> None:
        for name, module in self.agent.modules().items():
            ckpt.load_module(name, module)
        states = {name: ckpt.state(name) for name in self.agent.states()}
        self.agent.load_states(states)
        self.buffer.rng.bit_generator.state = ckpt.state("buffer_rng")
        self.rng.bit_generator.state = ckpt.state("trainer_rng")
        if ckpt.has_state("scripted_rng"):
            self.scripted_rng.bit_generator.state = ckpt.state("scripted_rng")
        trainer = ckpt.state("trainer")
        self.step, self.episodes = int(trainer["step"]), int(trainer["episodes"])
        self.sim_errors = int(trainer.get("sim_errors", 0))
        self.scripted_episodes = int(trainer.get("scripted_episodes", 0))
        self.recent.extend(trainer["recent"])
        self._credit = float(trainer["credit"])
        if ckpt.has_arrays():
            self.buffer.load_arrays(ckpt.arrays())
        print(f"resumed {self.out} at step {self.step} ({self.episodes} episodes)")
        if not ckpt.has_arrays():
            print(
                "note: this checkpoint holds no replay buffer (the run had save_buffer off): "
                "training goes on from an empty buffer, so it does not continue the run exactly"
            )


def _learned_models(cfg: TrainConfig) -> Any:
    """The learned captioner / reward model a config asks for (None: rule captioner)."""
    if not cfg.relabel.learned:
        return None
    from train.tasks import is_language

    if not is_language(cfg.env):
        raise LcrlError("learned relabelling is for language goals (lang2d, robosuite)")
    if cfg.env.image_obs:
        raise LcrlError("learned relabelling with image observations is not supported yet")
    from captioner.learned import LearnedCaptioner

    models = LearnedCaptioner.load(cfg.relabel.checkpoint, device=cfg.agent.device)
    trained_on = models.meta.get("dataset_meta", {}).get("env")
    if trained_on is not None and trained_on != cfg.env.kind:
        raise LcrlError(
            f"the learned models in {cfg.relabel.checkpoint} read {trained_on!r} frames; this "
            f"run's env is {cfg.env.kind!r}"
        )
    return models


def _next(step: int, every: int) -> float:
    if every <= 0:
        return math.inf
    return (step // every + 1) * every


def _progress(total: int, initial: int, enabled: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=initial,
        disable=not enabled,
        unit="step",
        dynamic_ncols=True,
        smoothing=0.05,
    )


def _tensorboard(path: Path) -> Any:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        print("tensorboard is not installed: no TensorBoard logs (pip install tensorboard)")
        return None
    return SummaryWriter(str(path))

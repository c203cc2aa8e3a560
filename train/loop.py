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
from lcrl.multitask import CONFLICT_KEYS, TaskSampler
from train.config import TrainConfig, config_from_dict, config_to_dict
from train.environments import canonical_kind
from train.evaluate import build_agent, build_task, evaluate, format_results
from train.report import write_report
from train.tasks import ScriptedActor, is_language, make_env, reset_feasible, task_texts


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


def open_run(cfg: TrainConfig) -> tuple[TrainConfig, Any]:
    """Prepare ``cfg.out`` for a run: with ``cfg.resume``, load its latest checkpoint and
    the config saved there (keeping ``total_steps``, ``out`` and ``resume`` from ``cfg``);
    otherwise refuse a folder that already holds a run unless ``cfg.overwrite``, in which
    case its checkpoints and logs are removed.

    Returns:
        The config to run with and the checkpoint to resume from (None for a new run).
    """
    out = Path(cfg.out)
    if cfg.resume:
        latest = find_latest(out)
        if latest is None:
            raise LcrlError(f"--resume: no checkpoint in {out} (no latest.json)")
        ckpt = load_checkpoint(latest)
        saved = config_from_dict(ckpt.meta["config"])
        saved.total_steps = cfg.total_steps
        saved.resume = True
        saved.out = cfg.out
        return saved, ckpt
    if (out / "latest.json").exists():
        if not cfg.overwrite:
            raise LcrlError(
                f"{out} already holds a run; pass --resume to continue it, "
                "--overwrite to replace it, or choose another --out"
            )
        for name in ("checkpoints", "tb"):
            shutil.rmtree(out / name, ignore_errors=True)
        for name in ("latest.json", "progress.csv", "eval.csv", "report.md", "curves.png"):
            (out / name).unlink(missing_ok=True)
    return cfg, None


def eval_row(results: Mapping[str, Any], task: Any, step: int, episodes: int) -> dict[str, Any]:
    """The eval.csv row of an evaluation: step, episodes, success per set and per family
    (every family of the task gets a column, even one that no episode of this round drew)."""
    row: dict[str, Any] = {"step": step, "episodes": episodes}
    families = tuple(getattr(task, "families", ()))
    for name, res in results.items():
        row[f"{name}/success"] = res["success"]
        for fam in dict.fromkeys((*families, *res["families"])):
            row[f"{name}/{fam}"] = res["families"].get(fam, float("nan"))
        for t in res.get("tasks", ()):  # a fixed task set: success per task id
            row[f"tasks/{t['id']}"] = t["success"]
    return row


def checkpoint_meta(
    cfg: TrainConfig, algo: str, problem: Any, env: Any, task: Any, step: int, episodes: int
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``meta`` and JSON files of a run's checkpoint: config, algo, problem, env spaces,
    and for language tasks the instruction table, the split and the text encoder."""
    meta: dict[str, Any] = {
        "config": config_to_dict(cfg),
        "algo": algo,
        "problem": problem.to_dict(),
        "step": step,
        "episodes": episodes,
        "env": {
            "kind": cfg.env.kind,
            "observation_space": str(env.observation_space),
            "action_space": str(env.action_space),
        },
    }
    json_files: dict[str, Any] = {}
    table = getattr(task, "table", None)
    if table is not None:
        json_files["instructions"] = {"texts": table, "num_train": task.num_train}
        json_files["split"] = task.split.to_dict()
        meta["text_encoder"] = {
            "model": cfg.text_encoder.model,
            "dim": int(task.embeddings.shape[1]),
        }
    return meta, json_files


def prune_checkpoints(out: Path, keep: int) -> None:
    """Delete all but the ``keep`` latest ``checkpoints/step_*`` folders of a run."""
    kept = sorted((out / "checkpoints").glob("step_*"))
    for old in kept[:-keep]:
        shutil.rmtree(old, ignore_errors=True)


def save_interrupted(run: Any, unit: str) -> None:
    """Ctrl-C: checkpoint the run (``Trainer`` or ``BCTrainer``), say how to continue it,
    and close it."""
    path = run.save()
    print(f"interrupted at {unit} {run.step}: saved {path}; continue with --resume")
    run.close()


def finish_run(run: Any) -> dict[str, Any]:
    """The end of a run (``Trainer`` or ``BCTrainer``): the last progress row, the final
    evaluation, a checkpoint and the report; returns the evaluation."""
    if run._last_logged != run.step:
        run._log()
    results = run.evaluate()
    path = run.save()
    report = write_report(run.out, results)
    print(f"final checkpoint: {path}")
    print(f"report: {report}")
    run.close()
    return results


class Trainer:
    """Builds everything a run needs from a :class:`TrainConfig` and runs it.

    Args:
        cfg: the run's configuration. With ``cfg.resume`` the latest checkpoint in
            ``cfg.out`` is loaded, with the config saved there (and ``cfg.total_steps``).
    """

    def __init__(self, cfg: TrainConfig) -> None:
        cfg.validate()
        if cfg.algo == "bc":
            raise LcrlError(
                "behavioural cloning learns from demonstrations, not in this loop: run it "
                "with lcrl train (train.bc.BCTrainer)"
            )
        self.out = Path(cfg.out)
        cfg, ckpt = open_run(cfg)
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
        # a fixed task set: each training episode's task is drawn by the sampler
        self.tasks = task_texts(cfg.env)
        self.sampler = (
            TaskSampler.from_options(len(self.tasks), cfg.agent.multitask) if self.tasks else None
        )
        self.task_rng = np.random.default_rng([cfg.seed, 2])
        self._grad_metrics: dict[str, list[float]] = {}
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
            save_interrupted(self, "step")
            raise
        bar.close()
        return finish_run(self)

    def close(self) -> None:
        """Close the TensorBoard writer."""
        if getattr(self, "tb", None) is not None:
            self.tb.close()
            self.tb = None

    def collect_episode(self) -> None:
        """Run one episode (acting, stepping, updating) and store it in the buffer."""
        cfg, task, env = self.cfg, self.task, self.env
        seed = int(cfg.seed * 1_000_003 + self.episodes)
        task_id = None
        if self.sampler is not None:  # the sampled task, in a layout where it is feasible
            task_id = self.sampler.sample(self.task_rng)
            obs, info = reset_feasible(env, seed, self.tasks[task_id])
        else:
            obs, info = env.reset(seed=seed)
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
            if task_id is not None:
                self.sampler.update(task_id, succeeded)
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
                if k.startswith("grad/"):  # gradient conflict: measured on some updates
                    self._grad_metrics.setdefault(k, []).append(v)
                    continue
                self._metrics[k] = self._metrics.get(k, 0.0) + v
            self._metric_count += 1

    # --- evaluation, logging ---------------------------------------------------------
    def evaluate(self) -> dict[str, Any]:
        """Evaluate on every instruction set; log and return the results."""
        cfg = self.cfg
        results = evaluate(self.agent, self.task, cfg, episodes=cfg.eval_episodes, seed=cfg.seed)
        self.last_eval = results
        row = eval_row(results, self.task, self.step, self.episodes)
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
        row.update(self._multitask_columns())
        self.progress_log.write(row)
        self._last_logged = self.step
        if self.tb is not None:
            for k, v in row.items():
                if k != "step":
                    self.tb.add_scalar(f"train/{k}", v, self.step)

    def _multitask_columns(self) -> dict[str, float]:
        """progress.csv columns of a task set, every one from the first row: per task the
        live success (the policy's last ``multitask.window`` episodes of it) and its
        sampling probability; the gradient-conflict statistics (NaN until measured)."""
        row: dict[str, float] = {}
        if self.sampler is not None:
            rates, probs = self.sampler.success_rates(), self.sampler.probs()
            for i in range(len(self.tasks)):
                row[f"tasks/{i}/success"] = float(rates[i])
                row[f"tasks/{i}/prob"] = float(probs[i])
        if self.tasks and self.cfg.agent.multitask.measures_conflict:
            for net in ("critic", "actor"):
                for key in CONFLICT_KEYS:
                    name = f"grad/{net}_{'conflict' if key == 'conflict_fraction' else key}"
                    values = [v for v in self._grad_metrics.get(name, []) if v == v]
                    row[name] = float(np.mean(values)) if values else float("nan")
        self._grad_metrics = {}
        return row

    # --- checkpoints -----------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint the run (weights, optimiser and RNG state, buffer, tables)."""
        cfg = self.cfg
        directory = self.out / "checkpoints" / f"step_{self.step:09d}"
        meta, json_files = checkpoint_meta(
            cfg, self.algo, self.problem, self.env, self.task, self.step, self.episodes
        )
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
        if self.sampler is not None:
            states["task_sampler"] = self.sampler.state_dict()
            states["task_rng"] = self.task_rng.bit_generator.state
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
        prune_checkpoints(self.out, cfg.keep_checkpoints)
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
        if self.sampler is not None and ckpt.has_state("task_sampler"):
            self.sampler.load_state_dict(ckpt.state("task_sampler"))
            self.task_rng.bit_generator.state = ckpt.state("task_rng")
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
    if not is_language(cfg.env):
        raise LcrlError("learned relabelling is for language goals (lang2d, robosuite)")
    if cfg.env.image_obs:
        raise LcrlError("learned relabelling with image observations is not supported yet")
    from captioner.learned import LearnedCaptioner

    models = LearnedCaptioner.load(cfg.relabel.checkpoint, device=cfg.agent.device)
    trained_on = models.meta.get("dataset_meta", {}).get("env")
    if trained_on is not None and canonical_kind(trained_on) != cfg.env.kind:
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

"""The training loop: collect an episode, label it, store it, update, evaluate, checkpoint.

:class:`Trainer` is the online-RL :class:`train.training.trainer.BaseTrainer`: the base class runs
the loop (``run``), and :meth:`Trainer.collect_episode` reads top to bottom. One
environment steps at a time; after ``learning_starts`` steps of random actions every step
is followed by ``updates_per_step`` gradient updates on relabelled batches. Every
``eval_every`` steps the policy is evaluated (deterministically) on each instruction set;
every ``checkpoint_every`` steps, at the end, and on Ctrl-C the run is checkpointed (the
unfinished episode of an interrupted run is discarded and collected again on resume).
"""

from __future__ import annotations

import copy
import dataclasses
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lcrl.algos import ALGOS, Agent
from lcrl.buffer import HindsightReplayBuffer
from lcrl.errors import LcrlError
from lcrl.multitask import CONFLICT_KEYS, TaskSampler
from train.configs.config import TrainConfig, config_to_dict, family_thresholds
from train.configs.run_meta import restoring, state_fields
from train.environments.simulators import canonical_kind
from train.environments.tasks import (
    ScriptedActor,
    is_language,
    make_env,
    task_texts,
)
from train.evaluation.evaluate import build_agent, build_task
from train.runtime.machine import ThreadWatcher, automatic_threads, set_threads
from train.runtime.memory import check_memory
from train.training.collection import Collection
from train.training.explore import Explorer
from train.training.stages import SequentialStages
from train.training.trainer import BaseTrainer, eval_row, open_run

__all__ = ["Trainer", "checkpoint_meta", "eval_row", "open_run"]


def attach_phrasings(agent: Any, task: Any) -> None:
    """Give the agent the training-only phrasings of the instructions
    (``cfg.env.phrasings``), when the task embedded some."""
    found = task.phrasing_embeddings()
    if found is not None:
        agent.set_phrasings(*found)


def text_goal_sample(task: Any) -> np.ndarray:
    """The goal vectors the text-goal normaliser's statistics come from: the training
    instructions' embeddings and, with ``cfg.env.phrasings``, their other phrasings."""
    vectors = task.embeddings[: task.num_train]
    found = task.phrasing_embeddings()
    if found is None:
        return vectors
    variants, counts = found
    filled = np.arange(variants.shape[1])[None, :] < counts[:, None]
    return np.concatenate([vectors, variants[filled]], 0)


def attach_grounding(agent: Any, task: Any, cfg: TrainConfig) -> None:
    """Give the agent the slots each instruction names when ``cfg.agent.grounding`` is on
    and the task has instructions; other goals (state, image, task ids) name no object, so
    a preset's grounding loss stays off when its goal type is changed."""
    targets = task.grounding_targets() if cfg.agent.grounding else None
    if targets is not None:
        agent.set_grounding(targets)


def checkpoint_meta(
    cfg: TrainConfig,
    algo: str,
    problem: Any,
    env: Any,
    task: Any,
    step: int,
    episodes: int,
    eval_pending: bool = False,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``meta`` and JSON files of a run's checkpoint: config, algo, problem, env spaces,
    whether a periodic evaluation at this step is still to run, and for language tasks
    the instruction table, the split and the text encoder."""
    meta: dict[str, Any] = {
        "config": config_to_dict(cfg),
        "algo": algo,
        "problem": problem.to_dict(),
        "step": step,
        "episodes": episodes,
        "eval_pending": bool(eval_pending),
        "env": {
            "kind": cfg.env.kind,
            "observation_space": str(env.observation_space),
            "action_space": str(env.action_space),
        },
    }
    json_files: dict[str, Any] = {}
    table = task.table
    if table is not None:
        json_files["instructions"] = {"texts": table, "num_train": task.num_train}
        json_files["split"] = task.split.to_dict()
        meta["text_encoder"] = {
            "model": cfg.text_encoder.model,
            "dim": int(task.embeddings.shape[1]),
        }
    return meta, json_files


class Trainer(SequentialStages, Collection, BaseTrainer):
    """Builds everything a run needs from a :class:`TrainConfig` and runs it.

    Args:
        cfg: the run's configuration. With ``cfg.resume`` the latest checkpoint in
            ``cfg.out`` is loaded, with the config saved there (and ``cfg.total_steps``).
        resume_explore: ``explore`` fields a resumed run takes from ``cfg`` (the options
            given on its command line; see :func:`train.training.trainer.open_run`).
    """

    def __init__(self, cfg: TrainConfig, resume_explore: Mapping[str, Any] | None = None) -> None:
        cfg.validate()
        self.check_algo(cfg)
        self.out = Path(cfg.out)
        cfg, ckpt = open_run(cfg, resume_explore)
        self.cfg = cfg
        models = _learned_models(cfg)
        env_cfg = cfg.env
        if models is not None:  # the training env renders the frames the models read
            size = models.frame_shape[0]
            env_cfg = dataclasses.replace(
                cfg.env, extra={**cfg.env.extra, "image": True, "image_size": size}
            )
        if cfg.relabel.reward != "rule":
            # The env's own success is the privileged rule: ending a training episode there
            # would tell the policy what the learned rewards are to judge, and where they
            # miss it, teach that reaching the goal ends the episode with nothing. Episodes
            # run to the time limit; the value target still ends where the learned reward
            # says the goal was reached.
            env_cfg = dataclasses.replace(env_cfg, train_until_success=False)
        c = cfg.collect
        local_workers = c.workers if c.backend == "ray" and not c.address else 0
        set_threads(cfg.torch_threads, helpers=local_workers)
        if automatic_threads(cfg.torch_threads):
            self.thread_watch = ThreadWatcher(helpers=local_workers)
        #: The families of each sequential stage (empty: one stage of everything).
        self.stages = cfg.sequential.families()
        self.stage = 0
        self._env_cfg = env_cfg
        #: The training environments, stepped together (``collect.envs``).
        self.envs = self._make_envs(0)
        # the task (instruction table, checkpoints) spans every family of every stage
        self.env = make_env(env_cfg, "train", training=True) if self.stages else self.envs[0]
        self.task = build_task(cfg, self.env, ckpt)
        if models is not None:
            from captioner.learned import LearnedLabeller

            r = cfg.relabel
            self.task.labeller = LearnedLabeller(
                models,
                self.task.table,
                self.task.num_train,
                captioner=r.captioner in ("learned", "both"),
                reward_labels=r.captioner in ("reward", "both"),
                reward=r.reward == "learned",
                captioner_rewards=r.reward == "captioner",
                min_logprob=r.min_logprob,
                beam=r.beam,
                threshold=r.threshold,
                family_thresholds=family_thresholds(r.family_thresholds),
                agree=r.agree,
                confirm=r.confirm,
            )
        self.problem = self.task.problem()
        self.algo = cfg.resolved_algo(self.problem.discrete)
        self.agent: Agent = build_agent(
            self.algo, self.problem, cfg, self.task.goal_space.embed, self.env
        )
        self.buffer = self._new_buffer()
        self.rng = np.random.default_rng(cfg.seed)  # random actions
        self.scripted_rng = np.random.default_rng([cfg.seed, 1])  # scripted choice, noise
        self.memory_rng = np.random.default_rng([cfg.seed, 9])  # replay memory draws
        #: Sequential stages: the success matrix so far, the replay memory of each
        #: finished stage, the episodes of the current one (kept only for replay).
        self.stage_rows: list[dict[str, Any]] = []
        self.memory: list[list[dict[str, Any]]] = []
        self._stage_episodes: list[dict[str, Any]] = []
        if self.stages:
            self._stage_labels()
            if cfg.sequential.ewc:
                from lcrl.continual import EWC

                self.agent.ewc = EWC(cfg.sequential.ewc)
        #: One scripted controller per environment (none without scripted episodes).
        self.scripted = [
            ScriptedActor(cfg.env, self.task, cfg.scripted_noise)
            for _ in (self.envs if cfg.scripted_fraction > 0 or cfg.explore.handover else ())
        ]
        #: Chains, hand-overs and the family curriculum (None: all off).
        self.explorer = (
            Explorer(cfg.explore, cfg.env.families, self.scripted_rng)
            if cfg.explore.active
            else None
        )
        self._init_rest(cfg, ckpt)

    #: The replay buffer is filled again from its source on resume (offline runs), so
    #: checkpoints do not carry it.
    refills_buffer = False

    def check_algo(self, cfg: TrainConfig) -> None:
        """Refuse a learner that does not learn in this loop."""
        if cfg.algo in ALGOS and ALGOS[cfg.algo].learns_from != "env":
            raise LcrlError(
                f"{cfg.algo} learns from demonstrations, not in this loop: run it with lcrl "
                "train (train.training.bc.BCTrainer), or from any dataset with --offline FILE"
            )

    def _new_buffer(self) -> HindsightReplayBuffer:
        """An empty replay buffer of the run's settings, refused before it is allocated
        where the machine's memory cannot hold it (:func:`train.runtime.memory.check_memory`)."""
        cfg, p = self.cfg, self.problem
        spec = {
            k: (shape, np.uint8 if len(shape) == 3 else np.float32)
            for k, shape in p.obs_shapes.items()
        }
        action = (() if p.discrete else (p.action_dim,), np.int64 if p.discrete else np.float32)
        capacity = cfg.buffer.capacity
        need = HindsightReplayBuffer.estimate_bytes(capacity, spec, *action, self.task.goal_space)
        per_slot = need // max(capacity, 1)
        frames = any(len(shape) == 3 for shape, _ in spec.values())
        what = (
            f"the replay buffer ({capacity:,} slots of {per_slot:,} bytes"
            f"{', camera frames included' if frames else ''})"
        )
        check_memory(need, what, "--buffer.capacity", per_slot)
        return HindsightReplayBuffer(
            capacity,
            spec,
            *action,
            self.task.goal_space,
            strategy=cfg.buffer.strategy,
            k=cfg.buffer.k,
            seed=cfg.seed,
            random_fraction=cfg.buffer.random_fraction,
            n_step=cfg.buffer.n_step,
            gamma=getattr(self.agent.cfg, "gamma", 0.99),  # bc has none (n_step 1)
            device=self.agent.device if cfg.buffer.storage == "device" else None,
        )

    def _make_envs(self, stage: int) -> list[Any]:
        """The training environments of a stage (its families only, with stages)."""
        env_cfg = self._env_cfg
        if self.stages:
            env_cfg = dataclasses.replace(env_cfg, families=self.stages[stage])
        return [make_env(env_cfg, "train", training=True) for _ in range(self.cfg.collect.envs)]

    def _init_rest(self, cfg: TrainConfig, ckpt: Any) -> None:
        """The task sampler, the counters, and what a checkpoint restores."""
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
        # BC -> RL fine-tuning (cfg.finetune): offline updates done, demonstrations stored
        self.pretrained = 0
        self._demos_loaded = False
        if cfg.finetune.demos:
            self._check_demos()
        if ckpt is not None:
            self.restore(ckpt)
        elif self.task.text_goals:
            self.agent.observe({}, text_goal_sample(self.task))
        attach_grounding(self.agent, self.task, cfg)
        attach_phrasings(self.agent, self.task)
        if self.explorer is not None:
            self.explorer.apply(self.envs)
        if cfg.collect.backend == "ray":
            self.start_workers()

    # --- the loop ------------------------------------------------------------------
    def advance(self) -> None:
        """Collect one episode per environment (acting, stepping, updating) and store
        them; with Ray workers, store the next episode one returns and update."""
        if self.stages:
            if not self.stage_rows:  # before the first stage: the forward-transfer base
                self._stage_row("init")
            if self.step >= self._stage_end(self.stage) and self.stage < len(self.stages) - 1:
                with self.holding_signals():  # a stage ends whole: a stop waits for it
                    self.next_stage()
        ft = self.cfg.finetune
        if ft.demos:
            if not self._demos_loaded:
                with self.holding_signals():  # the file goes in whole
                    self._load_demos()
            if self.pretrained < ft.pretrain_updates:
                self._pretrain()
                return
            self.agent.q_weight, self.agent.extra_bc = 1.0, ft.weight(self.step)
        if self.cfg.collect.backend == "ray":
            self.collect_remote()
        else:
            self.collect_episode()
        if self.stages and self.cfg.sequential.replay:
            self._stage_episodes.extend(self._last_episodes)

    # --- BC -> RL fine-tuning ----------------------------------------------------------
    def _check_demos(self) -> None:
        """The demonstration file fits this run (one error line naming what does not)."""
        from lcrl.demos import DemoDataset
        from train.training.demos import check_dataset

        path = self.cfg.finetune.demos
        with DemoDataset(path) as data:
            check_dataset(data, path, self.problem, self.task, self.env)

    def _load_demos(self) -> None:
        """Every episode of ``finetune.demos`` into the replay buffer, labelled like the
        run's own episodes (they age out as the buffer fills, like any episode)."""
        from lcrl.demos import DemoDataset
        from train.training.demos import buffer_episode

        path = self.cfg.finetune.demos
        with DemoDataset(path) as data:
            for e in range(data.num_episodes):
                episode = buffer_episode(data, e, path, self.task, self.env)
                self.buffer.add_episode(episode)
                self.agent.observe(episode["obs"], episode.get("achieved_goal"))
            steps = data.num_steps
        self._demos_loaded = True
        print(
            f"fine-tuning from {path}: {data.num_episodes} episodes ({steps} steps) in the "
            f"replay buffer; {self.cfg.finetune.pretrain_updates - self.pretrained} offline "
            "updates first",
            flush=True,
        )

    def _pretrain(self) -> None:
        """A block of offline updates on what the buffer holds: the critic as online, the
        actor cloning (no Q term; the hindsight BC term at ``finetune.bc_weight``)."""
        ft = self.cfg.finetune
        self._start = self.snapshot()
        n = min(500, ft.pretrain_updates - self.pretrained)
        self.agent.q_weight, self.agent.extra_bc = 0.0, ft.bc_weight
        self._update(n)
        self.pretrained += n
        self._start = None

    # --- sequential stages -------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """Everything an episode changes before it is stored, copied: the learner's
        weights, optimiser and random states, the random generators, the step and the
        update credit, the metrics gathered for the next progress row."""
        return {
            "modules": {
                name: copy.deepcopy(module.state_dict())
                for name, module in self.agent.modules().items()
            },
            "states": copy.deepcopy(self.agent.states()),
            "rngs": [g.bit_generator.state for g in self._generators()],
            "step": self.step,
            "credit": self._credit,
            "metrics": (dict(self._metrics), self._metric_count),
            "grad": {k: list(v) for k, v in self._grad_metrics.items()},
            "explore": None if self.explorer is None else copy.deepcopy(self.explorer.state_dict()),
        }

    def _generators(self) -> list[np.random.Generator]:
        return [self.rng, self.scripted_rng, self.task_rng, self.buffer.rng]

    def rollback(self) -> None:
        """Undo the episode in hand (nothing when the run is between episodes)."""
        start = getattr(self, "_start", None)
        if start is None:
            return
        for name, module in self.agent.modules().items():
            module.load_state_dict(start["modules"][name])
        self.agent.load_states(start["states"])
        for g, state in zip(self._generators(), start["rngs"], strict=True):
            g.bit_generator.state = state
        self.step, self._credit = start["step"], start["credit"]
        (self._metrics, self._metric_count) = start["metrics"]
        self._grad_metrics = start["grad"]
        if self.explorer is not None:
            self.explorer.load_state_dict(start["explore"])
            self.explorer.drop_pending()
        self._start = None

    def _updates_due(self, steps: int = 1) -> int:
        """Gradient updates due after ``steps`` environment steps."""
        cfg = self.cfg
        if self.step < cfg.learning_starts or self.buffer.size == 0:
            return 0
        self._credit += cfg.updates_per_step * steps
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

    def finish(self) -> dict[str, Any]:
        """The end of the run; with sequential stages, the last stage's matrix row first."""
        if self.stages and len(self.stage_rows) == self.stage + 1:
            self._stage_row("+".join(self.stages[self.stage]))
        return super().finish()

    def close(self) -> None:
        """Close the training environments, the Ray workers and the logs."""
        envs = list(getattr(self, "envs", ()))
        if envs and getattr(self, "stages", None):
            envs.append(self.env)  # the table's env of a sequential run
        for env in envs:
            env.close()
        self.envs = []
        if self.remote is not None:
            self.remote.close()
            self.remote = None
        super().close()

    # --- logging --------------------------------------------------------------------
    def postfix(self) -> str:
        """Episodes, the live success rate and the last evaluation."""
        sr = np.mean(self.recent) if self.recent else 0.0
        return f"ep {self.episodes} success {sr:.2f} " + super().postfix()

    def log(self) -> None:
        """A progress.csv row: counts, live success, speed, mean update metrics."""
        row: dict[str, Any] = {
            "step": self.step,
            "episodes": self.episodes,
            "success": float(np.mean(self.recent)) if self.recent else 0.0,
            "steps_per_s": self.rate(),
            "updates": self.agent.updates,
            "buffer": self.buffer.size,
            "sim_errors": self.sim_errors,
            "scripted_episodes": self.scripted_episodes,
            "torch_threads": torch.get_num_threads(),
        }
        if self.cfg.collect.backend == "ray":
            # this process's Ray worker restarts (each dropped the episode in hand)
            row["worker_restarts"] = self.remote.restarts if self.remote is not None else 0
        labeller = self.task.labeller
        if labeller is not None:  # learned relabelling, against the rule captioner
            row.update(labeller.agreement())
        n = max(self._metric_count, 1)
        row.update({k: v / n for k, v in sorted(self._metrics.items())})
        self._metrics, self._metric_count = {}, 0
        row.update(self._multitask_columns())
        if self.explorer is not None:
            row.update(self.explorer.columns())
        self.progress_log.write(row)
        self.last_logged = self.step
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
        learned = getattr(self.agent, "learned_task_weights", lambda: None)()
        if learned is not None:  # GradNorm's weights, every column from the first row
            for i, w in enumerate(learned):
                row[f"tasks/{i}/weight"] = float(w)
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
        meta, json_files = checkpoint_meta(
            cfg,
            self.algo,
            self.problem,
            self.env,
            self.task,
            self.step,
            self.episodes,
            self.eval_pending,
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
                "train_s": self.train_seconds(),
                "pretrained": self.pretrained,
                "demos_loaded": self._demos_loaded,
            },
        }
        if self.explorer is not None:
            states["explore"] = self.explorer.state_dict()
        if self.stages:
            states["sequential"] = {"stage": self.stage, "rows": self.stage_rows}
            if self.agent.ewc is not None:
                states["ewc"] = self.agent.ewc.state_dict()
        if self.sampler is not None:
            states["task_sampler"] = self.sampler.state_dict()
            states["task_rng"] = self.task_rng.bit_generator.state
        arrays = self.buffer.arrays() if cfg.save_buffer and not self.refills_buffer else None
        return self.write_checkpoint(meta, json_files, states, arrays)

    def restore(self, ckpt: Any) -> None:
        """Weights, optimiser and RNG states, counters and the replay buffer of a
        checkpoint."""
        self.resume_schedule(ckpt)
        trainer = state_fields(
            ckpt,
            "trainer",
            {"step": int, "episodes": int, "recent": list, "credit": float},
            optional={
                "sim_errors": int,
                "scripted_episodes": int,
                "train_s": float,
                "pretrained": int,
                "demos_loaded": bool,
            },
        )
        for name, module in self.agent.modules().items():
            ckpt.load_module(name, module)
        with restoring(ckpt, "the learner's states"):
            states = {name: ckpt.state(name) for name in self.agent.states()}
            self.agent.load_states(states)
        for name, rng in (("buffer_rng", self.buffer.rng), ("trainer_rng", self.rng)):
            with restoring(ckpt, f"the state {name!r}"):
                rng.bit_generator.state = ckpt.state(name)
        if ckpt.has_state("scripted_rng"):
            with restoring(ckpt, "the state 'scripted_rng'"):
                self.scripted_rng.bit_generator.state = ckpt.state("scripted_rng")
        self.step, self.episodes = int(trainer["step"]), int(trainer["episodes"])
        self.sim_errors = int(trainer.get("sim_errors", 0))
        self.scripted_episodes = int(trainer.get("scripted_episodes", 0))
        self.recent.extend(float(x) for x in trainer["recent"])
        self._credit = float(trainer["credit"])
        self.train_s_before = float(trainer.get("train_s", 0.0))
        self.pretrained = int(trainer.get("pretrained", 0))
        # demonstrations come back with the buffer; without it they are loaded again
        self._demos_loaded = bool(trainer.get("demos_loaded", False)) and ckpt.has_arrays()
        if self.sampler is not None and ckpt.has_state("task_sampler"):
            with restoring(ckpt, "the states 'task_sampler' and 'task_rng'"):
                self.sampler.load_state_dict(ckpt.state("task_sampler"))
                self.task_rng.bit_generator.state = ckpt.state("task_rng")
        if self.stages and ckpt.has_state("sequential"):
            self._restore_stage(ckpt)
        if self.explorer is not None and ckpt.has_state("explore"):
            with restoring(ckpt, "the state 'explore'"):
                self.explorer.load_state_dict(ckpt.state("explore"))
        if ckpt.has_arrays():
            self.buffer.load_arrays(ckpt.arrays())
        print(f"resumed {self.out} at step {self.step} ({self.episodes} episodes)")
        if not ckpt.has_arrays() and not self.refills_buffer:
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

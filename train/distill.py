"""Teacher -> student distillation with DAgger: ``lcrl distill TEACHER_RUN``.

A policy trained on the simulator's privileged state (the teacher) is distilled into a
student that acts from what the cameras show: the object slots a perception model
estimates from each frame (``--perception MODEL``), or the camera frames and the robot's
proprioception themselves (``--image-obs``, a CNN: the GPU path). Both see the same
instruction embedding, so the student inherits the teacher's instruction table.

DAgger (Ross et al., 2011), one round at a time:

1. collect ``distill.episodes_per_round`` episodes. At every step the teacher names its
   action for the true state; the action executed is the teacher's with probability
   ``beta_r = beta * beta_decay ** r`` and the student's own otherwise, so control is
   handed over round by round and the student visits the states its own mistakes lead to;
2. add every visited state, with the teacher's action, to the dataset (it only grows);
3. run ``distill.updates_per_round`` behavioural-cloning updates of the student on the
   whole dataset (:class:`lcrl.bc.BC`, squared error of the mean action).

``total_steps``, ``eval_every``, ``checkpoint_every`` and ``log_every`` count rounds. The
student's checkpoints are ``bc`` policies in the format of every run (with the perception
model they act through), so ``lcrl eval``, ``lcrl act``, ``lcrl.load`` and ``lcrl report``
work unchanged. Checkpoints keep the dataset, so ``--resume`` continues exactly; a stop
inside a round goes back to the round's start.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from train.config import BCConfig, ExploreConfig, FinetuneConfig, TrainConfig
from train.evaluate import build_agent, build_task, load_policy, resolve_checkpoint
from train.loop import attach_grounding, checkpoint_meta
from train.tasks import make_env
from train.trainer import BaseTrainer, open_run

#: Seeds of the collection episodes: round r, episode e of a run with seed s.
EPISODE_SEED = 1_000_003


def student_config(
    teacher_cfg: TrainConfig,
    *,
    perception: str = "",
    image_obs: bool = False,
    out: str = "runs/distill",
    **overrides: Any,
) -> TrainConfig:
    """The student's run config: the teacher's environment and networks, acting through
    ``perception`` (or from ``image_obs``), cloned with ``algo="bc"``; ``overrides`` set
    any other :class:`TrainConfig` field (``distill``, ``total_steps`` ...). How the
    teacher's own episodes were shaped (``explore``: chains, hand-overs, a curriculum) and
    the demonstrations it started from (``finetune``) are not the student's: DAgger
    collects its episodes itself.

    Raises:
        LcrlError: neither a perception model nor image observations, or both.
    """
    if bool(perception) == bool(image_obs):
        raise LcrlError(
            "the student acts from camera frames: give --perception MODEL (object slots "
            "estimated from each frame) or --image-obs (a CNN over the frames), one of them"
        )
    cfg = copy.deepcopy(teacher_cfg)
    env = dataclasses.replace(cfg.env, perception=perception, image_obs=image_obs)
    agent = dataclasses.replace(cfg.agent, privileged_critic=False)
    return dataclasses.replace(
        cfg,
        out=out,
        env=env,
        agent=agent,
        algo="bc",
        bc=BCConfig(loss="mse", hindsight=False),
        demos="",
        explore=ExploreConfig(),
        finetune=FinetuneConfig(),
        resume=False,
        overwrite=False,
        **overrides,
    )


class DistillTrainer(BaseTrainer):
    """DAgger from a privileged-state teacher (``cfg.distill.teacher``) into a ``bc``
    student that acts from camera frames.

    Args:
        cfg: the student's run config (:func:`student_config`). With ``cfg.resume`` the
            latest checkpoint in ``cfg.out`` is loaded, with its config (and
            ``cfg.total_steps``).

    Raises:
        LcrlError: no teacher, a teacher without language goals or of another environment
            than the student's, or a student that reads the true state.
    """

    unit = "round"

    def __init__(self, cfg: TrainConfig) -> None:
        cfg.validate()
        if not cfg.distill.teacher:
            raise LcrlError("distillation needs a teacher: lcrl distill TEACHER_RUN")
        if cfg.algo != "bc":
            raise LcrlError(f"the student is a bc policy, not {cfg.algo!r}")
        teacher = load_policy(resolve_checkpoint(cfg.distill.teacher))
        self.out = Path(cfg.out)
        cfg, ckpt = open_run(cfg)
        self.cfg = cfg
        self.algo = "bc"
        self.teacher = teacher
        self.env = make_env(cfg.env, "train", training=True)
        try:
            self._build(ckpt)
        except BaseException:
            self.env.close()
            raise

    def _build(self, ckpt: Any) -> None:
        cfg, teacher = self.cfg, self.teacher
        if teacher.task.query != "text":
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} was not trained with language goals "
                f"({teacher.cfg.env.goal_type} goals): DAgger here distils instruction-"
                "following policies"
            )
        if teacher.cfg.env.image_obs or teacher.cfg.env.perception:
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} acts from camera frames itself: a "
                "teacher reads the privileged state"
            )
        space = self.env.observation_space
        source = "privileged" if "privileged" in space.spaces else "observation"
        self._source = source
        theirs = tuple(teacher.task.problem().obs_shapes["observation"])
        ours = tuple(space[source].shape)
        if theirs != ours or teacher.cfg.env.kind != cfg.env.kind:
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} reads the {teacher.cfg.env.kind} env's "
                f"state of shape {theirs}; the student's {cfg.env.kind} env gives {ours}: "
                "distil a teacher of the same environment and observation features"
            )
        table = (list(teacher.task.table), teacher.task.num_train)  # the teacher's ids
        self.task = build_task(cfg, self.env, ckpt, table=None if ckpt else table)
        if list(self.task.table) != list(teacher.task.table):
            raise LcrlError(
                "the student's instruction table differs from the teacher's: resume with the "
                "run's own config"
            )
        self.problem = self.task.problem()
        if self.problem.privileged:
            raise LcrlError("the student is a policy: it reads no privileged state")
        self.agent = build_agent("bc", self.problem, cfg, self.task.goal_space.embed)
        self.keys = list(self.problem.obs_shapes)
        self.data: dict[str, list[np.ndarray]] = {k: [] for k in [*self.keys, "action", "goal"]}
        self.rng = np.random.default_rng([cfg.seed, 3])
        self.step = 0
        self.episodes = 0
        self.rows = 0
        self._round: dict[str, float] = {}
        self._start: dict[str, Any] | None = None
        if ckpt is not None:
            self.restore(ckpt)
        else:
            self.agent.observe({}, self.task.embeddings[: self.task.num_train])
        attach_grounding(self.agent, self.task, cfg)

    # --- the loop --------------------------------------------------------------------
    def begin(self) -> None:
        """Say who teaches whom."""
        cfg = self.cfg
        how = f"perception {cfg.env.perception}" if cfg.env.perception else "camera frames"
        print(
            f"DAgger: teacher {self.teacher.checkpoint.path} (step "
            f"{self.teacher.checkpoint.meta.get('step')}) -> student acting through {how}; "
            f"{cfg.distill.episodes_per_round} episodes and {cfg.distill.updates_per_round} "
            "updates per round"
        )

    def beta(self, round_index: int) -> float:
        """The teacher's share of the executed actions in a round."""
        d = self.cfg.distill
        return float(d.beta * d.beta_decay**round_index) if round_index else float(d.beta)

    def advance(self) -> None:
        """One DAgger round: collect with the mixed policy, label with the teacher,
        aggregate, fit the student."""
        self._start = self.snapshot()
        cfg = self.cfg
        beta = self.beta(self.step)
        added, teacher_steps, steps, successes = 0, 0, 0, 0
        for e in range(cfg.distill.episodes_per_round):
            seed = int(cfg.seed * EPISODE_SEED * 7 + self.step * 1000 + e)
            rows, executed, success = self._episode(seed, beta)
            added += rows
            teacher_steps += executed
            steps += rows
            successes += int(success)
        losses = []
        for _ in range(cfg.distill.updates_per_round):
            losses.append(self.agent.update(self._batch())["loss"])
        with self.holding_signals():  # a round is counted whole, or not at all
            self.step += 1
            self.episodes += cfg.distill.episodes_per_round
            self._round = {
                "beta": beta,
                "teacher_share": teacher_steps / max(steps, 1),
                "success": successes / cfg.distill.episodes_per_round,
                "rows": float(self.rows),
                "loss": float(np.mean(losses)) if losses else float("nan"),
                "loss_first": float(losses[0]) if losses else float("nan"),
            }
            self._start = None

    def _episode(self, seed: int, beta: float) -> tuple[int, int, bool]:
        """One episode under the mixed policy; every visited state is kept with the
        teacher's action. Returns the rows added, the teacher's executed steps and
        whether the instruction was achieved."""
        env, task, teacher = self.env, self.task, self.teacher
        obs, _ = env.reset(seed=seed)
        first = obs
        goal = task.goal(obs, env)
        goal_batch = np.asarray([goal])
        rows: dict[str, list[np.ndarray]] = {k: [] for k in self.data}
        executed, success = 0, False
        while True:
            mine = task.storage_obs(obs, first)
            view = {"observation": obs[self._source]}
            theirs = teacher.task.storage_obs(view, {"observation": first[self._source]})
            label = teacher.agent.act(
                {k: v[None] for k, v in theirs.items()}, goal_batch, deterministic=True
            )[0]
            for k in self.keys:
                rows[k].append(mine[k])
            rows["action"].append(np.asarray(label, np.float32))
            rows["goal"].append(np.asarray(goal, np.int64))
            if self.rng.random() < beta:
                action = label
                executed += 1
            else:
                batch = {k: v[None] for k, v in mine.items()}
                action = self.agent.act(batch, goal_batch, deterministic=True)[0]
            obs, _, terminated, truncated, info = env.step(task.scale_action(action))
            success = success or bool(info.get("is_success", False))
            if terminated or truncated:
                break
        for k, v in rows.items():
            self.data[k].append(np.stack(v))
        n = len(rows["action"])
        self.rows += n
        self.agent.observe({k: np.stack(rows[k]) for k in self.keys})
        return n, executed, success

    def _batch(self) -> Batch:
        """Rows drawn uniformly from everything gathered so far."""
        arrays = self._arrays()
        idx = self.rng.integers(self.rows, size=self.cfg.batch_size)
        obs = {k: arrays[k][idx] for k in self.keys}
        n = len(idx)
        return Batch(
            obs=obs,
            action=arrays["action"][idx],
            reward=np.zeros(n, np.float32),
            next_obs=obs,
            terminated=np.zeros(n, np.float32),
            goal=arrays["goal"][idx],
            relabelled=np.zeros(n, bool),
            index=idx,
        )

    def _arrays(self) -> dict[str, np.ndarray]:
        """The dataset as one array per key (consolidated on first use after a round)."""
        for k, parts in self.data.items():
            if len(parts) > 1:
                self.data[k] = [np.concatenate(parts)]
        return {k: parts[0] for k, parts in self.data.items()}

    # --- stopping inside a round --------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """What a round changes before it is counted, copied."""
        return {
            "modules": {
                name: copy.deepcopy(m.state_dict()) for name, m in self.agent.modules().items()
            },
            "states": copy.deepcopy(self.agent.states()),
            "rng": self.rng.bit_generator.state,
            "data": {k: list(v) for k, v in self.data.items()},
            "rows": self.rows,
        }

    def rollback(self) -> None:
        """Undo the round in hand (nothing between rounds)."""
        start = self._start
        if start is None:
            return
        for name, module in self.agent.modules().items():
            module.load_state_dict(start["modules"][name])
        self.agent.load_states(start["states"])
        self.rng.bit_generator.state = start["rng"]
        self.data, self.rows = start["data"], start["rows"]
        self._start = None

    # --- logging ---------------------------------------------------------------------
    def postfix(self) -> str:
        """The last round's teacher share and loss, and the last evaluation."""
        r = self._round
        text = f"beta {r['beta']:.2f} loss {r['loss']:.4g} " if r else ""
        return text + super().postfix()

    def log(self) -> None:
        """A progress.csv row per round: the teacher's share, the students' loss, the
        mixed policy's success, the dataset's size."""
        row: dict[str, Any] = {
            "step": self.step,
            "episodes": self.episodes,
            "updates": self.agent.updates,
            "steps_per_s": self.rate(),
            **self._round,
        }
        self.progress_log.write(row)
        self.last_logged = self.step
        if self.tb is not None:
            for k, v in row.items():
                if k != "step":
                    self.tb.add_scalar(f"train/{k}", v, self.step)

    # --- checkpoints -----------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint the student (with the perception model it acts through), the
        dataset and the random state."""
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
        meta["distill"] = {
            "teacher": str(self.teacher.checkpoint.path),
            "teacher_step": self.teacher.checkpoint.meta.get("step"),
            "rows": self.rows,
        }
        states = {
            **self.agent.states(),
            "trainer": {"step": self.step, "episodes": self.episodes, "round": self._round},
            "rng": self.rng.bit_generator.state,
        }
        arrays = {f"data_{k}": v for k, v in self._arrays().items()} if self.rows else None
        return self.write_checkpoint(meta, json_files, states, arrays)

    def restore(self, ckpt: Any) -> None:
        """The student, the dataset and the random state of a checkpoint."""
        self.resume_schedule(ckpt)
        for name, module in self.agent.modules().items():
            ckpt.load_module(name, module)
        self.agent.load_states({name: ckpt.state(name) for name in self.agent.states()})
        trainer = ckpt.state("trainer")
        self.step = int(trainer["step"])
        self.episodes = int(trainer["episodes"])
        self._round = dict(trainer.get("round") or {})
        self.rng.bit_generator.state = ckpt.state("rng")
        if ckpt.has_arrays():
            arrays = ckpt.arrays()
            self.data = {k: [np.asarray(arrays[f"data_{k}"])] for k in self.data}
            self.rows = len(self.data["action"][0])
        print(f"resumed {self.out} at round {self.step} ({self.rows} labelled states)")

    def close(self) -> None:
        """Close the environments and TensorBoard."""
        self.env.close()
        self.teacher.env.close()
        super().close()

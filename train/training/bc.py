"""Behavioural cloning from a demonstration file: ``lcrl train lang2d-bc --demos FILE``.

:class:`BCTrainer` reads an ``lcrl-demos`` file (``lcrl demos record``), builds the
environment and instruction table of the config exactly as an RL run does, checks that the
demonstrations fit the environment (observation keys and shapes, action space), maps the
dataset's instructions onto the table by their text, then runs ``total_steps`` gradient
updates of :class:`lcrl.bc.BC` on uniformly drawn segment transitions. With BC,
``total_steps``, ``eval_every``, ``checkpoint_every`` and ``log_every`` count gradient
updates. Evaluations run the policy in the environment on every instruction set (seen,
held-out combinations, paraphrases); logs (progress.csv, eval.csv, TensorBoard),
checkpoints (``algo = "bc"``) and the report have the format of RL runs, so
``lcrl eval RUN``, ``lcrl act RUN``, ``lcrl.load(RUN)`` and ``lcrl report RUN`` work
unchanged.

Instructions
    A dataset instruction whose text is a training instruction of the table trains that
    entry. One that is missing from the table but that the grammar parses (a phrasing of a
    training meaning, e.g. from a relabelled or imported dataset) becomes a training
    instruction of its own: it is added to the training part of the table, which the
    checkpoint saves. Refused, with the offending texts: instructions of the held-out
    combinations or the paraphrase set of the split (training on them would leak the
    evaluation), instructions of families the run does not train, and texts the grammar
    cannot parse.

Resuming
    The batch stream is reseeded at every periodic checkpoint (every ``checkpoint_every``
    updates) with a seed made of the run's seed and the checkpoint's index; a run resumed
    from any checkpoint, periodic or written on Ctrl-C, re-creates the stream of its block
    and skips the batches already used, so it continues exactly as the uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.algos import ALGOS
from lcrl.bc import BC
from lcrl.errors import LcrlError
from train.configs.config import TrainConfig
from train.configs.presets import PRESETS
from train.configs.run_meta import restoring, state_fields
from train.environments.tasks import make_env, make_task
from train.evaluation.evaluate import build_agent, build_task
from train.runtime.memory import check_memory
from train.training.loop import attach_grounding, checkpoint_meta
from train.training.trainer import BaseTrainer, open_run

#: What to do when no demonstration file is given.
DEMOS_HINT = "pass --demos FILE (record one with lcrl demos record)"
#: Seeds of the batch stream: block b of a run with seed s draws with s * STREAM_SEED + b.
STREAM_SEED = 1_000_003
#: Rows per batch when fitting the observation normalisers.
NORM_BATCH = 1024


def open_demos(path: str) -> Any:
    """Open a demonstration file (:class:`lcrl.demos.DemoDataset`).

    Raises:
        LcrlError: no path given, no file there, or not a demonstration file.
    """
    if not path:
        raise LcrlError(f"behavioural cloning needs demonstrations: {DEMOS_HINT}")
    if not Path(path).is_file():
        raise LcrlError(f"no demonstration file at {path}: {DEMOS_HINT}")
    from lcrl.demos import DemoDataset

    return DemoDataset(path)


class BCTrainer(BaseTrainer):
    """Builds a behavioural-cloning run from a :class:`TrainConfig` (``algo="bc"``) and
    runs it.

    Args:
        cfg: the run's configuration; ``cfg.demos`` names the demonstration file. With
            ``cfg.resume`` the latest checkpoint in ``cfg.out`` is loaded, with the config
            saved there (and ``cfg.total_steps``).

    Raises:
        LcrlError: no or unreadable demonstrations, demonstrations that do not fit the
            environment, or instructions that cannot be trained on.
    """

    def __init__(self, cfg: TrainConfig) -> None:
        cfg.validate()
        spec = ALGOS.get(cfg.algo)
        if spec is None or spec.learns_from != "demos":
            learners = [name for name, s in ALGOS.items() if s.learns_from == "demos"]
            raise LcrlError(
                f"BCTrainer trains algorithms that learn from demonstrations "
                f"({', '.join(learners)}), not {cfg.algo!r}: pass --algo {learners[0]}"
            )
        if not cfg.resume:  # check before a previous run in --out is cleared
            open_demos(cfg.demos).close()
        self.out = Path(cfg.out)
        cfg, ckpt = open_run(cfg)
        self.cfg = cfg
        self.algo = cfg.algo
        self.data = open_demos(cfg.demos)
        try:
            self._build(ckpt)
        except BaseException:
            self.data.close()
            if getattr(self, "env", None) is not None:
                self.env.close()
            raise

    def _build(self, ckpt: Any) -> None:
        cfg, data = self.cfg, self.data
        self.env = make_env(cfg.env, "train", training=True)
        task = build_task(cfg, self.env, ckpt)
        if task.table is None:
            raise LcrlError(
                "behavioural cloning learns instruction-following from demonstrations: it "
                f"needs language goals (lang2d, or robosuite with goal_type language), not a "
                f"{cfg.env.kind} env with {cfg.env.goal_type} goals"
            )
        self.problem = task.problem()
        check_demos(data, self.problem, cfg)
        recorded = recorded_env(data)
        diff = env_differences(recorded, cfg) if recorded is not None else []
        if diff and ckpt is None:
            print(
                f"note: {cfg.demos} was recorded with other env options than this run's "
                f"({' '.join(diff)}); the shapes fit, and the policy is evaluated on this "
                "run's env"
            )
        self.segments = data.segments(hindsight=cfg.bc.hindsight)
        if len(self.segments) == 0:
            raise LcrlError(f"{cfg.demos} holds no segments to learn from")
        used = sorted({int(i) for i in self.segments[:, 3]})
        texts = [data.instructions[i] for i in used]
        fixed = bool(getattr(cfg.env, "tasks", ()))  # a task set: the table is exactly it
        extras = match_instructions(texts, task, cfg.demos, allow_new=not fixed)
        if extras:  # new phrasings of training meanings join the training instructions
            n = task.num_train
            table = [*task.table[:n], *extras, *task.table[n:]]
            encoder = task.encoder
            task = make_task(
                cfg.env, self.env, encoder.encode, table=table, num_train=n + len(extras)
            )
            task.encoder = encoder
        self.task = task
        self.goal_map = np.full(len(data.instructions), -1, np.int64)
        for i, text in zip(used, texts, strict=True):
            self.goal_map[i] = task.ids[text]
        self.rows = int((self.segments[:, 2] - self.segments[:, 1]).sum())
        self.keys = list(self.problem.obs_shapes)
        self._check_cache(data.num_observations)
        self.agent: BC = build_agent(self.algo, self.problem, cfg, task.goal_space.embed)
        self.step = 0
        self._metrics: dict[str, float] = {}
        self._metric_count = 0
        self._stream: Iterator[Any] | None = None
        self._last_metrics: Mapping[str, float] = {}
        if ckpt is not None:
            self.restore(ckpt)
        else:
            self.fit_normalisers()

    # --- data ------------------------------------------------------------------------
    def _check_cache(self, observations: int) -> None:
        """Refuse a demonstration cache (``bc.cache_steps`` observations held in memory,
        camera frames included) that the machine's memory cannot hold."""
        per_obs = sum(
            int(np.prod(shape)) * (1 if len(shape) == 3 else 4)
            for shape in self.problem.obs_shapes.values()
        )
        held = min(self.cfg.bc.cache_steps, observations)
        what = f"the demonstration cache ({held:,} observations of {per_obs:,} bytes)"
        check_memory(held * per_obs, what, "--bc.cache-steps", per_obs, "observations")

    def fit_normalisers(self) -> None:
        """Fit the observation normalisers on up to ``bc.norm_rows`` dataset rows (and the
        text-goal normaliser on the training instructions' embeddings)."""
        cfg = self.cfg
        vector_keys = [k for k, shape in self.problem.obs_shapes.items() if len(shape) == 1]
        if cfg.agent.normalize_obs and vector_keys:
            rows = min(cfg.bc.norm_rows, self.rows)
            stream = self.data.batches(
                NORM_BATCH,
                vector_keys,
                seed=cfg.seed * STREAM_SEED + STREAM_SEED - 1,
                hindsight=cfg.bc.hindsight,
                cache_steps=cfg.bc.cache_steps,
            )
            for _ in range(math.ceil(rows / NORM_BATCH)):
                self.agent.observe(next(stream).obs)
            _close(stream)
        if self.task.text_goals:
            self.agent.observe({}, self.task.embeddings[: self.task.num_train])
        attach_grounding(self.agent, self.task, cfg)

    def _open_stream(self) -> Iterator[Any]:
        """The batch stream at the current step: its block's stream, with the batches
        this block already used skipped."""
        cfg = self.cfg
        every = cfg.checkpoint_every
        block = self.step // every if every else 0
        stream = self.data.batches(
            cfg.batch_size,
            self.keys,
            seed=cfg.seed * STREAM_SEED + block,
            hindsight=cfg.bc.hindsight,
            cache_steps=cfg.bc.cache_steps,
        )
        for _ in range(self.step - block * every):
            next(stream)
        return stream

    def _batch(self) -> Any:
        """The next batch, goals as ids of the run's instruction table."""
        if self._stream is None:
            self._stream = self._open_stream()
        batch = next(self._stream)
        return batch._replace(goal=self.goal_map[np.asarray(batch.goal, np.int64)])

    # --- the loop --------------------------------------------------------------------
    unit = "update"

    # --- the loop ----------------------------------------------------------------------
    def begin(self) -> None:
        """Say what is cloned."""
        cfg = self.cfg
        print(
            f"behavioural cloning on {cfg.demos}: {self.data.num_episodes} episodes, "
            f"{len(self.segments)} segments ({self.rows} transitions, hindsight "
            f"{'on' if cfg.bc.hindsight else 'off'}), {int((self.goal_map >= 0).sum())} "
            "instructions"
        )

    def advance(self) -> None:
        """One gradient update on a batch of demonstration transitions."""
        batch = self._batch()
        with self.holding_signals():  # an update is applied and counted whole
            metrics = self.agent.update(batch)
            self.step += 1
        for k, v in metrics.items():
            self._metrics[k] = self._metrics.get(k, 0.0) + v
        self._metric_count += 1
        self._last_metrics = metrics

    def after_checkpoint(self) -> None:
        """The next block of batches draws from a fresh stream (what resuming re-creates)."""
        _close(self._stream)
        self._stream = None

    def close(self) -> None:
        """Close the batch stream, the demonstration file, the env and TensorBoard."""
        _close(self._stream)
        self._stream = None
        self.data.close()
        self.env.close()
        super().close()

    # --- logging ---------------------------------------------------------------------
    def postfix(self) -> str:
        """The last update's loss and the last evaluation."""
        loss = self._last_metrics.get("loss")
        text = f"loss {loss:.4g} " if loss is not None else ""
        return text + super().postfix()

    def log(self) -> None:
        """A progress.csv row: updates, epochs, speed, mean losses."""
        row: dict[str, Any] = {
            "step": self.step,
            "updates": self.agent.updates,
            "epochs": self.step * self.cfg.batch_size / max(self.rows, 1),
            # no training episodes: the curve of live success stays empty
            "success": float("nan"),
            "steps_per_s": self.rate(),
        }
        n = max(self._metric_count, 1)
        row.update({k: v / n for k, v in sorted(self._metrics.items())})
        self._metrics, self._metric_count = {}, 0
        self.progress_log.write(row)
        self.last_logged = self.step
        if self.tb is not None:
            for k, v in row.items():
                if k not in ("step", "success"):
                    self.tb.add_scalar(f"train/{k}", v, self.step)

    # --- checkpoints -----------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint the run: weights, optimiser and RNG state, the instruction table."""
        cfg = self.cfg
        meta, json_files = checkpoint_meta(
            cfg, self.algo, self.problem, self.env, self.task, self.step, 0, self.eval_pending
        )
        meta["demos"] = {
            "path": str(cfg.demos),
            "episodes": int(self.data.num_episodes),
            "segments": len(self.segments),
            "transitions": self.rows,
            "hindsight": bool(cfg.bc.hindsight),
        }
        states = {**self.agent.states(), "trainer": {"step": self.step}}
        return self.write_checkpoint(meta, json_files, states)

    def restore(self, ckpt: Any) -> None:
        """Weights, optimiser and RNG states and the batch stream's place."""
        self.resume_schedule(ckpt)
        trainer = state_fields(ckpt, "trainer", {"step": int})
        for name, module in self.agent.modules().items():
            ckpt.load_module(name, module)
        with restoring(ckpt, "the learner's states"):
            self.agent.load_states({name: ckpt.state(name) for name in self.agent.states()})
        self.step = int(trainer["step"])
        print(f"resumed {self.out} at update {self.step}")


# --- checks --------------------------------------------------------------------------------
def check_demos(data: Any, problem: Any, cfg: TrainConfig) -> None:
    """Refuse demonstrations whose observations or actions do not fit the env's.

    The policy's ``initial`` observation is read from the dataset's ``observation`` (at
    the start of each segment); every other key must be stored with the same shape.

    Raises:
        LcrlError: discrete against continuous actions, or different keys or shapes; the
            message names the preset (or the env options) the dataset was recorded with.
    """
    path = cfg.demos
    if bool(data.discrete) != bool(problem.discrete):
        have = "discrete" if data.discrete else "continuous"
        want = "discrete" if problem.discrete else "continuous"
        raise LcrlError(
            f"{path} holds {have} actions but this run's env has {want} actions"
            f"{_recorded_hint(data, cfg)}"
        )
    want_obs = {k: tuple(shape) for k, shape in problem.obs_shapes.items()}  # what the policy reads
    stored = {k: tuple(v) for k, v in data.obs_shapes.items()}
    missing = [
        k
        for k, shape in want_obs.items()
        if stored.get("observation" if k == "initial" else k) != shape
    ]
    action_ok = problem.discrete or tuple(data.action_shape) == (problem.action_dim,)
    if missing or not action_ok:
        raise LcrlError(
            f"{path} does not fit this run's env: it stores observations "
            f"[{_shapes(stored)}] and {_actions(data.action_shape, data.discrete)}, the "
            f"policy reads [{_shapes(want_obs)}] and acts with "
            f"{_actions((problem.action_dim,), problem.discrete)}{_recorded_hint(data, cfg)}"
        )


def match_instructions(
    texts: Sequence[str], task: Any, path: str = "the dataset", allow_new: bool = True
) -> list[str]:
    """Check dataset instructions against a language task's table.

    Args:
        texts: the dataset's instructions to train on.
        task: the run's language task (``table``, ``ids``, ``num_train``, ``split``).
        path: the dataset, for messages.
        allow_new: whether texts missing from the table may join its training part (not
            with a fixed task set).

    Returns:
        The texts missing from the table that the grammar parses as training meanings of
        the task's families (to be added as training instructions).

    Raises:
        LcrlError: texts of the held-out or paraphrase evaluation sets (or of held-out
            combinations), of other families, that the grammar cannot parse, or missing
            from the table when ``allow_new`` is false.
    """
    from captioner.grammar import try_parse

    extras, leaked, other, unknown = [], [], [], []
    families = tuple(task.families)
    split = task.split
    for text in texts:
        i = task.ids.get(text)
        if i is not None:
            if i >= task.num_train:
                leaked.append(text)
            continue
        meaning = try_parse(text)
        if meaning is None:
            unknown.append(text)
        elif families and meaning.family not in families:
            other.append(text)
        elif split is not None and split.is_heldout(meaning):
            leaked.append(text)
        else:
            extras.append(text)
    if leaked:
        raise LcrlError(
            f"{path} trains on {len(leaked)} instructions this run evaluates as unseen "
            f"(held-out combinations or paraphrases of split seed {_split_seed(task)}), "
            f"e.g. {_few(leaked)}: training on them would leak the evaluation; relabel with "
            "train-only instructions (lcrl demos relabel) or match the recording's "
            "--env.split-seed"
        )
    if other:
        fams = sorted({m.family for m in map(try_parse, other) if m is not None})
        raise LcrlError(
            f"{path} holds instructions of families {fams} that this run does not train "
            f"({', '.join(families)}), e.g. {_few(other)}: pass --env.families with them"
        )
    if unknown:
        raise LcrlError(
            f"{len(unknown)} instructions of {path} are not in this run's instruction table "
            f"and the grammar cannot parse them, e.g. {_few(unknown)}: train on instructions "
            "the grammar knows (lcrl parse TEXT shows how it reads one)"
        )
    if extras and (not allow_new or not task.text_goals):
        raise LcrlError(
            f"{path} holds {len(extras)} instructions outside this run's task set, e.g. "
            f"{_few(extras)}: add them to --env.tasks or train on a dataset of those tasks"
        )
    return extras


def recorded_env(data: Any) -> dict[str, Any] | None:
    """The env config a dataset was recorded with (its meta's ``env``, JSON-normalised),
    or None when the meta does not say."""
    meta = getattr(data, "meta", {}) or {}
    env = meta.get("env")
    return json.loads(json.dumps(env)) if isinstance(env, dict) else None


def env_differences(recorded: Mapping[str, Any], cfg: TrainConfig) -> list[str]:
    """The ``--env.*`` options that turn ``cfg.env`` into the recorded env config."""
    mine = json.loads(json.dumps(dataclasses.asdict(cfg.env)))
    flags = []
    for key in sorted(recorded):
        value = recorded[key]
        if key not in mine or value == mine[key] or isinstance(value, dict):
            continue
        name = key.replace("_", "-")
        if isinstance(value, bool):
            flags.append(f"--env.{name}" if value else f"--env.no-{name}")
        elif isinstance(value, list):
            flags.append(f"--env.{name} " + " ".join(map(str, value)))
        else:
            flags.append(f"--env.{name} {value}")
    return flags


def _recorded_hint(data: Any, cfg: TrainConfig) -> str:
    """``: it was recorded with ...`` - the preset or env options that fit the dataset."""
    env = recorded_env(data)
    if env is None:
        return ": record the demonstrations with the env of this run (lcrl demos record)"
    presets = [
        name
        for name, (_, p) in PRESETS.items()
        if json.loads(json.dumps(dataclasses.asdict(p.env))) == env
    ]
    bc = [name for name in presets if name.endswith("-bc")]
    if bc:
        return (
            f": it was recorded with the env of preset {bc[0]}; train with lcrl train {bc[0]} "
            f"--demos {cfg.demos}"
        )
    if presets:
        return (
            f": it was recorded with the env of preset {presets[0]}; train with lcrl train "
            f"{presets[0]} --algo bc --demos {cfg.demos}"
        )
    diff = env_differences(env, cfg)
    if diff:
        preset = (getattr(data, "meta", {}) or {}).get("preset")
        named = f" (preset {preset} with changes)" if preset else ""
        return f": it was recorded with other env options{named}; pass {' '.join(diff)}"
    return ""


def _shapes(shapes: Mapping[str, tuple[int, ...]]) -> str:
    return ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())


def _actions(shape: Sequence[int], discrete: bool) -> str:
    if discrete:
        return "discrete actions"
    return f"{shape[0] if len(shape) == 1 else tuple(shape)}-d actions"


def _few(texts: Sequence[str], n: int = 3) -> str:
    shown = ", ".join(repr(t) for t in texts[:n])
    return shown + (f" (and {len(texts) - n} more)" if len(texts) > n else "")


def _split_seed(task: Any) -> Any:
    split = task.split
    return getattr(split, "seed", "?")


def _close(stream: Any) -> None:
    close = getattr(stream, "close", None)
    if close is not None:
        close()


def _write_json(path: Path, doc: Any) -> None:
    """Write JSON atomically (a temporary file renamed over ``path``)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

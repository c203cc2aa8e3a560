"""The one interface of every trainer, and the run-folder pieces they share.

A trainer (:class:`train.loop.Trainer` for online RL, :class:`train.bc.BCTrainer` for
behavioural cloning; offline and distillation trainers enter the same way) subclasses
:class:`BaseTrainer` and implements five things:

* :meth:`~BaseTrainer.advance`: one unit of work (an episode collected with its updates, a
  gradient update), moving :attr:`~BaseTrainer.step` on;
* :meth:`~BaseTrainer.log`: one ``progress.csv`` row;
* :meth:`~BaseTrainer.save` and :meth:`~BaseTrainer.restore`: a checkpoint, and resuming
  from one (called by its constructor with ``cfg.resume``);
* :meth:`~BaseTrainer.close`: release files and environments.

The base class owns the loop (progress bar, periodic log, evaluation and checkpoint), the
periodic evaluation (through :func:`train.evaluate.evaluate`, the engine of ``lcrl
eval``), the end of a run (last row, final evaluation, checkpoint, report) and Ctrl-C (a
checkpoint, a hint to ``--resume``); nothing outside a trainer touches its private state.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lcrl.checkpoint import find_latest, load_checkpoint
from lcrl.errors import LcrlError
from train.config import TrainConfig, config_from_dict, config_to_dict
from train.evaluate import evaluate, format_results
from train.report import write_report


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


def prune_checkpoints(out: Path, keep: int) -> None:
    """Delete all but the ``keep`` latest ``checkpoints/step_*`` folders of a run."""
    kept = sorted((out / "checkpoints").glob("step_*"))
    for old in kept[:-keep]:
        shutil.rmtree(old, ignore_errors=True)


def next_multiple(step: int, every: int) -> float:
    """The first multiple of ``every`` after ``step`` (infinity when ``every`` is 0)."""
    if every <= 0:
        return math.inf
    return (step // every + 1) * every


def progress_bar(total: int, initial: int, enabled: bool, unit: str = "step") -> Any:
    """A tqdm bar over ``total`` units, starting at ``initial``."""
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=initial,
        disable=not enabled,
        unit=unit,
        dynamic_ncols=True,
        smoothing=0.05,
    )


def tensorboard_writer(path: Path) -> Any:
    """A TensorBoard writer at ``path`` (None, with a note, without the package)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        print("tensorboard is not installed: no TensorBoard logs (pip install tensorboard)")
        return None
    return SummaryWriter(str(path))


class BaseTrainer(ABC):
    """A training run: the loop, evaluation, the end of the run and Ctrl-C.

    Subclasses build everything in ``__init__`` (setting :attr:`cfg`, :attr:`out`,
    :attr:`algo`, :attr:`agent`, :attr:`task` and, when resuming, calling
    :meth:`restore`) and implement :meth:`advance`, :meth:`log`, :meth:`save`,
    :meth:`restore` and :meth:`close`.
    """

    #: What ``total_steps`` and the ``*_every`` settings count: ``step`` (environment
    #: steps) or ``update`` (gradient updates).
    unit = "step"

    cfg: TrainConfig
    out: Path
    algo: str
    agent: Any
    task: Any
    #: Units done so far.
    step: int = 0
    #: Training episodes collected so far (0 for trainers that collect none).
    episodes: int = 0
    #: The last evaluation's results (None before the first).
    last_eval: dict[str, Any] | None = None
    #: The step of the last progress.csv row (-1: none yet).
    last_logged: int = -1
    tb: Any = None

    # --- what a trainer implements -----------------------------------------------------
    @abstractmethod
    def advance(self) -> None:
        """Do one unit of work (or a few: an episode is many steps) and move
        :attr:`step` on; never past ``total_steps`` by more than the work in hand."""

    @abstractmethod
    def log(self) -> None:
        """Write a progress.csv row (and TensorBoard scalars); set :attr:`last_logged`."""

    @abstractmethod
    def save(self) -> Path:
        """Checkpoint the run (everything :meth:`restore` needs); return its folder."""

    @abstractmethod
    def restore(self, ckpt: Any) -> None:
        """Continue from a checkpoint written by :meth:`save`."""

    def close(self) -> None:
        """Release what the run holds (TensorBoard, files, environments)."""
        if self.tb is not None:
            self.tb.close()
            self.tb = None

    # --- hooks with defaults -----------------------------------------------------------
    def begin(self) -> None:
        """Called once the outputs are open, before the first unit (a summary line)."""
        return None

    def after_checkpoint(self) -> None:
        """Called after each periodic checkpoint."""
        return None

    def postfix(self) -> str:
        """The progress bar's text: the last evaluation's success per set."""
        if not self.last_eval:
            return ""
        return "eval " + " ".join(f"{k} {v['success']:.2f}" for k, v in self.last_eval.items())

    # --- the run -----------------------------------------------------------------------
    def open_outputs(self) -> None:
        """Create the run folder, its config.json, progress.csv, eval.csv and TensorBoard."""
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(
            json.dumps({**config_to_dict(cfg), "resolved_algo": self.algo}, indent=1)
        )
        self.progress_log = CsvLog(self.out / "progress.csv")
        self.eval_log = CsvLog(self.out / "eval.csv")
        self.tb = tensorboard_writer(self.out / "tb") if cfg.tensorboard else None

    def run(self) -> dict[str, Any]:
        """Train to ``total_steps``; returns the final evaluation. Ctrl-C checkpoints the
        run (continue it with ``--resume``) and raises ``KeyboardInterrupt`` again."""
        cfg = self.cfg
        self.open_outputs()
        self.begin()
        bar = progress_bar(cfg.total_steps, self.step, cfg.progress, self.unit)
        self._t0, self._step0 = time.perf_counter(), self.step
        next_eval = next_multiple(self.step, cfg.eval_every)
        next_ckpt = next_multiple(self.step, cfg.checkpoint_every)
        next_log = next_multiple(self.step, cfg.log_every)
        try:
            while self.step < cfg.total_steps:
                before = self.step
                self.advance()
                bar.update(self.step - before)
                if self.step >= next_log:
                    self.log()
                    next_log = next_multiple(self.step, cfg.log_every)
                if cfg.eval_every and self.step >= next_eval and self.step < cfg.total_steps:
                    self.evaluate()
                    next_eval = next_multiple(self.step, cfg.eval_every)
                if cfg.checkpoint_every and self.step >= next_ckpt and self.step < cfg.total_steps:
                    self.save()
                    next_ckpt = next_multiple(self.step, cfg.checkpoint_every)
                    self.after_checkpoint()
                bar.set_postfix_str(self.postfix(), refresh=False)
        except KeyboardInterrupt:
            bar.close()
            self.interrupted()
            raise
        bar.close()
        return self.finish()

    def elapsed(self) -> float:
        """Seconds since this process started the loop."""
        return time.perf_counter() - self._t0

    def rate(self) -> float:
        """Units per second since this process started the loop."""
        return (self.step - self._step0) / max(self.elapsed(), 1e-9)

    def evaluate(self) -> dict[str, Any]:
        """Evaluate on every set of the task (the engine of ``lcrl eval``, the run's
        seed); write the eval.csv row and return the results."""
        cfg = self.cfg
        results = evaluate(self.agent, self.task, cfg, episodes=cfg.eval_episodes, seed=cfg.seed)
        self.last_eval = results
        row = eval_row(results, self.task, self.step, self.episodes)
        self.eval_log.write(row)
        if self.tb is not None:
            for k, v in row.items():
                if k not in ("step", "episodes"):
                    self.tb.add_scalar(f"eval/{k}", v, self.step)
        print(f"[{self.unit} {self.step}] " + format_results(results).replace("\n", " | "))
        return results

    def finish(self) -> dict[str, Any]:
        """The end of a run: the last progress row, the final evaluation, a checkpoint and
        the report; returns the evaluation."""
        if self.last_logged != self.step:
            self.log()
        results = self.evaluate()
        path = self.save()
        report = write_report(self.out, results)
        print(f"final checkpoint: {path}")
        print(f"report: {report}")
        self.close()
        return results

    def interrupted(self) -> None:
        """Ctrl-C: checkpoint the run, say how to continue it, and close it."""
        path = self.save()
        print(f"interrupted at {self.unit} {self.step}: saved {path}; continue with --resume")
        self.close()

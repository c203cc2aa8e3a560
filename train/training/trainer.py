"""The one interface of every trainer, and the run-folder pieces they share.

A trainer (:class:`train.training.loop.Trainer` for online RL,
:class:`train.training.bc.BCTrainer` for
behavioural cloning; offline and distillation trainers enter the same way) subclasses
:class:`BaseTrainer` and implements five things:

* :meth:`~BaseTrainer.advance`: one unit of work (an episode collected with its updates, a
  gradient update), moving :attr:`~BaseTrainer.step` on;
* :meth:`~BaseTrainer.log`: one ``progress.csv`` row;
* :meth:`~BaseTrainer.save` and :meth:`~BaseTrainer.restore`: a checkpoint, and resuming
  from one (called by its constructor with ``cfg.resume``);
* :meth:`~BaseTrainer.close`: release files and environments.

The base class owns the loop (progress bar, periodic log, evaluation and checkpoint), the
periodic evaluation (through :func:`train.evaluation.evaluate.evaluate`, the engine of ``lcrl
eval``), the end of a run (last row, final evaluation, checkpoint, report) and stopping;
nothing outside a trainer touches its private state.

Stopping
    Ctrl-C (SIGINT) and SIGTERM (what cluster schedulers send before they kill a job) stop
    a run the same way: the trainer goes back to the state at the start of the unit in
    hand (:meth:`BaseTrainer.rollback`: an episode's updates and random draws are undone),
    writes a checkpoint and exits with status 130 (SIGINT) or 143 (SIGTERM); ``--resume``
    then continues exactly as if nothing had happened. While a checkpoint is being
    written, further SIGINT and SIGTERM are held back and reported, so the checkpoint is
    always completed: stopping again only repeats the note. A stop during a periodic
    evaluation saves it as pending (:attr:`BaseTrainer.eval_pending`): the resumed run
    evaluates at that step first, so eval.csv has every row. SIGKILL cannot be caught:
    ``--resume`` continues from the last checkpoint, cuts ``progress.csv`` and
    ``eval.csv`` back to its step and removes half-written checkpoint folders.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from lcrl.checkpoint import (
    CheckpointCorruptError,
    CheckpointWriteError,
    find_latest,
    remove_stale,
    save_checkpoint,
    verify_checkpoint,
    write_latest,
    write_problem,
)
from lcrl.errors import LcrlError
from train.configs.config import TrainConfig, config_to_dict
from train.configs.run_meta import run_meta
from train.evaluation.evaluate import evaluate, format_results
from train.evaluation.report import write_report
from train.runtime.machine import ThreadWatcher
from train.runtime.run_lock import lock_run, unlock_run


class CsvLog:
    """Append rows to a CSV file. The header is that of the first row (or of the file);
    a row with columns the header lacks (the update metrics, which begin only once
    learning starts) widens it: the file is rewritten with the new columns at the end,
    empty in the earlier rows."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fields: list[str] | None = None
        if path.exists():
            with path.open() as f:
                header = f.readline().strip()
            self.fields = header.split(",") if header else None

    def write(self, row: Mapping[str, Any]) -> None:
        """Write one row.

        Raises:
            LcrlError: the file cannot be written (a full disk), naming it.
        """
        new = self.fields is None
        fields = list(row) if new else list(self.fields)
        extra = [k for k in row if k not in fields]
        with writing(self.path):
            if extra:
                fields += extra
                self._widen(fields)
            with self.path.open("a", newline="") as f:
                w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
                if new:
                    w.writeheader()
                w.writerow({k: _fmt(v) for k, v in row.items()})
        self.fields = fields

    def _widen(self, fields: list[str]) -> None:
        """Rewrite the file under the header ``fields`` (atomically)."""
        with self.path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        tmp = self.path.with_name(self.path.name + ".tmp")
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(rows)
        tmp.replace(self.path)


@contextlib.contextmanager
def writing(path: Path) -> Iterator[None]:
    """Name ``path`` in the error of a write inside the block that fails: an ``OSError``
    (a full disk, a read-only folder) becomes an :class:`LcrlError` saying which file and
    what went wrong (the operating system's error of a failed write names no file)."""
    try:
        yield
    except OSError as e:
        raise LcrlError(f"cannot write {path}: {write_problem(e)}") from None


def _fmt(v: Any) -> Any:
    return f"{v:.6g}" if isinstance(v, float) else v


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by a signal (SIGINT or SIGTERM); ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)
        self.reported = False  # set once a run has said what it saved

    @property
    def exit_status(self) -> int:
        """The shell's status of a process ended by the signal (130, 143)."""
        return 128 + self.signum


class RunAlreadyDone(LcrlError):
    """``--resume --total-steps N`` where the run is already at N or beyond."""


class StopSignals:
    """SIGINT and SIGTERM as :class:`RunInterrupted`, except while a checkpoint is written.

    Installed for the duration of a run (main thread only; elsewhere it does nothing). The
    first signal raises :class:`RunInterrupted` in the loop. Inside :meth:`holding` (a
    checkpoint being written) a signal is remembered and raised once the block ends, so no
    save is ever cut short; a second signal while the final save is written is reported in
    one line and otherwise waits for it.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.pending: int | None = None
        #: Set by the loop once the interrupt has reached it; until then a later signal
        #: raises again (a library's catch-all may have swallowed the first on its way up).
        self.received = False
        self._holding = 0
        self._stopping = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _handle(self, signum: int, frame: Any) -> None:
        if self._stopping and not self.received and not self._holding:
            raise RunInterrupted(signum)  # the first never reached the loop
        if self._holding or self._stopping:
            self.pending = self.pending or signum
            if not self._stopping:
                return  # a periodic save ends in moments; the run's one line follows it
            print(
                f"\nlcrl: {signal.Signals(signum).name} while the checkpoint is written: it "
                "is completed first, then the run stops (kill -9 stops at once and keeps the "
                "previous checkpoint)",
                file=sys.stderr,
                flush=True,
            )
            return
        self._stopping = True  # later signals wait for the checkpoint of this one
        raise RunInterrupted(signum)

    @contextlib.contextmanager
    def holding(self) -> Iterator[None]:
        """Hold SIGINT and SIGTERM back while the block runs; raise the first one held
        (as :class:`RunInterrupted`) when it ends, unless the run is already stopping."""
        self._holding += 1
        try:
            yield
        finally:
            self._holding -= 1
        if not self._holding and self.pending is not None and not self._stopping:
            signum, self.pending = self.pending, None
            self._stopping = True
            raise RunInterrupted(signum)


def open_run(
    cfg: TrainConfig, explore: Mapping[str, Any] | None = None, perception: str = ""
) -> tuple[TrainConfig, Any]:
    """Prepare ``cfg.out`` for a run: with ``cfg.resume``, load its latest checkpoint and
    the config saved there (keeping ``total_steps``, ``out`` and ``resume`` from ``cfg``),
    remove what a killed process left half-written and cut the logs back to the
    checkpoint's step; otherwise refuse a folder that already holds a run unless
    ``cfg.overwrite``, in which case its checkpoints and logs are removed.

    Args:
        cfg: the run's config (from the command line).
        explore: ``explore`` fields a resumed run takes from ``cfg`` instead of its saved
            config (those given on the command line): they change where the next
            episodes start, not what the run has learned.
        perception: with ``cfg.resume``, a perception model the resumed run acts through
            from now on instead of the one its checkpoint carries (a model fine-tuned on
            the run's own frames); empty: the checkpoint's.

    Returns:
        The config to run with and the checkpoint to resume from (None for a new run).
        A resumed run keeps its saved config, apart from ``total_steps``, ``out``,
        ``progress``, ``torch_threads`` and the ``explore`` fields named.

    Raises:
        RunAlreadyDone: ``--resume`` with ``total_steps`` at or below the checkpoint's step.
        LcrlError: no checkpoint to resume, a run in the way, an unusable ``out``, or a
            folder that another live process holds (:mod:`train.runtime.run_lock`).
    """
    out = Path(cfg.out)
    check_out_dir(out)
    note = lock_run(out)  # before anything in the folder is read, removed or written
    if note:
        print(f"lcrl: {note}", file=sys.stderr)
    if cfg.resume:
        remove_stale(out)
        latest = find_latest(out)
        if latest is None:
            raise LcrlError(f"--resume: no checkpoint in {out} (no latest.json)")
        ckpt = newest_intact(out, latest)
        latest = ckpt.path
        meta = run_meta(ckpt)
        if cfg.total_steps <= meta.step:
            raise RunAlreadyDone(
                f"{out} is already at step {meta.step} (checkpoint {latest.name}): nothing to "
                f"do for --total-steps {cfg.total_steps}; pass a larger --total-steps to train on"
            )
        saved = meta.config
        if perception:  # a new model from here on (its shapes are checked as any)
            print(f"lcrl: the resumed run acts through {perception} from now on")
            saved.env.perception = perception
        elif "perception" in ckpt.meta:  # the copy of the model the policy acts through
            saved.env.perception = str(keep_perception(latest, out))
        saved.total_steps = cfg.total_steps
        saved.resume = True
        saved.out = cfg.out
        # how this process shows and paces its work, not what the run learns
        saved.progress, saved.torch_threads = cfg.progress, cfg.torch_threads
        if explore:
            saved.explore = dataclasses.replace(saved.explore, **explore)
            saved.validate()
        for name in ("progress.csv", "eval.csv"):
            truncate_log(out / name, meta.step)
        return saved, ckpt
    if (out / "latest.json").exists():
        if not cfg.overwrite:
            raise LcrlError(
                f"{out} already holds a run; pass --resume to continue it, "
                "--overwrite to replace it, or choose another --out"
            )
        for name in ("checkpoints", "tb", RESUMED_PERCEPTION):
            shutil.rmtree(out / name, ignore_errors=True)
        for name in ("latest.json", "progress.csv", "eval.csv", "report.md", "curves.png"):
            (out / name).unlink(missing_ok=True)
    return cfg, None


#: The suffix a corrupt checkpoint folder is renamed with when a resumed run passes it by:
#: it is kept, and no longer counted among the run's checkpoints.
CORRUPT_SUFFIX = ".corrupt"


def newest_intact(out: Path, latest: Path) -> Any:
    """The checkpoint to resume from: ``latest`` with every file verified against its
    checksum, or, where one is corrupt, the newest other checkpoint of the run that is
    intact. The corrupt one is never deleted: it is renamed ``<name>.corrupt`` (so that
    pruning and later saves at its step leave it alone) and ``latest.json`` is pointed at
    the one resumed; what happened is printed.

    Raises:
        LcrlError: no intact checkpoint remains (the corrupt file is named).
    """
    try:
        return verify_checkpoint(latest)
    except CheckpointCorruptError as e:
        corrupt = e
    others = sorted(
        (p for p in (out / "checkpoints").glob("step_*") if p.is_dir() and p != latest),
        reverse=True,
    )
    for candidate in others:
        try:
            ckpt = verify_checkpoint(candidate)
        except LcrlError:
            continue
        kept = latest.with_name(latest.name + CORRUPT_SUFFIX)
        if not kept.exists():
            latest.rename(kept)
        write_latest(out, candidate)
        print(
            f"lcrl: warning: {corrupt}; resuming from the newest intact checkpoint "
            f"{candidate} instead (the corrupt one is kept as {kept})",
            file=sys.stderr,
        )
        return ckpt
    raise LcrlError(f"--resume: {corrupt}; no other intact checkpoint is left in {out}")


def check_out_dir(out: Path, what: str = "the run folder") -> None:
    """Refuse a run folder that cannot be one: a file, or a folder that cannot be written.
    Leaves nothing behind: folders made for the check are removed again.

    Args:
        out: the folder (``--out``).
        what: what it is, in the message.

    Raises:
        LcrlError: naming the path and the problem.
    """
    if out.exists() and not out.is_dir():
        raise LcrlError(f"--out {out} is a file, not a folder: choose another --out")
    made = [p for p in (out, *out.parents) if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise LcrlError(f"cannot write {what} {out}: {e.strerror or e}") from None
    finally:
        for p in made:  # innermost first
            with contextlib.suppress(OSError):
                p.rmdir()


def truncate_log(path: Path, step: int) -> int:
    """Drop the rows of a CSV log whose ``step`` is past ``step`` (what a killed run wrote
    after its last checkpoint); returns how many were dropped."""
    if not path.is_file():
        return 0
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows or "step" not in rows[0]:
        return 0
    col = rows[0].index("step")
    keep = [rows[0]]
    for row in rows[1:]:
        try:
            if float(row[col]) > step:
                continue
        except (IndexError, ValueError):
            continue  # a row cut short by the kill
        keep.append(row)
    dropped = len(rows) - len(keep)
    if dropped:
        tmp = path.with_name(f".{path.name}.tmp")
        with tmp.open("w", newline="") as f:
            csv.writer(f).writerows(keep)
        tmp.replace(path)
    return dropped


def eval_row(results: Mapping[str, Any], task: Any, step: int, episodes: int) -> dict[str, Any]:
    """The eval.csv row of an evaluation: step, episodes, success per set and per family
    (every family of the task gets a column, even one that no episode of this round drew)."""
    row: dict[str, Any] = {"step": step, "episodes": episodes}
    families = tuple(task.families)
    for name, res in results.items():
        row[f"{name}/success"] = res["success"]
        for fam in dict.fromkeys((*families, *res["families"])):
            row[f"{name}/{fam}"] = res["families"].get(fam, float("nan"))
        for t in res.get("tasks", ()):  # a fixed task set: success per task id
            row[f"tasks/{t['id']}"] = t["success"]
    return row


#: Where a resumed run keeps the perception model its checkpoints carry
#: (:func:`keep_perception`).
RESUMED_PERCEPTION = "perception"


def keep_perception(checkpoint: Path, out: Path) -> Path:
    """Copy the perception model that a policy checkpoint carries (with the policy's
    weights; not its arrays or buffer) to ``out/perception``, a folder that
    ``--env.perception`` reads, and return it: a resumed run's environments act through
    it after :func:`prune_checkpoints` has removed the checkpoint it resumed from."""
    dest = out / RESUMED_PERCEPTION
    part = out / f"{RESUMED_PERCEPTION}.part"
    shutil.rmtree(part, ignore_errors=True)
    part.mkdir()
    for f in checkpoint.iterdir():
        if f.is_file() and f.suffix in (".json", ".safetensors"):
            shutil.copy2(f, part / f.name)
    shutil.rmtree(dest, ignore_errors=True)
    part.rename(dest)
    return dest


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
    #: A periodic evaluation was due at :attr:`step` and did not finish (the run was
    #: stopped during it): saved with the checkpoint, and run first when the run resumes,
    #: so that eval.csv has the row an uninterrupted run has.
    eval_pending: bool = False
    #: Chooses torch's threads again while the run trains (None: the threads are fixed,
    #: by ``--torch-threads``, ``OMP_NUM_THREADS`` or ``LCRL_PROCESSES``).
    thread_watch: ThreadWatcher | None = None
    #: A periodic evaluation is running (what :meth:`interrupted` saves as pending).
    _periodic_eval: bool = False
    #: Seconds of training (evaluations excluded) before this process resumed the run.
    train_s_before: float = 0.0
    #: Seconds this process spent in evaluations.
    _eval_s: float = 0.0
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

    def write_checkpoint(
        self,
        meta: dict[str, Any],
        json_files: dict[str, Any],
        states: dict[str, Any],
        arrays: dict[str, Any] | None = None,
    ) -> Path:
        """What :meth:`save` implementations share: the learner's weights (and the
        perception model its policy acts through, which the checkpoint carries) saved
        with ``meta``, ``json_files``, ``states`` and ``arrays`` at the current step;
        ``latest.json`` pointed at it; older checkpoints pruned."""
        from train.environments.perception import embedded_meta, find_perception

        modules = dict(self.agent.modules())
        reader = getattr(getattr(self, "task", None), "encoder", None)
        if hasattr(reader, "reader"):  # --env.text-reader: the reader travels with the weights
            states = {**states, "text_reader": reader.state_dict()}
        perceiving = find_perception(self.env)
        if perceiving is not None:
            modules["perception"] = perceiving.model
            meta = {**meta, "perception": embedded_meta(perceiving.model, self.cfg.env.perception)}
        path = save_checkpoint(
            self.out / "checkpoints" / f"step_{self.step:09d}",
            modules=modules,
            states=states,
            meta=meta,
            json_files=json_files,
            arrays=arrays,
        )
        write_latest(self.out, path)
        prune_checkpoints(self.out, self.cfg.keep_checkpoints)
        return path

    def rollback(self) -> None:
        """Go back to the state at the start of the unit in hand (called when a run is
        stopped inside one, before its checkpoint): what :meth:`advance` changed must not
        be saved half-done. Trainers whose unit cannot be interrupted need nothing."""
        return None

    def close(self) -> None:
        """Release what the run holds (TensorBoard, files, environments, the folder's
        lock)."""
        if self.tb is not None:
            self.tb.close()
            self.tb = None
        if getattr(self, "out", None) is not None:
            unlock_run(self.out)

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
        with writing(self.out / "config.json"):
            (self.out / "config.json").write_text(
                json.dumps({**config_to_dict(cfg), "resolved_algo": self.algo}, indent=1)
            )
        self._t0, self._step0 = time.perf_counter(), self.step  # run() starts them again
        self.progress_log = CsvLog(self.out / "progress.csv")
        self.eval_log = CsvLog(self.out / "eval.csv")
        self.tb = tensorboard_writer(self.out / "tb") if cfg.tensorboard else None

    def run(self) -> dict[str, Any]:
        """Train to ``total_steps``; returns the final evaluation. Ctrl-C checkpoints the
        run (continue it with ``--resume``) and raises ``KeyboardInterrupt`` again."""
        cfg = self.cfg
        known = tuple(self.task.sets)
        unknown = [name for name in cfg.eval_sets if name not in known]
        if unknown:
            self.close()
            raise LcrlError(f"eval_sets {unknown}: this task's sets are {known}")
        self.open_outputs()
        self.begin()
        bar = progress_bar(cfg.total_steps, self.step, cfg.progress, self.unit)
        self._t0, self._step0 = time.perf_counter(), self.step
        next_eval = next_multiple(self.step, cfg.eval_every)
        next_ckpt = next_multiple(self.step, cfg.checkpoint_every)
        next_log = next_multiple(self.step, cfg.log_every)
        with StopSignals() as self.signals:
            try:
                if self.eval_pending and self.step < cfg.total_steps:
                    self.periodic_evaluation()  # the one a stop cut short at this step
                self.eval_pending = False
                while self.step < cfg.total_steps:
                    before = self.step
                    self.advance()
                    bar.update(self.step - before)
                    if self.thread_watch is not None:
                        self.thread_watch.poll()
                    if self.step >= next_log:
                        self.log()
                        next_log = next_multiple(self.step, cfg.log_every)
                    if cfg.eval_every and self.step >= next_eval and self.step < cfg.total_steps:
                        self.periodic_evaluation()
                        next_eval = next_multiple(self.step, cfg.eval_every)
                    if (
                        cfg.checkpoint_every
                        and self.step >= next_ckpt
                        and self.step < cfg.total_steps
                    ):
                        self.checkpoint()
                        next_ckpt = next_multiple(self.step, cfg.checkpoint_every)
                        self.after_checkpoint()
                    bar.set_postfix_str(self.postfix(), refresh=False)
                bar.close()
                return self.finish()  # a stop during the final evaluation saves too
            except KeyboardInterrupt as e:
                self.signals.received = True
                bar.close()
                self.interrupted(e)
                raise

    def periodic_evaluation(self) -> None:
        """:meth:`evaluate`, remembered as pending while it runs: a run stopped during it
        saves that, and its resumption runs the evaluation again at the same step."""
        self._periodic_eval = True
        self.evaluate(tuple(self.cfg.eval_sets) or None)
        self._periodic_eval = False

    def resume_schedule(self, ckpt: Any) -> None:
        """Read what the loop itself keeps in a checkpoint (an evaluation left pending);
        called by :meth:`restore`."""
        self.eval_pending = ckpt.meta.get("eval_pending", False) is True

    def holding_signals(self) -> Any:
        """A context in which SIGINT and SIGTERM wait (see :class:`StopSignals`)."""
        signals = getattr(self, "signals", None)
        return signals.holding() if signals is not None else contextlib.nullcontext()

    def checkpoint(self) -> Path:
        """:meth:`save`, with SIGINT and SIGTERM held back until it is complete; the path
        is remembered so that stopping right after does not write it again."""
        with self.holding_signals():
            path = self.save_or_explain()
        self._saved = (self.step, path)
        return path

    def save_or_explain(self) -> Path:
        """:meth:`save`; a checkpoint that cannot be written (a full disk, a folder that
        became read-only) is an :class:`LcrlError` naming it and the checkpoint kept."""
        try:
            return self.save()
        except (OSError, CheckpointWriteError) as e:
            if isinstance(e, CheckpointWriteError):
                where, problem = e.path, e.problem
            else:
                where, problem = e.filename or self.out / "checkpoints", write_problem(e)
            try:
                kept = find_latest(self.out)
            except LcrlError:
                kept = None
            keep = (
                f"the previous checkpoint {kept} is kept (latest.json points at it)"
                if kept
                else "no earlier checkpoint exists"
            )
            raise LcrlError(
                f"cannot write a checkpoint at {self.unit} {self.step} in {where}: "
                f"{problem}; {keep}"
            ) from None

    def elapsed(self) -> float:
        """Seconds since this process started the loop."""
        return time.perf_counter() - self._t0

    def rate(self) -> float:
        """Units per second since this process started the loop."""
        return (self.step - self._step0) / max(self.elapsed(), 1e-9)

    def train_seconds(self) -> float:
        """Wall-clock seconds of training so far, over every process of the run (resumed
        ones too), evaluations excluded: the time a user waits for this policy (the
        ``train_s`` column of eval.csv)."""
        if not hasattr(self, "_t0"):
            return self.train_s_before
        return self.train_s_before + self.elapsed() - self._eval_s

    def evaluate(self, sets: tuple[str, ...] | None = None) -> dict[str, Any]:
        """Evaluate on ``sets`` (default: every set of the task) with the engine of ``lcrl
        eval`` and the run's seed; write the eval.csv row and return the results."""
        cfg = self.cfg
        t0 = time.perf_counter()
        results = evaluate(
            self.agent, self.task, cfg, episodes=cfg.eval_episodes, seed=cfg.seed, sets=sets
        )
        self._eval_s += time.perf_counter() - t0
        self.last_eval = results
        row = eval_row(results, self.task, self.step, self.episodes)
        row["train_s"] = round(self.train_seconds(), 2)
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
        path = self.checkpoint()
        report = write_report(self.out, results)
        print(f"final checkpoint: {path}")
        print(f"report: {report}")
        self.close()
        return results

    def interrupted(self, why: BaseException | None = None) -> None:
        """Stopped (Ctrl-C, SIGTERM): undo the unit in hand, checkpoint the run unless
        that step is saved already, say how to continue it, and close it. Signals that
        arrive meanwhile are held back and reported (:class:`StopSignals`)."""
        name = why.args[0] if isinstance(why, RunInterrupted) else "SIGINT"
        with self.holding_signals():
            self.rollback()
            self.eval_pending = self._periodic_eval
            saved = getattr(self, "_saved", None)
            if saved is not None and saved[0] == self.step:
                path = saved[1]
            else:
                path = self.save_or_explain()
        print(
            f"interrupted at {self.unit} {self.step} by {name}: saved {path}; continue with "
            "--resume",
            flush=True,
        )
        if isinstance(why, RunInterrupted):
            why.reported = True
        self.close()

"""Reading a run folder: its logs, its config, its checkpoint's run and its saved evaluations."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from lcrl.errors import LcrlError
from train.environments.simulators import ENVS, KIND_ALIASES, describe
from train.environments.tasks import GOALS, goals_label

EVAL_FORMAT = "lcrl-eval"


EVAL_VERSION = 1


# --- reading a run ---------------------------------------------------------------------------
def _read(path: Path) -> list[dict[str, float]]:
    """Rows of a run's CSV log as floats (missing values are NaN); [] without the file."""
    if not path.exists():
        return []
    try:
        with path.open() as f:
            rows = []
            for r in csv.DictReader(f):
                rows.append(
                    {
                        k: float(v) if v not in ("", None) else float("nan")
                        for k, v in r.items()
                        if k is not None
                    }
                )
            return rows
    except (ValueError, csv.Error, UnicodeDecodeError) as e:
        raise LcrlError(f"{path} is not a valid log (CSV of numbers): {e}") from None


def _config(run: Path) -> dict[str, Any]:
    if not run.exists():
        raise LcrlError(f"{run} is not a run folder: it does not exist")
    if not run.is_dir():
        raise LcrlError(f"{run} is not a run folder: it is a file")
    path = run / "config.json"
    if not path.exists():
        raise LcrlError(f"{run} is not a run folder (no config.json)")
    try:
        config = json.loads(path.read_text())
        if not isinstance(config["env"]["kind"], str):
            raise TypeError("env.kind is not a string")
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise LcrlError(f"{path} is not a valid run config: {e!r}") from None
    return config


def run_of_checkpoint(checkpoint: str | Path) -> Path | None:
    """The run folder a checkpoint folder belongs to (``RUN/checkpoints/step_N``), if any."""
    p = Path(checkpoint).resolve()
    run = p.parent.parent
    if p.parent.name == "checkpoints" and (run / "config.json").is_file():
        try:  # as the user would type it, when it is below the working directory
            return run.relative_to(Path.cwd().resolve())
        except ValueError:
            return run
    return None


def task_name(env: dict[str, Any]) -> str:
    """A short name of a run's task from its (saved) env config: ``2D tabletop
    reach/push``, ``2D tabletop (state goals)``, ``robosuite tabletop (image goals)``, a
    gym id."""
    kind, alias_goal = KIND_ALIASES.get(str(env.get("kind", "?")), (env.get("kind", "?"), None))
    goal_type = str(alias_goal or env.get("goal_type", "language"))
    name = describe(env)
    spec = ENVS.get(kind)
    modality = GOALS.get(goal_type)
    text = modality is not None and modality.text
    if text and spec is not None and spec.families:
        name += " " + "/".join(env.get("families", ()))
    tasks = env.get("tasks") or ()
    if tasks:
        return name + f", {len(tasks)} tasks as {goals_label(goal_type)}"
    if not text:
        name += f" ({goals_label(goal_type)})"
    return name


def _sets_of(evals: list[dict[str, float]]) -> list[str]:
    return [k.split("/")[0] for k in (evals[0] if evals else {}) if k.endswith("/success")]


def final_from_log(run: str | Path) -> dict[str, Any] | None:
    """The last evaluation of a run's ``eval.csv`` in the shape of
    :func:`train.evaluation.evaluate.evaluate`'s results (None when it has no row)."""
    run = Path(run)
    evals = _read(run / "eval.csv")
    if not evals:
        return None
    config = _config(run)
    last = evals[-1]
    out = {}
    for s in _sets_of(evals):
        fams = {
            k.split("/", 1)[1]: v
            for k, v in last.items()
            if k.startswith(f"{s}/") and k != f"{s}/success" and not math.isnan(v)
        }
        out[s] = {
            "success": last[f"{s}/success"],
            "episodes": int(config.get("eval_episodes", 0)),
            "families": fams,
            "step": int(last["step"]),
        }
    tasks = config["env"].get("tasks") or ()
    if tasks and "train" in out:  # a fixed task set: success per task, run round robin
        n, k = out["train"]["episodes"], len(tasks)
        out["train"]["tasks"] = [
            {
                "id": i,
                "instruction": t,
                "success": last.get(f"tasks/{i}", float("nan")),
                "episodes": n // k + (i < n % k),
            }
            for i, t in enumerate(tasks)
        ]
    return out


def find_evaluations(run: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """Every ``eval.json`` one or two folder levels below a run folder, oldest
    checkpoint first: ``[(folder, document)]``. Files that are not evaluations are skipped."""
    run = Path(run)
    found = []
    for path in sorted([*run.glob("*/eval.json"), *run.glob("*/*/eval.json")]):
        if "checkpoints" in path.relative_to(run).parts:
            continue
        try:
            doc = load_evaluation(path)
        except LcrlError:
            continue
        found.append((path.parent, doc))
    found.sort(key=lambda x: (x[1].get("step") or 0, str(x[0])))
    return found


def load_evaluation(path: str | Path) -> dict[str, Any]:
    """Read an ``eval.json`` written by ``lcrl eval --out`` (a file or its folder)."""
    p = Path(path)
    if p.is_dir():
        p = p / "eval.json"
    if not p.is_file():
        raise LcrlError(f"no evaluation at {p}")
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise LcrlError(f"{p} is not valid JSON: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != EVAL_FORMAT or "sets" not in doc:
        raise LcrlError(f"{p} is not an evaluation written by lcrl eval")
    if doc.get("version") != EVAL_VERSION:
        raise LcrlError(f"{p}: evaluation format version {doc.get('version')} is not supported")
    return doc

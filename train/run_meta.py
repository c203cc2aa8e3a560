"""What a run's checkpoint says about itself, read and checked field by field.

``meta.json`` of a training checkpoint holds the run's config, the algorithm, the learner's
problem (shapes and goal encoding), the step and the episode count; language runs add
``instructions.json`` (the instruction table). :func:`run_meta` reads each field once and
checks its type, so a file that is valid JSON but lacks a key or holds a wrong type ends in
a :class:`lcrl.checkpoint.CheckpointError` naming the file and the field, never in a
``KeyError`` deep inside the loader.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lcrl.algos import ALGOS, Problem
from lcrl.checkpoint import Checkpoint, CheckpointError
from lcrl.errors import LcrlError
from train.config import TrainConfig, config_from_dict


@dataclass
class RunMeta:
    """The checked fields of a training checkpoint.

    Attributes:
        config: the run's config.
        algo: the algorithm that wrote it.
        problem: the learner's problem.
        step: units trained (environment steps, or updates for BC).
        episodes: training episodes collected.
        table: the instruction table (texts) and how many of them are training
            instructions; None for runs without one.
    """

    config: TrainConfig
    algo: str
    problem: Problem
    step: int
    episodes: int
    table: tuple[list[str], int] | None


def _field(ckpt: Checkpoint, key: str, kind: type | tuple[type, ...], what: str) -> Any:
    where = ckpt.path / "meta.json"
    if key not in ckpt.meta:
        raise CheckpointError(f"{where}: the field {key!r} ({what}) is missing")
    value = ckpt.meta[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and bool not in _kinds(kind)):
        raise CheckpointError(
            f"{where}: the field {key!r} ({what}) should be {_name(kind)}, not "
            f"{type(value).__name__} {str(value)[:60]!r}"
        )
    return value


def _kinds(kind: type | tuple[type, ...]) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)


def _name(kind: type | tuple[type, ...]) -> str:
    names = {dict: "an object", str: "a string", int: "an integer", list: "a list"}
    return " or ".join(names.get(k, k.__name__) for k in _kinds(kind))


def _config(config: dict[str, Any], where: Any) -> TrainConfig:
    """The saved config, built and validated; any failure names the field."""
    try:
        cfg = config_from_dict(config)
        cfg.validate()
    except LcrlError as e:
        raise CheckpointError(f"{where}: the field 'config' is not a valid config: {e}") from None
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise CheckpointError(
            f"{where}: the field 'config' is not a valid config ({type(e).__name__}: {e})"
        ) from None
    return cfg


def run_meta(ckpt: Checkpoint) -> RunMeta:
    """Read and check the fields of a training checkpoint.

    Raises:
        CheckpointError: a field is missing or of the wrong type or value; the message
            names the file and the field.
    """
    where = ckpt.path / "meta.json"
    config = _field(ckpt, "config", dict, "the run's config")
    cfg = _config(config, where)
    algo = _field(ckpt, "algo", str, "the algorithm")
    if algo not in ALGOS:
        raise CheckpointError(
            f"{where}: the field 'algo' is {algo!r}, which is none of {tuple(ALGOS)}"
        )
    problem_doc = _field(ckpt, "problem", dict, "the learner's shapes and goals")
    try:
        problem = Problem.from_dict(problem_doc)
    except KeyError as e:
        raise CheckpointError(f"{where}: the field 'problem' lacks {e.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{where}: the field 'problem' is malformed ({e})") from None
    step = _field(ckpt, "step", int, "units trained")
    episodes = ckpt.meta.get("episodes", 0)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 0 or step < 0:
        raise CheckpointError(f"{where}: 'step' and 'episodes' must be integers >= 0")
    table = None
    if problem.goal_kind == "text":
        doc = ckpt.json("instructions")
        texts = doc.get("texts") if isinstance(doc, dict) else None
        num_train = doc.get("num_train") if isinstance(doc, dict) else None
        if (
            not isinstance(texts, list)
            or not all(isinstance(t, str) for t in texts)
            or isinstance(num_train, bool)
            or not isinstance(num_train, int)
            or not 0 < num_train <= len(texts)
        ):
            raise CheckpointError(
                f"{ckpt.path / 'instructions.json'}: expected 'texts' (a list of strings) and "
                "'num_train' (an integer between 1 and their number)"
            )
        table = (texts, num_train)
    return RunMeta(cfg, algo, problem, step, episodes, table)

"""What a run's checkpoint says about itself, read and checked field by field.

``meta.json`` of a training checkpoint holds the run's config, the algorithm, the learner's
problem (shapes and goal encoding), the step and the episode count; language runs add
``instructions.json`` (the instruction table). :func:`run_meta` reads each field once and
checks its type (the saved config's values against its fields' annotations), so a file
that is valid JSON but lacks a key or holds a wrong type ends in a
:class:`lcrl.checkpoint.CheckpointError` naming the file and the field, never in a
``KeyError`` deep inside the loader. The trainers read ``state.json`` through
:func:`state_fields` and :func:`restoring`, to the same effect.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from lcrl.algos import ALGOS, Problem
from lcrl.checkpoint import Checkpoint, CheckpointError
from lcrl.errors import LcrlError
from lcrl.nets import GOAL_ENCODERS
from train.configs.config import ConfigFieldError, TrainConfig, config_from_dict
from train.environments.tasks import goal_modality


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
        eval_pending: a periodic evaluation at ``step`` was stopped before it finished.
    """

    config: TrainConfig
    algo: str
    problem: Problem
    step: int
    episodes: int
    table: tuple[list[str], int] | None
    eval_pending: bool = False


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
        cfg = config_from_dict(config, prefix="config.")
    except ConfigFieldError as e:
        raise CheckpointError(f"{where}: {e}") from None
    try:
        cfg.validate(files=False)  # acting from a checkpoint needs none of its input files
    except LcrlError as e:
        raise CheckpointError(f"{where}: the field 'config' is not a valid config: {e}") from None
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise CheckpointError(
            f"{where}: the field 'config' is not a valid config ({type(e).__name__}: {e})"
        ) from None
    return cfg


def _shape(value: Any) -> bool:
    """A list of non-negative integers."""
    return isinstance(value, list) and all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in value
    )


def _count(minimum: int) -> Any:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= minimum


#: The fields of ``meta.json``'s ``problem``: (check, what it should be, required).
PROBLEM_FIELDS: dict[str, tuple[Any, str, bool]] = {
    "obs_shapes": (
        lambda v: isinstance(v, dict) and all(_shape(s) for s in v.values()),
        "an object of shapes (lists of integers)",
        True,
    ),
    "goal_kind": (lambda v: v in GOAL_ENCODERS, f"one of {tuple(GOAL_ENCODERS)}", True),
    "goal_shape": (_shape, "a list of integers", True),
    "action_dim": (_count(1), "a positive integer", True),
    "discrete": (lambda v: isinstance(v, bool), "true or false", True),
    "num_tasks": (_count(0), "an integer >= 0", False),
    "privileged": (
        lambda v: isinstance(v, list) and all(isinstance(k, str) for k in v),
        "a list of observation keys",
        False,
    ),
    "perceived": (
        lambda v: isinstance(v, list) and all(isinstance(k, str) for k in v),
        "a list of observation keys",
        False,
    ),
    "perceived_dim": (_count(0), "an integer >= 0", False),
}


def _problem(doc: dict[str, Any], where: Any) -> Problem:
    """The learner's problem, each field checked (a shape of strings would otherwise
    read as a mismatch with the environment)."""
    for key, (ok, expected, required) in PROBLEM_FIELDS.items():
        if key not in doc:
            if required:
                raise CheckpointError(f"{where}: the field 'problem.{key}' is missing")
            continue
        value = doc[key]
        if not ok(value):
            text = repr(value)[:60]
            raise CheckpointError(
                f"{where}: the field 'problem.{key}' should be {expected}, not "
                f"{type(value).__name__} {text}"
            )
    unknown = sorted(set(doc) - set(PROBLEM_FIELDS))
    if unknown:
        raise CheckpointError(f"{where}: unknown fields in 'problem': {unknown}")
    return Problem.from_dict(doc)


def instruction_table(ckpt: Checkpoint) -> tuple[list[str], int]:
    """The instruction table of a language-goal checkpoint (``instructions.json``): its
    texts and how many of them are training instructions, checked.

    Raises:
        CheckpointError: the file is missing or malformed, naming it and the field.
    """
    doc = ckpt.json("instructions")
    path = ckpt.path / "instructions.json"
    if not isinstance(doc, dict):
        raise CheckpointError(f"{path}: expected an object, not {type(doc).__name__}")
    texts, num_train = doc.get("texts"), doc.get("num_train")
    if not isinstance(texts, list) or not all(isinstance(t, str) for t in texts):
        raise CheckpointError(f"{path}: the field 'texts' should be a list of strings")
    if not _count(1)(num_train) or num_train > len(texts):
        raise CheckpointError(
            f"{path}: the field 'num_train' should be an integer between 1 and the number of "
            f"texts ({len(texts)}), not {num_train!r}"
        )
    return texts, num_train


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
    problem = _problem(_field(ckpt, "problem", dict, "the learner's shapes and goals"), where)
    step = _field(ckpt, "step", int, "units trained")
    episodes = ckpt.meta.get("episodes", 0)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 0 or step < 0:
        raise CheckpointError(f"{where}: 'step' and 'episodes' must be integers >= 0")
    pending = ckpt.meta.get("eval_pending", False)
    if not isinstance(pending, bool):
        raise CheckpointError(
            f"{where}: the field 'eval_pending' should be true or false, not {pending!r}"
        )
    table = instruction_table(ckpt) if goal_modality(cfg.env.goal_type).text else None
    return RunMeta(cfg, algo, problem, step, episodes, table, pending)


# --- state.json -----------------------------------------------------------------------------
def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


#: Checks of the JSON values a trainer keeps in ``state.json``, by type.
STATE_TYPES: dict[type, tuple[Any, str]] = {
    int: (_count(0), "an integer >= 0"),
    float: (_number, "a number"),
    list: (lambda v: isinstance(v, list) and all(_number(x) for x in v), "a list of numbers"),
    bool: (lambda v: isinstance(v, bool), "true or false"),
}


def state_fields(
    ckpt: Checkpoint,
    name: str,
    fields: dict[str, type],
    optional: dict[str, type] | None = None,
) -> dict[str, Any]:
    """The saved state ``name`` of ``state.json``, an object whose ``fields`` are each
    present with their type (``optional`` ones may be absent): ``int`` (>= 0), ``float``
    (any number), ``list`` (of numbers), ``bool``.

    Raises:
        CheckpointError: the state or a field is missing or of the wrong type, naming
            ``state.json`` and the field (``trainer.credit``).
    """
    where = ckpt.path / "state.json"
    if not ckpt.has_state(name):
        raise CheckpointError(f"{where}: the state {name!r} is missing")
    doc = ckpt.state(name)
    if not isinstance(doc, dict):
        raise CheckpointError(
            f"{where}: the state {name!r} should be an object, not {type(doc).__name__}"
        )
    for key, kind in {**fields, **(optional or {})}.items():
        if key not in doc:
            if key in fields:
                raise CheckpointError(f"{where}: the field '{name}.{key}' is missing")
            continue
        ok, expected = STATE_TYPES[kind]
        if not ok(doc[key]):
            raise CheckpointError(
                f"{where}: the field '{name}.{key}' should be {expected}, not "
                f"{type(doc[key]).__name__} {repr(doc[key])[:60]}"
            )
    return doc


@contextlib.contextmanager
def restoring(ckpt: Checkpoint, what: str) -> Iterator[None]:
    """Put saved states back inside the block: a field missing or of the wrong type deep
    inside one (an optimiser's moments, a random generator's state) becomes a
    :class:`CheckpointError` naming ``state.json`` and ``what`` (the states being read),
    never a ``KeyError`` from the loader."""
    where = ckpt.path / "state.json"
    try:
        yield
    except (CheckpointError, LcrlError):
        raise
    except KeyError as e:
        raise CheckpointError(f"{where}: the field {e.args[0]!r} of {what} is missing") from None
    except (TypeError, ValueError, AttributeError, IndexError, RuntimeError) as e:
        first = (str(e).splitlines() or [""])[0][:120]
        raise CheckpointError(
            f"{where}: {what} cannot be restored ({type(e).__name__}: {first})"
        ) from None

"""Learners for goal-conditioned RL and behavioural cloning, and :data:`ALGOS`, their registry.

Every learner takes a :class:`Problem` (observation shapes, goal encoding, action space),
acts with :meth:`Agent.act`, and learns with ``update(batch) -> dict[str, float]``:

========  ==================================================================
``sac``   soft actor-critic (:mod:`lcrl.algos.sac`), multi-task options
``td3``   twin delayed DDPG (:mod:`lcrl.algos.td3`)
``crl``   contrastive RL (:mod:`lcrl.algos.crl`)
``dqn``   double DQN, discrete actions (:mod:`lcrl.algos.dqn`)
``bc``    behavioural cloning from demonstrations (:mod:`lcrl.algos.bc`)
========  ==================================================================

Each algorithm module ends with an :class:`AlgoSpec` of itself (agent class, config class,
action spaces, multi-task support, data source), and :data:`ALGOS` below is the one place
an algorithm is listed: :func:`build_agent`, :func:`check_algo`, the training config's
validation and the command line derive from it. Adding an algorithm takes a module with
its agent, config (with ``validate()``) and ``SPEC``, one line in :data:`ALGOS`, and a
field of the same name holding its config in :class:`train.config.TrainConfig`.
"""

from __future__ import annotations

from typing import Any

from lcrl.algos import bc, crl, dqn, sac, td3
from lcrl.algos.base import (
    ACTION_KINDS,
    DATA_SOURCES,
    GOAL_NORMALISERS,
    TEXT_GOAL_NORMS,
    Agent,
    AgentOptions,
    AlgoConfig,
    AlgoSpec,
    GoalEmbedder,
    Problem,
    check_fields,
    flat_target,
    resolve_device,
)
from lcrl.algos.bc import ACTION_CLIP, BC, BC_LOSSES, BCConfig, tanh_gaussian_log_prob
from lcrl.algos.crl import CRL, CRLConfig
from lcrl.algos.dqn import DQN, DQNConfig
from lcrl.algos.sac import SAC, SACConfig
from lcrl.algos.td3 import TD3, TD3Config
from lcrl.errors import LcrlError
from lcrl.multitask import MultiTaskOptions

#: Every algorithm, by name: the single list of them.
ALGOS: dict[str, AlgoSpec] = {
    "sac": sac.SPEC,
    "td3": td3.SPEC,
    "crl": crl.SPEC,
    "dqn": dqn.SPEC,
    "bc": bc.SPEC,
}

#: What ``auto`` stands for, by action space.
AUTO_ALGOS = {"continuous": "sac", "discrete": "dqn"}

__all__ = [
    "ACTION_CLIP",
    "ACTION_KINDS",
    "ALGOS",
    "AUTO_ALGOS",
    "BC",
    "BC_LOSSES",
    "CRL",
    "DATA_SOURCES",
    "DQN",
    "GOAL_NORMALISERS",
    "SAC",
    "TD3",
    "TEXT_GOAL_NORMS",
    "Agent",
    "AgentOptions",
    "AlgoConfig",
    "AlgoSpec",
    "BCConfig",
    "CRLConfig",
    "DQNConfig",
    "GoalEmbedder",
    "Problem",
    "SACConfig",
    "TD3Config",
    "algo_choices",
    "build_agent",
    "check_algo",
    "check_fields",
    "check_multitask",
    "flat_target",
    "resolve_algo",
    "resolve_device",
    "tanh_gaussian_log_prob",
]


def _one_of(names: list[str] | tuple[str, ...], word: str = "or") -> str:
    """``a, b or c``."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} {word} {names[-1]}"


def algo_choices() -> tuple[str, ...]:
    """The values ``--algo`` takes: ``auto`` and every name in :data:`ALGOS`."""
    return ("auto", *ALGOS)


def resolve_algo(name: str, discrete: bool) -> str:
    """The algorithm ``name`` stands for: ``auto`` is DQN for discrete actions and SAC for
    continuous ones (:data:`AUTO_ALGOS`), any other name itself.

    Args:
        name: ``auto`` or a name in :data:`ALGOS` (not checked here: see
            :func:`check_algo`).
        discrete: whether the environment's actions are discrete.
    """
    if name == "auto":
        return AUTO_ALGOS["discrete" if discrete else "continuous"]
    return name


def check_algo(name: str, discrete: bool | None = None) -> None:
    """Refuse an unknown algorithm, or one that does not take the environment's actions.

    Args:
        name: ``auto`` or a name in :data:`ALGOS`.
        discrete: whether the environment's actions are discrete; ``None`` (not known
            yet) checks the name only.

    Raises:
        LcrlError: an unknown name (the message lists :func:`algo_choices`), or an
            algorithm for the other kind of actions (the message names one that fits).
    """
    choices = algo_choices()
    if name not in choices:
        raise LcrlError(f"unknown algo {name!r}; choose {_one_of(choices)}")
    if discrete is None:
        return
    spec = ALGOS[resolve_algo(name, discrete)]
    if not spec.takes(discrete):
        have, need = ("discrete", "continuous") if discrete else ("continuous", "discrete")
        raise LcrlError(
            f"{spec.name} needs {need} actions; this env has {have} actions: use "
            f"{resolve_algo('auto', discrete)}"
        )


def check_multitask(name: str, options: MultiTaskOptions) -> None:
    """Refuse active multi-task options (PCGrad, task weights, conflict measurement) for an
    algorithm whose spec does not implement them.

    Args:
        name: the algorithm (``auto`` is not resolved: it passes).
        options: the multi-task options.

    Raises:
        LcrlError: the options are active and ``name`` is not a multi-task algorithm.
    """
    if not options.active or name == "auto":
        return
    spec = ALGOS.get(name)
    if spec is not None and spec.multitask:
        return
    able = [n for n, s in ALGOS.items() if s.multitask]
    what = "PCGrad, task weights and gradient-conflict measurement"
    if not able:
        raise LcrlError(f"{what} are not implemented by any algorithm: turn them off")
    raise LcrlError(
        f"{what} are implemented for {_one_of([n.upper() for n in able], 'and')}, not {name}: "
        f"use --algo {_one_of(able)} or turn the multitask options off"
    )


def build_agent(
    name: str,
    problem: Problem,
    options: AgentOptions,
    goal_embed: GoalEmbedder,
    config: Any = None,
) -> Agent:
    """The learner ``name`` for ``problem``, through its :class:`AlgoSpec`.

    Args:
        name: ``auto`` or a name in :data:`ALGOS`.
        problem: observation shapes, goal encoding, action space.
        options: networks, normalisation, device, seed, multi-task options.
        goal_embed: ``(goal ids or vectors, device) -> embedded goals``.
        config: an instance of the spec's config class (its defaults when ``None``);
            validated before the agent is built.

    Raises:
        LcrlError: an unknown algorithm, one for the other kind of actions, a config of
            another class, or settings the config or the agent refuse.
    """
    check_algo(name, problem.discrete)
    spec = ALGOS[resolve_algo(name, problem.discrete)]
    if config is None:
        config = spec.config()
    elif not isinstance(config, spec.config):
        raise LcrlError(
            f"{spec.name} takes a {spec.config.__name__}, not a {type(config).__name__}"
        )
    config.validate()
    agent = spec.agent(problem, options, goal_embed, config)
    if options.compile:
        agent.compile_networks()
    return agent

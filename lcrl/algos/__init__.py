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
field of the same name holding its config in :class:`train.configs.config.TrainConfig`.
"""

from __future__ import annotations

from typing import Any

from lcrl.algos import bc, crl, dqn, sac, td3
from lcrl.algos.base import (
    ACTION_KINDS,
    ALGOS,
    AUTO_ALGOS,
    DATA_SOURCES,
    GOAL_NORMALISERS,
    TEXT_GOAL_NORMS,
    Agent,
    AgentOptions,
    AlgoConfig,
    AlgoSpec,
    GoalEmbedder,
    Problem,
    algo_choices,
    check_algo,
    check_fields,
    check_multitask,
    flat_target,
    resolve_algo,
    resolve_device,
)
from lcrl.algos.bc import ACTION_CLIP, BC, BC_LOSSES, BCConfig, tanh_gaussian_log_prob
from lcrl.algos.crl import CRL, CRLConfig
from lcrl.algos.dqn import DQN, DQNConfig
from lcrl.algos.sac import SAC, SACConfig
from lcrl.algos.td3 import TD3, TD3Config
from lcrl.errors import LcrlError

# Every algorithm, by name: the single list of them. The dict itself lives in
# lcrl.algos.base (so that an agent checks itself against it without importing upward).
ALGOS.update(sac=sac.SPEC, td3=td3.SPEC, crl=crl.SPEC, dqn=dqn.SPEC, bc=bc.SPEC)

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

"""The algorithm registry (:data:`lcrl.algos.ALGOS`) and what derives from it: agent building,
the action-space and multi-task checks, each config's ``validate()``, the training config's
validation and fields, and rebuilding nested configs from saved dicts."""

from __future__ import annotations

import dataclasses
import re
import typing
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch
from helpers import cli, error_line

import train.evaluation.evaluate
from lcrl import algos
from lcrl.algos import (
    ALGOS,
    BC,
    CRL,
    DQN,
    SAC,
    TD3,
    Agent,
    AgentOptions,
    AlgoSpec,
    BCConfig,
    CRLConfig,
    DQNConfig,
    Problem,
    SACConfig,
    TD3Config,
    algo_choices,
    build_agent,
    check_algo,
    check_multitask,
    resolve_algo,
)
from lcrl.errors import LcrlError
from lcrl.multitask import MultiTaskOptions
from lcrl.nets import NetConfig
from train.configs.config import TrainConfig, config_from_dict, config_to_dict, nested_configs
from train.configs.presets import PRESETS

CONTINUOUS = Problem({"state": (3,)}, "vector", (2,), 2)
DISCRETE = Problem({"state": (3,)}, "vector", (2,), 4, discrete=True)
TASKS = Problem({"state": (3,)}, "onehot", (3,), 2, num_tasks=3)


def embed(goals: np.ndarray, device: torch.device) -> torch.Tensor:
    """Vector goals as they are; task ids one-hot over three tasks."""
    g = np.asarray(goals)
    if g.dtype.kind in "iu":
        return torch.eye(3, device=device)[torch.as_tensor(g, dtype=torch.long, device=device)]
    return torch.as_tensor(g, dtype=torch.float32, device=device)


def small(**fields) -> AgentOptions:
    """Agent options with tiny networks."""
    return AgentOptions(net=NetConfig(hidden=(8,), text_dim=4), **fields)


# --- a toy algorithm, registered from here ---------------------------------------------------
@dataclass
class ToyConfig:
    """A config with one setting."""

    lr: float = 0.1

    def validate(self) -> None:
        """Refuse a non-positive learning rate."""
        if not self.lr > 0:
            raise LcrlError(f"toy.lr must be positive, got {self.lr}")


class Toy(Agent):
    """An agent that acts with zeros and learns nothing."""

    name = "toy"

    def __init__(
        self,
        problem: Problem,
        options: AgentOptions,
        goal_embed: algos.GoalEmbedder,
        config: ToyConfig | None = None,
    ) -> None:
        super().__init__(problem, options, goal_embed)
        self.cfg = config or ToyConfig()

    def act(self, obs, goal, deterministic=False, embedded=False) -> np.ndarray:
        """Zero actions."""
        return np.zeros((len(goal), self.problem.action_dim), np.float32)

    def update(self, batch) -> dict[str, float]:
        """Nothing to learn."""
        self.updates += 1
        return {"loss": 0.0}


TOY = AlgoSpec(
    name="toy",
    agent=Toy,
    config=ToyConfig,
    actions="discrete",
    multitask=True,
    summary="a test algorithm",
)


@pytest.fixture
def toy(monkeypatch) -> AlgoSpec:
    """:data:`TOY` registered in ALGOS for the test."""
    monkeypatch.setitem(ALGOS, "toy", TOY)
    return TOY


# --- the registry ----------------------------------------------------------------------------
def test_registry_lists_every_algorithm_once_with_its_classes():
    assert list(ALGOS) == ["sac", "td3", "crl", "dqn", "bc"]
    expected = {
        "sac": (SAC, SACConfig, "continuous", True, "env"),
        "td3": (TD3, TD3Config, "continuous", False, "env"),
        "crl": (CRL, CRLConfig, "continuous", False, "env"),
        "dqn": (DQN, DQNConfig, "discrete", False, "env"),
        "bc": (BC, BCConfig, "any", False, "demos"),
    }
    for name, spec in ALGOS.items():
        assert spec.name == name == spec.agent.name
        assert (spec.agent, spec.config, spec.actions, spec.multitask, spec.learns_from) == (
            expected[name]
        )
        assert spec.summary
        spec.config().validate()  # the defaults are valid
    assert algo_choices() == ("auto", "sac", "td3", "crl", "dqn", "bc")


def test_every_algorithm_has_a_train_config_field_holding_its_config():
    hints = typing.get_type_hints(TrainConfig)
    defaults = TrainConfig()
    for name, spec in ALGOS.items():
        assert hints[name] is spec.config, name
        assert isinstance(getattr(defaults, name), spec.config)
    assert nested_configs(TrainConfig)["sac"] is SACConfig


def test_resolve_algo():
    assert resolve_algo("auto", discrete=False) == "sac"
    assert resolve_algo("auto", discrete=True) == "dqn"
    assert resolve_algo("td3", discrete=False) == "td3"


def test_check_algo_errors():
    choices = r"unknown algo 'ppo'; choose auto, sac, td3, crl, dqn or bc$"
    with pytest.raises(LcrlError, match=choices):
        check_algo("ppo")
    with pytest.raises(
        LcrlError, match=r"^sac needs continuous actions; this env has discrete actions: use dqn$"
    ):
        check_algo("sac", discrete=True)
    with pytest.raises(LcrlError, match=r"^td3 needs continuous actions"):
        check_algo("td3", discrete=True)
    with pytest.raises(
        LcrlError, match=r"^dqn needs discrete actions; this env has continuous actions: use sac$"
    ):
        check_algo("dqn", discrete=False)
    for discrete in (False, True):
        check_algo("auto", discrete)
        check_algo("bc", discrete)  # behavioural cloning takes either
    check_algo("dqn")  # the action space is not known yet: the name only


def test_check_multitask_follows_the_specs():
    active = MultiTaskOptions(pcgrad=True)
    check_multitask("sac", active)
    check_multitask("auto", active)  # resolved (and checked) when the agent is built
    check_multitask("td3", MultiTaskOptions())
    for name in ("td3", "dqn", "bc"):
        with pytest.raises(LcrlError, match=f"implemented for SAC, not {name}: use --algo sac"):
            check_multitask(name, active)


def test_build_agent_through_the_specs():
    agent = build_agent("auto", DISCRETE, small(), embed)
    assert isinstance(agent, DQN) and agent.cfg == DQNConfig()
    agent = build_agent("sac", CONTINUOUS, small(), embed, SACConfig(gamma=0.9))
    assert isinstance(agent, SAC) and agent.cfg.gamma == 0.9
    assert isinstance(build_agent("bc", DISCRETE, small(), embed), BC)
    with pytest.raises(LcrlError, match="sac takes a SACConfig, not a TD3Config"):
        build_agent("sac", CONTINUOUS, small(), embed, TD3Config())
    with pytest.raises(LcrlError, match=r"sac.gamma must be in \(0, 1\], got 0.0"):
        build_agent("sac", CONTINUOUS, small(), embed, SACConfig(gamma=0.0))
    with pytest.raises(LcrlError, match="unknown algo 'ppo'"):
        build_agent("ppo", CONTINUOUS, small(), embed)
    with pytest.raises(LcrlError, match="td3 needs continuous actions"):
        build_agent("td3", DISCRETE, small(), embed)


def test_train_build_agent_takes_the_config_field_named_after_the_algorithm():
    cfg = TrainConfig(agent=small(), td3=TD3Config(policy_delay=5), dqn=DQNConfig(lr=0.5))
    agent = train.evaluation.evaluate.build_agent("td3", CONTINUOUS, cfg, embed)
    assert isinstance(agent, TD3) and agent.cfg.policy_delay == 5
    agent = train.evaluation.evaluate.build_agent("auto", DISCRETE, cfg, embed)
    assert isinstance(agent, DQN) and agent.cfg.lr == 0.5
    with pytest.raises(LcrlError, match="dqn needs discrete actions"):
        train.evaluation.evaluate.build_agent("dqn", CONTINUOUS, cfg, embed)


def test_agents_check_their_spec_when_built_directly():
    with pytest.raises(LcrlError, match="sac needs continuous actions"):
        SAC(DISCRETE, small(), embed)
    with pytest.raises(LcrlError, match="implemented for SAC, not bc"):
        BC(TASKS, small(multitask=MultiTaskOptions(conflict_every=2)), embed)
    sac = SAC(TASKS, small(multitask=MultiTaskOptions(conflict_every=2)), embed)
    assert sac.multitask is not None


def test_a_toy_algorithm_registered_in_algos_builds_through_the_registry(toy):
    assert algo_choices() == ("auto", "sac", "td3", "crl", "dqn", "bc", "toy")
    agent = build_agent("toy", DISCRETE, small(), embed)
    assert isinstance(agent, Toy) and agent.cfg == ToyConfig()
    agent = build_agent("toy", DISCRETE, small(), embed, ToyConfig(lr=0.5))
    assert agent.cfg.lr == 0.5
    with pytest.raises(LcrlError, match=r"toy\.lr must be positive"):
        build_agent("toy", DISCRETE, small(), embed, ToyConfig(lr=-1.0))
    with pytest.raises(LcrlError, match=r"toy needs discrete actions; .* use sac"):
        build_agent("toy", CONTINUOUS, small(), embed)
    with pytest.raises(LcrlError, match="toy needs discrete actions"):
        Toy(CONTINUOUS, small(), embed)  # built directly, the spec still applies
    # multi-task support comes from the spec: the toy declares it, so do the messages
    problem = dataclasses.replace(TASKS, discrete=True, action_dim=4)
    build_agent("toy", problem, small(multitask=MultiTaskOptions(pcgrad=True)), embed)
    with pytest.raises(LcrlError, match="implemented for SAC and TOY, not dqn"):
        check_multitask("dqn", MultiTaskOptions(pcgrad=True))


def test_unregistered_agents_refuse_multitask_options():
    class Other(Toy):
        name = "other"

    Other(CONTINUOUS, small(), embed)  # no spec: no action-space check
    with pytest.raises(LcrlError, match="not other"):
        Other(TASKS, small(multitask=MultiTaskOptions(pcgrad=True)), embed)


def test_spec_checks_its_fields():
    with pytest.raises(LcrlError, match="actions must be one of"):
        AlgoSpec(name="toy", agent=Toy, config=ToyConfig, actions="both")
    with pytest.raises(LcrlError, match="learns_from must be one of"):
        AlgoSpec(name="toy", agent=Toy, config=ToyConfig, actions="any", learns_from="web")
    with pytest.raises(LcrlError, match="names agent class Toy whose name is 'toy'"):
        AlgoSpec(name="toy2", agent=Toy, config=ToyConfig, actions="any")


# --- validate() of every config ------------------------------------------------------------
@pytest.mark.parametrize(
    ("config", "match"),
    [
        (SACConfig(gamma=0.0), r"sac.gamma must be in \(0, 1\]"),
        (SACConfig(gamma=1.5), r"sac.gamma must be in \(0, 1\]"),
        (SACConfig(tau=0.0), r"sac.tau must be in \(0, 1\]"),
        (SACConfig(actor_lr=0.0), "sac.actor_lr must be positive"),
        (SACConfig(critic_lr=-1e-3), "sac.critic_lr must be positive"),
        (SACConfig(alpha_lr=float("nan")), "sac.alpha_lr must be positive"),
        (SACConfig(init_alpha=0.0), "sac.init_alpha must be positive"),
        (SACConfig(hindsight_bc=-1.0), "sac.hindsight_bc must be >= 0"),
        (SACConfig(max_grad_norm=0.0), r"sac.max_grad_norm must be positive \(or None\)"),
        (SACConfig(target_entropy=float("inf")), r"sac.target_entropy must be finite"),
        (TD3Config(gamma=2.0), r"td3.gamma must be in \(0, 1\]"),
        (TD3Config(tau=1.5), r"td3.tau must be in \(0, 1\]"),
        (TD3Config(actor_lr=0.0), "td3.actor_lr must be positive"),
        (TD3Config(policy_delay=0), "td3.policy_delay must be positive"),
        (TD3Config(policy_noise=-0.1), "td3.policy_noise must be >= 0"),
        (TD3Config(noise_clip=-0.1), "td3.noise_clip must be >= 0"),
        (TD3Config(exploration_noise=-0.1), "td3.exploration_noise must be >= 0"),
        (TD3Config(max_grad_norm=-1.0), "td3.max_grad_norm must be positive"),
        (DQNConfig(gamma=0.0), r"dqn.gamma must be in \(0, 1\]"),
        (DQNConfig(tau=0.0), r"dqn.tau must be in \(0, 1\]"),
        (DQNConfig(lr=0.0), "dqn.lr must be positive"),
        (DQNConfig(eps_start=1.5), r"dqn.eps_start must be in \[0, 1\]"),
        (DQNConfig(eps_end=-0.1), r"dqn.eps_end must be in \[0, 1\]"),
        (DQNConfig(eps_decay_steps=-1), "dqn.eps_decay_steps must be >= 0"),
        (DQNConfig(max_grad_norm=0.0), "dqn.max_grad_norm must be positive"),
        (BCConfig(loss="huber"), "unknown bc.loss"),
        (BCConfig(lr=0.0), "bc.lr must be positive"),
        (BCConfig(weight_decay=-1.0), "bc.weight_decay must be >= 0"),
        (BCConfig(max_grad_norm=0.0), "bc.max_grad_norm must be positive"),
        (BCConfig(norm_rows=0), "bc.norm_rows must be positive"),
    ],
)
def test_config_validate_refuses_bad_settings(config, match):
    with pytest.raises(LcrlError, match=match):
        config.validate()


def test_config_validate_accepts_edge_values():
    SACConfig(gamma=1.0, tau=1.0, max_grad_norm=None, target_entropy=-3.0).validate()
    TD3Config(policy_noise=0.0, noise_clip=0.0, exploration_noise=0.0).validate()
    DQNConfig(eps_start=0.0, eps_end=1.0, eps_decay_steps=0, max_grad_norm=None).validate()
    BCConfig(weight_decay=0.0, max_grad_norm=None).validate()


# --- the training config ---------------------------------------------------------------------
def test_train_config_validates_the_chosen_algorithm_and_its_config():
    base = TrainConfig()
    base.validate()
    choices = "unknown algo 'ppo'; choose auto, sac, td3, crl, dqn or bc"
    with pytest.raises(LcrlError, match=choices):
        dataclasses.replace(base, algo="ppo").validate()
    with pytest.raises(LcrlError, match=r"td3\.policy_delay"):
        dataclasses.replace(base, algo="td3", td3=TD3Config(policy_delay=0)).validate()
    # only the chosen algorithm's config is checked; auto checks both it may stand for
    dataclasses.replace(base, algo="sac", td3=TD3Config(policy_delay=0)).validate()
    with pytest.raises(LcrlError, match=r"dqn\.lr"):
        dataclasses.replace(base, dqn=DQNConfig(lr=0.0)).validate()
    with pytest.raises(LcrlError, match=r"bc\.lr"):
        dataclasses.replace(base, algo="bc", bc=BCConfig(lr=0.0)).validate()
    demos_only = "--demos is read by behavioural cloning only: add --algo bc"
    with pytest.raises(LcrlError, match=demos_only):
        dataclasses.replace(base, demos="demos.h5").validate()
    for _, cfg in PRESETS.values():
        cfg.validate()


def test_cli_refuses_an_unknown_algorithm(capsys):
    assert cli("train", "lang2d-quick", "--algo", "ppo", "--no-progress") == 2
    err = error_line(capsys.readouterr().err)
    assert "unknown algo 'ppo'; choose auto, sac, td3, crl, dqn or bc" in err


# --- rebuilding nested configs ---------------------------------------------------------------
@dataclass
class Inner:
    """A nested config."""

    sizes: tuple[int, ...] = (1, 2)
    rate: float = 0.5


@dataclass
class Outer:
    """A config holding another (annotations are strings here)."""

    inner: Inner = field(default_factory=Inner)
    maybe: Inner | None = None
    count: int = 3


def test_nested_configs_read_the_annotations():
    assert nested_configs(Outer) == {"inner": Inner}
    assert nested_configs(AgentOptions) == {"net": NetConfig, "multitask": MultiTaskOptions}
    top = nested_configs(TrainConfig)
    assert {"env", "agent", "buffer", "relabel", "text_encoder", *ALGOS} <= set(top)
    assert "algo" not in top and "out" not in top


def test_config_from_dict_rebuilds_nested_configs():
    cfg = PRESETS["lang2d-tasks"][1]
    saved = config_to_dict(cfg)
    back = config_from_dict(saved)
    assert back == cfg
    assert isinstance(back.agent.net, NetConfig) and isinstance(back.agent.net.hidden, tuple)
    assert isinstance(back.agent.multitask, MultiTaskOptions)
    assert back.env.tasks == cfg.env.tasks and isinstance(back.env.tasks, tuple)
    # a config saved before newer fields existed: they take their defaults
    old = config_to_dict(TrainConfig(sac=SACConfig(gamma=0.9)))
    del old["sac"]["hindsight_bc"], old["agent"]["multitask"], old["bc"]
    del old["agent"]["text_goal_norm"]
    back = config_from_dict(old)
    assert back.sac == SACConfig(gamma=0.9)
    assert back.agent.multitask == MultiTaskOptions() and back.bc == BCConfig()
    assert back.agent.text_goal_norm == "standardize"
    old["sac"]["momentum"] = 0.9
    unknown = r"unknown SACConfig fields in a saved config: \['momentum'\]"
    with pytest.raises(LcrlError, match=unknown):
        config_from_dict(old)


def test_config_from_dict_checks_every_value_against_its_field():
    from train.configs.config import ConfigFieldError

    saved = config_to_dict(PRESETS["lang2d"][1])
    saved["sac"]["gamma"] = 1  # an integer where a number goes
    saved["sac"]["max_grad_norm"] = None  # optional
    saved["env"]["extra"] = {"image_size": 32}
    back = config_from_dict(saved)
    assert back.sac.gamma == 1 and back.sac.max_grad_norm is None
    assert back.env.extra == {"image_size": 32} and isinstance(back.agent.net.slots, tuple)
    cases = [
        (("agent", "net", "hidden"), "big", "'x.agent.net.hidden' should be a list of integers"),
        (("agent", "net", "hidden"), [1, True], "should be a list of integers, not list"),
        (("env", "families"), [1], "'x.env.families' should be a list of strings"),
        (("env", "extra"), [], "'x.env.extra' should be an object, not list []"),
        (("total_steps",), "9", "'x.total_steps' should be an integer, not str '9'"),
        (("progress",), 1, "'x.progress' should be true or false, not int 1"),
        (("sac", "actor_lr"), "fast", "'x.sac.actor_lr' should be a number, not str 'fast'"),
        (("buffer",), 3, "'x.buffer' should be an object, not int 3"),
    ]
    for path, value, message in cases:
        doc = config_to_dict(PRESETS["lang2d"][1])
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
        with pytest.raises(ConfigFieldError, match=re.escape(message)):
            config_from_dict(doc, prefix="x.")

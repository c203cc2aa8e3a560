"""The named presets of ``lcrl train PRESET``: each a one-line description and a
:class:`train.configs.config.TrainConfig`. ``lcrl train --help`` lists them; a test holds
each description to its config (``tests/test_presets.py``)."""

from __future__ import annotations

import dataclasses
from typing import Any

from lcrl.algos import (
    AgentOptions,
    SACConfig,
)
from lcrl.multitask import MultiTaskOptions
from lcrl.nets import NetConfig
from train.configs.config import BufferConfig, CollectionConfig, ExploreConfig, TrainConfig
from train.environments.tasks import (
    EnvConfig,
    goal_modality,
    slot_attributes,
)

#: Object slots of the 2D tabletop's observation with relative positions and
#: displacements: after the pusher's x, y, 8 kinds of [x, y, present, x - pusher x,
#: y - pusher y, x - x at reset, y - y at reset].
SLOTS_2D = (2, 8, 7)
#: The attributes of the 8 object slots of both tabletops (slot ``k`` holds
#: ``envs.scene.OBJECT_KINDS[k]``): each slot's colour index, then its shape index, for
#: ``--agent.net.slot-mode attributes``.
SLOT_ATTRIBUTES = slot_attributes()


def _env2d(**fields: Any) -> EnvConfig:
    """The 2D tabletop with language goals, object slots extended by positions relative to
    the pusher and displacements since the reset (what reach and push are judged on)."""
    values: dict[str, Any] = {"families": ("reach", "push")}
    values.update(fields)
    return EnvConfig(kind="tabletop2d", relative_positions=True, displacements=True, **values)


def _net2d(**fields: Any) -> AgentOptions:
    """Language goals pick object slots by position (``slot_mode="select"``) and read
    positions relative to the pusher: the critic learns the reach reward several times
    faster than from the plain concatenation (see docs/design.md)."""
    return AgentOptions(net=NetConfig(**{"slots": SLOTS_2D, "slot_mode": "select", **fields}))


def _grounded2d(**fields: Any) -> AgentOptions:
    """:func:`_net2d` with slots picked through their colour and shape and the grounding
    loss: held-out word combinations reach their objects (docs/design.md)."""
    agent = _net2d(slot_mode="attributes", slot_attributes=SLOT_ATTRIBUTES, **fields)
    agent.grounding = 1.0
    return agent


#: The fastest collection measured on the 2D tabletop: 8 environments stepped at once and
#: batches of 128 reached 80% seen success on lang2d in 225 s, where one environment at
#: batch 256 took 542 s (benchmarks/results/time_to_success.md).
FAST_2D: dict[str, Any] = {"collect": CollectionConfig(envs=8), "batch_size": 128}
#: The same settings on the goal-reaching presets (state2d, fetch-reach): on validation
#: seeds they reached 90% success in 17-18 s of training where one environment at batch
#: 256 took 27-65 s (state2d), 11-12 s against 15-16 s (fetch-reach) (docs/scale.md).
FAST_GOALS: dict[str, Any] = dict(FAST_2D)


def _lang2d(**overrides: Any) -> TrainConfig:
    cfg = TrainConfig(
        out="runs/lang2d",
        env=_env2d(),
        agent=_net2d(),
        buffer=BufferConfig(k=4, random_fraction=0.1),
        total_steps=100_000,
        scripted_fraction=0.2,
        eval_every=10_000,
        eval_episodes=100,
    )
    return dataclasses.replace(cfg, **overrides)


#: The task set of the lang2d-tasks presets: 4 reach and 4 push instructions of the 2D
#: split's training set (seed 0), over four objects, pushes in all four directions.
TASKS_2D = (
    "reach the red cube",
    "reach the green cylinder",
    "reach the blue cube",
    "reach the yellow cube",
    "push the red cube left",
    "push the green cylinder right",
    "push the blue cube forward",
    "push the yellow cube backward",
)


def _lang2d_tasks(goal_type: str, **overrides: Any) -> TrainConfig:
    """The 8 tasks of :data:`TASKS_2D` on the 2D tabletop, 30k steps: one-hot task ids
    without relabelling (``task``) or the same instructions as language goals with
    language HER (``language``); gradient conflict measured every 10 updates.

    The language goals collect with :data:`FAST_2D`: on seeds 100 and 101 they reached 50%
    seen success in 168 s of training against 255 s from one environment at batch 256,
    ending at 0.69 against 0.64. Task ids keep one environment at batch 256: it reached
    15% (their runs end near 0.2) in 177 s against 278 s, although 8 environments ended
    higher, 0.23 against 0.18 (benchmarks/results/preset-settings-lang2d-tasks*.md)."""
    relabel = goal_modality(goal_type).relabel
    agent = _net2d()
    agent.multitask = MultiTaskOptions(conflict_every=10)
    cfg = _lang2d(
        out=f"runs/lang2d-tasks{'-lang' if relabel else ''}",
        env=_env2d(goal_type=goal_type, tasks=TASKS_2D),
        agent=agent,
        buffer=BufferConfig(k=4, random_fraction=0.1) if relabel else BufferConfig(k=0),
        total_steps=30_000,
        eval_every=5_000,
        eval_episodes=80,
        **(FAST_2D if relabel else {}),
    )
    return dataclasses.replace(cfg, **overrides)


def _robosuite(**overrides: Any) -> TrainConfig:
    env = dict(kind="robosuite", families=("reach", "push"), max_objects=3)
    env.update(overrides.pop("env", {}))
    cfg = TrainConfig(
        out="runs/robosuite",
        env=EnvConfig(**env),
        buffer=BufferConfig(k=4, random_fraction=0.1),
        total_steps=100_000,
        learning_starts=2_000,
        eval_every=10_000,
        eval_episodes=50,
    )
    return dataclasses.replace(cfg, **overrides)


_IMAGE_AGENT = AgentOptions(net=NetConfig(share_cnn=True), augment_pad=4)

#: Object slots of the robosuite tabletop's observation with relative positions and
#: displacements: after the gripper's x, y, z and opening, 8 kinds of [x, y, z, present,
#: 3 positions relative to the gripper, 3 displacements since the reset].
SLOTS_ROBOSUITE = (4, 8, 10)


def _robosuite_slots(families: tuple[str, ...] = ("reach",), **env: Any) -> TrainConfig:
    """The robosuite tabletop with the 2D tabletop's lessons: positions relative to the
    gripper and displacements since the reset in each object slot, slots picked by the
    goal, 20% scripted exploration episodes; 30k steps."""
    return _robosuite(
        out="runs/robosuite-reach",
        env={"families": families, "relative_positions": True, "displacements": True, **env},
        agent=AgentOptions(net=NetConfig(slots=SLOTS_ROBOSUITE, slot_mode="select")),
        scripted_fraction=0.2,
        total_steps=30_000,
        eval_every=5_000,
    )


def _robosuite_reach() -> TrainConfig:
    """:func:`_robosuite_slots` with slots picked through their colour and shape, the
    grounding loss and TD targets clipped to the value bound of success rewards: over 3
    seeds, seen 0.98 and held-out combinations 0.94 of it, where slot selection by position
    had 0.88 and 0.10 (benchmarks/results/compositional-robosuite.md)."""
    cfg = _robosuite_slots()
    agent = AgentOptions(
        net=NetConfig(
            slots=SLOTS_ROBOSUITE, slot_mode="attributes", slot_attributes=SLOT_ATTRIBUTES
        ),
        grounding=1.0,
    )
    return dataclasses.replace(cfg, agent=agent, sac=dataclasses.replace(cfg.sac, target_clip=1.0))


#: robosuite-reach's collection: on seeds 100 and 101, 8 environments at batch 128 reached
#: 80% seen success in 270-282 s of training where one environment at batch 256 took
#: 355-431 s, and ended as high (docs/scale.md). Only that preset takes it: the presets
#: built on :func:`_robosuite_reach` (the camera ones) were not measured.
FAST_ROBOSUITE_REACH: dict[str, Any] = dict(FAST_2D)


#: The perception model kept in the repository (3,000 episodes, benchmarks/models/README.md):
#: the camera presets' default, so that they train from a fresh clone.
PERCEPTION_KEPT = "benchmarks/models/perception-3k/model"


def _robosuite_image_reach() -> TrainConfig:
    """:func:`_robosuite_reach` acting through perception's estimate of the object slots
    from the agentview camera, with a critic that reads the true state in training."""
    cfg = _robosuite_reach()
    env = dataclasses.replace(cfg.env, perception=PERCEPTION_KEPT)
    agent = dataclasses.replace(cfg.agent, privileged_critic=True)
    return dataclasses.replace(cfg, out="runs/robosuite-image-reach", env=env, agent=agent)


#: The robosuite instruction families in the order the manipulation curriculum opens them.
MANIPULATION_FAMILIES = ("reach", "push", "lift", "put", "stack")


def _robosuite_manip(families: tuple[str, ...] = MANIPULATION_FAMILIES) -> TrainConfig:
    """:func:`_robosuite_slots` for manipulation: 100-step episodes (the scripted put and
    stack take up to about 90), a third of the policy's episodes begun by the scripted
    controller, chains of up to 3 instructions, and with several families a curriculum
    that opens them in order; 300k steps, a checkpoint (with the replay buffer) every 10k
    so that ``--resume`` carries a run across sessions."""
    name = "manip" if len(families) > 1 else families[0]
    cfg = _robosuite_slots(families, max_episode_steps=100)
    return dataclasses.replace(
        cfg,
        out=f"runs/robosuite-{name}",
        explore=ExploreConfig(
            chain=0.5,
            handover=0.3,
            handover_steps=60,
            curriculum=families if len(families) > 1 else (),
        ),
        total_steps=300_000,
        eval_every=10_000,
        checkpoint_every=10_000,
        keep_checkpoints=1,
    )


def _robosuite_family(family: str) -> TrainConfig:
    """:func:`_robosuite_manip` on one grasping family (``put``, ``stack``) with
    robosuite-reach's grounded slots (colour and shape, the grounding loss, whose second
    head picks the reference object), TD targets clipped to the value bound and 3-step
    returns. From 2,000 scripted demonstrations of the five families (``--finetune.demos``,
    ``--sac.demo-bc 1.0``), stack alone reached 0.66 to 0.76 seen success at 5k to 15k
    steps, where the same run with slots picked by position and 1-step returns was at 0.10
    to 0.26 (benchmarks/results/robosuite-manipulation-rl.md)."""
    cfg = _robosuite_manip((family,))
    agent = AgentOptions(
        net=NetConfig(
            slots=SLOTS_ROBOSUITE, slot_mode="attributes", slot_attributes=SLOT_ATTRIBUTES
        ),
        grounding=1.0,
    )
    return dataclasses.replace(
        cfg,
        agent=agent,
        sac=dataclasses.replace(cfg.sac, target_clip=1.0),
        buffer=dataclasses.replace(cfg.buffer, n_step=3),
    )


PRESETS: dict[str, tuple[str, TrainConfig]] = {
    "lang2d": (
        "2D tabletop, language goals (reach, push), SAC + language HER, 20% scripted "
        "exploration episodes, 8 environments at once, batches of 128, an update every "
        "second step, 100k steps",
        # half an update per step, chosen on validation seeds 100-103: 80% seen success in
        # 226-378 s of training against 312-594 s; on seeds 102 and 103 final seen success
        # at 60k steps 0.94 against 0.93 (benchmarks/results/preset-settings-lang2d-60k.md)
        _lang2d(updates_per_step=0.5, **FAST_2D),
    ),
    "lang2d-noher": (
        "the lang2d run without hindsight relabelling (the baseline it must beat)",
        _lang2d(out="runs/lang2d-noher", buffer=BufferConfig(k=0), **FAST_2D),
    ),
    "lang2d-rl": (
        "the lang2d run without scripted episodes: every training episode is the policy's",
        _lang2d(out="runs/lang2d-rl", scripted_fraction=0.0, **FAST_2D),
    ),
    "lang2d-grounded": (
        "lang2d with slots picked through their colour and shape, the grounding loss and "
        "16 training-only phrasings per instruction: held-out word combinations as seen "
        "ones; 8 environments at once, batches of 128",
        _lang2d(
            out="runs/lang2d-grounded",
            env=_env2d(phrasings=16),
            agent=_grounded2d(),
            **FAST_2D,
        ),
    ),
    "lang2d-quick": (
        "a small lang2d run (reach, 2 objects, 8k steps, small networks, slots picked through "
        "their colour and shape with the grounding loss): a few minutes on a CPU",
        _lang2d(
            out="runs/lang2d-quick",
            env=_env2d(families=("reach",), min_objects=2, max_objects=2, max_episode_steps=30),
            agent=_grounded2d(hidden=(128, 128), text_dim=32),
            total_steps=8_000,
            learning_starts=500,
            batch_size=128,
            eval_every=4_000,
            eval_episodes=50,
            checkpoint_every=0,
        ),
    ),
    "lang2d-dqn": (
        "2D tabletop, language goals, 8 discrete moves, double DQN + language HER",
        _lang2d(
            out="runs/lang2d-dqn",
            env=_env2d(discrete=True),
        ),
    ),
    "lang2d-td3": (
        "2D tabletop, language goals (reach, push), TD3 + language hindsight relabelling, "
        "8 environments at once, batches of 128",
        # chosen on validation seeds 100 and 101: 80% seen success after 286 and 457 s of
        # training against 758 and 1,059 s with one environment at batch 256, final seen
        # success 0.87 against 0.89 (benchmarks/results/preset-settings-lang2d-td3.md)
        _lang2d(out="runs/lang2d-td3", algo="td3", **FAST_2D),
    ),
    "state2d": (
        "2D tabletop with state goals (pusher position), SAC + HER, 8 environments at once, "
        "batches of 128, 20k steps",
        TrainConfig(
            out="runs/state2d",
            env=EnvConfig(kind="tabletop2d", goal_type="state", goal="pusher"),
            total_steps=20_000,
            eval_every=5_000,
            **FAST_GOALS,
        ),
    ),
    "robosuite": (
        "robosuite Panda tabletop, language goals (reach, push), privileged state, SAC + "
        "language HER, 100k steps",
        _robosuite(),
    ),
    "robosuite-reach": (
        "robosuite Panda tabletop, reach instructions, privileged state, positions relative "
        "to the gripper and displacements, slots picked through their colour and shape with "
        "the grounding loss, TD targets clipped to the value bound, 20% scripted episodes, "
        "8 environments at once, batches of 128, 30k steps",
        dataclasses.replace(_robosuite_reach(), **FAST_ROBOSUITE_REACH),
    ),
    "robosuite-manip": (
        "robosuite Panda tabletop, all five families (reach, push, lift, put, stack) in one "
        "policy, privileged state: object slots picked by position, starts along scripted "
        "demonstrations, chains of instructions and a curriculum over families, 300k steps",
        _robosuite_manip(),
    ),
    "robosuite-push": (
        "robosuite-manip's recipe on push instructions alone, 300k steps",
        _robosuite_manip(("push",)),
    ),
    "robosuite-lift": (
        "robosuite-manip's recipe on lift instructions alone, 300k steps",
        _robosuite_manip(("lift",)),
    ),
    "robosuite-put": (
        "robosuite-manip's recipe on put instructions alone, with robosuite-reach's grounded "
        "slots (colour and shape, the grounding loss), clipped TD targets and 3-step "
        "returns, 300k steps",
        _robosuite_family("put"),
    ),
    "robosuite-stack": (
        "robosuite-put's recipe on stack instructions, 300k steps",
        _robosuite_family("stack"),
    ),
    "robosuite-image-reach": (
        "robosuite-reach (slots picked through their colour and shape, the grounding loss, "
        "TD targets clipped to the value bound, 20% scripted episodes, 30k steps) acting "
        "from the agentview camera and proprioception through a frozen perception model "
        f"(--env.perception, default the kept {PERCEPTION_KEPT}); the critic reads the true "
        "state in training",
        _robosuite_image_reach(),
    ),
    "robosuite-state": (
        "robosuite Panda tabletop, state goals (one object moved), SAC + HER",
        _robosuite(out="runs/robosuite-state", env={"goal_type": "state"}),
    ),
    "robosuite-image-goal": (
        "robosuite Panda tabletop, image goals and 64x64 camera observations, one CNN for "
        "both, random-shift augmentation, SAC + HER",
        _robosuite(
            out="runs/robosuite-image-goal",
            env={"goal_type": "image", "image_obs": True},
            agent=_IMAGE_AGENT,
            buffer=BufferConfig(capacity=200_000, k=4),
        ),
    ),
    "robosuite-image": (
        "robosuite Panda tabletop, language goals (reach, push) from 64x64 camera images and "
        "proprioception, SAC + language HER",
        _robosuite(
            out="runs/robosuite-image",
            env={"image_obs": True},
            agent=AgentOptions(augment_pad=4),
            buffer=BufferConfig(capacity=200_000, k=4, random_fraction=0.1),
        ),
    ),
    "lang2d-bc": (
        "behavioural cloning on the lang2d env from --demos (record them with lcrl demos "
        "record --preset lang2d), 20k updates",
        _lang2d(
            out="runs/lang2d-bc",
            algo="bc",
            total_steps=20_000,
            eval_every=5_000,
            checkpoint_every=5_000,
            log_every=500,
        ),
    ),
    "robosuite-bc": (
        "behavioural cloning on the robosuite env from --demos (record them with lcrl demos "
        "record --preset robosuite), 20k updates",
        _robosuite(
            out="runs/robosuite-bc",
            algo="bc",
            total_steps=20_000,
            eval_every=5_000,
            checkpoint_every=5_000,
            log_every=500,
        ),
    ),
    "lang2d-tasks": (
        "multi-task RL on the 2D tabletop: 8 fixed tasks (4 reach, 4 push) as one-hot task "
        "ids, each with its own reward, no relabelling, SAC, 30k steps (add "
        "--agent.multitask.pcgrad for PCGrad)",
        _lang2d_tasks("task"),
    ),
    "lang2d-tasks-lang": (
        "the 8 tasks of lang2d-tasks as language goals with language HER among them, SAC, "
        "8 environments at once, batches of 128, 30k steps (add --agent.multitask.pcgrad "
        "for PCGrad)",
        _lang2d_tasks("language"),
    ),
    "fetch-reach": (
        "gymnasium-robotics FetchReach-v4 (state goals), SAC + HER, 8 environments at once, "
        "batches of 128, 10k steps",
        TrainConfig(
            out="runs/fetch-reach",
            env=EnvConfig(kind="gym", goal_type="state", gym_id="FetchReach-v4"),
            sac=SACConfig(gamma=0.95),
            total_steps=10_000,
            learning_starts=1_000,
            eval_every=2_000,
            eval_episodes=50,
            checkpoint_every=0,
            **FAST_GOALS,
        ),
    ),
}

"""Goal spaces: what a goal is, how it is relabelled, how its reward is recomputed.

The replay buffer (:mod:`lcrl.buffer`) stores episodes and picks which transitions to
relabel; a goal space owns everything goal-specific behind one small interface:

``allocate(capacity)``
    preallocate per-slot storage for a buffer of ``capacity`` observation slots.
``write(start, episode)``
    store one episode's goal data at slots ``start .. start + T`` (``T + 1`` observation
    slots for ``T`` transitions; slot ``start + t + 1`` is what step ``t`` achieved).
``desired(idx)``
    the goals the transitions at slots ``idx`` were collected with.
``relabel(idx, ep_start, ep_end, strategy, rng)``
    goals achieved in the same episode at or after each transition (``future``), at its
    end (``final``) or anywhere in it (``episode``), plus a mask of the transitions for
    which such a goal exists.
``relabelable(idx, ep_start, ep_end, strategy)``
    which transitions have such a goal (all of them for state goals).
``random_goals(slots, rng)``
    goals achieved anywhere in the buffer (HER's ``random`` strategy), given random slots.
``reward(idx, goals)``
    the sparse reward of the transitions at ``idx`` under ``goals``, from what they
    achieved (vectorised).
``embed(goals, device)``
    the goals as a float tensor for the networks.

Two goal spaces are provided:

:class:`StateGoals`
    goals are vectors (``achieved_goal`` / ``desired_goal``); the reward is any
    vectorised ``reward_fn(achieved, desired) -> reward``, e.g. a gymnasium-robotics
    env's ``compute_reward`` with ``info=None``.
:class:`LabelGoals`
    goals are integer ids into a table: instructions (embedded by the frozen text encoder,
    looked up by id when a batch is made) or one-hot task ids. What each step achieved is
    a set of ids written at insertion (the captioner's labels); relabelled goals are drawn
    from labels achieved later in the same episode, and the reward is whether the goal is
    among the labels of the step's next observation, i.e. the captioner's ``satisfied``
    check on ``(s0, s_{t+1})``, evaluated once at insertion and stored as a bitset.

:class:`ImageGoals`
    the policy sees a camera frame as its goal; the frame is what the policy is shown,
    the privileged state behind it is what judges success. A relabelled goal is a slot
    index into the buffer's own image storage (the frame of a later step of the same
    episode), so frames are stored once; the reward is a :class:`StateGoals` reward on
    that slot's achieved state.

:class:`TaskGoals`
    one-hot task ids of a fixed task set, each task with its own reward function
    (multi-task RL). Whether an episode achieved its own task is stored per step; a goal
    achieved by one task's episode says nothing about another task's reward, so these
    goals are never relabelled (``can_relabel = False``: the buffer refuses ``k > 0``).

A goal space with an ``attach(obs_arrays)`` method is handed the buffer's observation
arrays after :meth:`allocate` (image goals read their frames there). One with
``can_relabel = False`` cannot be relabelled in hindsight.
"""

from __future__ import annotations

from lcrl.goals.base import (
    STRATEGIES as STRATEGIES,
    GoalSpace as GoalSpace,
    RewardFn as RewardFn,
    pick_step as pick_step,
)
from lcrl.goals.images import (
    ImageGoals as ImageGoals,
)
from lcrl.goals.labels import (
    LabelGoals as LabelGoals,
    label_ids as label_ids,
)
from lcrl.goals.state import (
    StateGoals as StateGoals,
)
from lcrl.goals.tasks import (
    TASK_RELABEL_ERROR as TASK_RELABEL_ERROR,
    TaskGoals as TaskGoals,
    TaskRewardFn as TaskRewardFn,
)

__all__ = [
    "STRATEGIES",
    "TASK_RELABEL_ERROR",
    "GoalSpace",
    "ImageGoals",
    "LabelGoals",
    "RewardFn",
    "StateGoals",
    "TaskGoals",
    "TaskRewardFn",
    "label_ids",
    "pick_step",
]

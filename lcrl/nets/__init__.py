"""Encoders and universal value function approximators (UVFA) for goal-conditioned RL.

A network sees an observation and a goal through *separate* encoders, then fuses them:

* the observation encoder concatenates one encoder per observation key: an MLP (or the
  identity) for vector keys, a CNN for uint8 image keys (``(H, W, C)``);
* the goal encoder is an MLP (or the identity) for vector goals, a learned projection of
  the frozen text embedding for language goals, a linear layer for one-hot task ids, or a
  CNN for image goals: :data:`GOAL_ENCODERS` names the encoder of each goal kind;
* fusion is concatenation followed by an MLP (default), or FiLM: the goal produces a
  per-unit scale and shift for every hidden layer of the MLP that reads the observation.

Parameters of each network are packed into one flat buffer (:func:`flatten_parameters`)
so that :class:`FlatAdam` updates them with a handful of vectorised operations.
"""

from __future__ import annotations

from lcrl.nets.encoders import (
    GOAL_ENCODERS as GOAL_ENCODERS,
    GoalEncoder as GoalEncoder,
    GoalEncoderFactory as GoalEncoderFactory,
    GoalEncoderSpec as GoalEncoderSpec,
    ObsEncoder as ObsEncoder,
    build_encoders as build_encoders,
    goal_encoder_spec as goal_encoder_spec,
    image_goal_encoder as image_goal_encoder,
    projected_goal_encoder as projected_goal_encoder,
    vector_goal_encoder as vector_goal_encoder,
)
from lcrl.nets.heads import (
    FusedMLP as FusedMLP,
    GoalConditionedEnsemble as GoalConditionedEnsemble,
    GoalConditionedNet as GoalConditionedNet,
    TaskHeads as TaskHeads,
    check_task_heads as check_task_heads,
)
from lcrl.nets.layers import (
    FUSIONS as FUSIONS,
    SLOT_MODES as SLOT_MODES,
    BatchedLinear as BatchedLinear,
    ConvEncoder as ConvEncoder,
    NetConfig as NetConfig,
    mlp as mlp,
    random_shift as random_shift,
    spatial_softmax as spatial_softmax,
)
from lcrl.nets.optim import (
    FlatAdam as FlatAdam,
    RunningNorm as RunningNorm,
    WhiteningNorm as WhiteningNorm,
    flatten_parameters as flatten_parameters,
    gaussian_log_prob_tanh as gaussian_log_prob_tanh,
    polyak as polyak,
)
from lcrl.nets.slots import (
    SlotAttention as SlotAttention,
    SlotAttributes as SlotAttributes,
    SlotSelect as SlotSelect,
    grounding_loss as grounding_loss,
)

__all__ = [
    "FUSIONS",
    "GOAL_ENCODERS",
    "SLOT_MODES",
    "BatchedLinear",
    "ConvEncoder",
    "FlatAdam",
    "FusedMLP",
    "GoalConditionedEnsemble",
    "GoalConditionedNet",
    "GoalEncoder",
    "GoalEncoderFactory",
    "GoalEncoderSpec",
    "NetConfig",
    "ObsEncoder",
    "RunningNorm",
    "SlotAttention",
    "SlotAttributes",
    "SlotSelect",
    "TaskHeads",
    "WhiteningNorm",
    "build_encoders",
    "check_task_heads",
    "flatten_parameters",
    "gaussian_log_prob_tanh",
    "goal_encoder_spec",
    "grounding_loss",
    "image_goal_encoder",
    "mlp",
    "polyak",
    "projected_goal_encoder",
    "random_shift",
    "spatial_softmax",
    "vector_goal_encoder",
]

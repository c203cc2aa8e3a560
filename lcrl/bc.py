"""Behavioural cloning: the names of :mod:`lcrl.algos.bc`, where it lives with the other
learners, kept importable from here."""

from lcrl.algos.bc import (
    ACTION_CLIP,
    BC,
    BC_LOSSES,
    LOG_STD_MAX,
    LOG_STD_MIN,
    BCConfig,
    tanh_gaussian_log_prob,
)

__all__ = [
    "ACTION_CLIP",
    "BC",
    "BC_LOSSES",
    "LOG_STD_MAX",
    "LOG_STD_MIN",
    "BCConfig",
    "tanh_gaussian_log_prob",
]

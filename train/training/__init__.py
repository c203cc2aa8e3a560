"""Trainers.

- ``trainer``: the interface every trainer shares, run folders, checkpoints, stopping.
- ``loop``: online RL with hindsight relabelling (``lcrl train``), with its parts
  ``collection`` (its own environments or Ray workers) and ``stages`` (sequential stages).
- ``episodes``: one training episode as collected; ``explore``: where episodes start.
- ``ray_collect``: rollout workers on Ray.
- ``bc``, ``offline``, ``distill``: behavioural cloning, offline RL, DAgger distillation.
- ``demos``: demonstration files (``lcrl demos``), with ``demo_episodes`` (episodes as
  the trainers read them), ``demo_recording`` and ``demo_relabelling``.
"""

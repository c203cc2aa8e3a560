"""Training configs.

- ``config``: the training config (:class:`TrainConfig`), validated where it is made,
  read from and written to dicts; ``sections``: its buffer, relabelling, collection,
  stages, exploration, fine-tuning and distillation sections.
- ``presets``: the named presets of ``lcrl train PRESET``.
- ``run_meta``: what a run's checkpoint says about itself (its config, problem, tables).
"""

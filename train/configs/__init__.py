"""Training configs.

- ``config``: typed dataclasses (one docstring per field) and the named presets.
- ``run_meta``: what a run's checkpoint says about itself (its config, problem, tables).
"""

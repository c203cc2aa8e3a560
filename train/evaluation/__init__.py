"""Evaluating policies and reporting on runs.

- ``evaluate``: agents and tasks built from a config, episodes run, results summarised.
- ``eval_suite``: ``lcrl eval`` (sets, families, slot values, chains, parallel envs),
  over ``eval_episodes`` (episodes in a vector env), ``instruction_files`` and
  ``statistics`` (Wilson intervals).
- ``report``: curves, summaries and figures of runs and evaluations.
- ``sequential``: the success matrix and forgetting of sequential stages.
"""

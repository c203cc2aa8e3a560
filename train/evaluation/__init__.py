"""Evaluating policies and reporting on runs.

- ``evaluate``: agents and tasks built from a config, episodes run, results summarised.
- ``eval_suite``: ``lcrl eval`` (sets, families, slot values, chains, parallel envs),
  over ``eval_episodes`` (episodes in a vector env) and ``instruction_files``
  (Wilson intervals come from :mod:`lcrl.statistics`).
- ``report``: a run's report and runs compared, over ``run_logs`` (reading a run),
  ``report_plots`` (figures) and ``evaluation_report`` (an evaluation's document).
- ``sequential``: the success matrix and forgetting of sequential stages.
"""

"""Environments as training tasks.

- ``simulators``: the simulator registry (``ENVS``) and the env config that picks one.
- ``tasks``: goal modalities (``GOALS``) and building an env for a config; the tasks
  themselves (what is stored, what the goal is, how episodes are labelled) in
  ``task_base`` (goal vectors and frames) and ``language_tasks`` (instructions).
- ``perception``: slots read from camera frames (``lcrl perception``, the env wrapper).
- ``text_reading``: the instruction readers (``--env.text-reader``, ``--env.canonical-reader``).
"""

"""Environments as training tasks.

- ``simulators``: the simulator registry (``ENVS``) and the env config that picks one.
- ``tasks``: goal modalities (``GOALS``): what is stored, what the goal is, how episodes
  are labelled; building an env for a config.
- ``perception``: slots read from camera frames (``lcrl perception``, the env wrapper).
- ``text_reading``: the instruction readers (``--env.text-reader``, ``--env.canonical-reader``).
"""

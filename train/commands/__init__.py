"""The ``lcrl`` commands.

- ``entry``: the console script (signals handled from its first instant).
- ``cli``: the command line (``lcrl train | eval | act | report | ...``).
- ``act``: ``lcrl act``, free-text instructions one at a time, videos, interactive.
- ``demo``: ``lcrl demo``, scenes, scripted and random episodes, captions.
- ``captions``: caption datasets acted by a trained policy.
- ``pipeline``: ``lcrl train robosuite-camera`` (and ``robosuite-privileged``), a policy built
  stage by stage; ``pipeline_settings`` holds its options, ``pipeline_steps`` runs one
  stage's commands, ``pipeline_parts`` keeps and takes up the stages before the student.
"""

"""What every run stands on.

- ``machine``: the machine, its cores and the torch threads a run takes.
- ``memory``: what a run's large arrays will take, checked before they are allocated.
- ``run_lock``: one process per run folder; output files checked before work.
"""

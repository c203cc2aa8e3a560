"""The benchmark scripts and their shared harness.

``benchmarks.common`` is the harness every script builds on: it starts ``lcrl`` runs
(:func:`~benchmarks.common.train_arms` over arms and seeds, one thread each, resumable;
:func:`~benchmarks.common.run_logged`), evaluates them on named seeds
(:func:`~benchmarks.common.evaluate`, :func:`~benchmarks.common.final_eval`), and writes a
result's JSON, Markdown and PNG with its ``headline``, ``command``, ``machine``, ``date``,
``git`` commit and ``tried`` (:func:`~benchmarks.common.save_json`,
:func:`~benchmarks.common.publish`). ``benchmarks.protocol`` holds the measuring protocol
(validation and test seeds, one policy, like for like). Run a script as a module from the
repository root: ``python -m benchmarks.NAME``."""

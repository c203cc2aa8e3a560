"""The benchmark scripts and their shared harness."""

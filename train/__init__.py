"""Command line and training entry points."""

"""Workflows: one module per job (load, check, run, return a result object); the CLI and the
Python API both call them. Workflows never print and never exit."""

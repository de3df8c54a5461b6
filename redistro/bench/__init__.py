"""Benchmarks: ``redistro bench cycle`` and ``redistro bench ipc``."""

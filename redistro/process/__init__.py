"""Manager and Worker runtime: Initialization, Routine, Cleanup, Idle.

Kept import-free: ``python -m redistro.process`` blocks signals before numpy loads.
"""

"""The only code that touches posix_ipc/sysv_ipc, mmap, signals, timers and scheduling.

Submodules are imported explicitly (``from redistro.ipc import signals``) so that a
process entry point can block its signals before numpy is imported.
"""

"""redistro: a multi-process robot controller in the REDIESTRO style.

Nothing is imported here: process entry points import this package before
they block their signals, so it must not start any thread.
"""

__version__ = "0.1.0"

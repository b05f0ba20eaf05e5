"""Stop signals held back where an interruption would do harm.

Ctrl-C (SIGINT), ``kill`` (SIGTERM) and a closed terminal (SIGHUP) make the command line raise
KeyboardInterrupt wherever the main thread is (``tools.console``). Two places must not be cut in
the middle: a set of renames that must all happen or none (``backend.data.files``), and numba
loading or compiling a kernel (a KeyboardInterrupt raised inside llvmlite's code leaves its objects
half made, and the process later dies of a segmentation fault). :func:`held` blocks the three
signals for such a block; one that arrives meanwhile is delivered, and handled, right after it.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["STOP_SIGNALS", "held"]

#: The signals that stop a command (those present on this platform)
STOP_SIGNALS = frozenset(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextmanager
def held() -> Iterator[None]:
    """Block :data:`STOP_SIGNALS` for the block (in the main thread, where Python handles signals;
    elsewhere, or without ``pthread_sigmask``, nothing changes)."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)

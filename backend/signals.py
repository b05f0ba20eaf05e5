"""Stop signals held back where an interruption would do harm.

Ctrl-C (SIGINT), ``kill`` (SIGTERM) and a closed terminal (SIGHUP) make the command line raise
KeyboardInterrupt wherever the main thread is (``tools.console``). Two places must not be cut in
the middle: a set of renames that must all happen or none (``backend.data.files``), and numba
loading or compiling a kernel (a KeyboardInterrupt raised inside llvmlite's code leaves its objects
half made, and the process later dies of a segmentation fault). :func:`held` blocks the three
signals for such a block; one that arrives meanwhile is delivered, and handled, right after it.

Blocking reaches the main thread only: a signal sent to the process is delivered to any thread
that does not block it (a timer, a pool's worker), and Python then runs its handler in the main
thread at once, inside the block. So a handler that stops the work asks :func:`deferred` first:
inside a held block it leaves the signal to :func:`held`, which raises it again on the way out.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["STOP_SIGNALS", "held", "deferred"]

#: The signals that stop a command (those present on this platform)
STOP_SIGNALS = frozenset(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


_depth = 0  # held blocks the main thread is in
_pending: list[int] = []  # stop signals a handler left to held (deferred), in order


def deferred(signum: int) -> bool:
    """For a stop handler (main thread): whether ``signum`` arrived inside a held block, in which case
    it is kept and raised again when the outermost block ends; the handler then returns at once."""
    if _depth <= 0:
        return False
    _pending.append(signum)
    return True


@contextmanager
def held() -> Iterator[None]:
    """Block :data:`STOP_SIGNALS` for the block (in the main thread, where Python handles signals;
    elsewhere, or without ``pthread_sigmask``, nothing changes) and defer those another thread
    received (:func:`deferred`) until it ends."""
    global _depth
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS) if hasattr(signal, "pthread_sigmask") else None
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)  # a blocked one is delivered here
        if _depth == 0 and _pending:
            signum = _pending[0]
            _pending.clear()
            signal.raise_signal(signum)  # its handler runs now, outside the block

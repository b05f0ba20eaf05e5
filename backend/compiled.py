"""Compiled kernels (numba): the decorator every kernel uses, and their warm-up.

Kernels are compiled on first use and cached beside their source (``cache=True``): the first run
after an install compiles for up to a minute; later processes load the cache in ~0.5 s. numba
keys a kernel's cache to its own file only, and a kernel that calls one of another module holds
that one's machine code too: after a change of that module alone (a ``git pull`` into an
editable install) it would run the old code. So the caches under ``backend/`` are dropped
whenever a source there changed since they were written (:func:`drop_stale_caches`). A module that
defines kernels registers a function calling each of them once on tiny arguments of the types
the filter passes, every argument passed as the filter passes it (an omitted default is another
signature, compiled again) (:func:`warms_up`); :func:`warm_up` runs every registered one that
has not run yet, so no step of a run pays for compiling, and reports the seconds apart from the
run's timing. Kernels only a real IMU's run calls are registered as ``only="inertial"`` and
warmed up only for such a run: a velocity run does not compile them.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Callable

#: LLVM's optimization level for the kernels (numba's NUMBA_OPT, read when numba is imported): 2
#: unless the environment sets it. Against numba's default 3, measured on ece276a_0027: the first
#: run after an install 30.7 s against 34.9 s, peak memory 497 against 531 MB; the filter the same
#: (0.96 s), the two-view fits of the decisions 0.45 against 0.43 s. It holds for numba code the
#: process compiles after importing vislam, too; set NUMBA_OPT to choose.
os.environ.setdefault("NUMBA_OPT", "2")

from numba import njit  # noqa: E402 (after NUMBA_OPT)

from . import signals

__all__ = ["jit", "warms_up", "warm_up", "warm_up_seconds", "drop_stale_caches", "NOTICE_AFTER"]

#: The file under ``backend/__pycache__`` holding the sources' fingerprint the caches were made from.
FINGERPRINT = "kernels.fingerprint"


def _walk(root: Path):
    for entry in os.scandir(root):
        if entry.is_dir(follow_symlinks=False):
            yield from _walk(Path(entry.path))
        else:
            yield entry


def drop_stale_caches(root: Path = Path(__file__).resolve().parent) -> int:
    """Delete numba's cache files (``*.nbi``, ``*.nbc``) under ``root`` when a ``.py`` file there
    changed (size or time stamp) since the last call, and note the sources' new fingerprint; returns
    the files deleted. Where ``root`` is not writable (an installed package) numba caches elsewhere
    and nothing is done."""
    entries = list(_walk(root))
    sources = sorted((e.path, e.stat().st_size, e.stat().st_mtime_ns) for e in entries
                     if e.name.endswith(".py") and "__pycache__" not in e.path)
    fingerprint = repr(sources)
    stamp = root / "__pycache__" / FINGERPRINT
    try:
        if stamp.read_text() == fingerprint:
            return 0
    except OSError:
        pass
    dropped = 0
    try:
        for e in entries:
            if e.name.endswith((".nbi", ".nbc")):
                os.unlink(e.path)
                dropped += 1
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}")
        tmp.write_text(fingerprint)
        os.replace(tmp, stamp)
    except OSError:  # read-only install, or another process got there first
        pass
    return dropped


drop_stale_caches()

#: The options of every kernel: cached, GIL released, numpy's error model (1/0 -> inf, no exception).
jit = njit(cache=True, nogil=True, error_model="numpy")

#: Seconds after which :func:`warm_up` calls its ``notice`` (it is compiling, not loading).
NOTICE_AFTER = 2.0

_registered: list[Callable[[], None]] = []
_only: dict[Callable[[], None], str] = {}  # registered warm-ups that serve one kind of run
_done: set[Callable[[], None]] = set()
_seconds = 0.0
_lock = threading.Lock()


def warms_up(function: Callable[[], None] | None = None, *, only: str | None = None):
    """Decorator: register ``function`` (no arguments; calls a module's kernels once) for
    :func:`warm_up`; ``@warms_up(only="inertial")``: for a real IMU's runs only."""

    def register(f: Callable[[], None]) -> Callable[[], None]:
        _registered.append(f)
        if only is not None:
            _only[f] = only
        return f

    return register if function is None else register(function)


def warm_up(notice: Callable[[], None] | None = None, inertial: bool = False) -> float:
    """Compile or load every registered kernel not warmed up yet in this process (those registered
    ``only="inertial"`` with ``inertial`` only); returns the seconds spent (0 when there was nothing
    left). ``notice()`` is called from a timer thread when it takes longer than :data:`NOTICE_AFTER`
    seconds (compiling after an install or an update)."""
    global _seconds
    with _lock:
        todo = [f for f in _registered if f not in _done and (inertial or _only.get(f) != "inertial")]
        if not todo:
            return 0.0
        timer = threading.Timer(NOTICE_AFTER, notice) if notice is not None else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        t0 = time.perf_counter()
        try:
            for function in todo:
                with signals.held():  # numba cut in the middle crashes later; a stop waits for this module
                    function()
                _done.add(function)
        finally:
            if timer is not None:
                timer.cancel()
        spent = time.perf_counter() - t0
        _seconds += spent
        return spent


def warm_up_seconds() -> float:
    """Seconds this process spent in :func:`warm_up` so far: the start-up cost a run reports apart."""
    return _seconds

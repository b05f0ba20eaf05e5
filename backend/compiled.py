"""Compiled kernels (numba): the decorator every kernel uses, and their warm-up.

Kernels are compiled on first use and cached beside their source (``cache=True``): the first run
after an install compiles for about 25 s of CPU (a velocity run's kernels in one process, LLVM at
-O2), shared by two processes (below); later processes load the cache in ~0.3 s. numba
keys a kernel's cache to its own file only, and a kernel that calls one of another module holds
that one's machine code too: after a change of that module alone (a ``git pull`` into an
editable install) it would run the old code. So the caches under ``backend/`` are dropped
whenever a source there changed since they were written (:func:`drop_stale_caches`). A module that
defines kernels registers a function calling each of them that a run calls from Python once on
tiny arguments of the types the filter passes, every argument passed as the filter passes it (an
omitted default is another signature, compiled again) (:func:`warms_up`); a kernel only other
kernels call is compiled into their caches and is not loaded on its own (a velocity run's 15
such kernels took about 40 ms of its start-up to load); :func:`warm_up` runs every registered one that
has not run yet, so no step of a run pays for compiling, and reports the seconds apart from the
run's timing. Kernels only a real IMU's run calls are registered as ``only="inertial"`` and
warmed up only for such a run: a velocity run does not compile them.

When nothing is cached yet (the first run after an install or a change), a helper process
compiles modules beside this one, both going down one list of the modules by source size, the
helper from the largest (the two-view fits, ~8 s alone) and this process from the second (the
invariant model, then the update: the invariant model's kernels call the update's and the SE(3)
functions, so those are compiled in one process, not in both), each then claiming the next module
not yet claimed (a file created exclusively; no lock to leak); the caches the helper writes are
then loaded here. Against the helper from the largest down and this process from the smallest up
(``/usr/bin/time``, every cache removed, a 2-core machine shared with other work): EuRoC's slice (a
window run) peaked at 352 MB against 403 and took 35 s of CPU against 38; ece276a_0027 peaked at
341 MB against 307 (this process then compiles the estimator's larger modules besides holding the
data) and took 33-37 s of CPU against 32-35, 18.4 s wall against 20.8 when both cores were free.
numba compiles in one thread, so on 2 idle cores the helper nearly halves the wait. A stop
(Ctrl-C, SIGTERM) ends the helper with the run.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import tempfile
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


def _drop_llvm_lock_events() -> bool:
    """Unregister numba's callbacks on llvmlite's lock (``numba.core.base._initialize_llvm_lock_event``):
    every LLVM call (thousands while a process loads its cached kernels: each kernel's bitcode
    parsed, its symbols listed one call each) broadcast two ``numba:llvm_lock`` events through
    Python, which only time numba's compiles for its metadata (``Dispatcher.get_metadata``). A
    velocity run's kernel loading took 0.27 s median against 0.35 s with them (six alternated
    processes on a loaded 2-core machine). Returns whether they were found (nothing is changed
    where numba or llvmlite no longer have them)."""
    try:
        from llvmlite.binding import ffi
        import numba.core.base  # noqa: F401 (registers the callbacks when imported)

        callbacks = list(ffi.lib._lock._cblist)
    except (ImportError, AttributeError):
        return False
    found = False
    for acquire, release in callbacks:
        if (getattr(acquire, "__module__", None) == "numba.core.base"
                and "_initialize_llvm_lock_event" in getattr(acquire, "__qualname__", "")):
            ffi.unregister_lock_callback(acquire, release)
            found = True
    return found


_drop_llvm_lock_events()

__all__ = ["jit", "warms_up", "warm_up", "warm_up_seconds", "drop_stale_caches", "NOTICE_AFTER"]

#: The file under ``backend/__pycache__`` holding the sources' fingerprint the caches were made from.
FINGERPRINT = "kernels.fingerprint"
#: ... and the file saying a whole warm-up has written its caches since (a velocity run's kernels).
WARMED = "kernels.warmed"
#: The directory of both, beside the kernels' sources.
CACHE_NOTES = Path(__file__).resolve().parent / "__pycache__"


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
        (stamp.parent / WARMED).unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}")
        tmp.write_text(fingerprint)
        os.replace(tmp, stamp)
    except OSError:  # read-only install, or another process got there first
        pass
    return dropped


drop_stale_caches()


def _compiling_everything() -> bool:
    """Whether a warm-up will compile rather than load: numba caches beside the sources (their
    ``__pycache__`` is writable) and no whole warm-up has written its caches since they changed.
    (Where the package is read-only numba caches elsewhere, and this says no.)"""
    return not (CACHE_NOTES / WARMED).exists() and os.access(CACHE_NOTES if CACHE_NOTES.exists()
                                                            else CACHE_NOTES.parent, os.W_OK)


def warmed_before() -> bool:
    """Whether a whole warm-up wrote the kernels' caches since the sources last changed (or numba
    caches elsewhere): a process then only loads them. A command that starts a pool of workers
    warms up first where this is False, so the workers load what it compiled (with its helper)
    rather than each compiling everything."""
    return not _compiling_everything()


def _note_warmed() -> None:
    """Say that a whole warm-up (every kernel but a real IMU's run's) has written its caches."""
    if all(f in _done for f in _registered if _serves(f, False)) and not (CACHE_NOTES / WARMED).exists():
        try:
            (CACHE_NOTES / WARMED).touch()
        except OSError:
            pass

#: The options of every kernel: cached, GIL released, numpy's error model (1/0 -> inf, no exception).
jit = njit(cache=True, nogil=True, error_model="numpy")

#: Seconds after which :func:`warm_up` calls its ``notice`` (it is compiling, not loading).
NOTICE_AFTER = 2.0

_registered: list[Callable[[], None]] = []
_only: dict[Callable[[], None], str] = {}  # registered warm-ups that serve one kind of run
_done: set[Callable[[], None]] = set()
_seconds = 0.0
_lock = threading.Lock()


#: The kinds of run a warm-up can be registered for (``warms_up(only=...)``), and which runs each
#: serves: a velocity run and a real IMU's run with landmarks in the state use the landmark filter's
#: kernels, a window run (a real IMU's with ``estimator.window``) none of them
ONLY = {
    "inertial": "a real IMU's runs",
    "window": "a real IMU's runs with a sliding window of clones",
    "landmarks": "runs with landmarks in the state (every run but a window's)",
    "velocity": "runs with body velocities",
}


def warms_up(function: Callable[[], None] | None = None, *, only: str | None = None):
    """Decorator: register ``function`` (no arguments; calls a module's kernels once) for
    :func:`warm_up`; ``only`` (a key of :data:`ONLY`): for that kind of run only, else for every run."""
    if only is not None and only not in ONLY:
        raise ValueError(f"warms_up: only must be one of {sorted(ONLY)}, got {only!r}")

    def register(f: Callable[[], None]) -> Callable[[], None]:
        _registered.append(f)
        if only is not None:
            _only[f] = only
        return f

    return register if function is None else register(function)


def _serves(function: Callable[[], None], inertial: bool, window: bool = False) -> bool:
    """Whether the registered warm-up ``function`` serves a run (a real IMU's with ``inertial``, with a
    sliding window of clones with ``window`` too; :data:`ONLY`)."""
    only = _only.get(function)
    return (only is None or (only == "inertial" and inertial) or (only == "window" and inertial and window)
            or (only == "landmarks" and not (inertial and window)) or (only == "velocity" and not inertial))


def warm_up(notice: Callable[[], None] | None = None, inertial: bool = False, window: bool = False) -> float:
    """Compile or load every registered kernel not warmed up yet in this process that serves the run
    (:func:`_serves`: a run compiles what it uses); returns the seconds spent (0 when there was
    nothing left).
    ``notice()`` is called from a timer thread when it takes longer than :data:`NOTICE_AFTER`
    seconds (compiling after an install or an update)."""
    global _seconds
    with _lock:
        todo = [f for f in _registered if f not in _done and _serves(f, inertial, window)]
        if not todo:
            return 0.0
        timer = threading.Timer(NOTICE_AFTER, notice) if notice is not None else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        t0 = time.perf_counter()
        try:
            if (_cores() > 1 and len({f.__module__ for f in todo}) > 1 and _compiling_everything()
                    and not multiprocessing.current_process().daemon):  # a pool's worker may not start one
                _compile_with_a_helper(todo, inertial, window)
            for function in todo:
                if function not in _done:
                    with signals.held():  # numba cut in the middle crashes later; a stop waits for this module
                        function()
                    _done.add(function)
            _note_warmed()
        finally:
            if timer is not None:
                timer.cancel()
        spent = time.perf_counter() - t0
        _seconds += spent
        return spent


def warm_up_seconds() -> float:
    """Seconds this process spent in :func:`warm_up` so far: the start-up cost a run reports apart."""
    return _seconds


def _cores() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _by_size(functions: list[Callable[[], None]]) -> list[str]:
    """The modules of ``functions``, the largest source first (the most to compile, roughly)."""
    modules = {f.__module__ for f in functions}
    return sorted(modules, key=lambda m: -os.path.getsize(importlib.import_module(m).__file__))


def _claim(directory: str, name: str) -> bool:
    """Whether this process takes module ``name``: the first to create its file in ``directory``."""
    try:
        os.close(os.open(os.path.join(directory, name), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


def _compile_in_helper(modules: list[str], claims: str, inertial: bool, window: bool = False) -> None:
    """The helper process: warm up each of ``modules`` it claims in ``claims`` (:func:`_claim`); numba
    caches what it compiles for the process that started it."""
    for name in modules:
        if _claim(claims, name):
            importlib.import_module(name)  # registers its warm-ups here
            for f in _registered:
                if f.__module__ == name and _serves(f, inertial, window):
                    f()


def _helper_main(argv: list[str]) -> None:
    """The helper's entry: ``argv`` = [claims, inertial 0/1, window 0/1, module ...]. Ctrl-C is the
    run's to handle (it ends the helper with SIGTERM), so the helper ignores SIGINT."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    claims, inertial, window, *modules = argv
    _compile_in_helper(modules, claims, inertial == "1", window == "1")


def _compile_with_a_helper(todo: list[Callable[[], None]], inertial: bool, window: bool = False) -> None:
    """Compile the modules of ``todo`` here and in one helper process, each claiming the next module of
    one list by size (the helper from its first, this process from its second); the helper's modules
    are left for the caller, whose warm-ups then load its caches. The helper is a new interpreter
    that imports this module alone (``sys.executable -c``, the caller's ``sys.path``), not a
    multiprocessing child: a spawned child would run the caller's main script again, which a script
    without an ``if __name__ == "__main__"`` guard does from its top (its data loaded twice, and the
    child's own warm-up refused)."""
    modules = _by_size(todo)
    claims = tempfile.mkdtemp(prefix="vislam-compile-")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    code = f"import sys; from {__name__} import _helper_main; _helper_main(sys.argv[1:])"
    helper = subprocess.Popen([sys.executable, "-c", code, claims, str(int(inertial)), str(int(window)), *modules],
                              env=env, stdin=subprocess.DEVNULL)
    try:
        for name in modules[1:] + modules[:1]:  # the helper starts at the first
            if _claim(claims, name):
                for function in todo:
                    if function.__module__ == name:
                        with signals.held():
                            function()
                        _done.add(function)
        helper.wait()
    finally:
        if helper.poll() is None:  # a stop: the helper goes with the run
            helper.terminate()
            helper.wait()
        shutil.rmtree(claims, ignore_errors=True)

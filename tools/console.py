"""What the command line says on the terminal: one-line messages and progress bars, on stderr;
and Ctrl-C, which must not be lost.

Python raises KeyboardInterrupt wherever the main thread is when SIGINT arrives; inside a
finalizer (``__del__``, as llvmlite's objects run while numba compiles) it is printed as "ignored"
and the work goes on. :func:`interrupt_handler` therefore also records the signal (and keeps that
"ignored" traceback off the terminal), and every progress callback (:func:`progress_bar`, once per
step or frame) raises KeyboardInterrupt again once it was recorded.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Callable, Iterator, Optional

_interrupted = threading.Event()


def _on_sigint(signum, frame) -> None:
    _interrupted.set()
    raise KeyboardInterrupt


@contextmanager
def interrupt_handler(after=None) -> Iterator[Callable[[], bool]]:
    """Record Ctrl-C while the block runs (in the main thread; elsewhere nothing changes); yields a
    function telling whether it was pressed. ``after``: the SIGINT handler to install at the end
    (default: the one before)."""
    _interrupted.clear()
    if threading.current_thread() is not threading.main_thread():
        yield _interrupted.is_set
        return
    previous = signal.signal(signal.SIGINT, _on_sigint)
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_interrupt(previous_hook)
    try:
        yield _interrupted.is_set
    finally:
        signal.signal(signal.SIGINT, previous if after is None else after)
        sys.unraisablehook = previous_hook


def _quiet_interrupt(hook):
    """An unraisable-exception hook that keeps a swallowed KeyboardInterrupt quiet (it is recorded and
    raised again at the next progress callback) and passes everything else to ``hook``."""
    def quiet(unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            hook(unraisable)
    return quiet


def check_interrupted() -> None:
    """KeyboardInterrupt if Ctrl-C was pressed, even when the first one was swallowed."""
    if _interrupted.is_set():
        raise KeyboardInterrupt


def sayer(quiet: bool) -> Callable[[str], None]:
    """A function printing one message to stderr, or doing nothing when ``quiet``."""
    if quiet:
        return lambda message: None
    return lambda message: print(message, file=sys.stderr, flush=True)


@contextmanager
def progress_bar(total: Optional[int], desc: str, unit: str, quiet: bool) -> Iterator[Optional[Callable[[int], None]]]:
    """A callback advancing a tqdm bar by one per call (no bar when ``quiet``), closed at the end;
    each call raises KeyboardInterrupt if Ctrl-C was pressed (:func:`check_interrupted`)."""
    if quiet:
        yield lambda *_: check_interrupted()
        return
    from tqdm import tqdm

    bar = tqdm(total=total, unit=unit, file=sys.stderr, desc=desc)

    def advance(*_) -> None:
        check_interrupted()
        bar.update(1)

    try:
        yield advance
    finally:
        bar.close()


def add_verbosity_options(p) -> None:
    """--verbose, --quiet and --no-progress: a one-screen start by default (input, decisions, noise,
    the options that differ from the defaults), the full configuration with --verbose, nothing
    but errors with --quiet; the progress bar has its own switch."""
    p.add_argument("--verbose", action="store_true", help="also print the full configuration at the start")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors (no progress bar, no summary)")
    p.add_argument("--no-progress", dest="no_progress", action="store_true", help="no progress bar")


def progress_off(args) -> bool:
    """True when the progress bar is off (--quiet or --no-progress)."""
    return bool(getattr(args, "quiet", False) or getattr(args, "no_progress", False))


def configuration_text(verbose: bool, *tables) -> str:
    """The configuration for the start of a command: every option (``verbose``), else one line with
    the options that differ from their defaults (``OptionSet`` / ``OptionTable`` objects)."""
    if verbose:
        return "configuration:\n" + "\n".join(t.describe() for t in tables)
    changed = []
    for t in tables:
        parts = t.tables().values() if hasattr(t, "tables") else (t,)
        for table in parts:
            defaults = type(table)().as_dict()
            changed += [f"{table.TABLE}.{k}={v!r}" for k, v in table.as_dict().items() if defaults.get(k) != v]
    if not changed:
        return "configuration: the defaults (every option: --verbose, or config.toml of a run)"
    return f"configuration: the defaults but {', '.join(changed)} (every option: --verbose, or config.toml of a run)"


"""What the command line says on the terminal: one-line messages and progress bars, on stderr;
and interruptions (Ctrl-C, ``kill``, a closed terminal), which must not be lost.

SIGINT, SIGTERM and SIGHUP (:data:`STOP_SIGNALS`) are handled alike: the handler records the
signal and raises KeyboardInterrupt wherever the main thread is, so every cleanup written for
Ctrl-C (staging directories, temporary files, pool workers) runs for each of them, and the command
exits with 128 + the signal's number (130, 143, 129: :func:`interrupted_exit_code`). Inside a
finalizer (``__del__``, as llvmlite's objects run while numba compiles) the KeyboardInterrupt is
printed as "ignored" and the work goes on; :func:`interrupt_handler` therefore keeps that
"ignored" traceback off the terminal, and every progress callback (:func:`progress_bar`, once per
step or frame) raises KeyboardInterrupt again once a signal was recorded.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Callable, Iterator, Optional

from ..backend import signals

#: The signals that stop a command cleanly, like Ctrl-C (those present on this platform)
STOP_SIGNALS = tuple(sorted(signals.STOP_SIGNALS))

_interrupted = threading.Event()
_received: list[int] = []  # the stop signals received while the handler was in place, in order


def _on_signal(signum, frame) -> None:
    if signals.deferred(signum):  # inside work a stop must not cut (numba): raised again after it
        return
    _received.append(signum)
    _interrupted.set()
    raise KeyboardInterrupt


def interrupted_exit_code() -> int:
    """128 + the number of the first stop signal received (130 for Ctrl-C, also when none was)."""
    return 128 + (_received[0] if _received else int(signal.SIGINT))


def interrupted_text() -> str:
    """'interrupted', naming the signal when it was not Ctrl-C: 'interrupted (SIGTERM)'."""
    if not _received or _received[0] == signal.SIGINT:
        return "interrupted"
    return f"interrupted ({signal.Signals(_received[0]).name})"


@contextmanager
def interrupt_handler(after=None) -> Iterator[Callable[[], bool]]:
    """Record the stop signals (:data:`STOP_SIGNALS`) while the block runs (in the main thread;
    elsewhere nothing changes); yields a function telling whether one arrived. ``after``: the
    handler to install for each at the end (default: the one before)."""
    _interrupted.clear()
    _received.clear()
    if threading.current_thread() is not threading.main_thread():
        yield _interrupted.is_set
        return
    previous = {signum: signal.signal(signum, _on_signal) for signum in STOP_SIGNALS}
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_interrupt(previous_hook)
    try:
        yield _interrupted.is_set
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler if after is None else after)
        sys.unraisablehook = previous_hook


def _quiet_interrupt(hook):
    """An unraisable-exception hook that keeps a swallowed KeyboardInterrupt quiet (it is recorded and
    raised again at the next progress callback), and after a stop signal also what finalizers of the
    interrupted work report (a ``ZipFile`` closed half-way while ``map.npz`` was written: its file is
    removed anyway); everything else goes to ``hook``."""
    def quiet(unraisable) -> None:
        if not (isinstance(unraisable.exc_value, KeyboardInterrupt) or _interrupted.is_set()):
            hook(unraisable)
    return quiet


def check_interrupted() -> None:
    """KeyboardInterrupt if a stop signal arrived, even when the first one was swallowed."""
    if _interrupted.is_set():
        raise KeyboardInterrupt


_bars: list = []  # the progress bar on screen, if any


def say(message: str) -> None:
    """One message on stderr, above the progress bar when one is on screen (never on its line)."""
    if _bars:
        _bars[-1].write(message, file=sys.stderr)
    else:
        print(message, file=sys.stderr, flush=True)


def sayer(quiet: bool) -> Callable[[str], None]:
    """A function printing one message to stderr (:func:`say`), or doing nothing when ``quiet``."""
    if quiet:
        return lambda message: None
    return say


@contextmanager
def progress_bar(total: Optional[int], desc: str, unit: str, quiet: bool) -> Iterator[Optional[Callable[[int], None]]]:
    """A callback advancing a tqdm bar by one per call (no bar when ``quiet``), closed at the end;
    each call raises KeyboardInterrupt if a stop signal arrived (:func:`check_interrupted`).

    The bar appears at the first call, once the work it counts has begun: the lines printed
    before (the input, the decisions taken from the data) stay on lines of their own, and its rate
    and time left are those of the work, not of the start-up."""
    if quiet:
        yield lambda *_: check_interrupted()
        return
    from tqdm import tqdm

    bar = None

    def advance(*_) -> None:
        nonlocal bar
        check_interrupted()
        if bar is None:
            bar = tqdm(total=total, unit=unit, file=sys.stderr, desc=desc)
            _bars.append(bar)
        bar.update(1)

    try:
        yield advance
    finally:
        if bar is not None:
            bar.close()
            _bars.remove(bar)


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


"""The command's clock: the seconds a user waits. When the command is the process (the ``vislam``
console script, ``python -m vislam.tools.cli``), they count from the operating system's start of
the process, start-up and imports included; when a program calls ``vislam.tools.cli.main`` (tests,
scripts), from that call.

The process's start comes, on Linux, from ``/proc/self/stat`` (field 22, clock ticks after boot)
against ``/proc/uptime``; elsewhere from ``psutil`` when installed; else from the first import of
this module (the interpreter's own start-up then goes uncounted: :func:`startup_seconds` is None).
"""

from __future__ import annotations

import os
import time

__all__ = ["count_from_process_start", "mark_command_start", "process_seconds", "startup_seconds"]

_IMPORTED = time.monotonic()
_from_process = False
_command_start: float | None = None  # time.monotonic() when the command began
_offset: float | None = None  # the process's age at _IMPORTED (None: unknown)


def _process_age() -> float | None:
    """Seconds since this process started (None when the system does not say)."""
    try:
        with open("/proc/self/stat", "rb") as fh:
            stat = fh.read().decode()
        with open("/proc/uptime", "rb") as fh:
            uptime = float(fh.read().split()[0])
        fields = stat[stat.rindex(")") + 2:].split()  # after the command name, which may hold spaces
        return max(uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"), 0.0)  # field 22 of the line
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    try:
        import psutil
    except ImportError:
        return None
    return max(time.time() - psutil.Process().create_time(), 0.0)


def count_from_process_start() -> None:
    """The command is the process: count from the process's start (the console script calls this)."""
    global _from_process, _offset
    _from_process = True
    age = _process_age()
    _offset = None if age is None else age - (time.monotonic() - _IMPORTED)


def mark_command_start() -> None:
    """Record that the command itself begins now (imports and argument parsing done)."""
    global _command_start
    _command_start = time.monotonic()


def process_seconds() -> float:
    """Wall seconds the user has waited so far: since the process started (a command that is the
    process), else since :func:`mark_command_start` (or this module's import when not marked)."""
    now = time.monotonic()
    if _from_process:
        return (_offset or 0.0) + now - _IMPORTED
    return now - (_command_start if _command_start is not None else _IMPORTED)


def startup_seconds() -> float | None:
    """Seconds from the process's start to the command's (None when that is not counted)."""
    if not _from_process or _offset is None or _command_start is None:
        return None
    return _offset + _command_start - _IMPORTED

"""The ``vislam`` command line: one parser, one module per command (``tools.commands``).

Every user error is one line on stderr and exit code 2; Ctrl-C exits 130, SIGTERM 143 and SIGHUP
129 (``tools.console``), and none of them leaves a half file, a staging directory or a worker.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys

from .. import __version__
from ..backend.errors import VislamError
from . import clock, console
from .commands import COMMANDS

EXIT_USAGE = 2
#: The arguments of any command that name what it reads: no output may land on them
#: (``backend.data.files.inputs_of_the_run``); readers add what they find themselves (calibration files).
INPUT_ARGUMENTS = ("data", "inputs", "images", "estimates", "ground_truth", "imu", "imu_T_cam", "gt", "covariance",
                   "config", "calib", "imu_calib")
EXIT_INTERRUPTED = 130  # after Ctrl-C; 128 + the signal's number after SIGTERM or SIGHUP
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, as a shell reports a command whose reader left


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vislam", description="Stereo visual-inertial EKF SLAM on SE(3).")
    parser.add_argument("--version", action="version", version=f"vislam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit code (0, 2 for a refusal, 128 + the signal after an interruption)."""
    return _main(argv)


def _main(argv: list[str] | None, sigint_after=None) -> int:
    """:func:`main`; ``sigint_after``: the handler to leave in place for the stop signals (default: the
    ones before)."""
    args = build_parser().parse_args(argv)
    clock.mark_command_start()
    with console.interrupt_handler(sigint_after) as interrupted:
        rc = _dispatch(args)
    if interrupted() and rc != console.interrupted_exit_code():  # swallowed where Python ignores exceptions
        print(f"vislam: {console.interrupted_text()} (after the work was done: its outputs are complete)",
              file=sys.stderr)
        return console.interrupted_exit_code()
    return rc


def _dispatch(args: argparse.Namespace) -> int:
    """The command, with every error as one line and its exit code."""
    from ..backend.data.files import inputs_of_the_run

    try:
        with inputs_of_the_run(_inputs(args)):
            return args.func(args)
    except VislamError as exc:
        print(f"vislam: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"vislam: {console.interrupted_text()}", file=sys.stderr)
        return console.interrupted_exit_code()
    except BrokenPipeError:  # the reader of stdout left (`vislam eval ... | head -1`): nothing more to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return EXIT_BROKEN_PIPE
    except OSError as exc:  # the system refused a read or write the checks could not foresee (a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"vislam: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:
        if not _interrupted(exc):
            raise
        print(f"vislam: {console.interrupted_text()}", file=sys.stderr)
        return console.interrupted_exit_code()


def _inputs(args: argparse.Namespace) -> list[str]:
    """The paths among the command's :data:`INPUT_ARGUMENTS`."""
    paths = []
    for name in INPUT_ARGUMENTS:
        value = getattr(args, name, None)
        paths += [str(v) for v in value] if isinstance(value, list) else [str(value)] if value else []
    return paths


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` wraps a Ctrl-C: compiled code (numba) re-raises KeyboardInterrupt as a
    SystemError, and an import it interrupts (open3d, matplotlib) as an ImportError."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def entry() -> None:  # pragma: no cover - the console script; tests call main()
    """``vislam``: :func:`main`, then leave at once, its two streams flushed: every output is in place
    (or cleaned up after an interruption) and every helper process and thread has ended, so the
    interpreter's teardown would only free memory (0.25 s after a run, numba's and LLVM's objects;
    and the teardown of native libraries would change the exit code after an interruption: open3d
    reports "memory leaks" and exits 1 when an import or a write of it was interrupted). A Ctrl-C
    once the work is done changes nothing."""
    clock.count_from_process_start()  # the user waits from the process's start: the figures say so
    rc = _main(None, sigint_after=signal.SIG_IGN)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # the reader of a pipe left: as a shell reports it
            rc = rc or EXIT_BROKEN_PIPE
    _stop_resource_tracker()
    os._exit(rc)


def _stop_resource_tracker() -> None:
    """Stop and reap multiprocessing's resource tracker where the command's helper processes started
    one: it ends when its pipe closes, which leaving by ``os._exit`` would leave to after the command,
    an orphan outliving it for a moment (its own ``_stop``, what the interpreter's exit would call)."""
    tracker = sys.modules.get("multiprocessing.resource_tracker")
    stop = getattr(getattr(tracker, "_resource_tracker", None), "_stop", None)
    if stop is not None:
        try:
            stop()
        except Exception:  # noqa: BLE001 - a tracker already gone, or an interpreter that differs: nothing to stop
            pass


if __name__ == "__main__":  # pragma: no cover
    entry()

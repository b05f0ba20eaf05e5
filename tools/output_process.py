"""A helper process for the outputs whose libraries cost most to start: the PNG figures (matplotlib)
and the PLY point clouds (open3d).

``vislam run`` starts it with the command. It imports both while the run computes; a thread could
not do that without slowing the run, whose Python holds the interpreter lock. Then it writes the
files it is sent (each atomically, as in-process), while the run writes the rest. The run waits
for its replies before the outputs are moved into place. Where it cannot start, dies or fails, the
run writes those files itself: the helper changes how long the outputs take, never what they are.
A stop (Ctrl-C, SIGTERM) ends it with the run; it ignores Ctrl-C itself (the run handles it), and
a run killed outright closes its pipe, which ends it too.
"""

from __future__ import annotations

import multiprocessing
import signal
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Optional

__all__ = ["OutputProcess", "output_process"]

#: Seconds to wait for the helper to end once it was told to.
JOIN_SECONDS = 5.0


def _serve(conn) -> None:
    """The helper: import the libraries, then call each function it is sent (a module-level function,
    sent by its name) until the run's end of the pipe closes (or the run terminates it)."""
    for name in ("SIGINT", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    from . import outputs, plots  # noqa: F401 (the modules of the functions it is sent, imported now; not the
    # filter's: numba and scipy would cost it 0.6 s of CPU beside the run)

    outputs.import_open3d()
    import matplotlib.figure  # noqa: F401 (imported now, while the run computes)

    while True:
        try:
            function, args, kwargs = conn.recv()
        except EOFError:
            return
        try:
            value = function(*args, **kwargs)
            conn.send((True, value if isinstance(value, bool) else None))  # an answer (write_map_ply's), no figure
        except Exception:  # the run writes it itself, and says why if that fails too
            conn.send((False, None))


class OutputProcess:
    """The helper process (module docstring): :meth:`submit` jobs, then :meth:`results` waits for them."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(child,), name="vislam-outputs", daemon=True)
        self._process.start()
        child.close()
        self._jobs: list[tuple[Callable[..., Any], tuple, dict]] = []

    def submit(self, function: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Send the helper one output to write: ``function(*args, **kwargs)``, a module-level function."""
        self._jobs.append((function, args, kwargs))
        try:
            self._conn.send((function, args, kwargs))
        except (OSError, ValueError):  # the helper is gone: results() does the job here
            pass

    def results(self) -> list[Any]:
        """Wait for every job sent; each one's value in order (a bool, or None: figures stay in the
        helper). A job the helper did not do (it failed, or is gone) is done here, and its value is
        this process's call's."""
        out = []
        for function, args, kwargs in self._jobs:
            try:
                done, value = self._conn.recv()
            except (EOFError, OSError):
                done = False
            out.append(value if done else function(*args, **kwargs))
        self._jobs = []
        return out

    def close(self) -> None:
        """End the helper: it has answered every job (or a stop came in the middle), so it is terminated
        rather than left to unload matplotlib and open3d while the run waits."""
        if self._process.is_alive():
            self._process.terminate()
        self._process.join(JOIN_SECONDS)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._conn.close()


@contextmanager
def output_process() -> Iterator[Optional[OutputProcess]]:
    """The helper for the block (None where it cannot start: the run then writes everything), ended
    when the block ends, by a stop too."""
    try:
        helper = OutputProcess()
    except (OSError, ValueError, RuntimeError):
        helper = None
    try:
        yield helper
    finally:
        if helper is not None:
            helper.close()

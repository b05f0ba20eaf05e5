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


def _functions() -> dict[str, Callable[..., Any]]:
    """The outputs the helper writes, by name."""
    from . import outputs, plots, report

    return {"write_map_ply": outputs.write_map_ply, "plot_trajectories_topdown": plots.plot_trajectories_topdown,
            "write_error_plot": report.write_error_plot}


def _serve(conn) -> None:
    """The helper: import the libraries, then call each function it is sent until the run's end of
    the pipe closes (or the run terminates it)."""
    for name in ("SIGINT", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    from . import outputs

    outputs.import_open3d()
    import matplotlib.figure  # noqa: F401 (imported now, while the run computes)

    functions = _functions()
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        name, args, kwargs = job
        try:
            value = functions[name](*args, **kwargs)
            conn.send(("ok", name, value if isinstance(value, bool) else None))  # write_map_ply's answer
        except Exception as exc:  # the run writes it itself and says why if that fails too
            conn.send(("error", name, f"{type(exc).__name__}: {exc}"))


class OutputProcess:
    """The helper process (module docstring): :meth:`submit` jobs, then :meth:`results` waits for them."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(child,), name="vislam-outputs", daemon=True)
        self._process.start()
        child.close()
        self._jobs: list[tuple[str, tuple, dict]] = []

    def submit(self, name: str, *args: Any, **kwargs: Any) -> None:
        """Send the helper one output to write: the function ``name`` of :func:`_functions` with its arguments."""
        self._jobs.append((name, args, kwargs))
        try:
            self._conn.send((name, args, kwargs))
        except (OSError, ValueError):  # the helper is gone: results() leaves the job to the caller
            pass

    def results(self) -> list[tuple[str, tuple, dict, Optional[tuple[Any]]]]:
        """Wait for every job sent: ``(name, args, kwargs, (value,))`` per job in order, ``None`` in place
        of ``(value,)`` where the helper did not write it (it failed, or is gone): the caller's to write."""
        out = []
        for name, args, kwargs in self._jobs:
            try:
                status, _, value = self._conn.recv()
            except (EOFError, OSError):
                status, value = "gone", None
            out.append((name, args, kwargs, (value,) if status == "ok" else None))
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

"""Where many runs execute: a local process pool, or a Ray cluster (``--ray ADDRESS``).

Both are ``concurrent.futures.Executor``-like (``submit(fn, *args)`` returning a
``concurrent.futures.Future``, ``shutdown``), so ``vislam batch`` and ``vislam mc`` submit the same
picklable, module-level functions to either. Ray is an optional extra (``pip install
'vislam[cluster]'``) imported only when asked for.

No worker outlives the command: when the work stops early (Ctrl-C, SIGTERM, SIGHUP, an error)
the local workers are terminated at once rather than left to finish their runs, and each worker
asks the kernel (Linux) to stop it when its parent dies, so even a killed ``vislam`` leaves none.
Workers ignore Ctrl-C themselves: the terminal sends it to the whole process group, and the parent
decides.
"""

from __future__ import annotations

import concurrent.futures
import os
import signal
import sys
from contextlib import contextmanager
from typing import Iterator, Optional

from ..backend.errors import ConfigError

__all__ = ["executor", "compile_for_workers", "ProcessPool", "RayExecutor"]


class RayExecutor:
    """``submit(fn, *args)`` as Ray tasks: one ``ray.remote`` per function, futures from object refs.

    ``address``: "local" starts a Ray instance in this process for the duration (as ``ray.init()``
    does with no cluster), anything else is passed to ``ray.init(address=...)`` ("auto", or
    "ray://host:10001"); ``workers`` caps the CPUs a local instance uses.
    """

    def __init__(self, address: str, workers: Optional[int] = None) -> None:
        try:
            import ray
        except ImportError:
            raise ConfigError("--ray needs the optional cluster extra: pip install 'vislam[cluster]'") from None
        self._ray = ray
        self._remote = {}
        self._refs = []
        self._own = not ray.is_initialized()
        if self._own:
            import logging

            kwargs = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
            if address == "local":
                kwargs["num_cpus"] = workers or os.cpu_count() or 1
            else:
                kwargs["address"] = address
            try:
                ray.init(**kwargs)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise ConfigError(f"--ray {address}: cannot connect ({str(exc).splitlines()[0]})") from None

    def submit(self, fn, *args) -> concurrent.futures.Future:
        remote = self._remote.get(fn)
        if remote is None:
            remote = self._remote[fn] = self._ray.remote(fn)
        ref = remote.remote(*args)
        self._refs.append(ref)
        return ref.future()

    def stop(self) -> None:
        """Cancel every task still pending or running (their workers are stopped)."""
        for ref in self._refs:
            try:
                self._ray.cancel(ref, force=True)
            except Exception:  # finished already, or the cluster is gone
                pass

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        if cancel_futures:
            self.stop()
        if self._own and self._ray.is_initialized():
            self._ray.shutdown()


def compile_for_workers(say, inertial: bool = False, window: bool = False) -> None:
    """On the first run after an install (or a change of the sources): compile the kernels here, with
    the compile helper, before a local pool starts, so that its workers load them. A worker may not
    start a helper of its own (a daemonic process) and would compile every kernel itself, each of
    them at once. ``say``: where the compile notice goes; ``inertial``, ``window``: the runs' kind
    (:func:`~vislam.backend.compiled.warm_up`)."""
    from ..backend import compiled
    from ..backend.run.runner import COMPILING

    if not compiled.warmed_before():
        compiled.warm_up(notice=lambda: say(COMPILING), inertial=inertial, window=window)


def _start_worker(parent: int) -> None:
    """In each local worker: Ctrl-C is the parent's to handle; SIGTERM and SIGHUP stop the worker
    (not the parent's handlers, inherited by a fork); the kernel sends SIGTERM when the parent dies."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # pragma: no cover - a libc without prctl
            pass
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


class ProcessPool:
    """``submit(fn, *args)`` on local worker processes (``multiprocessing.Pool``), futures as
    ``concurrent.futures.Future``; :meth:`stop` terminates the workers at once, running work and
    all (``ProcessPoolExecutor`` can only wait for running work to finish)."""

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self._pool = multiprocessing.Pool(workers, initializer=_start_worker, initargs=(os.getpid(),))

    def submit(self, fn, *args) -> concurrent.futures.Future:
        future = concurrent.futures.Future()
        future.set_running_or_notify_cancel()
        self._pool.apply_async(fn, args, callback=lambda value: _settle(future, future.set_result, value),
                               error_callback=lambda exc: _settle(future, future.set_exception, exc))
        return future

    def stop(self) -> None:
        """Terminate the workers now and reap them."""
        self._pool.terminate()
        self._pool.join()

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        if cancel_futures:
            self.stop()
            return
        self._pool.close()
        if wait:
            self._pool.join()


def _settle(future: concurrent.futures.Future, setter, value) -> None:
    """Give ``future`` its outcome unless it has one already (a caller may have cancelled it)."""
    try:
        if not future.done():
            setter(value)
    except concurrent.futures.InvalidStateError:  # settled meanwhile
        pass


@contextmanager
def executor(workers: Optional[int] = None, ray_address: Optional[str] = None, jobs: int = 1) -> Iterator:
    """A process pool of ``workers`` (default: every core, at most ``jobs``), or Ray at
    ``ray_address``; shut down on exit; on an exception (an interruption included) pending work is
    cancelled and the workers are stopped at once (module docstring)."""
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if ray_address:
        pool = RayExecutor(ray_address, workers)
    else:
        pool = ProcessPool(min(workers or os.cpu_count() or 1, max(jobs, 1)))
    completed = False
    try:
        yield pool
        completed = True
    finally:
        pool.shutdown(wait=True, cancel_futures=not completed)

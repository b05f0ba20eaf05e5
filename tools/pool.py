"""Where many runs execute: a local process pool, or a Ray cluster (``--ray ADDRESS``).

Both are ``concurrent.futures.Executor``-like (``submit(fn, *args)`` returning a
``concurrent.futures.Future``, ``shutdown``), so ``vislam batch`` and ``vislam mc`` submit the same
picklable, module-level functions to either. Ray is an optional extra (``pip install
'vislam[cluster]'``) imported only when asked for.
"""

from __future__ import annotations

import concurrent.futures
import os
from contextlib import contextmanager
from typing import Iterator, Optional

from ..backend.errors import ConfigError

__all__ = ["executor", "RayExecutor"]


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
        return remote.remote(*args).future()

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        if self._own and self._ray.is_initialized():
            self._ray.shutdown()


@contextmanager
def executor(workers: Optional[int] = None, ray_address: Optional[str] = None, jobs: int = 1) -> Iterator:
    """A process pool of ``workers`` (default: every core, at most ``jobs``), or Ray at
    ``ray_address``; shut down on exit, pending work cancelled on an exception (Ctrl-C)."""
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if ray_address:
        pool = RayExecutor(ray_address, workers)
    else:
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=min(workers or os.cpu_count() or 1, max(jobs, 1)))
    completed = False
    try:
        yield pool
        completed = True
    finally:
        pool.shutdown(wait=True, cancel_futures=not completed)

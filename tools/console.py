"""What the command line says on the terminal: one-line messages and progress bars, on stderr."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Callable, Iterator, Optional


def sayer(quiet: bool) -> Callable[[str], None]:
    """A function printing one message to stderr, or doing nothing when ``quiet``."""
    if quiet:
        return lambda message: None
    return lambda message: print(message, file=sys.stderr, flush=True)


@contextmanager
def progress_bar(total: Optional[int], desc: str, unit: str, quiet: bool) -> Iterator[Optional[Callable[[int], None]]]:
    """A callback advancing a tqdm bar by one per call (None when ``quiet``), closed at the end."""
    if quiet:
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(total=total, unit=unit, file=sys.stderr, desc=desc)
    try:
        yield lambda *_: bar.update(1)
    finally:
        bar.close()

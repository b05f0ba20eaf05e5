"""Writing a file so that it is either complete or not there (the one atomic writer of vislam)."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_write"]


def _temp_path(path: Path) -> Path:
    """``dir/name.ext`` -> ``dir/.name.tmp-<pid>.ext`` (the suffix is kept for writers
    such as open3d or matplotlib that choose the format by the file extension)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


@contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` on success.

    The temporary name is ``.<stem>.tmp-<pid><suffix>`` in the same directory (so
    ``os.replace`` is atomic and the extension is preserved). If the body raises anything,
    ``KeyboardInterrupt`` included, the temporary file is removed, an existing ``path`` is
    left untouched and the exception propagates.
    """
    target = Path(path)
    tmp = _temp_path(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise

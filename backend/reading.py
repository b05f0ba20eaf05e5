"""Reading input files without hanging or exhausting memory: only regular files, up to a size.

A FIFO given as ``--config`` or ``--gt`` would block the read until Ctrl-C, ``/dev/zero`` never
ends, and a file of many GiB would be read whole before any check: :func:`read_regular_file`
refuses each by what it is (``os.stat``) before opening it.
"""

from __future__ import annotations

import os
import stat

from .errors import InputError

__all__ = ["describe_mode", "read_regular_file"]


def describe_mode(mode: int) -> str:
    """What a file mode (``os.stat``) is, for messages: 'a regular file', 'a FIFO', ..."""
    for test, what in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a directory"),
                       (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"


def read_regular_file(path: str | os.PathLike, max_bytes: int, what: str = "file", error=None) -> bytes:
    """The bytes of the regular file ``path``; ``error`` (default InputError) naming it when it is
    missing, not a regular file (a FIFO would block, a device never end) or larger than ``max_bytes``."""
    error = error or InputError
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:  # a loop of symbolic links, a permission
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: is {describe_mode(st.st_mode)}, not a regular file (the {what})")
    if st.st_size > max_bytes:
        raise error(f"{path}: {st.st_size / 2**20:.1f} MiB, more than the {max_bytes / 2**20:.0f} MiB a {what} "
                    "may have")
    try:
        with open(path, "rb") as handle:
            return handle.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None

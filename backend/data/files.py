"""Writing so that nothing is lost: a file is either complete or not there, and nothing but a
regular file is ever replaced.

- :func:`check_output_file` refuses, before any work, a target that is not a regular file (a
  directory, a symbolic link, a FIFO, a device), whose directory is missing or not writable;
- :func:`atomic_write` writes to a temporary name beside the target and renames it at the end;
- :func:`output_directory` does the same for a whole directory of outputs: they are written into
  a temporary directory beside the target, which becomes the target at the end; an interrupted or
  failed run leaves nothing behind.
"""

from __future__ import annotations

import os
import shutil
import signal
import stat
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import OutputError

__all__ = ["atomic_write", "check_output_file", "output_directory"]


def _temp_path(path: Path) -> Path:
    """``dir/name.ext`` -> ``dir/.name.tmp-<pid>.ext`` (the suffix is kept for writers
    such as open3d or matplotlib that choose the format by the file extension)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def _describe(mode: int) -> str:
    for test, what in ((stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"


def check_output_file(path: str | os.PathLike, overwrite: bool = True) -> Path:
    """``path`` as a Path if a regular file can be written there: an existing regular file (only
    with ``overwrite``) or a new name in an existing, writable directory; OutputError otherwise."""
    target = Path(path)
    if not str(path):
        raise OutputError("output path is empty")
    try:
        mode = os.lstat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"{target}: cannot inspect the output path: {exc.strerror}") from None
    if mode is not None:
        if not stat.S_ISREG(mode):
            raise OutputError(f"{target}: is {_describe(mode)}, not a regular file; refusing to replace it")
        if not overwrite:
            raise OutputError(f"{target}: exists; refusing to overwrite it (use --force)")
    parent = target.parent
    if not parent.is_dir():
        raise OutputError(f"{target}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{target}: directory {parent} is not writable")
    return target


@contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` on success.

    The target must be a regular file or not exist (:func:`check_output_file`). The temporary name
    is ``.<stem>.tmp-<pid><suffix>`` in the same directory (so ``os.replace`` is atomic and the
    extension is preserved). If the body raises anything, ``KeyboardInterrupt`` included, the
    temporary file is removed, an existing ``path`` is left untouched and the exception propagates;
    an OSError of the body (a full disk, say) becomes a one-line OutputError.
    """
    target = check_output_file(path)
    tmp = _temp_path(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise OutputError(f"{target}: cannot write: {exc.strerror or exc}") from None
        raise


@contextmanager
def _sigint_blocked() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back for the block: a few renames that must all happen or none."""
    main = threading.current_thread() is threading.main_thread()
    if main and hasattr(signal, "pthread_sigmask"):
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
    else:  # pragma: no cover - other threads or platforms
        yield


def check_output_directory(path: str | os.PathLike, force: bool) -> Path:
    """``path`` as a Path if outputs can go there: a new name in a writable directory, an empty
    writable directory, or (with ``force``) a non-empty writable one; OutputError otherwise."""
    if not str(path):
        raise OutputError("output directory path is empty")
    target = Path(path)
    try:
        mode = os.lstat(target).st_mode
    except FileNotFoundError:
        mode = None
    except NotADirectoryError:
        blocker = next(p for p in target.absolute().parents if p.exists())
        raise OutputError(f"{target}: cannot create the output directory: {blocker} is not a directory") from None
    except OSError as exc:
        raise OutputError(f"{target}: cannot inspect the output directory: {exc.strerror}") from None
    if mode is not None:
        if not stat.S_ISDIR(mode):
            raise OutputError(f"{target}: is {_describe(mode)}, not a directory")
        if not os.access(target, os.W_OK | os.X_OK):
            raise OutputError(f"{target}: output directory is not writable")
        if not force and any(target.iterdir()):
            raise OutputError(f"{target}: output directory exists and is not empty; use --force to write into it")
    parent = target.absolute().parent
    while not parent.exists():  # the directories to create: the nearest existing one must be writable
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{target}: cannot create the output directory: {parent} is not writable")
    return target


def _merge_plan(src: Path, dst: Path) -> list[tuple[Path, Path]]:
    """The renames that move the tree ``src`` into the existing directory ``dst``: new names and
    regular files replaced; OutputError where a name in ``dst`` is something else."""
    moves = []
    for item in sorted(src.iterdir()):
        there = dst / item.name
        try:
            mode = os.lstat(there).st_mode
        except FileNotFoundError:
            moves.append((item, there))
            continue
        if item.is_dir() and stat.S_ISDIR(mode):
            moves += _merge_plan(item, there)
        elif item.is_file() and stat.S_ISREG(mode):
            moves.append((item, there))
        else:
            raise OutputError(f"{there}: is {_describe(mode)}; refusing to replace it with the output of that name")
    return moves


def _make_parents(target: Path) -> list[Path]:
    """Create the missing directories above ``target``; the ones created, innermost first."""
    missing = []
    parent = target.parent
    while not parent.exists():
        missing.append(parent)
        parent = parent.parent
    for folder in reversed(missing):
        try:
            folder.mkdir()
        except OSError as exc:
            _remove_empty(missing)
            raise OutputError(f"{target}: cannot create {folder}: {exc.strerror}") from None
    return missing


def _remove_empty(folders: list[Path]) -> None:
    for folder in folders:  # innermost first
        try:
            folder.rmdir()
        except OSError:
            pass


@contextmanager
def output_directory(path: str | os.PathLike, force: bool, min_free_bytes: int = 0) -> Iterator[Path]:
    """Yield a temporary directory to write a set of outputs into; they end up in ``path``.

    Checked before the work (:func:`check_output_directory`, and at least ``min_free_bytes`` free
    on its file system). A new target: the finished temporary directory (made beside it) becomes
    ``path`` in one rename. An existing one (empty, or with ``force`` not empty; ``.`` included):
    the temporary directory is made inside it and the outputs are moved up one by one with Ctrl-C
    held back, overwriting files of the same names and keeping the others; every clash (a name
    that is not a regular file where an output file goes) is refused before anything moves. If the
    body raises (Ctrl-C included) the temporary directory and the parents created for ``path`` are
    removed: the file system is left as it was.
    """
    target = Path(os.path.abspath(check_output_directory(path, force)))
    shown = Path(path)
    existing = target.is_dir()
    anchor = target
    while not anchor.exists():
        anchor = anchor.parent
    free = shutil.disk_usage(anchor).free
    if free < min_free_bytes:
        raise OutputError(f"{shown}: {free / 2**20:.0f} MiB free on its file system, the outputs need about "
                          f"{min_free_bytes / 2**20:.0f} MiB")
    created = [] if existing else _make_parents(target)
    tmp = (target / f".vislam.tmp-{os.getpid()}" if existing
           else target.parent / f".{target.name}.tmp-{os.getpid()}")
    try:
        tmp.mkdir()
    except OSError as exc:
        _remove_empty(created)
        raise OutputError(f"{shown}: cannot create a temporary directory {tmp.name} there: {exc.strerror}") from None
    try:
        yield tmp
        if existing:
            moves = _merge_plan(tmp, target)  # every clash checked before anything moves
            with _sigint_blocked():
                for src, dst in moves:
                    os.replace(src, dst)
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with _sigint_blocked():
                os.replace(tmp, target)  # one rename: the outputs appear all at once
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)
        if isinstance(exc, OSError):
            raise OutputError(f"{shown}: cannot write the outputs: {exc.strerror or exc}") from None
        raise

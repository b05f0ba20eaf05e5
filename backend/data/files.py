"""Writing so that nothing is lost: a file is either complete or not there, nothing but a
regular file is ever replaced, and no output ever lands on an input of the same run.

- :func:`inputs_of_the_run` holds what a command reads: the paths it was given, and what its
  readers note (:func:`note_input`: the files they read, the folders they list). While it is in
  place, every check below also refuses (:func:`check_not_an_input`) an output path that resolves
  to an input file or folder or lies in a folder read whole: ``--draw`` into ``image_0`` or
  ``--out`` onto ``calib.txt`` is refused, ``--out`` to a new name beside the images is not. The
  rule holds with or without ``--force``;
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
import stat
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from .. import signals
from ..errors import OutputError
from ..reading import describe_mode

__all__ = ["atomic_write", "check_not_an_input", "check_output_file", "inputs_of_the_run", "note_input",
           "output_directory"]


@dataclass(frozen=True)
class _Input:
    """One input of the run: a file, a folder, or a folder read whole (everything under it)."""

    path: Path  # absolute, symbolic links resolved
    shown: str  # as the user or the reader named it
    folder: bool = False
    read_whole: bool = False  # a folder whose contents are the input (image folders, mav0)


_inputs: dict[Path, _Input] = {}  # by resolved path
_open_runs = [0]  # inputs_of_the_run blocks in progress: outside them nothing is recorded
_staging: set[Path] = set()  # output_directory's temporary folders: what goes there is checked on the way out


def _resolved(path: str | os.PathLike) -> Path:
    return Path(os.path.realpath(os.path.abspath(path)))


def note_input(path: str | os.PathLike, contents: bool = False) -> None:
    """Add ``path`` (a file or a folder; nothing if it does not exist) to the inputs of the run
    (:func:`inputs_of_the_run`); ``contents``: everything under the folder is input too (readers
    call it for the folders they list, ``image_0/`` or ``mav0/``, and the files they read). Outside
    an :func:`inputs_of_the_run` block (the library used directly) nothing is recorded."""
    if not _open_runs[0]:
        return
    resolved = _resolved(path)
    if not resolved.exists():
        return
    item = _Input(resolved, str(path), resolved.is_dir(), contents and resolved.is_dir())
    known = _inputs.get(resolved)
    if known is None or (item.read_whole and not known.read_whole):
        _inputs[resolved] = item


@contextmanager
def inputs_of_the_run(paths: Iterable[str | os.PathLike | None]) -> Iterator[None]:
    """For the block, ``paths`` (None skipped) and whatever the readers add (:func:`note_input`)
    are the inputs no output may resolve to (module docstring); forgotten at the end."""
    saved = dict(_inputs)
    _open_runs[0] += 1
    try:
        for path in paths:
            if path is not None and str(path):
                note_input(path)
        yield
    finally:
        _open_runs[0] -= 1
        _inputs.clear()
        _inputs.update(saved)


def check_not_an_input(path: str | os.PathLike) -> None:
    """OutputError if the output ``path`` resolves to an input of the run or lies inside a folder
    read whole (:func:`inputs_of_the_run`)."""
    if not _inputs:
        return
    target = _resolved(path)
    if any(parent in _staging for parent in target.parents):
        return
    item = _inputs.get(target)
    if item is not None:
        kind = "folder" if item.folder else "file"
        raise OutputError(f"{path}: is the input {kind} {item.shown} of this run; refusing to write over it")
    for parent in target.parents:
        item = _inputs.get(parent)
        if item is not None and item.read_whole:
            raise OutputError(f"{path}: lies in {item.shown}, a folder this run reads; refusing to write into an input")


def _temp_path(path: Path) -> Path:
    """``dir/name.ext`` -> ``dir/.name.tmp-<pid>.ext`` (the suffix is kept for writers
    such as open3d or matplotlib that choose the format by the file extension)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def check_output_file(path: str | os.PathLike, overwrite: bool = True) -> Path:
    """``path`` as a Path if a regular file can be written there: an existing regular file (only
    with ``overwrite``) or a new name in an existing, writable directory; OutputError otherwise."""
    target = Path(path)
    if not str(path):
        raise OutputError("output path is empty")
    check_not_an_input(target)
    try:
        mode = os.lstat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"{target}: cannot inspect the output path: {exc.strerror}") from None
    if mode is not None:
        if not stat.S_ISREG(mode):
            raise OutputError(f"{target}: is {describe_mode(mode)}, not a regular file; refusing to replace it")
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
        check_not_an_input(target)  # again: the readers may have noted more inputs meanwhile
        os.replace(tmp, target)
    except BaseException as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise OutputError(f"{target}: cannot write: {exc.strerror or exc}") from None
        raise


def check_output_directory(path: str | os.PathLike, force: bool) -> Path:
    """``path`` as a Path if outputs can go there: a new name in a writable directory, an empty
    writable directory, or (with ``force``) a non-empty writable one; OutputError otherwise."""
    if not str(path):
        raise OutputError("output directory path is empty")
    target = Path(path)
    check_not_an_input(target)
    try:
        mode = os.lstat(target).st_mode
        if stat.S_ISLNK(mode) and target.is_dir():  # a link to a directory: the outputs go into that directory
            mode = os.stat(target).st_mode
    except FileNotFoundError:
        mode = None
    except NotADirectoryError:
        blocker = next(p for p in target.absolute().parents if p.exists())
        raise OutputError(f"{target}: cannot create the output directory: {blocker} is not a directory") from None
    except OSError as exc:
        raise OutputError(f"{target}: cannot inspect the output directory: {exc.strerror}") from None
    if mode is not None:
        if not stat.S_ISDIR(mode):
            raise OutputError(f"{target}: is {describe_mode(mode)}, not a directory")
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
        check_not_an_input(there)
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
            raise OutputError(f"{there}: is {describe_mode(mode)}; refusing to replace it with the output of that name")
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
    staged = _resolved(tmp)
    _staging.add(staged)
    try:
        yield tmp
        check_not_an_input(shown)  # again: the readers may have noted more inputs meanwhile
        if existing:
            moves = _merge_plan(tmp, target)  # every clash checked before anything moves
            with signals.held():
                for src, dst in moves:
                    os.replace(src, dst)
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with signals.held():
                os.replace(tmp, target)  # one rename: the outputs appear all at once
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)
        if isinstance(exc, OSError):
            raise OutputError(f"{shown}: cannot write the outputs: {exc.strerror or exc}") from None
        raise
    finally:
        _staging.discard(staged)

"""Tests of vislam.backend.data.files: check_output_file, atomic_write, check_output_directory and
output_directory (nothing but a regular file is ever replaced; a failed or interrupted write leaves
the target as it was and no temporary file or directory behind)."""

from __future__ import annotations

import errno
import os
import signal
import stat
from pathlib import Path

import pytest
from vislam.backend.data import files
from vislam.backend.data.files import (
    atomic_write,
    check_output_directory,
    check_output_file,
    output_directory,
)
from vislam.backend.errors import OutputError


def snapshot(root: Path) -> dict:
    """Everything under ``root`` (itself included), by relative path: kind and content, without
    following symbolic links."""
    out = {}

    def visit(p: Path, rel: str) -> None:
        mode = os.lstat(p).st_mode
        if stat.S_ISLNK(mode):
            out[rel] = ("link", os.readlink(p))
        elif stat.S_ISFIFO(mode):
            out[rel] = ("fifo",)
        elif stat.S_ISREG(mode):
            out[rel] = ("file", p.read_bytes())
        elif stat.S_ISDIR(mode):
            out[rel] = ("dir",)
            for child in sorted(os.listdir(p)):
                visit(p / child, f"{rel}/{child}")
        else:  # pragma: no cover
            out[rel] = ("other", mode)

    if os.path.lexists(root):
        visit(root, ".")
    return out


def assert_one_line_naming(exc: pytest.ExceptionInfo, path) -> None:
    message = str(exc.value)
    assert "\n" not in message
    assert str(path) in message


def make_specials(tmp_path: Path) -> dict[str, Path]:
    """A symlink to a file, a dangling symlink, a FIFO and a directory, in ``tmp_path``."""
    real = tmp_path / "real.txt"
    real.write_bytes(b"real content")
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    dangling = tmp_path / "dangling.txt"
    dangling.symlink_to(tmp_path / "nowhere.txt")
    fifo = tmp_path / "fifo.txt"
    os.mkfifo(fifo)
    directory = tmp_path / "dir.txt"
    directory.mkdir()
    (directory / "inside").write_text("x")
    return {"symlink": link, "dangling symlink": dangling, "FIFO": fifo, "directory": directory}


SPECIAL_WORDS = {"symlink": "symbolic link", "dangling symlink": "symbolic link", "FIFO": "FIFO",
                 "directory": "directory"}


# ---------------------------------------------------------------- check_output_file


def test_check_output_file_refuses_empty_path():
    """An empty output path is refused with OutputError."""
    with pytest.raises(OutputError, match="empty"):
        check_output_file("")


@pytest.mark.parametrize("kind", list(SPECIAL_WORDS))
def test_check_output_file_refuses_non_regular_and_leaves_it(tmp_path, kind):
    """A symlink (live or dangling), a FIFO or a directory is refused, named, and left exactly as it was."""
    path = make_specials(tmp_path)[kind]
    before = snapshot(tmp_path)
    with pytest.raises(OutputError) as exc:
        check_output_file(path)
    assert_one_line_naming(exc, path)
    assert SPECIAL_WORDS[kind] in str(exc.value)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("kind", list(SPECIAL_WORDS))
def test_atomic_write_refuses_non_regular_before_the_body(tmp_path, kind):
    """atomic_write onto a symlink/FIFO/directory raises before its body and keeps the symlink a
    symlink to the same place, the FIFO a FIFO, the directory as it was; no temporary file."""
    path = make_specials(tmp_path)[kind]
    before = snapshot(tmp_path)
    ran = []
    with pytest.raises(OutputError), atomic_write(path) as tmp:
        ran.append(tmp)
        tmp.write_text("overwrite")
    assert ran == []
    assert snapshot(tmp_path) == before
    if kind.endswith("symlink"):
        assert path.is_symlink() and os.readlink(path) == before[f"./{path.name}"][1]
    if kind == "FIFO":
        assert stat.S_ISFIFO(os.lstat(path).st_mode)


def test_check_output_file_refuses_missing_parent(tmp_path):
    """A file in a directory that does not exist is refused, naming the path."""
    path = tmp_path / "missing" / "out.txt"
    with pytest.raises(OutputError) as exc:
        check_output_file(path)
    assert_one_line_naming(exc, path)
    assert not (tmp_path / "missing").exists()


def test_check_output_file_refuses_parent_that_is_a_file(tmp_path):
    """A file 'inside' a regular file is refused (also for root), and that file keeps its bytes."""
    parent = tmp_path / "plain"
    parent.write_bytes(b"plain")
    path = parent / "out.txt"
    with pytest.raises(OutputError) as exc:
        check_output_file(path)
    assert_one_line_naming(exc, path)
    assert parent.read_bytes() == b"plain"


def test_check_output_file_new_name_is_accepted(tmp_path):
    """A new name in an existing directory is accepted and returned as a Path, without creating it."""
    path = tmp_path / "new.txt"
    assert check_output_file(str(path)) == path
    assert not path.exists()


def test_check_output_file_existing_regular_file_and_overwrite(tmp_path):
    """An existing regular file is fine with overwrite=True, refused with overwrite=False; untouched either way."""
    path = tmp_path / "old.txt"
    path.write_bytes(b"old")
    assert check_output_file(path, overwrite=True) == path
    with pytest.raises(OutputError) as exc:
        check_output_file(path, overwrite=False)
    assert_one_line_naming(exc, path)
    assert path.read_bytes() == b"old"


# ---------------------------------------------------------------- atomic_write


def test_atomic_write_success_leaves_only_the_target(tmp_path):
    """After a successful body the target holds the new bytes and no temporary file remains."""
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with atomic_write(target) as tmp:
        assert tmp != target and tmp.parent == tmp_path
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new"
    assert os.listdir(tmp_path) == ["out.bin"]


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
@pytest.mark.parametrize("existing", [False, True])
def test_atomic_write_body_raises_leaves_target_and_no_temp(tmp_path, exc_type, existing):
    """An exception or KeyboardInterrupt in the body propagates, removes the temporary file and
    leaves the target as before (missing stays missing, an existing one keeps its bytes)."""
    target = tmp_path / "out.npz"
    if existing:
        target.write_bytes(b"previous")
    with pytest.raises(exc_type), atomic_write(target) as tmp:
        tmp.write_bytes(b"partial")
        raise exc_type("stop")
    assert os.listdir(tmp_path) == (["out.npz"] if existing else [])
    if existing:
        assert target.read_bytes() == b"previous"


def test_atomic_write_body_oserror_becomes_output_error(tmp_path):
    """An OSError of the body (a full disk) becomes a one-line OutputError naming the file; the
    existing target keeps its bytes and no temporary file remains."""
    target = tmp_path / "out.txt"
    target.write_bytes(b"keep me")
    with pytest.raises(OutputError) as exc, atomic_write(target) as tmp:
        tmp.write_bytes(b"half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert_one_line_naming(exc, target)
    assert os.strerror(errno.ENOSPC) in str(exc.value)
    assert target.read_bytes() == b"keep me"
    assert os.listdir(tmp_path) == ["out.txt"]


# ---------------------------------------------------------------- check_output_directory


def test_check_output_directory_refuses_empty_path():
    """An empty output directory path is refused with OutputError."""
    with pytest.raises(OutputError, match="empty"):
        check_output_directory("", force=True)


@pytest.mark.parametrize("force", [False, True])
def test_check_output_directory_refuses_a_regular_file_and_takes_a_link_to_a_directory(tmp_path, force):
    """A regular file is refused as output directory, even with force; a symbolic link to a directory
    is that directory (empty: taken; holding files: only with force), a link to a file is refused."""
    plain = tmp_path / "plain"
    plain.write_text("x")
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real)
    to_file = tmp_path / "to_file"
    to_file.symlink_to(plain)
    before = snapshot(tmp_path)
    for path in (plain, to_file):
        with pytest.raises(OutputError) as exc:
            check_output_directory(path, force)
        assert_one_line_naming(exc, path)
    assert check_output_directory(link, force) == link
    (real / "old.txt").write_text("kept")
    if force:
        assert check_output_directory(link, force) == link
    else:
        with pytest.raises(OutputError, match="--force"):
            check_output_directory(link, force)
    (real / "old.txt").unlink()
    assert snapshot(tmp_path) == before


def test_check_output_directory_cases(tmp_path):
    """New names (missing parents too) and empty dirs pass; a non-empty dir needs force; nothing is created."""
    assert check_output_directory(tmp_path / "a" / "b" / "out", force=False) == tmp_path / "a" / "b" / "out"
    assert not (tmp_path / "a").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_output_directory(empty, force=False) == empty
    full = tmp_path / "full"
    full.mkdir()
    (full / "f").write_text("x")
    with pytest.raises(OutputError) as exc:
        check_output_directory(full, force=False)
    assert_one_line_naming(exc, full)
    assert check_output_directory(full, force=True) == full


def test_check_output_directory_refuses_below_a_regular_file(tmp_path):
    """An output directory whose ancestor is a regular file is refused (also for root)."""
    plain = tmp_path / "plain"
    plain.write_text("x")
    path = plain / "sub" / "out"
    with pytest.raises(OutputError) as exc:
        check_output_directory(path, force=True)
    assert_one_line_naming(exc, path)


# ---------------------------------------------------------------- output_directory


def staging_left(parent: Path, name: str) -> list[str]:
    return [p for p in os.listdir(parent) if p.startswith(f".{name}.tmp-")]


def write_outputs(staging: Path, outputs: dict[str, bytes]) -> None:
    for rel, data in outputs.items():
        p = staging / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)


OUTPUTS = {"summary.json": b"{}", "trajectory.txt": b"1 2 3", "plots/error.png": b"png"}


def expected_tree(outputs: dict[str, bytes]) -> dict:
    tree = {".": ("dir",)}
    for rel, data in outputs.items():
        parts = rel.split("/")
        for i in range(1, len(parts)):
            tree["./" + "/".join(parts[:i])] = ("dir",)
        tree["./" + rel] = ("file", data)
    return tree


def test_output_directory_new_target_with_missing_parents(tmp_path):
    """A new target under missing parents ends as a directory holding exactly the staged files, and
    no .NAME.tmp-* staging directory is left."""
    target = tmp_path / "a" / "b" / "run"
    with output_directory(target, force=False) as staging:
        assert staging != target and staging.is_dir() and not target.exists()
        assert staging.parent == target.parent and staging.name.startswith(".run.tmp-")
        write_outputs(staging, OUTPUTS)
    assert snapshot(target) == expected_tree(OUTPUTS)
    assert os.listdir(target.parent) == ["run"]


def test_output_directory_existing_empty_target(tmp_path):
    """An existing empty directory is accepted without force and ends holding the outputs."""
    target = tmp_path / "run"
    target.mkdir()
    with output_directory(target, force=False) as staging:
        write_outputs(staging, OUTPUTS)
    assert snapshot(target) == expected_tree(OUTPUTS)
    assert staging_left(tmp_path, "run") == []


def test_output_directory_non_empty_refused_before_the_body(tmp_path):
    """A non-empty target without force is refused before the body runs; nothing changes, no staging dir."""
    target = tmp_path / "run"
    target.mkdir()
    (target / "old.txt").write_bytes(b"old")
    before = snapshot(tmp_path)
    ran = []
    with pytest.raises(OutputError) as exc, output_directory(target, force=False) as staging:
        ran.append(staging)
    assert ran == []
    assert_one_line_naming(exc, target)
    assert snapshot(tmp_path) == before


def test_output_directory_force_merges(tmp_path):
    """With force the outputs are merged: new files added, same-named files replaced, other files
    kept, a nested subdirectory merged the same way; no staging directory left."""
    target = tmp_path / "run"
    write_outputs(target, {"same.txt": b"old", "keep.txt": b"keep", "sub/same.txt": b"old sub",
                           "sub/keep.txt": b"keep sub", "sub/deep/keep.txt": b"deep"})
    with output_directory(target, force=True) as staging:
        write_outputs(staging, {"same.txt": b"new", "new.txt": b"added", "sub/same.txt": b"new sub",
                                "sub/new.txt": b"added sub", "sub/deep/new.txt": b"deep new", "fresh/x.txt": b"x"})
    assert snapshot(target) == expected_tree({
        "same.txt": b"new", "keep.txt": b"keep", "new.txt": b"added", "sub/same.txt": b"new sub",
        "sub/keep.txt": b"keep sub", "sub/new.txt": b"added sub", "sub/deep/keep.txt": b"deep",
        "sub/deep/new.txt": b"deep new", "fresh/x.txt": b"x"})
    assert staging_left(tmp_path, "run") == []


def _make_clash(target: Path, kind: str) -> dict[str, bytes]:
    """Fill ``target`` so that the returned outputs clash with it under the name 'sub/m.txt' (or 'm')."""
    write_outputs(target, {"a.txt": b"old a", "sub/keep.txt": b"keep"})
    if kind == "directory":
        (target / "sub" / "m.txt").mkdir()
        (target / "sub" / "m.txt" / "inner").write_bytes(b"inner")
    elif kind == "symlink":
        (target / "sub" / "m.txt").symlink_to(target / "a.txt")
    elif kind == "dangling symlink":
        (target / "sub" / "m.txt").symlink_to(target / "nowhere")
    elif kind == "file where a directory goes":
        (target / "m").write_bytes(b"a file")
        return {"a.txt": b"new a", "b.txt": b"new b", "m/x.txt": b"x"}
    return {"a.txt": b"new a", "b.txt": b"new b", "sub/m.txt": b"file", "sub/z.txt": b"z"}


@pytest.mark.parametrize("kind", ["directory", "symlink", "dangling symlink", "file where a directory goes"])
def test_output_directory_force_clash_changes_nothing(tmp_path, kind):
    """With force, an output name held in the target by something else than what is written (a
    directory or symlink where a file goes, a file where a directory goes) is refused with
    OutputError and no file of the target changes (not even those sorted before the clash)."""
    target = tmp_path / "run"
    outputs = _make_clash(target, kind)
    before = snapshot(target)
    with pytest.raises(OutputError) as exc, output_directory(target, force=True) as staging:
        write_outputs(staging, outputs)
    assert "\n" not in str(exc.value)
    assert snapshot(target) == before
    assert staging_left(tmp_path, "run") == []


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
@pytest.mark.parametrize("state", ["missing", "empty", "non-empty"])
def test_output_directory_body_raises_leaves_target(tmp_path, exc_type, state):
    """An exception or KeyboardInterrupt in the body propagates, leaves the target exactly as before
    (missing stays missing, an existing directory keeps its content) and no staging directory."""
    target = tmp_path / "run"
    if state != "missing":
        target.mkdir()
    if state == "non-empty":
        write_outputs(target, {"old.txt": b"old", "sub/old.txt": b"old sub"})
    before = snapshot(tmp_path)
    with pytest.raises(exc_type), output_directory(target, force=True) as staging:
        write_outputs(staging, {"old.txt": b"new", "sub/old.txt": b"new", "new.txt": b"new"})
        raise exc_type("stop")
    assert snapshot(tmp_path) == before
    assert staging_left(tmp_path, "run") == []


def test_output_directory_body_oserror_becomes_output_error(tmp_path):
    """An OSError in the body becomes a one-line OutputError naming the target; nothing is left behind."""
    target = tmp_path / "run"
    with pytest.raises(OutputError) as exc, output_directory(target, force=False) as staging:
        write_outputs(staging, OUTPUTS)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert_one_line_naming(exc, target)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("failure", ["body raises", "too little free space"])
def test_output_directory_failure_leaves_no_created_parents(tmp_path, failure):
    """A failed output under missing parents leaves nothing behind, not even the parents ("an
    interrupted or failed run leaves nothing behind", module docstring)."""
    target = tmp_path / "a" / "b" / "run"
    min_free = 2**62 if failure == "too little free space" else 0
    with pytest.raises((RuntimeError, OutputError)), output_directory(target, False, min_free) as staging:
        write_outputs(staging, OUTPUTS)
        raise RuntimeError("stop")
    assert os.listdir(tmp_path) == []


def test_output_directory_refuses_too_little_free_space(tmp_path):
    """min_free_bytes beyond the disk's free space is refused (message in MiB, naming the target)
    before the body; the target stays missing and no staging directory is made."""
    target = tmp_path / "run"
    ran = []
    with pytest.raises(OutputError) as exc, output_directory(target, force=False, min_free_bytes=2**62) as staging:
        ran.append(staging)
    assert ran == []
    assert_one_line_naming(exc, target)
    assert "MiB" in str(exc.value)
    assert os.listdir(tmp_path) == []


def test_output_directory_small_min_free_bytes_is_fine(tmp_path):
    """A min_free_bytes the disk has (1 byte) does not refuse the output."""
    target = tmp_path / "run"
    with output_directory(target, force=False, min_free_bytes=1) as staging:
        write_outputs(staging, OUTPUTS)
    assert snapshot(target) == expected_tree(OUTPUTS)


@pytest.mark.parametrize("force", [False, True])
def test_output_directory_refuses_a_regular_file_target(tmp_path, force):
    """A target that is a regular file is refused (even with force) before the body and keeps its bytes."""
    target = tmp_path / "run"
    target.write_bytes(b"a file")
    ran = []
    with pytest.raises(OutputError) as exc, output_directory(target, force=force) as staging:
        ran.append(staging)
    assert ran == []
    assert_one_line_naming(exc, target)
    assert target.read_bytes() == b"a file"
    assert os.listdir(tmp_path) == ["run"]


def test_output_directory_writes_through_a_link_to_a_directory(tmp_path):
    """A target that is a symbolic link to a directory: the outputs land in that directory (with
    force, beside what it held), and the link stays a link to the same place."""
    real = tmp_path / "real"
    real.mkdir()
    (real / "f").write_bytes(b"f")
    target = tmp_path / "run"
    target.symlink_to(real)
    with output_directory(target, force=True) as staging:
        write_outputs(staging, OUTPUTS)
    assert target.is_symlink() and os.readlink(target) == str(real)
    assert {str(p.relative_to(real)): p.read_bytes() for p in real.rglob("*") if p.is_file()} == {"f": b"f", **OUTPUTS}


STOP = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}


@pytest.mark.parametrize("state", ["missing", "non-empty"])
def test_output_directory_renames_with_the_stop_signals_blocked(tmp_path, monkeypatch, state):
    """The final rename(s) happen with SIGINT, SIGTERM and SIGHUP blocked (pthread_sigmask SIG_BLOCK
    before, the old mask restored after), for the one-rename and the merge cases."""
    target = tmp_path / "run"
    if state == "non-empty":
        write_outputs(target, {"keep.txt": b"keep"})
    events = []
    real_mask, real_replace = signal.pthread_sigmask, os.replace

    def mask(how, signals):
        old = real_mask(how, signals)
        events.append(("mask", how, set(signals), set(old)))
        return old

    def replace(src, dst):
        events.append(("replace", Path(dst), STOP <= real_mask(signal.SIG_BLOCK, [])))
        return real_replace(src, dst)

    assert signal.SIGINT not in real_mask(signal.SIG_BLOCK, [])
    monkeypatch.setattr(signal, "pthread_sigmask", mask)
    monkeypatch.setattr(files.os, "replace", replace)
    with output_directory(target, force=True) as staging:
        write_outputs(staging, {"a.txt": b"a", "b.txt": b"b"})
        events.clear()  # only what happens at the end
    monkeypatch.undo()

    kinds = [e[0] for e in events]
    assert kinds[0] == "mask" and kinds[-1] == "mask" and set(kinds[1:-1]) == {"replace"}
    _, how, sigs, old = events[0]
    assert how == signal.SIG_BLOCK and STOP <= sigs and signal.SIGINT not in old
    _, how, sigs, _ = events[-1]
    assert how == signal.SIG_SETMASK and signal.SIGINT not in sigs
    replaced = [e for e in events if e[0] == "replace"]
    assert all(blocked for _, _, blocked in replaced)  # the signals really were blocked during each rename
    expected = [target] if state == "missing" else [target / "a.txt", target / "b.txt"]
    assert sorted(dst for _, dst, _ in replaced) == expected
    assert signal.SIGINT not in real_mask(signal.SIG_BLOCK, [])  # restored
    assert (target / "a.txt").read_bytes() == b"a"


def test_output_directory_dot_in_an_empty_working_directory(tmp_path, monkeypatch):
    """'.' naming an empty working directory is accepted by the checks, so it must end holding the outputs."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert check_output_directory(".", force=False) == Path(".")
    with output_directory(".", force=False) as staging:
        write_outputs(staging, OUTPUTS)
    assert snapshot(work) == expected_tree(OUTPUTS)

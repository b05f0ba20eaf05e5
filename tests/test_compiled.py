"""The kernels' caches (backend.compiled): dropped when a source changed, kept otherwise."""

from __future__ import annotations

import os

import numpy as np

from vislam.backend.compiled import FINGERPRINT, drop_stale_caches


def _caches(root):
    return sorted(p.name for p in root.rglob("*") if p.suffix in (".nbi", ".nbc"))


def test_caches_are_dropped_when_any_source_changed_and_kept_otherwise(tmp_path):
    """numba keys a cache to its own file only; a change of another module (whose kernels it calls)
    must drop it too: every cache under the root goes when any .py file there changed."""
    (tmp_path / "a.py").write_text("x = 1\n")
    sub = tmp_path / "sub"
    (sub / "__pycache__").mkdir(parents=True)
    (sub / "b.py").write_text("y = 2\n")

    def make_caches():
        for name in ("b.f-3.py311.nbi", "b.f-3.py311.2.nbc"):
            (sub / "__pycache__" / name).write_bytes(b"machine code")

    make_caches()
    assert drop_stale_caches(tmp_path) == 2  # no fingerprint yet: caches of unknown sources go
    assert (tmp_path / "__pycache__" / FINGERPRINT).is_file()
    make_caches()
    assert drop_stale_caches(tmp_path) == 0 and len(_caches(tmp_path)) == 2  # nothing changed: kept
    (tmp_path / "a.py").write_text("x = 10\n")  # another module than the cached one
    assert drop_stale_caches(tmp_path) == 2 and _caches(tmp_path) == []
    make_caches()
    st = (sub / "b.py").stat()
    os.utime(sub / "b.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # same size, newer
    assert drop_stale_caches(tmp_path) == 2



_PROBE = '''
import os, time
from vislam.backend.compiled import warms_up

@warms_up
def _warm_up():
    """Stands for a module's kernels: notes which process warmed it up."""
    if __name__ in os.environ.get("PROBE_FAIL", "").split() and os.getpid() == int(os.environ["PROBE_MAIN"]):
        raise KeyboardInterrupt  # a stop while this process compiles
    time.sleep({seconds})
    with open(os.environ["PROBE_LOG"], "a") as log:
        log.write(f"{{__name__}} {{os.getpid()}}\\n")
'''


def _probes(tmp_path, monkeypatch, count=4):
    """``count`` importable modules whose warm-ups log (module, pid), registered here only."""
    import importlib
    import sys

    from vislam.backend import compiled

    monkeypatch.setattr(compiled, "_registered", [])
    monkeypatch.setattr(compiled, "_done", set())
    monkeypatch.syspath_prepend(str(tmp_path))  # a spawned helper gets this process's sys.path
    monkeypatch.setenv("PROBE_LOG", str(tmp_path / "log.txt"))
    monkeypatch.setenv("PROBE_MAIN", str(os.getpid()))
    names = []
    for i in range(count):
        name = f"vislam_probe_{i}"
        (tmp_path / f"{name}.py").write_text(_PROBE.format(seconds=0.5 + 0.1 * i))
        sys.modules.pop(name, None)
        importlib.import_module(name)
        monkeypatch.delitem(sys.modules, name)
        names.append(name)
    return compiled, names


def test_a_first_compile_shares_the_modules_with_a_helper_process(tmp_path, monkeypatch):
    """With nothing cached the modules are compiled here and in one helper process, each module once
    between them; the caller then runs the helper's modules' warm-ups itself (loading their caches)."""
    compiled, names = _probes(tmp_path, monkeypatch)
    compiled._compile_with_a_helper(list(compiled._registered), inertial=False)
    lines = [line.split() for line in (tmp_path / "log.txt").read_text().splitlines()]
    by_module = {}
    for module, pid in lines:
        by_module.setdefault(module, []).append(int(pid))
    assert sorted(by_module) == sorted(names) and all(len(p) == 1 for p in by_module.values())  # each once
    pids = {p[0] for p in by_module.values()}
    assert os.getpid() in pids and len(pids) == 2  # here and in the helper
    mine = {f.__module__ for f in compiled._done}
    assert mine == {m for m, p in by_module.items() if p == [os.getpid()]}  # the helper's are left to the caller


def _children() -> list[int]:
    """The processes whose parent is this one (Linux's /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == os.getpid() and fields[0] != "Z":
                out.append(int(entry))
    return out


def test_a_stop_during_a_first_compile_ends_the_helper(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM (a KeyboardInterrupt here) while this process compiles: the helper process
    is ended with it, none is left behind."""
    import pytest

    compiled, names = _probes(tmp_path, monkeypatch)
    monkeypatch.setenv("PROBE_FAIL", " ".join(names))  # whichever module this process takes first
    before = set(_children())
    with pytest.raises(KeyboardInterrupt):
        compiled._compile_with_a_helper(list(compiled._registered), inertial=False)
    assert set(_children()) <= before


_SCRIPT = """
import os
with open(os.environ["PROBE_TOP"], "a") as top:  # a script's top level, no __main__ guard
    top.write(f"{os.getpid()}\\n")
from vislam.backend import compiled
import vislam_probe_0, vislam_probe_1, vislam_probe_2
compiled._compile_with_a_helper(list(compiled._registered), inertial=False)
"""


def test_a_script_without_a_main_guard_runs_once_while_a_helper_compiles(tmp_path):
    """A user's script calling the API at its top level (no ``if __name__ == "__main__"``) on a first
    run: its top runs once, in its own process, while the modules are still shared with a helper
    process (a multiprocessing child would run the script's top again)."""
    import subprocess
    import sys

    for i in range(3):
        (tmp_path / f"vislam_probe_{i}.py").write_text(_PROBE.format(seconds=0.5 + 0.1 * i))
    (tmp_path / "script.py").write_text(_SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path)] + sys.path), PROBE_LOG=str(tmp_path / "log.txt"),
               PROBE_TOP=str(tmp_path / "top.txt"), PROBE_MAIN="0")
    done = subprocess.run([sys.executable, str(tmp_path / "script.py")], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    tops = (tmp_path / "top.txt").read_text().split()
    assert len(tops) == 1 and "Error" not in done.stderr
    lines = [line.split() for line in (tmp_path / "log.txt").read_text().splitlines()]
    assert sorted(m for m, _ in lines) == [f"vislam_probe_{i}" for i in range(3)]  # each module once
    assert len({pid for _, pid in lines}) == 2 and tops[0] in {pid for _, pid in lines}  # the script and a helper


def test_a_helper_is_used_until_a_whole_warm_up_wrote_its_caches(tmp_path, monkeypatch):
    """The first warm-up after a change (no note of a whole warm-up) compiles with a helper; once every
    kernel but the real IMU's is warmed up the note is written, and later runs just load; a change of a
    source drops the note with the caches."""
    from vislam.backend import compiled

    (tmp_path / "a.py").write_text("x = 1\n")
    drop_stale_caches(tmp_path)
    monkeypatch.setattr(compiled, "CACHE_NOTES", tmp_path / "__pycache__")
    assert compiled._compiling_everything()

    def kernels():
        pass

    def imu_kernels():
        pass

    monkeypatch.setattr(compiled, "_registered", [kernels, imu_kernels])
    monkeypatch.setattr(compiled, "_only", {imu_kernels: "inertial"})
    monkeypatch.setattr(compiled, "_done", set())
    compiled._note_warmed()
    assert compiled._compiling_everything()  # nothing warmed up yet
    compiled._done.add(kernels)
    compiled._note_warmed()
    assert not compiled._compiling_everything()  # the velocity run's kernels are all cached
    (tmp_path / "a.py").write_text("x = 10\n")
    drop_stale_caches(tmp_path)
    assert compiled._compiling_everything()


def _warm_up_in_a_daemonic_worker(conn) -> None:
    from vislam.backend import compiled

    try:
        compiled.warm_up()
        conn.send(("ok", sorted(f.__name__ for f in compiled._done)))
    except Exception as exc:  # noqa: BLE001 (reported to the test)
        conn.send(("failed", repr(exc)))


def test_a_pool_worker_compiling_first_does_not_start_a_helper(monkeypatch):
    """A pool's worker (``vislam mc`` / ``batch`` on a fresh install) is a daemonic process, which may
    not start children: with nothing cached it compiles its kernels itself instead of failing with
    "daemonic processes are not allowed to have children"."""
    import multiprocessing

    from vislam.backend import compiled

    def one():
        pass

    def two():
        pass

    one.__module__, two.__module__ = "vislam.backend.compiled", "vislam.backend.signals"  # two modules
    monkeypatch.setattr(compiled, "_registered", [one, two])
    monkeypatch.setattr(compiled, "_done", set())
    monkeypatch.setattr(compiled, "_compiling_everything", lambda: True)
    monkeypatch.setattr(compiled, "_cores", lambda: 2)
    ctx = multiprocessing.get_context("fork")  # the worker inherits the patched state
    parent, child = ctx.Pipe()
    worker = ctx.Process(target=_warm_up_in_a_daemonic_worker, args=(child,), daemon=True)
    worker.start()
    status, detail = parent.recv()
    worker.join(10)
    assert status == "ok", detail
    assert detail == ["one", "two"]


def test_numbas_llvm_lock_events_are_dropped():
    """Importing the kernels' module unregisters numba's per-LLVM-call event callbacks (start-up: a
    process loading its cached kernels makes thousands of LLVM calls); the kernels still run."""
    from llvmlite.binding import ffi

    from vislam.backend import compiled
    from vislam.backend.geometry.camera import triangulate_rows

    assert not any(getattr(a, "__module__", None) == "numba.core.base" for a, _ in ffi.lib._lock._cblist)
    assert compiled._drop_llvm_lock_events() is False  # nothing left to drop
    points, _ = triangulate_rows(np.array([[600.0, 180.0, 560.0, 180.0]] * 2), 700.0, 700.0, 600.0, 180.0, 0.5, 0.0)
    np.testing.assert_allclose(points[:, 2], 700.0 * 0.5 / 40.0)  # depth = fx b / disparity

"""The kernels' caches (backend.compiled): dropped when a source changed, kept otherwise."""

from __future__ import annotations

import os

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


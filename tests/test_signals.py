"""Whole ``vislam`` processes stopped by a signal: SIGTERM and SIGHUP are handled like Ctrl-C.

Each case starts the console entry point, waits until its staging directory exists (the checks
passed, the work is under way), sends the signal to the ``vislam`` process alone (as ``kill PID``
does) and checks: the exit code 128 + the signal's number, one last line naming the signal, no
output and no temporary name left, and no worker process alive afterwards."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers import street_file
from vislam.tools.cli import main

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads process parents from /proc (Linux)")


@pytest.fixture(scope="module")
def long_file(tmp_path_factory) -> Path:
    return street_file(tmp_path_factory.mktemp("long"), 1500)


def leftovers(folder: Path) -> list[str]:
    """Temporary names left anywhere under ``folder`` (staging directories, half files)."""
    return [str(p.relative_to(folder)) for p in folder.rglob("*") if ".tmp-" in p.name]


def children(pid: int) -> set[int]:
    """The live processes whose parent is ``pid`` (from /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # gone meanwhile
            continue
        fields = text.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            found.add(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


def still_alive(pids: set[int], wait: float = 10.0) -> list[int]:
    """The processes among ``pids`` still alive after up to ``wait`` seconds."""
    deadline = time.monotonic() + wait
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return [pid for pid in pids if alive(pid)]


def interrupt(args: list[str], folder: Path, signum: int, workers: int = 0) -> tuple[int, str, set[int]]:
    """Run ``vislam ARGS`` in ``folder``; once its staging directory exists (and ``workers`` children
    run), send ``signum``. (exit code, stderr, the children seen before the signal)."""
    proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "vislam.tools.cli", *args], cwd=folder,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    seen: set[int] = set()
    while proc.poll() is None and time.monotonic() < deadline:
        seen |= children(proc.pid)
        if leftovers(folder) and len(seen) >= workers:
            break
        time.sleep(0.05)
    time.sleep(0.3)
    seen |= children(proc.pid)
    assert proc.poll() is None, "the command ended before the signal: the case no longer tests an interruption"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err, seen


def assert_clean_stop(rc: int, err: str, signum: int, folder: Path, seen: set[int]) -> None:
    assert rc == 128 + signum, err
    name = signal.Signals(signum).name
    assert err.strip().splitlines()[-1] == f"vislam: interrupted ({name})" and "Traceback" not in err, err
    assert not leftovers(folder), leftovers(folder)
    assert not still_alive(seen), "worker processes outlived the command"


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_run_stopped_by_a_signal_leaves_no_output(long_file, tmp_path, signum):
    rc, err, seen = interrupt(["run", str(long_file), "--out", "out", "--quiet"], tmp_path, signum)
    assert_clean_stop(rc, err, signum, tmp_path, seen)
    assert not (tmp_path / "out").exists()


def test_sigterm_with_force_keeps_the_previous_outputs(long_file, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "trajectory.txt").write_text("the previous run's")
    rc, err, seen = interrupt(["run", str(long_file), "--out", "out", "--quiet", "--force"], tmp_path, signal.SIGTERM)
    assert_clean_stop(rc, err, signal.SIGTERM, tmp_path, seen)
    assert [p.name for p in out.iterdir()] == ["trajectory.txt"]
    assert (out / "trajectory.txt").read_text() == "the previous run's"


def test_an_image_run_stopped_by_sigterm_leaves_no_output(tmp_path_factory, tmp_path):
    scene = tmp_path_factory.mktemp("render") / "street"
    assert main(["synth", "--scenario", "street", "--steps", "80", "--seed", "3", "--out", str(scene), "--render",
                 "--quiet"]) == 0
    rc, err, seen = interrupt(["run", str(scene), "--imu", str(scene / "data.npz"), "--out", "out", "--quiet"],
                              tmp_path, signal.SIGTERM)
    assert_clean_stop(rc, err, signal.SIGTERM, tmp_path, seen)
    assert not (tmp_path / "out").exists()


def _pool_command(name: str, long_file: Path) -> list[str]:
    """A batch or mc run on a pool of two workers, long enough to be interrupted."""
    if name == "batch":
        return ["batch", str(long_file), "--vary", "noise.pixel_sigma=1,1.5,2,2.5", "--workers", "2", "--out", "out",
                "--quiet"]
    return ["mc", "--runs", "40", "--steps", "300", "--workers", "2", "--out", "out", "--quiet"]


@pytest.mark.parametrize("command", ["batch", "mc"])
def test_a_pool_command_stopped_by_sigterm_stops_its_workers(command, long_file, tmp_path):
    rc, err, seen = interrupt(_pool_command(command, long_file), tmp_path, signal.SIGTERM, workers=2)
    assert len(seen) >= 2, "the pool's workers were never seen"
    assert_clean_stop(rc, err, signal.SIGTERM, tmp_path, seen)
    assert not (tmp_path / "out").exists()


def test_a_killed_batch_leaves_no_worker(long_file, tmp_path):
    """SIGKILL cannot be handled: its staging directory stays, but the kernel stops the workers."""
    rc, err, seen = interrupt(_pool_command("batch", long_file), tmp_path, signal.SIGKILL, workers=2)
    assert rc == -signal.SIGKILL and len(seen) >= 2
    assert not still_alive(seen), "workers outlived a killed parent"


def test_finalizers_of_interrupted_work_stay_quiet_and_others_do_not(monkeypatch):
    """After a stop signal, what a finalizer of the interrupted work raises (a ZipFile closed half-way
    while map.npz was written) is not reported; before one, it goes to the hook Python reports with."""
    from vislam.tools import console

    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda unraisable: reported.append(str(unraisable.exc_value)))

    class Broken:
        def __del__(self):
            raise ValueError("seek of closed file")

    with console.interrupt_handler() as interrupted:
        Broken()
        assert reported == ["seek of closed file"]
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGTERM)
            time.sleep(1)
        assert interrupted() and console.interrupted_exit_code() == 143
        assert console.interrupted_text() == "interrupted (SIGTERM)"
        Broken()
        assert reported == ["seek of closed file"]
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the handler before is back


def test_a_stop_another_thread_receives_waits_for_the_held_block():
    """Blocking reaches the main thread only: a SIGTERM sent to the process while the main thread is
    in a held block (numba loading a kernel) goes to another thread that does not block it (the
    compile notice's timer), and Python runs the handler in the main thread at once. The handler
    leaves it to the block, which finishes its work and raises it on the way out: exit as a stop,
    never a KeyboardInterrupt inside numba (a crash later)."""
    import os
    import threading

    from vislam.backend import signals
    from vislam.tools import console

    other = threading.Thread(target=time.sleep, args=(3.0,), daemon=True)  # its mask: nothing blocked
    other.start()
    done = []
    with console.interrupt_handler():
        with pytest.raises(KeyboardInterrupt):
            with signals.held():
                os.kill(os.getpid(), signal.SIGTERM)  # the process: the kernel picks the other thread
                for _ in range(50):  # bytecode boundaries, where the main thread runs the handler
                    time.sleep(0.01)
                done.append("the held work")
        assert console.interrupted_text() == "interrupted (SIGTERM)"
    assert done == ["the held work"]


def test_a_finished_run_leaves_no_process_behind(tmp_path):
    """A run that ends by itself has ended and reaped every process it started (the output and
    compile helpers, multiprocessing's resource tracker) by the time it exits: the moment it has
    exited, its process group (its own session) is empty, with no orphan still running or waiting to
    be reaped."""
    data = street_file(tmp_path, 200)
    proc = subprocess.Popen([sys.executable, "-m", "vislam.tools.cli", "run", str(data), "--out", "out", "--quiet"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    seen: set[int] = set()
    while proc.poll() is None:
        seen |= children(proc.pid)
        time.sleep(0.02)
    assert proc.returncode == 0, proc.stderr.read()
    assert seen, "no helper process was seen: the case no longer tests what a run leaves"
    try:
        os.killpg(proc.pid, 0)
        left = True
    except ProcessLookupError:
        left = False
    assert not left, "a process of the run's group outlived it"

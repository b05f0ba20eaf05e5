"""Hostile input and interruptions through the command line: each case is refused in one line with
exit 2, handled, or reported as a health warning; Ctrl-C exits 130 and leaves a complete output
set or none; nothing that is not a regular file is replaced."""

from __future__ import annotations

import builtins
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import street_file
from vislam.backend.data.npz import load_sequence, save_sequence
from vislam.backend.data.tum import write_tum
from vislam.backend.errors import VislamError
from vislam.backend.run import runner
from vislam.synth.scene import SceneConfig, make_scene
from vislam.tools import outputs
from vislam.tools.cli import EXIT_INTERRUPTED, EXIT_USAGE, main


@pytest.fixture(scope="module")
def scene():
    return make_scene(SceneConfig(steps=60, landmark_density=0.5))


@pytest.fixture(scope="module")
def arrays(scene, tmp_path_factory) -> dict:
    """The scene as the course's dense arrays (layout 2022)."""
    path = tmp_path_factory.mktemp("scene") / "scene.npz"
    save_sequence(scene.sequence, path, dense=True)
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def write(folder: Path, arrays: dict, name: str = "data.npz", **changes) -> Path:
    path = folder / name
    np.savez(path, **{**arrays, **changes})
    return path


def leftovers(folder: Path) -> list[str]:
    """Temporary names left beside the outputs (staging directories, half files)."""
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name]


def one_line_error(capsys, *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("vislam: error: "), err
    for needle in needles:
        assert needle in err, err
    return err


def never_called(*args, **kwargs):
    raise AssertionError("the run started although the input should have been refused first")


# ------------------------------------------------------------------------------------------------
# 1. vision that does nothing is reported, not presented as SLAM


def _rectification_broken(a):
    f = a["features"].copy()
    seen = f[0] != -1
    f[3][seen] += 30.0  # the right image 30 px lower: not rectified
    return {"features": f}


def _zero_disparity(a):
    f = a["features"].copy()
    seen = f[0] != -1
    f[2][seen] = f[0][seen]
    return {"features": f}


HOSTILE_VISION = {
    "every-feature-minus-1": lambda a: {"features": np.full_like(a["features"], -1.0)},
    "no-features": lambda a: {"features": np.zeros((4, 0, a["features"].shape[2]))},
    "zero-disparity": _zero_disparity,
    "velocity-1e6": lambda a: {"linear_velocity": np.full_like(a["linear_velocity"], 1e6)},
    "angular-rate-1000": lambda a: {"angular_velocity": np.full_like(a["angular_velocity"], 1000.0)},
    "unrectified": _rectification_broken,
}


@pytest.mark.parametrize("case", sorted(HOSTILE_VISION))
def test_vision_that_did_nothing_is_a_health_warning(arrays, tmp_path, capsys, case):
    path = write(tmp_path, arrays, **HOSTILE_VISION[case](arrays))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    said = [m for m in summary["health"] if "dead reckoning" in m]
    assert said, summary["health"]
    captured = capsys.readouterr()
    assert any(m in captured.out + captured.err for m in said)  # on screen too, even with --quiet


def test_a_pixel_sigma_that_gates_everything_is_a_health_warning(arrays, tmp_path, capsys):
    path = write(tmp_path, arrays)
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--set", "noise.pixel_sigma=1e-300"]) == 0
    health = json.loads((tmp_path / "out" / "summary.json").read_text())["health"]
    assert any("dead reckoning" in m for m in health), health


def test_a_sound_run_has_no_dead_reckoning_warning(scene, arrays, tmp_path):
    path = write(tmp_path, arrays)
    config = tmp_path / "scene.toml"
    config.write_text(scene.config.filter_config().to_toml())
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--config", str(config)]) == 0
    health = json.loads((tmp_path / "out" / "summary.json").read_text())["health"]
    assert not any("dead reckoning" in m for m in health), health


def test_mc_without_landmarks_warns(capsys, tmp_path):
    assert main(["mc", "--runs", "2", "--steps", "30", "--workers", "1", "--landmark-density", "0",
                 "--out", str(tmp_path / "mc")]) == 0
    out = capsys.readouterr().out
    assert "warning (2 of 2 runs): no valid stereo observation in the input" in out, out


# ------------------------------------------------------------------------------------------------
# 2. Ctrl-C and failures: a complete output set or none


def _raise(exc: BaseException):
    def fail(*args, **kwargs):
        raise exc
    return fail


def _wrapped_interrupt(kind):
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as e:
        try:
            raise kind("interrupted in compiled code or an import") from e
        except kind as wrapped:
            return wrapped


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), "SystemError", "ImportError"])
def test_ctrl_c_during_the_run_exits_130_and_leaves_nothing(arrays, tmp_path, capsys, monkeypatch, exc):
    """numba re-raises Ctrl-C as a SystemError, an interrupted import as an ImportError: both are Ctrl-C."""
    if isinstance(exc, str):
        exc = _wrapped_interrupt(getattr(builtins, exc))
    path = write(tmp_path, arrays)
    monkeypatch.setattr(runner, "run_sequence", _raise(exc))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == EXIT_INTERRUPTED
    assert capsys.readouterr().err.strip() == "vislam: interrupted"
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path)


def test_a_ctrl_c_swallowed_by_a_finalizer_still_stops_the_run(arrays, tmp_path, capsys, monkeypatch):
    """SIGINT inside a __del__ (as in llvmlite's objects while numba compiles) is printed as "ignored"
    by Python and the work goes on; the next progress callback stops it, quietly."""
    path = write(tmp_path, arrays)
    steps = []

    class Finalizer:
        def __del__(self):
            signal.raise_signal(signal.SIGINT)
            sum(range(1000))  # the handler runs here, inside the finalizer

    def run(seq, config, progress=None, **kwargs):
        Finalizer()  # deleted at once
        steps.append("after the swallowed interrupt")
        progress(0)
        steps.append("not reached")

    monkeypatch.setattr(runner, "run_sequence", run)
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == EXIT_INTERRUPTED
    assert steps == ["after the swallowed interrupt"]
    assert capsys.readouterr().err.strip() == "vislam: interrupted"  # no "Exception ignored" traceback
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path)


def test_ctrl_c_while_writing_leaves_no_partial_set_and_no_blocking_directory(arrays, tmp_path, capsys, monkeypatch):
    path = write(tmp_path, arrays)
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(outputs, "write_json", _raise(KeyboardInterrupt()))  # summary.json comes after the trajectories
        assert main(["run", str(path), "--out", str(out), "--quiet"]) == EXIT_INTERRUPTED
    assert not out.exists() and not leftovers(tmp_path)
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0  # nothing blocks a re-run without --force
    assert {"summary.json", "config.toml", "trajectory.txt", "map.npz"} <= {p.name for p in out.iterdir()}


def test_ctrl_c_with_force_keeps_the_previous_outputs(arrays, tmp_path, monkeypatch):
    path = write(tmp_path, arrays)
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(outputs, "write_json", _raise(KeyboardInterrupt()))
    assert main(["run", str(path), "--out", str(out), "--quiet", "--force"]) == EXIT_INTERRUPTED
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before and not leftovers(tmp_path)


def test_a_failed_run_leaves_nothing(arrays, tmp_path, capsys, monkeypatch):
    path = write(tmp_path, arrays)
    monkeypatch.setattr(runner, "run_sequence", _raise(VislamError("something went wrong")))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "something went wrong")
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path)


def test_a_full_disk_is_one_line_and_leaves_nothing(arrays, tmp_path, capsys, monkeypatch):
    import errno

    path = write(tmp_path, arrays)
    monkeypatch.setattr(outputs, "write_json", _raise(OSError(errno.ENOSPC, "No space left on device")))
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "No space left on device")
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path)


@pytest.fixture(scope="module")
def long_file(tmp_path_factory) -> Path:
    return street_file(tmp_path_factory.mktemp("long"), 1500)


def test_a_real_sigint_during_the_filter(long_file, tmp_path):
    """The console entry point under a real SIGINT: exit 130, one line, no output, no staging directory."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "vislam.tools.cli", "run", str(long_file), "--out", str(out),
                             "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not leftovers(tmp_path) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # the staging directory exists once the checks passed, before the filter starts
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert err.strip().splitlines()[-1] == "vislam: interrupted" and "Traceback" not in err, err
    assert not out.exists() and not leftovers(tmp_path)


# ------------------------------------------------------------------------------------------------
# 4. writers never replace what is not a regular file


@pytest.fixture(scope="module")
def trajectories(scene, tmp_path_factory):
    folder = tmp_path_factory.mktemp("tum")
    seq = scene.sequence
    write_tum(folder / "est.txt", seq.time_stamps, scene.world_T_imu_true)
    write_tum(folder / "gt.txt", seq.time_stamps, scene.world_T_imu_true)
    return folder / "est.txt", folder / "gt.txt"


def test_eval_json_onto_a_symlink_or_fifo_is_refused_and_left_alone(trajectories, tmp_path, capsys):
    target = tmp_path / "real.json"
    target.write_text("keep")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path, what in ((link, "symbolic link"), (fifo, "FIFO"), (tmp_path, "directory")):
        assert main(["eval", *map(str, trajectories), "--json", str(path)]) == EXIT_USAGE
        one_line_error(capsys, str(path), what)
    assert link.is_symlink() and os.readlink(link) == str(target) and target.read_text() == "keep"
    assert fifo.is_fifo()


def test_eval_json_under_a_missing_directory_is_refused(trajectories, tmp_path, capsys):
    assert main(["eval", *map(str, trajectories), "--json", str(tmp_path / "no" / "e.json")]) == EXIT_USAGE
    one_line_error(capsys, "does not exist")


def test_output_directory_that_cannot_be_made_is_refused_before_the_run(arrays, tmp_path, capsys, monkeypatch):
    path = write(tmp_path, arrays)
    monkeypatch.setattr(runner, "run_sequence", never_called)
    assert main(["run", str(path), "--out", str(path / "out"), "--quiet"]) == EXIT_USAGE  # under a regular file
    one_line_error(capsys, "data.npz is not a directory")
    assert main(["run", str(path), "--out", "", "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "empty")


# ------------------------------------------------------------------------------------------------
# 5. implausible scales


@pytest.mark.parametrize("change, needle", [
    (lambda a: {"time_stamps": (a["time_stamps"] * 1e9).astype(np.int64) + 1_700_000_000_000_000_000},
     "nanoseconds"),
    (lambda a: {"time_stamps": a["time_stamps"] + np.where(np.arange(a["time_stamps"].size) >= 30, 1e6, 0.0)},
     "gap of"),
    (lambda a: {"K": a["K"] + np.array([[0, 100.0, 0], [0, 0, 0], [0, 0, 0]])}, "skew"),
    (lambda a: {"time_stamps": a["time_stamps"][:, :1], "features": a["features"][:, :, :1],
                "linear_velocity": a["linear_velocity"][:, :1], "angular_velocity": a["angular_velocity"][:, :1]},
     "at least 2 steps"),
])
def test_implausible_input_is_refused_by_check_and_run_alike(arrays, tmp_path, capsys, monkeypatch, change, needle):
    path = write(tmp_path, arrays, **change(arrays))
    monkeypatch.setattr(runner, "run_sequence", never_called)
    assert main(["check", str(path)]) == EXIT_USAGE
    one_line_error(capsys, "data.npz", needle)
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "data.npz", needle)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------------
# 6. reasonable input accepted


def _typed(T: np.ndarray, decimals: int) -> np.ndarray:
    return np.round(T, decimals)


@pytest.mark.parametrize("decimals", [5, 3])
def test_a_rotation_typed_to_few_decimals_is_accepted_and_reported(arrays, tmp_path, capsys, decimals):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [-91.3, 0.7, -88.1], degrees=True).as_matrix()
    T[:3, 3] = [0.3, -0.07, 1.08]
    typed = _typed(T, decimals)
    assert np.abs(typed[:3, :3].T @ typed[:3, :3] - np.eye(3)).max() > 1e-6  # not orthonormal as typed
    path = write(tmp_path, arrays, imu_T_cam=typed)
    seq = load_sequence(path)
    R = seq.imu_T_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(seq.imu_T_cam, typed, atol=10.0 ** -decimals)  # the nearest rotation
    assert seq.notes and "re-orthonormalized" in seq.notes[0]
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert any("re-orthonormalized" in n for n in json.loads((tmp_path / "out" / "summary.json").read_text())["notes"])


def test_a_rotation_far_from_orthonormal_is_refused_with_the_number(arrays, tmp_path, capsys):
    T = np.eye(4)
    T[0, 1] = 0.01
    path = write(tmp_path, arrays, imu_T_cam=T)
    assert main(["check", str(path)]) == EXIT_USAGE
    one_line_error(capsys, "imu_T_cam", "0.01")


def test_the_imu_t_cam_text_typed_to_5_decimals_is_accepted_with_a_note(tmp_path):
    from scipy.spatial.transform import Rotation

    from vislam.frontend.imu_input import read_imu

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [12.3, -45.6, 78.9], degrees=True).as_matrix()
    ext = tmp_path / "imu_T_cam.txt"
    ext.write_text("\n".join(" ".join(f"{v:.5f}" for v in row) for row in T) + "\n")
    csv = tmp_path / "imu.csv"
    csv.write_text("".join(f"{0.1 * i},1,0,0,0,0,0\n" for i in range(3)))
    imu = read_imu(csv, 3, ext)
    np.testing.assert_allclose(imu.imu_T_cam[:3, :3].T @ imu.imu_T_cam[:3, :3], np.eye(3), atol=1e-12)
    assert any("re-orthonormalized" in n and "imu_T_cam.txt" in n for n in imu.notes)


def test_both_layouts_that_agree_are_read(arrays, tmp_path):
    path = write(tmp_path, arrays, rotational_velocity=arrays["angular_velocity"],
                 cam_T_imu=np.linalg.inv(arrays["imu_T_cam"]))
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.angular_velocity, arrays["angular_velocity"].T)
    assert any("both layouts" in n for n in seq.notes)


def test_a_features_member_in_npy_format_3_is_read(arrays, tmp_path):
    import zipfile

    from numpy.lib import format as npformat

    path = tmp_path / "v3.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in arrays.items():
            with zf.open(key + ".npy", "w") as member:
                npformat.write_array(member, np.asarray(value), version=(3, 0) if key == "features" else None)
    seq = load_sequence(path)
    reference = load_sequence(write(tmp_path, arrays))
    np.testing.assert_array_equal(seq.obs_pixels, reference.obs_pixels)


# ------------------------------------------------------------------------------------------------
# 7. refusals instead of tracebacks


@pytest.mark.parametrize("delta", ["0", "-5", "nan", "inf"])
def test_eval_delta_must_be_positive(trajectories, capsys, delta):
    assert main(["eval", *map(str, trajectories), f"--delta={delta}"]) == EXIT_USAGE
    one_line_error(capsys, "--delta")


def _config_dir(tmp_path: Path) -> Path:
    folder = tmp_path / "conf.d"
    folder.mkdir()
    return folder


def _config_latin1(tmp_path: Path) -> Path:
    path = tmp_path / "latin1.toml"
    path.write_bytes('[noise]\n# caf\xe9\npixel_sigma = 1.0\n'.encode("latin-1"))
    return path


@pytest.mark.parametrize("make, needle", [(_config_dir, "is a directory"), (_config_latin1, "not UTF-8")])
@pytest.mark.parametrize("command", ["run", "mc", "track"])
def test_an_unreadable_config_file_is_one_line(arrays, tmp_path, capsys, monkeypatch, make, needle, command):
    config = make(tmp_path)
    data = write(tmp_path, arrays)
    monkeypatch.setattr(runner, "run_sequence", never_called)
    argv = {"run": ["run", str(data), "--out", str(tmp_path / "out"), "--quiet"],
            "mc": ["mc", "--runs", "1", "--steps", "10", "--workers", "1", "--out", str(tmp_path / "out")],
            "track": ["track", str(tmp_path), "--imu", str(data), "--out", str(tmp_path / "t.npz"), "--quiet"]}[command]
    assert main([*argv, "--config", str(config)]) == EXIT_USAGE
    one_line_error(capsys, str(config), needle)
    assert not (tmp_path / "out").exists() and not (tmp_path / "t.npz").exists()


def test_track_out_onto_a_directory_is_refused_even_with_force(arrays, tmp_path, capsys):
    data = write(tmp_path, arrays)
    (tmp_path / "out.npz").mkdir()
    assert main(["track", str(tmp_path), "--imu", str(data), "--out", str(tmp_path / "out.npz"), "--force",
                 "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "out.npz", "directory")


@pytest.mark.parametrize("flag", ["--draw", "--imu", "--imu-T-cam"])
def test_image_only_flags_with_a_feature_file_are_refused(arrays, tmp_path, capsys, flag):
    data = write(tmp_path, arrays)
    assert main(["run", str(data), "--out", str(tmp_path / "out"), "--quiet", flag, str(tmp_path / "x")]) == EXIT_USAGE
    one_line_error(capsys, flag, "image directory")


# ------------------------------------------------------------------------------------------------
# 8. memory bounded before allocating


def test_mc_refuses_a_landmark_density_beyond_memory(tmp_path, capsys):
    assert main(["mc", "--runs", "1", "--steps", "300", "--workers", "1", "--landmark-density", "1e6",
                 "--out", str(tmp_path / "mc")]) == EXIT_USAGE
    one_line_error(capsys, "landmark_density", "GiB")
    assert not (tmp_path / "mc").exists()


# ------------------------------------------------------------------------------------------------
# 9. clear and consistent messages


def test_an_unreadable_file_says_so(arrays, tmp_path, capsys, monkeypatch):
    from vislam.backend.data import npz as npz_mod

    path = write(tmp_path, arrays)

    def denied(file, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(file))

    monkeypatch.setattr(npz_mod, "open", denied, raising=False)  # root reads a chmod 000 file anyway
    assert main(["check", str(path)]) == EXIT_USAGE
    err = one_line_error(capsys, "data.npz", "Permission denied")
    assert "zip" not in err


def test_cx_zero_names_the_options_to_set(arrays, tmp_path, capsys):
    K = arrays["K"].copy()
    K[0, 2] = 0.0
    path = write(tmp_path, arrays, K=K)
    assert main(["check", str(path)]) == EXIT_USAGE
    one_line_error(capsys, "input.image_width", "input.image_height")


def test_ground_truth_that_does_not_match_is_refused_before_the_run(arrays, scene, tmp_path, capsys, monkeypatch):
    path = write(tmp_path, arrays)
    gt = tmp_path / "other_gt.txt"
    write_tum(gt, scene.sequence.time_stamps + 1000.0, scene.world_T_imu_true)
    monkeypatch.setattr(runner, "run_sequence", never_called)
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--gt", str(gt), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "other_gt.txt", "ground-truth stamp")
    assert main(["eval", str(gt), str(tmp_path / "no.txt")]) == EXIT_USAGE  # eval names its missing file too
    one_line_error(capsys, "no.txt")


def test_a_one_frame_image_directory_is_refused(tmp_path, capsys):
    for side in ("image_0", "image_1"):
        (tmp_path / side).mkdir()
        (tmp_path / side / "000000.png").write_bytes(b"")
    assert main(["track", str(tmp_path), "--imu", "x.csv", "--out", str(tmp_path / "t.npz"), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, "image_0", "at least 2")


# ------------------------------------------------------------------------------------------------
# sizes checked before any work; files that are not regular files refused, not read


@pytest.mark.parametrize("argv, needle", [
    (["synth", "--steps", "100000000"], "steps must be an integer from 2 to"),
    (["synth", "--steps", str(2**70)], "steps must be an integer from 2 to"),
    (["mc", "--steps", "1000000000"], "steps must be an integer from 2 to"),
    (["mc", "--runs", "1000000000"], "--runs must be from 1 to"),
])
def test_sizes_that_would_exhaust_memory_are_refused_before_any_work(argv, needle, tmp_path, capsys):
    assert main([*argv, "--out", str(tmp_path / "o")]) == EXIT_USAGE
    one_line_error(capsys, needle)
    assert not (tmp_path / "o").exists()


def test_a_fifo_or_a_device_as_config_or_ground_truth_is_refused_without_reading(arrays, tmp_path, capsys):
    """A FIFO would block the read until Ctrl-C and /dev/zero never ends: both are refused by type."""
    path = write(tmp_path, arrays)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for flag, target, what in (("--config", fifo, "FIFO"), ("--gt", fifo, "FIFO"),
                               ("--config", Path("/dev/zero"), "character device")):
        assert main(["run", str(path), "--out", str(tmp_path / "o"), flag, str(target), "--quiet"]) == EXIT_USAGE
        one_line_error(capsys, str(target), what, "not a regular file")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, needle", [
    ("[noise]\npixel_sigma = 1e308\n", "out of range"),
    ("a = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
    ("[noise]\npixel_sigma = '" + "9" * (2**20) + "'\n", "MiB"),
])
def test_configs_that_overflow_recurse_or_are_huge_are_one_line(arrays, tmp_path, capsys, text, needle):
    path = write(tmp_path, arrays)
    config = tmp_path / "c.toml"
    config.write_text(text)
    assert main(["run", str(path), "--out", str(tmp_path / "o"), "--config", str(config), "--quiet"]) == EXIT_USAGE
    err = one_line_error(capsys, str(config), needle)
    assert len(err) < 300  # the value is not echoed whole


def test_out_as_a_link_to_an_empty_folder_is_written_through_and_a_file_is_named_so(arrays, tmp_path, capsys):
    path = write(tmp_path, arrays)
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    assert main(["run", str(path), "--out", str(tmp_path / "link"), "--quiet"]) == 0
    assert (real / "trajectory.txt").is_file() and (tmp_path / "link").is_symlink()
    assert not leftovers(tmp_path) and not leftovers(real)
    plain = tmp_path / "plain"
    plain.write_text("keep")
    assert main(["run", str(path), "--out", str(plain), "--quiet"]) == EXIT_USAGE
    one_line_error(capsys, str(plain), "is a regular file, not a directory")
    assert plain.read_text() == "keep"

"""Frames per second of the stereo tracker (frontend.tracker) at 1241 x 376, 300 target tracks.

    python benchmarks/bench_tracker.py                 # from the project root
    python benchmarks/bench_tracker.py --repeat 5 --threads 1

Inputs: the 51 real KITTI pairs of ../shared/images (skipped if absent) and a rendered street
(synth, default scene, seed 0). Images are decoded (or rendered) before timing; "tracker" is the
time of StereoTracker.step alone, "with PNG decoding" the whole iter_tracks loop over the files
(frames decoded on a worker thread while the previous one is tracked). Each number is the median
of --repeat runs. Prints a markdown table and the command line.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from vislam.backend.options import parse_assignment
from vislam.frontend.config import TrackerConfig
from vislam.frontend.images import open_stereo_directory
from vislam.frontend.track import iter_tracks, opencv_threads
from vislam.frontend.tracker import StereoTracker

KITTI = ROOT.parent / "shared" / "images" / "kitti_odom01_f000000-000050"


def time_tracker(pairs, K, baseline, config: TrackerConfig) -> tuple[float, float, float]:
    """(frames per second, mean tracks per frame, 90th percentile ms per frame) of one run."""
    tracker = StereoTracker(config, K, baseline)
    counts, times = [], []
    with opencv_threads(config.threads):
        start = time.perf_counter()
        for left, right in pairs:
            t = time.perf_counter()
            ids, _ = tracker.step(left, right)
            times.append(time.perf_counter() - t)
            counts.append(ids.size)
        total = time.perf_counter() - start
    return len(pairs) / total, float(np.mean(counts)), float(np.percentile(times, 90) * 1e3)


def time_directory(directory, config: TrackerConfig) -> float:
    """Frames per second of iter_tracks over the PNG files (decoding included)."""
    start = time.perf_counter()
    n = sum(1 for _ in iter_tracks(directory, config))
    return n / (time.perf_counter() - start)


def rendered_street(frames: int):
    from vislam.synth.render import RENDER_STREAM, build_street_planes, render_pair
    from vislam.synth.scene import SceneConfig, make_scene

    scene = make_scene(SceneConfig(steps=frames, seed=0))
    cal = scene.config.calibration
    planes = build_street_planes(scene.world_T_imu_true, np.random.default_rng([0, RENDER_STREAM]))
    render_pair(planes, scene.world_T_imu_true[0], cal)  # textures built and cached before the timing
    start = time.perf_counter()
    pairs = [render_pair(planes, T, cal) for T in scene.world_T_imu_true]
    render_fps = len(pairs) / (time.perf_counter() - start)
    return scene, pairs, np.asarray(cal.K, dtype=float), float(cal.baseline), render_fps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per input (median reported)")
    parser.add_argument("--frames", type=int, default=50, help="frames of the rendered street")
    parser.add_argument("--threads", type=int, default=None, help="cv2.setNumThreads (default: the config's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="tracker option (a key of [tracker])")
    args = parser.parse_args(argv)
    values = dict(parse_assignment(a) for a in args.set + ([f"threads={args.threads}"] if args.threads else []))
    config = TrackerConfig.from_values(values)

    rows = []

    def run(name, pairs, K, baseline, directory=None):
        runs = [time_tracker(pairs, K, baseline, config) for _ in range(args.repeat)]
        fps, tracks, p90 = (float(np.median([r[i] for r in runs])) for i in range(3))
        full = float(np.median([time_directory(directory, config) for _ in range(args.repeat)])) if directory else None
        rows.append((name, len(pairs), tracks, fps, 1e3 / fps, p90, full))

    if KITTI.is_dir():
        stereo = open_stereo_directory(KITTI)
        pairs = [(left, right) for _, left, right in stereo.frames(prefetch=False)]
        run("KITTI odometry 01, frames 0-50 (real)", pairs, stereo.K, stereo.baseline, stereo)
    else:
        print(f"real images not found at {KITTI}: skipped", file=sys.stderr)

    scene, pairs, K, baseline, render_fps = rendered_street(args.frames)
    with tempfile.TemporaryDirectory() as tmp:
        from vislam.synth.render import write_kitti_sequence

        directory = write_kitti_sequence(Path(tmp) / "street", scene)
        run(f"rendered street, seed 0 ({args.frames} frames)", pairs, K, baseline, directory)

    command = "python benchmarks/bench_tracker.py " + " ".join(argv if argv is not None else sys.argv[1:])
    cpu = f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}"
    print(f"Tracker speed at 1241 x 376, target {config.target_tracks} tracks, cv2.setNumThreads({config.threads}), "
          f"OpenCV {cv2.__version__}, {cpu}; median of {args.repeat} runs.\n")
    print("| input | frames | tracks / frame | tracker fps | ms / frame | p90 ms | fps with PNG decoding |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, n, tracks, fps, ms, p90, full in rows:
        full_text = "-" if full is None else f"{full:.1f}"
        print(f"| {name} | {n} | {tracks:.0f} | {fps:.1f} | {ms:.1f} | {p90:.1f} | {full_text} |")
    print(f"\nStereo renderer (synth.render.render_pair, the same {args.frames} frames, 1241 x 376): {render_fps:.1f} pairs/s.")
    print(f"\n`{command.strip()}`")
    return 0


if __name__ == "__main__":
    sys.exit(main())

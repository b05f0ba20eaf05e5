"""ROS bags: read speed of ``frontend.bag`` and whole ``vislam run`` processes on bags of the EuRoC
slice (ROS 1, ROS 2; raw and PNG-compressed images, every IMU sample of the flight), against the
same run on its ASL folder; and a bag of a synthetic inertial drive with rendered images, run end to
end against its ground-truth topic.

    python benchmarks/bags.py          (needs ../shared/euroc and rosbags)

Prints a Markdown table for BENCHMARKS.md.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from bags import euroc_messages, synthetic_street_bag, write_bag, write_camchain, write_kalibr_imu  # noqa: E402

from vislam.backend.data.tum import read_tum  # noqa: E402
from vislam.frontend.bag import open_bag  # noqa: E402
from vislam.frontend.euroc import read_euroc  # noqa: E402

MAV0 = Path(__file__).resolve().parents[1].parent / "shared" / "euroc" / "V1_01_easy_first40" / "mav0"
REPEATS = 3
SYNTHETIC_SECONDS = 10.0


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.iterdir())


def _run(args: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "vislam.tools.cli", "run", *args, "--quiet", "--force"], check=True)
    return time.perf_counter() - t0


def main() -> None:
    data = read_euroc(MAV0)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        calib = write_camchain(root / "camchain.yaml", data)
        imu_calib = write_kalibr_imu(root / "imu.yaml", data.imu.samples.noise)
        bags = {"ROS 1, raw mono8": write_bag(root / "raw.bag", euroc_messages(data, True), True),
                "ROS 2 (sqlite3), raw mono8": write_bag(root / "raw_ros2", euroc_messages(data, False), False),
                "ROS 1, PNG": write_bag(root / "png.bag", euroc_messages(data, True, "png"), True)}
        folder = _run([str(MAV0), "--out", str(root / "asl")])
        _, asl = read_tum(root / "asl" / "trajectory.txt")
        print("| bag | size MB | open: stamps and IMU s | pairs decoded and rectified s (pairs/s) | read MB/s "
              "| whole `vislam run` s | trajectory vs the ASL folder's, max m |")
        print("|---|---|---|---|---|---|---|")
        for name, path in bags.items():
            best = None
            for _ in range(REPEATS):
                t0 = time.perf_counter()
                bag = open_bag(path, calib, imu_calib)
                t1 = time.perf_counter()
                pairs = sum(1 for _ in bag.pairs())
                t2 = time.perf_counter()
                if best is None or t2 - t0 < best[2]:
                    best = (t1 - t0, t2 - t1, t2 - t0)
            whole = _run([str(path), "--calib", str(MAV0), "--out", str(root / "run")])
            _, est = read_tum(root / "run" / "trajectory.txt")
            size = _size(path) / 1e6
            print(f"| {name} | {size:.1f} | {best[0]:.2f} ({bag.imu.samples.num_samples} IMU samples) | {best[1]:.2f} "
                  f"({pairs / best[1]:.0f}) | {size / best[2]:.0f} | {whole:.2f} | {np.abs(est - asl).max():.1e} |")
        print(f"\nThe same run on the ASL folder: {folder:.2f} s. {os.cpu_count()} cores.")
        import json

        t0 = time.perf_counter()
        bag, camchain, imu_yaml, scene = synthetic_street_bag(root, SYNTHETIC_SECONDS)
        made = time.perf_counter() - t0
        whole = _run([str(bag), "--calib", str(camchain), "--imu-calib", str(imu_yaml), "--gt-topic", "/truth",
                      "--out", str(root / "street")])
        summary = json.loads((root / "street" / "summary.json").read_text())
        e = summary["errors"]
        print(f"\n| synthetic street drive (seed 0, {SYNTHETIC_SECONDS:g} s, 2 s at rest), ROS 1 | frames | bag MB | "
              "ATE m | dead reckoning ATE m | path m | position NEES mean / inside 95 % | whole `vislam run` s |")
        print("|---|---|---|---|---|---|---|---|")
        nees = e["nees"]["position"]
        print(f"| rendered in {made:.1f} s | {scene.sequence.num_steps} | {_size(bag) / 1e6:.0f} | "
              f"{e['estimate']['ate_rmse']:.4f} | {e['dead_reckoning']['ate_rmse']:.3f} | "
              f"{e['estimate']['path_length']:.1f} | {nees['mean']:.2f} / {100 * nees['share_inside_95']:.0f} % | "
              f"{whole:.2f} |")


if __name__ == "__main__":
    main()

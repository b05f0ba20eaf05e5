"""The configuration of a command: defaults < ``--config`` TOML < dedicated flags < ``--set``."""

from __future__ import annotations

import argparse

from ..backend.config import Config
from ..backend.errors import ConfigError
from ..backend.options import printable_name, parse_assignment
from ..frontend.config import TrackerConfig

TRACKER = TrackerConfig.TABLE


def add_config_options(p: argparse.ArgumentParser, tables: str = "any table",
                       example: str = "noise.pixel_sigma=1.0") -> None:
    p.add_argument("--config", metavar="TOML", help=f"configuration file ({tables}; see config.toml of a run)")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help=f"override one option, e.g. {example} (repeatable)")


def add_bag_options(p: argparse.ArgumentParser) -> None:
    """The options of a ROS bag input (``frontend.bag``): its calibration and, where the bag does
    not tell them, its topics."""
    p.add_argument("--calib", metavar="FILE|DIR", help="a ROS bag's cameras: Kalibr's camchain.yaml (cam0 and cam1: "
                   "intrinsics, radtan distortion, resolution, T_cam_imu, timeshift_cam_imu) or an EuRoC folder "
                   "holding cam0/sensor.yaml, cam1/sensor.yaml (and imu0/sensor.yaml: the IMU's noise)")
    p.add_argument("--imu-calib", dest="imu_calib", metavar="FILE",
                   help="a ROS bag's IMU noise: Kalibr's imu.yaml (noise densities and random walks; default: "
                        "the EuRoC folder's imu0/sensor.yaml, else measured at rest)")
    for side, what in (("left", "the left camera's sensor_msgs/Image or CompressedImage"),
                       ("right", "the right camera's"), ("imu", "the sensor_msgs/Imu")):
        p.add_argument(f"--{side}-topic", dest=f"{side}_topic", metavar="TOPIC",
                       help=f"{what} topic of a ROS bag (default: the calibration's rostopic, else the only "
                            "candidate; two image topics: left the first by name)")


def check_bag_options(args: argparse.Namespace, positional: str) -> bool:
    """Whether ``args.<positional>`` is a ROS bag (``frontend.bag.is_bag``); ConfigError when a bag
    option is given for another input, or ``--imu`` / ``--imu-T-cam`` for a bag."""
    from ..frontend.bag import is_bag

    bag = is_bag(getattr(args, positional))
    if bag:
        for flag, value in (("--imu", args.imu), ("--imu-T-cam", args.imu_T_cam)):
            if value:
                raise ConfigError(f"{getattr(args, positional)}: {flag} is not for a ROS bag: its IMU topic and "
                                  "--calib give them")
    else:
        for flag in ("calib", "imu_calib", "left_topic", "right_topic", "imu_topic", "gt_topic"):
            if getattr(args, flag, None) is not None:
                raise ConfigError(f"{getattr(args, positional)}: --{flag.replace('_', '-')} is for a ROS bag (a ROS 1 "
                                  ".bag file or a ROS 2 bag folder with metadata.yaml)")
    return bag


def add_filter_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=["slam", "mapping", "dead-reckoning"], help="estimator.mode (default slam)")
    p.add_argument("--full-state", action="store_true", help="estimator.full_state: keep every landmark in the state")
    p.add_argument("--imu-flip", choices=["auto", "yes", "no"], help="conventions.imu_flip: flip the IMU's y and z axes")
    p.add_argument("--velocity-index", choices=["auto", "this", "next"],
                   help="conventions.velocity_index: velocity stamped k (this) or k+1 (next) drives step k->k+1")


def _split(assignments: list[str]) -> tuple[list[str], dict[str, str]]:
    """(assignments of the filter's tables, {key: value} of the tracker's); a bare tracker key is
    refused with its new name."""
    rest, tracker = [], {}
    for item in assignments:
        key, value = parse_assignment(item)
        table, _, leaf = key.partition(".")
        if table == TRACKER and not leaf:
            raise ConfigError(f"--set {printable_name(item)!s}: names no option (expected {TRACKER}.KEY=VALUE)")
        if table == TRACKER:
            tracker[leaf] = value
        elif not leaf and key in TrackerConfig.keys():
            raise ConfigError(f"config key '{key}' is now '{TRACKER}.{key}'")
        else:
            rest.append(item)
    return rest, tracker


def filter_config(args: argparse.Namespace, base: Config | None = None) -> Config:
    """The estimator's and the run's options (every table but ``[tracker]``)."""
    config = Config.load(args.config, base, foreign=(TRACKER,)) if args.config else (base or Config())
    flags = {}
    if getattr(args, "mode", None):
        flags["estimator.mode"] = args.mode
    if getattr(args, "full_state", False):
        flags["estimator.full_state"] = True
    if getattr(args, "imu_flip", None):
        flags["conventions.imu_flip"] = args.imu_flip
    if getattr(args, "velocity_index", None):
        flags["conventions.velocity_index"] = args.velocity_index
    rest, _ = _split(args.set)
    return config.with_values(flags).with_assignments(rest, foreign=(TRACKER,))


def tracker_config(args: argparse.Namespace, only: bool = False) -> TrackerConfig:
    """The ``[tracker]`` table; ``only``: every ``--set`` must be a tracker option (``vislam track``)."""
    config = TrackerConfig.load(args.config) if args.config else TrackerConfig()
    rest, tracker = _split(args.set)
    if only and rest:
        raise ConfigError(f"--set {rest[0]!r}: this command reads only the [{TRACKER}] table (--set {TRACKER}.KEY=VALUE)")
    return TrackerConfig.from_values(tracker, config)

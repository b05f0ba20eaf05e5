"""ROS 1 bags (``.bag``) and ROS 2 bag folders (``metadata.yaml`` with sqlite3 or MCAP storage) as
input, read with ``rosbags`` (no ROS installation): a stereo pair's images and an IMU's samples, with
Kalibr's calibration (``frontend.kalibr``).

* Topics: ``sensor_msgs/Image`` (``mono8``, ``8UC1``, ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``) or
  ``sensor_msgs/CompressedImage`` (JPEG, PNG) for the left and right cameras, ``sensor_msgs/Imu``.
  Given by the options, else the calibration's ``rostopic`` entries, else found when unambiguous
  (two image topics, left the first by name, and one IMU topic); otherwise one line lists the
  bag's topics and types.
* Stamps: each message's ``header.stamp`` (read from the serialized bytes, no image decoded for
  it); the cameras' stamps plus Kalibr's ``timeshift_cam_imu`` are IMU time. A left and a right
  image whose stamps differ by at most :func:`pair_tolerance` are one stereo pair; the others are
  counted and dropped (a note).
* Streaming: the stamps are read in one pass over the image topics, the IMU samples in one over
  its topic (each sample is 7 numbers), and :meth:`BagDataset.pairs` decodes the images in a last
  pass in bag order, holding only the images whose partner or predecessor has not arrived yet: a
  bag of many GB is never loaded whole.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backend.data.files import note_input
from ..backend.data.inertial import ImuNoiseDensities, check_imu_samples
from ..backend.data.tum import ns_to_seconds, poses_from_quaternions
from ..backend.errors import InputError
from .euroc import CameraCalibration, EurocImu, RectifiedRig, StereoRectification
from .kalibr import KalibrCameras, read_camchain, read_kalibr_imu

__all__ = ["BagDataset", "BagFrames", "BagTopics", "BagTruth", "is_bag", "open_bag", "pair_tolerance"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMU = "sensor_msgs/msg/Imu"
#: Ground-truth message types (``--gt-topic``) and where each holds the pose
POSES = {"geometry_msgs/msg/PoseStamped": "pose", "geometry_msgs/msg/PoseWithCovarianceStamped": "pose.pose",
         "geometry_msgs/msg/TransformStamped": "transform", "nav_msgs/msg/Odometry": "pose.pose"}
#: Image encodings read, and the OpenCV conversion to grey of each (None: already grey)
ENCODINGS = {"mono8": None, "8uc1": None, "bgr8": "COLOR_BGR2GRAY", "rgb8": "COLOR_RGB2GRAY",
             "bgra8": "COLOR_BGRA2GRAY", "rgba8": "COLOR_RGBA2GRAY"}
#: The widest stamp difference of a stereo pair (s), whatever the frame rate
MAX_PAIR_TOLERANCE = 0.005


def is_bag(path) -> bool:
    """Whether ``path`` is a ROS 1 bag (a ``.bag`` file) or a ROS 2 bag folder (``metadata.yaml``)."""
    p = Path(path)
    return (p.is_file() and p.suffix == ".bag") or (p.is_dir() and (p / "metadata.yaml").is_file())


@dataclass(frozen=True)
class BagTopics:
    """The topics read: left and right images, the IMU."""

    left: str
    right: str
    imu: str


@dataclass(frozen=True, eq=False)
class BagTruth:
    """Ground truth from a bag topic: the poses of its (child) frame, taken as the IMU's."""

    times: np.ndarray  # (G,) s, strictly increasing
    world_T_imu: np.ndarray  # (G,4,4)
    source: str  # "<bag> (topic <topic>, <type>)"


@dataclass(frozen=True, eq=False)
class BagFrames:
    """The stereo pairs of a bag: their stamps (IMU time) and the header stamps (ns) of their images."""

    times: np.ndarray  # (N,) s: the left image's stamp + the time shift
    left_ns: np.ndarray  # (N,) int64 header stamps of the left images
    right_ns: np.ndarray  # (N,) int64 of the right images
    unmatched: int  # images without a partner within the tolerance, dropped

    def __len__(self) -> int:
        return int(self.times.shape[0])


def pair_tolerance(left_ns: np.ndarray) -> float:
    """Largest stamp difference (s) of a left and a right image of one pair: a quarter of the median
    frame interval, at most :data:`MAX_PAIR_TOLERANCE`."""
    if left_ns.size < 2:
        return MAX_PAIR_TOLERANCE
    return float(min(MAX_PAIR_TOLERANCE, 0.25 * np.median(np.diff(np.sort(left_ns))) * 1e-9))


def _reader(path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    return AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _open_error(path, exc: Exception) -> InputError:
    return InputError(f"{path}: cannot read as a ROS bag: {' '.join(str(exc).split()) or type(exc).__name__}")


_HEADER_WITH_SEQ = re.compile(r"MSG: std_msgs/Header\s*\n\s*uint32\s+seq\b")


def _stamp_offset(connection, ros2: bool) -> int:
    """Where ``header.stamp`` starts in a serialized message of ``connection`` whose first field is a
    ``std_msgs/Header`` (Image, CompressedImage, Imu): ROS 2 (CDR) after the 4-byte encapsulation
    header; ROS 1 after ``uint32 seq`` where the bag's message definition has it (ROS 1's Header
    does; a bag written with ROS 2's definitions does not)."""
    if ros2:
        return 4
    return 4 if _HEADER_WITH_SEQ.search(connection.msgdef.data) else 0


def _header_ns(raw, ros2: bool, offset: int) -> int:
    """``header.stamp`` (ns) of a serialized message, read at ``offset`` (:func:`_stamp_offset`):
    ``uint32 sec, uint32 nsec`` (ROS 1, little-endian) or ``int32 sec, uint32 nanosec`` (CDR, in the
    byte order its encapsulation header names)."""
    if ros2:
        order = "<" if raw[1] == 1 else ">"
        sec, nsec = struct.unpack_from(order + "iI", raw, offset)
    else:
        sec, nsec = struct.unpack_from("<II", raw, offset)
    return int(sec) * 1_000_000_000 + int(nsec)


def _stamp_ns(stamp) -> int:
    """A deserialized ``builtin_interfaces/Time`` (ROS 1's time alike) in nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _by_stamp(rows: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (n,) int64 ns, values (n, k)) of ``rows`` = (ns, value, ...), in the order of their
    stamps (bag order is the order of arrival)."""
    ns = np.array([r[0] for r in rows], dtype=np.int64)
    values = np.array([r[1:] for r in rows], dtype=np.float64)
    order = np.argsort(ns, kind="stable")
    return ns[order], values[order]


def _topics(path, connections, cameras: KalibrCameras, imu_topic_calib, left, right, imu) -> BagTopics:
    types = {}
    for c in connections:
        types.setdefault(c.topic, c.msgtype)
    listing = ", ".join(f"{t} ({types[t]})" for t in sorted(types)) or "none"
    images = sorted(t for t, m in types.items() if m in (IMAGE, COMPRESSED))
    imus = sorted(t for t, m in types.items() if m == IMU)
    left = left or cameras.topics[0]
    right = right or cameras.topics[1]
    imu = imu or imu_topic_calib
    if left is None and right is None and len(images) == 2:
        left, right = images
    if imu is None and len(imus) == 1:
        imu = imus[0]
    for option, topic, wanted in (("--left-topic", left, (IMAGE, COMPRESSED)), ("--right-topic", right,
                                                                                 (IMAGE, COMPRESSED)),
                                  ("--imu-topic", imu, (IMU,))):
        if topic is None:
            raise InputError(f"{path}: cannot tell which topic is {option[2:-6]}: give {option} (the bag's topics: "
                             f"{listing})")
        if topic not in types:
            raise InputError(f"{path}: no topic {topic} ({option} or the calibration's rostopic); the bag's topics: "
                             f"{listing}")
        if types[topic] not in wanted:
            raise InputError(f"{path}: topic {topic} is {types[topic]}, not {' or '.join(wanted)} ({option}); the "
                             f"bag's topics: {listing}")
    if left == right:
        raise InputError(f"{path}: the left and the right camera are one topic ({left})")
    return BagTopics(left, right, imu)


def _stamps(reader, connections, path, topic: str) -> np.ndarray:
    chosen = [c for c in connections if c.topic == topic]
    offsets = {c.id: _stamp_offset(c, reader.is2) for c in chosen}
    stamps = np.fromiter((_header_ns(raw, reader.is2, offsets[c.id]) for c, _, raw in reader.messages(connections=chosen)),
                         dtype=np.int64)
    if stamps.size == 0:
        raise InputError(f"{path}: topic {topic}: no message")
    return stamps


def _pairs(left_ns: np.ndarray, right_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(left stamps, right stamps) of the pairs, each left image with the nearest right one within the
    tolerance, both unique and in time order; and the images left without a partner. Both topics
    hold a message (``_stamps``)."""
    tol = int(round(pair_tolerance(left_ns) * 1e9))
    lefts, rights = np.unique(left_ns), np.unique(right_ns)
    after = np.searchsorted(rights, lefts)
    before, after = np.clip(after - 1, 0, rights.size - 1), np.clip(after, 0, rights.size - 1)
    j = np.where(np.abs(rights[before] - lefts) <= np.abs(rights[after] - lefts), before, after)
    ok = np.abs(rights[j] - lefts) <= tol
    keep_l, keep_r = lefts[ok], rights[j[ok]]
    _, first = np.unique(keep_r, return_index=True)  # a right image in one pair only
    first = np.sort(first)
    keep_l, keep_r = keep_l[first], keep_r[first]
    return keep_l, keep_r, int(left_ns.size + right_ns.size - 2 * keep_l.size)


def _imu_samples(reader, connections, path, topic: str, noise: ImuNoiseDensities | None):
    chosen = [c for c in connections if c.topic == topic]
    rows = []
    for connection, _, raw in reader.messages(connections=chosen):
        msg = reader.deserialize(raw, connection.msgtype)
        a, w = msg.linear_acceleration, msg.angular_velocity
        rows.append((_stamp_ns(msg.header.stamp), a.x, a.y, a.z, w.x, w.y, w.z))
    if len(rows) < 2:
        raise InputError(f"{path}: topic {topic}: {len(rows)} IMU message(s), at least 2 needed")
    ns, values = _by_stamp(rows)
    return check_imu_samples(f"{path} (topic {topic})", ns_to_seconds(ns), values[:, :3], values[:, 3:], noise,
                             keys=("header.stamp", "linear_acceleration", "angular_velocity"))


def _truth(reader, connections, path, topic: str) -> BagTruth:
    """The poses of ``topic`` (:data:`POSES`) by header stamp; InputError (one line) for another
    type, fewer than 3 poses, a zero quaternion or a repeated stamp."""
    types = {c.topic: c.msgtype for c in connections}
    if topic not in types:
        raise InputError(f"{path}: no topic {topic} (--gt-topic); the bag's topics: "
                         + ", ".join(f"{t} ({m})" for t, m in sorted(types.items())))
    if types[topic] not in POSES:
        raise InputError(f"{path}: topic {topic} is {types[topic]}, not one of {', '.join(POSES)} (--gt-topic)")
    where = POSES[types[topic]]
    rows = []
    for connection, _, raw in reader.messages(connections=[c for c in connections if c.topic == topic]):
        msg = reader.deserialize(raw, connection.msgtype)
        pose = msg
        for name in where.split("."):
            pose = getattr(pose, name)
        p, q = (pose.translation, pose.rotation) if where == "transform" else (pose.position, pose.orientation)
        rows.append((_stamp_ns(msg.header.stamp), p.x, p.y, p.z, q.x, q.y, q.z, q.w))
    if len(rows) < 3:
        raise InputError(f"{path}: topic {topic}: {len(rows)} pose(s), at least 3 needed as ground truth")
    ns, values = _by_stamp(rows)
    if np.any(np.diff(ns) <= 0):
        raise InputError(f"{path}: topic {topic}: two poses share the stamp {ns[np.flatnonzero(np.diff(ns) <= 0)[0]]} ns")
    good = np.isfinite(values).all(axis=1) & np.any(values[:, 3:] != 0, axis=1)
    if not good.all():
        bad = int(np.flatnonzero(~good)[0])
        raise InputError(f"{path}: topic {topic}: the pose at {ns[bad] * 1e-9:.9f} s is not finite or its quaternion "
                         "is zero")
    return BagTruth(ns_to_seconds(ns), poses_from_quaternions(values[:, :3], values[:, 3:]),
                    f"{path} (topic {topic}, {types[topic]})")


@dataclass(frozen=True, eq=False)
class BagDataset(RectifiedRig):
    """A stereo-inertial bag and its calibration: everything but the image pixels, which
    :meth:`pairs` decodes in one pass.

    Attributes
    ----------
    root : Path
        The bag (``.bag`` file or ROS 2 folder).
    cam0, cam1 : CameraCalibration
    imu : EurocImu
        The samples (IMU frame) with Kalibr's noise densities, ``body_T_imu`` the identity (Kalibr's
        body frame is the IMU's).
    frames : BagFrames
    rectification : StereoRectification
    topics : BagTopics
    timeshift : float
        Kalibr's ``timeshift_cam_imu`` (s), added to the camera stamps.
    ground_truth : BagTruth or None
        From ``gt_topic`` (:func:`open_bag`), else None.
    notes : tuple of str
    """

    root: Path
    cam0: CameraCalibration
    cam1: CameraCalibration
    imu: EurocImu
    frames: BagFrames
    rectification: StereoRectification
    topics: BagTopics
    timeshift: float = 0.0
    ground_truth: BagTruth | None = None
    notes: tuple[str, ...] = ()

    def pairs(self):
        """Yield (index, left, right) of every pair in time order, rectified; InputError naming the bag,
        topic and stamp of an image that cannot be decoded or is not of the calibration's size."""
        index_left = {int(ns): k for k, ns in enumerate(self.frames.left_ns)}
        index_right = {int(ns): k for k, ns in enumerate(self.frames.right_ns)}
        pending: dict[int, dict[str, np.ndarray]] = {}
        following = 0
        try:
            reader = _reader(self.root)
            reader.open()
        except Exception as exc:  # rosbags raises its own types for every damage
            raise _open_error(self.root, exc) from None
        try:
            chosen = [c for c in reader.connections if c.topic in (self.topics.left, self.topics.right)]
            offsets = {c.id: _stamp_offset(c, reader.is2) for c in chosen}
            for connection, _, raw in reader.messages(connections=chosen):
                side = "left" if connection.topic == self.topics.left else "right"
                ns = _header_ns(raw, reader.is2, offsets[connection.id])
                k = (index_left if side == "left" else index_right).get(ns)
                if k is None or k < following:
                    continue  # an image without a partner (counted in frames.unmatched)
                pending.setdefault(k, {})[side] = self._decode(reader, connection, raw, ns)
                while following in pending and len(pending[following]) == 2:
                    pair = pending.pop(following)
                    yield (following, *self.rectification.rectify(pair["left"], pair["right"]))
                    following += 1
        except InputError:
            raise
        except Exception as exc:  # a damaged chunk or message met in this pass
            raise _open_error(self.root, exc) from None
        finally:
            reader.close()
        if following < len(self.frames):
            raise InputError(f"{self.root}: {len(self.frames) - following} stereo pairs were not found again in the "
                             "bag's last pass (was it changed while being read?)")

    def _decode(self, reader, connection, raw, ns: int) -> np.ndarray:
        import cv2

        where = f"{self.root}: topic {connection.topic}, stamp {ns * 1e-9:.9f}"
        msg = reader.deserialize(raw, connection.msgtype)
        if connection.msgtype == COMPRESSED:
            img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f"{where}: cannot decode the compressed image (format {msg.format!r})")
        else:
            encoding = str(msg.encoding).lower()
            if encoding not in ENCODINGS:
                raise InputError(f"{where}: image encoding {msg.encoding!r} is not read (only "
                                 f"{', '.join(ENCODINGS)})")
            conversion = ENCODINGS[encoding]
            channels = 1 if conversion is None else 4 if encoding.endswith("a8") else 3
            h, w, step = int(msg.height), int(msg.width), int(msg.step)
            data = np.asarray(msg.data, dtype=np.uint8)
            if step < w * channels or data.size < h * step:
                raise InputError(f"{where}: {data.size} bytes for a {w}x{h} {msg.encoding} image of step {step}")
            img = data[:h * step].reshape(h, step)[:, :w * channels]
            img = img if conversion is None else cv2.cvtColor(np.ascontiguousarray(img).reshape(h, w, channels),
                                                              getattr(cv2, conversion))
        width, height = self.rectification.size
        if img.shape != (height, width):
            raise InputError(f"{where}: size {img.shape[1]}x{img.shape[0]} differs from the calibration's "
                             f"{width}x{height} ({self.cam0.source})")
        return np.ascontiguousarray(img)


def _read_calibration(calib) -> tuple[KalibrCameras, np.ndarray, ImuNoiseDensities | None]:
    """(the cameras, ``body_T_imu`` (4,4), the IMU's noise or None) of ``calib``: a Kalibr
    ``camchain.yaml`` (the body frame is the IMU's; no noise in it), or an EuRoC folder (``mav0`` or
    the folder holding it) whose ``cam0/sensor.yaml``, ``cam1/sensor.yaml`` and, when present,
    ``imu0/sensor.yaml`` give the pair, the IMU's place and its noise."""
    path = Path(calib)
    if not path.is_dir():
        return read_camchain(path), np.eye(4), None
    from .euroc import read_camera_yaml, read_imu_yaml

    root = path / "mav0" if (path / "mav0").is_dir() else path
    cam0, cam1 = (read_camera_yaml(root / cam / "sensor.yaml") for cam in ("cam0", "cam1"))
    body_T_imu, noise = np.eye(4), None
    if (root / "imu0" / "sensor.yaml").is_file():
        noise, body_T_imu, _, _ = read_imu_yaml(root / "imu0" / "sensor.yaml")
    return KalibrCameras(cam0, cam1, (None, None), 0.0, str(root)), body_T_imu, noise


def open_bag(path, calib, imu_calib=None, left_topic: str | None = None, right_topic: str | None = None,
             imu_topic: str | None = None, gt_topic: str | None = None) -> BagDataset:
    """The bag at ``path`` with the calibration ``calib`` (:func:`_read_calibration`: Kalibr's
    ``camchain.yaml`` or an EuRoC folder's ``sensor.yaml`` files) and ``imu_calib`` (Kalibr's
    ``imu.yaml``, the noise densities; without either, the run measures them at rest): topics
    (module docstring), the stereo pairs' stamps, the IMU's samples, the rectification and, with
    ``gt_topic`` (``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``
    or ``nav_msgs/Odometry``), the ground truth.
    InputError (one line) naming the bag for a damaged or unreadable one, missing or ambiguous
    topics, and too few pairs or samples.

    Returns
    -------
    BagDataset
    """
    root = Path(path)
    if calib is None:
        raise InputError(f"{root}: a bag needs its cameras' calibration: --calib camchain.yaml (Kalibr) or an EuRoC "
                         "folder holding cam0/sensor.yaml and cam1/sensor.yaml")
    cameras, body_T_imu, noise = _read_calibration(calib)
    imu_topic_calib = None
    if imu_calib is not None:
        noise, imu_topic_calib = read_kalibr_imu(imu_calib)
    note_input(root, contents=True)
    try:
        reader = _reader(root)
        reader.open()
    except Exception as exc:
        raise _open_error(root, exc) from None
    try:
        connections = list(reader.connections)
        topics = _topics(root, connections, cameras, imu_topic_calib, left_topic, right_topic, imu_topic)
        left_ns, right_ns = (_stamps(reader, connections, root, t) for t in (topics.left, topics.right))
        samples = _imu_samples(reader, connections, root, topics.imu, noise)
        truth = _truth(reader, connections, root, gt_topic) if gt_topic is not None else None
    except InputError:
        raise
    except Exception as exc:
        raise _open_error(root, exc) from None
    finally:
        reader.close()
    pair_left, pair_right, unmatched = _pairs(left_ns, right_ns)
    if pair_left.size < 2:
        raise InputError(f"{root}: {pair_left.size} stereo pair(s) of {topics.left} and {topics.right} within "
                         f"{pair_tolerance(left_ns) * 1e3:.1f} ms of each other; at least 2 needed")
    times = ns_to_seconds(pair_left) + cameras.timeshift
    frames = BagFrames(times, pair_left, pair_right, unmatched)
    rectification = StereoRectification.from_cameras(cameras.cam0, cameras.cam1)
    notes = [*cameras.cam0.notes]
    if unmatched:
        notes.append(f"{root}: {unmatched} images of {topics.left} / {topics.right} without a partner within "
                     f"{pair_tolerance(left_ns) * 1e3:.1f} ms dropped")
    t = samples.time_stamps
    outside = int(np.count_nonzero((times < t[0]) | (times > t[-1])))
    if outside:
        notes.append(f"{root}: {outside} of {len(frames)} stereo pairs lie outside the IMU record ({topics.imu})")
    if cameras.timeshift:
        notes.append(f"{cameras.source}: timeshift_cam_imu {cameras.timeshift:+.6f} s added to the camera stamps")
    imu = EurocImu(samples=samples, body_T_imu=body_T_imu)
    return BagDataset(root=root, cam0=cameras.cam0, cam1=cameras.cam1, imu=imu, frames=frames,
                      rectification=rectification, topics=topics, timeshift=cameras.timeshift, ground_truth=truth,
                      notes=tuple(notes))

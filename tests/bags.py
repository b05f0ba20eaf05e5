"""Writing ROS 1 bags and ROS 2 bag folders (``rosbags``) and Kalibr files for the tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _header(ts, ros1: bool, ns: int, seq: int, frame: str):
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=int(ns // 10**9), nanosec=int(ns % 10**9))
    return Header(seq=seq, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)


def image_message(ts, ros1: bool, ns: int, seq: int, img: np.ndarray, compressed: str | None = None):
    """A sensor_msgs/Image (mono8) or, with ``compressed`` ("png", "jpeg"), a CompressedImage."""
    header = _header(ts, ros1, ns, seq, "cam")
    if compressed:
        ok, data = cv2.imencode("." + compressed, img)
        assert ok
        return ts.types["sensor_msgs/msg/CompressedImage"](header=header, format=compressed, data=data.ravel())
    return ts.types["sensor_msgs/msg/Image"](header=header, height=img.shape[0], width=img.shape[1], encoding="mono8",
                                              is_bigendian=0, step=img.shape[1], data=np.ascontiguousarray(img).ravel())


def imu_message(ts, ros1: bool, ns: int, seq: int, accel, gyro):
    Vec3, Quat = ts.types["geometry_msgs/msg/Vector3"], ts.types["geometry_msgs/msg/Quaternion"]
    return ts.types["sensor_msgs/msg/Imu"](
        header=_header(ts, ros1, ns, seq, "imu"), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=Vec3(x=gyro[0], y=gyro[1], z=gyro[2]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=Vec3(x=accel[0], y=accel[1], z=accel[2]),
        linear_acceleration_covariance=np.zeros(9))


def pose_message(ts, ros1: bool, ns: int, seq: int, T: np.ndarray, msgtype: str):
    """A geometry_msgs/PoseStamped, TransformStamped or nav_msgs/Odometry of the pose ``T`` (4,4)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    Vec3, Point, Quat = (ts.types[f"geometry_msgs/msg/{n}"] for n in ("Vector3", "Point", "Quaternion"))
    rotation = Quat(x=q[0], y=q[1], z=q[2], w=q[3])
    header = _header(ts, ros1, ns, seq, "world")
    pose = ts.types["geometry_msgs/msg/Pose"](position=Point(x=T[0, 3], y=T[1, 3], z=T[2, 3]), orientation=rotation)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return ts.types[msgtype](header=header, pose=pose)
    if msgtype == "geometry_msgs/msg/TransformStamped":
        transform = ts.types["geometry_msgs/msg/Transform"](translation=Vec3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                                              rotation=rotation)
        return ts.types[msgtype](header=header, child_frame_id="body", transform=transform)
    with_cov = ts.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    twist = ts.types["geometry_msgs/msg/TwistWithCovariance"](
        twist=ts.types["geometry_msgs/msg/Twist"](linear=Vec3(x=0.0, y=0.0, z=0.0), angular=Vec3(x=0.0, y=0.0, z=0.0)),
        covariance=np.zeros(36))
    return ts.types[msgtype](header=header, child_frame_id="body", pose=with_cov, twist=twist)


def truth_messages(data, ros1: bool, msgtype: str, topic: str = "/truth", every: int = 1):
    """Messages of an EuRoC dataset's ground truth (every ``every``-th pose) as ``msgtype``."""
    ts = _typestore(ros1)
    gt = data.ground_truth
    ns = _seconds_to_ns(gt.times)
    return [(int(ns[i]), topic, msgtype, pose_message(ts, ros1, int(ns[i]), i, gt.world_T_imu[i], msgtype))
            for i in range(0, len(ns), every)]


def write_bag(path: Path, messages, ros1: bool, mcap: bool = False) -> Path:
    """``messages``: (receive ns, topic, msgtype, message) in write order, from :func:`euroc_messages`;
    a ROS 2 bag in sqlite3 storage, or MCAP with ``mcap``."""
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    connections = {}
    with writer:
        for ns, topic, msgtype, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], ns, serialize(msg, msgtype))
    return path


def euroc_messages(data, ros1: bool, compressed: str | None = None, left="/cam0/image_raw", right="/cam1/image_raw",
                   imu="/imu0", frames: int | None = None):
    """The messages of an EuRoC dataset (``frontend.euroc.EurocDataset``): its raw pairs and every IMU
    sample, stamped as the ASL folder, sorted by time (the receive time is the stamp)."""
    ts = _typestore(ros1)
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    out = []
    stamps = [int(ns) for ns in data.frames.stamps_ns]
    for k in range(len(data.frames) if frames is None else frames):
        left_img, right_img = data.read_pair(k, rectified=False)
        out.append((stamps[k], left, image_type, image_message(ts, ros1, stamps[k], k, left_img, compressed)))
        out.append((stamps[k], right, image_type, image_message(ts, ros1, stamps[k], k, right_img, compressed)))
    samples = data.imu.samples
    imu_ns = _seconds_to_ns(samples.time_stamps)
    for i, (ns, a, w) in enumerate(zip(imu_ns, samples.linear_acceleration, samples.angular_velocity)):
        out.append((int(ns), imu, "sensor_msgs/msg/Imu", imu_message(ts, ros1, int(ns), i, a, w)))
    out.sort(key=lambda m: m[0])
    return out


def _seconds_to_ns(seconds: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(seconds) * 1e9).astype(np.int64)


def write_camchain(path: Path, data, topics=("/cam0/image_raw", "/cam1/image_raw"), timeshift: float = 0.0,
                   chain: bool = False) -> Path:
    """Kalibr's camchain.yaml of an EuRoC dataset's cameras (``T_cam_imu = inv(T_BS_cam) T_BS_imu``;
    ``chain``: cam1 by ``T_cn_cnm1`` instead)."""
    doc = {}
    imu = data.imu.body_T_imu
    for name, cam, topic in (("cam0", data.cam0, topics[0]), ("cam1", data.cam1, topics[1])):
        K = cam.K
        entry = dict(camera_model="pinhole", intrinsics=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
                     distortion_model="radtan", distortion_coeffs=[float(x) for x in cam.distortion],
                     resolution=list(cam.resolution), T_cam_imu=(np.linalg.inv(cam.body_T_cam) @ imu).tolist(),
                     timeshift_cam_imu=timeshift)
        if topic is not None:
            entry["rostopic"] = topic
        doc[name] = entry
    if chain:
        doc["cam1"]["T_cn_cnm1"] = (np.linalg.inv(data.cam1.body_T_cam) @ data.cam0.body_T_cam).tolist()
        del doc["cam1"]["T_cam_imu"]
    path.write_text(yaml.safe_dump(doc))
    return path


def write_kalibr_imu(path: Path, noise, topic: str | None = "/imu0") -> Path:
    entry = dict(accelerometer_noise_density=noise.accelerometer_noise_density,
                 accelerometer_random_walk=noise.accelerometer_random_walk,
                 gyroscope_noise_density=noise.gyroscope_noise_density,
                 gyroscope_random_walk=noise.gyroscope_random_walk, update_rate=200.0)
    if topic is not None:
        entry["rostopic"] = topic
    path.write_text(yaml.safe_dump({"imu0": entry}))
    return path


def synthetic_street_bag(root: Path, duration: float, ros1: bool = True, encoding: str = "mono8"):
    """A bag of ``vislam synth --imu inertial --scenario street``'s drive (seed 0) with rendered stereo
    images (``synth.render``: the street world along its path, the KITTI-like rig) on ``/left`` and
    ``/right``, its IMU samples on ``/imu`` and its true poses on ``/truth`` (PoseStamped); Kalibr's
    camchain.yaml and imu.yaml of it. Returns (bag, camchain, imu.yaml, the scene)."""
    from vislam.backend.geometry import se3
    from vislam.synth.inertial_scene import InertialSceneConfig, make_inertial_scene
    from vislam.synth.observe import kitti_calibration
    from vislam.synth.render import RENDER_STREAM, build_street_planes, render_pair

    scene = make_inertial_scene(InertialSceneConfig(scenario="street", duration=duration, seed=0))
    seq, cal, T = scene.sequence, kitti_calibration(), scene.world_T_imu_true
    planes = build_street_planes(T, np.random.default_rng([0, RENDER_STREAM]))
    ts = _typestore(ros1)
    frames_ns = _seconds_to_ns(seq.time_stamps)
    messages = []
    for k, ns in enumerate(int(n) for n in frames_ns):
        for topic, img in zip(("/left", "/right"), render_pair(planes, T[k], cal)):
            msg = image_message(ts, ros1, ns, k, img)
            if encoding == "bgr8":
                colour = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                msg = ts.types["sensor_msgs/msg/Image"](header=msg.header, height=img.shape[0], width=img.shape[1],
                                                        encoding="bgr8", is_bigendian=0, step=3 * img.shape[1],
                                                        data=colour.ravel())
            messages.append((ns, topic, "sensor_msgs/msg/Image", msg))
        messages.append((ns, "/truth", "geometry_msgs/msg/PoseStamped",
                         pose_message(ts, ros1, ns, k, T[k], "geometry_msgs/msg/PoseStamped")))
    imu = seq.imu
    for i, (ns, a, w) in enumerate(zip(_seconds_to_ns(imu.time_stamps), imu.linear_acceleration, imu.angular_velocity)):
        messages.append((int(ns), "/imu", "sensor_msgs/msg/Imu", imu_message(ts, ros1, int(ns), i, a, w)))
    messages.sort(key=lambda m: m[0])
    bag = write_bag(root / ("street.bag" if ros1 else "street_ros2"), messages, ros1)
    K = cal.K
    cam_T_imu = se3.inverse(cal.imu_T_cam)
    right_T_left = np.eye(4)
    right_T_left[0, 3] = -cal.baseline
    doc = {name: dict(camera_model="pinhole", intrinsics=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
                      distortion_model="radtan", distortion_coeffs=[0.0] * 4, resolution=[cal.width, cal.height],
                      T_cam_imu=T_cam_imu.tolist(), rostopic=topic)
           for name, T_cam_imu, topic in (("cam0", cam_T_imu, "/left"), ("cam1", right_T_left @ cam_T_imu, "/right"))}
    camchain = root / "street_camchain.yaml"
    camchain.write_text(yaml.safe_dump(doc))
    return bag, camchain, write_kalibr_imu(root / "street_imu.yaml", imu.noise, "/imu"), scene

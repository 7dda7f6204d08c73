"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``, ``.db3`` or ``.mcap``) bags as recordings.

Read through ``rosbags.highlevel.AnyReader`` (no ROS installation needed).  Every message is placed at its
**header stamp** (the sensor's time), not at the bag's receive time; messages are ordered by that stamp.

| topic type | option | sensor | columns |
|---|---|---|---|
| ``sensor_msgs/msg/Imu`` | ``--imu`` | ``imu0``, ``imu1``, ... | EuRoC's six (rad s^-1, m s^-2) |
| ``sensor_msgs/msg/PointCloud2`` | ``--points`` | ``lidar0``, ... | ``points [1]``; ``<timestamp>.ply`` per cloud |
| ``geometry_msgs/msg/PointStamped`` | ``--pose`` | ``pose0``, ... | ``x, y, z [m]`` |
| ``geometry_msgs/msg/PoseStamped`` | ``--pose`` | ``pose0``, ... | ``x, y, z [m]``, ``qx, qy, qz, qw [1]`` |

IMU noise: where a message's ``angular_velocity_covariance`` / ``linear_acceleration_covariance`` is given
(ROS: all zeros means "unknown", ``-1`` in element 0 "no such measurement"), the per-sample variance
``sigma^2`` of white noise sampled at ``f`` becomes Kalibr's density ``sigma / sqrt(f)`` (Kalibr's discrete
sigma is ``density * sqrt(f)``); otherwise sensor.yaml carries no noise key, as a recorder's does, and each
estimator uses its own default.  See docs/importers.md.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from selfcal.io.recording import Recording, RecordingError, SensorData, imu_sensor

IMU_TYPE = "sensor_msgs/msg/Imu"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
POINT_TYPE = "geometry_msgs/msg/PointStamped"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
ACCEPTED = {"imu": (IMU_TYPE,), "points": (CLOUD_TYPE,), "pose": (POINT_TYPE, POSE_TYPE)}
SENSOR_PREFIX = {"imu": "imu", "points": "lidar", "pose": "pose"}
CLOUD_FILE_PATTERN = "{timestamp}.ply"
# sensor_msgs/PointField datatypes -> numpy
_POINT_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _open(bag: Path):
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore
    if not bag.exists():
        raise RecordingError(f"{bag}: no such bag (a ROS 1 .bag file, or a ROS 2 bag folder)")
    if bag.is_dir() and not (bag / "metadata.yaml").is_file():
        raise RecordingError(f"{bag}: cannot open as a ROS 2 bag (a ROS 2 bag folder holds a metadata.yaml)")
    try:
        # bags without embedded message definitions (ROS 2 before Iron) are read with the latest ROS 2 types
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except (AnyReaderError, OSError, KeyError, ValueError) as err:
        raise RecordingError(f"{bag}: cannot open as a ROS 1 or ROS 2 bag ({' '.join(str(err).split())})") from None
    return reader


def _imu_row(msg, where: str) -> tuple:
    w, a = msg.angular_velocity, msg.linear_acceleration
    g_cov, a_cov = msg.angular_velocity_covariance, msg.linear_acceleration_covariance
    return (w.x, w.y, w.z, a.x, a.y, a.z, g_cov[0], g_cov[4], g_cov[8], a_cov[0], a_cov[4], a_cov[8])


def _pose_row(msg, where: str) -> tuple:
    if hasattr(msg, "point"):  # PointStamped
        return msg.point.x, msg.point.y, msg.point.z
    p, q = msg.pose.position, msg.pose.orientation
    return p.x, p.y, p.z, q.x, q.y, q.z, q.w


def _topic_rows(reader, bag: Path, topic: str, kind: str, row_of) -> tuple[dict, np.ndarray, list]:
    """(sensor.yaml origin keys, header stamps in ns sorted, ``row_of(message, where)`` in that order) of ``topic``.

    Each message is reduced to its row as it is read (a bag of a million IMU messages is not held decoded).
    """
    from rosbags.highlevel import AnyReaderError
    topics = reader.topics
    listing = ", ".join(f"{name} [{info.msgtype}]" for name, info in sorted(topics.items())) or "none"
    if topic not in topics:
        raise RecordingError(f"{bag}: no topic {topic!r} (topics: {listing})")
    msgtype = topics[topic].msgtype
    if msgtype not in ACCEPTED[kind]:
        raise RecordingError(f"{bag}: topic {topic!r} is {msgtype}; --{kind} takes {' or '.join(ACCEPTED[kind])}")
    where = f"{bag}: topic {topic!r}"
    stamps, rows, frame_id = [], [], None
    try:
        for connection, _, raw in reader.messages(connections=[c for c in reader.connections if c.topic == topic]):
            msg = reader.deserialize(raw, connection.msgtype)
            stamps.append(_stamp_ns(msg))  # the header stamp; the bag's receive time (_) is not the sensor's
            rows.append(row_of(msg, f"{where} at {stamps[-1]} ns"))
            frame_id = msg.header.frame_id if frame_id is None else frame_id
    except AnyReaderError as err:
        raise RecordingError(f"{where}: cannot decode a message ({' '.join(str(err).split())})") from None
    if not rows:
        raise RecordingError(f"{where} holds no messages")
    stamps = np.array(stamps, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")  # drivers publish late sometimes; the header stamp orders them
    stamps = stamps[order]
    same = np.flatnonzero(np.diff(stamps) == 0)
    if same.size:  # two samples at one instant: a recording cannot hold them, and guessing which is right is no fix
        hint = " (header stamps not set by the driver?)" if stamps[0] == stamps[-1] else ""
        raise RecordingError(f"{where}: {same.size} messages repeat an earlier header stamp "
                             f"(first: {stamps[same[0]]} ns){hint}")
    origin = {"frame_id": frame_id, "topic": topic, "message_type": msgtype, "source": f"{bag.name}{topic}"}
    return origin, stamps, [rows[i] for i in order]


def _noise_density(variances: np.ndarray, rate_hz: float) -> float | None:
    """Kalibr density from the per-message covariance diagonals (M, 3) of ROS, or None where none is given.

    A message gives its variances when element 0 is not -1 ("no such measurement") and all three are positive
    (all zeros: "unknown").  The per-axis variances (median over the messages that give them) are averaged
    over the axes: Kalibr keeps one density per sensor.  White noise of per-sample variance sigma^2 at f Hz has
    the density sigma / sqrt(f) (Kalibr's discrete-time sigma is density * sqrt(f)).
    """
    given = (variances[:, 0] != -1) & np.all(np.isfinite(variances) & (variances > 0), axis=1)
    if not given.any():
        return None
    variance = float(np.mean(np.median(variances[given], axis=0)))
    return float(f"{math.sqrt(variance) / math.sqrt(rate_hz):.6g}")


def _imu(name: str, origin: dict, t_ns: np.ndarray, rows: list) -> SensorData:
    table = np.array(rows, dtype=np.float64)
    meta = {"sensor_type": "imu"}
    sources = []
    if len(t_ns) > 1:
        meta["rate_hz"] = float(f"{1e9 / float(np.median(np.diff(t_ns))):.6g}")
        for key, field, columns in (("gyroscope_noise_density", "angular_velocity_covariance", slice(6, 9)),
                                    ("accelerometer_noise_density", "linear_acceleration_covariance", slice(9, 12))):
            density = _noise_density(table[:, columns], meta["rate_hz"])
            if density is not None:
                meta[key] = density
                sources.append(field)
    meta["noise_source"] = (f"{' and '.join(sources)}: sqrt(variance) / sqrt(rate_hz)" if sources else
                            "none in the bag (covariances unknown): each estimator's default applies")
    return imu_sensor(name, t_ns, table[:, 0:3], table[:, 3:6], meta={**meta, **origin})


def _pose(name: str, origin: dict, t_ns: np.ndarray, rows: list) -> SensorData:
    table = np.array(rows, dtype=np.float64)
    position_only = origin["message_type"] == POINT_TYPE
    columns = ("x", "y", "z") if position_only else ("x", "y", "z", "qx", "qy", "qz", "qw")
    units = {c: "m" if c in "xyz" else "1" for c in columns}
    meta = {"sensor_type": "position" if position_only else "pose", **origin}
    if not position_only:
        meta["frames"] = "x, y, z: position of child in frame_id; qx, qy, qz, qw: frame_id_R_child (Hamilton, as ROS)"
    return SensorData(name, t_ns, {c: table[:, j].copy() for j, c in enumerate(columns)}, units, meta)


def cloud_points_m(msg, where: str) -> np.ndarray:
    """The x, y, z of a PointCloud2 as (N, 3) float64, points with a non-finite coordinate dropped."""
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise RecordingError(f"{where}: PointCloud2 without field {missing[0]!r} (fields: {', '.join(fields)})")
    for c in "xyz":
        if fields[c].datatype not in _POINT_FIELD_DTYPES:
            raise RecordingError(f"{where}: PointCloud2 field {c!r} has unknown datatype {fields[c].datatype}")
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": list("xyz"),
                      "formats": [order + _POINT_FIELD_DTYPES[fields[c].datatype] for c in "xyz"],
                      "offsets": [fields[c].offset for c in "xyz"], "itemsize": msg.point_step})
    data = np.asarray(msg.data, dtype=np.uint8)
    rows = data[:msg.height * msg.row_step].reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(-1)  # row_step may pad each row: cut per row
    xyz = np.column_stack([points[c].astype(np.float64) for c in "xyz"])
    return xyz[np.isfinite(xyz).all(axis=1)]


def _clouds(name: str, origin: dict, t_ns: np.ndarray, clouds: list) -> tuple[SensorData, dict[str, bytes]]:
    from selfcal.io.pointcloud import point_cloud_bytes
    counts = np.array([len(xyz) for xyz in clouds])
    keep = counts > 0  # a cloud without a finite point has no file: it is no sample
    if not keep.any():
        raise RecordingError(f"{origin['source']}: every cloud is empty (no finite x, y, z)")
    payloads = {f"{name}/{CLOUD_FILE_PATTERN.format(timestamp=int(t))}": point_cloud_bytes(xyz)
                for t, xyz in zip(t_ns[keep], (c for c, k in zip(clouds, keep) if k))}
    meta = {"sensor_type": "lidar", "file_pattern": CLOUD_FILE_PATTERN, **origin,
            "points": "x, y, z in m in frame_id; non-finite points dropped, other fields not kept"}
    sensor = SensorData(name, t_ns[keep], {"points": counts[keep].astype(np.float64)}, {"points": "1"}, meta)
    return sensor, payloads


def import_rosbag(bag, imu_topics=(), points_topics=(), pose_topics=()) -> Recording:
    """A recording from the topics of a ROS 1 or ROS 2 bag.

    Parameters
    ----------
    bag : str or Path
        A ROS 1 ``.bag`` file, or a ROS 2 bag folder (``metadata.yaml`` + ``.db3`` / ``.mcap``).
    imu_topics, points_topics, pose_topics : sequence of str
        Topics of ``sensor_msgs/msg/Imu`` (-> ``imu0``, ``imu1``, ...), ``sensor_msgs/msg/PointCloud2``
        (-> ``lidar0``, ...) and ``geometry_msgs/msg/PointStamped`` or ``PoseStamped`` (-> ``pose0``, ...).

    Returns
    -------
    Recording
        One sensor per topic, in the order given, with the clouds as PLY payloads.

    Raises
    ------
    RecordingError
        One line: a bag that cannot be opened, a missing topic (the bag's topics listed with their types), a
        topic of another message type, an empty topic, header stamps that repeat, an IMU the recording's checks
        refuse.
    """
    bag = Path(bag)
    if not (imu_topics or points_topics or pose_topics):
        raise RecordingError(f"{bag}: no topic asked for (give --imu, --points or --pose)")
    reader = _open(bag)
    sensors, payloads = {}, {}
    try:
        for kind, topics in (("imu", imu_topics), ("points", points_topics), ("pose", pose_topics)):
            for k, topic in enumerate(topics):
                name = f"{SENSOR_PREFIX[kind]}{k}"
                if kind == "imu":
                    sensors[name] = _imu(name, *_topic_rows(reader, bag, topic, kind, _imu_row))
                elif kind == "points":
                    sensors[name], clouds = _clouds(name, *_topic_rows(reader, bag, topic, kind, cloud_points_m))
                    payloads.update(clouds)
                else:
                    sensors[name] = _pose(name, *_topic_rows(reader, bag, topic, kind, _pose_row))
    finally:
        reader.close()
    rec = Recording(path=bag, sensors=sensors, payloads=payloads)
    for name in rec.imu_names():  # the recording's IMU checks (physics at the boundary) before anything is written
        rec.imu(name)
    rec.path = None
    return rec

"""``selfcal import rosbag``: ROS 1 and ROS 2 bags written here with ``rosbags`` itself, from simulated data.

The truth is the simulation: the imported columns must equal the simulated samples bit for bit (ROS messages
carry float64; CDR and ROS 1 serialisation are exact), at the header stamps (not at the receive times, which
are written late and out of order here), and the calibration of the imported recording must find the
simulated intrinsics within 3 sigma of its own reported uncertainty.
"""
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from selfcal.cli.main import main
from selfcal.io.pointcloud import read_point_cloud
from selfcal.io.recording import RecordingError, read_recording, read_truth
from selfcal.io.rosbag import import_rosbag
from selfcal.sim.imu import ImuScenario, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

RATE_HZ = 100.0
GYRO_DENSITY = 0.00016968  # rad s^-1 Hz^-1/2, the simulator's default; written into the bag as a variance
IMU_TYPE = "sensor_msgs/msg/Imu"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A multi-position recording (9 poses, 38 s at 100 Hz: 3800 samples) and its truth."""
    scenario = ImuScenario(MultiPositionTrajectory(n_poses=10, static_s=2.0, move_s=1.5, initial_static_s=10.0,
                                                   seed=3), *random_intrinsics(3), rate_hz=RATE_HZ)
    path = scenario.write(tmp_path_factory.mktemp("sim") / "rec", seed=5)
    return read_recording(path).imu("imu0"), read_truth(path)


# ------------------------------------------------------------------------------------------- writing bags

def typestore_of(kind):
    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


def header(ts, kind, t_ns, frame="imu_link"):
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=int(t_ns // 10**9), nanosec=int(t_ns % 10**9))
    Header = ts.types["std_msgs/msg/Header"]
    return Header(seq=0, stamp=stamp, frame_id=frame) if kind == "ros1" else Header(stamp=stamp, frame_id=frame)


def imu_messages(ts, kind, imu, gyro_variance=None, accel_cov0=0.0):
    """sensor_msgs/Imu messages of the simulated samples; gyro covariance diagonal ``gyro_variance`` (None: all
    zeros = unknown), accelerometer covariance element 0 ``accel_cov0`` (-1: no estimate, 0: unknown)."""
    Imu, V3, Q = (ts.types[f"{p}/msg/{n}"] for p, n in
                  (("sensor_msgs", "Imu"), ("geometry_msgs", "Vector3"), ("geometry_msgs", "Quaternion")))
    gyro_cov = np.diag([gyro_variance] * 3).ravel() if gyro_variance else np.zeros(9)
    accel_cov = np.zeros(9)
    accel_cov[0] = accel_cov0
    return [Imu(header=header(ts, kind, t), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8), angular_velocity=V3(x=w[0], y=w[1], z=w[2]),
                angular_velocity_covariance=gyro_cov, linear_acceleration=V3(x=a[0], y=a[1], z=a[2]),
                linear_acceleration_covariance=accel_cov)
            for t, w, a in zip(imu.t_ns.tolist(), imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist())]


def write_bag(path: Path, kind: str, topics: dict) -> Path:
    """Write ``topics`` (name -> (msgtype, messages)) as a ``ros1`` .bag or a ROS 2 bag (``sqlite3``, ``mcap``).

    Receive time = header stamp + 5 ms, and every 50th message is received after its successor: a bag's order
    is its arrival order, which the importer must not trust.
    """
    ts = typestore_of(kind)
    if kind == "ros1":
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else
                         StoragePlugin.SQLITE3)
    serialize = ts.serialize_ros1 if kind == "ros1" else ts.serialize_cdr
    with writer:
        for topic, (msgtype, messages) in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=ts)
            order = list(range(len(messages)))
            for k in range(0, len(order) - 1, 50):
                order[k], order[k + 1] = order[k + 1], order[k]
            base = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in messages]
            for rank, k in enumerate(order):
                receive_ns = max(base[min(rank, len(base) - 1)], base[k]) + 5_000_000
                writer.write(connection, receive_ns, serialize(messages[k], msgtype))
    return path


# -------------------------------------------------------------------------------------------------- IMU

@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "ros1"])
def test_imu_values_at_header_stamps(tmp_path, simulated, kind):
    imu, _ = simulated
    ts = typestore_of(kind)
    # ROS covariance is the per-sample variance: white noise of density d sampled at f has sigma = d sqrt(f)
    variance = (GYRO_DENSITY * np.sqrt(RATE_HZ)) ** 2
    accel_cov0 = -1.0 if kind == "ros1" else 0.0  # "no estimate" / "unknown": both leave the key out
    bag = write_bag(tmp_path / ("b.bag" if kind == "ros1" else "b"), kind,
                    {"/imu/data": (IMU_TYPE, imu_messages(ts, kind, imu, variance, accel_cov0))})
    rec = import_rosbag(bag, imu_topics=["/imu/data"])
    got = rec.imu("imu0")
    assert np.array_equal(got.t_ns, imu.t_ns)  # header stamps, sorted: not the (late, shuffled) receive times
    assert np.array_equal(got.gyro_rad_s, imu.gyro_rad_s) and np.array_equal(got.accel_m_s2, imu.accel_m_s2)
    meta = rec.sensors["imu0"].meta
    assert meta["rate_hz"] == RATE_HZ
    assert meta["gyroscope_noise_density"] == pytest.approx(GYRO_DENSITY, rel=1e-5)  # 6 significant digits kept
    assert "accelerometer_noise_density" not in meta
    assert meta["topic"] == "/imu/data" and meta["frame_id"] == "imu_link" and meta["message_type"] == IMU_TYPE


def test_imported_bag_calibrates_to_the_simulated_intrinsics(tmp_path, simulated, capsys):
    imu, truth = simulated
    bag = write_bag(tmp_path / "b", "sqlite3", {"/imu": (IMU_TYPE, imu_messages(typestore_of("ros2"), "ros2", imu))})
    out = tmp_path / "rec"
    assert main(["import", "rosbag", str(bag), str(out), "--imu", "/imu"]) == 0
    back = read_recording(out).imu("imu0")  # what the estimators read
    assert np.array_equal(back.t_ns, imu.t_ns) and np.array_equal(back.gyro_rad_s, imu.gyro_rad_s)
    meta = yaml.safe_load((out / "imu0" / "sensor.yaml").read_text())
    assert "gyroscope_noise_density" not in meta and "none in the bag" in meta["noise_source"]  # all-zero: unknown

    assert main(["calibrate", "imu", str(out), "--out", str(tmp_path / "cal.yaml")]) == 0
    cal = yaml.safe_load((tmp_path / "cal.yaml").read_text())["imu0"]
    for group in ("accelerometers", "gyroscopes"):
        error = np.subtract(cal[group]["bias"], truth["sensors"]["imu0"][group]["bias"])
        assert np.all(np.abs(error) < 3 * np.asarray(cal[group]["bias_sigma"])), (group, error)


def test_two_imus_numbered_in_the_order_given(tmp_path, simulated):
    imu, _ = simulated
    ts = typestore_of("ros2")
    bag = write_bag(tmp_path / "b", "sqlite3", {"/a": (IMU_TYPE, imu_messages(ts, "ros2", imu)[:500]),
                                                "/b": (IMU_TYPE, imu_messages(ts, "ros2", imu)[500:1000])})
    rec = import_rosbag(bag, imu_topics=["/b", "/a"])
    assert list(rec.sensors) == ["imu0", "imu1"]
    assert np.array_equal(rec.sensors["imu0"].t_ns, imu.t_ns[500:1000])
    assert np.array_equal(rec.sensors["imu1"].t_ns, imu.t_ns[:500])


# --------------------------------------------------------------------------------------- poses and clouds

def test_point_and_pose_stamped(tmp_path):
    ts = typestore_of("ros2")
    Point, Pose, P, Q = (ts.types[f"geometry_msgs/msg/{n}"] for n in ("PointStamped", "PoseStamped", "Point",
                                                                       "Quaternion"))
    rng = np.random.default_rng(0)
    t_ns = 1_700_000_000_000_000_000 + np.arange(40, dtype=np.int64) * 20_000_000
    xyz = rng.normal(scale=10.0, size=(40, 3))
    q = rng.normal(size=(40, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    points = [Point(header=header(ts, "ros2", t, "tracker"), point=P(x=p[0], y=p[1], z=p[2]))
              for t, p in zip(t_ns.tolist(), xyz.tolist())]
    poses = [Pose(header=header(ts, "ros2", t, "world"), pose=ts.types["geometry_msgs/msg/Pose"](
        position=P(x=p[0], y=p[1], z=p[2]), orientation=Q(x=r[0], y=r[1], z=r[2], w=r[3])))
             for t, p, r in zip(t_ns.tolist(), xyz.tolist(), q.tolist())]
    bag = write_bag(tmp_path / "b", "sqlite3", {"/prism": ("geometry_msgs/msg/PointStamped", points),
                                                "/body": ("geometry_msgs/msg/PoseStamped", poses)})
    out = tmp_path / "rec"
    assert main(["import", "rosbag", str(bag), str(out), "--pose", "/prism", "--pose", "/body"]) == 0
    rec = read_recording(out)
    position, pose = rec.sensors["pose0"], rec.sensors["pose1"]
    assert position.units == {"x": "m", "y": "m", "z": "m"} and position.meta["sensor_type"] == "position"
    assert np.array_equal(position.t_ns, t_ns)
    assert np.array_equal(np.column_stack([position.values[c] for c in "xyz"]), xyz)
    assert list(pose.values) == ["x", "y", "z", "qx", "qy", "qz", "qw"] and pose.units["qw"] == "1"
    assert np.array_equal(np.column_stack([pose.values[c] for c in ("qx", "qy", "qz", "qw")]), q)
    assert pose.meta["frame_id"] == "world"


def cloud_message(ts, t_ns, xyz_f32, padding_bytes=4, row_pad=8):
    """A PointCloud2 with fields x y z (float32) + intensity, ``padding_bytes`` after each point and ``row_pad``
    after each of its 2 rows, as drivers lay them out."""
    PointField = ts.types["sensor_msgs/msg/PointField"]
    n = len(xyz_f32) // 2
    point_step = 16 + padding_bytes
    row = np.zeros((2, n * point_step + row_pad), dtype=np.uint8)
    for r in range(2):
        block = np.zeros((n, point_step), dtype=np.uint8)
        block[:, :12] = xyz_f32[r * n:(r + 1) * n].astype("<f4").view(np.uint8).reshape(n, 12)
        block[:, 12:16] = np.full(n, 7.0, dtype="<f4").view(np.uint8).reshape(n, 4)
        row[r, :n * point_step] = block.ravel()
    fields = [PointField(name=c, offset=4 * k, datatype=7, count=1) for k, c in enumerate(("x", "y", "z",
                                                                                           "intensity"))]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=header(ts, "ros2", t_ns, "lidar"), height=2, width=n, fields=fields, is_bigendian=False,
        point_step=point_step, row_step=row.shape[1], data=row.ravel(), is_dense=False)


def test_point_clouds_become_ply_files(tmp_path):
    ts = typestore_of("ros2")
    rng = np.random.default_rng(1)
    clouds = [rng.normal(scale=5.0, size=(100, 3)).astype(np.float32) for _ in range(3)]
    clouds[1][7] = np.nan  # "no return": dropped
    t_ns = [1_000_000_000 * (k + 1) for k in range(3)]
    bag = write_bag(tmp_path / "b", "mcap", {"/cloud": ("sensor_msgs/msg/PointCloud2",
                                                        [cloud_message(ts, t, c) for t, c in zip(t_ns, clouds)])})
    out = tmp_path / "rec"
    assert main(["import", "rosbag", str(bag), str(out), "--points", "/cloud"]) == 0
    lidar = read_recording(out).sensors["lidar0"]
    assert lidar.meta["sensor_type"] == "lidar" and lidar.meta["file_pattern"] == "{timestamp}.ply"
    assert np.array_equal(lidar.t_ns, t_ns) and np.array_equal(lidar.values["points"], [100, 99, 100])
    for t, cloud in zip(t_ns, clouds):
        loaded = read_point_cloud(out / "lidar0" / f"{t}.ply")
        expected = cloud[np.isfinite(cloud).all(axis=1)].astype(np.float64)
        assert np.array_equal(np.asarray(loaded.cloud.points), expected)  # float32 -> float64 PLY: exact


# ------------------------------------------------------------------------------------------------ errors

def one_line_error(capsys, argv) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture
def small_bag(tmp_path, simulated):
    imu, _ = simulated
    ts = typestore_of("ros2")
    Point, P = ts.types["geometry_msgs/msg/PointStamped"], ts.types["geometry_msgs/msg/Point"]
    bag = tmp_path / "b"
    write_bag(bag, "sqlite3", {"/imu": (IMU_TYPE, imu_messages(ts, "ros2", imu)[:300]),
                               "/prism": ("geometry_msgs/msg/PointStamped",
                                          [Point(header=header(ts, "ros2", 10**9), point=P(x=1.0, y=2.0, z=3.0))])})
    return bag


def test_missing_topic_lists_the_bags_topics(capsys, tmp_path, small_bag):
    err = one_line_error(capsys, ["import", "rosbag", str(small_bag), str(tmp_path / "o"), "--imu", "/imu0"])
    assert "'/imu0'" in err and "/imu [sensor_msgs/msg/Imu]" in err and "/prism [geometry_msgs/msg/PointStamped]" in err
    assert not (tmp_path / "o").exists()


def test_wrong_message_type(capsys, tmp_path, small_bag):
    err = one_line_error(capsys, ["import", "rosbag", str(small_bag), str(tmp_path / "o"), "--imu", "/prism"])
    assert "'/prism'" in err and "geometry_msgs/msg/PointStamped" in err and "sensor_msgs/msg/Imu" in err
    err = one_line_error(capsys, ["import", "rosbag", str(small_bag), str(tmp_path / "o"), "--pose", "/imu"])
    assert "PoseStamped" in err


def test_empty_topic(capsys, tmp_path):
    ts = typestore_of("ros2")
    bag = tmp_path / "b"
    with Writer2(bag, version=9) as writer:
        writer.add_connection("/imu", IMU_TYPE, typestore=ts)
    err = one_line_error(capsys, ["import", "rosbag", str(bag), str(tmp_path / "o"), "--imu", "/imu"])
    assert "'/imu'" in err and "no messages" in err


@pytest.mark.parametrize("what", ["junk.bag", "folder", "missing"])
def test_bag_that_cannot_be_opened(capsys, tmp_path, what):
    bag = tmp_path / what
    if what == "junk.bag":
        bag.write_bytes(b"#ROSBAG V1.2\nnot a bag")
    elif what == "folder":
        bag.mkdir()
        (bag / "notes.txt").write_text("no metadata.yaml here")
    err = one_line_error(capsys, ["import", "rosbag", str(bag), str(tmp_path / "o"), "--imu", "/imu"])
    assert str(bag) in err and ("cannot open" in err or "no such bag" in err)


def test_repeated_header_stamps_are_refused(capsys, tmp_path, simulated):
    imu, _ = simulated
    ts = typestore_of("ros2")
    messages = imu_messages(ts, "ros2", imu)[:200]
    messages[101].header = messages[100].header
    bag = write_bag(tmp_path / "b", "sqlite3", {"/imu": (IMU_TYPE, messages)})
    err = one_line_error(capsys, ["import", "rosbag", str(bag), str(tmp_path / "o"), "--imu", "/imu"])
    assert "1 messages repeat" in err and str(imu.t_ns[100]) in err


def test_imu_in_wrong_units_is_refused_at_import(tmp_path, simulated):
    imu, _ = simulated
    ts = typestore_of("ros2")
    messages = imu_messages(ts, "ros2", imu)[:1500]
    for m in messages:  # a driver that publishes g instead of m/s^2
        a = m.linear_acceleration
        a.x, a.y, a.z = a.x / 9.80665, a.y / 9.80665, a.z / 9.80665
    bag = write_bag(tmp_path / "b", "sqlite3", {"/imu": (IMU_TYPE, messages)})
    with pytest.raises(RecordingError, match="9.80665"):
        import_rosbag(bag, imu_topics=["/imu"])

"""EuRoC ``mav0`` folders: read by the recording reader in place, and by ``selfcal import euroc``.

The synthetic ``mav0`` trees below carry the real EuRoC headers and sensor.yaml layout (CRLF line ends as in the
published zip files): ``cam0/data.csv`` is ``#timestamp [ns],filename``, the ground truth starts with
``#timestamp`` without a unit and has ``q_RS_w []``, ``leica0`` is a valid position sensor.  These folders used
to make the reader refuse the whole dataset.
"""
import numpy as np
import pytest
import yaml

from selfcal.cli.main import main
from selfcal.io.euroc import import_euroc
from selfcal.io.recording import RecordingError, read_recording
from selfcal.sim.imu import ImuScenario
from selfcal.sim.trajectories import MultiPositionTrajectory

T0_NS = 1403636579763555584  # MH_01_easy's first camera stamp
IMU_YAML = """\
#Default imu sensor yaml file
sensor_type: imu
comment: VI-Sensor IMU (ADIS16448)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 200

# inertial sensor noise model parameters (static)
gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )
gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )
accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]  ( accel "white noise" )
accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )
"""
CAM_YAML = """\
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
         -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
GT_HEADER = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
             "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]")
IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],"
              "a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")


@pytest.fixture(scope="module")
def simulated_imu(tmp_path_factory):
    """41.5 s of a simulated IMU at 200 Hz (10 poses, enough to calibrate): written into mav0/imu0/data.csv."""
    trajectory = MultiPositionTrajectory(n_poses=10, static_s=2.0, move_s=1.5, initial_static_s=10.0, seed=2)
    rec = ImuScenario(trajectory, rate_hz=200.0, t0_ns=T0_NS).perturbed_measurements(4)
    return rec.imu("imu0")


def write_mav0(root, imu, imu_header=IMU_HEADER):
    """A mav0 tree as the EuRoC zip files hold it (CRLF line ends)."""
    mav = root / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    for folder in ("imu0", "leica0", "state_groundtruth_estimate0"):
        (mav / folder).mkdir()
    rows = [f"{t},{w[0]!r},{w[1]!r},{w[2]!r},{a[0]!r},{a[1]!r},{a[2]!r}"
            for t, w, a in zip(imu.t_ns.tolist(), imu.gyro_rad_s.tolist(), imu.accel_m_s2.tolist())]
    (mav / "imu0" / "data.csv").write_bytes(("\r\n".join([imu_header, *rows]) + "\r\n").encode())
    (mav / "imu0" / "sensor.yaml").write_text(IMU_YAML)
    stamps = imu.t_ns[::10]
    (mav / "cam0" / "data.csv").write_bytes(("\r\n".join(["#timestamp [ns],filename"] +
                                                         [f"{t},{t}.png" for t in stamps]) + "\r\n").encode())
    (mav / "cam0" / "sensor.yaml").write_text(CAM_YAML)
    gt = [f"{t},4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,-0.027876,0.033207,0.800006,"
          "-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593" for t in stamps]
    (mav / "state_groundtruth_estimate0" / "data.csv").write_bytes(("\r\n".join([GT_HEADER, *gt]) + "\r\n").encode())
    (mav / "state_groundtruth_estimate0" / "sensor.yaml").write_text("sensor_type: visual-inertial\n")
    leica = [f"{t},4.6,-1.7,0.8" for t in stamps]
    (mav / "leica0" / "data.csv").write_bytes(
        ("\r\n".join(["#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]", *leica]) + "\r\n").encode())
    (mav / "leica0" / "sensor.yaml").write_text("sensor_type: position\ncomment: Leica Nova MS50\n")
    (mav / "body.yaml").write_text("comment: 'Body frame'\n")
    return mav


def test_recording_reader_reads_a_mav0_in_place(tmp_path, simulated_imu):
    mav = write_mav0(tmp_path, simulated_imu)
    rec = read_recording(mav)
    assert sorted(rec.sensors) == ["imu0", "leica0"]  # valid recording sensors
    assert sorted(rec.skipped) == ["cam0", "state_groundtruth_estimate0"]  # other tools' files: skipped, said why
    assert "'filename'" in rec.skipped["cam0"] and "'#timestamp'" in rec.skipped["state_groundtruth_estimate0"]
    imu = rec.imu("imu0")
    assert np.array_equal(imu.t_ns, simulated_imu.t_ns) and np.array_equal(imu.gyro_rad_s, simulated_imu.gyro_rad_s)
    assert imu.meta["T_BS"]["rows"] == 4 and imu.rate_hz == 200
    with pytest.raises(RecordingError, match="cam0 skipped: .*'filename'"):
        rec.imu("cam0")  # asking for a skipped folder says why it is none


def test_calibrate_accepts_a_mav0(tmp_path, simulated_imu, capsys):
    mav = write_mav0(tmp_path, simulated_imu)
    assert main(["calibrate", "imu", str(mav), "--imu", "imu0", "--out", str(tmp_path / "cal.yaml")]) == 0
    assert "imu0" in yaml.safe_load((tmp_path / "cal.yaml").read_text())


def test_a_broken_imu_is_still_refused(tmp_path, simulated_imu):
    """Tolerance covers other tools' folders only: an IMU header that is not the recording's stays an error."""
    mav = write_mav0(tmp_path, simulated_imu, imu_header=IMU_HEADER.replace("#timestamp [ns]", "#timestamp"))
    with pytest.raises(RecordingError, match=r"imu0/data.csv:1: header must start with"):
        read_recording(mav)


def test_parent_folder_is_refused_by_the_reader_with_a_hint(tmp_path, simulated_imu):
    write_mav0(tmp_path, simulated_imu)
    with pytest.raises(RecordingError, match="point at its mav0 folder"):
        read_recording(tmp_path)


@pytest.mark.parametrize("point_at", ["mav0", "parent"])
def test_import_euroc(tmp_path, simulated_imu, capsys, point_at):
    mav = write_mav0(tmp_path / "MH_01_easy", simulated_imu)
    # ground truth that is not even CSV: never read, so never a reason to refuse
    (mav / "state_groundtruth_estimate0" / "data.csv").write_bytes(b"\x00\xff garbage")
    out = tmp_path / "rec"
    source = mav if point_at == "mav0" else mav.parent
    assert main(["import", "euroc", str(source), str(out)]) == 0
    rec = read_recording(out)
    assert list(rec.sensors) == ["imu0"]
    imu = rec.imu("imu0")
    assert np.array_equal(imu.t_ns, simulated_imu.t_ns)
    assert np.array_equal(imu.accel_m_s2, simulated_imu.accel_m_s2)
    meta = yaml.safe_load((out / "imu0" / "sensor.yaml").read_text())
    assert meta["gyroscope_noise_density"] == 1.6968e-04 and meta["accelerometer_random_walk"] == 3.0e-3
    assert meta["T_BS"]["data"][:4] == [1.0, 0.0, 0.0, 0.0] and meta["rate_hz"] == 200
    assert meta["source"] == "euroc/MH_01_easy/mav0/imu0"


def test_import_euroc_missing_imu_names_the_folders(tmp_path, simulated_imu):
    mav = write_mav0(tmp_path, simulated_imu)
    with pytest.raises(RecordingError) as info:
        import_euroc(tmp_path, ["imu1"])
    msg = str(info.value)
    assert "no imu1/data.csv" in msg and "cam0, imu0, leica0" in msg and str(mav) in msg and "\n" not in msg
    with pytest.raises(RecordingError, match="no such EuRoC"):
        import_euroc(tmp_path / "nowhere")

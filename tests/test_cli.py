"""The command line: known mistakes give one line on stderr and exit code 1; the calibration YAML keeps its contract.

Most checks run ``selfcal.cli.main.main`` in-process (stdout/stderr captured by capsys); one runs the installed
``selfcal`` console script in a subprocess, to prove the entry point declared in pyproject.toml.
"""
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from selfcal.cli.main import main
from selfcal.graphs.imu import MIN_POSES_FULL_ACCEL
from selfcal.io.recording import read_recording
from selfcal.core.inertial import ImuNoise
from selfcal.sim.imu import ImuPairScenario, ImuScenario
from selfcal.sim.trajectories import HandheldTrajectory, MultiPositionTrajectory
from shared_data import SHARED_DATA

REPO_ROOT = Path(__file__).resolve().parents[1]
XSENS_REC = REPO_ROOT / "data" / "xsens_mti_multiposition"
SHARED = SHARED_DATA
XSENS_SOURCE = SHARED / "imu_tk_xsens_multiposition"


def run_cli(capsys, *argv):
    """(exit code, stdout, stderr) of ``selfcal argv`` run in-process."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err):
    """A user mistake: exit code 1, one line on stderr, no traceback."""
    assert code == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("selfcal: error:"), err
    assert "Traceback" not in err
    return lines[0]


def short_recording(path, n_poses, seed=0):
    """A small simulated single-IMU multi-position recording (100 Hz, exact measurements) written to ``path``."""
    trajectory = MultiPositionTrajectory(n_poses=n_poses, static_s=3.0, move_s=2.0, initial_static_s=10.0, seed=seed)
    return ImuScenario(trajectory, noise=ImuNoise.zero(), rate_hz=100.0).write(path)


def console_script() -> Path:
    """The ``selfcal`` script installed next to this interpreter (a venv's bin/), else the one on PATH."""
    beside = Path(sys.executable).parent / "selfcal"
    if beside.is_file():
        return beside
    import shutil
    found = shutil.which("selfcal")
    if found is None:
        pytest.fail("console script 'selfcal' not installed (pip install -e .): the entry point is part of the "
                    "product, so its absence is a failure, not a skip")
    return Path(found)


# --- the installed entry point -------------------------------------------------------------------------------

def test_console_script_unknown_option_one_line_exit_1(tmp_path):
    proc = subprocess.run([str(console_script()), "calibrate", "imu", str(XSENS_REC), "--no-such-option"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    line = assert_one_line_error(proc.returncode, proc.stderr)
    assert "--no-such-option" in line
    assert proc.stdout == ""


# --- user mistakes, in-process --------------------------------------------------------------------------------

@pytest.mark.parametrize("argv", [["calibrate", "imu", "REC", "--bogus"], ["--bogus"], ["calibrate"],
                                  ["calibrate", "imu-pair"], ["import", "no-such-kind", "SRC", "OUT"]])
def test_usage_mistakes_one_line_exit_1(capsys, tmp_path, argv):
    argv = [str(tmp_path / a) if a in ("REC", "SRC", "OUT") else a for a in argv]
    code, out, err = run_cli(capsys, *argv)
    assert_one_line_error(code, err)
    assert out == ""


@pytest.mark.parametrize("system", ["imu", "imu-pair"])
def test_missing_recording_folder(capsys, tmp_path, system):
    missing = tmp_path / "no_such_recording"
    code, _, err = run_cli(capsys, "calibrate", system, missing)
    line = assert_one_line_error(code, err)
    assert str(missing) in line


def test_nan_in_data_csv_names_file_and_line(capsys, tmp_path):
    rec = short_recording(tmp_path / "rec", n_poses=3)
    csv = rec / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    bad_line = 7  # 1-based: line 1 is the header, so this is the 6th sample
    fields = lines[bad_line - 1].split(",")
    fields[5] = "nan"  # a_RS_S_y
    lines[bad_line - 1] = ",".join(fields)
    csv.write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "calibrate", "imu", rec)
    line = assert_one_line_error(code, err)
    assert f"{csv}:{bad_line}:" in line
    assert "NaN" in line and "a_RS_S_y" in line


def test_too_few_static_poses_gives_advice(capsys, tmp_path):
    rec = short_recording(tmp_path / "rec", n_poses=3)
    code, _, err = run_cli(capsys, "calibrate", "imu", rec, "--out", tmp_path / "cal.yaml")
    line = assert_one_line_error(code, err)
    # says what it found, what is needed and what to do
    assert re.search(r"\b3\b", line) and f"at least {MIN_POSES_FULL_ACCEL}" in line and "hold the IMU still" in line
    assert not (tmp_path / "cal.yaml").exists()  # no partial result


# --- results --------------------------------------------------------------------------------------------------

def shape(x):
    return np.shape(np.asarray(x, dtype=float))


def test_calibrate_imu_writes_the_yaml_contract(capsys, tmp_path):
    out = tmp_path / "tmp" / "cal.yaml"
    out.parent.mkdir()
    code, stdout, err = run_cli(capsys, "calibrate", "imu", XSENS_REC, "--out", out)
    assert code == 0, err
    assert "imu0" in stdout and "Traceback" not in err
    cal = yaml.safe_load(out.read_text())
    assert list(cal) == ["imu0"]  # one entry per IMU of the recording
    acc, gyro = cal["imu0"]["accelerometers"], cal["imu0"]["gyroscopes"]
    assert shape(acc["M"]) == shape(acc["M_sigma"]) == (3, 3)
    assert shape(acc["bias"]) == shape(acc["bias_sigma"]) == (3,)
    assert np.allclose(np.tril(np.asarray(acc["M"]), -1), 0.0)  # upper triangular by definition of the frame
    for key, expected in (("M", (3, 3)), ("bias", (3,)), ("A", (3, 3))):
        assert shape(gyro[key]) == shape(gyro[f"{key}_sigma"]) == expected, key
    for block in (acc, gyro):
        for key in [k for k in block if k.endswith("_sigma")]:
            sigma = np.asarray(block[key], dtype=float)
            assert np.all(np.isfinite(sigma)) and np.all(sigma >= 0), key
    # the diagonal sigmas of an estimated matrix are strictly positive (every block was estimated)
    assert np.all(np.diag(np.asarray(acc["M_sigma"])) > 0) and np.all(np.asarray(gyro["M_sigma"]) > 0)
    residual = cal["imu0"]["residual_rms"]
    assert set(residual) == {"accel", "gyro"}
    assert all(isinstance(residual[k], float) and residual[k] >= 0 for k in residual)


def test_calibrate_imu_pair_writes_the_yaml_contract(capsys, tmp_path):
    noise = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
    scenario = ImuPairScenario.random(HandheldTrajectory(30.0, seed=4), seed=4, intrinsics=False, noise0=noise,
                                      noise1=noise, rate_hz=100.0)
    rec = scenario.write(tmp_path / "pair", seed=11)
    out = tmp_path / "pair.yaml"
    code, stdout, err = run_cli(capsys, "calibrate", "imu-pair", rec, "--out", out)
    assert code == 0, err
    assert "imu0 <- imu1" in stdout
    cal = yaml.safe_load(out.read_text())
    R = np.asarray(cal["rotation_imu0_imu1"], dtype=float)
    assert R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
    assert shape(cal["rotation_sigma_rad"]) == (3,)
    assert isinstance(cal["time_offset_s"], float) and cal["time_offset_sigma_s"] > 0
    assert shape(cal["lever_arm_m"]) == shape(cal["lever_arm_sigma_m"]) == (3,)
    assert np.all(np.asarray(cal["lever_arm_sigma_m"]) > 0)
    # The YAML means what its convention says (v_imu0 = R v_imu1, t_imu0 = t_imu1 + dt): against the simulated truth,
    # within the written sigmas (3 sigma; rotation sigma per axis of the right tangent, so a transposed or
    # inverted R would be off by twice the rotation angle, tens of degrees)
    e = Rotation.from_matrix(scenario.R_imu0_imu1.T @ R).as_rotvec()
    assert np.all(np.abs(e) < 3 * np.asarray(cal["rotation_sigma_rad"])), (e, cal["rotation_sigma_rad"])
    assert abs(cal["time_offset_s"] - scenario.dt_s) < 3 * cal["time_offset_sigma_s"]
    assert np.all(np.abs(np.asarray(cal["lever_arm_m"]) - scenario.r_m) < 3 * np.asarray(cal["lever_arm_sigma_m"]))


# --- import -----------------------------------------------------------------------------------------------------

@pytest.mark.skipif(not XSENS_SOURCE.is_dir(), reason=f"public dataset not available at {XSENS_SOURCE} "
                                                      "(set SELFCAL_SHARED_DATA)")
def test_import_imu_tk_xsens_then_refuse_to_overwrite(capsys, tmp_path):
    out = tmp_path / "xsens"
    code, stdout, err = run_cli(capsys, "import", "imu-tk-xsens", XSENS_SOURCE, out)
    assert code == 0, err
    assert str(out) in stdout
    imu = read_recording(out).imu("imu0")
    assert len(imu.t_ns) == 51175  # SOURCE.md: 51175 samples per file
    assert "raw_counts" in imu.meta

    before = (out / "imu0" / "data.csv").stat().st_mtime_ns
    code, _, err = run_cli(capsys, "import", "imu-tk-xsens", XSENS_SOURCE, out)
    line = assert_one_line_error(code, err)
    assert str(out) in line and "exists" in line
    assert (out / "imu0" / "data.csv").stat().st_mtime_ns == before  # the existing recording is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["xsens"]  # and no temporary folder left behind

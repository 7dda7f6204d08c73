"""Fuzzing the commands with mutated recordings (issue 16, item 7): every mutation class of the issue, drawn by
``hypothesis``, through the command line in-process.  Only two outcomes are allowed:

* refused: exit 1, exactly one line on stderr starting ``selfcal: error:``, no traceback, no output file;
* accepted: exit 0, a finite output, and an answer as good as the clean recording's: within twice the clean
  run's own error against the truth plus a floor set by the estimator's reported accuracy (stated per command).

The default run draws a bounded number of examples per command (derandomised: the same ones on every machine);
``-m slow`` draws many more, from a random seed.

Mutation classes (applied to ``imu0``): columns in other units (g, mg, deg/s), a dead (constant) column, a
placeholder value (1e300), a gap of 1 ms to 10 min, timestamps in us instead of ns, sensor.yaml noise zero,
negative or text, a recording cut to a few rows, and the identity (which must be accepted and equal the clean
result); and a ship's speed log in knots (``speed0``; the identity for recordings without one): the 60 s calm
voyage holds no speed change to judge the unit by, so it is let through with a warning, and its answer must be
as good (knots move the calm voyage's attitude by 0.001 deg: its known acceleration is tiny).
"""
from __future__ import annotations

import contextlib
import io
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from selfcal.cli.main import main
from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.io.recording import ACCEL_COLUMNS, GYRO_COLUMNS, write_recording

G = STANDARD_GRAVITY_M_S2
SCALES = {"accel in g": (ACCEL_COLUMNS, 1 / G), "accel in mg": (ACCEL_COLUMNS, 1000 / G),
          "gyro in deg/s": (GYRO_COLUMNS, 180 / np.pi)}

mutations = st.one_of(
    st.just(("identity", None)),
    st.tuples(st.just("units"), st.sampled_from(sorted(SCALES))),
    st.tuples(st.just("dead column"), st.sampled_from(GYRO_COLUMNS + ACCEL_COLUMNS)),
    st.tuples(st.just("placeholder"), st.tuples(st.sampled_from(GYRO_COLUMNS + ACCEL_COLUMNS),
                                                 st.floats(0.05, 0.95))),
    st.tuples(st.just("gap"), st.tuples(st.floats(0.1, 0.9), st.floats(-3.0, 2.8))),  # log10 of the gap in s
    st.just(("timestamps in us", None)),
    st.tuples(st.just("noise"), st.sampled_from([0.0, -1e-3, "abc"])),
    st.tuples(st.just("truncated"), st.integers(2, 40)),
    st.just(("speed in knots", None)),
)
KNOTS = 1.0 / 0.514444


def mutate(rec, mutation):
    kind, arg = mutation
    if kind == "speed in knots":
        if "speed0" not in rec.sensors:
            return rec
        log = rec.sensors["speed0"]
        return replace(rec, sensors={**rec.sensors, "speed0": replace(log, values={
            **log.values, "speed_log": log.values["speed_log"] * KNOTS})})
    s = rec.sensors["imu0"]
    values, t_ns, meta = {c: v.copy() for c, v in s.values.items()}, s.t_ns.copy(), dict(s.meta)
    if kind == "units":
        columns, factor = SCALES[arg]
        for c in columns:
            values[c] *= factor
    elif kind == "dead column":
        values[arg][:] = values[arg][0]
    elif kind == "placeholder":
        values[arg[0]][int(arg[1] * len(t_ns))] = 1e300
    elif kind == "gap":
        t_ns[int(arg[0] * len(t_ns)):] += int(10 ** arg[1] * 1e9)
    elif kind == "timestamps in us":
        t_ns = t_ns[0] + (t_ns - t_ns[0]) // 1000
    elif kind == "noise":
        meta["gyroscope_noise_density"] = arg
    elif kind == "truncated":
        values, t_ns = {c: v[:arg] for c, v in values.items()}, t_ns[:arg]
    return replace(rec, sensors={**rec.sensors, "imu0": replace(s, values=values, t_ns=t_ns, meta=meta)})


def run(argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


def check_outcome(code, err, out: Path, good_enough, mutation):
    """The two allowed outcomes (module docstring); ``good_enough(out)`` judges an accepted answer."""
    lines = err.strip().splitlines()
    assert "Traceback" not in err, (mutation, err)
    if code == 1:
        assert len(lines) == 1 and lines[0].startswith("selfcal: error:"), (mutation, err)
        assert not out.exists(), mutation
        assert mutation[0] != "identity", err
        return
    assert code == 0, (mutation, code, err)
    assert out.exists(), mutation
    good_enough(out, mutation)


# --- the commands --------------------------------------------------------------------------------------------------

class ImuCalibration:
    """``calibrate imu`` on a 12-pose multi-position recording.  Accepted answers: every accelerometer and gyro
    bias and scale/misalignment entry within 5 reported sigma (of the clean run) of the truth, or within twice
    the clean run's own error."""
    argv = ("calibrate", "imu")
    suffix = "cal.yaml"

    def __init__(self):
        from selfcal.core.inertial import ImuNoise
        from selfcal.sim.imu import ImuScenario, random_intrinsics
        from selfcal.sim.trajectories import MultiPositionTrajectory
        accel, gyro = random_intrinsics(3)
        self.truth = {"accelerometers": accel, "gyroscopes": gyro}
        self.recording = ImuScenario(MultiPositionTrajectory(n_poses=12, seed=3), accel=accel, gyro=gyro,
                                     noise=ImuNoise(), rate_hz=100.0).perturbed_measurements(3)

    def errors(self, out: Path) -> dict:
        cal = yaml.safe_load(out.read_text())["imu0"]
        return {(sensor, key): np.abs(np.asarray(cal[sensor][key], float) - np.asarray(getattr(self.truth[sensor],
                key), float)) for sensor in self.truth for key in ("bias", "M")}

    def clean(self, out: Path) -> None:
        cal = yaml.safe_load(out.read_text())["imu0"]
        self.sigma = {(sensor, key): np.asarray(cal[sensor][f"{key}_sigma"], float)
                      for sensor in self.truth for key in ("bias", "M")}
        self.clean_errors = self.errors(out)

    def good_enough(self, out: Path, mutation) -> None:
        for key, error in self.errors(out).items():
            assert np.all(np.isfinite(error)), (mutation, key)
            assert np.all(error <= np.maximum(5 * self.sigma[key], 2 * self.clean_errors[key])), (mutation, key,
                                                                                               error)


class ShipSmoothing:
    """``smooth ship`` on a 60 s calm voyage.  Accepted answers: roll and pitch RMS error against the truth within
    twice the clean run's plus 0.1 deg (a tenth of the accelerometer-tilt sigma floor)."""
    argv = ("smooth", "ship")
    suffix = "ship.tum"

    def __init__(self):
        from selfcal.sim.ship import ShipScenario
        self.scenario = ShipScenario(kind="calm", duration_s=60.0, seed=2)
        self.recording = self.scenario.perturbed_measurements(5)
        self.t0_ns = int(self.recording.sensors["imu0"].t_ns[0])

    def error_deg(self, out: Path) -> float:
        from scipy.spatial.transform import Rotation
        tum = np.loadtxt(out, ndmin=2)
        assert np.all(np.isfinite(tum))
        t_s = tum[:, 0] - self.t0_ns * 1e-9
        yaw, pitch, roll = Rotation.from_quat(tum[:, 4:8]).as_euler("ZYX").T
        roll_true, pitch_true = self.scenario.motion.euler(t_s)[:2]
        return float(np.degrees(np.sqrt(np.mean((roll - roll_true) ** 2 + (pitch - pitch_true) ** 2))))

    def clean(self, out: Path) -> None:
        self.clean_error = self.error_deg(out)

    def good_enough(self, out: Path, mutation) -> None:
        assert self.error_deg(out) <= 2 * self.clean_error + 0.1, mutation


class TrackerSmoothing:
    """``smooth tracker`` on a 30 s TBM run.  Accepted answers: position RMS error against the truth within twice
    the clean run's plus 1 mm (twice the tracker's 0.5 mm sigma)."""
    argv = ("smooth", "tracker")
    suffix = "tracker.tum"

    def __init__(self):
        from selfcal.sim.tracker import TrackerScenario
        self.scenario = TrackerScenario(duration_s=30.0, seed=5)
        self.recording = self.scenario.measurements(seed=105)  # with noise: exact data are no physical run
        self.t0_ns = int(self.scenario.t0_ns)

    def error_m(self, out: Path) -> float:
        tum = np.loadtxt(out, ndmin=2)
        assert np.all(np.isfinite(tum))
        _, p_true = self.scenario.truth_pose(tum[:, 0] - self.t0_ns * 1e-9)
        return float(np.sqrt(np.mean(np.sum((tum[:, 1:4] - p_true) ** 2, axis=1))))

    def clean(self, out: Path) -> None:
        self.clean_error = self.error_m(out)

    def good_enough(self, out: Path, mutation) -> None:
        assert self.error_m(out) <= 2 * self.clean_error + 1e-3, mutation


class PairCalibration:
    """``calibrate imu-pair`` on an 8-pose two-IMU recording (imu0 mutated).  Accepted answers: the rotation
    within twice the clean run's error plus 3 of its reported sigmas (the rotation's own chi-square scale)."""
    argv = ("calibrate", "imu-pair")
    suffix = "pair.yaml"

    def __init__(self):
        from selfcal.pipelines.imu_pair import pair_scenario
        self.scenario = pair_scenario(seed=7)
        self.recording = self.scenario.perturbed_measurements(7)
        self.R_true = np.asarray(self.scenario.truth()["pair"]["rotation_imu0_imu1"], float)

    def error_rad(self, out: Path) -> float:
        from scipy.spatial.transform import Rotation
        R = np.asarray(yaml.safe_load(out.read_text())["rotation_imu0_imu1"], float)
        assert np.all(np.isfinite(R))
        return float(Rotation.from_matrix(R @ self.R_true.T).magnitude())

    def clean(self, out: Path) -> None:
        self.clean_error = self.error_rad(out)
        self.sigma = float(np.linalg.norm(yaml.safe_load(out.read_text())["rotation_sigma_rad"]))

    def good_enough(self, out: Path, mutation) -> None:
        assert self.error_rad(out) <= 2 * self.clean_error + 3 * self.sigma, mutation


class TrackerOnline(TrackerSmoothing):
    """``track --replay`` (the online path) on the same run; the same rule as ``smooth tracker``."""
    argv = ("track", "--system", "tracker", "--replay")
    suffix = "online.tum"
    out_option = "--out-tum"


COMMANDS = {"calibrate imu": ImuCalibration, "calibrate imu-pair": PairCalibration, "smooth ship": ShipSmoothing,
            "smooth tracker": TrackerSmoothing, "track": TrackerOnline}


@pytest.fixture(scope="module", params=sorted(COMMANDS))
def command(request, tmp_path_factory):
    cmd = COMMANDS[request.param]()
    folder = tmp_path_factory.mktemp("clean")
    rec = write_recording(cmd.recording, folder / "rec")
    out = folder / cmd.suffix
    code, err = run([*cmd.argv, str(rec), getattr(cmd, "out_option", "--out"), str(out)])
    assert code == 0, err  # the clean recording must be accepted
    cmd.clean(out)
    return cmd


def fuzz(command, mutation):
    folder = Path(tempfile.mkdtemp())
    try:
        rec = write_recording(mutate(command.recording, mutation), folder / "rec")
        out = folder / command.suffix
        code, err = run([*command.argv, str(rec), getattr(command, "out_option", "--out"), str(out)])
        check_outcome(code, err, out, command.good_enough, mutation)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutation=mutations)
def test_a_mutated_recording_is_refused_in_one_line_or_answered_as_well_as_the_clean_one(command, mutation):
    fuzz(command, mutation)


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutation=mutations)
def test_many_mutated_recordings(command, mutation):
    fuzz(command, mutation)

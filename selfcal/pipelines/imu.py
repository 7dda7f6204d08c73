"""Use case ``selfcal calibrate imu``: recording in, result object out."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from selfcal.core import inertial
from selfcal.graphs import imu as gi
from selfcal.core.errors import SelfcalError
from selfcal.io.recording import ImuData, Recording, RecordingError, read_recording
from selfcal.pipelines.fleet import flat_columns, register_task, sensor_option
from selfcal.models import imu

log = logging.getLogger(__name__)


def nested_list(a) -> list:
    return np.asarray(a, dtype=float).tolist()


def gravity_of(data: ImuData, override: float | None = None) -> float:
    return float(override or data.meta.get("gravity_m_s2", inertial.STANDARD_GRAVITY_M_S2))


@dataclass
class ImuCalibration:
    sensor: str
    estimate: gi.IntrinsicsEstimate
    n_static_poses: int
    gravity_m_s2: float
    raw_counts: dict | None = None

    def to_dict(self) -> dict:
        """The calibration YAML contract: f = M (a_raw - bias); w = M (w_raw - bias - A f); 1-sigma each."""
        e = self.estimate
        accel_M_sigma = np.zeros((3, 3))
        if "accel_M" in e.covariance:
            for s, (i, j) in zip(e.sigma("accel_M"), imu.UPPER_TRIANGULAR_INDEX):
                accel_M_sigma[i, j] = s
        accel_scale, accel_angles = imu.scale_and_misalignment(e.accel.M)
        gyro_scale, _ = imu.scale_and_misalignment(e.gyro.M)
        out = {
            "accelerometers": {
                "M": nested_list(e.accel.M), "M_sigma": nested_list(accel_M_sigma),
                "bias": nested_list(e.accel.bias), "bias_sigma": nested_list(e.sigma("accel_bias")),
                "scale": nested_list(accel_scale), "misalignment_rad": nested_list(accel_angles)},
            "gyroscopes": {
                "M": nested_list(e.gyro.M),
                "M_sigma": nested_list(e.sigma("gyro_M").reshape(3, 3)) if "gyro_M" in e.covariance else None,
                "bias": nested_list(e.gyro.bias), "bias_sigma": nested_list(e.sigma("gyro_bias")),
                "A": nested_list(e.gyro.A),
                "A_sigma": nested_list(e.sigma("gyro_A").reshape(3, 3)) if "gyro_A" in e.covariance else None,
                "scale": nested_list(gyro_scale)},
            "residual_rms": {"accel": float(np.sqrt(np.mean(e.accel_norm_residual_m_s2**2))),
                             "gyro": float(np.sqrt(np.mean(e.gyro_direction_residual_rad**2)))
                             if len(e.gyro_direction_residual_rad) else None},
            "units": {"accel": "m s^-2", "gyro": "rad s^-1", "A": "rad s^-1 per m s^-2",
                      "residual_rms.gyro": "rad (gravity direction after each move)"},
            "static_poses": self.n_static_poses,
            "gravity_m_s2": self.gravity_m_s2,
        }
        if self.raw_counts:
            # f = K (counts - offset) / c_nominal along each axis, so the sensitivity is c_nominal / K
            out["raw_counts"] = {
                "accelerometer_counts_per_unit": nested_list(
                    np.asarray(self.raw_counts["accelerometer"]["counts_per_unit"]) * (1 + accel_scale)),
                "gyroscope_counts_per_unit": nested_list(
                    np.asarray(self.raw_counts["gyroscope"]["counts_per_unit"]) * (1 + gyro_scale))}
        return out

    def summary(self) -> str:
        d = self.to_dict()
        return (f"{self.sensor}: {d['static_poses']} static poses; accel scale "
                f"{np.round(np.array(d['accelerometers']['scale']) * 100, 3)} %, residual |f|-g "
                f"{d['residual_rms']['accel']:.4g} m/s^2; gyro scale "
                f"{np.round(np.array(d['gyroscopes']['scale']) * 100, 3)} %, direction residual "
                f"{np.degrees(d['residual_rms']['gyro'] or 0):.3g} deg")


def calibrate_imu(recording: Recording, sensor: str, spec: gi.IntrinsicsSpec = gi.IntrinsicsSpec(),
                  gravity_m_s2: float | None = None) -> ImuCalibration:
    data = recording.imu(sensor, gyro_saturation_allowed=True)  # the moves it falls in are weakened (graphs.imu)
    problem = gi.problem_from_imu(data, gravity_of(data, gravity_m_s2))
    for note in problem.notes:
        log.warning(note)
    estimate = gi.solve_intrinsics(problem.poses, problem.moves, problem.gravity_m_s2, spec)
    return ImuCalibration(sensor, estimate, len(problem.poses), problem.gravity_m_s2, data.meta.get("raw_counts"))


# Kalibr's keys of each quantity and the unit of its noise density
KALIBR_NOISE = {"accel": ("accelerometer_noise_density", "accelerometer_random_walk", "m s^-2", "m s^-3"),
                "gyro": ("gyroscope_noise_density", "gyroscope_random_walk", "rad s^-1", "rad s^-2")}
MIN_REST_SAMPLES = 64  # an Allan curve of three octaves, the least the white line is fitted to


def kalibr_noise_values(data: ImuData) -> tuple[dict, str | None]:
    """Kalibr's imu.yaml noise values of one IMU from the Allan analysis of its longest rest, largest axis.

    A random walk the rest is too short to show is taken from sensor.yaml if declared there, else it is the
    largest value the Allan curve allows (:class:`selfcal.audit.noise.KalibrNoise`).  Returns the values
    (:class:`selfcal.io.exports.NoiseValue` by key) and, when a random walk was not measured, one line saying so.
    """
    from selfcal.audit.noise import kalibr_noise
    from selfcal.core.static_intervals import detect_static_intervals
    from selfcal.io.exports import NoiseValue
    start, end = max(detect_static_intervals(data.t_s, data.accel_m_s2), key=lambda run: run[1] - run[0],
                     default=(0, 0))
    if end - start < MIN_REST_SAMPLES:
        raise SelfcalError(f"{data.name}: no rest of {MIN_REST_SAMPLES} samples or more for the Allan analysis "
                           "(record the IMU at rest, longer)")
    values, unseen = {}, []
    for quantity, samples in (("accel", data.accel_m_s2), ("gyro", data.gyro_rad_s)):
        density_key, walk_key, unit, walk_unit = KALIBR_NOISE[quantity]
        n = kalibr_noise(samples[start:end], data.rate_hz, quantity, data.name)
        axes = lambda a: ", ".join(f"{v:.3e}" for v in a)  # noqa: E731
        values[density_key] = NoiseValue(float(np.max(n.white_density)), (
            f"{unit} / sqrt(Hz): N line of the Allan deviation at tau = 1 s, largest axis of x, y, z = "
            f"{axes(n.white_density)}"))
        rest = f"{n.duration_s:.0f} s rest, taus to {n.tau_max_s:.3g} s"
        if n.random_walk_seen:
            values[walk_key] = NoiseValue(float(np.nanmax(n.random_walk)), (
                f"{walk_unit} / sqrt(Hz): +1/2 line at tau = 3 s, largest axis of x, y, z = {axes(n.random_walk)} "
                f"(nan: none seen; {rest})"))
            continue
        unseen.append(quantity)
        bound = float(np.max(n.random_walk_bound))
        if walk_key in data.meta:
            values[walk_key] = NoiseValue(float(data.meta[walk_key]), (
                f"{walk_unit} / sqrt(Hz): NOT MEASURED, the sensor.yaml value; the Allan curve ({rest}) shows no "
                f"random walk and bounds it by {bound:.3e}"))
        else:
            values[walk_key] = NoiseValue(bound, (
                f"{walk_unit} / sqrt(Hz): NOT MEASURED, an upper bound: the largest +1/2 line under the one-sigma upper "
                f"end of the Allan curve ({rest})"))
    note = None
    if unseen:
        note = (f"{data.name}: its longest rest ({(end - start) / data.rate_hz:.0f} s) is too short to show the "
                f"{' and '.join(unseen)} random walk: imu.yaml holds the sensor.yaml value or an upper bound "
                "(see its comments)")
    return values, note


def audit_system(recording: Recording, base: str, sensors: list[str] | None = None):
    """The audit's view of one IMU (``sensors[0]``, default the first): a static log (one orientation
    throughout: bias and noise) or a multi-position recording (intrinsics)."""
    from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
    from selfcal.audit.imu.static import ImuStaticAudit, is_static_log
    name = _imu_names(recording, sensors, 1)[0]
    data = recording.imu(name, gyro_saturation_allowed=True)  # multi-position: the moves it falls in are weakened
    if is_static_log(data):
        data = recording.imu(name)  # a static log has no move to weaken: a saturated gyro is refused
        if base != "bias":
            raise SelfcalError(f"{data.name}: a static log is audited against the base model 'bias', not {base!r}")
        return ImuStaticAudit(data)
    return ImuIntrinsicsAudit(data, gravity_of(data), base)


def _imu_names(recording: Recording, sensors: list[str] | None, count: int) -> list[str]:
    """The IMUs to use: the ones given, else the recording's first ``count``."""
    names = list(sensors or recording.imu_names())
    if len(names) < count:
        raise RecordingError(f"{recording.path}: needs {count} IMU sensor folder(s), found {names}")
    return names[:count]


# --- fleet ------------------------------------------------------------------------------------------------------

def calibrate_imu_task(recording_path, options: dict) -> dict:
    """IMU intrinsics (``selfcal calibrate imu``) of one IMU (option ``imu``, default the first), flattened."""
    rec = read_recording(recording_path)
    sensor = sensor_option(rec, options, "imu", 0)
    d = calibrate_imu(rec, sensor, gravity_m_s2=options.get("gravity")).to_dict()
    d.pop("units")
    return {"sensor": sensor, **flat_columns(d)}


register_task("calibrate-imu", calibrate_imu_task, ("imu", "gravity"), "IMU intrinsics from a multi-position recording")

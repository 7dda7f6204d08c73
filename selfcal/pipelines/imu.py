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
    data = recording.imu(sensor)
    problem = gi.problem_from_imu(data, gravity_of(data, gravity_m_s2))
    estimate = gi.solve_intrinsics(problem.poses, problem.moves, problem.gravity_m_s2, spec)
    return ImuCalibration(sensor, estimate, len(problem.poses), problem.gravity_m_s2, data.meta.get("raw_counts"))


def audit_system(recording: Recording, base: str, sensors: list[str] | None = None):
    """The audit's view of one IMU (``sensors[0]``, default the first): a static log (one orientation
    throughout: bias and noise) or a multi-position recording (intrinsics)."""
    from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
    from selfcal.audit.imu.static import ImuStaticAudit, is_static_log
    data = recording.imu(_imu_names(recording, sensors, 1)[0])
    if is_static_log(data):
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

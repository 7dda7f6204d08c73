"""Use cases ``selfcal calibrate imu`` and ``selfcal calibrate imu-pair``: recording in, result object out."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from selfcal.graphs import imu_intrinsics as gi
from selfcal.graphs import imu_pair as gp
from selfcal.io.recording import ImuData, Recording, RecordingError
from selfcal.models import imu

log = logging.getLogger(__name__)


def _nested(a) -> list:
    return np.asarray(a, dtype=float).tolist()


def gravity_of(data: ImuData, override: float | None = None) -> float:
    return float(override or data.meta.get("gravity_m_s2", imu.STANDARD_GRAVITY_M_S2))


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
                "M": _nested(e.accel.M), "M_sigma": _nested(accel_M_sigma),
                "bias": _nested(e.accel.bias), "bias_sigma": _nested(e.sigma("accel_bias")),
                "scale": _nested(accel_scale), "misalignment_rad": _nested(accel_angles)},
            "gyroscopes": {
                "M": _nested(e.gyro.M),
                "M_sigma": _nested(e.sigma("gyro_M").reshape(3, 3)) if "gyro_M" in e.covariance else None,
                "bias": _nested(e.gyro.bias), "bias_sigma": _nested(e.sigma("gyro_bias")),
                "A": _nested(e.gyro.A),
                "A_sigma": _nested(e.sigma("gyro_A").reshape(3, 3)) if "gyro_A" in e.covariance else None,
                "scale": _nested(gyro_scale)},
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
                "accelerometer_counts_per_unit": _nested(
                    np.asarray(self.raw_counts["accelerometer"]["counts_per_unit"]) * (1 + accel_scale)),
                "gyroscope_counts_per_unit": _nested(
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


# --- two IMUs -----------------------------------------------------------------------------------------------

@dataclass
class PairCalibration:
    imu0: str
    imu1: str
    estimate: gp.PairEstimate
    n_static: int
    n_dynamic: int

    def to_dict(self) -> dict:
        e = self.estimate
        out = {
            "imu0": self.imu0, "imu1": self.imu1,
            "rotation_imu0_imu1": _nested(e.R_imu0_imu1),
            "rotation_sigma_rad": _nested(np.sqrt(np.diag(e.rotation_cov_rad2))),
            "rotation_convention": "v_imu0 = R v_imu1; sigma on the right-perturbation tangent (imu1 axes)",
            "time_offset_s": e.time_offset_s, "time_offset_sigma_s": e.time_offset_sigma_s,
            "time_offset_convention": "t_imu0 = t_imu1 + dt",
            "lever_arm_m": _nested(e.lever_arm_m) if e.lever_arm_m is not None else None,
            "lever_arm_sigma_m": _nested(e.lever_arm_sigma_m) if e.lever_arm_sigma_m is not None else None,
            "residual_rms": e.residual_rms,
            "static_poses": self.n_static, "dynamic_samples": self.n_dynamic,
            "notes": e.notes,
        }
        return out

    def summary(self) -> str:
        e = self.estimate
        angle = np.degrees(np.linalg.norm(imu.so3.log(e.R_imu0_imu1)))
        sigma = np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(e.rotation_cov_rad2))))
        lines = [f"{self.imu0} <- {self.imu1}: rotation {angle:.3f} deg (1-sigma {sigma:.3g} deg) from "
                 f"{self.n_static} static poses and {self.n_dynamic} moving samples"]
        if e.time_offset_s is not None:
            lines.append(f"  time offset {e.time_offset_s * 1e3:.3f} ms (1-sigma {e.time_offset_sigma_s * 1e3:.3g} ms)")
        if e.lever_arm_m is not None:
            lines.append(f"  lever arm {np.round(e.lever_arm_m, 4)} m (1-sigma {np.round(e.lever_arm_sigma_m, 4)} m)")
        lines += [f"  note: {n}" for n in e.notes]
        return "\n".join(lines)


# A lever arm known only to a centimetre, or a clock offset only to a millisecond, is not worth reporting as
# calibrated: at hand-held rates they change the predicted specific force by less than MEMS noise.
LEVER_ARM_SIGMA_MAX_M = 0.01
TIME_OFFSET_SIGMA_MAX_S = 1e-3


def calibrate_imu_pair(recording: Recording, imu0: str, imu1: str, lever_arm: bool | None = None,
                       time_offset: bool | None = None, lowpass_hz: float | None = 5.0) -> PairCalibration:
    """Rotation imu0 <- imu1 from the static poses (if any) and the moving parts of the recording.

    ``lever_arm`` / ``time_offset``: True forces, False skips, None estimates where the data determine them
    (1-sigma below ``LEVER_ARM_SIGMA_MAX_M`` / ``TIME_OFFSET_SIGMA_MAX_S``), and says so in the notes otherwise.
    """
    problem = gp.problem_from_imus(recording.imu(imu0), recording.imu(imu1), lowpass_hz)
    static, dynamic, dt0 = problem.static, problem.dynamic, problem.initial_dt_s
    if not static and dynamic is None:
        raise gp.DegenerateDataError(f"{imu0}/{imu1}: no static poses and no motion found in the recording")
    model = gp.PairModel(time_offset=dynamic is not None and time_offset is not False,
                         lever_arm=dynamic is not None and lever_arm is not False)
    estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
    weak_dt = model.time_offset and estimate.time_offset_sigma_s > TIME_OFFSET_SIGMA_MAX_S
    weak_r = model.lever_arm and float(np.max(estimate.lever_arm_sigma_m)) > LEVER_ARM_SIGMA_MAX_M
    advice = {"time offset": (weak_dt, "needs rotation whose rate changes quickly (shake or twist the rig)"),
              "lever arm": (weak_r, "needs rotation rate and angular acceleration about several axes")}
    forced = {"time offset": time_offset, "lever arm": lever_arm}
    for name, (weak, hint) in advice.items():
        if weak and forced[name]:
            raise gp.DegenerateDataError(f"{imu0}/{imu1}: {name} not determined by this recording: {hint}")
    if weak_dt or weak_r:
        model = gp.PairModel(time_offset=model.time_offset and not weak_dt, lever_arm=model.lever_arm and not weak_r)
        estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
        estimate.notes += [f"{name} not estimated: the data do not determine it ({hint})"
                           for name, (weak, hint) in advice.items() if weak]
    return PairCalibration(imu0, imu1, estimate, len(static), 0 if dynamic is None else len(dynamic.t0_s))

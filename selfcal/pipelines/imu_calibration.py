"""Use cases ``selfcal calibrate imu`` and ``selfcal calibrate imu-pair``: recording in, result object out."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from selfcal.graphs import imu as gi
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
            "relative_gain_imu1": {
                name: {"G": _nested(G), "S_sigma": _nested(sigma),
                       "meaning": "v_imu0 = R G v_imu1, G = I + S symmetric: imu1's scale and non-orthogonality"}
                for name, (G, sigma) in e.gains.items()},
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


@dataclass(frozen=True)
class Optional_:
    """A pair quantity estimated only where the data determine it: its 1-sigma must stay below ``limit``."""

    label: str
    sigma: object  # PairEstimate -> float
    limit: float
    hint: str


# A lever arm known only to a centimetre, a clock offset only to a millisecond or a relative gain only to 0.2 %
# is not worth reporting as calibrated: at hand-held rates each changes the prediction by less than MEMS noise.
OPTIONAL = {
    "time_offset": Optional_("time offset", lambda e: e.time_offset_sigma_s, 1e-3,
                             "needs rotation whose rate changes quickly (shake or twist the rig)"),
    "lever_arm": Optional_("lever arm", lambda e: float(np.max(e.lever_arm_sigma_m)), 0.01,
                           "needs rotation rate and angular acceleration about several axes"),
    "accel_gain": Optional_("accelerometer relative gain", lambda e: float(np.max(e.gains["accel"][1])), 2e-3,
                            "needs static poses or motion with gravity along all three axes"),
    "gyro_gain": Optional_("gyro relative gain", lambda e: float(np.max(e.gains["gyro"][1])), 2e-3,
                           "needs rotation about all three axes"),
}


def calibrate_imu_pair(recording: Recording, imu0: str, imu1: str, lever_arm: bool | None = None,
                       time_offset: bool | None = None, lowpass_hz: float | None = 5.0,
                       gains: bool | None = False) -> PairCalibration:
    """Rotation imu0 <- imu1 from the static poses (if any) and the moving parts of the recording.

    ``lever_arm`` / ``time_offset`` / ``gains``: True forces, False skips, None estimates where the data
    determine them (1-sigma below the limits in ``OPTIONAL``), and says so in the notes otherwise.
    ``gains`` (off by default) adds imu1's scale and non-orthogonality relative to imu0, for raw outputs that
    were not calibrated first: R is then the rotation part of the map between them (polar decomposition).
    """
    problem = gp.problem_from_imus(recording.imu(imu0), recording.imu(imu1), lowpass_hz)
    static, dynamic, dt0 = problem.static, problem.dynamic, problem.initial_dt_s
    if not static and dynamic is None:
        raise gp.DegenerateDataError(f"{imu0}/{imu1}: no static poses and no motion found in the recording")
    requested = {"time_offset": time_offset, "lever_arm": lever_arm, "accel_gain": gains, "gyro_gain": gains}
    possible = {"time_offset": dynamic is not None, "lever_arm": dynamic is not None,
                "accel_gain": dynamic is not None or len(static) >= 6, "gyro_gain": dynamic is not None}
    model = gp.PairModel(**{name: possible[name] and requested[name] is not False for name in OPTIONAL})
    estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
    weak = {name: getattr(model, name) and spec.sigma(estimate) > spec.limit for name, spec in OPTIONAL.items()}
    for name, spec in OPTIONAL.items():
        if weak[name] and requested[name]:
            raise gp.DegenerateDataError(f"{imu0}/{imu1}: {spec.label} not determined by this recording: {spec.hint}")
    if any(weak.values()):
        model = gp.PairModel(**{name: getattr(model, name) and not weak[name] for name in OPTIONAL})
        estimate = gp.solve_pair(static, dynamic, model, initial_dt_s=dt0)
        estimate.notes += [f"{spec.label} not estimated: the data do not determine it ({spec.hint})"
                           for name, spec in OPTIONAL.items() if weak[name]]
    return PairCalibration(imu0, imu1, estimate, len(static), 0 if dynamic is None else len(dynamic.t0_s))

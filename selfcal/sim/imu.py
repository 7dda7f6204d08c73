"""Simulated IMU recordings with known truth: one IMU, or two rigidly mounted IMUs.

A scenario holds the truth as attributes (trajectory, intrinsics, noise, extrinsics) and gives
``exact_measurements()`` (the noise-free measurement model), ``perturbed_measurements(seed)`` (plus white
noise and bias random walk) and ``truth()`` (a YAML-serialisable dict, never part of a recording's sensors).

Measurement model (:mod:`selfcal.models.imu`), per IMU, at the true sampling instant t::

    f_S = R_W_S^T (a_W + g e_z)                                     specific force, body frame
    a_raw = inv(M_a) f_S + b_a(T) + sum_c k_a,c (c - c_ref) [+ n_a + walk_a]
    w_raw = inv(M_g) w_S + b_g(T) + A f_S + sum_c k_g,c (c - c_ref) [+ n_g + walk_g]

with T the temperature channel and c the auxiliary channels that carry an effect.  White noise has the
discrete sigma ``density * sqrt(rate_hz)`` per sample; the bias walk steps by ``random_walk * sqrt(dt)``
per sample and starts at 0 at the first sample (Kalibr's discrete model).

Two IMUs (``imu0``, ``imu1``): ``v_imu0 = R_imu0_imu1 v_imu1``, imu1 at ``r_m`` (imu0 frame), clocks with
``t_imu0 = t_imu1 + dt_s``: imu1's sample stamped t1 (its clock) is taken at imu0 time ``t1 + dt_s``,
where the trajectory is evaluated; its specific force follows the rigid-body lever-arm relation
(:func:`selfcal.core.inertial.specific_force_at_lever_arm`).  Both clocks start stamping at ``t0_ns``.

References
----------
Kalibr wiki, "IMU Noise Model" (noise densities and the discrete-time simulation used here).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from selfcal.core import inertial
from selfcal.core.inertial import ImuNoise
from selfcal.io.recording import Recording, imu_sensor, write_recording
from selfcal.models import imu
from selfcal.core import so3
from selfcal.models.imu import AccelIntrinsics, GyroIntrinsics
from selfcal.sim.trajectories import DEFAULT_T0_NS, Trajectory, TrajectorySample, to_plain

# --- noise -----------------------------------------------------------------------------------------------------

# --- environment: temperature and auxiliary channels -------------------------------------------------------------

@dataclass(frozen=True)
class TemperatureProfile:
    """First-order warm-up ``T(t) = end + (start - end) exp(-t / time_constant_s)`` in degC (t in s)."""

    start_degC: float = 20.0
    end_degC: float = 35.0
    time_constant_s: float = 600.0

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return self.end_degC + (self.start_degC - self.end_degC) * np.exp(-t / self.time_constant_s)

    def to_dict(self) -> dict:
        return {"kind": "first_order", "start_degC": self.start_degC, "end_degC": self.end_degC,
                "time_constant_s": self.time_constant_s}


@dataclass
class AuxChannel:
    """An auxiliary column (e.g. ``supply_voltage [V]``), optionally with a hidden effect on the raw output.

    ``values`` is a function of the true time t (s, imu0 clock) or an array with one value per sample of the
    sensor.  The effect adds ``accel_slope (c - reference)`` (m s^-2 per unit) to the raw accelerometer and
    ``gyro_slope (c - reference)`` (rad s^-1 per unit) to the raw gyro.
    """

    values: Callable[[np.ndarray], np.ndarray] | np.ndarray
    unit: str
    accel_slope: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_slope: np.ndarray = field(default_factory=lambda: np.zeros(3))
    reference: float = 0.0

    @classmethod
    def of(cls, spec) -> AuxChannel:
        """An AuxChannel as is, or a plain ``(values, unit)`` pair (no effect)."""
        return spec if isinstance(spec, AuxChannel) else cls(spec[0], spec[1])

    def at(self, t_s: np.ndarray) -> np.ndarray:
        values = self.values(t_s) if callable(self.values) else np.asarray(self.values, dtype=float)
        values = np.broadcast_to(np.asarray(values, dtype=float), np.shape(t_s))
        return np.array(values)

    def to_dict(self) -> dict:
        return {"unit": self.unit, "accel_slope": to_plain(np.asarray(self.accel_slope, dtype=float)),
                "gyro_slope": to_plain(np.asarray(self.gyro_slope, dtype=float)), "reference": float(self.reference),
                "values": "function of t" if callable(self.values) else "array"}


# --- intrinsics -------------------------------------------------------------------------------------------------

def _signed(rng, level, size):
    """Random sign times 0.5..1.5 x level: an effect that is present, of the stated order, never ~0 by chance."""
    return rng.choice([-1.0, 1.0], size=size) * rng.uniform(0.5, 1.5, size=size) * level + 0.0  # no -0.0


def tedaldi_T(angles_rad) -> np.ndarray:
    """Non-orthogonality ``T = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]]`` (Tedaldi 2014)."""
    a_yz, a_zy, a_zx = angles_rad
    return np.array([[1.0, -a_yz, a_zy], [0.0, 1.0, -a_zx], [0.0, 0.0, 1.0]])


def random_intrinsics(seed, accel_bias_m_s2: float = 0.05, gyro_bias_rad_s: float = 0.01,
                      scale: tuple[float, float] = (0.005, 0.02), misalignment_rad: float = 1e-3,
                      gyro_axis_rotation_rad: float = 1e-3, g_sensitivity: float = 0.0,
                      accel_temperature_slope: float = 0.0, gyro_temperature_slope: float = 0.0,
                      temperature_ref_degC: float = 25.0) -> tuple[AccelIntrinsics, GyroIntrinsics]:
    """Realistic MEMS intrinsics; every magnitude is a random sign times 0.5..1.5 of its level.

    Accelerometer ``M_a = T(angles) K`` (upper triangular), ``K = diag(1 / (1 + scale))`` so that
    ``a_raw_i = (1 + scale_i) f_i``; gyro ``M_g = Exp(rho) T(angles) K`` (full 3x3, rho the rotation of the
    gyro triad relative to the accelerometer frame).  Scales have magnitudes uniform in ``scale``.
    ``g_sensitivity`` (rad s^-1 per m s^-2, e.g. 1e-4), when non-zero, gives a random dense ``A``;
    temperature slopes in unit per degC (e.g. 1e-3 m s^-2/degC, 1e-4 rad s^-1/degC).
    """
    rng = np.random.default_rng(seed)

    def gains():
        s = rng.choice([-1.0, 1.0], size=3) * rng.uniform(*scale, size=3)
        return np.diag(1.0 / (1.0 + s))

    M_a = tedaldi_T(_signed(rng, misalignment_rad, 3)) @ gains()
    accel = AccelIntrinsics(M=M_a, bias=_signed(rng, accel_bias_m_s2, 3),
                            temperature_slope=_signed(rng, accel_temperature_slope, 3),
                            temperature_ref_degC=temperature_ref_degC)
    rho = _signed(rng, gyro_axis_rotation_rad, 3)
    M_g = so3.exp(rho) @ tedaldi_T(_signed(rng, misalignment_rad, 3)) @ gains()
    A = g_sensitivity * rng.normal(size=(3, 3)) if g_sensitivity else np.zeros((3, 3))
    gyro = GyroIntrinsics(M=M_g, bias=_signed(rng, gyro_bias_rad_s, 3), A=A,
                          temperature_slope=_signed(rng, gyro_temperature_slope, 3),
                          temperature_ref_degC=temperature_ref_degC)
    return accel, gyro


def _intrinsics_truth(accel: AccelIntrinsics, gyro: GyroIntrinsics) -> dict:
    """Intrinsics in the keys of the calibration YAML (``f = M (a_raw - bias)``, ``w = M (w_raw - bias - A f)``)."""
    accel_scale, accel_angles = imu.scale_and_misalignment(accel.M)
    gyro_scale, gyro_angles = imu.scale_and_misalignment(gyro.M)
    return {
        "accelerometers": {"M": accel.M, "bias": accel.bias, "scale": accel_scale, "misalignment_rad": accel_angles,
                           "temperature_slope": accel.temperature_slope,
                           "temperature_ref_degC": accel.temperature_ref_degC},
        "gyroscopes": {"M": gyro.M, "bias": gyro.bias, "A": gyro.A, "scale": gyro_scale,
                       "misalignment_rad": gyro_angles, "temperature_slope": gyro.temperature_slope,
                       "temperature_ref_degC": gyro.temperature_ref_degC},
    }


# --- one simulated IMU -----------------------------------------------------------------------------------------

@dataclass
class _Unit:
    """One IMU of a scenario: intrinsics, noise, rate, channels, pose on the body and clock offset."""

    name: str
    accel: AccelIntrinsics
    gyro: GyroIntrinsics
    noise: ImuNoise
    rate_hz: float
    channels: dict
    R_imu0_imu: np.ndarray = field(default_factory=lambda: np.eye(3))
    r_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dt_s: float = 0.0

    def stamps(self, duration_s: float, t0_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (int64 ns, own clock) over [0, duration_s], and the true imu0-clock instants (s) they mark."""
        n = int(np.floor(duration_s * self.rate_hz + 1e-9)) + 1
        offset_ns = np.round(np.arange(n) * (1e9 / self.rate_hz)).astype(np.int64)
        return t0_ns + offset_ns, offset_ns * 1e-9 + self.dt_s

    def kinematics(self, sample: TrajectorySample, gravity_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
        """True (w, f) in this IMU's frame: lever arm in the imu0 frame, then rotated, ``v_imu = R^T v_imu0``."""
        f0 = sample.specific_force_S(gravity_m_s2)
        if np.any(self.r_m):
            f0 = inertial.specific_force_at_lever_arm(f0, sample.w_S, sample.w_dot_S, self.r_m)
        return sample.w_S @ self.R_imu0_imu, f0 @ self.R_imu0_imu

    def meta(self, gravity_m_s2: float) -> dict:
        return {"sensor_type": "imu", "rate_hz": float(self.rate_hz), "gravity_m_s2": float(gravity_m_s2),
                **self.noise.to_dict()}

    def effects(self, temperature) -> list[str]:
        """Audit effect names present in this IMU's truth (``bias_instability`` only in perturbed data)."""
        a_scale, a_angles = imu.scale_and_misalignment(self.accel.M)
        g_scale, _ = imu.scale_and_misalignment(self.gyro.M)
        present = {
            "accel_bias": np.any(self.accel.bias), "gyro_bias": np.any(self.gyro.bias),
            "accel_scale": np.any(np.abs(a_scale) > 1e-15), "gyro_scale": np.any(np.abs(g_scale) > 1e-15),
            "accel_misalignment": np.any(np.abs(a_angles) > 1e-15),
            "gyro_misalignment": np.any(np.abs(self.gyro.M - np.diag(np.diag(self.gyro.M))) > 1e-15),
            "gyro_g_sensitivity": np.any(self.gyro.A),
            "bias_temperature": temperature is not None and (np.any(self.accel.temperature_slope)
                                                             or np.any(self.gyro.temperature_slope)),
            "bias_instability": self.noise.accelerometer_random_walk > 0 or self.noise.gyroscope_random_walk > 0,
        }
        names = [k for k, v in present.items() if v]
        names += [f"channel:{k}" for k, c in self.channels.items()
                  if np.any(c.accel_slope) or np.any(c.gyro_slope)]
        return names


def _temperature_at(temperature, t_s):
    return None if temperature is None else np.asarray(temperature(t_s), dtype=float) * np.ones_like(t_s)


class _ScenarioBase:
    """Shared engine: subclasses set ``trajectory``, ``gravity_m_s2``, ``temperature``, ``t0_ns``, ``_units()``."""

    trajectory: Trajectory
    gravity_m_s2: float
    temperature: Callable | None
    t0_ns: int

    def _units(self) -> list[_Unit]:
        raise NotImplementedError

    def _simulate(self, unit: _Unit):
        t_ns, t_true_s = unit.stamps(self.trajectory.duration_s, self.t0_ns)
        sample = self.trajectory.evaluate(t_true_s)
        w, f = unit.kinematics(sample, self.gravity_m_s2)
        temp = _temperature_at(self.temperature, t_true_s)
        accel_raw = unit.accel.raw_from_specific_force(f, temp)
        gyro_raw = unit.gyro.raw_from_rate(w, f, temp)
        channels = {} if temp is None else {"temperature": (temp, "degC")}
        for name, channel in unit.channels.items():
            c = channel.at(t_true_s)
            accel_raw = accel_raw + np.multiply.outer(c - channel.reference, np.asarray(channel.accel_slope, float))
            gyro_raw = gyro_raw + np.multiply.outer(c - channel.reference, np.asarray(channel.gyro_slope, float))
            channels[name] = (c, channel.unit)
        return t_ns, gyro_raw, accel_raw, channels

    def exact_measurements(self) -> Recording:
        """Noise-free raw measurements of every IMU through the measurement model."""
        sensors = {}
        for unit in self._units():
            t_ns, gyro_raw, accel_raw, channels = self._simulate(unit)
            sensors[unit.name] = imu_sensor(unit.name, t_ns, gyro_raw, accel_raw, channels,
                                            unit.meta(self.gravity_m_s2))
        return Recording(path=None, sensors=sensors)

    def noise_realisation(self, seed) -> dict:
        """The noise ``perturbed_measurements(seed)`` adds, per sensor: white and bias-walk parts, (N, 3) each.

        Returns ``{name: {"accel_white", "gyro_white", "accel_walk", "gyro_walk"}}``; the walks start at 0.
        """
        units = self._units()
        out = {}
        for unit, rng in zip(units, np.random.default_rng(seed).spawn(len(units))):
            n = len(unit.stamps(self.trajectory.duration_s, self.t0_ns)[0])
            z = rng.standard_normal((4, n, 3))
            sigma_a, sigma_g = unit.noise.white_sigma(unit.rate_hz)
            step_a, step_g = unit.noise.walk_step_sigma(unit.rate_hz)
            walk = np.cumsum(z[2:, :-1], axis=1)
            walk = np.concatenate([np.zeros((2, 1, 3)), walk], axis=1)
            out[unit.name] = {"accel_white": sigma_a * z[0], "gyro_white": sigma_g * z[1],
                              "accel_walk": step_a * walk[0], "gyro_walk": step_g * walk[1]}
        return out

    def perturbed_measurements(self, seed) -> Recording:
        """Exact measurements plus white noise and bias random walk, drawn from ``default_rng(seed)``."""
        noise = self.noise_realisation(seed)
        sensors = {}
        for unit in self._units():
            t_ns, gyro_raw, accel_raw, channels = self._simulate(unit)
            n = noise[unit.name]
            sensors[unit.name] = imu_sensor(unit.name, t_ns, gyro_raw + n["gyro_white"] + n["gyro_walk"],
                                            accel_raw + n["accel_white"] + n["accel_walk"], channels,
                                            unit.meta(self.gravity_m_s2))
        return Recording(path=None, sensors=sensors)

    def _sensor_truth(self, unit: _Unit) -> dict:
        # imu1's stamp t1 marks imu0 time t1 + dt: an interval [s, e] of imu0 time is [s - dt, e - dt] on its clock
        intervals_ns = [[self.t0_ns + round((start - unit.dt_s) * 1e9), self.t0_ns + round((end - unit.dt_s) * 1e9)]
                        for start, end in self.trajectory.static_intervals_s]
        return {"rate_hz": unit.rate_hz, "noise": unit.noise.to_dict(), **_intrinsics_truth(unit.accel, unit.gyro),
                "channels": {k: c.to_dict() for k, c in unit.channels.items()},
                "static_intervals_ns": intervals_ns, "effects": unit.effects(self.temperature)}

    def _common_truth(self) -> dict:
        temperature = None
        if self.temperature is not None:
            temperature = self.temperature.to_dict() if hasattr(self.temperature, "to_dict") else {"kind": "custom"}
        return {"gravity_m_s2": self.gravity_m_s2, "t0_ns": int(self.t0_ns),
                "static_intervals_s": [list(iv) for iv in self.trajectory.static_intervals_s],
                "static_intervals_convention": "true imu0-clock time in s after the first imu0 sample (t0_ns); "
                                               "the body is exactly at rest on each closed interval",
                "temperature": temperature, "trajectory": self.trajectory.to_dict(),
                "sensors": {u.name: self._sensor_truth(u) for u in self._units()}}

    def truth(self) -> dict:
        raise NotImplementedError

    def write(self, path, seed=None, overwrite: bool = False) -> Path:
        """Write the recording (exact if ``seed`` is None, else perturbed) with ``truth/truth.yaml``."""
        rec = self.exact_measurements() if seed is None else self.perturbed_measurements(seed)
        truth = self.truth()
        truth["measurements"] = "exact" if seed is None else {"perturbed_seed": seed}
        return write_recording(rec, path, truth=truth, overwrite=overwrite)


@dataclass
class ImuScenario(_ScenarioBase):
    """One IMU (sensor ``imu0``) moved along ``trajectory``; its body frame is the trajectory's S frame.

    ``temperature``: a :class:`TemperatureProfile` or any function t_s -> degC (recorded as channel
    ``temperature [degC]``, drives the intrinsics' temperature slopes).  ``channels``: name ->
    :class:`AuxChannel` or ``(values, unit)``.
    """

    trajectory: Trajectory
    accel: AccelIntrinsics = field(default_factory=AccelIntrinsics)
    gyro: GyroIntrinsics = field(default_factory=GyroIntrinsics)
    noise: ImuNoise = field(default_factory=ImuNoise)
    rate_hz: float = 200.0
    gravity_m_s2: float = inertial.STANDARD_GRAVITY_M_S2
    temperature: Callable | None = None
    channels: dict = field(default_factory=dict)
    t0_ns: int = DEFAULT_T0_NS

    def _units(self) -> list[_Unit]:
        return [_Unit("imu0", self.accel, self.gyro, self.noise, self.rate_hz,
                      {k: AuxChannel.of(v) for k, v in self.channels.items()})]

    def truth(self) -> dict:
        """All true parameters (plain lists and floats, YAML-serialisable)."""
        return to_plain({"kind": "imu", **self._common_truth()})


@dataclass
class ImuPairScenario(_ScenarioBase):
    """Two rigidly mounted IMUs (sensors ``imu0``, ``imu1``) on ``trajectory`` (imu0 = the S frame).

    ``R_imu0_imu1``: ``v_imu0 = R v_imu1``; ``r_m``: imu1's position in the imu0 frame (lever arm, m);
    ``dt_s``: ``t_imu0 = t_imu1 + dt_s``.  ``rate1_hz`` None means imu0's rate.
    """

    trajectory: Trajectory
    R_imu0_imu1: np.ndarray = field(default_factory=lambda: np.eye(3))
    r_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dt_s: float = 0.0
    accel0: AccelIntrinsics = field(default_factory=AccelIntrinsics)
    gyro0: GyroIntrinsics = field(default_factory=GyroIntrinsics)
    accel1: AccelIntrinsics = field(default_factory=AccelIntrinsics)
    gyro1: GyroIntrinsics = field(default_factory=GyroIntrinsics)
    noise0: ImuNoise = field(default_factory=ImuNoise)
    noise1: ImuNoise = field(default_factory=ImuNoise)
    rate_hz: float = 200.0
    rate1_hz: float | None = None
    gravity_m_s2: float = inertial.STANDARD_GRAVITY_M_S2
    temperature: Callable | None = None
    channels0: dict = field(default_factory=dict)
    channels1: dict = field(default_factory=dict)
    t0_ns: int = DEFAULT_T0_NS

    @classmethod
    def random(cls, trajectory: Trajectory, seed, rotation_deg: float = 180.0, lever_arm_m: float = 0.1,
               dt_s: float = 0.01, intrinsics: bool = True, **kwargs) -> ImuPairScenario:
        """Random extrinsics (rotation angle up to ``rotation_deg``, lever arm of norm ``lever_arm_m``, the given
        ``dt_s``) and, if ``intrinsics``, :func:`random_intrinsics` for each IMU; ``kwargs`` go to the class."""
        rng = np.random.default_rng(seed)
        axis = rng.normal(size=3)
        R = so3.exp(np.radians(rotation_deg) * rng.uniform(0.0, 1.0) * axis / np.linalg.norm(axis))
        r = rng.normal(size=3)
        r = lever_arm_m * r / np.linalg.norm(r)
        seed0, seed1 = (int(s) for s in rng.integers(0, 2**31, size=2))
        if intrinsics:
            for suffix, sub_seed in (("0", seed0), ("1", seed1)):
                accel, gyro = random_intrinsics(sub_seed)
                kwargs.setdefault("accel" + suffix, accel)
                kwargs.setdefault("gyro" + suffix, gyro)
        return cls(trajectory, R_imu0_imu1=R, r_m=r, dt_s=dt_s, **kwargs)

    def _units(self) -> list[_Unit]:
        return [
            _Unit("imu0", self.accel0, self.gyro0, self.noise0, self.rate_hz,
                  {k: AuxChannel.of(v) for k, v in self.channels0.items()}),
            _Unit("imu1", self.accel1, self.gyro1, self.noise1, self.rate1_hz or self.rate_hz,
                  {k: AuxChannel.of(v) for k, v in self.channels1.items()},
                  np.asarray(self.R_imu0_imu1, dtype=float), np.asarray(self.r_m, dtype=float), float(self.dt_s)),
        ]

    def truth(self) -> dict:
        """All true parameters, with the pair extrinsics in the keys of the pair calibration YAML."""
        pair = {"imu0": "imu0", "imu1": "imu1", "rotation_imu0_imu1": np.asarray(self.R_imu0_imu1, dtype=float),
                "rotation_convention": "v_imu0 = R v_imu1", "lever_arm_m": np.asarray(self.r_m, dtype=float),
                "lever_arm_convention": "position of imu1 in the imu0 frame",
                "time_offset_s": float(self.dt_s), "time_offset_convention": "t_imu0 = t_imu1 + dt",
                "effects": (["time_offset"] if self.dt_s else []) + (["lever_arm"] if np.any(self.r_m) else [])}
        return to_plain({"kind": "imu_pair", **self._common_truth(), "pair": pair})

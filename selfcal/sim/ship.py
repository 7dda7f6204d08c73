"""Simulated ship voyages: a drifting gyro, an accelerometer off the centre of rotation, a speed log and GPS.

The vessel of patent 003 (drift compensation from the accelerometer tilt): the ship rolls and pitches about
its equilibrium, heaves on the swell, accelerates, brakes and turns.  Its gyro drifts; the direction of the
total force vector measured by the accelerometer gives the tilt that corrects it, once the known
accelerations (surge ``dv/dt`` from the speed log or GPS speed, centrifugal ``v x yaw rate``) are removed;
heave changes only the magnitude of the force when the ship is level.

Frames and conventions
----------------------
Body ``S`` (= the gyro/IMU frame, origin at the centre of rotation): x forward, y to port (left), z up.
World ``W``: local level, z up (x, y horizontal; the heading ``yaw`` is measured from W's x axis towards
its y axis).  Attitude by ZYX Euler angles::

    R_W_S = Rz(yaw) Ry(pitch) Rx(roll)          v_W = R_W_S v_S

(right-handed: positive roll about x raises the port side, positive pitch about y (to port) lowers the
bow, positive yaw turns to port).  Body rates from the Euler rates, exact::

    w_S = [roll_dot - sin(pitch) yaw_dot,
           cos(roll) pitch_dot + sin(roll) cos(pitch) yaw_dot,
           -sin(roll) pitch_dot + cos(roll) cos(pitch) yaw_dot]

and ``w_dot_S`` is its analytic time derivative (exact to rounding; the tests compare it with a central
difference).  The centre moves with speed ``v(t)`` along the heading (plus an optional constant current)
and heaves by ``z(t)``, so its acceleration is exact::

    a_W = v_dot [cos yaw, sin yaw, 0] + v yaw_dot [-sin yaw, cos yaw, 0] + z_ddot e_z
                (surge)                   (centrifugal)                    (heave)

The accelerometer sits at ``r_m`` (body frame) from the centre (:func:`selfcal.core.inertial.specific_force_at_lever_arm`)::

    f_S = R_W_S^T (a_W + g e_z) + w_dot_S x r + w_S x (w_S x r)

Motion models (all continuous in time, evaluable at any t)
---------------------------------------------------------
* roll, pitch: sums of sinusoids with periods in 5-20 s (a few degrees);
* heave ``z``: sums of sinusoids (long swell, 25-60 s and metres in ``kind='heave'``);
* yaw: initial heading + small wave-induced sinusoid + the integral of a yaw rate made of smooth turns
  (each turn ramps up and down with the septic :func:`smooth_step`, integrated in closed form);
* speed through the water ``v``: initial speed + smooth surge (acceleration / braking) steps.

Measurements
------------
``imu0``: ``w_raw = (1 + s_g) w_S + b_g(t) [+ n_g]`` (per-axis gyro scale error ``s_g``, 0 by default),
``a_raw = f_S + b_a [+ n_a + walk_a]``.  The gyro bias ``b_g(t)``
is part of the truth (seeded by the scenario's seed): an initial bias of magnitude ``gyro_bias_deg_h`` in a
random direction plus a random walk precomputed on the IMU grid, present in *exact* measurements too
(``exact`` means "no white noise", not "no drift").  ``speed0``: ``speed_log [m s^-1]`` = ``speed_log_scale
* v`` (+ noise).  ``gps0``: ``speed [m s^-1]`` = horizontal speed over ground ``|v e_heading + current|``
(+ noise).  All clocks start at ``t0_ns``; stamps are int64 ns.

References
----------
CN103109159 (C2Sat), "Method for compensating drift in a position measuring device" (seed 003).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.core import inertial
from selfcal.io.recording import Recording, SensorData, imu_sensor, write_recording
from selfcal.sim.trajectories import DEFAULT_T0_NS
from selfcal.core.inertial import ImuNoise
from selfcal.sim.trajectories import E_Z, Trajectory, TrajectorySample, smooth_step, to_plain

KINDS = ("calm", "heave", "turning")
DEG_H = np.pi / 180.0 / 3600.0  # 1 deg/h in rad/s
# 1 deg/h/sqrt(h) in rad s^-2 Hz^-1/2 (= rad/s per sqrt(s)), Kalibr's gyroscope_random_walk unit
DEG_H_SQRT_H = DEG_H / np.sqrt(3600.0)


# --- smooth building blocks --------------------------------------------------------------------------------------

class SinusoidSum:
    """``x(t) = sum_k A_k sin(2 pi t / T_k + phase_k)`` with exact first and second derivatives."""

    def __init__(self, amplitude, period_s, phase_rad):
        self.amplitude = np.atleast_1d(np.asarray(amplitude, dtype=float))
        self.period_s = np.atleast_1d(np.asarray(period_s, dtype=float))
        self.phase_rad = np.atleast_1d(np.asarray(phase_rad, dtype=float))

    @property
    def omega(self) -> np.ndarray:
        return 2.0 * np.pi / self.period_s

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, x_dot, x_ddot at times t (N,)."""
        om = self.omega
        arg = np.multiply.outer(t, om) + self.phase_rad
        sin, cos = np.sin(arg), np.cos(arg)
        return sin @ self.amplitude, cos @ (self.amplitude * om), -(sin @ (self.amplitude * om**2))

    def second_derivative_bound(self) -> float:
        """``sum_k |A_k| omega_k^2``: no |x_ddot| exceeds it."""
        return float(np.sum(np.abs(self.amplitude) * self.omega**2))

    def scaled(self, factor: float) -> SinusoidSum:
        return SinusoidSum(self.amplitude * factor, self.period_s, self.phase_rad)

    def to_dict(self, unit_factor: float = 1.0, unit: str = "") -> dict:
        return {f"amplitude{unit}": (self.amplitude * unit_factor).tolist(), "period_s": self.period_s.tolist(),
                "phase_rad": self.phase_rad.tolist()}


def _step_integral(u):
    """``int_0^u s(x) dx`` of the septic step for u clipped to [0, 1], plus ``u - 1`` beyond 1."""
    uc = np.clip(u, 0.0, 1.0)
    return uc**5 * (7.0 - 14.0 * uc + 10.0 * uc**2 - 2.5 * uc**3) + np.maximum(u - 1.0, 0.0)


class SmoothSteps:
    """``y(t) = sum_k h_k s((t - start_k) / ramp_k)`` (septic steps) with its integral from 0 and derivatives.

    Each step rises by ``h_k`` over ``ramp_k`` seconds with zero 1st-3rd derivatives at both ends, so the
    sum has continuous rate, acceleration and jerk.
    """

    def __init__(self, start_s=(), ramp_s=(), height=()):
        self.start_s = np.asarray(start_s, dtype=float).reshape(-1)
        self.ramp_s = np.asarray(ramp_s, dtype=float).reshape(-1)
        self.height = np.asarray(height, dtype=float).reshape(-1)

    def evaluate(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(integral from 0 to t, y, y_dot, y_ddot) at times t (N,); steps must start at t >= 0."""
        u = (np.subtract.outer(t, self.start_s)) / self.ramp_s
        s, s1, s2 = smooth_step(u)
        integral = _step_integral(u) @ (self.height * self.ramp_s)
        return integral, s @ self.height, s1 @ (self.height / self.ramp_s), s2 @ (self.height / self.ramp_s**2)

    def scaled(self, factor: float) -> SmoothSteps:
        return SmoothSteps(self.start_s, self.ramp_s, self.height * factor)


# --- the ship's motion -------------------------------------------------------------------------------------------

def _sinusoids(rng, n, amplitude, period_s) -> SinusoidSum:
    return SinusoidSum(rng.uniform(*amplitude, size=n) * rng.choice([-1.0, 1.0], size=n),
                       rng.uniform(*period_s, size=n), rng.uniform(0.0, 2.0 * np.pi, size=n))


# per kind: roll/pitch/yaw-wave amplitudes (deg) and periods (s), heave amplitude (m) and periods (s), speeds
_KIND_PARAMS = {
    "calm": dict(roll_deg=(0.3, 1.0), pitch_deg=(0.15, 0.5), rp_period_s=(6.0, 14.0), yaw_wave_deg=(0.1, 0.3),
                 heave_m=(0.05, 0.2), heave_period_s=(6.0, 12.0), n_heave=2, speed_m_s=(5.0, 8.0)),
    "heave": dict(roll_deg=(1.0, 3.0), pitch_deg=(0.5, 1.5), rp_period_s=(5.0, 20.0), yaw_wave_deg=(0.2, 0.5),
                  heave_m=(1.0, 3.0), heave_period_s=(25.0, 60.0), n_heave=3, speed_m_s=(4.0, 7.0)),
    "turning": dict(roll_deg=(0.5, 1.5), pitch_deg=(0.25, 0.75), rp_period_s=(5.0, 20.0), yaw_wave_deg=(0.1, 0.3),
                    heave_m=(0.1, 0.4), heave_period_s=(6.0, 15.0), n_heave=2, speed_m_s=(8.0, 12.0)),
}


class ShipMotion(Trajectory):
    """Continuous-time truth of the ship's centre of rotation (see the module docstring for the equations).

    Attributes
    ----------
    roll, pitch, yaw_wave : SinusoidSum, rad.
    heave : SinusoidSum, m (vertical position of the centre).
    turns : SmoothSteps of the yaw rate, rad/s (each turn is a step up and a step down).
    surge : SmoothSteps of the speed through the water, m/s.
    yaw0_rad, speed0_m_s : initial heading and speed.
    current_W_m_s : (2,) constant water current over ground, m/s (affects GPS speed, not the accelerations).
    turn_list : list of dicts (start_s, ramp_s, hold_s, yaw_rate_deg_s) for the truth.
    surge_list : list of dicts (start_s, duration_s, dv_m_s).
    """

    def __init__(self, kind: str = "calm", duration_s: float = 3600.0, seed=0, roll_scale: float = 1.0,
                 pitch_scale: float = 1.0, yaw_wave_scale: float = 1.0, heave_scale: float = 1.0,
                 current_m_s=(0.0, 0.0)):
        if kind not in KINDS:
            raise ValueError(f"unknown ship scenario kind {kind!r} (choose from {', '.join(KINDS)})")
        self.kind, self.duration_s, self.seed = kind, float(duration_s), seed
        self.static_intervals_s = []
        p = _KIND_PARAMS[kind]
        rng = np.random.default_rng(seed)
        d = np.radians
        self.roll = _sinusoids(rng, 3, d(p["roll_deg"]), p["rp_period_s"]).scaled(roll_scale)
        self.pitch = _sinusoids(rng, 2, d(p["pitch_deg"]), p["rp_period_s"]).scaled(pitch_scale)
        self.yaw_wave = _sinusoids(rng, 1, d(p["yaw_wave_deg"]), (8.0, 20.0)).scaled(yaw_wave_scale)
        self.heave = _sinusoids(rng, p["n_heave"], p["heave_m"], p["heave_period_s"]).scaled(heave_scale)
        self.yaw0_rad = float(rng.uniform(-np.pi, np.pi))
        self.speed0_m_s = float(rng.uniform(*p["speed_m_s"]))
        self.current_W_m_s = np.asarray(current_m_s, dtype=float).reshape(2)
        self.turn_list, self.surge_list = [], []
        if kind == "turning":
            self._schedule_manoeuvres(rng)
        starts = [[t["start_s"], t["start_s"] + t["ramp_s"] + t["hold_s"]] for t in self.turn_list]
        rates = [[np.radians(t["yaw_rate_deg_s"]), -np.radians(t["yaw_rate_deg_s"])] for t in self.turn_list]
        ramps = [[t["ramp_s"], t["ramp_s"]] for t in self.turn_list]
        self.turns = SmoothSteps(starts, ramps, rates)
        self.surge = SmoothSteps([s["start_s"] for s in self.surge_list], [s["duration_s"] for s in self.surge_list],
                                 [s["dv_m_s"] for s in self.surge_list])

    def _schedule_manoeuvres(self, rng) -> None:
        """Turns of 1-4 deg/s (5-10 s ramps, 15-90 s holds) and surges keeping the speed in 5-15 m/s."""
        t = rng.uniform(30.0, 90.0)
        while t < self.duration_s:
            ramp, hold = rng.uniform(5.0, 10.0), rng.uniform(15.0, 90.0)
            rate = rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 4.0)
            self.turn_list.append({"start_s": float(t), "ramp_s": float(ramp), "hold_s": float(hold),
                                   "yaw_rate_deg_s": float(rate)})
            t += 2 * ramp + hold + rng.uniform(60.0, 240.0)
        t, v = rng.uniform(20.0, 60.0), self.speed0_m_s
        while t < self.duration_s:
            target = rng.uniform(5.0, 15.0)
            # mean acceleration 0.05-0.15 m/s^2, braking 0.1-0.25 m/s^2 (peaks 2.19x the mean for the septic step)
            mean_accel = rng.uniform(0.05, 0.15) if target > v else rng.uniform(0.1, 0.25)
            duration = max(abs(target - v) / mean_accel, 5.0)
            self.surge_list.append({"start_s": float(t), "duration_s": float(duration), "dv_m_s": float(target - v)})
            v = target
            t += duration + rng.uniform(60.0, 300.0)

    # -- continuous-time truth --

    def euler(self, t_s):
        """(roll, pitch, yaw) each as (angle, rate, acceleration) tuples of (N,) arrays; yaw unwrapped."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        yaw_turn, r0, r1, _ = self.turns.evaluate(t)
        y0, y1, y2 = self.yaw_wave.evaluate(t)
        return self.roll.evaluate(t), self.pitch.evaluate(t), (self.yaw0_rad + yaw_turn + y0, r0 + y1, r1 + y2)

    def speed(self, t_s):
        """Speed through the water along the heading and its derivative, m/s and m/s^2, (N,) each."""
        _, dv, dv_dot, _ = self.surge.evaluate(np.atleast_1d(np.asarray(t_s, dtype=float)))
        return self.speed0_m_s + dv, dv_dot

    def speed_over_ground(self, t_s) -> np.ndarray:
        """Horizontal speed over ground ``|v e_heading + current|`` (heave excluded), m/s."""
        v, _ = self.speed(t_s)
        yaw = self.euler(t_s)[2][0]
        return np.hypot(v * np.cos(yaw) + self.current_W_m_s[0], v * np.sin(yaw) + self.current_W_m_s[1])

    def body_rates(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Body rate w_S (N, 3) rad/s and its exact derivative w_dot_S (N, 3) rad/s^2 from the Euler rates."""
        (r, r1, r2), (p, p1, p2), (_, y1, y2) = self.euler(t_s)
        sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
        w = np.stack([r1 - sp * y1, cr * p1 + sr * cp * y1, -sr * p1 + cr * cp * y1], axis=1)
        w_dot = np.stack([
            r2 - sp * y2 - cp * p1 * y1,
            cr * p2 - sr * r1 * p1 + sr * cp * y2 + cr * cp * r1 * y1 - sr * sp * p1 * y1,
            -sr * p2 - cr * r1 * p1 + cr * cp * y2 - sr * cp * r1 * y1 - cr * sp * p1 * y1,
        ], axis=1)
        return w, w_dot

    def R_W_S(self, t_s) -> np.ndarray:
        """``Rz(yaw) Ry(pitch) Rx(roll)``, (N, 3, 3)."""
        (r, _, _), (p, _, _), (y, _, _) = self.euler(t_s)
        return Rotation.from_euler("ZYX", np.stack([y, p, r], axis=1)).as_matrix()

    def acceleration_W(self, t_s) -> np.ndarray:
        """Acceleration of the centre of rotation (gravity excluded), (N, 3) m/s^2 (see module docstring)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        v, v_dot = self.speed(t)
        _, _, (yaw, yaw_dot, _) = self.euler(t)
        c, s = np.cos(yaw), np.sin(yaw)
        _, _, z2 = self.heave.evaluate(t)
        return np.stack([v_dot * c - v * yaw_dot * s, v_dot * s + v * yaw_dot * c, z2], axis=1)

    def position_W(self, t_s, step_s: float = 0.05) -> np.ndarray:
        """Position of the centre (N, 3), m, from p(0) = (0, 0, heave(0)).

        Vertical: the heave, exact.  Horizontal: ``int (v e_heading + current) dt`` by the trapezoid rule on a
        ``step_s`` grid (local error ``step^3 |d2v/dt2| / 12`` per step, below 1e-6 m per hour for ship
        motion at 0.05 s) and cubic Hermite interpolation with the exact velocity between grid points.
        """
        from scipy.interpolate import CubicHermiteSpline

        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        end = max(float(np.max(t)), step_s)
        grid = np.linspace(0.0, end, int(np.ceil(end / step_s)) + 1)
        v_grid = self._horizontal_velocity(grid)
        steps = 0.5 * (v_grid[1:] + v_grid[:-1]) * np.diff(grid)[:, None]
        p_grid = np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        xy = CubicHermiteSpline(grid, p_grid, v_grid, axis=0)(t)
        return np.column_stack([xy, self.heave.evaluate(t)[0]])

    def _horizontal_velocity(self, t) -> np.ndarray:
        v, _ = self.speed(t)
        yaw = self.euler(t)[2][0]
        return np.column_stack([v * np.cos(yaw), v * np.sin(yaw)]) + self.current_W_m_s

    def evaluate(self, t_s) -> TrajectorySample:
        """Full kinematics of the centre of rotation as a :class:`TrajectorySample` (reusable by the IMU sims)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        w, w_dot = self.body_rates(t)
        z, z1, _ = self.heave.evaluate(t)
        v_W = np.column_stack([self._horizontal_velocity(t), z1])
        return TrajectorySample(t, self.R_W_S(t), w, w_dot, self.position_W(t), v_W, self.acceleration_W(t))

    def to_dict(self) -> dict:
        return to_plain({
            "kind": self.kind, "seed": self.seed, "duration_s": self.duration_s,
            "euler_convention": "R_W_S = Rz(yaw) Ry(pitch) Rx(roll); body x forward, y left, z up; W z up",
            "roll": self.roll.to_dict(180.0 / np.pi, "_deg"), "pitch": self.pitch.to_dict(180.0 / np.pi, "_deg"),
            "yaw_wave": self.yaw_wave.to_dict(180.0 / np.pi, "_deg"), "heave": self.heave.to_dict(1.0, "_m"),
            "yaw0_deg": np.degrees(self.yaw0_rad), "speed0_m_s": self.speed0_m_s,
            "current_W_m_s": self.current_W_m_s, "turns": self.turn_list, "surges": self.surge_list,
        })


# --- the scenario ------------------------------------------------------------------------------------------------

def _stamps(duration_s: float, rate_hz: float, t0_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (int64 ns) over [0, duration_s] at rate_hz, and the same instants in s after t0."""
    n = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    offset_ns = np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    return t0_ns + offset_ns, offset_ns * 1e-9


class ShipScenario:
    """A ship voyage with known truth: IMU (drifting gyro, lever-armed accelerometer), speed log and GPS speed.

    Parameters
    ----------
    kind : 'calm' | 'heave' | 'turning'
        'calm': small roll/pitch, short low heave, constant speed and heading.  'heave': heave-dominated long
        swell (periods 25-60 s, amplitudes 1-3 m per component), larger roll.  'turning': turns of 1-4 deg/s
        at 5-15 m/s with surge acceleration and braking.
    duration_s, rate_hz : voyage length and IMU rate.
    seed : seeds the motion, the gyro bias (initial direction and walk); ``perturbed_measurements`` has its own.
    lever_arm_m : accelerometer position in the body frame relative to the centre of rotation, m.
    gyro_bias_deg_h : magnitude of the initial gyro bias (random direction), deg/h.
    gyro_bias_walk_deg_h_sqrt_h : bias random walk, deg/h per sqrt(h) (per axis; 0 for a constant bias).
    accel_bias_m_s2 : constant accelerometer bias (3,), m/s^2.
    accel_bias_of : optional ``f(t_s (n,), euler_rad (n, 3) roll/pitch/yaw) -> (n, 3)`` m/s^2, an accelerometer
        bias that varies (effects outside the audit's catalog: one that follows the heading, a step, ...).
    noise : white noise densities (and accel random walk) added by ``perturbed_measurements``; its
        ``gyroscope_random_walk`` is replaced by the true bias walk in sensor.yaml and never added twice.
    speed_log_scale : true scale of the speed log (1.02 = reads 2 % high).
    gyro_scale : (3,) per-axis gyro scale error, dimensionless: the gyro reads ``(1 + gyro_scale) w`` (0 = nominal;
        0.02 = reads 2 % high).
    speed_log_noise_m_s, gps_speed_noise_m_s : white noise sigmas per sample (perturbed only), m/s.
    speed_log_rate_hz, gps_rate_hz : sample rates, Hz.
    roll_scale, pitch_scale, yaw_wave_scale, heave_scale : multiply the seeded amplitudes (0 switches a motion
        off, e.g. for a heave-only check).
    current_m_s : constant water current over ground (2,), m/s (separates GPS speed from the speed log).
    gravity_m_s2, t0_ns : gravity magnitude and the first stamp.

    Attributes
    ----------
    motion : ShipMotion (the continuous-time truth), plus every parameter above as given.
    gyro_bias0_rad_s : (3,) initial gyro bias, rad/s.
    """

    def __init__(self, kind: str = "calm", duration_s: float = 3600.0, rate_hz: float = 50.0, seed=0,
                 lever_arm_m=(2.0, 0.5, 5.0), gyro_bias_deg_h: float = 10.0,
                 gyro_bias_walk_deg_h_sqrt_h: float = 10.0, accel_bias_m_s2=(0.0, 0.0, 0.0),
                 noise: ImuNoise | None = None, speed_log_scale: float = 1.0, speed_log_noise_m_s: float = 0.05,
                 speed_log_rate_hz: float = 1.0, gps_rate_hz: float = 1.0, gps_speed_noise_m_s: float = 0.05,
                 roll_scale: float = 1.0, pitch_scale: float = 1.0, yaw_wave_scale: float = 1.0,
                 heave_scale: float = 1.0, current_m_s=(0.0, 0.0), gravity_m_s2: float = inertial.STANDARD_GRAVITY_M_S2,
                 t0_ns: int = DEFAULT_T0_NS, gyro_scale=(0.0, 0.0, 0.0), accel_bias_of=None):
        self.kind, self.duration_s, self.rate_hz, self.seed = kind, float(duration_s), float(rate_hz), seed
        self.lever_arm_m = np.asarray(lever_arm_m, dtype=float).reshape(3)
        self.gyro_bias_deg_h = float(gyro_bias_deg_h)
        self.gyro_bias_walk_deg_h_sqrt_h = float(gyro_bias_walk_deg_h_sqrt_h)
        self.accel_bias_m_s2 = np.asarray(accel_bias_m_s2, dtype=float).reshape(3)
        self.accel_bias_of = accel_bias_of
        self.gyro_scale = np.asarray(gyro_scale, dtype=float).reshape(3)
        self.noise = noise if noise is not None else ImuNoise()
        self.speed_log_scale, self.speed_log_noise_m_s = float(speed_log_scale), float(speed_log_noise_m_s)
        self.speed_log_rate_hz, self.gps_rate_hz = float(speed_log_rate_hz), float(gps_rate_hz)
        self.gps_speed_noise_m_s = float(gps_speed_noise_m_s)
        self.gravity_m_s2, self.t0_ns = float(gravity_m_s2), int(t0_ns)
        rng_motion, rng_bias = np.random.default_rng(seed).spawn(2)
        self.motion = ShipMotion(kind, duration_s, rng_motion, roll_scale=roll_scale, pitch_scale=pitch_scale,
                                 yaw_wave_scale=yaw_wave_scale, heave_scale=heave_scale, current_m_s=current_m_s)
        self.motion.seed = seed
        direction = rng_bias.normal(size=3)
        self.gyro_bias0_rad_s = self.gyro_bias_deg_h * DEG_H * direction / np.linalg.norm(direction)
        t_ns, _ = self.imu_stamps()
        steps = rng_bias.standard_normal((len(t_ns) - 1, 3))
        self._gyro_walk_grid = np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)]) * (
            self.gyro_bias_walk_rad_s2_sqrt_hz / np.sqrt(self.rate_hz))

    # -- truth --

    @property
    def gyro_bias_walk_rad_s2_sqrt_hz(self) -> float:
        """The bias walk in Kalibr's unit (rad s^-2 / sqrt(Hz)): per-sample step ``walk * sqrt(1 / rate_hz)``."""
        return self.gyro_bias_walk_deg_h_sqrt_h * DEG_H_SQRT_H

    def imu_stamps(self) -> tuple[np.ndarray, np.ndarray]:
        """IMU stamps (int64 ns) and their true times (s after t0)."""
        return _stamps(self.duration_s, self.rate_hz, self.t0_ns)

    def truth_attitude(self, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(roll, pitch, yaw) in rad at times t_s (s after t0); yaw is continuous (unwrapped)."""
        (r, _, _), (p, _, _), (y, _, _) = self.motion.euler(t_s)
        return r, p, y

    def truth_gyro_bias(self, t_s) -> np.ndarray:
        """True gyro bias (N, 3), rad/s: initial bias + the seeded walk, linear between IMU samples."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        _, grid = self.imu_stamps()
        walk = np.column_stack([np.interp(t, grid, self._gyro_walk_grid[:, i]) for i in range(3)])
        return self.gyro_bias0_rad_s + walk

    def true_imu(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """True body rate w_S (N, 3) and specific force at the accelerometer f_S (N, 3), no sensor errors."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        w, w_dot = self.motion.body_rates(t)
        R = self.motion.R_W_S(t)
        f0 = np.einsum("nji,nj->ni", R, self.motion.acceleration_W(t) + self.gravity_m_s2 * E_Z)
        return w, inertial.specific_force_at_lever_arm(f0, w, w_dot, self.lever_arm_m)

    def truth(self) -> dict:
        """Plain YAML-serialisable truth (no per-sample arrays: use truth_attitude / truth_gyro_bias)."""
        _, grid = self.imu_stamps()
        effects = ["gyro_bias"]
        if self.gyro_bias_walk_deg_h_sqrt_h > 0:
            effects.append("bias_instability")
        if np.any(self.lever_arm_m):
            effects.append("lever_arm")
        if np.any(self.accel_bias_m_s2):
            effects.append("accel_bias")
        if self.accel_bias_of is not None:
            effects.append("accel_bias_varying")
        if self.speed_log_scale != 1.0:
            effects.append("speed_log_scale")
        if np.any(self.gyro_scale):
            effects.append("gyro_scale")
        return to_plain({
            "kind": "ship", "scenario": self.kind, "seed": self.seed, "duration_s": self.duration_s,
            "gravity_m_s2": self.gravity_m_s2, "t0_ns": self.t0_ns, "motion": self.motion.to_dict(),
            "sensors": {
                "imu0": {"rate_hz": self.rate_hz, "lever_arm_m": self.lever_arm_m,
                         "lever_arm_convention": "accelerometer position in the body frame from the centre of "
                                                 "rotation (the gyro frame), m",
                         "gyro_bias0_rad_s": self.gyro_bias0_rad_s,
                         "gyro_bias0_deg_h": self.gyro_bias0_rad_s / DEG_H,
                         "gyro_bias_end_deg_h": self.truth_gyro_bias(grid[-1:])[0] / DEG_H,
                         "gyro_bias_walk_deg_h_sqrt_h": self.gyro_bias_walk_deg_h_sqrt_h,
                         "gyro_scale": self.gyro_scale,
                         "accel_bias_m_s2": self.accel_bias_m_s2, "noise": self.noise.to_dict()},
                "speed0": {"rate_hz": self.speed_log_rate_hz, "scale": self.speed_log_scale,
                           "noise_m_s": self.speed_log_noise_m_s},
                "gps0": {"rate_hz": self.gps_rate_hz, "noise_m_s": self.gps_speed_noise_m_s},
            },
            "effects": effects,
        })

    # -- measurements --

    def _imu_meta(self) -> dict:
        noise = self.noise.to_dict()
        noise["gyroscope_random_walk"] = float(self.gyro_bias_walk_rad_s2_sqrt_hz)
        return {"sensor_type": "imu", "rate_hz": self.rate_hz, "gravity_m_s2": self.gravity_m_s2, **noise}

    def _sensors(self, rng=None) -> dict:
        """Sensors of the recording; with ``rng`` (4 child generators) add white noise and the accel walk."""
        t_ns, t_s = self.imu_stamps()
        w, f = self.true_imu(t_s)
        gyro = w * (1.0 + self.gyro_scale) + self.truth_gyro_bias(t_s)  # scale 0: w * 1.0 is w, bit for bit
        accel = f + self.accel_bias_m_s2
        if self.accel_bias_of is not None:
            roll, pitch, yaw = self.motion.euler(t_s)
            accel = accel + self.accel_bias_of(t_s, np.column_stack([roll[0], pitch[0], yaw[0]]))
        log_ns, log_s = _stamps(self.duration_s, self.speed_log_rate_hz, self.t0_ns)
        gps_ns, gps_s = _stamps(self.duration_s, self.gps_rate_hz, self.t0_ns)
        speed_log = self.speed_log_scale * self.motion.speed(log_s)[0]
        gps_speed = self.motion.speed_over_ground(gps_s)
        if rng is not None:
            r_imu, r_walk, r_log, r_gps = rng
            sigma_a, sigma_g = self.noise.white_sigma(self.rate_hz)
            z = r_imu.standard_normal((2, len(t_s), 3))
            step_a, _ = self.noise.walk_step_sigma(self.rate_hz)
            walk = np.vstack([np.zeros((1, 3)), np.cumsum(r_walk.standard_normal((len(t_s) - 1, 3)), axis=0)])
            gyro = gyro + sigma_g * z[1]
            accel = accel + sigma_a * z[0] + step_a * walk
            speed_log = speed_log + self.speed_log_noise_m_s * r_log.standard_normal(len(log_s))
            gps_speed = gps_speed + self.gps_speed_noise_m_s * r_gps.standard_normal(len(gps_s))
        return {
            "imu0": imu_sensor("imu0", t_ns, gyro, accel, meta=self._imu_meta()),
            "speed0": SensorData("speed0", log_ns, {"speed_log": speed_log}, {"speed_log": "m s^-1"},
                                 {"sensor_type": "speed_log", "rate_hz": self.speed_log_rate_hz,
                                  "noise_m_s": self.speed_log_noise_m_s}),
            "gps0": SensorData("gps0", gps_ns, {"speed": gps_speed}, {"speed": "m s^-1"},
                               {"sensor_type": "gps_speed", "rate_hz": self.gps_rate_hz,
                                "noise_m_s": self.gps_speed_noise_m_s}),
        }

    def exact_measurements(self) -> Recording:
        """Noise-free measurements (the drifting gyro bias, accel bias and speed-log scale are included)."""
        return Recording(path=None, sensors=self._sensors())

    def perturbed_measurements(self, seed) -> Recording:
        """Exact measurements plus white noise (IMU, speed log, GPS) and the accel bias walk, from ``seed``."""
        return Recording(path=None, sensors=self._sensors(np.random.default_rng(seed).spawn(4)))

    def write(self, path, seed=None, overwrite: bool = False):
        """Write the recording (exact if ``seed`` is None, else perturbed) with ``truth/truth.yaml``."""
        rec = self.exact_measurements() if seed is None else self.perturbed_measurements(seed)
        truth = self.truth()
        truth["measurements"] = "exact" if seed is None else {"perturbed_seed": seed}
        return write_recording(rec, path, truth=truth, overwrite=overwrite)

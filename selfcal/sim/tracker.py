"""Simulated laser-tracker target on a tunnel-boring machine (patent 004), with injected sensor faults.

The machine advances slowly (``advance_mm_s``) along the tunnel (world +x, away from the tracker at the
origin), steers slowly (roll, pitch, yaw and lateral position change over minutes) and shakes in irregular
vibration *bursts* (Poisson arrivals; each burst a few sinusoids of 3-25 Hz, linear and angular, under a smooth
envelope).  The target carries

* ``imu0``  strapdown IMU at 200 Hz (EuRoC columns); biases = static offset + first-order Gauss-Markov process
  (the patent's static and dynamic bias states) + white noise;
* ``tracker0``  the laser tracker's prism position ``x, y, z [m]`` and velocity ``vx, vy, vz [m s^-1]`` at
  50 Hz, mm noise, beam breaks (no sample) and occasional jumps (outliers of some mm to cm);
* ``incl0``  dual-axis inclinometer ``roll, pitch [rad]`` at 10 Hz: the direction of the specific force
  averaged over ``incl_average_s`` (its internal filter), so vibration and acceleration corrupt it;
* ``cam0``  beam-spot camera ``u, v [px]`` at 10 Hz: the tracker's centre projected with ``cv2.projectPoints``
  (intrinsics and distortion in its sensor.yaml); no spot while the beam is broken.

Injected faults (``faults=True`` or a list of :class:`Fault`): inclinometer hard faults (``spike``: single
samples off by 0.5-3 deg) and soft faults (``ramp``: a bias growing linearly, then gone; ``stuck``: the output
frozen), tracker ``dropout`` (beam break) and ``jump`` (a few samples offset).  All truth, the burst schedule
and the fault log go to ``truth/`` and are never read by an estimator.

IMU samples are made consistent with GTSAM's zero-order-hold preintegration: ``w_k = Log(R_k^T R_k+1) / dt``,
``f_k = R_k^T ((v_k+1 - v_k) / dt + g e_z)``, so integrating exact samples reproduces the true rotation and
velocity (and the position to the trapezoid rule's O(dt^3) error per step).

Everything is seeded (``np.random.default_rng``): the scenario seed fixes motion, bursts, biases and faults;
``perturbed_measurements(seed)`` / ``stream(seed)`` fix the white noise, generated in 60 s chunks so a 3 h run
can be streamed in bounded memory and the streamed samples equal the recorded ones.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from selfcal.core import inertial
from selfcal.io.camera import camera_keys
from selfcal.io.recording import Recording, SensorData, imu_sensor, write_recording
from selfcal.core import so3
from selfcal.models import tracker as mt
from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.sim.trajectories import DEFAULT_T0_NS
from selfcal.sim.trajectories import E_Z, smooth_bump, to_plain

CHUNK_S = 60.0
DEG = np.pi / 180.0
TRACKER_COLUMNS = ("x", "y", "z")
TRACKER_VELOCITY_COLUMNS = ("vx", "vy", "vz")
INCL_COLUMNS = ("roll", "pitch")
CAM_COLUMNS = ("u", "v")


@dataclass(frozen=True)
class Fault:
    """One injected fault: ``sensor`` ('incl0' | 'tracker0'), ``kind``, [start_s, end_s), ``magnitude``.

    kinds: incl0 ``spike`` (rad, added to roll and/or pitch for one sample), ``ramp`` (rad/s: a bias growing
    from the start, on ``axis``), ``stuck`` (output frozen at its value at start_s); tracker0 ``dropout`` (no
    samples, camera spot lost too), ``jump`` (m, added to the position along a random direction).
    """

    sensor: str
    kind: str
    start_s: float
    end_s: float
    magnitude: float = 0.0
    axis: int = 0
    direction: tuple = (1.0, 0.0, 0.0)

    @property
    def hard(self) -> bool:
        return self.kind in ("spike", "jump", "dropout")


@dataclass
class Burst:
    start_s: float
    duration_s: float
    freq_hz: np.ndarray  # (K,)
    phase_rad: np.ndarray  # (K, 6)
    amplitude: np.ndarray  # (K, 6): position m (x, y, z), then roll, pitch, yaw rad


class _Sines:
    """Slow steering: ``x(t) = sum A sin(2 pi t / T + phi)`` per column, with first and second derivatives."""

    def __init__(self, amplitude, period_s, phase_rad):
        self.A, self.w, self.phi = (np.asarray(a, dtype=float) for a in (amplitude, 2 * np.pi / np.asarray(period_s),
                                                                         phase_rad))

    def evaluate(self, t):
        arg = np.multiply.outer(t, self.w) + self.phi  # (N, K, D)
        s, c = np.sin(arg), np.cos(arg)
        return ((self.A * s).sum(1), (self.A * self.w * c).sum(1), -(self.A * self.w**2 * s).sum(1))


class TrackerScenario:
    """A TBM target run with known truth.

    Parameters
    ----------
    duration_s : run length, s.
    seed : scenario seed (motion, bursts, biases, faults).
    faults : False (none), True (the default schedule, see :meth:`default_faults`) or a list of :class:`Fault`.
    advance_mm_s : forward advance speed, mm/s.
    burst_rate_per_min, burst_accel_m_s2, burst_angle_deg : vibration bursts: mean arrivals per minute,
        (min, max) linear acceleration amplitude per component, (min, max) angular amplitude per component.
    tracker_sigma_m, tracker_velocity_sigma_m_s, incl_sigma_rad, cam_sigma_px : white noise per sample.
    incl_bias_rad : constant inclinometer bias (roll, pitch) (an audit effect; 0 by default).
    incl_scale : inclinometer scale error (0 = nominal).
    incl_accel_sensitivity : the reading departs from gravity by (1 + k) times what the specific force alone
        gives (k = 0: a perfect specific-force sensor; an audit effect).
    tracker_clock_offset_s : ``t_tracker = t_imu + offset`` (the tracker stamps late by offset; an audit effect).
    lever_arm_prism_m, lever_arm_camera_m : prism and camera positions in the body (IMU) frame, m.
    tracker_W_m : the tracker station in the world frame, m (its positions are world coordinates; the camera sees
        the beam from there).  Below or beside the target's line of advance, steering changes the range.
    with_velocity : write tracker velocity columns.
    steer_angle_deg, steer_period_s : (min, max) amplitude and period of the slow steering sines of roll, pitch
        and yaw (3 each); larger ones make a calibration run (the audit needs the tilt to vary);
        ``steer_angle_axes`` weights roll, pitch and yaw (default 1 each; a yaw sweep: (1, 1, 5)).
    steer_position_m, steer_position_period_s : the same for the lateral and vertical position (m, s); a
        calibration run that moves the target (the clock offset shows only while it moves);
        ``steer_position_axes`` weights x, y, z (default lateral and vertical).
    """

    def __init__(self, duration_s: float = 600.0, seed=0, faults=False, advance_mm_s: float = 1.0,
                 burst_rate_per_min: float = 2.0, burst_accel_m_s2=(0.02, 0.3), burst_angle_deg=(0.002, 0.02),
                 tracker_sigma_m: float = 0.5e-3, tracker_velocity_sigma_m_s: float = 2e-3,
                 incl_sigma_rad: float = 0.005 * DEG, cam_sigma_px: float = 0.2, incl_bias_rad=(0.0, 0.0),
                 incl_scale: float = 0.0, incl_accel_sensitivity: float = 0.0, tracker_clock_offset_s: float = 0.0,
                 lever_arm_prism_m=(0.12, -0.05, 0.25), lever_arm_camera_m=(0.10, 0.03, 0.20),
                 tracker_W_m=(0.0, 0.0, 0.0),
                 with_velocity: bool = True, steer_angle_deg=(0.05, 0.3), steer_period_s=(60.0, 600.0),
                 steer_angle_axes=(1.0, 1.0, 1.0),
                 steer_position_m=(0.002, 0.01), steer_position_period_s=(120.0, 900.0),
                 steer_position_axes=(0.0, 1.0, 1.0),
                 imu_rate_hz: float = 200.0, tracker_rate_hz: float = 50.0,
                 incl_rate_hz: float = 10.0, cam_rate_hz: float = 10.0, incl_average_s: float = 0.02,
                 gyro_bias_rad_s: float = 2e-3, gyro_gm_sigma_rad_s: float = 2e-4, accel_bias_m_s2: float = 0.02,
                 accel_gm_sigma_m_s2: float = 2e-3, bias_tau_s: float = 300.0,
                 gyro_noise_density: float = 1.7e-4, accel_noise_density: float = 2e-3,
                 gravity_m_s2: float = STANDARD_GRAVITY_M_S2, t0_ns: int = DEFAULT_T0_NS):
        self.duration_s, self.seed = float(duration_s), seed
        self.advance_m_s = advance_mm_s * 1e-3
        self.tracker_sigma_m, self.tracker_velocity_sigma_m_s = tracker_sigma_m, tracker_velocity_sigma_m_s
        self.incl_sigma_rad, self.cam_sigma_px = incl_sigma_rad, cam_sigma_px
        self.incl_bias_rad = np.asarray(incl_bias_rad, dtype=float)
        self.incl_scale, self.incl_accel_sensitivity = float(incl_scale), float(incl_accel_sensitivity)
        self.tracker_clock_offset_s = float(tracker_clock_offset_s)
        self.r_P_B = np.asarray(lever_arm_prism_m, dtype=float)
        self.r_C_B = np.asarray(lever_arm_camera_m, dtype=float)
        self.tracker_W = np.asarray(tracker_W_m, dtype=float)
        # camera looks back along -x_B towards the tracker: z_C = -x_B, x_C = -y_B, y_C = -z_B
        self.R_B_C = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
        self.camera_matrix = np.array([[1200.0, 0.0, 320.0], [0.0, 1200.0, 240.0], [0.0, 0.0, 1.0]])
        self.dist_coeffs = np.array([-0.12, 0.05, 1e-4, -2e-4, 0.0])
        self.resolution_px = (640, 480)
        self.with_velocity = with_velocity
        self.rates = {"imu0": imu_rate_hz, "tracker0": tracker_rate_hz, "incl0": incl_rate_hz, "cam0": cam_rate_hz}
        self.incl_average_s = incl_average_s
        self.gyro_noise_density, self.accel_noise_density = gyro_noise_density, accel_noise_density
        self.bias_tau_s = bias_tau_s
        self.gravity_m_s2, self.t0_ns = float(gravity_m_s2), int(t0_ns)
        rng_motion, rng_burst, rng_bias, rng_fault = np.random.default_rng(seed).spawn(4)
        self.p0_W = np.array([30.0, 0.0, 0.0]) + rng_motion.uniform(-0.3, 0.3, 3)
        self.euler0 = rng_motion.uniform(-2.0, 2.0, 3) * DEG
        k = 3
        self.steer_pos = _Sines(rng_motion.uniform(*steer_position_m, (k, 3)) * np.asarray(steer_position_axes),
                                rng_motion.uniform(*steer_position_period_s, (k, 3)),
                                rng_motion.uniform(0, 2 * np.pi, (k, 3)))
        self.steer_att = _Sines(rng_motion.uniform(*steer_angle_deg, (k, 3)) * DEG * np.asarray(steer_angle_axes),
                                rng_motion.uniform(*steer_period_s, (k, 3)), rng_motion.uniform(0, 2 * np.pi, (k, 3)))
        self.bursts = self._schedule_bursts(rng_burst, burst_rate_per_min, burst_accel_m_s2, burst_angle_deg)
        self._burst_starts = np.array([b.start_s for b in self.bursts])
        self._max_burst_s = max([b.duration_s for b in self.bursts], default=0.0)
        # biases: static offset + first-order Gauss-Markov (exactly discretised on a 1 s grid, interpolated)
        self.gyro_bias0 = rng_bias.normal(0.0, gyro_bias_rad_s, 3)
        self.accel_bias0 = rng_bias.normal(0.0, accel_bias_m_s2, 3)
        n = int(np.ceil(self.duration_s)) + 2
        phi = np.exp(-1.0 / bias_tau_s)
        gm = np.zeros((n, 6))
        sig = np.array([gyro_gm_sigma_rad_s] * 3 + [accel_gm_sigma_m_s2] * 3)
        gm[0] = rng_bias.normal(0.0, 1.0, 6) * sig
        steps = rng_bias.normal(0.0, 1.0, (n - 1, 6)) * sig * np.sqrt(1 - phi**2)
        for i in range(1, n):
            gm[i] = phi * gm[i - 1] + steps[i - 1]
        self._gm = gm
        self.gyro_gm_sigma_rad_s, self.accel_gm_sigma_m_s2 = gyro_gm_sigma_rad_s, accel_gm_sigma_m_s2
        if faults is True:
            self.faults = self.default_faults(rng_fault)
        else:
            self.faults = list(faults or [])

    # --- schedules ---------------------------------------------------------------------------------------------

    def _schedule_bursts(self, rng, rate_per_min, accel, angle_deg) -> list[Burst]:
        bursts, t = [], 5.0
        while rate_per_min > 0:
            t += rng.exponential(60.0 / rate_per_min)
            duration = rng.uniform(2.0, 8.0)
            if t + duration > self.duration_s:
                break
            k = 3
            freq = rng.uniform(3.0, 25.0, k)
            w = 2 * np.pi * freq
            scale = rng.uniform(0.2, 1.0)  # irregular: some bursts are mild, some violent
            acc = rng.uniform(*accel, (k, 3)) * scale
            ang = rng.uniform(*angle_deg, (k, 3)) * DEG * scale
            amplitude = np.hstack([acc / w[:, None] ** 2, ang])
            bursts.append(Burst(t, duration, freq, rng.uniform(0, 2 * np.pi, (k, 6)), amplitude))
            t += duration
        return bursts

    def default_faults(self, rng) -> list[Fault]:
        """The default fault schedule, proportional to the duration: per 10 minutes, 10 inclinometer spikes,
        one bias ramp (0.01 deg/s for 40 s: 0.4 deg at its end), one stuck period (30 s), 3 beam breaks (2-8 s)
        and 4 tracker jumps (1-5 samples, 5-30 mm)."""
        d = self.duration_s
        per = d / 600.0
        faults = []
        for _ in range(int(round(10 * per))):
            t = rng.uniform(10.0, d - 5.0)
            faults.append(Fault("incl0", "spike", t, t + 0.05, rng.uniform(0.5, 3.0) * DEG * rng.choice([-1, 1]),
                                int(rng.integers(0, 2))))
        slots = np.linspace(60.0, d - 60.0, int(round(2 * per)) + 1)
        for i in range(len(slots) - 1):  # soft faults in separate slots so they never overlap
            t = rng.uniform(slots[i], slots[i + 1] - 60.0) if slots[i + 1] - slots[i] > 70 else slots[i]
            if i % 2 == 0:
                faults.append(Fault("incl0", "ramp", t, t + 40.0, 0.01 * DEG * rng.choice([-1, 1]),
                                    int(rng.integers(0, 2))))
            else:
                faults.append(Fault("incl0", "stuck", t, t + 30.0))
        for _ in range(int(round(3 * per))):
            t = rng.uniform(20.0, d - 20.0)
            faults.append(Fault("tracker0", "dropout", t, t + rng.uniform(2.0, 8.0)))
        for _ in range(int(round(4 * per))):
            t = rng.uniform(20.0, d - 20.0)
            direction = rng.normal(size=3)
            faults.append(Fault("tracker0", "jump", t, t + rng.integers(1, 6) / self.rates["tracker0"] - 1e-6,
                                rng.uniform(0.005, 0.03), 0, tuple(direction / np.linalg.norm(direction))))
        return sorted(faults, key=lambda f: f.start_s)

    # --- continuous-time truth ------------------------------------------------------------------------------------

    def _vibration(self, t):
        """Burst vibration (N, 6) and its first and second time derivatives (position m, angles rad)."""
        x, x1, x2 = (np.zeros((len(t), 6)) for _ in range(3))
        if not self.bursts:
            return x, x1, x2
        lo = np.searchsorted(self._burst_starts + self._max_burst_s, t[0])
        hi = np.searchsorted(self._burst_starts, t[-1], side="right")
        for b in self.bursts[lo:hi]:
            i0, i1 = np.searchsorted(t, [b.start_s, b.start_s + b.duration_s])
            if i1 <= i0:
                continue
            tt = t[i0:i1]
            e, e1, e2 = smooth_bump((tt - b.start_s) / b.duration_s)
            e1, e2 = e1 / b.duration_s, e2 / b.duration_s**2
            w = 2 * np.pi * b.freq_hz
            arg = np.multiply.outer(tt, w)[:, :, None] + b.phase_rad  # (n, K, 6)
            s = (b.amplitude * np.sin(arg)).sum(1)
            s1 = (b.amplitude * w[:, None] * np.cos(arg)).sum(1)
            s2 = -(b.amplitude * (w**2)[:, None] * np.sin(arg)).sum(1)
            x[i0:i1] += e[:, None] * s
            x1[i0:i1] += e1[:, None] * s + e[:, None] * s1
            x2[i0:i1] += e2[:, None] * s + 2 * e1[:, None] * s1 + e[:, None] * s2
        return x, x1, x2

    def kinematics(self, t_s):
        """Truth at times t_s (N,) (s after t0): R_W_B (N,3,3), p_W, v_W, a_W (N,3), w_B (N,3), euler (N,3)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        vib, vib1, vib2 = self._vibration(t)
        sp, sp1, sp2 = self.steer_pos.evaluate(t)
        sa, sa1, _ = self.steer_att.evaluate(t)
        fwd = np.outer(t, [self.advance_m_s, 0.0, 0.0])
        p = self.p0_W + fwd + sp + vib[:, :3]
        v = np.array([self.advance_m_s, 0.0, 0.0]) + sp1 + vib1[:, :3]
        a = sp2 + vib2[:, :3]
        euler = self.euler0 + sa + vib[:, 3:]
        euler_dot = sa1 + vib1[:, 3:]
        r, pt = euler[:, 0], euler[:, 1]
        r1, p1, y1 = euler_dot.T
        sr, cr, spt, cpt = np.sin(r), np.cos(r), np.sin(pt), np.cos(pt)
        w = np.stack([r1 - spt * y1, cr * p1 + sr * cpt * y1, -sr * p1 + cr * cpt * y1], axis=1)
        R = mt.rotation_from_euler(euler[:, 0], euler[:, 1], euler[:, 2])
        return R, p, v, a, w, euler

    def truth_pose(self, t_s):
        """(R_W_B (N,3,3), p_W (N,3)) of the body (IMU) frame at t_s."""
        R, p, *_ = self.kinematics(t_s)
        return R, p

    def truth_bias(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """True (gyro rad/s, accel m/s^2) biases (N, 3) each: static + Gauss-Markov."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        grid = np.arange(len(self._gm), dtype=float)
        gm = np.column_stack([np.interp(t, grid, self._gm[:, i]) for i in range(6)])
        return self.gyro_bias0 + gm[:, :3], self.accel_bias0 + gm[:, 3:]

    def _imu_exact(self, t):
        """Noise-free (w, f) consistent with zero-order-hold integration over [t_k, t_k + dt]."""
        dt = 1.0 / self.rates["imu0"]
        R0, _, v0, *_ = self.kinematics(t)
        R1, _, v1, *_ = self.kinematics(t + dt)
        w = so3.log(np.einsum("nji,njk->nik", R0, R1)) / dt
        f = np.einsum("nji,nj->ni", R0, (v1 - v0) / dt + self.gravity_m_s2 * E_Z)
        return w, f

    # --- measurements ------------------------------------------------------------------------------------------

    def stamps(self, sensor: str) -> np.ndarray:
        """Stamps of ``sensor`` in s after t0 over the run (on one common clock)."""
        rate = self.rates[sensor]
        return np.arange(int(np.floor(self.duration_s * rate + 1e-9)) + 1) / rate

    def _faults(self, sensor, kind=None):
        return [f for f in self.faults if f.sensor == sensor and (kind is None or f.kind == kind)]

    def _chunk(self, t_lo: float, t_hi: float, rng) -> dict:
        """Every sensor's samples with stamps in [t_lo, t_hi): name -> (t_s, {column: values}).  ``rng``: None
        for exact samples, else a Generator for the white noise."""
        out = {}
        g = self.gravity_m_s2

        def window(sensor):
            t = self.stamps(sensor)
            return t[(t >= t_lo) & (t < t_hi)]

        def noise(shape, sigma):
            return rng.standard_normal(shape) * sigma if rng is not None else np.zeros(shape)

        t = window("imu0")
        w, f = self._imu_exact(t)
        bg, ba = self.truth_bias(t)
        rate = self.rates["imu0"]
        gyro = w + bg + noise(w.shape, self.gyro_noise_density * np.sqrt(rate))
        accel = f + ba + noise(f.shape, self.accel_noise_density * np.sqrt(rate))
        out["imu0"] = (t, {"gyro": gyro, "accel": accel})

        t = window("tracker0")
        broken = np.zeros(len(t), dtype=bool)
        for flt in self._faults("tracker0", "dropout"):
            broken |= (t >= flt.start_s) & (t < flt.end_s)
        t_true = t - self.tracker_clock_offset_s  # stamped late by the offset: the sample shows an earlier state
        R, p, v, _, wb, _ = self.kinematics(t_true)
        pos = mt.prism_position_W(R, p, self.r_P_B) + noise((len(t), 3), self.tracker_sigma_m)
        vel = mt.prism_velocity_W(R, v, wb, self.r_P_B) + noise((len(t), 3), self.tracker_velocity_sigma_m_s)
        for flt in self._faults("tracker0", "jump"):
            sel = (t >= flt.start_s) & (t < flt.end_s)
            pos[sel] += flt.magnitude * np.asarray(flt.direction)
        out["tracker0"] = (t[~broken], {"position": pos[~broken], "velocity": vel[~broken]})

        t = window("incl0")
        n_avg = max(1, int(round(self.incl_average_s * rate)))
        sub = t[:, None] - np.arange(1, n_avg + 1)[None, ::-1] / rate  # IMU intervals covering [t - avg, t]
        _, f_sub = self._imu_exact(sub.ravel())
        f_mean = f_sub.reshape(len(t), n_avg, 3).mean(axis=1)
        roll, pitch = inertial.tilt_from_specific_force(f_mean)
        tilt = np.column_stack([roll, pitch])
        if self.incl_accel_sensitivity:  # over-/under-reaction to the non-gravitational part of the force
            euler = self.kinematics(t)[5]
            tilt = tilt + self.incl_accel_sensitivity * (tilt - euler[:, :2])
        tilt = tilt * (1.0 + self.incl_scale) + self.incl_bias_rad
        tilt = tilt + noise(tilt.shape, self.incl_sigma_rad)
        for flt in self._faults("incl0"):
            sel = (t >= flt.start_s) & (t < flt.end_s)
            if flt.kind == "spike":
                tilt[sel, flt.axis] += flt.magnitude
            elif flt.kind == "ramp":
                tilt[sel, flt.axis] += flt.magnitude * (t[sel] - flt.start_s)
            elif flt.kind == "stuck" and sel.any():
                tilt[sel] = self._stuck_value(flt)
        out["incl0"] = (t, {"tilt": tilt})

        t = window("cam0")
        broken = np.zeros(len(t), dtype=bool)
        for flt in self._faults("tracker0", "dropout"):
            broken |= (t >= flt.start_s) & (t < flt.end_s)
        R, p, *_ = self.kinematics(t)
        d_C = mt.beam_direction_C(R, p, self.r_C_B, self.R_B_C, self.tracker_W)
        uv = mt.pixel_from_direction_C(d_C, self.camera_matrix, self.dist_coeffs) + noise((len(t), 2),
                                                                                          self.cam_sigma_px)
        out["cam0"] = (t[~broken], {"uv": uv[~broken]})
        return out

    def _stuck_value(self, flt: Fault) -> np.ndarray:
        """The inclinometer's last good output before a stuck fault (exact tilt there, noise-free)."""
        rate = self.rates["incl0"]
        t_last = np.floor(flt.start_s * rate - 1e-9) / rate
        n_avg = max(1, int(round(self.incl_average_s * self.rates["imu0"])))
        sub = t_last - np.arange(1, n_avg + 1)[::-1] / self.rates["imu0"]
        _, f = self._imu_exact(sub)
        roll, pitch = inertial.tilt_from_specific_force(f.mean(axis=0))
        return np.array([roll, pitch]) + self.incl_bias_rad

    def _chunks(self, seed):
        n = int(np.ceil((self.duration_s + 1e-9) / CHUNK_S))
        for i in range(n):
            rng = None if seed is None else np.random.default_rng([int(seed), i])
            hi = (i + 1) * CHUNK_S if i < n - 1 else self.duration_s + 1e-6
            yield self._chunk(i * CHUNK_S, hi, rng)

    def _meta(self) -> dict:
        return {
            "imu0": {"sensor_type": "imu", "rate_hz": self.rates["imu0"], "gravity_m_s2": self.gravity_m_s2,
                     "gyroscope_noise_density": self.gyro_noise_density,
                     "accelerometer_noise_density": self.accel_noise_density,
                     "gyroscope_random_walk": float(self.gyro_gm_sigma_rad_s * np.sqrt(2.0 / self.bias_tau_s)),
                     "accelerometer_random_walk": float(self.accel_gm_sigma_m_s2 * np.sqrt(2.0 / self.bias_tau_s))},
            "tracker0": {"sensor_type": "laser_tracker", "rate_hz": self.rates["tracker0"],
                         "position_sigma_m": self.tracker_sigma_m,
                         "velocity_sigma_m_s": self.tracker_velocity_sigma_m_s,
                         "lever_arm_prism_m": self.r_P_B.tolist(), "tracker_W_m": self.tracker_W.tolist()},
            "incl0": {"sensor_type": "inclinometer", "rate_hz": self.rates["incl0"], "sigma_rad": self.incl_sigma_rad,
                      "averaging_s": self.incl_average_s, "T_B_I": "identity"},
            "cam0": {"sensor_type": "beam_spot_camera", "rate_hz": self.rates["cam0"], "sigma_px": self.cam_sigma_px,
                     **camera_keys(self.camera_matrix, self.dist_coeffs, self.resolution_px),
                     "R_B_C": self.R_B_C.tolist(), "lever_arm_camera_m": self.r_C_B.tolist()},
        }

    def _ns(self, t_s) -> np.ndarray:
        return self.t0_ns + np.round(np.asarray(t_s) * 1e9).astype(np.int64)

    def measurements(self, seed=None) -> Recording:
        """The whole recording: exact (``seed`` None) or with white noise from ``seed``."""
        parts = {}
        for chunk in self._chunks(seed):
            for name, (t, cols) in chunk.items():
                parts.setdefault(name, []).append((t, cols))
        joined = {name: (np.concatenate([t for t, _ in p]),
                         {k: np.concatenate([c[k] for _, c in p]) for k in p[0][1]}) for name, p in parts.items()}
        meta = self._meta()
        t, c = joined["imu0"]
        sensors = {"imu0": imu_sensor("imu0", self._ns(t), c["gyro"], c["accel"], meta=meta["imu0"])}
        t, c = joined["tracker0"]
        values = {name: c["position"][:, i] for i, name in enumerate(TRACKER_COLUMNS)}
        units = {name: "m" for name in TRACKER_COLUMNS}
        if self.with_velocity:
            values.update({name: c["velocity"][:, i] for i, name in enumerate(TRACKER_VELOCITY_COLUMNS)})
            units.update({name: "m s^-1" for name in TRACKER_VELOCITY_COLUMNS})
        sensors["tracker0"] = SensorData("tracker0", self._ns(t), values, units, meta["tracker0"])
        t, c = joined["incl0"]
        sensors["incl0"] = SensorData("incl0", self._ns(t), {"roll": c["tilt"][:, 0], "pitch": c["tilt"][:, 1]},
                                      {"roll": "rad", "pitch": "rad"}, meta["incl0"])
        t, c = joined["cam0"]
        sensors["cam0"] = SensorData("cam0", self._ns(t), {"u": c["uv"][:, 0], "v": c["uv"][:, 1]},
                                     {"u": "px", "v": "px"}, meta["cam0"])
        return Recording(path=None, sensors=sensors)

    def stream(self, seed=None):
        """Samples one at a time in timestamp order, as ``(sensor, t_ns, {column: value})`` with the recording's
        column names (no units): the input of an online estimator.  Bounded memory (60 s chunks)."""
        for chunk in self._chunks(seed):
            events = []
            t, c = chunk["imu0"]
            for i in range(len(t)):
                g, a = c["gyro"][i], c["accel"][i]
                events.append((t[i], 0, "imu0", {"w_RS_S_x": g[0], "w_RS_S_y": g[1], "w_RS_S_z": g[2],
                                                 "a_RS_S_x": a[0], "a_RS_S_y": a[1], "a_RS_S_z": a[2]}))
            t, c = chunk["tracker0"]
            for i in range(len(t)):
                values = dict(zip(TRACKER_COLUMNS, c["position"][i]))
                if self.with_velocity:
                    values.update(zip(TRACKER_VELOCITY_COLUMNS, c["velocity"][i]))
                events.append((t[i], 1, "tracker0", values))
            t, c = chunk["incl0"]
            for i in range(len(t)):
                events.append((t[i], 2, "incl0", {"roll": c["tilt"][i, 0], "pitch": c["tilt"][i, 1]}))
            t, c = chunk["cam0"]
            for i in range(len(t)):
                events.append((t[i], 3, "cam0", {"u": c["uv"][i, 0], "v": c["uv"][i, 1]}))
            events.sort(key=lambda e: (e[0], e[1]))
            for ts, _, name, values in events:
                yield name, int(self._ns(ts)), {k: float(v) for k, v in values.items()}

    def truth(self) -> dict:
        """Plain YAML truth: parameters, burst schedule, fault log, biases (no per-sample arrays)."""
        effects = ["lever_arm_prism"]
        if np.any(self.incl_bias_rad):
            effects.append("incl_bias")
        if self.incl_scale:
            effects.append("incl_scale")
        if self.incl_accel_sensitivity:
            effects.append("incl_accel_sensitivity")
        if self.tracker_clock_offset_s:
            effects.append("tracker_time_offset")
        return to_plain({
            "kind": "tracker", "seed": self.seed, "duration_s": self.duration_s, "t0_ns": self.t0_ns,
            "gravity_m_s2": self.gravity_m_s2, "advance_m_s": self.advance_m_s, "p0_W_m": self.p0_W,
            "euler0_rad": self.euler0, "lever_arm_prism_m": self.r_P_B, "lever_arm_camera_m": self.r_C_B,
            "incl_bias_rad": self.incl_bias_rad, "incl_scale": self.incl_scale,
            "incl_accel_sensitivity": self.incl_accel_sensitivity,
            "tracker_clock_offset_s": self.tracker_clock_offset_s,
            "gyro_bias0_rad_s": self.gyro_bias0, "accel_bias0_m_s2": self.accel_bias0,
            "bursts": [{"start_s": b.start_s, "duration_s": b.duration_s, "freq_hz": b.freq_hz,
                        "max_accel_m_s2": float(np.max(b.amplitude[:, :3] * (2 * np.pi * b.freq_hz[:, None])**2))}
                       for b in self.bursts],
            "faults": [{**asdict(f), "hard": f.hard} for f in self.faults],
            "effects": effects,
        })

    def truth_tum(self, rate_hz: float = 10.0) -> str:
        """The true body trajectory as TUM lines (t x y z qx qy qz qw), t in s since the epoch."""
        from scipy.spatial.transform import Rotation
        t = np.arange(int(self.duration_s * rate_hz) + 1) / rate_hz
        R, p = self.truth_pose(t)
        q = Rotation.from_matrix(R).as_quat()
        stamp = self.t0_ns * 1e-9 + t
        return "".join(f"{s:.9f} {x[0]:.6f} {x[1]:.6f} {x[2]:.6f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}\n"
                       for s, x, qq in zip(stamp, p, q))

    def write(self, path, seed=None, overwrite: bool = False):
        """Write the recording (exact if ``seed`` is None) with truth/truth.yaml and truth/poses.tum."""
        truth = self.truth()
        truth["measurements"] = "exact" if seed is None else {"perturbed_seed": seed}
        return write_recording(self.measurements(seed), path, truth=truth, overwrite=overwrite,
                               extra_files={"truth/poses.tum": self.truth_tum().encode()})

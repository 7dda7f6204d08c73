"""Use case ``selfcal smooth ship``: a vessel recording in, attitude and gyro bias out (TUM trajectory)."""
from __future__ import annotations

import logging
import math
import statistics

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from selfcal.core import inertial
from selfcal.core.progress import quiet
from selfcal.core.sanity import GAP_FLOOR_S, GAP_PERIODS, coverage_problems, speed_problems
from selfcal.graphs.ship import SPEED_RATE_WINDOW_S, ShipEstimate, ShipGraphOptions, ShipInputs, ShipSmoother
from selfcal.io.recording import Recording, RecordingError
from selfcal.models import ship

log = logging.getLogger(__name__)

SPEED_SOURCES = (("speed0", "speed_log"), ("gps0", "speed"))  # preferred first: the log measures through water


def ship_inputs(recording: Recording, imu_name: str = "imu0") -> ShipInputs:
    """IMU samples of ``imu_name`` and the speed (speed log, else GPS speed) with its rate on their times.

    The speed is a smoothing spline through the log's samples, its smoothing chosen by generalised
    cross-validation (scipy's ``make_smoothing_spline``): the log's own noise sets how much is smoothed, so the
    surge acceleration (the spline's derivative) carries neither the noise nor a fixed window's lag; its sigma and
    a slow rate for the audit's driver come with it (:func:`smoothed_speed`).
    """
    imu = recording.imu(imu_name)
    check_speed(recording, imu)
    data = uniformly_sampled(imu)
    speed = speed_rate = speed_rate_sigma = slow_rate = None
    source = speed_source(recording)
    if source is not None:
        s, column = recording.sensors[source[0]], source[1]
        t_log = (s.t_ns - data.t_ns[0]) * 1e-9
        t_imu = data.t_s - data.t_s[0]
        if len(t_log) >= 5:
            spline, rate_sigma, slow = smoothed_speed(t_log, s.values[column])
            speed, speed_rate = spline(t_imu), spline.derivative()(t_imu)
            speed_rate_sigma, slow_rate = np.interp(t_imu, t_log, rate_sigma), slow.derivative()(t_imu)
        else:
            speed = np.interp(t_imu, t_log, s.values[column])
    meta = data.meta
    gyro_noise = float(meta.get("gyroscope_noise_density", 1e-4))
    if not gyro_noise > 0.0:  # the graph weighs the gyro chain by it: 0 would call the gyro exact (singular)
        raise RecordingError(f"{imu_name}: gyroscope_noise_density must be positive, sensor.yaml says {gyro_noise}")
    return ShipInputs(data.t_s, data.gyro_rad_s, data.accel_m_s2, speed,
                      float(meta.get("gravity_m_s2", inertial.STANDARD_GRAVITY_M_S2)),
                      gyro_noise,
                      float(meta.get("gyroscope_random_walk", 1e-5)), speed_rate, speed_rate_sigma,
                      slow_rate)


RATE_NOISE_DRAWS = 128  # noise series pushed through the smoother: its rate's sigma to ~5 % (chi-square, 128 dof)
BIAS_WINDOW_SAMPLES = 5  # the rate's bias^2 is averaged over this many log samples (measured: 5 calibrates the
# sigma where a hull brakes best of global, 5, 11 and 21 on simulated turning voyages)
SLOW_LAM_FACTOR = 100.0  # the slow rate smooths this much more: its noise ~100^(-3/8) = 0.18 of the rate's


def smoothed_speed(t_s: np.ndarray, speed_m_s: np.ndarray):
    """(smoothing spline through the speed samples, the 1-sigma of its derivative at ``t_s`` in m/s^2, a slow
    spline).

    The spline's smoothing ``lam`` is chosen by generalised cross-validation (scipy's ``make_smoothing_spline``);
    with ``lam`` held the spline is linear in the samples, ``s = L y``, so the rate's noise is
    ``sigma_log^2 diag(L' L'^T)``.  ``diag(L' L'^T)`` and the smoother's trace (its degrees of freedom) are
    measured by pushing unit white noise series through the same smoother; ``sigma_log^2 = RSS / (n - tr L)``.
    Why it matters: the derivative of a 1 Hz log at 5 cm/s is off by ~0.01 m/s^2 (1 mrad of tilt), correlated
    over the smoother's seconds-long kernel, several times the accelerometer's tilt noise on a keyframe.
    The bias the smoothing leaves on a changing acceleration (GCV sets ``lam`` for the speed, not its rate:
    0.3-0.8 of the noise on simulated turning voyages) is added as ``(L s)' - s'``, the smooth smoothed once more
    (the plug-in estimate of ``(L y_true)' - y_true'``), squared and averaged over ``BIAS_WINDOW_SAMPLES``.

    The slow spline (``SLOW_LAM_FACTOR`` times the smoothing) gives the surge acceleration as a *driver* of the
    audit's terms: the rate's noise is in the tilt residual itself (its error tilts the force), so a driver that
    carried it would correlate with the residual by construction (errors in the variables) and name the log's own
    noise as an effect in surge acceleration; the slow rate shares 0.1 of the rate's noise variance (measured on
    a steady log).  The price: it smears changes of speed, 0.4-0.7 of the true surge's RMS off on the simulated
    braking voyages, so effects in surge acceleration are found with less power and sized coarsely.
    """
    from scipy.interpolate import make_smoothing_spline
    from scipy.optimize import minimize_scalar
    spline = make_smoothing_spline(t_s, speed_m_s)
    fitted = spline(t_s)
    # scipy does not return the lam it chose: the one whose spline is the same (a 1-D search, unimodal in log lam)
    scale = float(np.sum(fitted**2)) + 1e-300
    log_lam = minimize_scalar(lambda u: float(np.sum((make_smoothing_spline(t_s, speed_m_s, lam=10.0**u)(t_s)
                                                      - fitted) ** 2)) / scale,
                              bounds=(-8.0, 12.0), method="bounded", options={"xatol": 1e-4}).x
    draws = np.random.default_rng(0).standard_normal((len(t_s), RATE_NOISE_DRAWS))
    smoother = make_smoothing_spline(t_s, draws, lam=10.0**log_lam)
    dof = float(np.mean(np.sum(draws * smoother(t_s), axis=0)))  # Hutchinson: E z^T L z = tr L
    sigma_log = np.sqrt(np.sum((speed_m_s - fitted) ** 2) / max(len(t_s) - dof, 1.0))
    noise2 = sigma_log**2 * np.mean(smoother.derivative()(t_s) ** 2, axis=1)
    # the smoothing's bias on the rate, estimated by smoothing the smooth once more (L s - s ~ L y_true - y_true),
    # its square averaged over a few samples (the kernel's width): large where the hull starts or stops braking
    bias = make_smoothing_spline(t_s, fitted, lam=10.0**log_lam).derivative()(t_s) - spline.derivative()(t_s)
    bias2 = uniform_filter1d(bias**2, size=BIAS_WINDOW_SAMPLES, mode="nearest")
    slow = make_smoothing_spline(t_s, speed_m_s, lam=SLOW_LAM_FACTOR * 10.0**log_lam)
    return spline, np.sqrt(noise2 + bias2), slow


def speed_source(recording: Recording) -> tuple[str, str] | None:
    """(sensor, column) of the speed the estimators use: the first of :data:`SPEED_SOURCES` recorded."""
    return next(((sensor, column) for sensor, column in SPEED_SOURCES
                 if sensor in recording.sensors and column in recording.sensors[sensor].values), None)


def check_speed(recording: Recording, imu) -> None:
    """Refuse (RecordingError, one line) an IMU record cut short of the speed's (:func:`selfcal.core.sanity.
    coverage_problems`), a speed the accelerometer's surge shows is not in m/s (knots, km/h,
    cm/s: :func:`selfcal.core.sanity.speed_problems`), of the source the estimators use (:data:`SPEED_SOURCES`);
    say so in a warning where the voyage holds no speed change to judge it by."""
    source = speed_source(recording)
    if source is None:
        return
    sensor, column = source
    s = recording.sensors[sensor]
    problems = coverage_problems((imu.t_ns - imu.t_ns[0]) * 1e-9, (s.t_ns - imu.t_ns[0]) * 1e-9, sensor)
    if problems:
        raise RecordingError(f"{recording.path if recording.path is not None else '<recording>'}/{imu.name}: "
                             f"{problems[0]}")
    problems, unjudged = speed_problems((s.t_ns - imu.t_ns[0]) * 1e-9, s.values[column],
                                        (imu.t_ns - imu.t_ns[0]) * 1e-9, imu.accel_m_s2[:, 0])
    where = f"{recording.path if recording.path is not None else '<recording>'}/{sensor}"
    if problems:
        raise RecordingError(f"{where}: {problems[0]}")
    if unjudged:
        log.warning("%s: %s", where, unjudged)


def uniformly_sampled(data):
    """The IMU on a uniform grid at its mean rate when its stamps jitter (bursty USB/I2C loggers): the
    derivatives and the patent's fixed-coefficient filters need one sample period.  Linear interpolation; a
    uniformly sampled IMU is returned as it is."""
    from dataclasses import replace
    dt = np.diff(data.t_ns)
    if len(dt) == 0 or (dt.max() - dt.min()) <= 0.1 * np.median(dt):
        return data
    t_ns = np.linspace(data.t_ns[0], data.t_ns[-1], len(data.t_ns)).round().astype(np.int64)
    t, grid = data.t_ns.astype(float), t_ns.astype(float)
    resample = lambda x: np.column_stack([np.interp(grid, t, c) for c in x.T])
    return replace(data, t_ns=t_ns, gyro_rad_s=resample(data.gyro_rad_s), accel_m_s2=resample(data.accel_m_s2),
                   channels={k: np.interp(grid, t, v) for k, v in data.channels.items()})


def smooth_ship(recording: Recording, online: bool = False, remove_known_acceleration: bool = True,
                imu_name: str = "imu0", progress=quiet) -> ShipEstimate:
    """Attitude and gyro bias of a voyage, batch or iSAM2; ``progress(stage, done, total)`` is told how far
    it is (:mod:`selfcal.core.progress`)."""
    progress("IMU and speed on one time base")
    inputs = ship_inputs(recording, imu_name)
    if len(inputs.t_s) < 10:
        raise RecordingError(f"{imu_name}: too few samples for a voyage ({len(inputs.t_s)})")
    progress("keyframes")
    smoother = ShipSmoother(inputs, ShipGraphOptions(remove_known_acceleration=remove_known_acceleration))
    return smoother.online(progress=progress) if online else smoother.batch(progress=progress)


DEG_H = np.pi / 180.0 / 3600.0  # 1 deg/h in rad/s
BIAS_SIGMA_BOUND_DEG_H = 5.0  # a bias component known worse than this (1 sigma) is not reported as a number: at 5
# deg/h a ship gyro's 10 deg/h bias is not told from zero at 2 sigma (docs/ship.md, "What a voyage determines")
UNDETERMINED_REASON = {
    "x": "its sigma exceeds the bound: the tilt's noise over a voyage this short cannot carry the roll-axis drift",
    "y": "its sigma exceeds the bound: the tilt's noise over a voyage this short cannot carry the pitch-axis drift",
    "z": "heading-axis bias: gravity shows a rotation about the hull's z only through the roll and pitch (a degree "
         "or two), no heading reference is recorded, and the graph's own sigma for it is not a valid bound "
         "(20 turning voyages: NEES far above its chi-square interval, docs/ship.md)",
}
# The heading axis is never vouched for, whatever its sigma: measured inconsistent (benchmarks/ship_bias_consistency.py)
UNVOUCHED_AXES = ("z",)


def gyro_bias_report(estimate: ShipEstimate, sigma_bound_deg_h: float | None = None) -> dict:
    """The final gyro bias per axis with its marginal 1-sigma, each flagged ``determined`` or not.

    A component whose sigma exceeds ``sigma_bound_deg_h`` (default :data:`BIAS_SIGMA_BOUND_DEG_H`), and the
    heading axis always (:data:`UNVOUCHED_AXES`), is "not determined by this voyage", with the reason
    (:data:`UNDETERMINED_REASON`); its value and sigma are kept for the record, never as a bare result.
    """
    if sigma_bound_deg_h is None:
        sigma_bound_deg_h = BIAS_SIGMA_BOUND_DEG_H
    covariance = estimate.gyro_bias_covariance
    sigma = np.full(3, np.inf) if covariance is None else np.sqrt(np.diag(covariance)) / DEG_H  # singular: no axis
    report = {"unit": "deg/h", "sigma_bound_deg_h": float(sigma_bound_deg_h), "components": {}}
    for axis, value, s in zip("xyz", estimate.gyro_bias[-1] / DEG_H, sigma):
        determined = bool(s <= sigma_bound_deg_h) and axis not in UNVOUCHED_AXES
        entry = {"value": float(value), "sigma": float(s) if np.isfinite(s) else None, "determined": determined}
        if not determined:
            entry["reason"] = f"not determined by this voyage: {UNDETERMINED_REASON[axis]}"
        report["components"][axis] = entry
    return report


def gyro_bias_lines(report: dict) -> list[str]:
    """The report as one line per axis: ``x +6.44 +- 2.43 deg/h`` or the value, sigma and why it is not a result."""
    bound = report["sigma_bound_deg_h"]
    lines = []
    for axis, c in report["components"].items():
        if c["determined"]:
            lines.append(f"  gyro bias {axis}: {c['value']:+.3g} +- {c['sigma']:.2g} deg/h (1 sigma)")
        else:
            sigma = "unknown (singular information)" if c["sigma"] is None else f"{c['sigma']:.3g} deg/h"
            lines.append(f"  gyro bias {axis}: NOT DETERMINED by this voyage (value {c['value']:+.3g}, sigma {sigma}, "
                         f"bound {bound:g} deg/h; not a result): {UNDETERMINED_REASON[axis]}")
    return lines


def tum_text(estimate: ShipEstimate, t0_ns: int = 0) -> str:
    """TUM trajectory lines ``t x y z qx qy qz qw`` (attitude only: position 0), for evo."""
    q = Rotation.from_euler("ZYX", np.stack([estimate.yaw, estimate.pitch, estimate.roll], axis=1)).as_quat()
    lines = [f"{t0_ns * 1e-9 + t:.9f} 0 0 0 {x:.12g} {y:.12g} {z:.12g} {w:.12g}"
             for t, (x, y, z, w) in zip(estimate.t_s, q)]
    return "# t x y z qx qy qz qw (attitude of the hull, body x forward y left z up)\n" + "\n".join(lines) + "\n"


class OnlineShipTracker:
    """``selfcal track --system ship``: samples in (IMU, speed log or GPS speed), attitudes out, one per keyframe.

    ``push(sensor, t_ns, values)`` takes samples in timestamp order, with the recording's column names
    (``w_RS_S_x`` ... ``a_RS_S_z`` for ``imu0``; ``speed_log`` for ``speed0``, ``speed`` for ``gps0``).  A keyframe
    is solved once the IMU is ``angular_acceleration_window_s / 2`` past it (w_dot is a centred Savitzky-Golay
    derivative): the output delay.  The speed rate is the trailing slope over the last 5 s of speed samples, so
    the known acceleration needs no future data.  Outputs follow :mod:`selfcal.pipelines.track`: position is
    zero (attitude only) and the covariance's position block is zero; its rotation block is the marginal of the
    fixed-lag smoother.
    """

    def __init__(self, meta: dict[str, dict] | None = None, imu_name: str = "imu0",
                 options: ShipGraphOptions = ShipGraphOptions()):
        self._meta = meta
        self._start(meta, imu_name, options)

    def _start(self, meta, imu_name, options) -> None:
        from selfcal.graphs.ship import OnlineShip, ShipGraph
        meta = (meta or {}).get(imu_name, {})
        rate_hz = float(meta.get("rate_hz", 100.0))
        # an IMU gap longer than this is data missing: nothing bridges it (the sanity checks' rule)
        self._gap_s = max(GAP_PERIODS / rate_hz, GAP_FLOOR_S)
        self.imu_name, self.options = imu_name, options
        self.graph = ShipGraph(options, float(meta.get("gravity_m_s2", inertial.STANDARD_GRAVITY_M_S2)),
                               float(meta.get("gyroscope_noise_density", 1e-4)),
                               float(meta.get("gyroscope_random_walk", 1e-5)))
        self.online = OnlineShip(self.graph)
        self.t_s, self.gyro, self.accel = [], [], []  # IMU samples since the previous keyframe's window start
        self.speed_t_s, self.speed = [], []
        self.speed_sensor: str | None = None
        self.next_keyframe_s: float | None = None
        self.last_keyframe_index: int | None = None  # into the buffers

    def push(self, sensor: str, t_ns: int, values: dict) -> list[dict]:
        t_s = t_ns * 1e-9
        for name, column in SPEED_SOURCES:
            if sensor == name and column in values:
                if self.speed_sensor is not None and self.speed_sensor != name and name != SPEED_SOURCES[0][0]:
                    return []  # the speed log is preferred whenever it is there
                if self.speed_sensor != name:
                    self.speed_sensor, self.speed_t_s, self.speed = name, [], []
                self.speed_t_s.append(t_s)
                self.speed.append(float(values[column]))
                while self.speed_t_s and self.speed_t_s[0] < t_s - 2 * SPEED_RATE_WINDOW_S:
                    self.speed_t_s.pop(0)
                    self.speed.pop(0)
                return []
        if sensor != self.imu_name:
            return []
        if self.t_s and t_s - self.t_s[-1] > self._gap_s:
            log.warning("%s: %.3g s without samples before t = %d ns: the estimator starts over (no attitude is "
                        "bridged across the gap)", self.imu_name, t_s - self.t_s[-1], t_ns)
            self._start(self._meta, self.imu_name, self.options)
        self.t_s.append(t_s)
        self.gyro.append([values[c] for c in ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")])
        self.accel.append([values[c] for c in ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")])
        if self.next_keyframe_s is None:
            self.next_keyframe_s = t_s
        half = 0.5 * self.options.angular_acceleration_window_s
        outputs = []
        while t_s >= self.next_keyframe_s + half:
            outputs.append(self._solve_keyframe(t_ns))
            self.next_keyframe_s += self.options.keyframe_s
        return outputs

    def _solve_keyframe(self, t_ns_now: int) -> dict:
        from selfcal.graphs.ship import Keyframe, samples_per_keyframe, tilt_sigma_rad
        t = np.asarray(self.t_s)
        gyro, accel = np.asarray(self.gyro), np.asarray(self.accel)
        i = int(np.searchsorted(t, self.next_keyframe_s))
        i = min(i, len(t) - 1)
        window = np.abs(t - t[i]) <= 0.5 * self.options.angular_acceleration_window_s
        w_dot = _centred_slope(t[window], gyro[window], t[i])
        A = inertial.lever_arm_jacobian(gyro[i], w_dot)
        n_average, n_noise = samples_per_keyframe(1.0 / statistics.median(np.diff(t).tolist()), self.options)
        averaged = slice(max(0, i - n_average // 2), i + n_average // 2 + 1)  # the force's averaging window
        has_speed = bool(self.speed) and self.options.remove_known_acceleration
        if has_speed:
            recent = np.asarray(self.speed_t_s) >= t[i] - SPEED_RATE_WINDOW_S
            st, sv = np.asarray(self.speed_t_s)[recent], np.asarray(self.speed)[recent]
            speed = float(np.interp(t[i], st, sv)) if len(st) else self.speed[-1]
            rate = _slope(st, sv) if len(st) >= 3 else 0.0
            a_known = ship.known_acceleration_S(speed, rate, np.mean(gyro[averaged, 2]))
        else:
            a_known, speed = np.zeros(3), 0.0
        first = self.last_keyframe_index is None
        span = slice(0, 0) if first else slice(self.last_keyframe_index, i)
        f_mean, noise_var = ship.averaged_specific_force(accel, n_average, n_noise)
        sigma = tilt_sigma_rad(noise_var[i], n_average, a_known if has_speed else None, f_mean[i],
                               self.graph.gravity_m_s2, self.options)
        w_mean = np.mean(gyro[averaged], axis=0)
        frame = Keyframe(float(t[i]), gyro[span], np.diff(t)[span], f_mean[i], A, a_known, has_speed, sigma,
                         w_mean, speed * w_mean)
        (roll, pitch, yaw), bias, cov = self.online.add(frame, covariance=True)
        # drop what no later keyframe needs: samples before this keyframe's derivative window
        keep = max(0, min(i, int(np.searchsorted(t, t[i] - 0.5 * self.options.angular_acceleration_window_s))))
        del self.t_s[:keep], self.gyro[:keep], self.accel[:keep]
        self.last_keyframe_index = i - keep
        q = _quaternion_zyx(yaw, pitch, roll)
        covariance = np.zeros((6, 6))
        covariance[3:, 3:] = cov
        return {"t_ns": int(round(t[i] * 1e9)), "position": [0.0, 0.0, 0.0], "quaternion": q,
                "covariance": covariance.tolist(), "faults": {},
                "roll_rad": float(roll), "pitch_rad": float(pitch), "gyro_bias_rad_s": np.asarray(bias).tolist(),
                "delay_s": t_ns_now * 1e-9 - float(t[i]),
                **(self._unknown_speed() if self.graph.unknown_speed(frame) else {})}

    def _unknown_speed(self) -> dict:
        """The speed through the water the turns show (no speed source), with its marginal sigma."""
        key = self.graph.last_speed_key
        return {"speed_m_s": float(self.online.estimate.atVector(key)[0]),
                "speed_sigma_m_s": float(np.sqrt(self.online.smoother.marginalCovariance(key)[0, 0]))}


def _centred_slope(t_s: np.ndarray, x: np.ndarray, t0_s: float) -> np.ndarray:
    """d x / dt at ``t0_s`` from a quadratic least-squares fit over the window (the Savitzky-Golay derivative).

    Normal equations ``(V^T V) c = V^T x``, ``V = [1, tau, tau^2]``: tau spans +-1 s, so V^T V is well conditioned
    (lstsq's SVD cost ~40 us a keyframe, the streaming ship's largest Python item)."""
    if len(t_s) < 3:
        return np.zeros(x.shape[1])
    tau = t_s - t0_s
    V = np.stack([np.ones_like(tau), tau, tau**2], axis=1)
    return np.linalg.solve(V.T @ V, V.T @ x)[1]


def _slope(t_s: np.ndarray, x: np.ndarray) -> float:
    """Least-squares slope of x(t) (a straight-line fit, as ``np.polyfit(t, x, 1)[0]``, in closed form)."""
    tau = t_s - t_s.mean()
    return float(tau @ (x - x.mean()) / (tau @ tau))


def _quaternion_zyx(yaw: float, pitch: float, roll: float) -> list[float]:
    """(qx, qy, qz, qw) of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (scipy's ``from_euler("ZYX", ...)``), in closed
    form: scipy's Rotation costs ~40 us a keyframe."""
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    return [sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy]


def audit_system(recording: Recording, base: str = "attitude", sensors: list[str] | None = None):
    """The audit's view of a voyage: the attitude graph of the IMU ``sensors[0]`` (default the first)."""
    from selfcal.audit.ship import ShipAudit
    names = list(sensors or recording.imu_names()) or ["imu0"]
    return ShipAudit(ship_inputs(recording, names[0]), sensor=names[0])


def check_recording(recording: Recording, imu_name: str = "imu0") -> None:
    """What ``selfcal track --replay`` refuses before it starts: what :func:`smooth_ship` refuses, but a gap (the
    online estimator starts over there)."""
    check_speed(recording, recording.imu(imu_name, gaps_allowed=True))


def online_estimator(meta: dict[str, dict]):
    """``selfcal track --system ship``: the fixed-lag attitude smoother fed sample by sample."""
    return OnlineShipTracker(meta)

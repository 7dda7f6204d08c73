"""Physical sanity of IMU data: what a measurement must look like before anything computed from it is vouched for.

Each check is physics, not a threshold tuned to pass: on the ground the accelerometer's long-run magnitude is
gravity, a gyro integrates to at least the rotation the accelerometer's gravity direction shows between two rests
and not fifty times more, no MEMS part reads beyond its physical range, and a channel that never changes is
not measuring.  :func:`imu_problems` returns the findings as one line each, naming the likely cause and the fix;
the recording reader refuses the first (:meth:`selfcal.io.recording.Recording.imu`).

Numbers (why these and not others):

* accelerometer: the median over the recording of 1 s mean magnitudes must lie within [g/2, 2 g].  Any
  vehicle, hand or robot on the ground averages to g within a few per cent; a log in g reads 1, in mg 1000.
* gyro: between two static rests whose gravity directions differ by more than 20 deg, the angle the gyro
  integrates along the way (the path, ``sum |w| dt``: no wrap) is at least that angle and, for a hand or a
  turntable, a few times it at most; a median ratio above 15 is a gyro in deg/s (57.3), below 0.5 one that
  under-reads by a unit (mrad/s, or deg/s data converted twice).
* gyro, no rests (a ship in waves): the tilt oscillation at 1-30 s periods integrated from the gyro against the
  one the accelerometer's gravity direction shows, where they correlate (> 0.7): the same ratio bounds.
* ranges: |a| beyond 2000 m/s^2 (200 g, above any navigation or consumer MEMS range) or |w| beyond
  100 rad/s (5700 deg/s) is no measurement (a 1e300 placeholder, a mis-parsed column).
* a column with one value throughout is a dead channel.
* a column that holds its extreme value for ``SATURATION_RUN`` samples in a row, far (``SATURATION_SIGMAS`` of its
  sample-to-sample noise) from its median, is saturated: a sensor's noise and a moving signal never repeat a value
  exactly at the edge of everything the column shows, a clipped output does (the motion exceeded the sensor's
  range, and every sample at the limit under-reads by an unknown amount).
* time: a gap longer than ``max(20 sample periods, 1 s)`` is data missing, not a slow logger (the bursty USB
  loggers of the real MPU-6050 recordings stall for up to 0.28 s, once 0.5 s in 11 minutes).  A system whose
  estimator cannot bridge less sets its own, tighter limit (the tracker: :data:`selfcal.pipelines.tracker.
  MAX_IMU_GAP_S`).
* time: the median sample spacing against the sensor.yaml's ``rate_hz``, where there is one: a factor of 10
  either way (no logger runs at a tenth or ten times its stated rate) is timestamps in another unit read as ns
  (us: 1000x the rate, ms: 1e6x).  Without this the compressed time passed every other check on a ship at
  sea (its 30 s tilt band then lies beyond the recording) and was smoothed to exit 0, or was refused as an
  accelerometer in g (the 1 s means then average all the poses of a multi-position recording).

Other sensors, against the IMU on the same body (:func:`tracker_problems`, :func:`inclinometer_problems`,
:func:`coverage_problems`):

* time: the IMU carries every estimate between the aiding samples, so an aiding sample outside the IMU's record
  is used by nothing.  A recording's ends overhang by seconds of minutes (a few per cent of the samples); more
  than half of a sensor's samples outside is an IMU record cut short (a truncated file, a logger that stopped):
  the estimate would cover a sliver of the recording and drop the rest without a word.

* laser tracker: no laser tracker measures beyond 200 m (the longest-range ones, 80 m radius); and the
  acceleration its positions show must be what the accelerometer feels: ``|a_W + g e_z| = |f_B|`` whatever the
  attitude (W is gravity-aligned, z up).  Both sides are taken over the same 0.5 s windows (a quadratic fit to
  the positions, the mean specific force); the RMS of their difference may not exceed 0.1 g plus five times the
  noise the tracker's stated sigma puts on the fitted acceleration: 0.1 g covers a lever arm of 0.25 m turning at
  2 rad/s and any accelerometer bias.  Positions in mm turn every millimetre per second squared into a metre.
* inclinometer: its roll and pitch and the accelerometer's (from the same 1 s mean specific force) differ only by
  the mounting (a few degrees at most) and by dynamic accelerations (zero mean); a median difference over 10 deg
  is a reading in other units (degrees: 57 x the angle) or another frame.  Where the tilt varies well beyond
  the noise (the slope's own sigma ten times smaller than its distance from 1, the two correlating above 0.7), the
  inclinometer's gain on the accelerometer's tilt must lie in [0.1, 10]: degrees are 57, mrad 1000, while
  vibration aliased differently into a 10 Hz inclinometer and 1 s accelerometer means moved a clean near-still
  TBM's apparent gain to 0.24.

* clock jumps (:func:`clock_jump_problems`): an IMU gap while the inclinometer keeps streaming is samples lost (an
  online estimator is right to start over) or the IMU's clock jumping (every later sample restamped: its data then
  sit seconds out of step with the others').  The inclinometer reads the direction of the specific force averaged
  over its own window, so its tilt and that of the accelerometer's mean over the same window agree sample by
  sample at the right timing (vibration bursts, aliased alike into both) and not at another.  For the 60 s after
  each gap the mean square of their difference (per axis demeaned: mounting, bias) is scanned over shifts of the
  IMU's block from 0 to the whole gap (the stamps run ahead by what the gap holds beyond the samples lost), on the
  IMU's sample grid; a shift that fits better than the stamps beyond chance (F test at 1e-3 over all the shifts
  tried, Bonferroni) is a jump, refused with its size.  "The stamps" are every shift the 60 s before the gap are
  consistent with by the same test (a constant latency is the audit's time_offset, not a jump), or, where they
  cannot tell, any the estimator bridges as a gap.  Without motion both see, nothing tells: let through.

Speed (a ship's speed log or GPS speed, :func:`speed_problems`), against the accelerometer on the hull:

* the surge the speed shows is what the accelerometer's forward axis feels: ``f_x = dv/dt - g sin(pitch) +
  lever-arm terms`` (the turn's centripetal ``v r`` is in ``f_y``).  Sample by sample the waves' ``g sin(pitch)``
  and lever-arm terms (std 0.06-0.12 m/s^2 on the simulated voyages, periods 5-20 s) are as large as the surge
  (std 0.05-0.08): regressing ``dv/dt`` on ``f_x`` then gives 0.2-0.5 in correct units (errors in the regressor
  attenuate the slope; with the true pitch removed 0.8-0.94, the rest the lever arm's pitch acceleration).  Both
  are therefore averaged over the same 60 s windows (the mean of ``dv/dt`` over a window is exactly its speed
  change over 60 s; three periods of the longest pitch leave a tenth of it), and the window means of ``f_x`` are
  regressed (with an offset: accelerometer bias, trim) on those of ``dv/dt``: the noise is then in the regressand,
  where least squares expects it, and the slope ``b`` is 1 in m/s with its sigma from the residuals (a speed in
  knots gives 1/1.944, km/h 1/3.6, cm/s 1/100).  It is judged only where the voyage holds speed changes enough
  for ``sigma_b <= 0.04 |b|`` (relative, so that the judgement does not depend on the unit being judged); then
  ``b`` outside [0.72, 1.39] (the geometric midpoint to knots, both ways) is refused.  In m/s that takes
  ``|b - 1| / sigma_b >= 0.39 / (0.04 x 1.39) = 7.0`` (7.8 below), a t-statistic with ``n - 2 >= 8`` degrees of
  freedom: a false refusal probability at most 8e-5 for a 10-minute voyage, 1e-6 for 20 minutes, 7e-8 for 30,
  if the residuals are independent and normal; on 40 simulated 30-minute turning voyages (27 judged) the statistic
  ``(b - 1) / sigma_b`` measured mean -0.02, std 1.09, largest 2.65.  Without speed changes the unit cannot be
  checked, and the caller says so (a warning, not a refusal): there the speed's own noise, now in the regressor,
  pulls ``b`` towards 0 (calm voyages at constant speed: ``(b - 1) / sigma_b`` down to -6), which the relative
  sigma keeps from being judged.  What limits weak accelerations is the accelerometer's bias walk (the simulated
  MEMS's 2e-4 m/s^3/sqrt(Hz): 6e-3 m/s^2 over 15 minutes): one 10 m/s acceleration over 10 minutes is not judged.
"""
from __future__ import annotations

import numpy as np

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2, tilt_from_specific_force
from selfcal.core.static_intervals import StaticDetectionError, detect_static_intervals

ACCEL_RANGE_G = (0.5, 2.0)
MAX_ACCEL_M_S2 = 2000.0
MAX_RATE_RAD_S = 100.0
GYRO_PATH_RATIO = (0.5, 15.0)
MIN_ROTATION_DEG = 20.0
GAP_PERIODS, GAP_FLOOR_S = 20.0, 1.0
MAX_OUTSIDE_FRACTION = 0.5  # aiding samples outside the IMU record: more is a cut IMU, not an overhang
RATE_FACTOR = 10.0  # measured over stated rate: outside [1/10, 10] the timestamps are in another unit
MAX_TRACKER_RANGE_M = 200.0
TRACKER_WINDOW_S, TRACKER_ALLOWANCE_G, TRACKER_NOISE_SIGMAS = 0.5, 0.1, 5.0
MAX_TILT_DISAGREEMENT_DEG, TILT_WINDOW_S = 10.0, 1.0
GAIN_RANGE = (0.1, 10.0)  # units differ by 57 (deg) or 1000 (mrad); aliased vibration moved it to 0.24
CLOCK_WINDOW_S, CLOCK_MIN_SAMPLES, CLOCK_FALSE_ALARM = 60.0, 3, 1e-3  # clock jumps: block, judged (F dof >= 4), p
CLOCK_CHUNK = 256  # shifts evaluated at once (memory: chunk x inclinometer samples)
SPEED_WINDOW_S, MIN_SPEED_WINDOWS = 60.0, 10  # three periods of the longest pitch (20 s); t-statistic dof >= 8
SURGE_SLOPE_RANGE, SURGE_SLOPE_RELATIVE_SIGMA = (0.72, 1.39), 0.04  # 1/sqrt(1.944) either way; judged at sigma <= 4 %
SPEED_UNITS = ((1.0 / 1.943844, "knots? multiply by 0.514444"), (1.0 / 3.6, "km/h? divide by 3.6"),
               (0.01, "cm/s? multiply by 0.01"), (1.0 / 2.236936, "mph? multiply by 0.44704"))


SATURATION_RUN, SATURATION_SIGMAS = 5, 10.0


def imu_problems(t_s, gyro_rad_s, accel_m_s2, columns=("w_x", "w_y", "w_z", "a_x", "a_y", "a_z"),
                 gaps_allowed: bool = False, rate_hz: float | None = None,
                 gyro_saturation_allowed: bool = False) -> list[str]:
    """One line per physical problem of an IMU recording (empty: nothing found); ``columns`` names the six
    columns in the messages; ``gaps_allowed``: for an online replay, which starts over at a gap; ``rate_hz``:
    the stated sample rate (sensor.yaml), to which the timestamps' spacing must be near;
    ``gyro_saturation_allowed``: for a caller that excludes saturated gyro samples itself (the multi-position
    calibration weakens the moves they fall in, :mod:`selfcal.graphs.imu`)."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(gyro_rad_s, dtype=float)
    a = np.asarray(accel_m_s2, dtype=float)
    out = []
    for name, x in zip(columns, np.column_stack([w, a]).T):
        if x.size > 1 and np.ptp(x) == 0.0:
            out.append(f"column {name} is constant ({x[0]:g}) throughout: a dead channel, not a measurement")
        elif not (gyro_saturation_allowed and name in columns[:3]):
            out += _saturated(name, t, x)
    for label, x, limit, unit in (("accelerometer", a, MAX_ACCEL_M_S2, "m/s^2"), ("gyro", w, MAX_RATE_RAD_S, "rad/s")):
        with np.errstate(over="ignore", invalid="ignore"):
            norm = np.linalg.norm(x, axis=1)
        bad = np.flatnonzero(~(norm <= limit))
        if bad.size:
            out.append(f"{label} magnitude {norm[bad[0]]:.3g} {unit} at sample {bad[0] + 1} (and {bad.size - 1} more) "
                       f"is beyond any sensor's range ({limit:g} {unit}): a placeholder or a mis-read column")
    if out:
        return out
    out += _rate(t, rate_hz)
    if out:
        return out
    if not gaps_allowed:  # an online estimator starts over at a gap instead (and says so)
        out += _gap(t)
    out += _accel_units(t, a)
    if not out:
        out += _gyro_units(t, w, a) or _gyro_tilt_gain(t, w, a)
    return out


def saturated_samples(x: np.ndarray) -> np.ndarray:
    """Boolean mask of the samples of one column held at its extreme in runs of ``SATURATION_RUN`` or more, the
    extreme ``SATURATION_SIGMAS`` sample-to-sample noise sigmas from the column's median (see the module)."""
    x = np.asarray(x, dtype=float)
    mask = np.zeros(x.size, bool)
    if x.size < SATURATION_RUN or not np.all(np.isfinite(x)) or np.ptp(x) == 0.0:
        return mask
    noise = 1.4826 * float(np.median(np.abs(np.diff(x)))) / np.sqrt(2.0)  # robust: moves are few samples
    if noise == 0.0:  # noise-free (simulated exact) or coarser than its quantum: repeats say nothing
        return mask
    for extreme in (float(x.max()), float(x.min())):
        if abs(extreme - float(np.median(x))) <= SATURATION_SIGMAS * noise:
            continue
        at = np.r_[False, x == extreme, False]
        for start, end in zip(np.flatnonzero(~at[:-1] & at[1:]), np.flatnonzero(at[:-1] & ~at[1:])):
            if end - start >= SATURATION_RUN:
                mask[start:end] = True
    return mask


def _saturated(name: str, t: np.ndarray, x: np.ndarray) -> list[str]:
    mask = saturated_samples(x)
    if not mask.any():
        return []
    i = int(np.argmax(mask))
    return [f"column {name} sits at {x[i]:g} for {int(mask.sum())} samples (first at t = {t[i] - t[0]:.6g} s): "
            f"saturated, the motion exceeded the sensor's range? samples at the limit are not measurements"]


def _rate(t: np.ndarray, rate_hz: float | None) -> list[str]:
    if rate_hz is None or t.size < 2:
        return []
    spacing_s = float(np.median(np.diff(t)))
    ratio = 1.0 / (spacing_s * float(rate_hz)) if spacing_s > 0 else np.inf
    if 1.0 / RATE_FACTOR <= ratio <= RATE_FACTOR:
        return []
    hint = ("timestamps in us? multiply by 1000" if 300 < ratio < 3000 else
            "timestamps in ms? multiply by 1e6" if 3e5 < ratio < 3e6 else "timestamps not in ns, or rate_hz wrong")
    return [f"samples {spacing_s:.3g} s apart ({ratio * float(rate_hz):.4g} Hz) but sensor.yaml says rate_hz "
            f"{float(rate_hz):g}: {hint}"]


def _gap(t: np.ndarray) -> list[str]:
    if t.size < 3:
        return []
    dt = np.diff(t)
    limit = max(GAP_PERIODS * float(np.median(dt)), GAP_FLOOR_S)
    big = np.flatnonzero(dt > limit)
    if not big.size:
        return []
    i = int(big[np.argmax(dt[big])])
    return [f"{dt[i]:.3g} s without samples after t = {t[i] - t[0]:.6g} s (sample {i + 1}; {big.size} gap(s) over "
            f"{limit:.3g} s): data are missing there; split the recording at the gap"]


def _accel_units(t: np.ndarray, a: np.ndarray) -> list[str]:
    n = max(1, int(round(1.0 / max(float(np.median(np.diff(t))) if t.size > 1 else 1.0, 1e-9))))
    m = len(a) // n
    means = a[:m * n].reshape(m, n, 3).mean(axis=1) if m else a.mean(axis=0, keepdims=True)
    g_ratio = float(np.median(np.linalg.norm(means, axis=1))) / STANDARD_GRAVITY_M_S2
    if ACCEL_RANGE_G[0] <= g_ratio <= ACCEL_RANGE_G[1]:
        return []
    hint = ("accelerometer in g? multiply by 9.80665" if abs(g_ratio * STANDARD_GRAVITY_M_S2 - 1.0) < 0.5 else
            "accelerometer in mg? multiply by 0.00980665" if 500.0 < g_ratio * STANDARD_GRAVITY_M_S2 < 2000.0 else
            "raw counts? convert with the part's sensitivity")
    return [f"the accelerometer's long-run magnitude is {g_ratio * STANDARD_GRAVITY_M_S2:.4g} m/s^2 "
            f"({g_ratio:.3g} g, not 1 g): {hint}"]


def _smoothed(x: np.ndarray, n: int) -> np.ndarray:
    """Moving mean over n samples (same length; the ends use what there is)."""
    c = np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])
    i = np.arange(len(x))
    lo, hi = np.clip(i - n // 2, 0, len(x)), np.clip(i + n // 2 + 1, 0, len(x))
    return (c[hi] - c[lo]) / (hi - lo)[:, None]


def _gyro_tilt_gain(t: np.ndarray, w: np.ndarray, a: np.ndarray) -> list[str]:
    """Without rests (a ship in waves, a vehicle): the tilt oscillation the accelerometer's gravity direction
    shows against the gyro's integral about the same axes, both band-passed to 1-30 s periods where gravity
    dominates the specific force.  Gain 1 within the lateral accelerations of the motion (a factor 2 either way);
    deg/s gives 1/57.  Judged only where the two agree in shape (correlation above 0.7) and the tilt moves."""
    if t.size < 100:
        return []
    dt = float(np.median(np.diff(t)))
    n_fast, n_slow = max(1, int(round(1.0 / dt))), int(round(30.0 / dt))
    if t.size < 2 * n_slow:
        return []
    roll, pitch = tilt_from_specific_force(a)
    tilt_accel = np.column_stack([roll, pitch])
    tilt_gyro = np.cumsum(w[:, :2] * np.gradient(t)[:, None], axis=0)
    band = lambda x: _smoothed(x, n_fast) - _smoothed(x, n_slow)  # noqa: E731
    x, y = band(tilt_gyro), band(tilt_accel)
    ratios = []
    for k in range(2):
        var_x = float(x[:, k] @ x[:, k])
        if var_x == 0.0 or float(np.std(y[:, k])) < np.radians(0.2):  # the tilt must move to be judged
            continue
        gain = float(x[:, k] @ y[:, k]) / var_x
        corr = float(x[:, k] @ y[:, k]) / np.sqrt(var_x * float(y[:, k] @ y[:, k]))
        if corr > 0.7:
            ratios.append(1.0 / gain)
    if not ratios or all(GYRO_PATH_RATIO[0] <= r <= GYRO_PATH_RATIO[1] for r in ratios):
        return []
    ratio = float(np.median(ratios))
    hint = "gyro in deg/s? multiply by pi/180" if 30.0 < ratio < 120.0 else "check the gyro's unit (rad/s expected)"
    return [f"the gyro integrates {ratio:.3g} x the tilt oscillation the accelerometer's gravity direction shows "
            f"(1 expected): {hint}"]


def _gyro_units(t: np.ndarray, w: np.ndarray, a: np.ndarray) -> list[str]:
    """Integrated rotation path between consecutive static rests against their gravity directions' angle."""
    try:
        intervals = detect_static_intervals(t, a)
    except StaticDetectionError:
        return []  # no initial rest: not a multi-position recording, nothing to compare
    ratios = []
    for (s0, e0), (s1, e1) in zip(intervals[:-1], intervals[1:]):
        g0, g1 = a[s0:e0].mean(axis=0), a[s1:e1].mean(axis=0)
        angle = np.degrees(np.arccos(np.clip(g0 @ g1 / (np.linalg.norm(g0) * np.linalg.norm(g1)), -1.0, 1.0)))
        if angle < MIN_ROTATION_DEG:
            continue
        path = np.degrees(np.sum(np.linalg.norm(w[e0:s1], axis=1) * np.diff(t[e0:s1 + 1])))
        ratios.append(path / angle)
    if len(ratios) < 2:
        return []
    ratio = float(np.median(ratios))
    if GYRO_PATH_RATIO[0] <= ratio <= GYRO_PATH_RATIO[1]:
        return []
    hint = ("gyro in deg/s? multiply by pi/180" if 30.0 < ratio < 120.0 else
            "the gyro under-reads the rotation: check its unit (rad/s expected)" if ratio < 1.0 else
            "check the gyro's unit (rad/s expected)")
    return [f"between {len(ratios) + 1} rests the gyro integrates {ratio:.3g} x the rotation the accelerometer's "
            f"gravity direction shows (a rotation path is 1-3 x it): {hint}"]



def _window_means(t_s: np.ndarray, x: np.ndarray, centres_s: np.ndarray, half_width_s: float) -> np.ndarray:
    """Mean of the rows of ``x`` (N, k) within +-half_width of each centre (NaN where none), by cumulative sums."""
    c = np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])
    lo = np.searchsorted(t_s, centres_s - half_width_s)
    hi = np.searchsorted(t_s, centres_s + half_width_s)
    n = (hi - lo)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (c[hi] - c[lo]) / n, np.nan)


def quadratic_second_derivative_weights(n: int, dt_s: float) -> np.ndarray:
    """Weights (n,) whose dot product with ``n`` samples ``dt_s`` apart gives the second derivative, at the middle
    sample, of the least-squares quadratic through them: the interior of ``scipy.signal.savgol_filter(x, n, 2,
    deriv=2, delta=dt_s)`` (equal to 1e-13 relative).  Importing scipy.signal costs ~1.1 s of CPU, a tenth of
    ``selfcal track --replay`` on 300 s of tracker data, for these few lines."""
    half = n // 2
    x = np.arange(-half, half + 1) * dt_s
    return 2.0 * np.linalg.pinv(np.vander(x, 3, increasing=True))[2]  # 2 c2 of the fit c0 + c1 x + c2 x^2


def coverage_problems(t_imu_s, t_other_s, other: str) -> list[str]:
    """The IMU's record against an aiding sensor's samples (one clock, s; module docstring)."""
    t_imu, t = np.asarray(t_imu_s, dtype=float), np.asarray(t_other_s, dtype=float)
    if t_imu.size == 0 or t.size == 0:
        return []
    outside = int(np.count_nonzero((t < t_imu[0]) | (t > t_imu[-1])))
    if outside <= MAX_OUTSIDE_FRACTION * t.size:
        return []
    return [f"the IMU record covers {t_imu[-1] - t_imu[0]:.4g} s, {other} {t[-1] - t[0]:.4g} s ({outside} of {t.size} "
            f"of its samples outside): the IMU record is cut short (a truncated file, a logger that stopped)"]


def tracker_problems(t_tracker_s, p_W_m, t_imu_s, f_B_m_s2, tracker_W_m=(0.0, 0.0, 0.0),
                     position_sigma_m: float = 0.5e-3, gravity_m_s2: float = STANDARD_GRAVITY_M_S2) -> list[str]:
    """One line per physical problem of laser-tracker positions (W, m) against the IMU on the same body
    (``t_*_s`` on one clock, s): the range, and the acceleration the positions show against the one the
    accelerometer feels (module docstring)."""
    t = np.asarray(t_tracker_s, dtype=float)
    p = np.asarray(p_W_m, dtype=float)
    distance = float(np.median(np.linalg.norm(p - np.asarray(tracker_W_m, dtype=float), axis=1)))
    if distance > MAX_TRACKER_RANGE_M:
        hint = "positions in mm? multiply by 0.001" if distance / 1000.0 <= MAX_TRACKER_RANGE_M else "check its unit (m)"
        return [f"the target is {distance:.4g} m from the tracker (median), beyond any laser tracker's range "
                f"({MAX_TRACKER_RANGE_M:g} m): {hint}"]
    n = int(round(TRACKER_WINDOW_S / float(np.median(np.diff(t))))) | 1 if t.size > 1 else 0
    if n < 5 or t.size < 3 * n:
        return []
    dt = float(np.median(np.diff(t)))
    weights = quadratic_second_derivative_weights(n, dt)
    a_W = np.lib.stride_tricks.sliding_window_view(p, n, axis=0) @ weights  # (N - n + 1, 3): the window centres
    centres = t[n // 2:-(n // 2)]
    f_mean = _window_means(np.asarray(t_imu_s, dtype=float), np.asarray(f_B_m_s2, dtype=float), centres, n * dt / 2)
    ok = np.isfinite(f_mean[:, 0])
    if ok.sum() < n:
        return []
    seen = np.linalg.norm(a_W[ok] + np.array([0.0, 0.0, gravity_m_s2]), axis=1)
    felt = np.linalg.norm(f_mean[ok], axis=1)
    mismatch = float(np.sqrt(np.mean((seen - felt) ** 2)))
    # noise of the fitted acceleration: the tracker sigma through the second-derivative weights
    allowed = TRACKER_ALLOWANCE_G * gravity_m_s2 + TRACKER_NOISE_SIGMAS * position_sigma_m * float(
        np.linalg.norm(weights))
    if mismatch <= allowed:
        return []
    return [f"its positions accelerate unlike the IMU it rides with (RMS of |a + g| - |f| = {mismatch:.3g} m/s^2, "
            f"allowed {allowed:.2g}): positions in mm or another unit? they must be in m, on the IMU's clock"]


def inclinometer_problems(t_s, roll_pitch_rad, accel_roll_pitch_rad) -> list[str]:
    """One line if an inclinometer's (roll, pitch) (N, 2) at times ``t_s`` disagree with the accelerometer's tilt
    at the same times (N, 2; :func:`accelerometer_tilt_at`): by more than a mounting offset, or, where the tilt
    varies enough to tell, by a gain other than 1 (a reading in degrees has 57)."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(roll_pitch_rad, dtype=float)
    ref = np.asarray(accel_roll_pitch_rad, dtype=float)
    ok = np.all(np.isfinite(ref), axis=1)
    if ok.sum() < 3:
        return []
    t, x, ref = t[ok], x[ok], ref[ok]
    wrap = lambda d: np.abs(np.angle(np.exp(1j * d)))  # noqa: E731
    diff = np.degrees(np.median(wrap(x - ref), axis=0))
    gains = [_gain(t, x[:, k], ref[:, k]) for k in range(2)]
    if np.all(diff <= MAX_TILT_DISAGREEMENT_DEG) and all(GAIN_RANGE[0] <= g <= GAIN_RANGE[1] for g in gains):
        return []
    in_degrees = np.degrees(np.median(wrap(np.radians(x) - ref), axis=0))
    hint = ("in degrees? multiply by pi/180" if np.all(in_degrees <= MAX_TILT_DISAGREEMENT_DEG) else
            "check its unit (rad) and its axes (roll about x, pitch about y of the IMU)")
    return [f"its roll and pitch differ from the accelerometer's by {diff[0]:.3g} and {diff[1]:.3g} deg (median; "
            f"mounting allows a few), gain {gains[0]:.3g} and {gains[1]:.3g} (1 expected): {hint}"]


def _gain(t: np.ndarray, x: np.ndarray, ref: np.ndarray) -> float:
    """Slope of ``x`` on ``ref`` (with an offset), over 1 s means so that neighbours are independent; 1.0 when
    the reference's variation is under ten times the slope's own uncertainty could tell (nothing to judge)."""
    bins = np.floor((t - t[0]) / TILT_WINDOW_S).astype(int)
    count = np.bincount(bins)
    keep = count > 0
    xm, rm = (np.bincount(bins, v)[keep] / count[keep] for v in (x, ref))
    if xm.size < 10:
        return 1.0
    rc, xc = rm - rm.mean(), xm - xm.mean()
    var = float(rc @ rc)
    if var == 0.0:
        return 1.0
    slope = float(rc @ xc) / var
    resid = xc - slope * rc
    slope_sigma = float(np.sqrt(resid @ resid / (xm.size - 2) / var))
    corr = float(rc @ xc) / np.sqrt(var * float(xc @ xc)) if float(xc @ xc) > 0 else 0.0
    # judged only where the two follow each other (vibration aliases differently into a 10 Hz inclinometer and a
    # 200 Hz accelerometer's 1 s means: on a near-still TBM their tilts then hardly correlate, in any unit)
    return slope if corr > 0.7 and abs(slope - 1.0) > 10.0 * slope_sigma else 1.0


def accelerometer_tilt_at(t_s, t_imu_s, f_B_m_s2) -> np.ndarray:
    """(N, 2) roll and pitch of the 1 s mean specific force around each time (NaN where no IMU sample)."""
    f = _window_means(np.asarray(t_imu_s, dtype=float), np.asarray(f_B_m_s2, dtype=float),
                      np.asarray(t_s, dtype=float), TILT_WINDOW_S / 2)
    return np.column_stack(tilt_from_specific_force(f))


def speed_problems(t_speed_s, speed, t_imu_s, f_x_m_s2) -> tuple[list[str], str | None]:
    """The speed (m/s expected) at ``t_speed_s`` against the accelerometer's forward specific force ``f_x_m_s2``
    at ``t_imu_s`` (one clock, s): one line per problem, and the reason the unit could not be judged (None when
    it was).  The slope of the 60 s means of ``f_x`` on the speed's mean rate over the same windows (module
    docstring)."""
    t_v, v = np.asarray(t_speed_s, dtype=float), np.asarray(speed, dtype=float)
    ok = np.isfinite(v)
    t_v, v = t_v[ok], v[ok]
    t_imu = np.asarray(t_imu_s, dtype=float)
    start, end = max(t_v[0], t_imu[0]) if t_v.size else 0.0, min(t_v[-1], t_imu[-1]) if t_v.size else 0.0
    n = int((end - start) // SPEED_WINDOW_S) if t_v.size >= 2 else 0
    if n < MIN_SPEED_WINDOWS:
        return [], (f"cannot check the speed's unit: the voyage is shorter than {MIN_SPEED_WINDOWS} windows of "
                    f"{SPEED_WINDOW_S:g} s")
    edges = start + SPEED_WINDOW_S * np.arange(n + 1)
    surge = np.diff(np.interp(edges, t_v, v)) / SPEED_WINDOW_S  # the window's mean dv/dt, exactly
    c = np.concatenate([[0.0], np.cumsum(np.asarray(f_x_m_s2, dtype=float))])
    i = np.searchsorted(t_imu, edges)
    counts = np.diff(i)
    if np.any(counts == 0):
        return [], "cannot check the speed's unit: the IMU has windows without samples"
    f_mean = np.diff(c[i]) / counts
    sc, fc = surge - surge.mean(), f_mean - f_mean.mean()
    var = float(sc @ sc)
    slope = float(sc @ fc) / var if var > 0 else 0.0
    resid = fc - slope * sc
    sigma = float(np.sqrt(resid @ resid / (n - 2) / var)) if var > 0 else np.inf
    if not sigma <= SURGE_SLOPE_RELATIVE_SIGMA * abs(slope):  # relative: the same judgement in any unit
        return [], (f"cannot check the speed's unit: the voyage holds no speed change the accelerometer tells from "
                    f"the waves (slope {slope:.3g} +- {sigma:.2g} over {n} windows of {SPEED_WINDOW_S:g} s; a "
                    f"sigma under {100 * SURGE_SLOPE_RELATIVE_SIGMA:g} % of it needed)")
    if SURGE_SLOPE_RANGE[0] <= slope <= SURGE_SLOPE_RANGE[1]:
        return [], None
    factor, hint = min(SPEED_UNITS, key=lambda u: abs(np.log(max(slope, 1e-12) / u[0])))
    hint = f"speed in {hint} to get m/s" if 0.9 < slope / factor < 1.1 else "check its unit (m/s expected)"
    return [f"its speed changes {1.0 / slope if slope else np.inf:.3g} x as fast as the accelerometer's surge "
            f"(slope of f_x on dv/dt {slope:.3g} +- {sigma:.2g} over {n} windows of {SPEED_WINDOW_S:g} s; 1 "
            f"expected): {hint}"], None



def clock_jump_problems(t_imu_s, f_B_m_s2, t_incl_s, tilt_incl_rad, average_s: float, min_gap_s: float,
                        window_s: float = CLOCK_WINDOW_S) -> list[str]:
    """One line per IMU gap longer than ``min_gap_s`` after which the IMU's stamps no longer agree in time with
    the inclinometer's (``t_*_s`` on one clock, s; module docstring): a clock jump, not data lost.  Gaps where
    the inclinometer cannot tell (no motion it and the accelerometer both see) are let through."""
    t = np.asarray(t_imu_s, dtype=float)
    f = np.asarray(f_B_m_s2, dtype=float)
    t_inc, tilt = np.asarray(t_incl_s, dtype=float), np.asarray(tilt_incl_rad, dtype=float)
    if t.size < 3 or t_inc.size < CLOCK_MIN_SAMPLES:
        return []
    dt = float(np.median(np.diff(t)))
    ends = np.flatnonzero(np.diff(t) > min_gap_s)  # the last sample before each gap
    bounds = np.concatenate([[0], ends + 1, [t.size]])
    out = []
    for g, i in enumerate(ends):
        gap_s = float(t[i + 1] - t[i])
        before = slice(max(bounds[g], int(np.searchsorted(t, t[i] - window_s))), i + 1)
        after = slice(i + 1, min(bounds[g + 2], int(np.searchsorted(t, t[i + 1] + window_s))))
        # the reference: the shifts the block before the gap is consistent with (a latency, the audit's
        # time_offset, not a jump); where it cannot tell, any the estimator would bridge as a gap
        pre = _shift_scan(t[before], f[before], t_inc, tilt, average_s, dt, -min_gap_s, min_gap_s)
        consistent = _consistent(pre) if pre is not None else np.zeros(0, dtype=bool)
        lo, hi = (pre[0][consistent].min(), pre[0][consistent].max()) if consistent.any() else (-min_gap_s, min_gap_s)
        reference = 0.0 if lo <= 0.0 <= hi else float(pre[0][np.argmin(pre[1])])  # as stamped, unless shown off
        # after the gap the stamps run ahead by what the gap holds beyond the samples lost: 0 to the whole gap
        post = _shift_scan(t[after], f[after], t_inc, tilt, average_s, dt, lo - 0.5 * dt, hi + gap_s)
        if post is None:
            continue
        shifts, mean_square, _ = post
        in_reference = (shifts >= lo - 0.5 * dt) & (shifts <= hi + 0.5 * dt)
        if not _significant(post, in_reference):
            continue
        best = int(np.argmin(mean_square))
        jump = float(shifts[best]) - reference
        rms_stamped, rms = np.sqrt(np.min(mean_square[in_reference])), np.sqrt(mean_square[best])
        out.append(f"its clock jumps {jump:.4g} s at its {gap_s:.4g} s gap after t = {t[i] - t[0]:.6g} s: after the "
                   f"gap its accelerometer's tilt matches the inclinometer's {jump:.4g} s off its stamps (RMS "
                   f"{1e3 * rms_stamped:.2g} mrad as stamped, {1e3 * rms:.2g} shifted): samples restamped, not "
                   "lost; correct its timestamps after the gap, or split the recording there")
    return out


def _critical_ratio(scan, ref: int, best: int) -> float:
    """The F test's critical ratio of two mean squares of a scan at CLOCK_FALSE_ALARM over every shift tried
    (Bonferroni)."""
    from scipy.special import fdtri  # the F distribution's quantile (scipy.stats costs seconds to import)

    shifts, _, counts = scan
    return float(fdtri(2 * counts[ref] - 2, 2 * counts[best] - 2, 1.0 - CLOCK_FALSE_ALARM / shifts.size))


def _consistent(scan) -> np.ndarray:
    """The shifts of a scan (:func:`_shift_scan`) that fit not significantly worse than its best (F test)."""
    shifts, mean_square, _ = scan
    if not np.isfinite(mean_square).any() or not mean_square.min() > 0:
        return np.zeros(shifts.size, dtype=bool)
    best = int(np.argmin(mean_square))
    return np.array([np.isfinite(m) and m / mean_square[best] <= _critical_ratio(scan, k, best)
                     for k, m in enumerate(mean_square)])


def _significant(scan, reference: np.ndarray) -> bool:
    """Whether the best shift of a scan fits better than the best within ``reference`` (a mask over its shifts)
    beyond chance (F test)."""
    shifts, mean_square, counts = scan
    if not np.isfinite(mean_square[reference]).any():
        return False
    ref = int(np.flatnonzero(reference)[np.argmin(mean_square[reference])])
    best = int(np.argmin(mean_square))
    if best == ref or not mean_square[best] > 0:
        return False
    return bool(mean_square[ref] / mean_square[best] > _critical_ratio(scan, ref, best))


def _shift_scan(t, f, t_inc, tilt, average_s, dt, lo_s, hi_s):
    """The IMU block (``t``, ``f``) read ``shift`` s off its stamps (IMU stamp = inclinometer time + shift), for
    shifts in [lo_s, hi_s] that are multiples of the IMU's sample period ``dt``: the mean square of the per-axis demeaned
    difference between the inclinometer's tilt and the tilt of the accelerometer's mean over the inclinometer's
    averaging window.  Returns (shifts, mean squares (inf where too few inclinometer samples to judge), their
    counts of inclinometer samples), or None when the block is too short."""
    if t.size < 2:
        return None
    window = max(average_s, dt)
    c = np.vstack([np.zeros(3), np.cumsum(f, axis=0)])
    shifts = dt * np.arange(np.ceil(lo_s / dt - 1e-9), np.floor(hi_s / dt + 1e-9) + 1)
    first, last = np.searchsorted(t_inc, [t[0] + window - shifts.max(), t[-1] + dt - shifts.min()])
    t_inc, tilt = t_inc[first:last], tilt[first:last]  # every inclinometer sample some shift puts in the block
    mean_square, counts = np.full(shifts.size, np.inf), np.zeros(shifts.size, dtype=int)
    for k in range(0, shifts.size, CLOCK_CHUNK):  # (shifts, samples) at once, a chunk of shifts at a time
        tau = t_inc[None, :] + shifts[k:k + CLOCK_CHUNK, None]  # the inclinometer's samples on the IMU's stamps
        lo, hi = np.searchsorted(t, tau - window - 1e-9), np.searchsorted(t, tau - 1e-9)
        ok = (hi > lo) & (tau - window >= t[0]) & (tau <= t[-1] + dt)
        with np.errstate(invalid="ignore", divide="ignore"):
            f_mean = (c[hi] - c[lo]) / (hi - lo)[..., None]
            r = np.stack(tilt_from_specific_force(f_mean.reshape(-1, 3)), axis=-1).reshape(*tau.shape, 2) - tilt
        r = np.where(ok[..., None], r, 0.0)
        n = ok.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            r_mean = r.sum(axis=1) / n[:, None]
            ms = (np.sum(r ** 2, axis=(1, 2)) - n * np.sum(r_mean ** 2, axis=1)) / (2 * n)  # per-axis demeaned
        judged = n >= CLOCK_MIN_SAMPLES
        mean_square[k:k + CLOCK_CHUNK] = np.where(judged, ms, np.inf)
        counts[k:k + CLOCK_CHUNK] = n
    return shifts, mean_square, counts

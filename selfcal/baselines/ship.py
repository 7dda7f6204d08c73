"""Baseline: gyro drift compensation by low-pass-filtered accelerometer tilt, as patent seed 003 writes it.

The method (C2SAT, "用于对位置测量装置中的漂移进行补偿的方法", method for compensating drift in a position
measuring device, Fig. 2):

1. a gyro (50) gives the angles Psi, Theta, Phi (yaw, roll, pitch); each is low-pass filtered (51, 52, 53);
2. an accelerometer (20) gives the total force vector; the tilt is computed from it (module 23), so a vertical
   translation (heave), which changes only the magnitude of the force, leaves the tilt unchanged; the tilt is
   low-pass filtered (24, 25);
3. per axis a controller (54, 55, 56), preferably PID, acts on the difference of the two low-pass signals; its
   compensation is ADDED (57, 58, 59) to the instantaneous gyro angle; the adder's output is both the input of
   the gyro low-pass filter and the final drift-compensated angle;
4. all low-pass filters share one cutoff (claim 12), chosen above the typical heave frequency and below the
   typical roll/pitch frequency (claim 1);
5. known accelerations are subtracted before the tilt (claims 2-8): the surge acceleration dv/dt from the speed
   log / GPS speed on the longitudinal axis, the centrifugal acceleration v * yaw_rate (yaw rate from the gyro)
   on the transverse axis;
6. yaw is compensated from a compass if there is one (claim 11).

Deviations, stated:

* our gyro outputs body rates, not angles: the "gyro angles" are integrated from the rates with the ZYX
  Euler-angle kinematics (see `euler_rates_zyx`), evaluated at the current compensated attitude;
* we have no compass, so yaw is integrated and left uncompensated (its correction column is zero);
* the known accelerations are subtracted on the body axes directly (small-tilt approximation, as the patent
  does): at roll phi the centrifugal term is mis-projected by ``v r (1 - cos phi)`` on y and ``v r sin phi``
  on z.

Conventions: body x forward, y left, z up; world z up; ``R = Rz(yaw) Ry(pitch) Rx(roll)`` maps body to world;
specific force at rest ``f = R^T (0, 0, g)`` (points up).

Loop analysis (continuous time, first-order low-pass ``L = wc / (s + wc)``, ``wc = 2 pi f_c``, PI
``C = kp + ki / s``).  Because the low-pass filters are linear and share one cutoff,
``LP(tilt) - LP(angle) = LP(tilt - angle)``, so the loop closes on ``L C``; its characteristic polynomial is
``s^2 + wc (1 + kp) s + wc ki``.  The default ``kp = 1``, ``ki = wc`` puts a double pole at ``-wc``
(critically damped, natural frequency wc): an initial attitude error decays as ``(1 + wc t) exp(-wc t)``, below
2 % after ``5.8 / wc`` and below 0.1 % after ``9.2 / wc``.  A gyro bias ``b`` makes the gyro angle a ramp; a PI
(one integrator) follows it with a constant error ``b / ki`` (= ``b / wc`` by default; 10 deg/h at
f_c = 0.05 Hz gives 0.009 deg).  With a second-order Butterworth low-pass the characteristic polynomial is
``s^3 + sqrt(2) wc s^2 + wc^2 (1 + kp) s + wc^2 ki``, stable (Routh) while ``ki < sqrt(2) (1 + kp) wc``; the
default gains satisfy it by a factor 2.8.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter


G_M_S2 = 9.80665

# Sampling must be uniform for the fixed-coefficient IIR filters: tolerated spread of dt around its median.
_DT_RELATIVE_TOLERANCE = 0.01


@dataclass
class PatentDriftResult:
    """Output of `PatentDriftFilter.run`, one row per sample.

    Attributes
    ----------
    roll, pitch, yaw : (N,) drift-compensated angles in rad (the adders' 57-59 outputs); yaw is uncompensated.
    correction : (N, 3) compensation in rad added to the integrated gyro roll, pitch, yaw (yaw column zero).
    tilt_roll, tilt_pitch : (N,) instantaneous accelerometer tilt in rad, after known-acceleration removal.
    """

    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    correction: np.ndarray
    tilt_roll: np.ndarray
    tilt_pitch: np.ndarray


def euler_rates_zyx(roll: float, pitch: float, omega_body) -> tuple[float, float, float]:
    """Euler-angle rates from body rates for ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (standard kinematics).

    ``roll' = p + tan(pitch) (q sin roll + r cos roll)``, ``pitch' = q cos roll - r sin roll``,
    ``yaw' = (q sin roll + r cos roll) / cos(pitch)``; singular at pitch = +-90 deg.
    """
    p, q, r = omega_body
    sr, cr = math.sin(roll), math.cos(roll)
    qr = q * sr + r * cr
    cp = math.cos(pitch)
    return p + math.tan(pitch) * qr, q * cr - r * sr, qr / cp


def cutoff_between(heave_period_s: float, roll_period_s: float) -> float:
    """Common low-pass cutoff in Hz for claim 1: above the heave frequency, below the roll/pitch frequency.

    Returns the geometric mean ``1 / sqrt(T_heave T_roll)``, equally far (in log frequency) from both.

    Raises
    ------
    ValueError
        if a period is not positive, or the heave period is not longer than the roll period (no cutoff can
        lie above the heave frequency and below the roll frequency).
    """
    if not (heave_period_s > 0.0 and roll_period_s > 0.0):
        raise ValueError(f"periods must be positive, got heave {heave_period_s} s, roll {roll_period_s} s")
    if heave_period_s <= roll_period_s:
        raise ValueError(
            f"heave period {heave_period_s} s is not longer than roll period {roll_period_s} s: no cutoff lies "
            "above the heave frequency and below the roll/pitch frequency")
    return 1.0 / math.sqrt(heave_period_s * roll_period_s)


def vessel_cutoff_hz(heave_periods_s, roll_periods_s) -> float:
    """The cutoff a user sets from the vessel's own periods: claim 1's rule (:func:`cutoff_between`) on the
    fastest heave and the slowest roll/pitch period.  Where the swell is not slower than the roll (calm seas,
    turning), the rule cannot be met; the cutoff then sits an octave below the slowest roll/pitch period."""
    roll_s = float(max(roll_periods_s))
    try:
        return cutoff_between(float(min(heave_periods_s)), roll_s)
    except ValueError:
        return 0.5 / roll_s


def default_gains(cutoff_hz: float) -> tuple[float, float]:
    """PI gains ``(kp, ki)`` = ``(1, 2 pi f_c)``: closed-loop double pole at ``-2 pi f_c`` (module docstring)."""
    return 1.0, 2.0 * math.pi * cutoff_hz


def settling_time_s(cutoff_hz: float, fraction: float = 0.02) -> float:
    """Time for ``(1 + wc t) exp(-wc t)`` (default gains, first-order low-pass) to fall to ``fraction``."""
    wc = 2.0 * math.pi * cutoff_hz
    x = 1.0
    for _ in range(60):  # Newton on h(x) = log(1 + x) - x - log(fraction), increasing root
        x -= (math.log1p(x) - x - math.log(fraction)) / (1.0 / (1.0 + x) - 1.0)
    return x / wc


def causal_speed_derivative(t_s, speed_m_s, window_s: float = 1.0) -> np.ndarray:
    """Surge acceleration ``dv/dt`` by a backward difference over ``window_s`` (causal; lag ``window_s / 2``).

    The first window uses the samples available so far; the first sample gets 0.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(speed_m_s, dtype=float)
    if v.shape != t.shape:
        raise ValueError(f"speed has shape {v.shape}, time {t.shape}")
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    n = max(1, int(round(window_s / dt)))
    k0 = np.maximum(np.arange(t.size) - n, 0)
    span = t - t[k0]
    out = np.zeros_like(v)
    ok = span > 0.0
    out[ok] = (v[ok] - v[k0[ok]]) / span[ok]
    return out


def _lowpass_coefficients(cutoff_hz: float, fs_hz: float, order: int) -> tuple[float, ...]:
    """Butterworth low-pass as one biquad ``(b0, b1, b2, a1, a2)`` (order 1 padded with zeros)."""
    if order not in (1, 2):
        raise ValueError(f"filter_order must be 1 or 2, got {order}")
    if not 0.0 < cutoff_hz < 0.5 * fs_hz:
        raise ValueError(f"cutoff {cutoff_hz} Hz must lie in (0, {0.5 * fs_hz}) Hz for sampling at {fs_hz} Hz")
    b, a = butter(order, cutoff_hz, fs=fs_hz)
    b = list(b) + [0.0] * (3 - len(b))
    a = list(a) + [0.0] * (3 - len(a))
    return float(b[0]), float(b[1]), float(b[2]), float(a[1]), float(a[2])


@dataclass
class PatentDriftFilter:
    """Online drift compensation of roll and pitch (patent seed 003, Fig. 2).

    Parameters
    ----------
    cutoff_hz : common cutoff of all low-pass filters (claim 12); see `cutoff_between` for claim 1's rule.
    kp, ki, kd : PID gains on ``LP(tilt) - LP(compensated angle)``; ``kp``/``ki`` default to `default_gains`,
        ``kd`` to 0 (the error is already low-passed; a D term adds nothing the PI needs).  ``ki`` in 1/s,
        ``kd`` in s.
    remove_known_acceleration : subtract ``dv/dt`` from f_x and ``v * yaw_rate`` from f_y before the tilt
        (claims 2-8), when a speed is given to `run`.
    filter_order : Butterworth order, 1 (default; the gains are tuned for it) or 2.
    speed_derivative_window_s : window of the causal backward difference of the speed.
    align_to_first_tilt : start the integrated roll/pitch at the first sample's tilt; otherwise at zero.
    """

    cutoff_hz: float
    kp: float | None = None
    ki: float | None = None
    kd: float = 0.0
    remove_known_acceleration: bool = True
    filter_order: int = 1
    speed_derivative_window_s: float = 1.0
    align_to_first_tilt: bool = True

    def gains(self) -> tuple[float, float, float]:
        kp0, ki0 = default_gains(self.cutoff_hz)
        return (kp0 if self.kp is None else float(self.kp), ki0 if self.ki is None else float(self.ki),
                float(self.kd))

    def run(self, t_s, gyro_rad_s, accel_m_s2, speed_m_s=None) -> PatentDriftResult:
        """Run the loop sample by sample (causal).

        Parameters
        ----------
        t_s : (N,) uniformly sampled times, s.
        gyro_rad_s : (N, 3) body rates (x forward, y left, z up), rad/s.
        accel_m_s2 : (N, 3) specific force, m/s^2 (``R^T (a + g z)``, +g up at rest).
        speed_m_s : (N,) speed over ground / through water along body x, or None (no known-acceleration removal).

        Returns
        -------
        PatentDriftResult
        """
        t = np.asarray(t_s, dtype=float)
        w = np.asarray(gyro_rad_s, dtype=float)
        f = np.asarray(accel_m_s2, dtype=float)
        n = t.size
        if t.ndim != 1 or n < 2:
            raise ValueError("t_s must be a 1-D array of at least 2 samples")
        if w.shape != (n, 3) or f.shape != (n, 3):
            raise ValueError(f"gyro {w.shape} and accel {f.shape} must both have shape ({n}, 3)")
        dts = np.diff(t)
        dt_med = float(np.median(dts))
        if dt_med <= 0.0 or np.any(np.abs(dts - dt_med) > _DT_RELATIVE_TOLERANCE * dt_med):
            raise ValueError("t_s must be increasing and uniformly sampled (the IIR filters have fixed coefficients)")
        b0, b1, b2, a1, a2 = _lowpass_coefficients(self.cutoff_hz, 1.0 / dt_med, self.filter_order)
        kp, ki, kd = self.gains()

        use_speed = self.remove_known_acceleration and speed_m_s is not None
        if use_speed:
            v = np.asarray(speed_m_s, dtype=float)
            a_surge = causal_speed_derivative(t, v, self.speed_derivative_window_s)
        else:
            v = np.zeros(n)
            a_surge = np.zeros(n)

        out_roll, out_pitch, out_yaw, out_u_roll, out_u_pitch, out_tr, out_tp = _loop(
            t.tolist(), w.tolist(), f.tolist(), v.tolist(), a_surge.tolist(), use_speed,
            (b0, b1, b2, a1, a2), kp, ki, kd, self.align_to_first_tilt)
        correction = np.zeros((n, 3))
        correction[:, 0] = out_u_roll
        correction[:, 1] = out_u_pitch
        return PatentDriftResult(np.array(out_roll), np.array(out_pitch), np.array(out_yaw), correction,
                                 np.array(out_tr), np.array(out_tp))


def integrate_euler_angles(t_s, gyro_rad_s, initial_rad=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Uncompensated gyro angles (roll, pitch, yaw), (N, 3): ZYX Euler kinematics, trapezoidal body rates."""
    t = np.asarray(t_s, dtype=float).tolist()
    w = np.asarray(gyro_rad_s, dtype=float).tolist()
    roll, pitch, yaw = (float(x) for x in initial_rad)
    out = [(roll, pitch, yaw)]
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        wp, wk = w[k - 1], w[k]
        dr, dp, dy = euler_rates_zyx(roll, pitch, (0.5 * (wp[0] + wk[0]), 0.5 * (wp[1] + wk[1]),
                                                   0.5 * (wp[2] + wk[2])))
        roll += dt * dr
        pitch += dt * dp
        yaw += dt * dy
        out.append((roll, pitch, yaw))
    return np.array(out)


def _loop(t, w, f, v, a_surge, use_speed, coefficients, kp, ki, kd, align):
    """The per-sample loop on plain floats (1 h at 50 Hz, 180k samples, in about 0.6 s).

    Per sample k: integrate the Euler rates at the compensated attitude; adder: angle = gyro angle + u(k-1)
    (the previous compensation, so the loop has no algebraic cycle); tilt from f minus known accelerations;
    low-pass both; PID on the difference gives u(k).
    """
    b0, b1, b2, a1, a2 = coefficients
    sin, cos, tan, atan2, sqrt = math.sin, math.cos, math.tan, math.atan2, math.sqrt
    n = len(t)
    out_roll, out_pitch, out_yaw = [0.0] * n, [0.0] * n, [0.0] * n
    out_ur, out_up, out_tr, out_tp = [0.0] * n, [0.0] * n, [0.0] * n, [0.0] * n

    def tilt(fk, vk, ak, yaw_rate):
        fx, fy, fz = fk
        if use_speed:
            fx -= ak  # surge: forward acceleration adds to f_x
            fy -= vk * yaw_rate  # centripetal, towards the turn centre (left for yaw_rate > 0)
        return atan2(fy, fz), atan2(-fx, sqrt(fy * fy + fz * fz))

    # sample 0: a first tilt with the body z rate as yaw rate, then again with the Euler yaw rate at the start
    tr, tp = tilt(f[0], v[0], a_surge[0], w[0][2])
    roll_g, pitch_g = (tr, tp) if align else (0.0, 0.0)
    tr, tp = tilt(f[0], v[0], a_surge[0], euler_rates_zyx(roll_g, pitch_g, w[0])[2])
    yaw = 0.0
    u_r = u_p = 0.0
    i_r = i_p = 0.0
    roll_c, pitch_c = roll_g, pitch_g

    # DF2T states initialised at steady state for the first input: z1 = (b1 + b2 - a1 - a2) x, z2 = (b2 - a2) x
    c1, c2 = b1 + b2 - a1 - a2, b2 - a2
    z_tr1, z_tr2 = c1 * tr, c2 * tr
    z_tp1, z_tp2 = c1 * tp, c2 * tp
    z_cr1, z_cr2 = c1 * roll_c, c2 * roll_c
    z_cp1, z_cp2 = c1 * pitch_c, c2 * pitch_c
    e_r_prev = tr - roll_c
    e_p_prev = tp - pitch_c
    out_roll[0], out_pitch[0], out_tr[0], out_tp[0] = roll_c, pitch_c, tr, tp

    for k in range(1, n):
        dt = t[k] - t[k - 1]
        wp, wk = w[k - 1], w[k]
        p = 0.5 * (wp[0] + wk[0])
        q = 0.5 * (wp[1] + wk[1])
        r = 0.5 * (wp[2] + wk[2])
        # ZYX Euler kinematics at the current (compensated) attitude
        sr, cr = sin(roll_c), cos(roll_c)
        qr = q * sr + r * cr
        roll_dot = p + tan(pitch_c) * qr
        pitch_dot = q * cr - r * sr
        yaw_dot = qr / cos(pitch_c)
        roll_g += dt * roll_dot
        pitch_g += dt * pitch_dot
        yaw += dt * yaw_dot
        # adders 57-59: instantaneous gyro angle + compensation
        roll_c = roll_g + u_r
        pitch_c = pitch_g + u_p

        tr, tp = tilt(f[k], v[k], a_surge[k], yaw_dot)

        # low-pass 24, 25 (tilt) and 52, 53 (compensated gyro angle), DF2T
        y_tr = b0 * tr + z_tr1
        z_tr1 = b1 * tr - a1 * y_tr + z_tr2
        z_tr2 = b2 * tr - a2 * y_tr
        y_tp = b0 * tp + z_tp1
        z_tp1 = b1 * tp - a1 * y_tp + z_tp2
        z_tp2 = b2 * tp - a2 * y_tp
        y_cr = b0 * roll_c + z_cr1
        z_cr1 = b1 * roll_c - a1 * y_cr + z_cr2
        z_cr2 = b2 * roll_c - a2 * y_cr
        y_cp = b0 * pitch_c + z_cp1
        z_cp1 = b1 * pitch_c - a1 * y_cp + z_cp2
        z_cp2 = b2 * pitch_c - a2 * y_cp

        # controllers 55, 56: PID on LP(tilt) - LP(compensated angle)
        e_r = y_tr - y_cr
        e_p = y_tp - y_cp
        i_r += ki * e_r * dt
        i_p += ki * e_p * dt
        out_ur[k], out_up[k] = u_r, u_p  # the compensation that produced this sample's angle
        u_r = kp * e_r + i_r + kd * (e_r - e_r_prev) / dt
        u_p = kp * e_p + i_p + kd * (e_p - e_p_prev) / dt
        e_r_prev, e_p_prev = e_r, e_p

        out_roll[k], out_pitch[k], out_yaw[k] = roll_c, pitch_c, yaw
        out_tr[k], out_tp[k] = tr, tp
    return out_roll, out_pitch, out_yaw, out_ur, out_up, out_tr, out_tp

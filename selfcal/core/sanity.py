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
* ranges: |a| beyond 2000 m/s^2 (200 g, above any navigation or consumer MEMS range) or |w| beyond
  100 rad/s (5700 deg/s) is no measurement (a 1e300 placeholder, a mis-parsed column).
* a column with one value throughout is a dead channel.
* time: a gap longer than ``max(20 sample periods, 1 s)`` is data missing, not a slow logger (the bursty USB
  loggers of the shipped MPU-6050 recordings stay below 0.1 s).
"""
from __future__ import annotations

import numpy as np

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.core.static_intervals import StaticDetectionError, detect_static_intervals

ACCEL_RANGE_G = (0.5, 2.0)
MAX_ACCEL_M_S2 = 2000.0
MAX_RATE_RAD_S = 100.0
GYRO_PATH_RATIO = (0.5, 15.0)
MIN_ROTATION_DEG = 20.0
GAP_PERIODS, GAP_FLOOR_S = 20.0, 1.0


def imu_problems(t_s, gyro_rad_s, accel_m_s2, columns=("w_x", "w_y", "w_z", "a_x", "a_y", "a_z")) -> list[str]:
    """One line per physical problem of an IMU recording (empty: nothing found); ``columns`` names the six
    columns in the messages."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(gyro_rad_s, dtype=float)
    a = np.asarray(accel_m_s2, dtype=float)
    out = []
    for name, x in zip(columns, np.column_stack([w, a]).T):
        if x.size > 1 and np.ptp(x) == 0.0:
            out.append(f"column {name} is constant ({x[0]:g}) throughout: a dead channel, not a measurement")
    for label, x, limit, unit in (("accelerometer", a, MAX_ACCEL_M_S2, "m/s^2"), ("gyro", w, MAX_RATE_RAD_S, "rad/s")):
        with np.errstate(over="ignore", invalid="ignore"):
            norm = np.linalg.norm(x, axis=1)
        bad = np.flatnonzero(~(norm <= limit))
        if bad.size:
            out.append(f"{label} magnitude {norm[bad[0]]:.3g} {unit} at sample {bad[0] + 1} (and {bad.size - 1} more) "
                       f"is beyond any sensor's range ({limit:g} {unit}): a placeholder or a mis-read column")
    if out:
        return out
    out += _gap(t)
    out += _accel_units(t, a)
    if not out:
        out += _gyro_units(t, w, a)
    return out


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


"""Static intervals of a multi-position IMU recording, detected from the accelerometer alone (imu_tk style).

Tedaldi, Pretto and Menegatti (ICRA 2014) classify every sample by the local variance magnitude of the
accelerometer: ``s_k = || (var_x, var_y, var_z) ||`` over a window centred on sample k; a sample is static
when ``s_k < k_th * s_init``, with ``s_init`` the same statistic on an initial period during which the IMU
must rest.  Here ``s_init`` is the median of ``s_k`` over that period (insensitive to a bump in it), and runs of
static samples shorter than a minimum duration are dropped (imu_tk drops intervals shorter than its window).

Units do not matter: the threshold is relative to the initial period, so the detector is invariant to scale
and offset and raw ADC counts work as well as m/s^2 (only direction counting needs the offset removed).

References
----------
D. Tedaldi, A. Pretto, E. Menegatti, "A Robust and Easy to Implement Method for IMU Calibration without
External Equipments", ICRA 2014, pp. 3042-3049; imu_tk ``staticIntervalsDetector`` (src/filters.cpp).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from selfcal.core.errors import SelfcalError

log = logging.getLogger(__name__)

DEFAULT_T_INIT_S = 10.0
DEFAULT_WINDOW_S = 1.0
DEFAULT_THRESHOLD_FACTOR = 6.0
DEFAULT_MIN_DURATION_S = 1.0
DEFAULT_MIN_SEPARATION_DEG = 10.0


class TooFewStaticPosesError(SelfcalError):
    """The recording does not hold enough distinct static orientations for the requested calibration."""


class StaticDetectionError(SelfcalError):
    """The recording cannot be segmented: too short for the initial static period, or that period moves."""


@dataclass
class StaticPose:
    """Samples ``start:end`` of one static interval: means and per-axis sample standard deviations.

    ``direction_id`` numbers the distinct gravity directions as :func:`static_poses` labels them (poses with the
    same id point within ``min_separation_deg`` of each other); None when the pose was built elsewhere.
    """

    start: int
    end: int
    n_samples: int
    accel_mean: np.ndarray
    gyro_mean: np.ndarray
    accel_std: np.ndarray
    gyro_std: np.ndarray
    direction_id: int | None = None


def _window_sums(x: np.ndarray, w: int) -> np.ndarray:
    """``sum(x[a : a + w])`` for a = 0 .. N - w, from prefix sums restarted every w samples.

    A window starting at offset o > 0 of block b is the tail of block b plus the head of block b + 1:
    ``total[b] - prefix[a - 1] + prefix[a + w - 1]``.  Each prefix runs over at most w samples, so the round-off
    is ~eps * w * max|x|, independent of the recording length (one global cumsum would grow like N^1.5).
    """
    n = len(x)
    n_blocks = -(-n // w)
    padded = np.zeros((n_blocks * w,) + x.shape[1:])
    padded[:n] = x
    prefix = np.cumsum(padded.reshape((n_blocks, w) + x.shape[1:]), axis=1).reshape(padded.shape)
    a = np.arange(n - w + 1)
    offset = a % w
    sums = prefix[(a // w) * w + w - 1]  # block totals: exact for windows aligned to a block (offset 0)
    tail = offset > 0
    sums[tail] += prefix[a[tail] + w - 1] - prefix[a[tail] - 1]
    return sums


def moving_variance_norm(x: np.ndarray, window: int) -> np.ndarray:
    """``|| var(x[k-h : k+h+1], axis=0) ||`` for every sample k with a full window, NaN at the h edge samples.

    ``window`` is made odd (``h = window // 2``); unbiased variance.  O(N) from block-restarted running sums of
    the mean-removed signal, with a round-off of a few eps * max(x - mean)^2.
    """
    x = np.asarray(x, dtype=float)
    h = window // 2
    w = 2 * h + 1
    out = np.full(len(x), np.nan)
    if len(x) < w:
        return out
    xc = x - x.mean(axis=0)
    sum1, sum2 = _window_sums(xc, w), _window_sums(xc**2, w)
    var = np.maximum(sum2 - sum1**2 / w, 0.0) / (w - 1)  # clipped: round-off can make a zero variance negative
    out[h:len(x) - h] = np.linalg.norm(var, axis=1)
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of every run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def detect_static_intervals(t_s, accel_m_s2, t_init_s: float = DEFAULT_T_INIT_S, window_s: float = DEFAULT_WINDOW_S,
                            threshold_factor: float = DEFAULT_THRESHOLD_FACTOR,
                            min_duration_s: float = DEFAULT_MIN_DURATION_S) -> list[tuple[int, int]]:
    """Static intervals ``[(start, end), ...]`` (start inclusive, end exclusive) from the accelerometer.

    A sample is static when the variance magnitude over the window centred on it is below
    ``threshold_factor`` times its median over the first ``t_init_s`` seconds (Tedaldi et al. 2014).  Because
    the window must be quiet, every interval starts and ends about half a window inside the true rest period,
    so transitions never leak into the means.

    Parameters
    ----------
    t_s : (N,) sample times, s, increasing.  Only used for the sample rate and the initial period.
    accel_m_s2 : (N, 3) accelerometer output; any units (raw counts work: the threshold is relative).
    t_init_s : length of the initial period during which the IMU rests.  It only sets the noise reference, and
        the median of ~10 windows is already stable (the real Xsens and MPU-6050 recordings give the same
        intervals for 5..36 s); 10 s matches ``selfcal.sim``'s initial rest.  imu_tk uses 50 s, because it also
        estimates the gyro bias from that period.
    window_s : variance window, s (imu_tk: 101 samples at 100 Hz).  Shorter windows let short holds through but
        make the statistic noisier; 1 s suits hand-held holds of 3 s or more.
    threshold_factor : multiple of the initial statistic (imu_tk searches 2..10).  The statistic on true rest
        scatters by ~sqrt(2 / window samples) (chi-square), so 6 never rejects quiet rest, and leaves room for
        the extra settling vibration of hand-placed poses (1-3x the initial level on the MPU-6050 recording).
    min_duration_s : shorter static runs are dropped (momentary pauses while turning the IMU).

    Returns
    -------
    list of (start, end) sample indices, in time order.

    Raises
    ------
    StaticDetectionError
        The recording is shorter than ``t_init_s``, the initial period spans fewer than two windows, or more
        than 5 % of the initial period looks like motion (the IMU was not at rest at the start).
    """
    t_s = np.asarray(t_s, dtype=float)
    accel = np.asarray(accel_m_s2, dtype=float)
    if t_s.ndim != 1 or accel.shape != (len(t_s), 3):
        raise StaticDetectionError(f"expected t (N,) and accel (N, 3), got {t_s.shape} and {accel.shape}")
    if len(t_s) < 2 or not np.all(np.diff(t_s) > 0):
        raise StaticDetectionError("sample times must be strictly increasing (at least two samples)")
    dt_s = float(np.median(np.diff(t_s)))
    window = 2 * int(round(0.5 * window_s / dt_s)) + 1
    h = window // 2
    duration_s = float(t_s[-1] - t_s[0])
    if duration_s < t_init_s:
        raise StaticDetectionError(f"the recording ({duration_s:.1f} s) is shorter than its initial static period "
                                   f"t_init_s = {t_init_s:g} s: record the IMU at rest first, or shorten t_init_s")
    n_init = int(np.searchsorted(t_s, t_s[0] + t_init_s))
    if n_init < 2 * window:
        raise StaticDetectionError(f"the initial static period ({t_init_s:g} s, {n_init} samples) must span at "
                                   f"least two variance windows ({window} samples each, window_s = {window_s:g})")
    stat = moving_variance_norm(accel, window)
    init_stat = stat[h:n_init - h]
    s_init = float(np.median(init_stat))
    # Floor well above the round-off of the window sums (a few eps max(x - mean)^2), so that noise-free simulated
    # data, whose rest variance is exactly zero, still count as static; far below any real sensor's noise.
    round_off = 1024 * np.finfo(float).eps * float(np.max((accel - accel.mean(axis=0)) ** 2))
    threshold = threshold_factor * s_init + round_off
    moving_fraction = float(np.mean(init_stat >= threshold))
    if moving_fraction > 0.05:
        raise StaticDetectionError(
            f"the first {t_init_s:g} s are not static ({100 * moving_fraction:.0f} % of it moves): start the "
            f"recording with the IMU at rest for t_init_s, or pass the length of the rest period actually recorded")
    static = np.zeros(len(t_s), dtype=bool)
    static[h:len(t_s) - h] = stat[h:len(t_s) - h] < threshold
    intervals = [(start, end) for start, end in _runs(static) if t_s[end - 1] - t_s[start] >= min_duration_s]
    log.debug("static detector: window %d samples, threshold %.4g (%.3g x initial), %d intervals",
              window, threshold, threshold_factor, len(intervals))
    return intervals


def direction_labels(accel_means, min_separation_deg: float = DEFAULT_MIN_SEPARATION_DEG) -> np.ndarray:
    """(N,) labels 0, 1, ... of distinct gravity directions, by greedy clustering in time order.

    Mean i gets the label of the first earlier representative within ``min_separation_deg``, else a new label
    (and becomes that label's representative).
    """
    means = np.asarray(accel_means, dtype=float).reshape(-1, 3)
    units = means / np.linalg.norm(means, axis=1, keepdims=True).clip(min=np.finfo(float).tiny)
    cos_min = np.cos(np.radians(min_separation_deg))
    representatives: list[np.ndarray] = []
    labels = np.empty(len(units), dtype=int)
    for i, u in enumerate(units):
        close = [j for j, r in enumerate(representatives) if u @ r >= cos_min]
        if close:
            labels[i] = close[0]
        else:
            labels[i] = len(representatives)
            representatives.append(u)
    return labels


def count_distinct_directions(accel_means, min_separation_deg: float = DEFAULT_MIN_SEPARATION_DEG) -> int:
    """Number of gravity directions among the static means that differ by more than ``min_separation_deg``.

    Repeated placements on the same face add noise averaging but no new equation for a calibration, so this,
    not the number of intervals, is what a calibration needs enough of.  ``accel_means`` must have the offset
    (bias) roughly removed: directions of raw counts around a mid-scale offset are meaningless.
    """
    labels = direction_labels(accel_means, min_separation_deg)
    return int(labels.max() + 1) if len(labels) else 0


def static_poses(t_s, accel, gyro, intervals, min_separation_deg: float = DEFAULT_MIN_SEPARATION_DEG
                 ) -> list[StaticPose]:
    """Mean and per-axis standard deviation of accelerometer and gyro over every interval, one pose each.

    One pose per interval, in order (moves between consecutive intervals stay aligned with the poses);
    ``direction_id`` labels the distinct gravity directions (``min_separation_deg`` apart).

    Parameters
    ----------
    t_s : (N,) sample times (validated against the signals' length).
    accel, gyro : (N, 3) signals; gyro may be None (its fields are then NaN).
    intervals : [(start, end), ...] from :func:`detect_static_intervals`.
    """
    accel = np.asarray(accel, dtype=float)
    gyro = np.full_like(accel, np.nan) if gyro is None else np.asarray(gyro, dtype=float)
    if accel.shape != (len(t_s), 3) or gyro.shape != accel.shape:
        raise ValueError(f"expected accel and gyro of shape ({len(t_s)}, 3), got {accel.shape} and {gyro.shape}")
    poses = []
    for start, end in intervals:
        a, g = accel[start:end], gyro[start:end]
        ddof = 1 if len(a) > 1 else 0
        poses.append(StaticPose(int(start), int(end), len(a), a.mean(axis=0), g.mean(axis=0),
                                a.std(axis=0, ddof=ddof), g.std(axis=0, ddof=ddof)))
    for pose, label in zip(poses, direction_labels([p.accel_mean for p in poses], min_separation_deg)):
        pose.direction_id = int(label)
    return poses


def require_static_poses(poses: list[StaticPose], minimum: int) -> int:
    """Number of distinct static orientations in ``poses``; TooFewStaticPosesError if fewer than ``minimum``.

    Uses the ``direction_id`` labels of :func:`static_poses`; poses built without them are counted with
    :func:`count_distinct_directions` at the default separation.
    """
    if all(p.direction_id is not None for p in poses):
        found = len({p.direction_id for p in poses})
    else:
        found = count_distinct_directions([p.accel_mean for p in poses])
    if found < minimum:
        raise TooFewStaticPosesError(
            f"found {found} distinct static orientation(s) in {len(poses)} static interval(s), need at least "
            f"{minimum}: hold the IMU still for a few seconds each in more different orientations (e.g. lay it "
            f"on each of its 6 faces and a few tilted orientations)")
    return found

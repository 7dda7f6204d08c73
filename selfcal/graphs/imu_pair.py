"""Rotation (and clock offset, lever arm, relative biases) between two rigidly mounted IMUs, as a factor graph.

Variables: ``R_imu0_imu1`` (Rot3, v_imu0 = R v_imu1), optional time offset ``dt_s`` (t_imu0 = t_imu1 + dt),
lever arm ``r_m`` (imu1's position in the imu0 frame), relative accelerometer and gyro offsets (imu0 frame).
Factors: the patent's static residual ``a0 - R a1`` per static pose, and blocks of dynamic samples (gyro:
``w0(t) - R w1(t - dt)``; accelerometer: ``a0(t) + L(t) r - R a1(t - dt)``).  Start: Wahba's problem solved
by SVD (scipy's ``Rotation.align_vectors``) on the same vectors; then Levenberg–Marquardt with a Huber kernel.

Sigmas: each factor group (static, gyro, accelerometer) gets its noise level re-estimated from its own
residuals after a first solve (variance-component estimation), so reported 1-sigmas follow the data — on
real rigs vibration, not sensor white noise, sets the residual of the dynamic pairs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.signal import butter, savgol_filter, sosfiltfilt
from scipy.spatial.transform import Rotation

from selfcal.factors import imu as fimu
from selfcal.core.solve import DegenerateDataError, marginal_covariances, optimize, robust
from selfcal.io.recording import ImuData
from selfcal.core.signals import cross_correlation_lag
from selfcal.core.static_intervals import detect_static_intervals
from selfcal.core.stats import correlation_inflation

ROTATION, TIME_OFFSET, LEVER_ARM = gtsam.symbol("R", 0), gtsam.symbol("t", 0), gtsam.symbol("l", 0)
ACCEL_OFFSET, GYRO_OFFSET = gtsam.symbol("o", 0), gtsam.symbol("o", 1)
ACCEL_GAIN, GYRO_GAIN = gtsam.symbol("s", 0), gtsam.symbol("s", 1)
ACCEL_AXIS_ROTATION = gtsam.symbol("s", 2)
GROUPS = ("static", "gyro", "accel")


@dataclass
class StaticPair:
    accel0: np.ndarray  # mean raw accelerometer output of imu0, m/s^2
    accel1: np.ndarray
    sigma: np.ndarray  # 1-sigma of accel0 - R accel1 from the noise of both means, per axis
    n_samples0: int = 0
    n_samples1: int = 0


@dataclass
class DynamicData:
    """imu0 samples (its clock) and imu1's signals (its clock) for the dynamic pair factors."""

    t0_s: np.ndarray
    gyro0: np.ndarray
    accel0: np.ndarray
    gyro_rate_dot0: np.ndarray  # smoothed angular acceleration of imu0, rad/s^2
    gyro1: fimu.Signal
    accel1: fimu.Signal
    gyro_sigma: float  # per-sample 1-sigma of w0 - R w1 (rad/s)
    accel_sigma: float  # per-sample 1-sigma of a0 - R a1 (m/s^2)
    block_s: float = 0.5
    gyro_bias0: np.ndarray = field(default_factory=lambda: np.zeros(3))  # imu0's gyro at absolute rest (rad/s)

    @property
    def rate0(self) -> np.ndarray:
        """imu0's angular rate for the lever arm's centripetal term, its bias at rest removed: with the raw rate
        a MEMS bias b (~0.01 rad/s) leaves ``b x (w x r) + w x (b x r)`` in the accelerometer pair, linear in w
        (~1 mm/s^2 per rad/s at 8 cm; the audit named it, a term in w_y beside the lever arm).  The gyro pair
        residual keeps the raw rate: its offset ``d_g`` takes the relative bias."""
        return self.gyro0 - self.gyro_bias0


@dataclass(frozen=True)
class PairModel:
    time_offset: bool = True
    lever_arm: bool = True
    accel_offset: bool = True
    gyro_offset: bool = True
    accel_gain: bool = False  # imu1's accelerometer scale/non-orthogonality relative to imu0 (symmetric, 6)
    gyro_gain: bool = False
    # imu1's accelerometer triad rotated relative to its gyro triad (relative to imu0's), 3; needs motion: while
    # the rig stands still only the accelerometers see the rotation R and it absorbs this one
    accel_axis_rotation: bool = False


@dataclass
class PairEstimate:
    R_imu0_imu1: np.ndarray
    rotation_cov_rad2: np.ndarray  # right-perturbation tangent (imu1 axes)
    time_offset_s: float | None = None
    time_offset_sigma_s: float | None = None
    lever_arm_m: np.ndarray | None = None
    lever_arm_sigma_m: np.ndarray | None = None
    accel_offset_m_s2: np.ndarray | None = None
    gyro_offset_rad_s: np.ndarray | None = None
    gains: dict = field(default_factory=dict)  # "accel"/"gyro" -> (I + S (3x3), sigma of the 6 entries of S)
    residual_rms: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def wahba_rotation(vectors0: np.ndarray, vectors1: np.ndarray, weights=None) -> np.ndarray:
    """R minimising sum w |v0 - R v1|^2 (SVD solution of Wahba's problem, via scipy)."""
    rotation, _ = Rotation.align_vectors(vectors0, vectors1, weights=weights)
    return rotation.as_matrix()


def coarse_time_offset(t0_s, gyro0, t1_s, gyro1, max_lag_s=0.5) -> float:
    """dt (t_imu0 = t_imu1 + dt) maximising the correlation of the rotation-invariant |w| signals.

    |w0|(t) = |w1|(t - dt): the delay of imu0's signal behind imu1's, on imu0's grid.
    """
    grid = np.arange(t0_s[0], t0_s[-1], float(np.median(np.diff(t0_s))))
    n0 = np.interp(grid, t0_s, np.linalg.norm(gyro0, axis=1))
    n1 = np.interp(grid, t1_s, np.linalg.norm(gyro1, axis=1))
    return cross_correlation_lag(grid, n1, n0, max_lag_s)


def _blocks(n, t_s, block_s):
    edges = np.searchsorted(t_s, np.arange(t_s[0], t_s[-1] + block_s, block_s))
    return [np.arange(a, b) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 3]


def _build(static: list[StaticPair], dynamic: DynamicData | None, model: PairModel, scale: dict, huber_k,
           channels: dict[str, list[tuple[int, np.ndarray]]] | None = None):
    """The pair graph; ``channels`` (group ``gyro``/``accel`` -> [(key, phi over the dynamic samples)]) adds
    relative offsets varying as ``k phi`` (the audit's generic terms)."""
    channels = channels or {}
    graph = gtsam.NonlinearFactorGraph()
    groups = []
    accel_offset = ACCEL_OFFSET if model.accel_offset else None
    accel_gain = ACCEL_GAIN if model.accel_gain else None
    gyro_gain = GYRO_GAIN if model.gyro_gain else None
    accel_rotation = ACCEL_AXIS_ROTATION if model.accel_axis_rotation else None
    for pair in static:
        graph.add(fimu.static_pair_factor(robust(pair.sigma * scale["static"], huber_k), pair.accel0, pair.accel1,
                                          ROTATION, accel_offset, accel_gain, accel_rotation))
        groups.append("static")
    if dynamic is not None:
        dt_key = TIME_OFFSET if model.time_offset else None
        for idx in _blocks(len(dynamic.t0_s), dynamic.t0_s, dynamic.block_s):
            n = len(idx)
            graph.add(fimu.dynamic_pair_factor(
                robust(np.full(3 * n, dynamic.gyro_sigma * scale["gyro"]), huber_k), dynamic.t0_s[idx],
                dynamic.gyro0[idx], dynamic.gyro1, ROTATION, dt_key, GYRO_OFFSET if model.gyro_offset else None,
                gain_key=gyro_gain, offset_channels=[(k, phi[idx]) for k, phi in channels.get("gyro", ())]))
            groups.append("gyro")
            graph.add(fimu.dynamic_pair_factor(
                robust(np.full(3 * n, dynamic.accel_sigma * scale["accel"]), huber_k), dynamic.t0_s[idx],
                dynamic.accel0[idx], dynamic.accel1, ROTATION, dt_key, accel_offset,
                LEVER_ARM if model.lever_arm else None, dynamic.rate0[idx], dynamic.gyro_rate_dot0[idx],
                gain_key=accel_gain, offset_channels=[(k, phi[idx]) for k, phi in channels.get("accel", ())],
                axis_rotation_key=accel_rotation))
            groups.append("accel")
    return graph, groups


def _group_residuals(graph, groups, values) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per factor group, each factor's (unwhitened, whitened) residual."""
    out: dict[str, list] = {}
    for i, name in enumerate(groups):
        factor = graph.at(i)
        e = factor.unwhitenedError(values)
        noise = factor.noiseModel()
        base = noise.noise() if isinstance(noise, gtsam.noiseModel.Robust) else noise
        out.setdefault(name, []).append((e, base.whiten(e)))
    return out


def _group_rms(graph, groups, values):
    """Per factor group: (whitened RMS, which is 1 when the sigmas match the data; RMS in physical units)."""
    return {g: (float(np.sqrt(np.mean(np.concatenate([w for _, w in r]) ** 2))),
                float(np.sqrt(np.mean(np.concatenate([e for e, _ in r]) ** 2))))
            for g, r in _group_residuals(graph, groups, values).items()}


def rotation_covariance_at(static: list[StaticPair], dynamic: DynamicData | None, model: PairModel,
                           values: gtsam.Values) -> np.ndarray:
    """Marginal covariance of R at given values with the data's stated sigmas (no robust kernel, no reweighting).

    Evaluated at the truth this is the Cramér–Rao bound of the graph's model for this data.
    """
    graph, _ = _build(static, dynamic, model, {g: 1.0 for g in GROUPS}, huber_k=None)
    return marginal_covariances(graph, values, [ROTATION], "the rotation between the IMUs")[ROTATION]


def pair_values(R_imu0_imu1, model: PairModel, dt_s=0.0, lever_arm_m=None, accel_offset=None,
                gyro_offset=None) -> gtsam.Values:
    """Values for the variables ``model`` estimates (zeros where not given)."""
    values = gtsam.Values()
    values.insert(ROTATION, gtsam.Rot3(np.asarray(R_imu0_imu1, dtype=float)))
    for flag, key, value, dim in ((model.time_offset, TIME_OFFSET, [dt_s], 1),
                                  (model.lever_arm, LEVER_ARM, lever_arm_m, 3),
                                  (model.accel_offset, ACCEL_OFFSET, accel_offset, 3),
                                  (model.gyro_offset, GYRO_OFFSET, gyro_offset, 3),
                                  (model.accel_gain, ACCEL_GAIN, None, 6), (model.gyro_gain, GYRO_GAIN, None, 6),
                                  (model.accel_axis_rotation, ACCEL_AXIS_ROTATION, None, 3)):
        if flag:
            values.insert(key, np.zeros(dim) if value is None else np.asarray(value, dtype=float))
    return values


def solve_pair(static: list[StaticPair], dynamic: DynamicData | None, model: PairModel = PairModel(),
               huber_k: float | None = 3.0, reweight: bool = True, initial_dt_s: float = 0.0) -> PairEstimate:
    """Estimate R_imu0_imu1 and, as the model asks, time offset, lever arm and relative offsets."""
    if dynamic is None:
        model = PairModel(False, False, model.accel_offset and len(static) >= 3, False)
    vectors0 = [p.accel0 for p in static]
    vectors1 = [p.accel1 for p in static]
    if dynamic is not None:
        vectors0 += list(dynamic.gyro0)
        vectors1 += list(dynamic.gyro1.at(dynamic.t0_s - initial_dt_s)[0])
    # specific force while moving also fixes the rotation (gravity sweeps as the rig turns)
    _check_rotation_excitation(np.array(vectors0 + ([] if dynamic is None else list(dynamic.accel0))))
    values = pair_values(wahba_rotation(np.array(vectors0), np.array(vectors1)), model, initial_dt_s)
    scale = {g: 1.0 for g in GROUPS}
    graph, groups = _build(static, dynamic, model, scale, huber_k)
    values = optimize(graph, values)
    if reweight:
        residuals = _group_residuals(graph, groups, values)
        scale = {g: 1.0 for g in GROUPS}
        for g, r in residuals.items():
            white = np.concatenate([w for _, w in r])
            if g == "static":
                # sigmas of static means come from the samples themselves: only inflate them when the residuals
                # are significantly larger (model error); n - 6 corrects for the rotation and offset fitted
                dof = max(len(white) - 6, 1)
                scale[g] = max(1.0, float(np.sqrt(np.sum(white**2) / dof)))
            else:
                inflation = correlation_inflation([w.reshape(-1, 3) for _, w in r])
                scale[g] = max(float(np.sqrt(np.mean(white**2) * inflation)), 1e-3)
        graph, groups = _build(static, dynamic, model, scale, huber_k)
        values = optimize(graph, values)

    keys = [k for k in (ROTATION, TIME_OFFSET, LEVER_ARM, ACCEL_GAIN, GYRO_GAIN) if values.exists(k)]
    cov = marginal_covariances(graph, values, keys, "the rotation between the IMUs")
    R = values.atRot3(ROTATION).matrix()
    rotation_sigma_deg = np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(cov[ROTATION]))))
    if rotation_sigma_deg > 2.0:
        raise DegenerateDataError(
            f"rotation between the IMUs undetermined (sigma {rotation_sigma_deg:.1f} deg): hold the rig still in "
            "at least two orientations with different gravity directions, or rotate it about two different axes")
    est = PairEstimate(R_imu0_imu1=R, rotation_cov_rad2=cov[ROTATION])
    est.residual_rms = {g: physical for g, (_, physical) in _group_rms(graph, groups, values).items()}
    if model.time_offset:
        est.time_offset_s = float(values.atVector(TIME_OFFSET)[0])
        est.time_offset_sigma_s = float(np.sqrt(cov[TIME_OFFSET][0, 0]))
    if model.lever_arm:
        est.lever_arm_m = values.atVector(LEVER_ARM)
        est.lever_arm_sigma_m = np.sqrt(np.diag(cov[LEVER_ARM]))
    if model.accel_offset:
        est.accel_offset_m_s2 = values.atVector(ACCEL_OFFSET)
    if model.gyro_offset:
        est.gyro_offset_rad_s = values.atVector(GYRO_OFFSET)
    for name, key in (("accel", ACCEL_GAIN), ("gyro", GYRO_GAIN)):
        if values.exists(key):
            est.gains[name] = (fimu.symmetric_gain(values.atVector(key)), np.sqrt(np.diag(cov[key])))
    return est


def _check_rotation_excitation(vectors: np.ndarray) -> None:
    directions = vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
    strong = directions[np.linalg.norm(vectors, axis=1) > 1e-3]
    if len(strong) < 2 or np.linalg.svd(strong, compute_uv=False)[1] / np.sqrt(len(strong)) < 0.02:
        raise DegenerateDataError(
            "all measured vectors are parallel, so the rotation about them is free: hold the rig still in at "
            "least two orientations with different gravity directions, or rotate it about two different axes")


# --- from recordings ----------------------------------------------------------------------------------------

def _sample_sigma(data: ImuData, key: str, fallback: float) -> float:
    density = data.meta.get(key)
    return float(density * np.sqrt(data.rate_hz)) if density else fallback


def truly_static_intervals(data: ImuData) -> list[tuple[int, int]]:
    """Static intervals that are static in absolute terms too, or none.

    The moving-variance detector is relative to the first seconds; a recording that never rests (a flight)
    would look static throughout.  Keep only intervals whose gyro scatter is within 5 sigma of the gyro's
    white noise (sensor.yaml), or 0.01 rad/s where the noise is not given.
    """
    try:
        intervals = detect_static_intervals(data.t_s, data.accel_m_s2)
    except ValueError:
        return []
    limit = 5 * _sample_sigma(data, "gyroscope_noise_density", 0.002)
    quiet = [(a, b) for a, b in intervals if np.max(np.std(data.gyro_rad_s[a:b], axis=0)) < limit]
    if not quiet:
        return []
    # a slow, steady rotation is quiet too: its mean rate stands out from the bias the rests share
    bias = np.median([data.gyro_rad_s[a:b].mean(axis=0) for a, b in quiet], axis=0)
    return [(a, b) for a, b in quiet if np.linalg.norm(data.gyro_rad_s[a:b].mean(axis=0) - bias) < limit]


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float | None) -> np.ndarray:
    """Zero-phase 4th-order Butterworth low-pass along time (no filtering when cutoff is None or >= Nyquist)."""
    if not cutoff_hz or cutoff_hz >= 0.5 * rate_hz:
        return x
    return sosfiltfilt(butter(4, cutoff_hz, fs=rate_hz, output="sos"), x, axis=0)


@dataclass
class PairProblem:
    """The graph's inputs extracted from a recording: static pose pairs, dynamic samples, a start dt."""

    static: list
    dynamic: DynamicData | None
    initial_dt_s: float


def problem_from_imus(d0: ImuData, d1: ImuData, lowpass_hz: float | None = 5.0) -> PairProblem:
    """Static pose pairs (means over imu0's truly static intervals) and the moving samples between them."""
    t0 = d0.t_s
    t1 = (d1.t_ns - d0.t_ns[0]) * 1e-9  # imu1 stamps on imu0's time axis, before the offset
    static = []
    moving = np.ones(len(t0), dtype=bool)
    at_rest = []  # imu0's raw gyro while the rig stands still in absolute terms: its bias
    for start, end in truly_static_intervals(d0):
        moving[start:end] = False
        at_rest.append(d0.gyro_rad_s[start:end])
        sel1 = (t1 >= t0[start]) & (t1 < t0[end - 1])
        if sel1.sum() < 3:
            continue
        a0, a1 = d0.accel_m_s2[start:end], d1.accel_m_s2[sel1]
        sigma = np.sqrt(a0.var(axis=0) / len(a0) + a1.var(axis=0) / len(a1))
        static.append(StaticPair(a0.mean(axis=0), a1.mean(axis=0), sigma, len(a0), len(a1)))
    inside = (t0 > t1[0] + 0.5) & (t0 < t1[-1] - 0.5)  # room for any clock offset up to 0.5 s
    rate = d0.rate_hz
    # Zero-phase low-pass on both IMUs: the relation w0 = R w1(t - dt) is linear and time-invariant, so it
    # survives identical filtering, while vibration that differs between mounting points does not pass.
    g0, a0 = lowpass(d0.gyro_rad_s, rate, lowpass_hz), lowpass(d0.accel_m_s2, rate, lowpass_hz)
    g1, a1 = lowpass(d1.gyro_rad_s, d1.rate_hz, lowpass_hz), lowpass(d1.accel_m_s2, d1.rate_hz, lowpass_hz)
    # Nyquist spacing of the filtered band keeps the kept samples ~uncorrelated, so per-sample sigmas hold
    step = max(1, round(rate / (2 * lowpass_hz))) if lowpass_hz else 1
    idx = np.flatnonzero(moving & inside)
    if len(idx) < max(50, 10 * step):  # under half a second of motion: nothing to learn from it
        return PairProblem(static, None, 0.0)
    idx = idx[::step]
    w_dot = savgol_filter(g0, 2 * int(0.05 * rate) + 3, 3, deriv=1, delta=1.0 / rate, axis=0)
    dynamic = DynamicData(
        t0[idx], g0[idx], a0[idx], w_dot[idx], fimu.Signal(t1, g1), fimu.Signal(t1, a1),
        gyro_sigma=np.hypot(_sample_sigma(d0, "gyroscope_noise_density", 0.01),
                            _sample_sigma(d1, "gyroscope_noise_density", 0.01)),
        accel_sigma=np.hypot(_sample_sigma(d0, "accelerometer_noise_density", 0.05),
                             _sample_sigma(d1, "accelerometer_noise_density", 0.05)),
        gyro_bias0=np.concatenate(at_rest).mean(axis=0) if at_rest else np.zeros(3))
    return PairProblem(static, dynamic, coarse_time_offset(t0, g0, t1, g1))

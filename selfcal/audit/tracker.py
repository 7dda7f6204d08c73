"""The laser-tracker target (``--system tracker``) for the audit.

Base model (``smoother``): the batch smoother of :mod:`selfcal.graphs.tracker` over the factors its gated
online pass accepted (IMU preintegration, tracker position and velocity, inclinometer, beam camera), with the
sensor.yaml geometry taken as exact.  The tracker and inclinometer factors are rebuilt with the calibration
effects of the catalog (:func:`selfcal.factors.tracker.calibrated_prism_factor`,
:func:`selfcal.factors.tracker.calibrated_inclinometer_factor`):

* ``lever_arm_prism``: the prism is not where sensor.yaml says (``r + dr``),
* ``tracker_time_offset``: the tracker stamps its samples ``dt`` late (``t_tracker = t_imu + dt``),
* ``incl_bias``: constant roll and pitch offsets of the inclinometer,
* ``incl_scale``: the inclinometer reads ``(1 + s)`` times the tilt,
* ``incl_accel_sensitivity``: the reading departs from gravity by ``(1 + k)`` times the tilt the
  non-gravitational acceleration gives the specific force (``k = 0``: a perfect specific-force sensor).

The inclinometer's vibration term.  The base model predicts the reading as ``tilt_g + w a``: ``a`` is the tilt
the accelerometer's mean specific force over the inclinometer's averaging window shows relative to the fit's
attitude, corrected by the fit's accelerometer bias (both states of the factor, so ``a`` follows them as a fit
moves them), ``w = v_acc / (v_acc + v_a)`` its Wiener weight (``v_acc``: the vibration variance the
accelerometer shows around the sample with the target's own rotation over the window taken out, ``v_a``: the
accelerometer noise's; only where ``v_acc >= 10 v_a``, else 0) and the sigma the conditional ``sigma^2 + v_d -
w v_acc`` (``v_d``: the variance the online pass gave the sample, which counts the rotation as vibration: a
steered run's readings keep that margin).  So ``E[reading | accelerometer]`` is
modelled, and ``incl_accel_sensitivity`` is the regression of what is left on ``w a``.  The reading (and
the accelerometer's mean) is the specific force averaged over the inclinometer's window, so its gravity part is
the attitude half a window before the stamp: both are turned to the keyframe with the base fit's body rate.

The clock offset.  A tracker stamping ``dt`` late shows the prism ``dt`` earlier: ``p - dt v`` per sample of a
block, ``v - dt a`` in the velocity factor.  The regressors are the state velocity interpolated between the
keyframes around the samples and ``a = (V_k - V_k-1) / span`` (:meth:`TrackerAudit._interpolation`), not the
tracker's own noisy velocity nor the online pass's filter; the offset is measured against the IMU (with ``dt``
free, states on time with a late tracker and late states with ``dt = 0`` fit the tracker alike).

Residual families: ``tracker0/position`` (m, per keyframe), ``incl0/tilt`` (rad, roll and pitch), ``cam0/
bearing`` (rad).  Folds split the run in two halves of keyframes; the held-out half is solved with the
effects' constants of the other half held fixed (a half's first keyframe keeps no tracker factors: no velocity
variable before it to move or interpolate its samples with).  Residuals correlated in time are reported to
the engine (:meth:`TrackerAudit.residual_correlation`), measured on the model with every open candidate in.

Score tests are done on the profiled problem.  The engine's :func:`~selfcal.audit.engine.score_test` is dense
(``lstsq`` and ranks of the whole Jacobian): a 30 s run has ~4500 state columns.  :meth:`TrackerAudit.extend`
therefore solves the linearised graph with and without the candidate sparsely (GTSAM's elimination), which
profiles the states out exactly, and hands the engine a graph of the candidate's variables alone with the
same residual sums and degrees of freedom: the same F statistic at a fraction of the cost.

Generic terms (:mod:`selfcal.audit.terms`, effect ``unlisted``): corrections applied to the measurement inside
its factor, ``e += G c``: on ``tracker0/position`` a distance error ``k phi(x)`` along each sample's line of sight
from ``tracker_W`` (m), on ``incl0/tilt`` a reading error ``k phi(x)`` in roll and pitch (rad).  Drivers: time,
range, azimuth, elevation, roll, pitch, yaw, speed, vibration (:meth:`TrackerAudit._driver_values`) and the
recording's auxiliary columns, the state ones from the fit with the catalog effects named so far
(:meth:`TrackerAudit.term_coordinates`).  The library is scored in information form (``information_form``,
:meth:`TrackerAudit.extend_all`): one linearisation and one factorisation of the base normal equations per
search step for every term at once.

Observability (what a run can show): the inclinometer's roll bias trades against the accelerometer's y bias
(both body-fixed), so only the camera's beam elevation pins the pitch and the accelerometer bias prior the
roll; the prism lever arm shows through the beam camera (its height against the inclinometer's pitch) and,
weakly, through rotation; the clock offset needs the target to move (steering: cm at seconds); the
inclinometer scale needs the tilt to change.  Each effect carries a weak prior (``PRIOR_SIGMA``) so an
unobservable direction comes out with its prior's sigma instead of a singular system.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy import signal

from selfcal.core import inertial, so3
from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.factors import tracker as ft
from selfcal.core.stats import correlation_inflation
from selfcal.core.solve import DegenerateDataError, joint_covariance, marginal_covariances
from selfcal.graphs.tracker import TrackerEstimator, gauss_newton
from selfcal.models import tracker as mt

log = logging.getLogger(__name__)

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B


# The online pass starts from a pose prior built with sensor.yaml's lever arm and the inclinometer's first reading
# (1 cm, 2 mrad): kept in the audit it pins the very quantities two catalog effects change, and a 3 cm prism height
# error paid (3 / 1)^2 = 9 in it against its look-alike, the inclinometer pitch bias (noise-free data: 9.7 vs 0.6;
# the lever arm then lost to the bias on most seeds).  The tracker measures the position and gravity, the
# inclinometer and the beam camera the attitude, so the audit keeps only a gauge prior, far wider than both.
GAUGE_PRIOR_SIGMAS = np.array([0.1, 0.1, 0.1, 1.0, 1.0, 1.0])  # rotation (rad), position (m)


def _gauge_prior(prior: gtsam.PriorFactorPose3) -> gtsam.PriorFactorPose3:
    return gtsam.PriorFactorPose3(prior.keys()[0], prior.prior(), gtsam.noiseModel.Diagonal.Sigmas(GAUGE_PRIOR_SIGMAS))


@dataclass(frozen=True)
class _Effect:
    key: int
    dim: int
    prior_sigma: float
    sensor: str
    target: str
    coordinate: str
    meaning: str


EFFECTS = {
    "lever_arm_prism": _Effect(gtsam.symbol("L", 0), 3, 0.2, "tracker0", "position", "attitude",
                               "the prism is displaced from the lever arm in sensor.yaml: r_P_B + dr"),
    "tracker_time_offset": _Effect(gtsam.symbol("O", 0), 1, 0.1, "tracker0", "position", "speed",
                                   "the tracker stamps its samples late: t_tracker = t_imu + dt_s"),
    "incl_bias": _Effect(gtsam.symbol("D", 0), 2, 0.01, "incl0", "tilt", "time",
                         "constant roll and pitch offsets of the inclinometer"),
    "incl_scale": _Effect(gtsam.symbol("S", 0), 1, 0.1, "incl0", "tilt", "tilt",
                          "the inclinometer reads (1 + scale) times the tilt"),
    "incl_accel_sensitivity": _Effect(gtsam.symbol("A", 0), 1, 1.0, "incl0", "tilt", "vibration",
                                      "the reading departs from gravity by (1 + k) times the tilt the "
                                      "non-gravitational acceleration gives the specific force"),
}
SPEED_SMOOTHING_S = 1.0  # the speed driver's smoother (see TrackerAudit._driver_values)
STRONG_VIBRATION = 10.0  # v_d / v_a above which the accelerometer's disturbance enters the prediction
PRIOR_SIGMA = {name: e.prior_sigma for name, e in EFFECTS.items()}


@dataclass(frozen=True)
class _TermTarget:
    """A residual family the generic terms act in: how many components a term's coefficient has, its unit, the
    symbol of its term variables and the weak prior on them (per unit of the scaled driver u in [-1, 1])."""

    dim: int
    unit: str
    symbol: str
    prior_sigma: float


# the tracker's distance error along each sample's line of sight (1 component, m); the inclinometer's reading error
# in roll and pitch (2 components, rad).  The camera's bearing takes no terms (its residual reports what remains)
TERM_TARGETS = {("tracker0", "position"): _TermTarget(1, "m", "u", 1.0),
                ("incl0", "tilt"): _TermTarget(2, "rad", "w", 0.1)}
DRIVER_UNITS = {"time": "s", "range": "m", "azimuth": "rad", "elevation": "rad", "roll": "rad", "pitch": "rad",
                "yaw": "rad", "speed": "m/s", "vibration": "rad"}
ANGLE_DRIVERS = ("azimuth", "elevation", "roll", "pitch", "yaw")


def _index(key: int) -> int:
    return int(gtsam.Symbol(key).index())


class TrackerAudit:
    """The tracker family of the audit (AuditSystem protocol of :mod:`selfcal.audit.engine`)."""

    name = "tracker"
    base_model = "smoother"
    base_effects: tuple = ()
    folds = 2
    # ~15 state columns per keyframe (thousands in a run): the library's score tests from one factorisation of the
    # normal equations (every candidate's columns at once); the states have the IMU chain and the tracker, the
    # biases and effects priors, so the base information is full rank
    information_form = True

    def __init__(self, estimator: TrackerEstimator, channels: dict | None = None):
        """``channels``: the recording's auxiliary columns, ``name -> (t_ns (N,), values (N,), unit)``, offered
        to the generic term library as drivers (interpolated to each residual's time)."""
        if estimator.graph_log is None:
            raise ValueError("the estimator must run with TrackerOptions(keep_graph=True)")
        e = estimator
        self.noise = e.noise
        self.n_keyframes = len(e.keyframe_t_ns)
        if self.n_keyframes < 20:
            raise DegenerateDataError(f"the tracker audit needs a run of some seconds ({self.n_keyframes} keyframes)")
        t0 = e.keyframe_t_ns[0]
        self.t0_ns = t0
        self.t_s = (np.asarray(e.keyframe_t_ns) - t0) * 1e-9
        kept = [entry for entry in e.graph_log if not entry[3]]
        graph = gtsam.NonlinearFactorGraph()
        for entry in kept:
            graph.add(entry[0])
        # the base model's states: the batch smoother with the factors as the online pass accepted them
        base = gauss_newton(graph, e.initial_values)
        self.base_values = base
        self.other: list[tuple[object, int, int]] = []  # (factor, lowest keyframe, highest keyframe)
        self.cam: list[tuple[object, int]] = []
        self.tracker: list[dict] = []
        self.velocity: list[dict] = []
        self.incl: list[dict] = []
        n = self.noise
        n_avg = max(1, int(round(n.incl_average_s * n.imu_rate_hz)))
        v_a = n.accel_noise_density**2 * n.imu_rate_hz / n_avg / n.gravity_m_s2**2  # per axis, rad^2
        for factor, tag, _, _, meta in kept:
            ks = [_index(key) for key in factor.keys()]
            if tag == "tracker0" and meta is not None:
                # one block per keyframe with every sample (moved to the keyframe by the IMU).  The samples were
                # moved with the IMU propagated from the previous keyframe's *filtered* velocity (``v_start``); its
                # error times (t_k - t_i) follows the velocity's change within the block and would read as a
                # clock offset: the factor redoes the move with the previous keyframe's velocity variable.  The
                # offset's regressor is the state velocity interpolated at each sample (see _interpolation)
                k = ks[0]
                v = meta["V"] if meta.get("V") is not None else np.tile(base.atVector(V(k)), (len(meta["Z"]), 1))
                self.tracker.append({"k": k, "z": meta["Z"], "v_W": np.asarray(v, dtype=float), "sigma": meta["sigma"],
                                     "lead_s": (e.keyframe_t_ns[k] - np.asarray(meta["t_ns"])) * 1e-9,
                                     "v_start": meta["v_start"]})
            elif tag in ("incl0", "incl0/provisional") and meta is not None:
                k = ks[0]
                # the inclinometer reads the direction of the specific force averaged over its window, whose
                # gravity part is the attitude half a window before the stamp: the online pass moved the reading
                # from the stamp to the keyframe; the half window is added here (u' = -w x u), else the lag reads
                # as a bias while the target is steered (10 ms at 0.01 rad/s: 1e-4 rad, about the noise; measured:
                # incl_bias p < 0.02 on 12 of 14 null runs of 20 s).  The accelerometer's mean over the same window
                # is turned from its middle to the keyframe likewise
                w_B, h = self._body_rate(k), 0.5 * n.incl_average_s
                lead = (e.keyframe_t_ns[k] - meta["t_ns"]) * 1e-9
                up = meta["up_B"] - h * mt.cross(w_B, meta["up_B"])
                v_d = max(0.5 * float(np.trace(meta["cov"])) - n.incl_sigma_rad**2, 0.0)
                # a burst's onset: a sample the online pass counted quiet whose followers vibrate (``onset``: the
                # inclinometer's own differences after it, the accelerometer after it corroborating); noise only,
                # nothing predicts it.  Not where the online pass counted vibration already: there the differences
                # follow the misfit as well (added there, a 4 mrad error harmonic in yaw read 6.7 +- 0.7 mrad)
                v_onset = meta.get("onset", 0.0) if v_d == 0.0 else 0.0
                # the weight from the vibration alone: the online pass's v_d with the accelerometer's part measured
                # without the target's rotation over the window (``accel_cov``, graphs.tracker.vibration.
                # accel_tilt_covariance; ``own``: the inclinometer's own measure, which the rotation does not
                # touch); only where it dwarfs the accelerometer's noise: an estimated weight (known to ~30 %) in
                # the regressor biases the sensitivity towards 0 - Var(w) / E[w^2]
                v_acc = 0.0 if meta.get("accel_cov") is None else 0.5 * float(np.trace(meta["accel_cov"]))
                v_acc = min(max(v_acc, meta.get("own", 0.0)), v_d)
                w = v_acc / (v_acc + v_a) if v_acc >= STRONG_VIBRATION * v_a else 0.0
                # the disturbance follows the fit's attitude and accelerometer bias (states of the factor): taken
                # once from the base fit, it stayed where an unmodelled effect had pulled them (measured: a
                # 100-sigma inclinometer bias, once named, left a vibration term behind on 3 of 20 runs)
                vibration = (ft.AccelerometerTilt(np.asarray(meta["f_B"], dtype=float),
                                                  np.eye(3) - (lead + h) * so3.hat(w_B), w, B(k))
                             if w > 0.0 else None)
                self.incl.append({"k": k, "t_ns": meta["t_ns"], "z": np.array(inertial.tilt_from_specific_force(up)),
                                  "accelerometer": vibration,
                                  "sigma": float(np.sqrt(n.incl_sigma_rad**2 + max(v_d - w * v_acc, 0.0) + v_onset)),
                                  "vibration": float(np.sqrt(v_d))})
            elif tag == "tracker0/velocity" and meta is not None:
                self.velocity.append({"k": ks[0], **meta})
            elif tag == "cam0":
                self.cam.append((factor, ks[0]))
            elif isinstance(factor, gtsam.PriorFactorPose3):
                self.other.append((_gauge_prior(factor), ks[0], ks[0]))
            else:
                self.other.append((factor, min(ks), max(ks)))
        # the log holds deferred inclinometer factors after later keyframes' ones: time order for the residuals'
        # correlation in time
        self.incl.sort(key=lambda m: m["t_ns"])
        self._interpolation()
        half = self.n_keyframes // 2
        self._parts = {None: (0, self.n_keyframes), 0: (0, half), 1: (half, self.n_keyframes)}
        self._bias_prior_sigmas = np.array([estimator.options.initial_accel_bias_sigma] * 3
                                           + [estimator.options.initial_gyro_bias_sigma] * 3)
        self.channel_units = {name: unit for name, (_, _, unit) in (channels or {}).items()}
        self._channels = channels or {}
        self._driver_values(base)
        self._drivers_from: tuple = ()  # the catalog effects of the fit the drivers were taken from
        self._keys_of = {target: library.TermKeys(t.symbol) for target, t in TERM_TARGETS.items()}
        self._inflations: dict = {}  # residual_correlation per model

    # --- the generic term library ----------------------------------------------------------------------------

    def _driver_values(self, base: gtsam.Values) -> None:
        """Every driver at every residual row, from the states ``base`` (a whole-run fit): ``m['drivers']`` per
        tracker block (arrays over its samples) and per inclinometer sample (arrays of one), and the tracker
        samples' line-of-sight unit vectors ``m['los']``.

        Range, azimuth and elevation are those of the fit's prism at the keyframe seen from the tracker
        (``tracker_W``); roll, pitch and yaw the fit's attitude there (yaw unwrapped over the run; for the
        inclinometer's rows roll and pitch are its readings); speed the fit's velocity's, smoothed over
        ``SPEED_SMOOTHING_S``; vibration the
        disturbance's standard deviation the online pass measured (rad, interpolated in time to tracker samples);
        time that of each sample; the recording's auxiliary channels at the rows' times.
        """
        n, channels = self.noise, self._channels
        ypr = np.array([base.atPose3(X(k)).rotation().ypr() for k in range(self.n_keyframes)])
        attitude = {"roll": ypr[:, 2], "pitch": ypr[:, 1], "yaw": np.unwrap(ypr[:, 0])}
        t_incl = np.array([(m["t_ns"] - self.t0_ns) * 1e-9 for m in self.incl])
        vibration = np.array([m["vibration"] for m in self.incl])

        def sight(p_W):
            d = np.atleast_2d(p_W) - n.tracker_W
            r = np.linalg.norm(d, axis=1)
            return d / r[:, None], {"range": r, "azimuth": np.arctan2(d[:, 1], d[:, 0]),
                                    "elevation": np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))}

        def aux(t_s):
            return {name: np.interp(t_s, (np.asarray(t_ns) - self.t0_ns) * 1e-9, np.asarray(v, dtype=float))
                    for name, (t_ns, v, _) in channels.items()}

        # speed from the fit's velocity smoothed over ~1 s (quadratic Savitzky-Golay): a keyframe's own velocity
        # carries the noise of its block's samples (~1 mm/s), the same noise as its position residuals, and where
        # the target barely moves that noise is the speed (measured: a distance term of 0.14 m per m/s in speed
        # at p = 4e-8 on the yawed null 2008); steering at >= 4 s periods passes the smoother unchanged (< 1 %)
        v_k = np.array([base.atVector(V(k)) for k in range(self.n_keyframes)])
        window = 2 * int(round(0.5 * SPEED_SMOOTHING_S / max(np.median(np.diff(self.t_s)), 1e-3))) + 1
        self._speed_noise = 0.0
        if self.n_keyframes >= window > 3:
            smoothed = signal.savgol_filter(v_k, window, 2, axis=0, mode="interp")
            # one keyframe's velocity noise (rms over the axes) from what the smoother takes out: a fraction
            # 1 - c0 of its variance (c0: the smoother's centre weight); a target that moves less than a few
            # times this is at rest, and its speed is that noise (terms.Coordinate.noise)
            c0 = signal.savgol_coeffs(window, 2)[window // 2]
            self._speed_noise = float(np.sqrt(np.mean((v_k - smoothed) ** 2) * 3 / (1 - c0)))
            v_k = smoothed
        speed_k = np.linalg.norm(v_k, axis=1)

        def at_keyframe(k, count):
            pose = base.atPose3(X(k))
            los, geometry = sight(pose.translation() + pose.rotation().matrix() @ n.r_P_B)
            return np.tile(los, (count, 1)), {**{g: np.full(count, v[0]) for g, v in geometry.items()},
                                              **{a: np.full(count, v[k]) for a, v in attitude.items()},
                                              "speed": np.full(count, speed_k[k])}

        # the geometry is the base fit's prism at the keyframe the samples were moved to, not the measured samples:
        # a driver holding the residual's own noise would regress the noise on itself (measured: a range term
        # "found" at p = 1e-141 on a run without any effect)
        for m in self.tracker:
            k, count = m["k"], len(m["z"])
            t = self.t_s[k] - m["lead_s"]
            m["los"], state = at_keyframe(k, count)
            m["drivers"] = {"time": t, **state,
                            "vibration": np.interp(t, t_incl, vibration) if t_incl.size else np.zeros(count),
                            **aux(t)}
        for m, t in zip(self.incl, t_incl):
            _, state = at_keyframe(m["k"], 1)
            # the inclinometer's roll and pitch drivers are its own readings: a reading error is a function of what
            # it reads (a cross-axis coupling: roll picks up k pitch), while the fit's attitude has already taken
            # part of it (its noise, 1e-4 rad against tilts of 1e-2, does not regress on itself measurably)
            state.update(roll=m["z"][:1], pitch=m["z"][1:])
            m["drivers"] = {"time": np.array([t]), **state, "vibration": np.array([m["vibration"]]),
                            **aux(np.array([t]))}
        full = self._rows(None)
        self._drivers = {target: {name: np.concatenate([m["drivers"][name] for m in rows])
                                  for name in (rows[0]["drivers"] if rows else {})}
                         for target, rows in full.items()}

    def _rows(self, part) -> dict[tuple[str, str], list[dict]]:
        """The blocks of each term target whose factors a fit of ``part`` holds, in its families' row order."""
        lo, hi = self._parts[part]
        return {("tracker0", "position"): [m for m in self.tracker if lo < m["k"] < hi and "fraction" in m],
                ("incl0", "tilt"): [m for m in self.incl if lo <= m["k"] < hi]}

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        """The drivers, taken from the states of the whole-run ``fit`` the library searches on whenever its
        catalog effects differ from those of the fit they were taken from (the base fit's at first).  States an
        unmodelled effect pulled carry its misfit: with a 4 mrad inclinometer offset named, the base fit's speed
        (its velocities had followed the tilted gravity) left a distance term in `speed` beside it (p ~ 1e-9 on
        3 of 20 runs); taken from the fit with the offset, none.  Library terms do not move them: a term's
        columns stay those it was accepted with."""
        if fit is not None and fit.context.get("fold") is None:
            catalog = tuple(sorted(c.key for c in fit.effects if c.term is None))
            if catalog != self._drivers_from:
                self._driver_values(fit.values)
                self._drivers_from = catalog
        def kind(name):
            return ("time" if name == "time" else "angle" if name in ANGLE_DRIVERS
                    else "channel" if name in self.channel_units else "state")
        units = {**DRIVER_UNITS, **self.channel_units}
        noise = {"speed": self._speed_noise}
        return {target: [Coordinate(name, v, units.get(name, ""), kind(name), noise=noise.get(name, 0.0))
                         for name, v in drivers.items()]
                for target, drivers in self._drivers.items()}

    def catalog_term(self, candidate: Candidate) -> None:
        return None  # no catalog effect of the tracker is one correction in one driver (scale, offset, lever arm
        # and sensitivity act through the attitude, the velocity or the disturbance)

    def _term_parts(self, effects, m: dict, target: tuple[str, str], known=None):
        """The generic terms of ``effects`` on one block of ``target``: ``[(key, G)]`` of the fitted ones (error
        ``+= G c``), or with ``known`` (values holding the trained coefficients) their correction, in the error's
        shape.  Tracker: ``G = phi(x_i) u_i`` (the line of sight, one coefficient per basis column); inclinometer:
        ``G = phi(x) I`` (roll and pitch)."""
        dim = TERM_TARGETS[target].dim
        columns, correction = [], np.zeros(np.size(m["z"]))
        for c in effects:
            if c.term is None or (c.sensor, c.target) != target:
                continue
            phi = c.term.columns(m["drivers"])
            for j, key in enumerate(self._keys_of[target](c.term)):
                G = (phi[:, j:j + 1] * m["los"]).reshape(-1, 1) if dim == 1 else phi[0, j] * np.eye(dim)
                if known is None:
                    columns.append((key, G))
                else:
                    correction = correction + G @ known.atVector(key)
        return columns, correction.reshape(np.shape(m["z"]))

    def _term_keys(self, effects) -> list[tuple[int, int, float]]:
        """(key, dimension, prior sigma) of every term variable of ``effects``."""
        out = []
        for c in effects:
            if c.term is not None:
                t = TERM_TARGETS[(c.sensor, c.target)]
                out += [(key, t.dim, t.prior_sigma) for key in self._keys_of[(c.sensor, c.target)](c.term)]
        return out

    def _body_rate(self, k: int) -> np.ndarray:
        """Body rate (rad/s, body frame) over the interval before keyframe ``k`` from the base fit's attitudes
        (the steering; vibration is faster, and the online pass's moves by the gyro already hold it)."""
        if k < 1:
            return np.zeros(3)
        R0, R1 = (self.base_values.atPose3(X(i)).rotation() for i in (k - 1, k))
        return gtsam.Rot3.Logmap(R0.between(R1)) / float(self.t_s[k] - self.t_s[k - 1])

    def _interpolation(self) -> None:
        """What the clock offset's regressors need: the samples' place between two keyframes' velocity variables.

        A tracker stamping ``dt`` late shows the prism ``dt`` earlier, ``p - dt v`` and ``v - dt a``.  The
        regressor ``v`` at each sample is the state velocity interpolated between the keyframe before and this
        one, plus the lever arm's rotation velocity ``R (w x r)`` (``w`` from the base fit's attitudes).  Not the
        tracker's own velocity: its noise (2 mm/s per sample) is as large as the velocity's change within a block
        and attenuates the offset (measured: a 30 ms offset estimated 21 +- 2 ms, 25 ms with the true velocity
        in its place); vibration velocities the interpolation misses are a few mm/s in a burst (~1e-4 m at
        30 ms, against the samples' 0.5 mm noise).

        The velocity factor is rewritten the same way: the samples' mean velocity against the state velocity
        interpolated at their mean time ``(1 - f) V_prev + f V``, with ``a = (V - V_prev) / span``.  The online
        pass moved each velocity sample to the keyframe with the IMU's velocity change over the rest of the
        interval; that IMU noise (~5e-4 m/s, as large as the averaged measurement's) is part of the IMU factor's
        noise as well, and the two together pulled the offset ~10 % low.  Subtracting the linear share of the
        whole interval's change ``(1 - f) dv`` leaves the Brownian bridge of the IMU noise, which is uncorrelated
        with the interval's total (the IMU factor's); its variance joins the factor's sigma, with the gyro's
        noise in ``w x r``.  A constant error of the online pass's bias or attitude cancels in the bridge.
        """
        n = self.noise
        base = self.base_values
        blocks = {}
        for m in self.tracker:
            k = m["k"]
            if k < 1:
                continue
            span = float(self.t_s[k] - self.t_s[k - 1])
            m["fraction"] = np.clip(1.0 - m["lead_s"] / span, 0.0, 1.0)
            R1 = base.atPose3(X(k)).rotation().matrix()
            m["v_rot"] = np.tile(R1 @ mt.cross(self._body_rate(k), n.r_P_B), (len(m["lead_s"]), 1))
            blocks[k] = (m, span)
        for m in self.velocity:
            if m["k"] not in blocks:
                continue
            block, span = blocks[m["k"]]
            tau = block["fraction"] * span  # s after the previous keyframe
            f = float(np.mean(block["fraction"]))
            bridge = n.accel_noise_density**2 * float(np.mean(np.minimum.outer(tau, tau) - np.outer(tau, tau) / span))
            gyro = n.gyro_noise_density**2 * n.imu_rate_hz / len(tau) * 2.0 / 3.0 * float(n.r_P_B @ n.r_P_B)
            m["bridge"] = {"z": m["z"] - (1.0 - f) * np.asarray(m["a_W"]) * span, "fraction": f, "span_s": span,
                           "sigma": float(np.sqrt(m["sigma"]**2 + bridge + gyro))}

    def candidates(self) -> list[Candidate]:
        return [Candidate(name, e.sensor, e.meaning, e.target, e.coordinate) for name, e in EFFECTS.items()]

    def _prism_factor(self, m: dict, noise, lo: int, lever_key, offset_key, lever, offset, effects=(), known=None):
        """The tracker block of keyframe ``m['k']`` with the calibration effects and the generic terms of
        ``effects`` (fitted, or known from ``known``), or None for the first keyframe of a part (its samples lie
        before it: no velocity variable to move or interpolate them with)."""
        k = m["k"]
        if k <= lo or "fraction" not in m:
            return None
        terms, correction = self._term_parts(effects, m, ("tracker0", "position"), known)
        # a known term is a known correction of the measurement: e = pred + G c - z = pred - (z - G c)
        z = m["z"] - correction
        return ft.calibrated_prism_factor(noise, X(k), z, self.noise.r_P_B, m["v_rot"], lever_key, offset_key,
                                          lever, offset, V(k - 1), m["lead_s"], m["v_start"],
                                          velocity_keys=(V(k - 1), V(k)), velocity_fraction=m["fraction"],
                                          term_columns=terms)

    def _incl_factor(self, m: dict, noise, keys: dict, fixed: dict, effects=(), known=None):
        """The inclinometer factor of one sample with the calibration effects and the generic terms of ``effects``
        (fitted, or known from ``known``)."""
        terms, correction = self._term_parts(effects, m, ("incl0", "tilt"), known)
        return ft.calibrated_inclinometer_factor(noise, X(m["k"]), m["z"] - correction, np.zeros(2), keys, fixed,
                                                 term_columns=terms, vibration=m["accelerometer"])

    def _velocity_factor(self, m: dict, lo: int, lever_key, offset_key, lever, offset):
        k = m["k"]
        if k <= lo or "bridge" not in m:
            return None
        b = m["bridge"]
        return ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, b["sigma"]), X(k), V(k),
                                                   b["z"], m["w_B"], self.noise.r_P_B, m["a_W"], offset_key, offset,
                                                   previous_velocity_key=V(k - 1), fraction=b["fraction"],
                                                   span_s=b["span_s"], lever_key=lever_key, lever_fixed=lever)

    # --- graphs ----------------------------------------------------------------------------------------------

    def _build(self, effects, part, fixed: dict | None = None, known=None):
        """Graph and initial values of keyframes [lo, hi) with ``effects`` as variables; ``fixed`` gives constant
        catalog effect values instead and ``known`` (values) the generic terms' (the held-out half)."""
        lo, hi = self._parts[part]
        inside = lambda k: lo <= k < hi  # noqa: E731
        names = {c.effect for c in effects}
        fixed = fixed or {}
        key = {name: (EFFECTS[name].key if name in names and name not in fixed else None) for name in EFFECTS}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for factor, k_min, k_max in self.other:
            if inside(k_min) and inside(k_max):
                graph.add(factor)
        if lo > 0:  # the second half has no prior of its own on the biases (the first keyframe's prior is in half 0)
            graph.add(gtsam.PriorFactorConstantBias(B(lo), self.base_values.atConstantBias(B(lo)),
                                                    gtsam.noiseModel.Diagonal.Sigmas(self._bias_prior_sigmas)))
        for factor, k in self.cam:
            if inside(k):
                graph.add(factor)
        lever = np.asarray(fixed.get("lever_arm_prism", np.zeros(3)), dtype=float)
        offset = float(np.asarray(fixed.get("tracker_time_offset", [0.0])).ravel()[0])
        for m in self.tracker:
            if inside(m["k"]):
                factor = self._prism_factor(m, gtsam.noiseModel.Isotropic.Sigma(m["z"].size, m["sigma"]), lo,
                                            key["lever_arm_prism"], key["tracker_time_offset"], lever, offset,
                                            effects, known)
                if factor is not None:
                    graph.add(factor)
        for m in self.velocity:
            if inside(m["k"]):
                factor = self._velocity_factor(m, lo, key["lever_arm_prism"], key["tracker_time_offset"], lever,
                                               offset)
                if factor is not None:
                    graph.add(factor)
        incl_keys = {"bias": key["incl_bias"], "scale": key["incl_scale"],
                     "accel_sensitivity": key["incl_accel_sensitivity"]}
        incl_fixed = {"bias": fixed.get("incl_bias", np.zeros(2)),
                      "scale": float(np.asarray(fixed.get("incl_scale", [0.0])).ravel()[0]),
                      "accel_sensitivity": float(np.asarray(fixed.get("incl_accel_sensitivity", [0.0])).ravel()[0])}
        for m in self.incl:
            if inside(m["k"]):
                graph.add(self._incl_factor(m, gtsam.noiseModel.Isotropic.Sigma(2, m["sigma"]), incl_keys,
                                            incl_fixed, effects, known))
        for k in range(lo, hi):
            values.insert(X(k), self.base_values.atPose3(X(k)))
            values.insert(V(k), self.base_values.atVector(V(k)))
            values.insert(B(k), self.base_values.atConstantBias(B(k)))
        for name, e in EFFECTS.items():
            if key[name] is not None:
                graph.add(gtsam.PriorFactorVector(e.key, np.zeros(e.dim),
                                                  gtsam.noiseModel.Isotropic.Sigma(e.dim, e.prior_sigma)))
                values.insert(e.key, np.zeros(e.dim))
        if known is None:
            for key, dim, sigma in self._term_keys(effects):
                graph.add(gtsam.PriorFactorVector(key, np.zeros(dim), gtsam.noiseModel.Isotropic.Sigma(dim, sigma)))
                values.insert(key, np.zeros(dim))
        return graph, values

    def fit(self, effects, fold=None) -> Fit:
        graph, values = self._build(effects, fold)
        values = gauss_newton(graph, values)
        return Fit(tuple(effects), graph, values, self._families(graph, values, fold, None, effects), {"fold": fold})

    def extend(self, fit: Fit, candidate: Candidate):
        """(equivalent graph, values, columns) for the engine's score test, with the states profiled out.

        Linearised at the fit (candidate at 0), the residual sums with the candidate (``rss_new``) and without it
        (``rss_old``) come from sparse solves; the returned graph has the candidate's variables only:
        ``[theta - c; r]`` with ``|c|^2 = rss_old - rss_new`` (one direction) and ``|r|^2 = rss_new`` spread over
        ``n_obs - n_params`` rows, so its dense test gives exactly the full problem's F and dof.  A generic term is
        tested on the whole graph (:meth:`extend_all`): the engine's information-form test profiles the states.
        """
        if candidate.term is not None:
            graph, values, groups = self.extend_all(fit, [candidate])
            return graph, values, groups[0]
        graph, _ = self._build(fit.effects + (candidate,), fit.context["fold"])
        e = EFFECTS[candidate.effect]
        start = gtsam.Values(fit.values)
        start.insert(e.key, np.zeros(e.dim))
        linear_new = graph.linearize(start)
        rss_new = 2.0 * linear_new.error(linear_new.optimize())
        linear_old = fit.graph.linearize(fit.values)
        rss_old = 2.0 * linear_old.error(linear_old.optimize())
        n_obs = sum(graph.at(i).dim() for i in range(graph.size()))
        dof = max(n_obs - int(start.dim()), 1)
        c = np.zeros(e.dim)
        c[0] = np.sqrt(max(rss_old - rss_new, 0.0))
        r = np.full(dof, np.sqrt(max(rss_new, 1e-300) / dof))

        def error(this, vals, H):
            theta = vals.atVector(e.key)
            if H is not None:
                H[0] = np.vstack([np.eye(e.dim), np.zeros((dof, e.dim))])
            return np.concatenate([theta - c, r])

        profiled = gtsam.NonlinearFactorGraph()
        profiled.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(e.dim + dof), [e.key], error))
        theta0 = gtsam.Values()
        theta0.insert(e.key, np.zeros(e.dim))
        return profiled, theta0, [(e.key, np.arange(e.dim))]

    def extend_all(self, fit: Fit, candidates):
        """One graph holding every candidate (new variables at zero) linearised at ``fit``: (graph, values, new
        columns each), for the engine's information-form score tests (one factorisation for all of them)."""
        graph, start = self._build(fit.effects + tuple(candidates), fit.context["fold"])
        values = gtsam.Values(fit.values)
        groups = []
        for cand in candidates:
            if cand.term is None:
                keys = [(EFFECTS[cand.effect].key, EFFECTS[cand.effect].dim)]
            else:
                keys = [(key, dim) for key, dim, _ in self._term_keys([cand])]
            for key, dim in keys:
                if not values.exists(key):
                    values.insert(key, start.atVector(key))
            groups.append([(key, np.arange(dim)) for key, dim in keys])
        return graph, values, groups

    def heldout_fit(self, fit: Fit, fold: int) -> Fit:
        """The other half solved with ``fit``'s effect values fixed (generic terms as trained): its whole graph (IMU
        factors included) and its residual families, for the engine's held-out comparison."""
        other = 1 - fold
        fixed = {c.effect: fit.values.atVector(EFFECTS[c.effect].key) for c in fit.effects if c.term is None}
        graph, values = self._build(fit.effects, other, fixed=fixed, known=fit.values)
        values = gauss_newton(graph, values)
        return Fit(tuple(fit.effects), graph, values,
                   self._families(graph, values, other, fixed, fit.effects, fit.values), {"fold": other})

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        return self.heldout_fit(fit, fold).families

    def _families(self, graph, values, part, fixed: dict | None = None, effects=(),
                  known=None) -> list[ResidualFamily]:
        """Residuals of the tracker, inclinometer and camera factors of keyframes in ``part`` at ``values``
        (effects from ``values`` where they are variables, else from ``fixed``; the generic terms of ``effects``
        from ``values``, or from ``known`` where they were trained on the other part)."""
        lo, hi = self._parts[part]
        tr, inc, cam = [], [], []
        fixed = dict(fixed or {})
        for name, e in EFFECTS.items():
            if values.exists(e.key):
                fixed[name] = values.atVector(e.key)
        lever = np.asarray(fixed.get("lever_arm_prism", np.zeros(3)))
        offset = float(np.asarray(fixed.get("tracker_time_offset", [0.0]))[0])
        unit = gtsam.noiseModel.Unit.Create
        for m in self.tracker:
            if lo <= m["k"] < hi:
                f = self._prism_factor(m, unit(m["z"].size), lo, None, None, lever, offset, effects, known)
                if f is None:
                    continue
                e = np.asarray(f.unwhitenedError(values)).reshape(-1, 3)
                for ei, vi in zip(e, m["v_W"]):
                    tr.append((ei, ei / m["sigma"], self.t_s[m["k"]], float(np.linalg.norm(vi))))
        incl_fixed = {"bias": fixed.get("incl_bias", np.zeros(2)),
                      "scale": float(np.asarray(fixed.get("incl_scale", [0.0]))[0]),
                      "accel_sensitivity": float(np.asarray(fixed.get("incl_accel_sensitivity", [0.0]))[0])}
        for m in self.incl:
            if lo <= m["k"] < hi:
                f = self._incl_factor(m, unit(2), {}, incl_fixed, effects, known)
                e = np.asarray(f.unwhitenedError(values))
                inc.append((e, e / m["sigma"], (m["t_ns"] - self.t0_ns) * 1e-9, float(np.linalg.norm(m["z"])),
                            m["vibration"]))
        for factor, k in self.cam:
            if lo <= k < hi:
                e = np.asarray(factor.unwhitenedError(values))
                cam.append((e, np.asarray(factor.noiseModel().whiten(e)), self.t_s[k]))
        families = []
        if tr:
            families.append(ResidualFamily("tracker0", "position", "m", np.array([x[1] for x in tr]),
                                           np.array([x[0] for x in tr]),
                                           {"time_s": np.array([x[2] for x in tr]),
                                            "speed": np.array([x[3] for x in tr])}))
        if inc:
            families.append(ResidualFamily("incl0", "tilt", "rad", np.array([x[1] for x in inc]),
                                           np.array([x[0] for x in inc]),
                                           {"time_s": np.array([x[2] for x in inc]),
                                            "tilt": np.array([x[3] for x in inc]),
                                            "vibration": np.array([x[4] for x in inc])}))
        if cam:
            families.append(ResidualFamily("cam0", "bearing", "rad", np.array([x[1] for x in cam]),
                                           np.array([x[0] for x in cam]), {"time_s": np.array([x[2] for x in cam])}))
        return families

    @staticmethod
    def _inflation(family: ResidualFamily) -> float:
        """Variance inflation ``1 + 2 sum rho_k`` of one family's whitened residuals in time order, lags up to 1 s
        (:func:`selfcal.core.stats.correlation_inflation`; the sum stops at the first non-positive rho)."""
        t = family.coordinates["time_s"]
        order = np.argsort(t, kind="stable")
        per_second = len(t) / max(float(t[order[-1]] - t[order[0]]), 1e-9)
        max_lag = min(max(10, int(round(per_second))), max(len(t) - 1, 1))
        return correlation_inflation([family.whitened[order]], max_lag=max_lag)

    def residual_correlation(self, fit: Fit) -> float:
        """The engine's hook: residuals correlated in time (vibration bursts seen by the tracker and the camera,
        the inclinometer's own averaging and its vibration model's misses, errors of the IMU interpolation within
        a keyframe) hold fewer independent samples than rows, and the F test must use the effective sizes.

        The correlation is that of the noise, measured on the residuals of the model with every open candidate
        in (the unrestricted model, as in HAC-robust tests): an effect not yet modelled leaves its own smooth
        signature in ``fit``'s residuals (a 3 cm lever-arm error: inflation ~17 from the camera's residuals,
        which follow the steering) and would pass for correlated noise, dividing every candidate's evidence
        by it.  Under the null hypothesis the two residual sets coincide.  The engine applies one inflation to
        every candidate: the largest of the families', so no candidate's evidence is overstated."""
        everything = tuple(fit.effects) + tuple(c for c in self.candidates() if c not in fit.effects)
        if len(everything) == len(fit.effects):
            return max((self._inflation(family) for family in fit.families), default=1.0)
        # the engine asks once per candidate of a step, always about the same model: a fit is deterministic in its
        # effects and fold, so the refit is done once per model
        key = (tuple(c.key for c in everything), fit.context["fold"])
        if key not in self._inflations:
            full = self.fit(everything, fit.context["fold"])
            self._inflations[key] = max((self._inflation(family) for family in full.families), default=1.0)
        return self._inflations[key]

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """Value and 1-sigma: marginal covariance scaled by the fit's variance factor and by the time
        correlation of its target family's residuals (fewer independent samples than factors).  A generic term's
        in the driver's own units (:func:`selfcal.audit.terms.describe`): the tracker's in m along the line of
        sight, the inclinometer's in rad for roll and pitch."""
        if candidate.term is not None:
            target = (candidate.sensor, candidate.target)
            keys = self._keys_of[target](candidate.term)
            family = fit.family(candidate.target, candidate.sensor)
            inflation = self._inflation(family) if family is not None else 1.0
            joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * (
                variance_factor(fit) * inflation)
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                             self._drivers[target], TERM_TARGETS[target].unit,
                                             {**DRIVER_UNITS, **self.channel_units}.get(candidate.term.driver, ""))
            estimate["target"] = f"{candidate.sensor}/{candidate.target}"
            if target == ("tracker0", "position"):
                estimate["direction"] = "line of sight (positive: the tracker reads the distance long)"
            else:
                estimate["axes"] = ["roll", "pitch"]
            return estimate, std
        e = EFFECTS[candidate.effect]
        cov = marginal_covariances(fit.graph, fit.values, [e.key], candidate.effect)[e.key]
        target = fit.family(e.target, e.sensor)
        inflation = self._inflation(target) if target is not None else 1.0
        sigma = np.sqrt(np.diag(cov) * variance_factor(fit) * inflation)
        value = fit.values.atVector(e.key)
        if candidate.effect == "lever_arm_prism":
            return {"r_m": (self.noise.r_P_B + value).tolist()}, {"r_m": sigma.tolist()}
        if candidate.effect == "tracker_time_offset":
            return {"dt_s": float(value[0])}, {"dt_s": float(sigma[0])}
        if candidate.effect == "incl_bias":
            return {"bias": value.tolist(), "axes": ["roll", "pitch"]}, {"bias": sigma.tolist()}
        if candidate.effect == "incl_scale":
            return {"scale": float(value[0])}, {"scale": float(sigma[0])}
        return {"sensitivity": float(value[0])}, {"sensitivity": float(sigma[0])}

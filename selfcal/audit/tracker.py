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
the accelerometer's mean specific force over the inclinometer's averaging window shows relative to the base
fit's attitude (bias-corrected), ``w = v_d / (v_d + v_a)`` its Wiener weight (``v_d``: the vibration variance
the online pass measured for that sample, ``v_a``: the accelerometer noise's; only where ``v_d >= 10 v_a``,
else 0) and the sigma the conditional ``sigma^2 + (1 - w) v_d``.  So ``E[reading | accelerometer]`` is
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

from selfcal.core import inertial
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.factors import tracker as ft
from selfcal.core.stats import correlation_inflation
from selfcal.core.solve import DegenerateDataError, marginal_covariances
from selfcal.graphs.tracker import TrackerEstimator, gauss_newton
from selfcal.models import tracker as mt

log = logging.getLogger(__name__)

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B


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
STRONG_VIBRATION = 10.0  # v_d / v_a above which the accelerometer's disturbance enters the prediction
PRIOR_SIGMA = {name: e.prior_sigma for name, e in EFFECTS.items()}


def _index(key: int) -> int:
    return int(gtsam.Symbol(key).index())


class TrackerAudit:
    """The tracker family of the audit (AuditSystem protocol of :mod:`selfcal.audit.engine`)."""

    name = "tracker"
    base_model = "smoother"
    base_effects: tuple = ()
    folds = 2

    def __init__(self, estimator: TrackerEstimator):
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
                R = base.atPose3(X(k)).rotation().matrix()
                # the inclinometer reads the direction of the specific force averaged over its window, whose
                # gravity part is the attitude half a window before the stamp: the online pass moved the reading
                # from the stamp to the keyframe; the half window is added here (u' = -w x u), else the lag reads
                # as a bias while the target is steered (10 ms at 0.01 rad/s: 1e-4 rad, about the noise; measured:
                # incl_bias p < 0.02 on 12 of 14 null runs of 20 s).  The accelerometer's mean over the same window
                # is turned from its middle to the keyframe likewise
                w_B, h = self._body_rate(k), 0.5 * n.incl_average_s
                lead = (e.keyframe_t_ns[k] - meta["t_ns"]) * 1e-9
                up = meta["up_B"] - h * mt.cross(w_B, meta["up_B"])
                f = meta["f_B"] - base.atConstantBias(B(k)).accelerometer()
                f = f - (lead + h) * mt.cross(w_B, f)
                a = np.array(inertial.tilt_from_specific_force(f)) - mt.tilt_of_rotation(R)
                v_d = max(0.5 * float(np.trace(meta["cov"])) - n.incl_sigma_rad**2, 0.0)
                # the Wiener weight only where the vibration dwarfs the accelerometer's noise: an estimated weight
                # (v_d known to ~30 %) in the regressor biases the sensitivity towards 0 - Var(w) / E[w^2]
                w = v_d / (v_d + v_a) if v_d >= STRONG_VIBRATION * v_a else 0.0
                self.incl.append({"k": k, "t_ns": meta["t_ns"], "z": np.array(inertial.tilt_from_specific_force(up)),
                                  "d": w * a, "sigma": float(np.sqrt(n.incl_sigma_rad**2 + (1 - w) * v_d)),
                                  "vibration": float(np.sqrt(v_d))})
            elif tag == "tracker0/velocity" and meta is not None:
                self.velocity.append({"k": ks[0], **meta})
            elif tag == "cam0":
                self.cam.append((factor, ks[0]))
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

    def _prism_factor(self, m: dict, noise, lo: int, lever_key, offset_key, lever, offset):
        """The tracker block of keyframe ``m['k']`` with the calibration effects, or None for the first keyframe
        of a part (its samples lie before it: no velocity variable to move or interpolate them with)."""
        k = m["k"]
        if k <= lo or "fraction" not in m:
            return None
        return ft.calibrated_prism_factor(noise, X(k), m["z"], self.noise.r_P_B, m["v_rot"], lever_key, offset_key,
                                          lever, offset, V(k - 1), m["lead_s"], m["v_start"],
                                          velocity_keys=(V(k - 1), V(k)), velocity_fraction=m["fraction"])

    def _velocity_factor(self, m: dict, lo: int, offset_key, offset):
        k = m["k"]
        if k <= lo or "bridge" not in m:
            return None
        b = m["bridge"]
        return ft.calibrated_prism_velocity_factor(gtsam.noiseModel.Isotropic.Sigma(3, b["sigma"]), X(k), V(k),
                                                   b["z"], m["w_B"], self.noise.r_P_B, m["a_W"], offset_key, offset,
                                                   previous_velocity_key=V(k - 1), fraction=b["fraction"],
                                                   span_s=b["span_s"])

    # --- graphs ----------------------------------------------------------------------------------------------

    def _build(self, effects, part, fixed: dict | None = None):
        """Graph and initial values of keyframes [lo, hi) with ``effects`` as variables; ``fixed`` gives constant
        effect values instead (the held-out half)."""
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
                                            key["lever_arm_prism"], key["tracker_time_offset"], lever, offset)
                if factor is not None:
                    graph.add(factor)
        for m in self.velocity:
            if inside(m["k"]):
                factor = self._velocity_factor(m, lo, key["tracker_time_offset"], offset)
                if factor is not None:
                    graph.add(factor)
        incl_keys = {"bias": key["incl_bias"], "scale": key["incl_scale"],
                     "accel_sensitivity": key["incl_accel_sensitivity"]}
        incl_fixed = {"bias": fixed.get("incl_bias", np.zeros(2)),
                      "scale": float(np.asarray(fixed.get("incl_scale", [0.0])).ravel()[0]),
                      "accel_sensitivity": float(np.asarray(fixed.get("incl_accel_sensitivity", [0.0])).ravel()[0])}
        for m in self.incl:
            if inside(m["k"]):
                graph.add(ft.calibrated_inclinometer_factor(gtsam.noiseModel.Isotropic.Sigma(2, m["sigma"]),
                                                            X(m["k"]), m["z"], m["d"], incl_keys, incl_fixed))
        for k in range(lo, hi):
            values.insert(X(k), self.base_values.atPose3(X(k)))
            values.insert(V(k), self.base_values.atVector(V(k)))
            values.insert(B(k), self.base_values.atConstantBias(B(k)))
        for name, e in EFFECTS.items():
            if key[name] is not None:
                graph.add(gtsam.PriorFactorVector(e.key, np.zeros(e.dim),
                                                  gtsam.noiseModel.Isotropic.Sigma(e.dim, e.prior_sigma)))
                values.insert(e.key, np.zeros(e.dim))
        return graph, values

    def fit(self, effects, fold=None) -> Fit:
        graph, values = self._build(effects, fold)
        values = gauss_newton(graph, values)
        return Fit(tuple(effects), graph, values, self._families(graph, values, fold), {"fold": fold})

    def extend(self, fit: Fit, candidate: Candidate):
        """(equivalent graph, values, columns) for the engine's score test, with the states profiled out.

        Linearised at the fit (candidate at 0), the residual sums with the candidate (``rss_new``) and without it
        (``rss_old``) come from sparse solves; the returned graph has the candidate's variables only:
        ``[theta - c; r]`` with ``|c|^2 = rss_old - rss_new`` (one direction) and ``|r|^2 = rss_new`` spread over
        ``n_obs - n_params`` rows, so its dense test gives exactly the full problem's F and dof.
        """
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

    def heldout_fit(self, fit: Fit, fold: int) -> Fit:
        """The other half solved with ``fit``'s effect values fixed: its whole graph (IMU factors included) and
        its residual families, for the engine's held-out comparison."""
        other = 1 - fold
        fixed = {c.effect: fit.values.atVector(EFFECTS[c.effect].key) for c in fit.effects}
        graph, values = self._build((), other, fixed=fixed)
        values = gauss_newton(graph, values)
        return Fit(tuple(fit.effects), graph, values, self._families(graph, values, other, fixed), {"fold": other})

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        return self.heldout_fit(fit, fold).families

    def _families(self, graph, values, part, fixed: dict | None = None) -> list[ResidualFamily]:
        """Residuals of the tracker, inclinometer and camera factors of keyframes in ``part`` at ``values``
        (effects from ``values`` where they are variables, else from ``fixed``)."""
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
                f = self._prism_factor(m, unit(m["z"].size), lo, None, None, lever, offset)
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
                f = ft.calibrated_inclinometer_factor(unit(2), X(m["k"]), m["z"], m["d"], {}, incl_fixed)
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
        full = self.fit(everything, fit.context["fold"]) if len(everything) > len(fit.effects) else fit
        return max((self._inflation(family) for family in full.families), default=1.0)

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """Value and 1-sigma: marginal covariance scaled by the fit's variance factor and by the time
        correlation of its target family's residuals (fewer independent samples than factors)."""
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

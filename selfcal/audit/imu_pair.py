"""The two-IMU system (``--system imu-pair``) for the audit.

Base model (``rotation``): the patent's relation ``v0 = R v1`` for static and moving samples, with constant
relative accelerometer and gyro offsets.  Catalog: ``time_offset`` (t_imu0 = t_imu1 + dt: shows as a gyro
residual proportional to angular acceleration) and ``lever_arm`` (imu1 displaced by r: shows as an
accelerometer residual ``[w_dot]x r + [w]x^2 r``, growing with rotation rate).

Residual families: ``pair_gyro`` (rad s^-1) and ``pair_accel`` (m s^-2) per moving sample, ``pair_static``
(m s^-2) per static pose; coordinates: time, |w|, |w_dot| of imu0.  Folds split the recording in two halves.
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from selfcal.core import stats
from selfcal.core import inertial
from selfcal.audit.engine import Candidate, Fit, ResidualFamily
from selfcal.factors import imu as fimu
from selfcal.graphs import imu_pair as gp
from selfcal.core.solve import marginal_covariances, optimize
from selfcal.io.recording import ImuData

MEANINGS = {"time_offset": "the clocks of the two IMUs are offset: t_imu0 = t_imu1 + dt",
            "lever_arm": "imu1 is displaced from imu0: rotation adds centripetal and tangential acceleration",
            "accel_relative_gain": "imu1's accelerometer scale / non-orthogonality differs from imu0's",
            "gyro_relative_gain": "imu1's gyro scale / non-orthogonality differs from imu0's"}
KEYS = {"time_offset": (gp.TIME_OFFSET, 1), "lever_arm": (gp.LEVER_ARM, 3),
        "accel_relative_gain": (gp.ACCEL_GAIN, 6), "gyro_relative_gain": (gp.GYRO_GAIN, 6)}


def pair_parameters(values: gtsam.Values, model: gp.PairModel):
    """(R, dt, r, accel offset, gyro offset, accel gain I + S, gyro gain I + S), nominal where not in the model."""
    return (values.atRot3(gp.ROTATION).matrix(),
            values.atVector(gp.TIME_OFFSET)[0] if model.time_offset else 0.0,
            values.atVector(gp.LEVER_ARM) if model.lever_arm else np.zeros(3),
            values.atVector(gp.ACCEL_OFFSET) if values.exists(gp.ACCEL_OFFSET) else np.zeros(3),
            values.atVector(gp.GYRO_OFFSET) if values.exists(gp.GYRO_OFFSET) else np.zeros(3),
            fimu.symmetric_gain(values.atVector(gp.ACCEL_GAIN)) if model.accel_gain else np.eye(3),
            fimu.symmetric_gain(values.atVector(gp.GYRO_GAIN)) if model.gyro_gain else np.eye(3))


class ImuPairAudit:
    name = "imu-pair"
    folds = 2
    base_model = "rotation"

    @property
    def diagnostics(self) -> dict:
        return {"cross_correlation_lag_s": {
            "value": self.initial_dt_s,
            "meaning": "delay maximising the correlation of |w| of the two IMUs (rotation-invariant): the "
                       "model-free estimate of t_imu0 - t_imu1, to compare with a time_offset finding"}}

    def simulate(self, fit: Fit, seed: int, noise_fit: Fit | None = None) -> ImuPairAudit:
        """The recording's scenario re-simulated with ``fit``'s model (:func:`simulate_pair_like`).  The pair has
        no independent noise level: pass the final fit as ``noise_fit``, its residual is the best estimate."""
        return simulate_pair_like(self, fit, seed, noise_fit)

    def __init__(self, d0: ImuData, d1: ImuData, lowpass_hz: float | None = 5.0):
        self.imu0, self.imu1 = d0.name, d1.name
        problem = gp.problem_from_imus(d0, d1, lowpass_hz)
        if problem.dynamic is None:
            raise gp.DegenerateDataError(f"{d0.name}/{d1.name}: the imu-pair audit needs motion (none found)")
        self.static, self.dynamic, self.initial_dt_s = problem.static, problem.dynamic, problem.initial_dt_s
        self.base_effects = ()
        half = 0.5 * (self.dynamic.t0_s[0] + self.dynamic.t0_s[-1])
        self._halves = [self.dynamic.t0_s < half, self.dynamic.t0_s >= half]
        self.scale = {g: 1.0 for g in gp.GROUPS}
        # per-group noise level from the residuals of the richest model (every catalog effect in), kept for every
        # later fit: the base fit's residuals would still hold the unmodelled effects and down-weight the very
        # group that shows them (as Mallows' Cp takes sigma from the full model)
        full = self.fit(tuple(self.candidates()))
        self.scale = {fam.quantity.removeprefix("pair_"): max(float(np.sqrt(np.mean(fam.whitened**2))), 1e-6)
                      for fam in full.families}
        for g in gp.GROUPS:
            self.scale.setdefault(g, 1.0)

    def candidates(self) -> list[Candidate]:
        return [Candidate("time_offset", self.imu1, MEANINGS["time_offset"], "pair_gyro", "angular acceleration"),
                Candidate("lever_arm", self.imu1, MEANINGS["lever_arm"], "pair_accel", "angular rate"),
                Candidate("accel_relative_gain", self.imu1, MEANINGS["accel_relative_gain"], "pair_accel",
                          "specific force"),
                Candidate("gyro_relative_gain", self.imu1, MEANINGS["gyro_relative_gain"], "pair_gyro",
                          "angular rate")]

    def _model(self, effects) -> gp.PairModel:
        names = {c.effect for c in effects}
        return gp.PairModel(time_offset="time_offset" in names, lever_arm="lever_arm" in names,
                            accel_gain="accel_relative_gain" in names, gyro_gain="gyro_relative_gain" in names)

    def _data(self, part):
        """Static pairs and dynamic samples of all data (None) or of one half."""
        if part is None:
            return self.static, self.dynamic
        mask = self._halves[part]
        d = self.dynamic
        dynamic = replace(d, t0_s=d.t0_s[mask], gyro0=d.gyro0[mask], accel0=d.accel0[mask],
                          gyro_rate_dot0=d.gyro_rate_dot0[mask])
        n = len(self.static)
        static = self.static[:n // 2] if part == 0 else self.static[n // 2:]
        return static, dynamic

    def fit(self, effects, fold=None) -> Fit:
        model = self._model(effects)
        static, dynamic = self._data(fold)
        graph, _ = gp._build(static, dynamic, model, self.scale, huber_k=None)
        vectors0 = [p.accel0 for p in static] + list(dynamic.gyro0)
        vectors1 = [p.accel1 for p in static] + list(dynamic.gyro1.at(dynamic.t0_s - self.initial_dt_s)[0])
        values = gp.pair_values(gp.wahba_rotation(np.array(vectors0), np.array(vectors1)), model,
                                self.initial_dt_s if model.time_offset else 0.0)
        values = optimize(graph, values)
        return Fit(tuple(effects), graph, values, self._families(values, model, static, dynamic),
                   {"model": model, "fold": fold})

    def extend(self, fit: Fit, candidate: Candidate):
        model = self._model(fit.effects + (candidate,))
        static, dynamic = self._data(fit.context["fold"])
        graph, _ = gp._build(static, dynamic, model, self.scale, huber_k=None)
        values = gtsam.Values(fit.values)
        key, dim = KEYS[candidate.effect]
        values.insert(key, np.zeros(dim))
        return graph, values, [(key, np.arange(dim))]

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        static, dynamic = self._data(1 - fold)
        return self._families(fit.values, fit.context["model"], static, dynamic)

    def _families(self, values, model: gp.PairModel, static, dynamic) -> list[ResidualFamily]:
        R, dt, r, d_a, d_g, G_a, G_g = pair_parameters(values, model)
        t = dynamic.t0_s
        coords = {"time_s": t, "angular_rate": np.linalg.norm(dynamic.gyro0, axis=1),
                  "angular_acceleration": np.linalg.norm(dynamic.gyro_rate_dot0, axis=1)}
        gyro = dynamic.gyro0 - dynamic.gyro1.at(t - dt)[0] @ (R @ G_g).T - d_g
        lever = np.einsum("nij,j->ni", inertial.lever_arm_jacobian(dynamic.gyro0, dynamic.gyro_rate_dot0), r)
        accel = dynamic.accel0 + lever - dynamic.accel1.at(t - dt)[0] @ (R @ G_a).T - d_a
        families = [
            ResidualFamily(self.imu1, "pair_gyro", "rad s^-1", gyro / (dynamic.gyro_sigma * self.scale["gyro"]), gyro,
                           coords),
            ResidualFamily(self.imu1, "pair_accel", "m s^-2", accel / (dynamic.accel_sigma * self.scale["accel"]),
                           accel, coords)]
        if static:
            e = np.array([p.accel0 - R @ G_a @ p.accel1 - d_a for p in static])
            sigma = np.array([p.sigma for p in static]) * self.scale["static"]
            families.append(ResidualFamily(self.imu1, "pair_static", "m s^-2", e / sigma, e,
                                           {"pose": np.arange(len(static), dtype=float)}))
        return families

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """The candidate's value and 1-sigma, with each group's noise level re-estimated from this fit's own
        residuals (the base fit's levels still held every effect not yet modelled)."""
        key, _ = KEYS[candidate.effect]
        scale = dict(self.scale)
        for fam in fit.families:
            group = fam.quantity.removeprefix("pair_")
            # filtered samples stay slightly correlated: inflate as the calibration does (effective sample size)
            inflation = 1.0 if group == "static" else stats.correlation_inflation([fam.whitened])
            scale[group] *= float(np.sqrt(np.mean(fam.whitened**2) * inflation))
        static, dynamic = self._data(fit.context["fold"])
        graph, _ = gp._build(static, dynamic, fit.context["model"], scale, huber_k=None)
        cov = marginal_covariances(graph, fit.values, [key], candidate.effect)[key]
        value, sigma = fit.values.atVector(key), np.sqrt(np.diag(cov))
        if key == gp.TIME_OFFSET:
            return {"dt_s": float(value[0])}, {"dt_s": float(sigma[0])}
        if key == gp.LEVER_ARM:
            return {"r_m": value.tolist()}, {"r_m": sigma.tolist()}
        diagonal, off = [0, 3, 5], [1, 2, 4]  # entries (00, 11, 22) and (01, 02, 12) of the symmetric S
        return ({"scale": value[diagonal].tolist(), "shear": value[off].tolist(),
                 "meaning": "v_imu0 = R (I + S) v_imu1, S symmetric: scale = diagonal, shear = off-diagonal"},
                {"scale": sigma[diagonal].tolist(), "shear": sigma[off].tolist()})


def simulate_pair_like(system: ImuPairAudit, fit: Fit, seed: int, noise_fit: Fit | None = None) -> ImuPairAudit:
    """The recording's own scenario re-simulated with the pair model of ``fit``.

    imu0's measured (filtered) signals are kept as the truth of the motion; imu1's are regenerated from them
    through the fitted relation (rotation, relative gains and offsets, lever arm, clock offset) at imu1's own
    sample times, plus white noise at the level the residuals of ``noise_fit`` show (default ``fit``; pass the
    final fit, whose residual is the best estimate of the sensors' noise).  The base model's simulation then says
    what residual the base model expects; the final model's, whether the extension explains the measurement.
    """
    rng = np.random.default_rng(seed)
    values, model = fit.values, fit.context["model"]
    R, dt, r, d_a, d_g, G_a, G_g = pair_parameters(values, model)
    rms = {fam.quantity.removeprefix("pair_"): fam.rms for fam in (noise_fit or fit).families}
    d = system.dynamic
    t1 = d.gyro1.t_s
    inside = (t1 + dt > d.t0_s[0]) & (t1 + dt < d.t0_s[-1])
    t1 = t1[inside]
    w0, w_dot0 = fimu.Signal(d.t0_s, d.gyro0), fimu.Signal(d.t0_s, d.gyro_rate_dot0)
    a0 = fimu.Signal(d.t0_s, d.accel0)
    w, w_dot = w0.at(t1 + dt)[0], w_dot0.at(t1 + dt)[0]
    f1_in_0 = a0.at(t1 + dt)[0] + np.einsum("nij,j->ni", inertial.lever_arm_jacobian(w, w_dot), r)
    to_imu1_g, to_imu1_a = np.linalg.inv(R @ G_g), np.linalg.inv(R @ G_a)
    # each pair residual carries both IMUs' noise: give imu1 the whole observed level (imu0's is in its data)
    gyro1 = (w - d_g) @ to_imu1_g.T + rng.normal(0, rms.get("gyro", 0.0) / np.sqrt(3), (len(t1), 3))
    accel1 = (f1_in_0 - d_a) @ to_imu1_a.T + rng.normal(0, rms.get("accel", 0.0) / np.sqrt(3), (len(t1), 3))
    dynamic = replace(d, gyro1=fimu.Signal(t1, gyro1), accel1=fimu.Signal(t1, accel1))
    static = [replace(p, accel1=to_imu1_a @ (p.accel0 - d_a) + rng.normal(0, p.sigma)) for p in system.static]
    twin = object.__new__(ImuPairAudit)
    twin.__dict__.update(system.__dict__)
    twin.dynamic, twin.static = dynamic, static
    half = 0.5 * (dynamic.t0_s[0] + dynamic.t0_s[-1])
    twin._halves = [dynamic.t0_s < half, dynamic.t0_s >= half]
    return twin

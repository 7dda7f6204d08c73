"""The two-IMU system (``--system imu-pair``) for the audit.

Base model (``rotation``): the patent's relation ``v0 = R v1`` for static and moving samples, with constant
relative accelerometer and gyro offsets.  Catalog: ``time_offset`` (t_imu0 = t_imu1 + dt: shows as a gyro
residual proportional to angular acceleration) and ``lever_arm`` (imu1 displaced by r: shows as an
accelerometer residual ``[w_dot]x r + [w]x^2 r``, growing with rotation rate).

Residual families: ``pair_gyro`` (rad s^-1) and ``pair_accel`` (m s^-2) per moving sample, ``pair_static``
(m s^-2) per static pose; coordinates: time, |w|, |w_dot| of imu0.  Folds split the recording in two halves.

Generic terms (:mod:`selfcal.audit.terms`): the relative gyro or accelerometer offset varying as a function of
one driver of the moving samples (time; imu1's own rate ``w_x w_y w_z``, its norm ``w_norm`` and specific force
``f_x f_y f_z``, in imu1's axes: the audited sensor is imu1; imu1's auxiliary channels such as ``temperature``),
fitted in the pair factors as offset channels; the static pairs keep the constant offset.
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.core import inertial, so3, stats
from selfcal.factors import imu as fimu
from selfcal.graphs import imu_pair as gp
from selfcal.core.solve import joint_covariance, marginal_covariances, optimize
from selfcal.io.recording import ImuData

MEANINGS = {"time_offset": "the clocks of the two IMUs are offset: t_imu0 = t_imu1 + dt",
            "lever_arm": "imu1 is displaced from imu0: rotation adds centripetal and tangential acceleration",
            "accel_relative_gain": "imu1's accelerometer scale / non-orthogonality differs from imu0's",
            "gyro_relative_gain": "imu1's gyro scale / non-orthogonality differs from imu0's",
            "accel_axis_rotation": "imu1's accelerometer triad is rotated relative to its gyro triad (relative to "
                                   "imu0's): the accelerometers and gyros disagree on the rotation between the IMUs"}
KEYS = {"time_offset": (gp.TIME_OFFSET, 1), "lever_arm": (gp.LEVER_ARM, 3),
        "accel_relative_gain": (gp.ACCEL_GAIN, 6), "gyro_relative_gain": (gp.GYRO_GAIN, 6),
        "accel_axis_rotation": (gp.ACCEL_AXIS_ROTATION, 3)}


def pair_parameters(values: gtsam.Values, model: gp.PairModel):
    """(R, dt, r, accel offset, gyro offset, accel gain I + S + [rho]x, gyro gain I + S), nominal where not in the
    model."""
    return (values.atRot3(gp.ROTATION).matrix(),
            values.atVector(gp.TIME_OFFSET)[0] if model.time_offset else 0.0,
            values.atVector(gp.LEVER_ARM) if model.lever_arm else np.zeros(3),
            values.atVector(gp.ACCEL_OFFSET) if values.exists(gp.ACCEL_OFFSET) else np.zeros(3),
            values.atVector(gp.GYRO_OFFSET) if values.exists(gp.GYRO_OFFSET) else np.zeros(3),
            (fimu.symmetric_gain(values.atVector(gp.ACCEL_GAIN)) if model.accel_gain else np.eye(3))
            + (so3.hat(values.atVector(gp.ACCEL_AXIS_ROTATION)) if model.accel_axis_rotation else 0.0),
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
        # the audited sensor is imu1: its own outputs (its axes) at imu0's sample instants are the drivers
        d = self.dynamic
        w1, f1 = d.gyro1.at(d.t0_s - self.initial_dt_s)[0], d.accel1.at(d.t0_s - self.initial_dt_s)[0]
        self._drivers = {"time": d.t0_s, **{f"w_{a}": w1[:, j] for j, a in enumerate("xyz")},
                         "w_norm": np.linalg.norm(w1, axis=1), **{f"f_{a}": f1[:, j] for j, a in enumerate("xyz")}}
        # imu1's auxiliary channels (temperature, ...) at the same instants: drivers of their own and the second
        # factor of products (a scale of imu1 drifting with its temperature is w_x x temperature)
        t1 = (d1.t_ns - d0.t_ns[0]) * 1e-9
        self._channel_units = {n: d1.channel_units.get(n, "") for n in d1.channels if n not in self._drivers}
        for name in self._channel_units:
            self._drivers[name] = np.interp(d.t0_s - self.initial_dt_s, t1, np.asarray(d1.channels[name], float))
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
                          "angular rate"),
                Candidate("accel_axis_rotation", self.imu1, MEANINGS["accel_axis_rotation"], "pair_accel",
                          "specific force")]

    def _model(self, effects) -> gp.PairModel:
        names = {c.effect for c in effects}
        return gp.PairModel(time_offset="time_offset" in names, lever_arm="lever_arm" in names,
                            accel_gain="accel_relative_gain" in names, gyro_gain="gyro_relative_gain" in names,
                            accel_axis_rotation="accel_axis_rotation" in names)

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

    # --- the generic term library -----------------------------------------------------------------------------

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        units = {"time": "s", "w_norm": "rad s^-1", **{f"w_{a}": "rad s^-1" for a in "xyz"},
                 **{f"f_{a}": "m s^-2" for a in "xyz"}}
        kinds = {"time": "time", **{n: "channel" for n in self._channel_units}}
        units.update(self._channel_units)
        coordinates = [Coordinate(n, v, units[n], kinds.get(n, "state")) for n, v in self._drivers.items()]
        return {(self.imu1, "pair_gyro"): coordinates, (self.imu1, "pair_accel"): coordinates}

    @staticmethod
    def _term_keys(effects) -> dict[Candidate, list[int]]:
        """Each term's offset-slope keys, one per basis column, numbered in the order of ``effects``."""
        out, index = {}, 0
        for c in effects:
            if c.term is not None:
                q = c.term.dof()
                out[c] = [gtsam.symbol("k", index + j) for j in range(q)]
                index += q
        return out

    def _channels(self, effects, part=None) -> dict[str, list[tuple[int, np.ndarray]]]:
        """Per group, (key, basis column over this part's moving samples) of every term among ``effects``."""
        mask = slice(None) if part is None else self._halves[part]
        out = {"gyro": [], "accel": []}
        for c, keys in self._term_keys(effects).items():
            for key, column in zip(keys, c.term.columns(self._drivers).T):
                out[c.target.removeprefix("pair_")].append((key, column[mask]))
        return out

    def catalog_term(self, candidate: Candidate) -> None:
        return None  # no catalog effect of the pair is a single library term

    def fit(self, effects, fold=None) -> Fit:
        model = self._model(effects)
        static, dynamic = self._data(fold)
        graph, _ = gp._build(static, dynamic, model, self.scale, huber_k=None, channels=self._channels(effects, fold))
        vectors0 = [p.accel0 for p in static] + list(dynamic.gyro0)
        vectors1 = [p.accel1 for p in static] + list(dynamic.gyro1.at(dynamic.t0_s - self.initial_dt_s)[0])
        values = gp.pair_values(gp.wahba_rotation(np.array(vectors0), np.array(vectors1)), model,
                                self.initial_dt_s if model.time_offset else 0.0)
        for group in self._channels(effects).values():
            for key, _ in group:
                values.insert(key, np.zeros(3))
        values = optimize(graph, values)
        return Fit(tuple(effects), graph, values, self._families(values, model, static, dynamic, effects, fold),
                   {"model": model, "fold": fold})

    def extend(self, fit: Fit, candidate: Candidate):
        return self._extended(fit, [candidate], single=True)

    def extend_all(self, fit: Fit, candidates: list[Candidate]):
        """One graph holding every library candidate (offset slopes at zero): (graph, values, new columns each)."""
        return self._extended(fit, candidates, single=False)

    def _extended(self, fit: Fit, candidates: list[Candidate], single: bool):
        effects = fit.effects + tuple(candidates)
        model = self._model(effects)
        static, dynamic = self._data(fit.context["fold"])
        graph, _ = gp._build(static, dynamic, model, self.scale, huber_k=None,
                             channels=self._channels(effects, fit.context["fold"]))
        values = gtsam.Values(fit.values)
        groups = []
        for cand in candidates:
            if cand.term is None:
                key, dim = KEYS[cand.effect]
                values.insert(key, np.zeros(dim))
                groups.append([(key, np.arange(dim))])
                continue
            keys = self._term_keys(effects)[cand]
            for key in keys:
                if not values.exists(key):
                    values.insert(key, np.zeros(3))
            groups.append([(key, np.arange(3)) for key in keys])
        return (graph, values, groups[0]) if single else (graph, values, groups)

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        static, dynamic = self._data(1 - fold)
        return self._families(fit.values, fit.context["model"], static, dynamic, fit.effects, 1 - fold)

    def _families(self, values, model: gp.PairModel, static, dynamic, effects=(), part=None) -> list[ResidualFamily]:
        R, dt, r, d_a, d_g, G_a, G_g = pair_parameters(values, model)
        varying = {group: sum((np.outer(phi, values.atVector(key)) for key, phi in channels), 0.0)
                   for group, channels in self._channels(effects, part).items()}
        d_g, d_a = d_g + varying["gyro"], d_a + varying["accel"]
        t = dynamic.t0_s
        coords = {"time_s": t, "angular_rate": np.linalg.norm(dynamic.gyro0, axis=1),
                  "angular_acceleration": np.linalg.norm(dynamic.gyro_rate_dot0, axis=1)}
        gyro = dynamic.gyro0 - dynamic.gyro1.at(t - dt)[0] @ (R @ G_g).T - d_g
        lever = np.einsum("nij,j->ni", inertial.lever_arm_jacobian(dynamic.rate0, dynamic.gyro_rate_dot0), r)
        accel = dynamic.accel0 + lever - dynamic.accel1.at(t - dt)[0] @ (R @ G_a).T - d_a
        families = [
            ResidualFamily(self.imu1, "pair_gyro", "rad s^-1", gyro / (dynamic.gyro_sigma * self.scale["gyro"]), gyro,
                           coords),
            ResidualFamily(self.imu1, "pair_accel", "m s^-2", accel / (dynamic.accel_sigma * self.scale["accel"]),
                           accel, coords)]
        if static:
            d_a = pair_parameters(values, model)[3]  # the static pairs keep the constant offset
            e = np.array([p.accel0 - R @ G_a @ p.accel1 - d_a for p in static])
            sigma = np.array([p.sigma for p in static]) * self.scale["static"]
            families.append(ResidualFamily(self.imu1, "pair_static", "m s^-2", e / sigma, e,
                                           {"pose": np.arange(len(static), dtype=float)}))
        return families

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """The candidate's value and 1-sigma, with each group's noise level re-estimated from this fit's own
        residuals (the base fit's levels still held every effect not yet modelled)."""
        scale = dict(self.scale)
        for fam in fit.families:
            group = fam.quantity.removeprefix("pair_")
            # filtered samples stay slightly correlated: inflate as the calibration does (effective sample size)
            inflation = 1.0 if group == "static" else stats.correlation_inflation([fam.whitened])
            scale[group] *= float(np.sqrt(np.mean(fam.whitened**2) * inflation))
        static, dynamic = self._data(fit.context["fold"])
        graph, _ = gp._build(static, dynamic, fit.context["model"], scale, huber_k=None,
                             channels=self._channels(fit.effects, fit.context["fold"]))
        if candidate.term is not None:
            keys = self._term_keys(fit.effects)[candidate]
            # the fit's own variance factor: on 6 hidden nonlinearities the per-group rescaling below gave an RMS
            # z of 1.6 for terms, this one 0.9 (a term spans all samples; the rescaling is per group)
            joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * variance_factor(fit)
            unit = "rad s^-1" if candidate.target == "pair_gyro" else "m s^-2"
            driver_unit = next(c.unit for c in self.term_coordinates()[(self.imu1, candidate.target)]
                               if c.name == candidate.term.driver)
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                             self._drivers, unit, driver_unit)
            estimate["target"] = f"{self.imu1}/{candidate.target}"
            return estimate, std
        key, _ = KEYS[candidate.effect]
        cov = marginal_covariances(graph, fit.values, [key], candidate.effect)[key]
        value, sigma = fit.values.atVector(key), np.sqrt(np.diag(cov))
        if key == gp.TIME_OFFSET:
            return {"dt_s": float(value[0])}, {"dt_s": float(sigma[0])}
        if key == gp.LEVER_ARM:
            return {"r_m": value.tolist()}, {"r_m": sigma.tolist()}
        if key == gp.ACCEL_AXIS_ROTATION:
            return ({"rho_rad": value.tolist(), "meaning": "a_imu0 = R (I + S + [rho]x) a_imu1, gyros fix R"},
                    {"rho_rad": sigma.tolist()})
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
    lever = inertial.lever_arm_jacobian(w - d.gyro_bias0, w_dot)
    f1_in_0 = a0.at(t1 + dt)[0] + np.einsum("nij,j->ni", lever, r)
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

"""The vessel system (``--system ship``) for the audit.

Base model (``attitude``): attitude and drifting gyro bias from the gyro and the accelerometer's total-force
tilt, known accelerations (speed log, yaw rate) removed, the accelerometer taken at the centre of rotation
(:mod:`selfcal.graphs.ship`).  Catalog:

* ``lever_arm``: the accelerometer sits at ``r`` from the centre of rotation; the hull's angular acceleration
  and rate add ``[w_dot]x r + [w]x^2 r`` to what it measures, which tilts the measured up with the waves,
* ``speed_log_scale``: the speed log reads ``(1 + k)`` times the true speed, so the surge and centripetal
  accelerations removed are off by ``k`` (a tilt during accelerations and turns),
* ``gyro_scale``: the gyro reads ``(1 + s_i)`` times the true rate on axis i, so the attitude it carries between
  keyframes over- or under-rotates the waves and the turns by ``s`` times the rotation: the accelerometer's tilt
  disagrees with it in proportion to the roll and pitch swings (x and y, determined by the waves) and, for z,
  only through turns made while heeled (the heading itself is never measured), so z mostly stays at its prior
  (:func:`selfcal.factors.ship.gyro_scale_rotation_factor`).  The yaw rate's other path, the centripetal
  acceleration ``v w_z`` removed from the tilt, is not part of this candidate (``speed_log_scale`` scales it).

Residual family ``tilt`` (rad, 2 per keyframe: the world-frame horizontal part of the corrected force
direction) with coordinates time, angular acceleration, surge acceleration, centripetal acceleration and the
rotation since the last keyframe.

Generic terms (:mod:`selfcal.audit.terms`): a tilt offset ``k phi(x)`` (``k`` two components, rad per unit)
inside each keyframe's tilt factor, in the drivers ``time``, ``roll``, ``pitch``, ``heading`` (rad, the gyro-carried
heading from the start: never measured absolutely), ``speed`` (the log's, when there is one),
``angular_acceleration``, ``surge_acceleration`` and ``centripetal_acceleration``.  A smooth term in roll, pitch or
heading is evaluated at each keyframe's attitude state (:class:`AttitudeColumn`); the first full fit the library
sees gives the other drivers' values, the heading's branch and the ranges the findings report.

Folds interleave blocks of ``FOLD_BLOCK_S`` (even / odd blocks in time), and every fit keeps the whole gyro chain:
a fold's graph holds the tilt factors of its own blocks only, the attitudes elsewhere carried by the gyro.  The
held-out blocks are scored by their predictive chi-square (:class:`PredictedFit`): the voyage re-solved with every
block's tilt and the trained constants and terms held, less the trained blocks' own RSS.  Halves in time would make
a term in time, or in a heading only one half visits, an extrapolation that fails for that reason alone (measured:
a heading-locked accelerometer bias with p = 1e-12 and a BIC gain of 1800 raised the held-out RSS of halves by
15-40 %); a continuous chain keeps one heading gauge for every block (a block started afresh would put its
world-frame tilt offsets in a yaw of its own).

The tilt sigma's floor (unmodelled slow horizontal accelerations) is measured on the voyage before the search
(:meth:`ShipAudit._measure_tilt_floor`) and said in the audit's notes.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.core import stats
from selfcal.graphs.ship import (GYRO_SCALE_KEY, LEVER_ARM_KEY, R_KEY, RELATIVE_TOLERANCE, SPEED_SCALE_KEY,
                                 ShipGraph, ShipGraphOptions, ShipInputs, keyframes_from_inputs)
from selfcal.core.solve import joint_covariance, marginal_covariances, optimize
from selfcal.models import ship as ship_model

MEANINGS = {"lever_arm": "the accelerometer is displaced from the centre of rotation: the hull's angular "
                         "acceleration and rate tilt the force it measures",
            "speed_log_scale": "the speed log reads (1 + k) times the true speed: surge and centripetal "
                               "accelerations are removed wrongly",
            "gyro_scale": "the gyro reads (1 + s) times the true rate per axis: the attitude it carries over- or "
                          "under-rotates the waves and turns, against the accelerometer's tilt"}
KEYS = {"lever_arm": (LEVER_ARM_KEY, 3), "speed_log_scale": (SPEED_SCALE_KEY, 1), "gyro_scale": (GYRO_SCALE_KEY, 3)}
ROTATION_COORDINATE = "rotation since last keyframe"  # rad: what a scale error multiplies
DRIVER_UNITS = {"time": "s", "roll": "rad", "pitch": "rad", "heading": "rad", "speed": "m s^-1",
                "angular_acceleration": "rad s^-2", "surge_acceleration": "m s^-2",
                "centripetal_acceleration": "m s^-2"}
AUDIT_KEYFRAME_S = 0.5  # coarser than smoothing: the audit refits the voyage a dozen times
FLOOR_PASSES = 3  # fits that measure the tilt floor (it settles within 1 % by the third on the simulated voyages)
MIN_FLOOR_RAD = 1e-5  # a floor never zero: the tilt sigma then rests on the accelerometer's measured noise alone
FOLD_BLOCK_S = 20.0  # folds' block length: longer than the wave periods (5-20 s) the tilt residuals correlate over,
# short enough that a 2-minute voyage gives each fold three blocks spread over it


@dataclass
class PredictedFit(Fit):
    """The voyage solved with every tilt factor and the trained constants held: ``rss`` is the joint RSS less the
    trained blocks' (``trained_rss``, at the trained states).  For a linear Gaussian model that difference is exactly
    the held-out residuals' chi-square under their predictive covariance (measurement noise plus the trained
    states' uncertainty, the gyro drift across a held-out block included), so neither of the two ways found wanting
    is taken: re-solving the held-out blocks alone lets their attitudes follow a slow tilt offset (half of a
    heading-locked bias absorbed), and predicted residuals weighed by the tilt noise alone count the gyro drift
    bridged over a 20 s block as misfit (3 false findings on 20 null voyages against 1)."""

    trained_rss: float = 0.0

    @property
    def rss(self) -> float:
        return 2.0 * self.graph.error(self.values) - self.trained_rss


ATTITUDE_DRIVERS = {"roll": 0, "pitch": 1, "heading": 2}  # index in models.ship.euler_zyx


class AttitudeColumn:
    """Column ``j`` of a generic term in roll, pitch or heading, at each keyframe a function of that keyframe's
    attitude (the state being solved), not of the attitude of the base fit: a heading-locked bias bends the base
    fit (measured: its heading 0.27 rad off the truth after 5 min of turns), and a term frozen on that heading
    left structure the audit named as a second effect (a harmonic in time; none with the true heading).
    ``reference`` (the frozen driver) fixes the branch of the unwrapped heading: the state's angle is taken
    within pi of it."""

    def __init__(self, term, j: int, reference: np.ndarray):
        self.term, self.j, self.reference = term, j, reference

    def __getitem__(self, k: int):
        return lambda R_W_S: self.at(R_W_S, float(self.reference[k]))

    def at(self, R_W_S: np.ndarray, reference: float) -> tuple[float, np.ndarray]:
        angles, jacobian = ship_model.euler_zyx(R_W_S)
        i = ATTITUDE_DRIVERS[self.term.driver]
        x = reference + (angles[i] - reference + np.pi) % (2.0 * np.pi) - np.pi
        h = 1e-6  # the basis' slope in its driver, central difference (the library's forms are smooth)
        phi = self.term.columns({self.term.driver: np.array([x - h, x, x + h])})[:, self.j]
        return float(phi[1]), (phi[2] - phi[0]) / (2.0 * h) * jacobian[i]


class ShipAudit:
    name = "ship"
    folds = 2
    base_model = "attitude"
    information_form = True  # score tests from the normal equations: the base graph is full rank (R0 and bias
    # priors); on 300 s voyages the dense Jacobian's SVDs were a quarter of an audit (same F to 1e-11, 40 % faster)

    def __init__(self, inputs: ShipInputs, sensor: str = "imu0", keyframe_s: float = AUDIT_KEYFRAME_S):
        self.inputs, self.sensor = inputs, sensor
        self.base_effects = ()
        self.options = ShipGraphOptions(keyframe_s=keyframe_s, estimate_lever_arm=False)
        self.frames = keyframes_from_inputs(inputs, self.options)
        t = np.array([f.t_s for f in self.frames])
        block = ((t - t[0]) // FOLD_BLOCK_S).astype(int) % 2
        self._parts = [np.flatnonzero(block == 0), np.flatnonzero(block == 1)]
        self.has_speed = inputs.speed_m_s is not None
        self._drivers: dict[str, np.ndarray] | None = None
        self._keys_of = library.TermKeys("u")
        stated = self.options.tilt_floor_rad
        self._measure_tilt_floor()
        self.notes = [f"tilt noise floor measured on the voyage's residuals: {self.options.tilt_floor_rad * 1e3:.3g} "
                      f"mrad (stated {stated * 1e3:.3g} mrad)"]

    def _measure_tilt_floor(self) -> None:
        """Set the tilt sigma's floor to what the base model's residuals show (a variance component estimate).

        The floor stands for slow horizontal accelerations nobody modelled (sway); stated too high, the graph
        trusts the gyro over the tilt, the attitude follows the gyro's integrated noise, and the tilt residuals
        carry that smooth error: structure in time the audit then names (measured: 2 of 20 null voyages at the
        stated 2 mrad floor, none at the 0.3-0.5 mrad the simulated voyages really show).  Per pass, ``floor^2 =
        mean((e_k - e_k-1)^2) / 2 - mean(white^2)``: the keyframe-to-keyframe spread of the tilt residuals (blind to
        misfits slower than a keyframe, which are the search's business) less the part the measured accelerometer
        noise explains (the hull terms, the speed log's rate among them, are slow: the spread does not see them).
        The residuals are taken as the noise itself (the attitudes absorb little of it between gyro links), which
        sets the floor a little low, not high.  Fewer than 3 keyframes: the stated floor stays."""
        if len(self.frames) < 3:
            return
        for _ in range(FLOOR_PASSES):
            fit = self.fit(())
            white2 = np.mean([f.noise_tilt_sigma_rad ** 2 for f in self.frames])
            e = fit.families[0].physical
            spread = float(np.mean(np.diff(e, axis=0) ** 2)) / 2.0  # keyframe to keyframe: blind to slow misfits
            measured = np.sqrt(max(spread - white2, MIN_FLOOR_RAD ** 2))
            self.options = replace(self.options, tilt_floor_rad=float(measured))
            self.frames = keyframes_from_inputs(self.inputs, self.options)

    def candidates(self) -> list[Candidate]:
        out = [Candidate("lever_arm", self.sensor, MEANINGS["lever_arm"], "tilt", "angular acceleration"),
               Candidate("gyro_scale", self.sensor, MEANINGS["gyro_scale"], "tilt", ROTATION_COORDINATE)]
        if self.has_speed:
            out.append(Candidate("speed_log_scale", "speed0", MEANINGS["speed_log_scale"], "tilt",
                                 "surge acceleration"))
        return out

    def _options(self, effects, fixed: gtsam.Values | None = None) -> ShipGraphOptions:
        names = {c.effect for c in effects}
        options = replace(self.options, estimate_lever_arm="lever_arm" in names and fixed is None,
                          estimate_speed_scale="speed_log_scale" in names and fixed is None,
                          estimate_gyro_scale="gyro_scale" in names and fixed is None)
        if fixed is not None:  # held-out half: the constants trained on the other half, held
            if fixed.exists(LEVER_ARM_KEY):
                options = replace(options, lever_arm_m=tuple(fixed.atVector(LEVER_ARM_KEY)))
            if fixed.exists(SPEED_SCALE_KEY):
                options = replace(options, speed_scale=float(fixed.atVector(SPEED_SCALE_KEY)[0]))
            if fixed.exists(GYRO_SCALE_KEY):
                options = replace(options, gyro_scale=tuple(fixed.atVector(GYRO_SCALE_KEY)))
        return options

    def _rows(self, part) -> np.ndarray:
        """Indices of the keyframes whose tilt a fit of ``part`` sees (None: all)."""
        return np.arange(len(self.frames)) if part is None else self._parts[part]

    def _build(self, effects, part, fixed=None):
        """(graph, start values, the builder) of the voyage with the tilt factors of ``part`` (None: all), the gyro
        chain whole; generic terms as tilt offsets, fitted (keys at zero) or, with ``fixed``, known."""
        builder = ShipGraph(self._options(effects, fixed), self.inputs.gravity_m_s2, self.inputs.gyro_noise_density,
                            self.inputs.gyro_random_walk)
        columns = self._term_columns(effects)
        if fixed is None:
            builder.term_columns = columns
        else:
            builder.known_terms = [(fixed.atVector(key), phi) for key, phi in columns]
        seen = np.zeros(len(self.frames), dtype=bool)
        seen[self._rows(part)] = True
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for j, frame in enumerate(self.frames):
            g, v = builder.add(frame, values if builder.k >= 0 else None, propagate=False)
            # the keyframe's tilt factor is the first ShipGraph.add makes: another fold's keyframe keeps only its
            # gyro link (and priors)
            for i in range(0 if seen[j] else 1, g.size()):
                graph.push_back(g.at(i))
            values.insert(v)
        for key, _ in builder.term_columns:
            values.insert(key, np.zeros(2))
        return graph, values, builder

    def fit(self, effects, fold=None) -> Fit:
        graph, values, builder = self._build(effects, fold)
        values = optimize(graph, values, max_iterations=50, relative_tolerance=RELATIVE_TOLERANCE)
        return Fit(tuple(effects), graph, values, self._families(values, builder, fold), {"fold": fold})

    def extend_all(self, fit: Fit, candidates):
        """One graph holding every candidate (new variables at zero): (graph, values, new columns each)."""
        graph, start, _ = self._build(fit.effects + tuple(candidates), fit.context["fold"])
        values = gtsam.Values(fit.values)
        groups = []
        for cand in candidates:
            keys = [KEYS[cand.effect]] if cand.term is None else [(k, 2) for k in self._keys_of(cand.term)]
            for key, dim in keys:
                values.insert(key, start.atVector(key) if start.exists(key) else np.zeros(dim))
            groups.append([(key, np.arange(dim)) for key, dim in keys])
        return graph, values, groups

    def heldout_fit(self, fit: Fit, fold: int) -> Fit:
        """The other blocks predicted by ``fit`` (trained on ``fold``): the voyage re-solved with every block's tilt
        factors and ``fit``'s constants and terms held; its RSS is the held-out blocks' predictive chi-square, the
        joint graph's less the trained blocks' (see :class:`PredictedFit`); its families the held-out rows'."""
        other = 1 - fold
        trained, _, _ = self._build(fit.effects, fold, fixed=fit.values)
        joint, values, builder = self._build(fit.effects, None, fixed=fit.values)
        start = gtsam.Values(fit.values)  # the trained states: the held-out blocks bridged by the gyro chain
        for key in start.keys():
            if not values.exists(key):
                start.erase(key)
        values = optimize(joint, start, max_iterations=50, relative_tolerance=RELATIVE_TOLERANCE)
        return PredictedFit(tuple(fit.effects), joint, values, self._families(values, builder, other), {"fold": other},
                            trained_rss=2.0 * trained.error(fit.values))

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        return self.heldout_fit(fit, fold).families

    def _families(self, values, builder: ShipGraph, part) -> list[ResidualFamily]:
        rows = self._rows(part)
        frames = [self.frames[j] for j in rows]
        e = np.array([builder.tilt_factor(self.frames[j], R_KEY(j), j, along_track=False).unwhitenedError(values)
                      for j in rows])
        normalized = np.array([builder.tilt_factor(self.frames[j], R_KEY(j), j).whitenedError(values) for j in rows])
        coords = {"time_s": np.array([f.t_s for f in frames]),
                  "angular acceleration": np.array([np.linalg.norm(f.A_S) for f in frames]),
                  "surge acceleration": self._surge_driver()[rows],
                  "centripetal acceleration": np.array([f.a_known_S[1] for f in frames]),
                  ROTATION_COORDINATE: np.array([np.linalg.norm(f.gyro_rad_s.T @ f.dt_s) for f in frames])}
        return [ResidualFamily(self.sensor, "tilt", "rad", normalized, e, coords)]

    # --- the generic term library -----------------------------------------------------------------------------

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        if self._drivers is None:
            self._drivers = self._driver_values(fit if fit is not None else self.fit(()))
        kinds = {"time": "time", "roll": "angle", "pitch": "angle", "heading": "angle"}
        return {(self.sensor, "tilt"): [Coordinate(n, v, DRIVER_UNITS[n], kinds.get(n, "state"))
                                        for n, v in self._drivers.items()]}

    def _driver_values(self, fit: Fit) -> dict[str, np.ndarray]:
        """Per keyframe of the voyage: time, attitude of ``fit`` (a full-voyage fit), speed, hull accelerations."""
        if fit.context["fold"] is not None:
            fit = self.fit(fit.effects)
        ypr = np.array([fit.values.atRot3(R_KEY(j)).ypr() for j in range(len(self.frames))])
        t = np.array([f.t_s for f in self.frames])
        drivers = {"time": t, "roll": ypr[:, 2], "pitch": ypr[:, 1], "heading": np.unwrap(ypr[:, 0])}
        if self.has_speed:
            drivers["speed"] = np.interp(t, self.inputs.t_s, self.inputs.speed_m_s)
        drivers.update(angular_acceleration=np.array([np.linalg.norm(f.A_S) for f in self.frames]),
                       surge_acceleration=self._surge_driver(),
                       centripetal_acceleration=np.array([f.a_known_S[1] for f in self.frames]))
        return drivers

    def _surge_driver(self) -> np.ndarray:
        """Surge acceleration per keyframe, m/s^2, as a driver: the log's slow rate where it has one (the rate the
        tilt is corrected by carries the log's noise, which is in the residual too: see ``smoothed_speed``)."""
        t = np.array([f.t_s for f in self.frames])
        if self.inputs.slow_speed_rate_m_s2 is not None:
            return np.interp(t, self.inputs.t_s, self.inputs.slow_speed_rate_m_s2)
        return np.array([f.a_known_S[0] for f in self.frames])

    def catalog_term(self, candidate: Candidate) -> None:
        return None  # no catalog effect of the ship is a single tilt offset in one driver

    def _term_columns(self, effects) -> list[tuple[int, object]]:
        """(key, phi over the keyframes) per column of each generic term: values of the frozen drivers, or, for a
        term in the attitude itself (roll, pitch, heading), :class:`AttitudeColumn` (the keyframe's state)."""
        out = []
        for c in effects:
            if c.term is None:
                continue
            if c.term.driver in ATTITUDE_DRIVERS and c.term.second is None and c.term.form != "step":  # smooth
                out += [(key, AttitudeColumn(c.term, j, self._drivers[c.term.driver]))
                        for j, key in enumerate(self._keys_of(c.term))]
            else:
                out += list(zip(self._keys_of(c.term), c.term.columns(self._drivers).T))
        return out

    def residual_correlation(self, fit: Fit) -> float:
        """Variance inflation of the tilt residuals: waves make neighbouring keyframes' residuals alike."""
        return stats.correlation_inflation([fam.whitened for fam in fit.families], max_lag=40)

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """Value and 1-sigma; the covariance is scaled by the fit's variance factor and by the tilt residuals'
        correlation in time (waves make neighbouring keyframes' residuals alike: fewer independent samples)."""
        if candidate.term is not None:
            keys = self._keys_of(candidate.term)
            joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * (
                variance_factor(fit) * self.residual_correlation(fit))
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                             self._drivers, "rad", DRIVER_UNITS[candidate.term.driver])
            estimate["target"] = f"{self.sensor}/tilt"
            return estimate, std
        key, _ = KEYS[candidate.effect]
        cov = marginal_covariances(fit.graph, fit.values, [key], candidate.effect)[key]
        sigma = np.sqrt(np.diag(cov) * variance_factor(fit) * self.residual_correlation(fit))
        value = fit.values.atVector(key)
        if key == LEVER_ARM_KEY:
            return {"r_m": value.tolist()}, {"r_m": sigma.tolist()}
        if key == GYRO_SCALE_KEY:  # the graph's s is the contract's scale: raw = (1 + s) x true
            return {"scale": value.tolist()}, {"scale": sigma.tolist()}
        # the graph's k corrects the log's acceleration (true = (1 + k) logged); the log reads 1 / (1 + k) - 1 high
        correction = 1.0 + float(value[0])
        return {"scale": 1.0 / correction - 1.0}, {"scale": float(sigma[0]) / correction**2}

"""The single-IMU system (``--system imu``) for the audit: intrinsics graph, residual families, effect catalog.

Residual families (evaluated from the parameters alone, so held-out poses are predicted the same way):

* ``accel``: ``|f_k| - g`` per static pose (m s^-2); coordinates: gravity direction ``up_x/y/z``, time, channels
* ``gyro``: static gyro output minus bias and g-sensitivity per pose and axis (rad s^-1); same coordinates
* ``gyro_motion``: ``u_{k+1} - delta_R^T u_k`` per move (rad), the up-directions from the calibrated
  accelerometer; coordinates: the move's rotation vector ``rot_x/y/z``, time, channels

Catalog (ARCHITECTURE.md's IMU table, plus ``bias_drift``: bias linear in time, the deterministic part of a
wandering bias, and the rival a channel collinear with time must be told apart from).

Generic terms (:mod:`selfcal.audit.terms`) are corrections of the accelerometer's or the gyro's output (all
three axes) by a function of one driver, fitted in the graph as bias slopes on derived channels (the basis
columns evaluated at every static pose and every sample of every move).  Drivers: time, the auxiliary channels,
the raw specific force ``f_x f_y f_z`` and, for the gyro in the moves (target ``gyro_motion``), the raw rate
``w_x w_y w_z`` and its norm ``w_norm``.  Catalog effects that are library terms keep their catalog names
(``bias_drift`` = poly1 in time, ``bias_temperature`` and ``channel:<name>`` = poly1 in that channel).
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.graphs import imu as gi
from selfcal.core.solve import joint_covariance, marginal_covariances, optimize
from selfcal.io.recording import ImuData
from selfcal.models import imu
from selfcal.core import so3

TIME_CHANNEL = "time_s"

MEANINGS = {
    "accel_scale": "accelerometer gain differs from nominal per axis",
    "accel_misalignment": "accelerometer axes are not orthogonal",
    "gyro_scale": "gyro gain differs from nominal per axis",
    "gyro_misalignment": "gyro axes are not orthogonal / not aligned with the accelerometer",
    "gyro_g_sensitivity": "gyro output depends on specific force",
    "bias_temperature": "bias linear in the temperature channel",
    "bias_drift": "bias changes linearly with time",
}


# physically plausible sizes of the catalog effects: beyond them, a unit error or an effect outside the catalog
# is the likelier cause (MEMS datasheets give scale errors of a few %, axis misalignment of about 1 deg,
# g-sensitivity up to about 0.1 deg/s/g = 1.7e-4 rad/s per m/s^2)
PLAUSIBLE = {"accel_scale": ("scale", 0.10), "gyro_scale": ("scale", 0.10),
             "accel_misalignment": ("angles", 0.10), "gyro_misalignment": ("angles", 0.10),
             "gyro_g_sensitivity": ("matrix", 1e-2)}
STATE_DRIVERS = {"accel": ("f_x", "f_y", "f_z"), "gyro": ("f_x", "f_y", "f_z"),
                 "gyro_motion": ("w_x", "w_y", "w_z", "w_norm")}
QUANTITY_OF_TARGET = {"accel": "accel", "gyro": "gyro", "gyro_motion": "gyro"}


def is_temperature(channel: str) -> bool:
    return channel.lower().startswith("temp")


def plausibility(candidate: Candidate, estimate: dict) -> str | None:
    """Why a catalog estimate is physically implausible (None: plausible)."""
    if candidate.effect not in PLAUSIBLE:
        return None
    key, limit = PLAUSIBLE[candidate.effect]
    largest = float(np.max(np.abs(estimate[key])))
    if largest <= limit:
        return None
    return (f"{candidate.effect} of {largest:.3g} exceeds the plausible {limit:g}: a unit error or an effect "
            "outside the catalog is the likelier cause")


class ImuIntrinsicsAudit:
    """Audit system for one IMU of a multi-position recording."""

    name = "imu"

    def __init__(self, data: ImuData, gravity_m_s2: float, base: str = "bias"):
        timed = replace(data, channels={**data.channels, TIME_CHANNEL: data.t_s},
                        channel_units={**data.channel_units, TIME_CHANNEL: "s"})
        self.problem = gi.problem_from_imu(timed, gravity_m_s2)
        self.notes = list(self.problem.notes)  # moves weakened by a gap while turning
        self._derived: dict[library.Term, tuple[str, ...]] = {}  # a term's derived channels in the problem
        self._drivers = self._driver_values()
        self.sensor = data.name
        self.base_model = base
        catalog = self.candidates()
        by_effect = {(c.effect, c.target): c for c in catalog}
        if base == "bias":
            self.base_effects = ()
        elif base == "standard":
            self.base_effects = tuple(by_effect[k] for k in (("accel_scale", "accel"), ("accel_misalignment", "accel"),
                                                             ("gyro_scale", "gyro_motion"),
                                                             ("gyro_misalignment", "gyro_motion")))
        else:
            raise ValueError(f"unknown base model {base!r} for system imu: choose 'bias' or 'standard'")
        # held-out folds: contiguous blocks of poses (in time order); two halves when there are many poses,
        # else three to five blocks, so every training set keeps enough poses for the full accelerometer model
        n = len(self.problem.poses)
        self.folds = 2 if n >= 40 else 3 if n >= 15 else max(2, min(5, n // 2))
        blocks = np.array_split(np.arange(n), self.folds)
        self._fold_poses = [[k for k in range(n) if k not in set(b)] for b in blocks]

    def simulate(self, fit: Fit, seed: int, noise_fit: Fit | None = None) -> ImuIntrinsicsAudit:
        """The recording's scenario re-simulated with ``fit``'s model (:func:`simulate_like`; the noise comes from
        the static samples' own scatter, so ``noise_fit`` is not needed)."""
        return simulate_like(self, fit, seed)

    # --- catalog --------------------------------------------------------------------------------------------

    def candidates(self) -> list[Candidate]:
        s = self.sensor
        out = [Candidate("accel_scale", s, MEANINGS["accel_scale"], "accel", "orientation"),
               Candidate("accel_misalignment", s, MEANINGS["accel_misalignment"], "accel", "orientation"),
               Candidate("gyro_scale", s, MEANINGS["gyro_scale"], "gyro_motion", "rotation of each move"),
               Candidate("gyro_misalignment", s, MEANINGS["gyro_misalignment"], "gyro_motion",
                         "rotation of each move"),
               Candidate("gyro_g_sensitivity", s, MEANINGS["gyro_g_sensitivity"], "gyro", "orientation")]
        for quantity in ("accel", "gyro"):
            out.append(Candidate("bias_drift", s, MEANINGS["bias_drift"], quantity, "time"))
            for channel in self._aux_channels():

                if is_temperature(channel):
                    out.append(Candidate("bias_temperature", s, MEANINGS["bias_temperature"], quantity, channel))
                else:
                    unit = self.problem.channel_units.get(channel, "")
                    out.append(Candidate(f"channel:{channel}", s,
                                         f"{quantity} bias depends on auxiliary channel {channel} [{unit}]",
                                         quantity, channel))
        return out

    def _aux_channels(self) -> list[str]:
        """The recording's auxiliary channels (not time, not the library's derived channels)."""
        derived = {n for names in self._derived.values() for n in names}
        return [n for n in self.problem.channel_refs if n != TIME_CHANNEL and n not in derived]

    @staticmethod
    def _channel_of(c: Candidate) -> str | None:
        if c.effect == "bias_drift":
            return TIME_CHANNEL
        if c.effect == "bias_temperature" or c.effect.startswith("channel:"):
            return c.coordinate
        return None

    def _channels_of(self, c: Candidate) -> tuple[str, ...]:
        """The bias channels a candidate adds (one for a catalog channel effect, the basis for a term)."""
        if c.term is not None:
            return self._derived_channels(c.term)
        channel = self._channel_of(c)
        return (channel,) if channel else ()

    def plausible(self, candidate: Candidate, estimate: dict) -> str | None:
        return plausibility(candidate, estimate)

    def catalog_term(self, candidate: Candidate) -> tuple[str, str] | None:
        """The library term a catalog effect is: a bias linear in time or in a channel."""
        channel = self._channel_of(candidate)
        return ("time" if channel == TIME_CHANNEL else channel, "poly1") if channel else None

    # --- the generic term library ---------------------------------------------------------------------------

    def _driver_values(self) -> dict[str, tuple[dict, list[dict]]]:
        """Every driver at the static poses and at every sample of every move: (pose values, [move values])."""
        p = self.problem
        poses = {"time": np.array([q.time_s for q in p.poses])}
        moves = [{"time": np.asarray(m.time_s, dtype=float)} for m in p.moves]
        for name in self._aux_channels():
            poses[name] = np.array([q.channels[name] for q in p.poses])
            for m, values in zip(p.moves, moves):
                values[name] = np.asarray(m.channels[name], dtype=float)
        for axis, j in zip("xyz", range(3)):
            poses[f"f_{axis}"] = np.array([q.accel_mean[j] for q in p.poses])
            poses[f"w_{axis}"] = np.array([q.gyro_mean[j] for q in p.poses])
            for m, values in zip(p.moves, moves):
                values[f"f_{axis}"], values[f"w_{axis}"] = m.accel_raw[:, j], m.gyro_raw[:, j]
        poses["w_norm"] = np.linalg.norm([q.gyro_mean for q in p.poses], axis=1)
        for m, values in zip(p.moves, moves):
            values["w_norm"] = np.linalg.norm(m.gyro_raw, axis=1)
        return {"poses": poses, "moves": moves}

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        """Drivers per target: the static poses' for ``accel`` and ``gyro``, the moves' samples for
        ``gyro_motion`` (where a rate-dependent gyro error shows)."""
        poses, moves = self._drivers["poses"], self._drivers["moves"]
        units = {**self.problem.channel_units, "time": "s", **{f"f_{a}": "m s^-2" for a in "xyz"},
                 **{f"w_{a}": "rad s^-1" for a in "xyz"}, "w_norm": "rad s^-1"}
        shared = ["time", *self._aux_channels()]
        out = {}
        for target, states in STATE_DRIVERS.items():
            if target == "gyro_motion":
                if not moves:
                    continue
                values = {n: np.concatenate([m[n] for m in moves]) for n in (*shared, *states)}
            else:
                values = {n: poses[n] for n in (*shared, *states)}
            out[(self.sensor, target)] = (
                [Coordinate(n, values[n], units.get(n, ""), "time" if n == "time" else "channel",
                            solo=target != "gyro_motion") for n in shared]
                + [Coordinate(n, values[n], units[n], "state") for n in states])
        return out

    def _derived_channels(self, term: library.Term) -> tuple[str, ...]:
        """The term's basis columns as channels of the problem, at every pose and move sample (added once)."""
        if term not in self._derived:
            p = self.problem
            pose_columns = term.columns(self._drivers["poses"])
            move_columns = [term.columns(values) for values in self._drivers["moves"]]
            names = tuple(f"{term.label}#{i}" for i in range(pose_columns.shape[1]))
            for i, name in enumerate(names):
                for k, pose in enumerate(p.poses):
                    pose.channels[name] = float(pose_columns[k, i])
                for move, columns in zip(p.moves, move_columns):
                    move.channels[name] = columns[:, i]
                p.channel_refs[name] = 0.0  # the basis is centred on the driver's range; the bias takes the rest
            self._derived[term] = names
        return self._derived[term]

    def spec_for(self, effects) -> gi.IntrinsicsSpec:
        names = {c.effect for c in effects}
        accel_free = sorted((gi.ACCEL_DIAGONAL if "accel_scale" in names else ())
                            + (gi.ACCEL_OFF_DIAGONAL if "accel_misalignment" in names else ()))
        gyro_free = sorted((gi.GYRO_DIAGONAL if "gyro_scale" in names else ())
                           + (gi.GYRO_OFF_DIAGONAL if "gyro_misalignment" in names else ()))
        channels = {q: tuple(n for c in effects if QUANTITY_OF_TARGET.get(c.target) == q
                             for n in self._channels_of(c)) for q in ("accel", "gyro")}
        return gi.IntrinsicsSpec(tuple(accel_free), tuple(gyro_free), "gyro_g_sensitivity" in names,
                                 channels["accel"], channels["gyro"])

    # --- fitting --------------------------------------------------------------------------------------------

    def _train_poses(self, fold):
        if fold is None:
            return list(range(len(self.problem.poses)))
        return self._fold_poses[fold]

    def fit(self, effects, fold=None) -> Fit:
        built = gi.build_graph(self.problem, self.spec_for(effects), huber_k=None,
                               pose_indices=self._train_poses(fold))
        values = optimize(built.graph, built.values)
        return Fit(tuple(effects), built.graph, values, self._families(built, values, built.pose_indices), built)

    def extend(self, fit: Fit, candidate: Candidate):
        old_spec = fit.context
        built = gi.build_graph(self.problem, self.spec_for(fit.effects + (candidate,)), huber_k=None,
                               pose_indices=old_spec.pose_indices)
        values = gtsam.Values()
        new_columns = []
        for key in built.values.keys():
            if fit.values.exists(key) and key not in (gi.ACCEL_M, gi.GYRO_M):
                values.insert(key, _get(fit.values, key))
            elif key in (gi.ACCEL_M, gi.GYRO_M):
                values.insert(key, _get(built.values, key))  # overwritten below
            else:
                # a new block starts at its nominal value (zero slope, zero g-sensitivity): build_graph may
                # already have fitted it in its accelerometer-only stage, and the score test must start at H0
                values.insert(key, np.zeros_like(built.values.atVector(key)))
        # grown matrices: old free entries keep their fitted values, new ones start at nominal
        for key, old_keys, new_keys, nominal in (
                (gi.ACCEL_M, old_spec.accel_keys, built.accel_keys, imu.upper_triangular_entries(np.eye(3))),
                (gi.GYRO_M, old_spec.gyro_keys, built.gyro_keys, np.eye(3).ravel())):
            if not values.exists(key):
                continue
            entries = nominal.copy()
            if fit.values.exists(key):
                entries[list(old_keys.M_free)] = fit.values.atVector(key)
            values.update(key, entries[list(new_keys.M_free)])
            added = [i for i, e in enumerate(new_keys.M_free) if not fit.values.exists(key) or e not in old_keys.M_free]
            if added:
                new_columns.append((key, np.array(added)))
        for key in built.values.keys():
            if not fit.values.exists(key) and key not in (gi.ACCEL_M, gi.GYRO_M):
                new_columns.append((key, np.arange(values.atVector(key).size)))
        return built.graph, values, new_columns

    def extend_all(self, fit: Fit, candidates: list[Candidate]):
        """One graph holding every library candidate (slopes at zero) for the engine's batched score tests:
        (graph, values, each candidate's new columns)."""
        built = gi.build_graph(self.problem, self.spec_for(fit.effects + tuple(candidates)), huber_k=None,
                               pose_indices=fit.context.pose_indices)
        values = gtsam.Values()
        for key in built.values.keys():
            values.insert(key, _get(fit.values, key) if fit.values.exists(key)
                          else np.zeros_like(built.values.atVector(key)))
        slots = {"accel": dict(built.accel_keys.channels), "gyro": dict(built.gyro_keys.channels)}
        groups = [[(slots[QUANTITY_OF_TARGET[c.target]][name], np.arange(3)) for name in self._channels_of(c)]
                  for c in candidates]
        return built.graph, values, groups

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        test = [k for k in range(len(self.problem.poses)) if k not in self._fold_poses[fold]]
        return self._families(fit.context, fit.values, test)

    # --- residuals ------------------------------------------------------------------------------------------

    def _families(self, built: gi.IntrinsicsGraph, values, poses) -> list[ResidualFamily]:
        p = self.problem
        accel, gyro = built.accel(values), built.gyro(values)
        slopes = built.channel_slopes(values)
        channel_names = self._aux_channels()

        def bias_offset(quantity, deviation):
            """sum of slope x channel deviation: (3,) for a pose, (n, 3) for the samples of a move."""
            return sum((np.multiply.outer(deviation[n], slopes[quantity][n]) for n in slopes[quantity]), 0.0)

        f, up = [], []
        coords = {k: [] for k in ("time_s", "up_x", "up_y", "up_z", "f_x", "f_y", "f_z", *channel_names)}
        accel_sig, gyro_res, gyro_sig = [], [], []
        for k in poses:
            pose, dev = p.poses[k], p.pose_deviation(k)
            fk = accel.M @ (pose.accel_mean - accel.bias - bias_offset("accel", dev))
            uk = fk / np.linalg.norm(fk)
            f.append(fk)
            up.append(uk)
            accel_sig.append(float(np.sqrt(np.sum((uk * pose.accel_sigma) ** 2))))
            gyro_res.append(pose.gyro_mean - gyro.bias - bias_offset("gyro", dev) - gyro.A @ (p.gravity_m_s2 * uk))
            gyro_sig.append(pose.gyro_sigma)
            coords["time_s"].append(pose.time_s)
            for axis, value in zip(("up_x", "up_y", "up_z"), uk):
                coords[axis].append(value)
            for axis, value in zip(("f_x", "f_y", "f_z"), pose.accel_mean):  # raw, the library's drivers
                coords[axis].append(value)
            for n in channel_names:
                coords[n].append(pose.channels[n])
        coords = {k: np.asarray(v) for k, v in coords.items()}
        accel_res = (np.linalg.norm(f, axis=1) - p.gravity_m_s2)[:, None]
        families = [
            ResidualFamily(self.sensor, "accel", "m s^-2", accel_res / np.asarray(accel_sig)[:, None], accel_res,
                           coords, tuple(channel_names)),
            ResidualFamily(self.sensor, "gyro", "rad s^-1", np.asarray(gyro_res) / np.asarray(gyro_sig),
                           np.asarray(gyro_res), coords, tuple(channel_names))]
        motion, motion_sig = [], []
        mcoords = {k: [] for k in ("time_s", "rot_x", "rot_y", "rot_z", "w_x", "w_y", "w_z", "w_norm",
                                   *channel_names)}
        index = {k: i for i, k in enumerate(poses)}
        for k in poses:
            if k + 1 not in index or k >= len(p.moves):
                continue
            move, dev = p.moves[k], p.move_deviation(k)
            f_move = accel.specific_force(move.accel_raw)
            w = gyro.rate(move.gyro_raw - bias_offset("gyro", dev), f_move)
            delta_R = so3.integrate_rates(w, move.dt_s)
            motion.append(up[index[k + 1]] - delta_R.T @ up[index[k]])
            motion_sig.append(move.angle_sigma_rad)
            rot = so3.log(so3.integrate_rates(move.gyro_raw, move.dt_s))
            mcoords["time_s"].append(float(np.mean(move.time_s)))
            for axis, value in zip(("rot_x", "rot_y", "rot_z"), rot):
                mcoords[axis].append(value)
            mean_rate = np.mean(move.gyro_raw, axis=0)  # the move's mean raw rate: where rate-driven terms show
            for axis, value in zip(("w_x", "w_y", "w_z", "w_norm"), (*mean_rate, np.linalg.norm(mean_rate))):
                mcoords[axis].append(value)
            for n in channel_names:
                mcoords[n].append(float(np.mean(move.channels[n])))
        if motion:
            motion = np.asarray(motion)
            families.append(ResidualFamily(self.sensor, "gyro_motion", "rad", motion / np.asarray(motion_sig)[:, None],
                                           motion, {k: np.asarray(v) for k, v in mcoords.items()},
                                           tuple(channel_names)))
        return families

    # --- estimates in the contract's keys -------------------------------------------------------------------

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        if candidate.term is not None:
            return self._term_estimate(fit, candidate)
        built: gi.IntrinsicsGraph = fit.context
        values = fit.values
        keys = [k for k in (gi.ACCEL_M, gi.GYRO_M, gi.GYRO_A) if values.exists(k)]
        keys += [k for _, k in built.accel_keys.channels + built.gyro_keys.channels]
        factor = variance_factor(fit)
        cov = {k: c * factor for k, c in marginal_covariances(fit.graph, values, keys, "the audited effect").items()}
        effect = candidate.effect
        if effect in ("accel_scale", "accel_misalignment", "gyro_scale", "gyro_misalignment"):
            accel_like = effect.startswith("accel")
            key, free = (gi.ACCEL_M, built.accel_keys.M_free) if accel_like else (gi.GYRO_M, built.gyro_keys.M_free)
            M = built.accel(values).M if accel_like else built.gyro(values).M
            sigma = np.zeros(6 if accel_like else 9)
            sigma[list(free)] = np.sqrt(np.diag(cov[key]))
            sigma_M = imu.upper_triangular(sigma) if accel_like else sigma.reshape(3, 3)
            K = np.diag(M)
            if effect.endswith("scale"):
                # scale = 1/K - 1, so its sigma is sigma_K / K^2
                return {"scale": (1 / K - 1).tolist()}, {"scale": (np.diag(sigma_M) / K**2).tolist()}
            T, sigma_T = M / K[None, :], sigma_M / K[None, :]
            if accel_like:  # Tedaldi's T = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]]
                idx, sign = [(0, 1), (0, 2), (1, 2)], np.array([-1.0, 1.0, -1.0])
            else:  # every off-diagonal entry of the full gyro matrix, row-major
                idx, sign = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)], np.ones(6)
            return ({"angles": (sign * np.array([T[i] for i in idx])).tolist()},
                    {"angles": np.array([sigma_T[i] for i in idx]).tolist()})
        if effect == "gyro_g_sensitivity":
            return ({"matrix": values.atVector(gi.GYRO_A).tolist()},
                    {"matrix": np.sqrt(np.diag(cov[gi.GYRO_A])).tolist()})
        channel = self._channel_of(candidate)
        slot = built.accel_keys if candidate.target == "accel" else built.gyro_keys
        key = dict(slot.channels)[channel]
        unit = "m s^-2" if candidate.target == "accel" else "rad s^-1"
        per = "s" if channel == TIME_CHANNEL else self.problem.channel_units.get(channel, "")
        target = f"{self.sensor}/{candidate.target}"
        return ({"slope": values.atVector(key).tolist(), "unit": f"{unit} per {per}", "target": target},
                {"slope": np.sqrt(np.diag(cov[key])).tolist()})

    def _term_estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        """A generic term's coefficients (bias slopes of its derived channels, all axes) in the driver's units."""
        built: gi.IntrinsicsGraph = fit.context
        quantity = QUANTITY_OF_TARGET[candidate.target]
        slot = dict((built.accel_keys if quantity == "accel" else built.gyro_keys).channels)
        keys = [slot[name] for name in self._derived_channels(candidate.term)]
        joint = joint_covariance(fit.graph, fit.values, keys, "the audited term")
        coefficients = np.array([fit.values.atVector(k) for k in keys])
        coordinates = {c.name: c.values for c in self.term_coordinates()[(self.sensor, candidate.target)]}
        unit = "m s^-2" if quantity == "accel" else "rad s^-1"
        driver_unit = next(c.unit for c in self.term_coordinates()[(self.sensor, candidate.target)]
                           if c.name == candidate.term.driver)
        estimate, std = library.describe(candidate.term, coefficients, joint * variance_factor(fit), coordinates, unit,
                                         driver_unit)
        estimate["target"] = f"{self.sensor}/{candidate.target}"
        return estimate, std


def _get(values: gtsam.Values, key: int):
    """A value of any of the types this system stores."""
    for getter in (values.atUnit3, values.atVector):
        try:
            return getter(key)
        except RuntimeError:
            continue
    raise KeyError(key)


def simulate_like(system: ImuIntrinsicsAudit, fit: Fit, seed: int) -> ImuIntrinsicsAudit:
    """The recording's own scenario re-simulated with the model of ``fit``: same poses, moves and channels.

    The first pose keeps its measured up-direction; every later one is where the fitted model's calibrated
    gyro carries it, so the simulated recording is self-consistent under that model.  Raw means and samples
    get white noise with the recording's own sigmas.  A model that explains the measurement leaves, on its
    simulation, the residuals it leaves on the measurement; a model that does not, predicts too little.
    """
    rng = np.random.default_rng(seed)
    built: gi.IntrinsicsGraph = fit.context
    accel, gyro = built.accel(fit.values), built.gyro(fit.values)
    slopes = built.channel_slopes(fit.values)
    p = system.problem
    g = p.gravity_m_s2

    def offset(quantity, deviation):
        return sum((np.multiply.outer(deviation[n], slopes[quantity][n]) for n in slopes[quantity]), 0.0)

    f0 = accel.specific_force(p.poses[0].accel_mean[None] - offset("accel", p.pose_deviation(0)))[0]
    up = f0 / np.linalg.norm(f0)
    poses, moves = [], []
    for k, pose in enumerate(p.poses):
        dev = p.pose_deviation(k)
        f = g * up
        a = accel.raw_from_specific_force(f[None])[0] + offset("accel", dev) + rng.normal(0, pose.accel_sigma)
        w = gyro.raw_from_rate(np.zeros((1, 3)), f[None])[0] + offset("gyro", dev) + rng.normal(0, pose.gyro_sigma)
        poses.append(replace(pose, accel_mean=a, gyro_mean=w))
        if k < len(p.moves):
            move, mdev = p.moves[k], p.move_deviation(k)
            f_move = accel.specific_force(move.accel_raw - offset("accel", mdev))
            rates = gyro.rate(move.gyro_raw - offset("gyro", mdev), f_move)
            sample_sigma = move.angle_sigma_rad / np.sqrt(np.sum(move.dt_s**2))
            raw = gyro.raw_from_rate(rates, f_move) + offset("gyro", mdev) + rng.normal(0, sample_sigma, rates.shape)
            moves.append(replace(move, gyro_raw=raw))
            up = so3.integrate_rates(rates, move.dt_s).T @ up
    twin = object.__new__(ImuIntrinsicsAudit)
    twin.__dict__.update(system.__dict__)
    twin.problem = replace(p, poses=poses, moves=moves)
    return twin


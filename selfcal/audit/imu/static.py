"""The static-recording system for the audit: one IMU at rest in one orientation (bias and noise logs).

The recording is cut into segments of ``segment_s``; each segment's mean is one residual per axis.  Base model:
a constant bias per axis.  Generic terms (:mod:`selfcal.audit.terms`) are bias corrections by a function of time
or of an auxiliary channel, fitted as bias slopes on derived channels (the basis columns per segment); the
sensor's own outputs are not offered as drivers (a segment mean would explain its own noise).  Catalog: ``bias_drift`` (bias linear in time), ``bias_temperature`` (bias linear
in a temperature channel) and ``channel:<name>`` (any other auxiliary channel), for accelerometer and gyro.
A slowly wandering bias (random walk) looks like drift over one half of the log and fails to predict the
other half, so the held-out test keeps it out of the deterministic findings; the Allan analysis
(:mod:`selfcal.audit.noise`) names it instead.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.audit import terms as library
from selfcal.audit.engine import Candidate, Fit, ResidualFamily, variance_factor
from selfcal.audit.imu.intrinsics import MEANINGS, is_temperature
from selfcal.audit.terms import Coordinate
from selfcal.audit.noise import noise_audit
from selfcal.factors.imu import linear_bias_factor
from selfcal.core.solve import gaussian, joint_covariance, marginal_covariances, optimize
from selfcal.io.recording import ImuData

QUANTITIES = {"accel": ("m s^-2", "accel_m_s2"), "gyro": ("rad s^-1", "gyro_rad_s")}
STATIC_LOG_MAX_TILT_DEG = 2.0
NOISE_AUDIT_MIN_S = 300.0  # Allan analysis needs taus of minutes to see a bias wander


def is_static_log(data: ImuData) -> bool:
    """One orientation throughout: the gravity direction of 1 s means never leaves a 2 deg cone."""
    n = max(1, int(round(data.rate_hz)))
    m = len(data.accel_m_s2) // n
    if m < 10:
        return False
    means = data.accel_m_s2[:m * n].reshape(m, n, 3).mean(axis=1)
    directions = means / np.linalg.norm(means, axis=1, keepdims=True)
    mean = directions.mean(axis=0)
    cos = directions @ (mean / np.linalg.norm(mean))
    return bool(np.degrees(np.arccos(np.clip(cos.min(), -1, 1))) < STATIC_LOG_MAX_TILT_DEG)


class ImuStaticAudit:
    name = "imu"
    folds = 2

    def __init__(self, data: ImuData, segment_s: float = 5.0):
        self.data = data
        self.sensor = data.name
        self.base_model = "bias"
        self.base_effects = ()
        t = data.t_s
        edges = np.arange(0.0, t[-1] + segment_s, segment_s)
        seg = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(edges) - 2)
        counts = np.bincount(seg, minlength=len(edges) - 1)
        keep = counts >= max(3, 0.5 * np.median(counts))
        self.n_segments = int(keep.sum())

        def means(x):
            sums = np.stack([np.bincount(seg, weights=x[:, i], minlength=len(counts)) for i in range(x.shape[1])], 1)
            return sums[keep] / counts[keep, None]

        self.time_s = means(t[:, None])[:, 0]
        self.means = {q: means(getattr(data, attr)) for q, (_, attr) in QUANTITIES.items()}
        # sigma of a segment mean from the sample scatter about the segment means (white-noise level)
        self.sigma = {}
        for q, (_, attr) in QUANTITIES.items():
            x = getattr(data, attr)
            full = np.zeros((len(counts), 3))
            full[keep] = self.means[q]
            resid = (x - full[seg])[keep[seg]]
            self.sigma[q] = np.maximum(resid.std(axis=0), 1e-12) / np.sqrt(np.median(counts[keep]))
        self.channels = {name: means(np.asarray(v, dtype=float)[:, None])[:, 0] for name, v in data.channels.items()}
        self.channel_units = dict(data.channel_units)
        self.channels["time_s"] = self.time_s
        self.channel_units["time_s"] = "s"
        self.refs = {name: float(np.mean(v)) for name, v in self.channels.items()}
        self._derived: dict[library.Term, tuple[str, ...]] = {}
        half = len(self.time_s) // 2
        self._folds = [np.arange(half), np.arange(half, len(self.time_s))]

    def candidates(self) -> list[Candidate]:
        out = []
        for q in QUANTITIES:
            out.append(Candidate("bias_drift", self.sensor, MEANINGS["bias_drift"], q, "time"))
            for name in self.channels:
                if name == "time_s" or name in self._derived_names():
                    continue
                if is_temperature(name):
                    out.append(Candidate("bias_temperature", self.sensor, MEANINGS["bias_temperature"], q, name))
                else:
                    out.append(Candidate(f"channel:{name}", self.sensor,
                                         f"{q} bias depends on auxiliary channel {name} "
                                         f"[{self.channel_units.get(name, '')}]", q, name))
        return out

    @staticmethod
    def _channel(c: Candidate) -> str:
        return "time_s" if c.effect == "bias_drift" else c.coordinate

    def _channels_of(self, c: Candidate) -> tuple[str, ...]:
        return self._derived_channels(c.term) if c.term is not None else (self._channel(c),)

    def _keys(self, effects):
        """Bias key per quantity and (channel, key) slopes per quantity, in a fixed order."""
        keys = {q: (gtsam.symbol("b", i), []) for i, q in enumerate(QUANTITIES)}
        j = 0
        for c in effects:
            for channel in self._channels_of(c):
                keys[c.target][1].append((channel, gtsam.symbol("k", j)))
                j += 1
        return keys

    # --- the generic term library -----------------------------------------------------------------------------

    def catalog_term(self, candidate: Candidate) -> tuple[str, str] | None:
        """bias_drift is poly1 in time; bias_temperature and channel:<name> are poly1 in that channel."""
        if candidate.term is not None:
            return None
        return ("time" if candidate.effect == "bias_drift" else candidate.coordinate, "poly1")

    def _drivers(self) -> dict[str, np.ndarray]:
        return {"time": self.time_s, **{n: v for n, v in self.channels.items() if n != "time_s"
                                        and n not in self._derived_names()}}

    def _derived_names(self) -> set[str]:
        return {n for names in self._derived.values() for n in names}

    def term_coordinates(self, fit: Fit | None = None) -> dict[tuple[str, str], list[Coordinate]]:
        drivers = self._drivers()
        units = {"time": "s", **self.channel_units}
        coordinates = [Coordinate(n, v, units.get(n, ""), "time" if n == "time" else "channel")
                       for n, v in drivers.items()]
        return {(self.sensor, q): coordinates for q in QUANTITIES}

    def _derived_channels(self, term: library.Term) -> tuple[str, ...]:
        """The term's basis columns as per-segment channels (centred on the driver's range; ref 0)."""
        if term not in self._derived:
            columns = term.columns(self._drivers())
            names = tuple(f"{term.label}#{i}" for i in range(columns.shape[1]))
            for i, name in enumerate(names):
                self.channels[name] = columns[:, i]
                self.refs[name] = 0.0
            self._derived[term] = names
        return self._derived[term]

    def _graph(self, effects, rows):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for q, (bias_key, slopes) in self._keys(effects).items():
            values.insert(bias_key, self.means[q][rows].mean(axis=0))
            for _, key in slopes:
                values.insert(key, np.zeros(3))
            for r in rows:
                deviation = {name: self.channels[name][r] - self.refs[name] for name, _ in slopes}
                graph.add(linear_bias_factor(gaussian(self.sigma[q]), self.means[q][r], bias_key, slopes, deviation))
        return graph, values

    def fit(self, effects, fold=None) -> Fit:
        rows = np.arange(len(self.time_s)) if fold is None else self._folds[fold]
        graph, values = self._graph(effects, rows)
        values = optimize(graph, values)
        return Fit(tuple(effects), graph, values, self._families(effects, values, rows), {"rows": rows})

    def extend(self, fit: Fit, candidate: Candidate):
        graph, values = self._graph(fit.effects + (candidate,), fit.context["rows"])
        for key in fit.values.keys():
            values.update(key, fit.values.atVector(key))
        new_keys = [key for key in values.keys() if not fit.values.exists(key)]
        return graph, values, [(key, np.arange(3)) for key in new_keys]

    def extend_all(self, fit: Fit, candidates: list[Candidate]):
        """One graph holding every library candidate (slopes at zero): (graph, values, new columns each)."""
        effects = fit.effects + tuple(candidates)
        graph, values = self._graph(effects, fit.context["rows"])
        for key in fit.values.keys():
            values.update(key, fit.values.atVector(key))
        keys = self._keys(effects)
        groups = []
        for c in candidates:
            slot = dict(keys[c.target][1])
            groups.append([(slot[name], np.arange(3)) for name in self._channels_of(c)])
        return graph, values, groups

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        return self._families(fit.effects, fit.values, self._folds[1 - fold])

    def _families(self, effects, values, rows) -> list[ResidualFamily]:
        derived = self._derived_names()
        coords = {"time_s": self.time_s[rows], **{n: v[rows] for n, v in self.channels.items()
                                                  if n != "time_s" and n not in derived}}
        out = []
        for q, (bias_key, slopes) in self._keys(effects).items():
            predicted = values.atVector(bias_key) + sum(
                (np.multiply.outer(self.channels[n][rows] - self.refs[n], values.atVector(k)) for n, k in slopes), 0.0)
            resid = self.means[q][rows] - predicted
            out.append(ResidualFamily(self.sensor, q, QUANTITIES[q][0], resid / self.sigma[q], resid, coords,
                                      tuple(n for n in coords if n != "time_s")))
        return out

    def estimate(self, fit: Fit, candidate: Candidate) -> tuple[dict, dict]:
        keys = self._keys(fit.effects)
        if candidate.term is not None:
            slot = dict(keys[candidate.target][1])
            term_keys = [slot[n] for n in self._derived_channels(candidate.term)]
            joint = joint_covariance(fit.graph, fit.values, term_keys, "the audited term") * variance_factor(fit)
            units = {"time": "s", **self.channel_units}
            estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in term_keys]),
                                             joint, self._drivers(), QUANTITIES[candidate.target][0],
                                             units.get(candidate.term.driver, ""))
            estimate["target"] = f"{self.sensor}/{candidate.target}"
            return estimate, std
        key = dict(keys[candidate.target][1])[self._channel(candidate)]
        cov = marginal_covariances(fit.graph, fit.values, [key], candidate.effect)[key] * variance_factor(fit)
        per = self.channel_units.get(self._channel(candidate), "")
        return ({"slope": fit.values.atVector(key).tolist(), "unit": f"{QUANTITIES[candidate.target][0]} per {per}",
                 "target": f"{self.sensor}/{candidate.target}"},
                {"slope": np.sqrt(np.diag(cov)).tolist()})

    def noise_audits(self, progress=None) -> list:
        """Allan analysis of gyro and accelerometer when the log is long enough to show a bias wander."""
        data = self.data
        if data.t_s[-1] < NOISE_AUDIT_MIN_S:
            return []
        out = []
        for quantity, samples in (("gyro", data.gyro_rad_s), ("accel", data.accel_m_s2)):
            if progress:
                progress(f"Allan analysis of {data.name}/{quantity}")
            out.append(noise_audit(samples, data.rate_hz, quantity, sensor=data.name))
        return out

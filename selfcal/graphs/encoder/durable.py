"""Durable self-calibration of the encoder (patent seed 000): iSAM2 follows slowly drifting array parameters from
ordinary measurements, starting from the last calibration as a prior.

State
-----
* the code edges ``alpha_e`` (static: a graduation does not drift) -- variables, started from the calibration
  with its joint covariance as one dense Gaussian prior (edges, geometry, aperture and a0 together: their
  correlations are what makes a new reading's sigma honest, see ``docs/encoder.md``);
* the drifting array parameters at frame J: the free geometry (``p, q``) ``G_J``, the aperture ``(t-, t+)``
  ``T_J`` and the dark level ``a0`` ``Z_J``, each a random walk between frames,
  ``x_J - x_{J-1} ~ N(0, q^2 dt)`` (``BetweenFactorVector``, process noise densities in :class:`DriftModel`);
* per frame, its rotation ``beta_J`` and light profile ``c_J`` (the light level needs no random walk: it is a
  free variable of every frame already).

Every frame adds one :func:`selfcal.factors.encoder.frame_factor` on (``beta_J``, the edges it sees, ``G_J``,
``T_J``, ``c_J``, ``Z_J``) and the random-walk factors; iSAM2 updates; the frame's ML angle and the current
drift state are read with their marginal sigmas; then ``beta_J``, ``c_J`` and the previous drift state are
marginalised (``ISAM2.marginalizeLeaves``; they are eliminated first, a constrained ordering).  Every factor
touches the newest drift state, so marginalisation folds them into one marginal on (edges, drift state): the
graph's size stays bounded (one dense factor over the edges and the state plus the newest frame) however
long the run.

A frame is pre-fitted with the current parameters held fixed (:func:`selfcal.graphs.encoder.calibration.measure_frame`):
its start values for iSAM2's single Gauss-Newton step, and its flags -- a flagged frame (saturated, dark,
undecodable, residual, jump) never enters the estimator.

Physics of the drift (why these parameters): ``p`` (image scale) is a ratio of distances light source -- disk
-- array and the code radius, all of which expand with temperature (aluminium housing 23e-6/K against a glass
disk 8e-6/K: ``dp/p`` ~ 1e-5/K); ``q`` (array tilt) creeps with the mount; the aperture is the blur of an edge's
shadow (source size times the disk-array gap, which grows with temperature); the dark level ``a0`` follows the
diodes' dark current (doubling every ~7 K) and the ADC offset.  The edges are etched into the disk: a common
thermal expansion of the disk leaves angles unchanged.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.factors import encoder as fenc
from selfcal.graphs.encoder import calibration as ge
from selfcal.models import encoder as enc

log = logging.getLogger(__name__)


def G(J: int) -> int:
    """Free geometry of the array at frame J (drift state)."""
    return gtsam.symbol("G", J)


def T(J: int) -> int:
    """Aperture ``(t-, t+)`` at frame J (drift state)."""
    return gtsam.symbol("T", J)


def Z(J: int) -> int:
    """Dark level a0 at frame J (drift state)."""
    return gtsam.symbol("Z", J)


@dataclass(frozen=True)
class DriftModel:
    """Random-walk process noise of the drifting parameters (1-sigma per sqrt(second)).

    ``p_rel``: relative image scale ``dp/p``; ``q``: array tilt (dimensionless); ``aperture_rel``: relative
    ``(t-, t+)``; ``a0_counts``: dark level.  Defaults: a housing warming at up to ~1 K/min with
    ``dp/p`` ~ 1e-5/K moves ``p`` by ~2e-7/s; a random walk follows a ramp of rate ``r`` with a lag of
    ``r sigma_m / q`` against a sigma of ``sqrt(q sigma_m)`` (steady state, frame sigma ``sigma_m`` per
    second), so ``q`` is set well above ``(2 r)^(2/3) sigma_m^(1/3)`` (lag below half a sigma).
    """

    p_rel: float = 5e-6
    q: float = 2e-6
    aperture_rel: float = 1e-4
    a0_counts: float = 0.05

    def sigmas(self, geometry: np.ndarray, free: tuple[int, ...], aperture: np.ndarray, dt_s: float):
        """Process noise over ``dt_s`` of (geometry free entries, aperture, a0)."""
        root = math.sqrt(max(dt_s, 1e-9))
        g = np.array([self.p_rel * abs(geometry[0]) if i == 0 else self.q for i in free]) * root
        return g, self.aperture_rel * np.abs(aperture) * root, np.array([self.a0_counts * root])


@dataclass
class DurablePrior:
    """The last calibration of one array: values and the joint covariance of ``edge_vars``, the free
    geometry, the aperture and a0 (in that order)."""

    code: enc.Code
    edges_rad: np.ndarray               # (E,) all edges (edge 0: the gauge, a constant)
    edge_vars: list[int]                # edges with a prior (the calibration's edge variables)
    geometry: np.ndarray                # (6,)
    geometry_free: tuple[int, ...]
    aperture: np.ndarray                # (2,)
    a0: float
    noise_sigma: float                  # counts
    covariance: np.ndarray              # (len(edge_vars) + len(free) + 3,) square
    illumination_degree: int = 2
    adc_max: float | None = None
    offset_rad: float = 0.0


@dataclass
class DurableStep:
    """Output of one frame: its ML angle and the current drifting parameters, each with its 1-sigma."""

    t_ns: int
    beta_rad: float
    beta_sigma_rad: float
    flag: str
    geometry: np.ndarray                # free entries
    geometry_sigma: np.ndarray
    aperture: np.ndarray
    aperture_sigma: np.ndarray
    a0: float
    a0_sigma: float
    residual_rms: float = float("nan")  # whitened, of the pre-fit


def _dense_prior_factor(keys: list[int], dims: list[int], mean: np.ndarray, covariance: np.ndarray):
    """One Gaussian prior on several vector variables: ``e = L^-1 D^-1 (x - mean)``, ``C = D R D``, ``R = L L^T``
    (unit noise).  Linear, so its Jacobian blocks are the columns of ``L^-1 D^-1``."""
    sd = np.sqrt(np.diag(covariance))
    corr = covariance / np.outer(sd, sd)
    L = np.linalg.cholesky(0.5 * (corr + corr.T))
    W = np.linalg.solve(L, np.diag(1.0 / sd))          # whitening, (d, d)
    offsets = np.concatenate([[0], np.cumsum(dims)])
    blocks = [W[:, offsets[i]:offsets[i + 1]] for i in range(len(keys))]

    def error(this, values, H):
        x = np.concatenate([values.atVector(k) for k in keys])
        if H is not None:
            for i, block in enumerate(blocks):
                H[i] = block
        return W @ (x - mean)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(mean.size), keys, error)


class DurableEncoder:
    """Incremental (iSAM2) estimator of one array's drifting parameters and each frame's angle.

    Parameters
    ----------
    prior : the last calibration (:class:`DurablePrior`).
    drift : process noise of the random walks.
    """

    def __init__(self, prior: DurablePrior, drift: DriftModel = DriftModel()):
        self.prior = prior
        self.drift = drift
        self.code = prior.code
        self.free = tuple(prior.geometry_free)
        self.edge_keys = {e: ge.EDGE(e) for e in prior.edge_vars}
        params = gtsam.ISAM2Params()
        # start values come from a per-frame fit, so one Gauss-Newton step is enough; the variables move by a
        # tiny fraction of a diode pitch afterwards (no relinearisation needed)
        params.setRelinearizeThreshold(1e-3)
        params.relinearizeSkip = 1
        params.findUnusedFactorSlots = True
        self.isam = gtsam.ISAM2(params)
        self.J = 0                          # index of the current drift state
        self.t_last_ns: int | None = None
        self.n_frames = 0
        self.state = {"edges": prior.edges_rad.copy(), "geometry": prior.geometry.copy(),
                      "aperture": prior.aperture.copy(), "a0": float(prior.a0)}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        keys = [self.edge_keys[e] for e in prior.edge_vars] + [G(0), T(0), Z(0)]
        dims = [1] * len(prior.edge_vars) + [len(self.free), 2, 1]
        mean = np.concatenate([prior.edges_rad[prior.edge_vars], prior.geometry[list(self.free)],
                               prior.aperture, [prior.a0]])
        for e in prior.edge_vars:
            values.insert(self.edge_keys[e], np.array([prior.edges_rad[e]]))
        values.insert(G(0), prior.geometry[list(self.free)].copy())
        values.insert(T(0), prior.aperture.copy())
        values.insert(Z(0), np.array([prior.a0]))
        graph.add(_dense_prior_factor(keys, dims, mean, prior.covariance))
        self.isam.update(graph, values)
        sd = np.sqrt(np.diag(prior.covariance))[len(prior.edge_vars):]
        self._state_sigma = (sd[:len(self.free)], sd[len(self.free):len(self.free) + 2], float(sd[-1]))

    # -- one frame ------------------------------------------------------------------------------------------
    def _calibration(self) -> ge.ArrayCalibration:
        s = self.state
        return ge.ArrayCalibration(s["geometry"], self.free, s["aperture"], s["a0"], self.prior.offset_rad,
                                   self.prior.noise_sigma, self.prior.illumination_degree, self.prior.adc_max)

    def add_frame(self, t_ns: int, frame: np.ndarray) -> DurableStep:
        """Fit one frame, update the drift state, marginalise the frame; returns its angle and the state."""
        frame = np.asarray(frame, dtype=float)
        s = self.state
        pre = ge.measure_frame(frame, self.code, s["edges"], self._calibration())
        if pre.flag:
            return self._step(t_ns, float("nan"), float("nan"), pre.flag, pre.residual_rms)
        J0, J = self.J, self.J + 1
        beta = pre.beta_rad
        arr = ge.ArrayData("durable", frame[None, :], s["geometry"], s["aperture"])
        edges, active, const = ge._frame_constants(
            arr, self.code, beta, s["edges"], s["geometry"], s["aperture"],
            np.zeros(self.prior.illumination_degree + 1), s["a0"], self.prior.offset_rad)
        # light profile start: the signal is linear in it at the pre-fitted angle
        _, jac = enc.frame_signal(const.s_diodes, const.edge_alpha_rad + const.edge_wrap_rad, const.weights,
                                  beta + self.prior.offset_rad, s["geometry"], s["aperture"],
                                  np.eye(self.prior.illumination_degree + 1)[0], s["a0"])
        illumination = np.linalg.lstsq(jac.d_illumination, frame - s["a0"], rcond=None)[0]
        edge_keys = tuple(self.edge_keys.get(int(e)) if act else None for e, act in zip(edges, active))
        keys = fenc.FrameKeys(beta=ge.B(J), edges=edge_keys, geometry=G(J), geometry_free=self.free,
                              aperture=T(J), illumination=ge.ILLUMINATION(0, J), a0=Z(J))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(fenc.frame_factor(gtsam.noiseModel.Isotropic.Sigma(frame.size, self.prior.noise_sigma), frame,
                                    keys, const))
        dt = 1.0 if self.t_last_ns is None else max((int(t_ns) - self.t_last_ns) * 1e-9, 1e-6)
        sg, sa, sz = self.drift.sigmas(s["geometry"], self.free, s["aperture"], dt)
        graph.add(gtsam.BetweenFactorVector(G(J0), G(J), np.zeros(len(self.free)),
                                            gtsam.noiseModel.Diagonal.Sigmas(sg)))
        graph.add(gtsam.BetweenFactorVector(T(J0), T(J), np.zeros(2), gtsam.noiseModel.Diagonal.Sigmas(sa)))
        graph.add(gtsam.BetweenFactorVector(Z(J0), Z(J), np.zeros(1), gtsam.noiseModel.Diagonal.Sigmas(sz)))
        values.insert(ge.B(J), np.array([beta]))
        values.insert(ge.ILLUMINATION(0, J), illumination)
        values.insert(G(J), s["geometry"][list(self.free)].copy())
        values.insert(T(J), s["aperture"].copy())
        values.insert(Z(J), np.array([s["a0"]]))
        leaves = [ge.B(J), ge.ILLUMINATION(0, J), G(J0), T(J0), Z(J0)]
        update = gtsam.ISAM2UpdateParams()
        # the keys to marginalise after this frame are eliminated first (leaves of the Bayes tree)
        constrained = gtsam.KeyGroupMap()
        for k in leaves:
            constrained.insert2(k, 0)
        for k in list(self.edge_keys.values()) + [G(J), T(J), Z(J)]:
            constrained.insert2(k, 1)
        update.constrainedKeys = constrained
        self.isam.update(graph, values, update)
        estimate = self.isam.calculateEstimate()
        beta_hat = estimate.atVector(ge.B(J))[0]
        # one joint marginal (beta_J and the drift state): each marginal costs an elimination of the root clique
        kv = gtsam.KeyVector()
        for k in (ge.B(J), G(J), T(J), Z(J)):
            kv.append(k)
        sd = np.sqrt(np.diag(self.isam.jointMarginalCovariance(kv).fullMatrix()))
        self._state_sigma = (sd[1:1 + len(self.free)], sd[1 + len(self.free):3 + len(self.free)], float(sd[-1]))
        self.J = J
        self.t_last_ns = int(t_ns)
        self.n_frames += 1
        s["geometry"] = s["geometry"].copy()
        s["geometry"][list(self.free)] = estimate.atVector(G(J))
        s["aperture"] = estimate.atVector(T(J))
        s["a0"] = float(estimate.atVector(Z(J))[0])
        for e, key in self.edge_keys.items():
            s["edges"][e] = estimate.atVector(key)[0]
        step = self._step(t_ns, float(np.remainder(beta_hat, 2 * math.pi)), float(sd[0]), "", pre.residual_rms)
        kl = gtsam.KeyList()
        for k in leaves:
            kl.push_back(k)
        self.isam.marginalizeLeaves(kl)
        return step

    def _step(self, t_ns, beta, beta_sigma, flag, rms) -> DurableStep:
        s = self.state
        sg, st, sz = self._state_sigma
        return DurableStep(int(t_ns), beta, beta_sigma, flag, s["geometry"][list(self.free)].copy(), sg.copy(),
                           s["aperture"].copy(), st.copy(), s["a0"], sz, rms)

    # -- the updated calibration -----------------------------------------------------------------------------
    def posterior(self) -> tuple[np.ndarray, np.ndarray]:
        """Current values and joint covariance of (edge_vars, free geometry, aperture, a0): the prior's layout,
        so the result is the next calibration."""
        keys = [self.edge_keys[e] for e in self.prior.edge_vars] + [G(self.J), T(self.J), Z(self.J)]
        kv = gtsam.KeyVector()
        for k in keys:
            kv.append(k)
        cov = self.isam.jointMarginalCovariance(kv).fullMatrix()
        s = self.state
        mean = np.concatenate([s["edges"][self.prior.edge_vars], s["geometry"][list(self.free)], s["aperture"],
                               [s["a0"]]])
        return mean, cov

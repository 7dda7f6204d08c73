"""Baseline: the encoder self-calibration of patent seed 000 carried out without the ML fit (no factor graph).

What the patent gives besides the ML estimation (CN1500202, Leica Geosystems, "Calibration method for a
measuring instrument", J. Weilenmann, priority 2001-03-31):

* decoding of each signal vector: the bars imaged on the array, identified through the l-bit window of the
  m-sequence (claim 4);
* start values (its eq. 15): the position of each bar's image from the signal by interpolation (maximum,
  centre or centroid of the peak; here: the half-level crossings of each edge, linearly interpolated between
  diodes), the theoretical edge angles ``2 pi i / m`` and nominal ``p, q``; the disk position from the image
  coordinates through the solution (1) of formula (0), ``beta = alpha + arctan z - arcsin(z'/sqrt(1+z^2))``.

Taken as a calibration procedure by itself (what a user without the ML machinery would do): alternate
``beta_J = mean_e (alpha_e - phi(s_eJ))`` and ``alpha_e = mean_J (beta_J + phi(s_eJ))``, with ``p, q``
re-fitted by least squares on the same crossings, the gauge fixed as in the library (edge 0 nominal).  A new
position is then measured as ``mean_e (alpha_e - phi(s_e))`` over its crossings.  Pure numpy on the model
module, so it stays an independent reference for the graph.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from selfcal.models import encoder as enc


@dataclass
class PatentCalibration:
    edges_rad: np.ndarray       # (E,) with edge 0 at its nominal angle (gauge)
    beta_rad: np.ndarray        # (N,), NaN for frames that did not decode
    geometry: np.ndarray        # (6,) (p, q re-fitted, u..y zero)
    flags: list[str]
    iterations: int


def _crossings(frames, code, geometry, adc_max, noise_sigma, edge_alpha=None):
    decoded = [enc.decode_frame(f, code, geometry, edge_alpha, adc_max=adc_max, noise_sigma=noise_sigma)
               for f in frames]
    J_idx, e_idx, s_obs, wrap = [], [], [], []
    for J, d in enumerate(decoded):
        if not d.ok:
            continue
        J_idx.append(np.full(d.edges.size, J))
        e_idx.append(d.edges)
        s_obs.append(d.edge_s)
    if not J_idx:
        return decoded, np.array([], int), np.array([], int), np.array([])
    return decoded, np.concatenate(J_idx), np.concatenate(e_idx), np.concatenate(s_obs)


def _wrapped(x):
    return np.remainder(x + math.pi, 2 * math.pi) - math.pi


def patent_calibration(frames: np.ndarray, code: enc.Code, geometry_nominal, adc_max=None, noise_sigma=None,
                       iterations: int = 300) -> PatentCalibration:
    """Self-calibration from decoded crossings by alternating averages (the patent's start values, iterated)."""
    geometry = np.array(geometry_nominal, dtype=float)
    decoded, J, e, s = _crossings(frames, code, geometry, adc_max, noise_sigma)
    N = len(frames)
    alpha = code.nominal_edge_angles().copy()
    beta = np.array([d.beta_rad if d.ok else np.nan for d in decoded])
    nominal0 = alpha[0]
    for _ in range(iterations):
        phi = enc.image_angle(s, geometry)
        # beta_J = mean over the frame's edges of alpha_e - phi  (angles near each other: average the wrapped
        # differences to the current value)
        d_beta = _wrapped(alpha[e] - phi - beta[J])
        beta_new = beta.copy()
        sums = np.bincount(J, d_beta, minlength=N)
        counts = np.bincount(J, minlength=N)
        used = counts > 0
        beta_new[used] += sums[used] / counts[used]
        beta = beta_new
        d_alpha = _wrapped(beta[J] + phi - alpha[e])
        sums = np.bincount(e, d_alpha, minlength=code.n_edges)
        counts = np.bincount(e, minlength=code.n_edges)
        seen = counts > 0
        alpha[seen] += sums[seen] / counts[seen]
        shift = alpha[0] - nominal0   # gauge: edge 0 nominal
        alpha -= shift
        beta -= shift
        # scale and perspective: one Gauss-Newton step of sum (alpha_e - beta_J - phi(s; p, q))^2 over p, q
        p, q = geometry[0], geometry[1]
        r = _wrapped(alpha[e] - beta[J] - enc.image_angle(s, geometry))
        z = p * s / (1 - q * s)
        dphi_dz = -1.0 / (1 + z * z)
        G = np.column_stack([dphi_dz * s / (1 - q * s), dphi_dz * p * s * s / (1 - q * s) ** 2])
        geometry[:2] += np.linalg.lstsq(G, r, rcond=None)[0]
    flags = [d.flag for d in decoded]
    return PatentCalibration(alpha, np.where(np.isfinite(beta), np.remainder(beta, 2 * math.pi), np.nan), geometry,
                             flags, iterations)


def patent_measure(frame: np.ndarray, code: enc.Code, calibration: PatentCalibration, adc_max=None,
                   noise_sigma=None) -> tuple[float, str]:
    """Angle of one new frame with the baseline's edges and scale: (beta, flag); NaN with the flag if undecodable."""
    d = enc.decode_frame(frame, code, calibration.geometry, adc_max=adc_max, noise_sigma=noise_sigma)
    if not d.ok:
        return float("nan"), d.flag
    phi = enc.image_angle(d.edge_s, calibration.geometry)
    alpha = calibration.edges_rad[d.edges]
    ref = alpha[0] - phi[0]
    return float(np.remainder(ref + np.mean(_wrapped(alpha - phi - ref)), 2 * math.pi)), d.flag

"""GTSAM factor for the encoder's signal vectors: a thin adapter around :func:`selfcal.models.encoder.frame_signal`.

One :class:`gtsam.CustomFactor` per recorded frame, with an n-dimensional residual ``model - measured`` (counts)
and analytic Jacobians, on the variables the frame sees.  Variable kinds (all plain vectors, so the tangent is
addition):

  ``beta``          (1)  disk rotation of the frame, rad
  ``alpha_e``       (1)  angle of code edge e, rad; the gauge edge is a constant, not a variable
  ``geometry``      (k)  the free entries of ``(p, q, u, v, x, y)`` of the frame's array
  ``eccentricity``  (2)  code-centre offset ``(eps_x, eps_y)`` (code radii): ``u += -kappa eps_y``,
                         ``v += kappa eps_x`` with the array's geometry factor ``kappa`` (1 for the standard layout)
  ``aperture``      (2)  ``(t-, t+)``
  ``illumination``  (d+1) Legendre coefficients of the frame's light profile, counts
  ``a0``            (1)  dark level, counts
  ``offset``        (1)  array offset: the array sees ``beta + offset`` (arrays 1..k)
  ``temperature``   (1)  relative scale per degC: ``p -> p (1 + k (T - T_ref))``
  ``gain``          (n)  per-diode gain (PRNU)
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.models import encoder as enc


@dataclass(frozen=True)
class FrameKeys:
    """Keys of one frame's variables; ``None`` = held at the value in :class:`FrameConstants`."""

    beta: int
    edges: tuple[int | None, ...]   # one per edge of the frame (None: constant)
    geometry: int | None = None
    geometry_free: tuple[int, ...] = (0, 1)
    aperture: int | None = None
    illumination: int | None = None
    a0: int | None = None
    offset: int | None = None
    eccentricity: int | None = None
    temperature: int | None = None
    gain: int | None = None


@dataclass(frozen=True)
class FrameConstants:
    """Values of the frame's inputs that are not variables (or the nominal value of those that are)."""

    s_diodes: np.ndarray
    weights: np.ndarray             # (E_f,) edge weights w_e
    edge_alpha_rad: np.ndarray      # (E_f,) value of constant edges (and of all edges, nominally)
    edge_wrap_rad: np.ndarray       # (E_f,) multiple of 2 pi added to unwrap each edge near beta
    geometry: np.ndarray            # (6,)
    aperture: np.ndarray            # (2,)
    illumination: np.ndarray        # (d+1,)
    a0: float
    offset_rad: float = 0.0
    kappa: float = 1.0              # eccentricity geometry factor of this array
    temperature_deviation_degC: float = 0.0
    gain: np.ndarray | None = None


def _vec(values, key, default):
    return values.atVector(key) if key is not None else default


def frame_inputs(values: gtsam.Values, keys: FrameKeys, const: FrameConstants):
    """(alpha (E_f,), beta, geometry (6,), aperture, illumination, a0, gain, p_factor) at ``values``."""
    alpha = np.array([values.atVector(k)[0] if k is not None else a
                      for k, a in zip(keys.edges, const.edge_alpha_rad)]) + const.edge_wrap_rad
    beta = values.atVector(keys.beta)[0] + (values.atVector(keys.offset)[0] if keys.offset is not None
                                            else const.offset_rad)
    geometry = const.geometry.copy()
    if keys.geometry is not None:
        geometry[list(keys.geometry_free)] = values.atVector(keys.geometry)
    if keys.eccentricity is not None:
        eps = values.atVector(keys.eccentricity)
        geometry[2] += -const.kappa * eps[1]
        geometry[3] += const.kappa * eps[0]
    p_factor = 1.0
    if keys.temperature is not None:
        p_factor = 1.0 + values.atVector(keys.temperature)[0] * const.temperature_deviation_degC
        geometry[0] *= p_factor
    return (alpha, beta, geometry, _vec(values, keys.aperture, const.aperture),
            _vec(values, keys.illumination, const.illumination),
            values.atVector(keys.a0)[0] if keys.a0 is not None else const.a0,
            _vec(values, keys.gain, const.gain), p_factor)


def frame_factor(noise: gtsam.noiseModel.Base, measured: np.ndarray, keys: FrameKeys,
                 const: FrameConstants, offset_columns=()) -> gtsam.CustomFactor:
    """``e = frame_signal(...) + sum_c k_c phi_c - measured`` for one recorded frame (n residuals, counts).

    ``offset_columns`` ``(key, phi (n,))``: a signal offset ``k phi`` per diode (``k`` a Vector1, counts per unit of
    the basis function ``phi`` of a driver: the audit's generic terms).

    Jacobians: the model's, chained through ``beta + offset``, the free geometry entries, the eccentricity map
    (``du/deps_y = -kappa``, ``dv/deps_x = kappa``) and the temperature scale (``dp/dk = p0 dT``).
    """
    measured = np.asarray(measured, dtype=float)
    edge_keys = [k for k in keys.edges if k is not None]
    edge_columns = [i for i, k in enumerate(keys.edges) if k is not None]
    ordered = [keys.beta] + edge_keys + [k for k in (keys.geometry, keys.aperture, keys.illumination, keys.a0,
                                                     keys.offset, keys.eccentricity, keys.temperature, keys.gain)
                                         if k is not None]
    terms = [(key, np.asarray(phi, dtype=float)) for key, phi in offset_columns]
    ordered += [key for key, _ in terms]

    def error(this, values, H):
        alpha, beta, geometry, aperture, illumination, a0, gain, p_factor = frame_inputs(values, keys, const)
        signal, jac = enc.frame_signal(const.s_diodes, alpha, const.weights, beta, geometry, aperture,
                                       illumination, a0, gain, jacobians=H is not None)
        if H is not None:
            blocks = [jac.d_beta[:, None]] + [jac.d_alpha[:, [i]] for i in edge_columns]
            if keys.geometry is not None:
                dg = jac.d_geometry[:, list(keys.geometry_free)].copy()
                if 0 in keys.geometry_free:  # d/dp0 of p = p0 (1 + k dT)
                    dg[:, list(keys.geometry_free).index(0)] *= p_factor
                blocks.append(dg)
            if keys.aperture is not None:
                blocks.append(jac.d_aperture)
            if keys.illumination is not None:
                blocks.append(jac.d_illumination)
            if keys.a0 is not None:
                blocks.append(jac.d_a0[:, None])
            if keys.offset is not None:
                blocks.append(jac.d_beta[:, None])
            if keys.eccentricity is not None:
                blocks.append(np.column_stack([const.kappa * jac.d_geometry[:, 3], -const.kappa * jac.d_geometry[:, 2]]))
            if keys.temperature is not None:
                blocks.append(jac.d_geometry[:, [0]] * (geometry[0] / p_factor) * const.temperature_deviation_degC)
            if keys.gain is not None:
                blocks.append(np.diag(jac.d_gain))
            blocks += [phi[:, None] for _, phi in terms]
            for i, block in enumerate(blocks):
                H[i] = block
        return signal + sum((phi * values.atVector(key)[0] for key, phi in terms), np.zeros(len(measured))) - measured

    return gtsam.CustomFactor(noise, ordered, error)


def linear_constraint_factor(noise: gtsam.noiseModel.Base, key: int, matrix: np.ndarray) -> gtsam.CustomFactor:
    """``e = M x`` on one vector variable: a (soft) linear constraint, e.g. PRNU orthogonal to the illumination
    basis (a gain pattern shaped like the light profile is the light profile)."""
    M = np.asarray(matrix, dtype=float)

    def error(this, values, H):
        if H is not None:
            H[0] = M
        return M @ values.atVector(key)

    return gtsam.CustomFactor(noise, [key], error)

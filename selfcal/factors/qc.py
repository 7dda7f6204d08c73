"""Sphere-target factors around :mod:`selfcal.models.qc`: all returns of one scene on one sphere.

Keys: the scene's sphere centre ``Vector3`` (sensor frame, m); optional ``Vector1`` offsets added to the nominal
radius (the common radius error, the scene's own radius deviation); an optional ``Vector1`` range offset (m);
optional ``Vector1`` coefficients of the audit's generic terms, each with its basis column over the returns.
"""
from __future__ import annotations

import gtsam
import numpy as np

from selfcal.models import qc


def sphere_returns_factor(noise, points_S_m, center_key: int, nominal_radius_m: float, radius_keys=(),
                          range_offset_key: int | None = None, term_columns=()) -> gtsam.CustomFactor:
    """Range residuals (N) of one scene's returns (:func:`selfcal.models.qc.range_residuals`) on a sphere of
    radius ``R0 + sum dR_k + sum_j k_j phi_j``.

    ``radius_keys``: keys of radius offsets (each dR_k adds to the radius of every return);
    ``term_columns``: ``(key, phi (N,))`` pairs, a radius varying over the returns as ``k phi`` (m per unit).
    """
    p = np.asarray(points_S_m, dtype=float)
    n = len(p)
    terms = [(key, np.asarray(phi, dtype=float)) for key, phi in term_columns]
    keys = [center_key, *radius_keys] + ([range_offset_key] if range_offset_key is not None else [])
    keys += [key for key, _ in terms]
    minus_one = -np.ones((n, 1))

    def error(this, values, H):
        radius = nominal_radius_m + sum(values.atVector(k)[0] for k in radius_keys)
        radius = radius + sum((phi * values.atVector(k)[0] for k, phi in terms), np.zeros(n))
        b = values.atVector(range_offset_key)[0] if range_offset_key is not None else 0.0
        e, de_dc, de_dR = qc.range_residuals(p, values.atVector(center_key), radius, b, with_jacobians=True)
        if H is not None:
            blocks = [de_dc] + [de_dR[:, None]] * len(radius_keys)
            blocks += [minus_one] if range_offset_key is not None else []
            blocks += [(de_dR * phi)[:, None] for _, phi in terms]
            for slot, block in enumerate(blocks):
                H[slot] = block
        return e

    return gtsam.CustomFactor(noise, keys, error)

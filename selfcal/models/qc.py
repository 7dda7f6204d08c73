"""A sphere target scanned by a ranging sensor (a LiDAR): the range residual of each return (numpy only).

Frame S is the sensor's: origin at its range zero point, points ``p_S`` in m.  A return is a range ``rho = |p|``
measured along a ray ``u = p / |p|`` whose direction the scanner knows far better than the range (encoder
angles against millimetres of range noise): the range is the measurement, the ray is not.  Model of one return
on a sphere of centre ``c_S`` and radius ``R``, the sensor reading every range ``b`` too long:

    m^2 = |c|^2 - (u . c)^2                (squared distance of the ray from the centre)
    s = sqrt(R^2 - m^2) = R cos(i)          (i: the incidence angle at which the ray meets the sphere)
    rho_hat = u . c - s + b                 (first intersection, plus the offset)
    e = rho - rho_hat                       (range residual, m; zero on exact data)

Derivatives: ``de/dc = -u - (c - (u . c) u) / s``, ``de/dR = R / s = 1 / cos(i)``, ``de/db = -1``.

Why the range and not the radial distance ``|p - c| - R``: the noise is along the ray, so a radial residual
carries it through the data's own geometry (``-delta cos(i)``), and a model free to bend the surface (a radius
varying with incidence or range) lowers its sum of squares by turning the surface towards the rays, where the
noise projects less: on simulated caps that bias reached several sigma.  In range, the noise is the residual.

Near the rim the intersection is singular (``s -> 0``): returns beyond ``MAX_INCIDENCE_RAD`` are left out of the
audit (:mod:`selfcal.graphs.qc`; real scanners mix rim returns with the background there anyway), and ``s`` is
floored at ``R cos(89 deg)`` so that an iterate that misses a ray still has a finite residual.

A constant range offset is not a radius error: it is a constant in every range, which a centre shift along the
view axis nearly absorbs (exactly so for parallel rays); what separates it from that shift is the spread of the
rays, ``m^2 / (|c| s)``, so it shows as an apparent radius that falls off as ``1 / |c|`` across scenes at
different ranges.
"""
from __future__ import annotations

import numpy as np

MAX_INCIDENCE_RAD = np.radians(80.0)  # returns beyond are left out of the audit
GRAZING_COS = np.cos(np.radians(89.0))  # s floored at R cos(89 deg): a numerical guard, far beyond that cut


def rays(points_S_m) -> np.ndarray:
    """Unit rays ``u = p / |p|`` (N, 3) from the sensor to each return."""
    p = np.asarray(points_S_m, dtype=float)
    return p / np.maximum(np.linalg.norm(p, axis=1), np.finfo(float).tiny)[:, None]


def range_residuals(points_S_m, center_S_m, radius_m, range_offset_m: float = 0.0, with_jacobians: bool = False):
    """Range residuals ``e = rho - rho_hat`` (N,), m; with Jacobians ``(e, de/dc (N, 3), de/dR (N,))``
    (``de/db = -1``).  ``radius_m`` may be a scalar or one radius per return (N,)."""
    p = np.asarray(points_S_m, dtype=float)
    rho = np.linalg.norm(p, axis=1)
    u = p / np.maximum(rho, np.finfo(float).tiny)[:, None]
    c = np.asarray(center_S_m, dtype=float)
    R = np.broadcast_to(np.asarray(radius_m, dtype=float), rho.shape)
    uc = u @ c
    floor = R * GRAZING_COS
    s2 = R**2 - (c @ c - uc**2)
    clamped = s2 < floor**2
    s = np.where(clamped, floor, np.sqrt(np.maximum(s2, 0.0)))
    e = rho - (uc - s + range_offset_m)
    if not with_jacobians:
        return e
    live = (~clamped)[:, None]
    de_dc = -u - np.where(live, (c - uc[:, None] * u) / s[:, None], 0.0)
    # a clamped s = R cos(max) still grows with R
    de_dR = np.where(clamped, GRAZING_COS, R / s)
    return e, de_dc, de_dR


def incidence_angle_rad(points_S_m, center_S_m, radius_m: float) -> np.ndarray:
    """Angle (N,), rad, at which each ray meets the sphere: 0 head-on, pi/2 grazing (and for rays that miss it).

    From the ray's direction alone, ``sin i = |u x c| / R`` (the ray's distance from the centre over the radius),
    not from the return's position: a return's own range noise must not set its incidence (and with it its
    weight, or a driver of the audit), or noise that lengthens a range would also steepen its incidence."""
    u = rays(points_S_m)
    miss = np.linalg.norm(np.cross(u, np.asarray(center_S_m, dtype=float)), axis=1)
    return np.arcsin(np.clip(miss / radius_m, 0.0, 1.0))

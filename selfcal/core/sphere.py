"""Sphere model: radial residuals, least-squares fit with covariance, robust (RANSAC) detection, coverage.

A sphere is its centre ``c`` (m, in the frame of the points) and radius ``R`` (m).  A point ``p`` on the
surface obeys the residual equation (the sphere-surface constraint of patent 001, |T p - O| - R = 0)::

    e(p) = |p - c| - R                    (m; > 0 outside the sphere)
    de/dc = -u,  de/dp = u,  de/dR = -1   with u = (p - c) / |p - c|

Fit: the algebraic (Kasa) form ``|p|^2 = 2 c.p + (R^2 - |c|^2)`` is linear in ``(c, R^2 - |c|^2)`` and gives the
start; scipy's Levenberg-Marquardt then minimises ``sum e_i^2`` (the geometric fit).  The covariance is
``s^2 (J^T J)^-1`` with ``s`` the given point sigma or the residual scatter ``sqrt(sum e^2 / (n - k))``.

Coverage: a scanner sees a sphere from one side; the visible patch is a cap whose half-angle ``theta`` (seen
from the centre) shrinks as the scanner's view narrows.  For points spread uniformly over a cap the mean of
the unit vectors ``u`` has length ``rho = (1 + cos theta) / 2``, so ``theta = arccos(2 rho - 1)`` is the
equivalent cap half-angle (180 deg: the whole sphere, 90 deg: a hemisphere).  A small cap makes the radius and
the centre along the view axis nearly indistinguishable (their correlation tends to 1): the size of such a
sphere cannot be measured, only its centre given a known radius.

References
----------
I. Kasa, "A circle fitting procedure and its error analysis", IEEE Trans. Instrum. Meas. 25 (1976) 8-14.
M. A. Fischler, R. C. Bolles, "Random sample consensus", Comm. ACM 24 (1981) 381-395.
P. H. S. Torr, A. Zisserman, "MLESAC" (the truncated quadratic cost used to score hypotheses), CVIU 78 (2000).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from selfcal.core.errors import SelfcalError

log = logging.getLogger(__name__)

#: below this equivalent cap half-angle a sphere counts as "seen from one side only": a hemisphere
#: (90 deg) still separates radius and centre (correlation ~0.9), a 60 deg cap much less so (~0.98).
ONE_SIDED_CAP_DEG = 60.0


class SphereNotFoundError(SelfcalError):
    """No sphere in the points (too few points, no consensus, radius out of bounds): a data problem."""


@dataclass
class SphereCoverage:
    """How much of a sphere the points see, from the centre.

    Attributes
    ----------
    mean_direction : np.ndarray
        Unit vector (3,) from the centre toward the mean of the points (toward the scanner, for one view).
    cap_half_angle_deg : float
        Equivalent cap half-angle from the mean resultant length (180: whole sphere, 90: hemisphere).
    solid_angle_fraction : float
        Fraction of 48 equal-area direction cells (4 bands x 12 sectors about the mean direction) holding at
        least a fifth of the points a uniformly covered sphere would put there.
    """

    mean_direction: np.ndarray
    cap_half_angle_deg: float
    solid_angle_fraction: float

    def one_sided(self, min_cap_deg: float = ONE_SIDED_CAP_DEG) -> bool:
        """True when the visible cap is narrower than ``min_cap_deg`` (size no longer measurable)."""
        return bool(self.cap_half_angle_deg < min_cap_deg)


@dataclass
class SphereFit:
    """A fitted sphere with its uncertainty.

    Attributes
    ----------
    center_m : np.ndarray
        Centre (3,), m, in the frame of the points.
    radius_m : float
        Radius, m (the given radius when it was known).
    covariance : np.ndarray
        (4, 4) for (cx, cy, cz, r), or (3, 3) for the centre when the radius was known; m^2.
    rms_m : float
        RMS of the radial residuals of the points used (the inliers), m.
    n_points : int
        Number of points used.
    coverage : SphereCoverage or None
        Angular coverage of the points used (see :func:`sphere_coverage`).
    radius_known : bool
        The radius was given, not estimated.
    form_error_m : float
        Range (max - min) of the radial residuals: the "probing error of form" of VDI/VDE 2634-2, m.
    """

    center_m: np.ndarray
    radius_m: float
    covariance: np.ndarray
    rms_m: float
    n_points: int
    coverage: SphereCoverage | None = None
    radius_known: bool = False
    form_error_m: float = float("nan")

    @property
    def center_sigma_m(self) -> np.ndarray:
        """1-sigma of the centre coordinates (3,), m."""
        return np.sqrt(np.diag(self.covariance)[:3])

    @property
    def radius_sigma_m(self) -> float:
        """1-sigma of the radius, m (0 when the radius was given)."""
        return 0.0 if self.radius_known else float(np.sqrt(self.covariance[3, 3]))


def sphere_residuals_m(points_m, center_m, radius_m) -> np.ndarray:
    """Radial residuals ``|p - c| - R`` (N,), m, of points (N, 3) against a sphere."""
    return np.linalg.norm(np.asarray(points_m, dtype=float) - np.asarray(center_m, dtype=float), axis=1) - radius_m


def sphere_residuals_and_jacobians(points_m, center_m, radius_m):
    """Residuals ``e = |p - c| - R`` (N,) and their derivatives.

    Returns
    -------
    e : np.ndarray
        (N,) m.
    de_dp : np.ndarray
        (N, 3) unit vectors ``u = (p - c) / |p - c|`` (derivative w.r.t. the point).
    de_dc : np.ndarray
        (N, 3) ``-u`` (derivative w.r.t. the centre); ``de/dR = -1``.
    """
    d = np.asarray(points_m, dtype=float) - np.asarray(center_m, dtype=float)
    dist = np.linalg.norm(d, axis=1)
    u = d / np.maximum(dist, np.finfo(float).tiny)[:, None]
    return dist - radius_m, u, -u


def _check_points(points_m, minimum: int) -> np.ndarray:
    pts = np.asarray(points_m, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {pts.shape}")
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        raise SphereNotFoundError(f"{np.count_nonzero(~finite)} of {len(pts)} points are not finite (NaN/inf)")
    if len(pts) < minimum:
        raise SphereNotFoundError(f"{len(pts)} points: a sphere needs at least {minimum}")
    return pts


def algebraic_sphere(points_m) -> tuple[np.ndarray, float]:
    """Kasa's linear fit: centre (3,) and radius from ``|p|^2 = 2 c.p + d``, ``d = R^2 - |c|^2``.

    Points are centred first (the normal equations are then well scaled far from the origin).
    """
    pts = np.asarray(points_m, dtype=float)
    mean = pts.mean(axis=0)
    q = pts - mean
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    # normal equations by einsum (4x4; well conditioned once centred): a threaded BLAS on tall-thin products
    # is slow on a busy machine, and these clouds are tall and thin
    try:
        sol = np.linalg.solve(np.einsum("ni,nj->ij", A, A), np.einsum("ni,n->i", A, np.einsum("ij,ij->i", q, q)))
    except np.linalg.LinAlgError as err:
        raise SphereNotFoundError("the points do not determine a sphere (collinear or coplanar)") from err
    r2 = sol[3] + sol[:3] @ sol[:3]
    if not np.isfinite(r2) or r2 <= 0.0:
        raise SphereNotFoundError("the points do not determine a sphere (degenerate algebraic fit)")
    return sol[:3] + mean, float(np.sqrt(r2))


def sphere_coverage(points_m, center_m) -> SphereCoverage:
    """Angular coverage of points on a sphere about ``center_m`` (see module docstring)."""
    d = np.asarray(points_m, dtype=float) - np.asarray(center_m, dtype=float)
    u = d / np.maximum(np.linalg.norm(d, axis=1), np.finfo(float).tiny)[:, None]
    mean = u.mean(axis=0)
    rho = float(np.linalg.norm(mean))
    axis = mean / rho if rho > 1e-12 else np.array([0.0, 0.0, 1.0])
    theta = float(np.degrees(np.arccos(np.clip(2.0 * rho - 1.0, -1.0, 1.0))))
    # equal-area cells about the mean direction: 4 bands equal in cos(polar angle), 12 azimuth sectors each
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    band = np.clip(((1.0 - np.einsum("ij,j->i", u, axis)) / 2.0 * 4).astype(int), 0, 3)
    azimuth = np.arctan2(np.einsum("ij,j->i", u, e2), np.einsum("ij,j->i", u, e1))
    sector = np.clip(((azimuth + np.pi) / (2 * np.pi) * 12).astype(int), 0, 11)
    # a cell counts when it holds a fifth of a uniform sphere's share: a few stragglers past the rim of a cap
    # (noise, a slightly tilted mean direction) do not inflate the coverage
    counts = np.bincount(band * 12 + sector, minlength=48)
    occupied = np.count_nonzero(counts >= max(1.0, 0.2 * len(u) / 48.0))
    return SphereCoverage(mean_direction=axis, cap_half_angle_deg=theta, solid_angle_fraction=occupied / 48.0)


def fit_sphere(points_m, radius_m: float | None = None, sigma_m: float | None = None) -> SphereFit:
    """Geometric least-squares sphere fit (algebraic start, Levenberg-Marquardt refit) with covariance.

    Parameters
    ----------
    points_m : array (N, 3)
        Points on the surface, m.  All are used: remove outliers first (:func:`ransac_sphere`).
    radius_m : float, optional
        Known radius: only the centre is estimated (3 unknowns).
    sigma_m : float, optional
        1-sigma of a point's radial noise.  Without it the covariance is scaled by the residual scatter
        ``sum e^2 / (N - k)``.

    Returns
    -------
    SphereFit

    Raises
    ------
    SphereNotFoundError
        Too few (or non-finite) points, or points that determine no sphere (collinear, coplanar).
    """
    k = 3 if radius_m is not None else 4
    pts = _check_points(points_m, k + 1)
    center0, radius0 = algebraic_sphere(pts)
    if radius_m is not None:
        # known radius: slide the algebraic centre along the view axis until the mean distance matches it
        mean_dir = pts.mean(axis=0) - center0
        mean_dir /= max(np.linalg.norm(mean_dir), np.finfo(float).tiny)
        center0 = center0 + mean_dir * (np.linalg.norm(pts - center0, axis=1).mean() - radius_m)
        radius0 = float(radius_m)

    def residuals(x):
        return sphere_residuals_m(pts, x[:3], x[3] if k == 4 else radius_m)

    def jacobian(x):
        _, _, de_dc = sphere_residuals_and_jacobians(pts, x[:3], x[3] if k == 4 else radius_m)
        return de_dc if k == 3 else np.column_stack([de_dc, -np.ones(len(pts))])

    x0 = np.r_[center0, radius0] if k == 4 else np.asarray(center0, dtype=float)
    # scipy's MINPACK LM needs N >= k; x_scale='jac' makes the steps scale-invariant (millimetre or km scenes)
    sol = least_squares(residuals, x0, jac=jacobian, method="lm", x_scale="jac")
    J = jacobian(sol.x)
    e = sol.fun
    dof = len(pts) - k
    s2 = sigma_m**2 if sigma_m is not None else (float(np.einsum("i,i->", e, e)) / dof if dof > 0 else np.inf)
    JtJ = np.einsum("ni,nj->ij", J, J)
    if np.linalg.cond(JtJ) > 1e14:
        raise SphereNotFoundError(f"{len(pts)} points do not determine a sphere (rank-deficient fit: "
                                  "points on a plane or a line?)")
    cov = s2 * np.linalg.inv(JtJ)
    center = sol.x[:3]
    radius = float(sol.x[3]) if k == 4 else float(radius_m)
    if radius <= 0.0:
        raise SphereNotFoundError(f"fit converged to a non-positive radius {radius:.4g} m")
    return SphereFit(center_m=center, radius_m=radius, covariance=cov, rms_m=float(np.sqrt(np.mean(e**2))),
                     n_points=len(pts), coverage=sphere_coverage(pts, center), radius_known=k == 3,
                     form_error_m=float(e.max() - e.min()))


def _spheres_from_4(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spheres through 4 points each: samples (M, 4, 3) -> centres (M, 3), radii (M,) (NaN if degenerate)."""
    p0 = samples[:, 0]
    D = samples[:, 1:] - p0[:, None, :]  # 2 (p_i - p0) . (c - p0) = |p_i - p0|^2
    rhs = 0.5 * np.einsum("mij,mij->mi", D, D)
    det = np.linalg.det(D)
    ok = np.abs(det) > 1e-12 * np.einsum("mij,mij->m", D, D) ** 1.5
    x = np.full((len(samples), 3), np.nan)
    if ok.any():
        x[ok] = np.linalg.solve(D[ok], rhs[ok][..., None])[..., 0]
    return p0 + x, np.linalg.norm(x, axis=1)


def _spheres_from_3(samples: np.ndarray, radius_m: float) -> np.ndarray:
    """Both centres (2M, 3) of spheres of known radius through 3 points each (NaN where none exists)."""
    a, b, c = samples[:, 0], samples[:, 1], samples[:, 2]
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    n2 = np.einsum("ij,ij->i", n, n)
    # circumcentre of the triangle: a + (|ac|^2 (n x ab) + |ab|^2 (ac x n)) / (2 |n|^2)
    with np.errstate(invalid="ignore", divide="ignore"):
        cc = a + (np.einsum("ij,ij->i", ac, ac)[:, None] * np.cross(n, ab)
                  + np.einsum("ij,ij->i", ab, ab)[:, None] * np.cross(ac, n)) / (2.0 * n2[:, None])
        rho2 = np.einsum("ij,ij->i", cc - a, cc - a)
        h = np.sqrt(radius_m**2 - rho2)  # NaN where the circumcircle is larger than the sphere
        unit_n = n / np.sqrt(n2)[:, None]
    return np.concatenate([cc + h[:, None] * unit_n, cc - h[:, None] * unit_n])


def _hypotheses(pts: np.ndarray, radius_m: float | None, count: int, rng: np.random.Generator,
                radius_bounds_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Hypothesis generation: spheres through ``count`` random minimal samples of ``pts``.

    A minimal sample is 4 points (radius estimated) or 3 points, which give both spheres of the known radius
    through them.  Degenerate samples and radii outside ``radius_bounds_m`` are dropped.

    Returns
    -------
    (np.ndarray, np.ndarray)
        Centres (H, 3) and radii (H,), m; H may be 0.
    """
    s = 3 if radius_m is not None else 4
    # indices drawn with replacement: a repeated point makes a degenerate sample, discarded below
    samples = pts[rng.integers(0, len(pts), size=(count, s))]
    if s == 4:
        centres, radii = _spheres_from_4(samples)
    else:
        centres = _spheres_from_3(samples, radius_m)
        radii = np.full(len(centres), float(radius_m))
    lo, hi = radius_bounds_m
    ok = np.isfinite(centres).all(axis=1) & (radii >= lo) & (radii <= hi)
    return centres[ok], radii[ok]


def _msac_costs(points_m: np.ndarray, centres_m: np.ndarray, radii_m: np.ndarray,
                threshold_m: float) -> tuple[np.ndarray, np.ndarray]:
    """MSAC score of each hypothesis: ``sum_i min(e_i^2, t^2)`` (Torr and Zisserman's truncated quadratic).

    Unlike the RANSAC inlier count, an inlier costs its squared residual, so of two hypotheses with the same
    support the one closer to the points wins.

    Returns
    -------
    (np.ndarray, np.ndarray)
        Costs (H,), m^2, and the squared residuals (H, M) of the points under each hypothesis.
    """
    # (H, M) residuals: one batch of hypotheses at a time, so the temporary stays ~ 64 x score_points
    e2 = (np.linalg.norm(points_m[None, :, :] - centres_m[:, None, :], axis=2) - radii_m[:, None]) ** 2
    return np.minimum(e2, threshold_m**2).sum(axis=1), e2


def _samples_needed(inlier_fraction: float, sample_size: int, confidence: float) -> int:
    """Adaptive stopping: samples needed to draw one all-inlier sample with probability ``confidence``.

    ``k = log(1 - p) / log(1 - w^s)`` for an inlier fraction ``w`` and samples of ``s`` points (Fischler and
    Bolles); ``1 - w^s`` is floored at 1e-12 so that ``w = 1`` (every scored point an inlier) gives a finite ``k``.
    """
    return int(np.ceil(np.log(1 - confidence) / np.log(max(1 - inlier_fraction**sample_size, 1e-12))))


def _best_hypothesis(pts: np.ndarray, scoring_m: np.ndarray, radius_m: float | None, threshold_m: float,
                     rng: np.random.Generator, max_iterations: int, confidence: float,
                     radius_bounds_m: tuple[float, float]) -> tuple[tuple[np.ndarray, float] | None, int]:
    """The minimal-sample sphere of least MSAC cost on ``scoring_m``, drawing batches of 64 samples until the
    adaptive bound (or ``max_iterations``) is reached.

    Returns
    -------
    ((np.ndarray, float) or None, int)
        Centre and radius of the best hypothesis (None if no sample gave one), and the samples drawn.
    """
    s = 3 if radius_m is not None else 4
    t2 = threshold_m**2
    best_cost, best = np.inf, None
    drawn, needed, batch = 0, max_iterations, 64
    while drawn < min(needed, max_iterations):
        m = min(batch, max_iterations - drawn)
        centres, radii = _hypotheses(pts, radius_m, m, rng, radius_bounds_m)
        drawn += m
        if not len(centres):
            continue
        cost, e2 = _msac_costs(scoring_m, centres, radii, threshold_m)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost, best = cost[i], (centres[i], radii[i])
            w = np.count_nonzero(e2[i] <= t2) / len(scoring_m)
            if w > 0:
                needed = _samples_needed(w, s, confidence)
    return best, drawn


def _local_refit(pts: np.ndarray, center_m: np.ndarray, radius_m: float, known_radius_m: float | None,
                 threshold_m: float, min_inliers: int, radius_bounds_m: tuple[float, float]) -> np.ndarray:
    """Local optimisation of the best hypothesis: refit on its inliers and re-select them, twice.

    The minimal-sample sphere carries the noise of 3 or 4 points; the least-squares sphere through all its
    inliers does not, and selects the inliers of the true sphere more faithfully.  A refit that fails or
    leaves the radius bounds keeps the previous selection.

    Returns
    -------
    np.ndarray
        Inlier mask (N,) of ``pts``.
    """
    s = 3 if known_radius_m is not None else 4
    lo, hi = radius_bounds_m
    inliers = np.abs(sphere_residuals_m(pts, center_m, radius_m)) <= threshold_m
    for _ in range(2):
        if np.count_nonzero(inliers) < max(min_inliers, s + 1):
            break
        try:
            fit = fit_sphere(pts[inliers], radius_m=known_radius_m)
        except SphereNotFoundError:
            break
        if not (lo <= fit.radius_m <= hi):
            break
        inliers = np.abs(sphere_residuals_m(pts, fit.center_m, fit.radius_m)) <= threshold_m
    return inliers


def ransac_sphere(points_m, radius_m: float | None = None, threshold_m: float = 0.01, rng=None,
                  max_iterations: int = 2000, confidence: float = 0.999, min_inliers: int = 20,
                  radius_bounds_m: tuple[float, float] | None = None, score_points: int = 20000,
                  sigma_m: float | None = None) -> tuple[SphereFit, np.ndarray]:
    """Robust sphere detection: RANSAC with the truncated-quadratic (MSAC) score, then a least-squares refit.

    Minimal samples: 4 points (radius estimated) or 3 points and both spheres of the known radius through
    them.  Hypotheses are scored in batches on at most ``score_points`` random points (the score of a
    large cloud is estimated from a subsample); the best one is refined (refit on its inliers, re-select,
    twice) on all points, and the final :func:`fit_sphere` runs on the final inliers.

    Parameters
    ----------
    points_m : array (N, 3)
        Candidate points, m (a cluster that may hold a sphere plus clutter).
    radius_m : float, optional
        Known radius, m.  Without it the radius is estimated.
    threshold_m : float
        Inlier distance ``|e| <= threshold_m``, m: about 3 x the point noise.
    rng : numpy Generator or int, optional
        Random source (seeded for reproducible results).
    max_iterations : int
        Upper bound on the number of minimal samples; fewer are drawn once ``confidence`` is reached.
    confidence : float
        Probability of having drawn at least one all-inlier sample (adaptive stopping).
    min_inliers : int
        Fewer inliers than this: no sphere.
    radius_bounds_m : (float, float), optional
        Plausible radius range; hypotheses outside it are discarded (estimated radius only).
    score_points : int
        Size of the scoring subsample.
    sigma_m : float, optional
        Point noise passed to :func:`fit_sphere` for the covariance.

    Returns
    -------
    (SphereFit, np.ndarray)
        The fit on the inliers and the inlier mask (N,) of ``points_m``.

    Raises
    ------
    SphereNotFoundError
        No hypothesis with at least ``min_inliers`` inliers (or too few / non-finite points).
    """
    s = 3 if radius_m is not None else 4
    pts = _check_points(points_m, max(s, min_inliers))
    rng = np.random.default_rng(rng)
    n = len(pts)
    scoring = pts[rng.choice(n, size=score_points, replace=False) if n > score_points else np.arange(n)]
    bounds = radius_bounds_m if radius_bounds_m is not None else (0.0, np.inf)
    lo, hi = bounds
    best, drawn = _best_hypothesis(pts, scoring, radius_m, threshold_m, rng, max_iterations, confidence, bounds)
    if best is None:
        raise SphereNotFoundError(f"no sphere hypothesis from {n} points"
                                  + (f" with a radius in [{lo:.3g}, {hi:.3g}] m" if radius_bounds_m else ""))
    inliers = _local_refit(pts, *best, radius_m, threshold_m, min_inliers, bounds)
    n_in = int(np.count_nonzero(inliers))
    if n_in < min_inliers:
        raise SphereNotFoundError(f"no sphere found: best hypothesis has {n_in} inliers within "
                                  f"{threshold_m:.3g} m of {n} points (need {min_inliers})")
    fit = fit_sphere(pts[inliers], radius_m=radius_m, sigma_m=sigma_m)
    if not (lo <= fit.radius_m <= hi):
        raise SphereNotFoundError(f"no sphere found: fitted radius {fit.radius_m:.4g} m outside "
                                  f"[{lo:.3g}, {hi:.3g}] m")
    log.debug("ransac_sphere: %d samples, %d/%d inliers, r=%.4f m", drawn, n_in, n, fit.radius_m)
    return fit, inliers

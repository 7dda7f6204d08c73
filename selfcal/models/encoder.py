"""Self-calibrating optical angle encoder (patent seed 000): code, central projection, diode aperture, frame.

A point light source ``L`` projects part of a radial bar code on a rotating disk onto a linear photodiode
array ``A``.  Everything the estimator needs to predict one recorded signal vector (a *frame*) is here, with
analytic Jacobians; the factor graph (``selfcal.factors.encoder``) is a thin adapter around
:func:`frame_signal`.

Code (claim 4)
--------------
An m-sequence ``b`` of ``m = 2^l - 1`` cells (``scipy.signal.max_len_seq``): every l-bit window occurs
exactly once, so any ``l`` consecutive cells seen on the array locate the disk.  Cell ``k`` spans disk angles
``[2 pi k / m, 2 pi (k+1) / m)``; ``1`` is transparent.  *Edges* are the cell boundaries where ``b`` changes;
edge ``e`` sits at disk angle ``alpha_e`` (nominal ``2 pi k_e / m`` plus its graduation error).  Edges
alternate rising (0 -> 1 in increasing alpha, the start ``alpha^-`` of a transparent bar) and falling (its end
``alpha^+``).

Projection: the derivation of the patent's formula (0)
------------------------------------------------------
Housing frame: origin ``D`` where the axis ``d`` crosses the disk plane, ``z`` along the axis, disk plane
``z = 0``.  The code is centred at ``C``, offset from the axis by ``epsilon`` in direction ``gamma`` of the
*disk* frame (eccentricity).  Edge ``e`` is the radial line from ``C`` at disk angle ``alpha``; with the disk
at rotation ``beta`` it is, in the housing,

    { delta(alpha) n(phi) + r t(phi) : r real },   phi = alpha - beta,
    t(phi) = (cos phi, sin phi, 0),  n(phi) = (-sin phi, cos phi, 0),  delta(alpha) = epsilon sin(gamma - alpha)

(``delta`` is the signed distance of the line from the axis; it depends on ``alpha`` only, because ``C``
turns with the disk).  The array is the line ``X(s) = A0 + s a``, ``s`` in [-1, 1], diode ``j`` of ``n`` centred
at ``s_j = (2j - 1)/n - 1``.  The shadow of the edge falls on ``X(s)`` when ``X(s)`` lies in the plane through
``L`` and the edge line: with ``P0 = delta n(phi)``,

    t(phi) . ((L - P0) x (X(s) - P0)) = 0   <=>   t(phi) . (L x X(s)) = delta(alpha) (X_z(s) - L_z)

(using ``t . (n x W) = W_z``).  Write ``L x X(s) = c + s d`` (``c = L x A0``, ``d = L x a``) and
``X_z(s) - L_z = h + s a_z`` (``h = A0_z - L_z``).  Choose the zero of ``beta`` (a rotation of the housing
frame about ``z``, the patent's "coordination of the zero points") so that ``c_x = 0``; divide by ``c_y``:

    (1 - q s) sin(phi) + p s cos(phi) = (u - x s) cos(alpha) + (v - y s) sin(alpha)            (0)

    p = d_x / c_y,  q = -d_y / c_y,
    u = epsilon sin(gamma) h / c_y,    x = -epsilon sin(gamma) a_z / c_y,
    v = -epsilon cos(gamma) h / c_y,   y =  epsilon cos(gamma) a_z / c_y.

Eleven position parameters (``L``: 3, ``A0``: 3, ``a``: 3, ``epsilon``, ``gamma``) become six dimensionless ones,
and ``beta`` enters only as ``alpha - beta`` (claim 6).  Dividing (0) by ``1 - q s`` gives the parts of the
patent's formula that survive in the text,

    sin(phi) + z cos(phi) = z',   z = p s / (1 - q s),
    z' = ((u - x s) cos(alpha) + (v - y s) sin(alpha)) / (1 - q s),

whose solution for the 2nd argument ``beta`` in ]alpha - pi/2, alpha + pi/2[ is

    beta = alpha + arctan(z) - arcsin(z' / sqrt(1 + z^2))          (real whenever |z'| < 1),

and (0) is linear in ``s`` (the "elementary algebra" solution for the image coordinate):

    s = (u cos(alpha) + v sin(alpha) - sin(phi)) / (p cos(phi) - q sin(phi) + x cos(alpha) + y sin(alpha)).

With eccentricity only, ``u y = v x``; the patent (and this model) keeps the four free, as tilts of the disk
add terms of the same form.  ``u, v`` act as a shift of edge ``alpha`` by
``(u cos(alpha) + v sin(alpha)) / ((1 - q s) cos(phi) - p s sin(phi)) ~ (u cos(alpha) + v sin(alpha)) (1 + q s)``:
a once-per-revolution graduation error but for the factor ``1 + q s``, so a calibration that estimates the
edges separates them only through ``q`` (and ``x, y``) -- weakly (see ``docs/encoder.md``).

Diode response (patent eq. 3-6)
-------------------------------
Diode ``j`` integrates the transmitted light over a symmetric quadratic spline aperture with compact support
``[-t+, t+]`` (knots ``+-t-``, ``+-t+``, C^1, unit integral):

    a(x) = K (1 - x^2 / (t- t+))               |x| <= t-
    a(x) = K (t+ - |x|)^2 / (t+ (t+ - t-))      t- <= |x| <= t+,      K = 3 / (2 (t+ + t-))

Its integral ``A(x)`` (a cubic spline, 0 -> 1) gives the response to a bright interval in closed form.
Transmission seen by diode ``j`` (the blurred bar pattern, in [0, 1])::

    T(s_j) = sum_e w_e A(s_j - s_e),   w_e = +1 for the edge at the low-s end of its bar, -1 at the high-s end

and the signal (illumination ``I(s) = sum_k c_k P_k(s)``, Legendre, per frame; optional per-diode gain ``g_j``)::

    a_j = a0 + (1 + g_j) I(s_j) T(s_j) + w_j,      w_j ~ N(0, sigma^2)                   (6), (13)

The patent takes one intensity per visible bar; a smooth profile per frame is used here (3 numbers instead of
~6, and no intensity of a bar cut by the array end left undetermined).  Taking ``I`` at the diode instead of
inside the convolution changes the signal by a term even about each edge, so edge positions are unbiased.

Units: angles in rad, ``s`` and ``t+-`` in array half-lengths (dimensionless), signals in ADC counts.

References
----------
J. Weilenmann (Leica Geosystems), "Calibration method for a measuring instrument", CN1500202 (WO 02/079730).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre
from scipy.signal import max_len_seq

GEOMETRY_NAMES = ("p", "q", "u", "v", "x", "y")
APERTURE_NAMES = ("t_minus", "t_plus")


# --- code ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Code:
    """An m-sequence code ring: cells, edges, bars, and the l-bit window look-up (claim 4).

    Attributes
    ----------
    l : int
        Window length; ``m = 2^l - 1`` cells.
    bits : (m,) uint8
        Cell values, 1 = transparent.
    edge_cell : (E,) int
        Edge ``e`` is the boundary between cells ``edge_cell[e] - 1`` and ``edge_cell[e]`` (sorted).
    edge_rising : (E,) bool
        True where the edge starts a transparent bar (0 -> 1 in increasing alpha).
    """

    l: int
    bits: np.ndarray
    edge_cell: np.ndarray = field(repr=False)
    edge_rising: np.ndarray = field(repr=False)
    _windows: dict = field(repr=False, compare=False)

    @classmethod
    def m_sequence(cls, l: int) -> Code:
        """The m-sequence of scipy's default taps for ``l`` bits (every l-bit window but all-zero, once)."""
        if not 3 <= l <= 20:
            raise ValueError(f"code length l={l} outside 3..20")
        bits, _ = max_len_seq(l)
        bits = bits.astype(np.uint8)
        m = bits.size
        change = bits != np.roll(bits, 1)  # cell k differs from cell k-1 (cyclic)
        edge_cell = np.flatnonzero(change)
        rising = bits[edge_cell] == 1
        ext = np.concatenate([bits, bits[:l - 1]])
        windows = {}
        for k in range(m):
            windows[ext[k:k + l].tobytes()] = k
        return cls(l, bits, edge_cell, rising, windows)

    @property
    def m(self) -> int:
        return int(self.bits.size)

    @property
    def n_edges(self) -> int:
        return int(self.edge_cell.size)

    @property
    def cell_rad(self) -> float:
        return 2.0 * math.pi / self.m

    def nominal_edge_angles(self) -> np.ndarray:
        """Nominal edge angles ``2 pi k_e / m`` (rad), (E,)."""
        return self.edge_cell * self.cell_rad

    def bar_partner(self, e: np.ndarray) -> np.ndarray:
        """The other edge of each edge's bar (rising -> next edge, falling -> previous), cyclic indices."""
        e = np.asarray(e)
        return np.where(self.edge_rising[e % self.n_edges], e + 1, e - 1)

    def locate(self, window_bits) -> int | None:
        """Start cell of ``l`` consecutive cell values, or None if no cell run of the code reads so."""
        key = np.asarray(window_bits, dtype=np.uint8)
        if key.size != self.l:
            raise ValueError(f"a window has {self.l} bits, got {key.size}")
        return self._windows.get(key.tobytes())

    def cells(self, start: int, count: int) -> np.ndarray:
        """Values of ``count`` consecutive cells from ``start`` (cyclic)."""
        return self.bits[np.arange(start, start + count) % self.m]


# --- projection ----------------------------------------------------------------------------------------------

@dataclass
class Projection:
    """``s`` of an edge and its derivatives (arrays of the edges' shape; ``ds_dgeometry`` has a trailing 6)."""

    s: np.ndarray
    ds_dalpha: np.ndarray
    ds_dbeta: np.ndarray
    ds_dgeometry: np.ndarray


def image_coordinate(alpha_rad, beta_rad, geometry) -> Projection:
    """Array coordinate ``s`` of the edge at disk angle ``alpha`` with the disk at ``beta``: formula (0) for s.

    ``s = N / D``, ``N = u cos(alpha) + v sin(alpha) - sin(phi)``,
    ``D = p cos(phi) - q sin(phi) + x cos(alpha) + y sin(alpha)``, ``phi = alpha - beta``.

    Parameters
    ----------
    alpha_rad, beta_rad : array_like
        Edge angle(s) on the disk and disk rotation (broadcast together), rad.
    geometry : array_like (6,)
        ``(p, q, u, v, x, y)``.
    """
    p, q, u, v, x, y = np.asarray(geometry, dtype=float)
    alpha = np.asarray(alpha_rad, dtype=float)
    phi = alpha - beta_rad
    ca, sa, cp, sp = np.cos(alpha), np.sin(alpha), np.cos(phi), np.sin(phi)
    N = u * ca + v * sa - sp
    D = p * cp - q * sp + x * ca + y * sa
    s = N / D
    # d/dphi at fixed alpha: dN = -cos(phi), dD = -p sin(phi) - q cos(phi)
    ds_dphi = (-cp - s * (-p * sp - q * cp)) / D
    # explicit alpha terms (eccentricity): dN = -u sin + v cos, dD = -x sin + y cos
    ds_dalpha_explicit = ((-u * sa + v * ca) - s * (-x * sa + y * ca)) / D
    ds_dgeom = np.stack([-s * cp / D, s * sp / D, ca / D, sa / D, -s * ca / D, -s * sa / D], axis=-1)
    return Projection(s, ds_dphi + ds_dalpha_explicit, -ds_dphi, ds_dgeom)


def patent_z(s, alpha_rad, geometry) -> tuple[np.ndarray, np.ndarray]:
    """The patent's surviving expressions: ``z = p s/(1 - q s)``, ``z' = ((u - x s) cos a + (v - y s) sin a)/(1 - q s)``."""
    p, q, u, v, x, y = np.asarray(geometry, dtype=float)
    s = np.asarray(s, dtype=float)
    z = p * s / (1.0 - q * s)
    z_prime = ((u - x * s) * np.cos(alpha_rad) + (v - y * s) * np.sin(alpha_rad)) / (1.0 - q * s)
    return z, z_prime


def rotation_from_image(s, alpha_rad, geometry) -> np.ndarray:
    """Disk rotation ``beta`` that images edge ``alpha`` at ``s``: ``alpha + arctan z - arcsin(z'/sqrt(1+z^2))``.

    The solution of (0) for its 2nd argument in ]alpha - pi/2, alpha + pi/2[ (the angle measurement itself).
    NaN where ``|z'| > sqrt(1 + z^2)`` (no such rotation).
    """
    z, z_prime = patent_z(s, alpha_rad, geometry)
    ratio = z_prime / np.sqrt(1.0 + z * z)
    with np.errstate(invalid="ignore"):
        return np.asarray(alpha_rad) + np.arctan(z) - np.arcsin(ratio)


@dataclass(frozen=True)
class PhysicalGeometry:
    """The eleven position parameters before reduction (housing frame, m): light ``L``, array centre ``A0``,
    array half-length vector ``a`` (from the centre to the end ``s = +1``), eccentricity ``epsilon_m`` of the
    code centre in disk direction ``gamma_rad``."""

    L: np.ndarray
    A0: np.ndarray
    a: np.ndarray
    epsilon_m: float = 0.0
    gamma_rad: float = 0.0

    def reduce(self) -> tuple[np.ndarray, float]:
        """``(p, q, u, v, x, y)`` and ``psi``: the housing frame turned by ``psi`` about z has ``c_x = 0``, so
        the model's rotation is ``beta_model = beta + psi`` (the coordinated zero of beta)."""
        L, A0, a = (np.asarray(v, dtype=float) for v in (self.L, self.A0, self.a))
        c, d = np.cross(L, A0), np.cross(L, a)
        # rotate x, y by -psi: c_x' = cos(psi) c_x + sin(psi) c_y = 0
        psi = math.atan2(-c[0], c[1])
        rot = np.array([[math.cos(psi), math.sin(psi)], [-math.sin(psi), math.cos(psi)]])
        cx, cy = rot @ c[:2]
        dx, dy = rot @ d[:2]
        h, a_z = A0[2] - L[2], a[2]
        eps, g = self.epsilon_m, self.gamma_rad - 0.0
        geometry = np.array([dx / cy, -dy / cy, eps * math.sin(g) * h / cy, -eps * math.cos(g) * h / cy,
                             -eps * math.sin(g) * a_z / cy, eps * math.cos(g) * a_z / cy])
        return geometry, psi


def shadow_coordinate(phys: PhysicalGeometry, alpha_rad: float, beta_rad: float) -> float:
    """``s`` of the shadow of edge ``alpha`` by direct ray geometry (for tests: an independent code path).

    The edge line (from the eccentric code centre, disk angle ``alpha``, disk at physical rotation ``beta``)
    and ``L`` span a plane; intersect the array line with it.
    """
    rot = lambda ang: np.array([math.cos(ang), math.sin(ang), 0.0])  # noqa: E731
    centre = phys.epsilon_m * rot(phys.gamma_rad - beta_rad)
    direction = rot(alpha_rad - beta_rad)
    normal = np.cross(direction, np.asarray(phys.L) - centre)
    A0, a = np.asarray(phys.A0, dtype=float), np.asarray(phys.a, dtype=float)
    return float(-(normal @ (A0 - centre)) / (normal @ a))


# --- aperture ------------------------------------------------------------------------------------------------

def aperture(x, t_minus: float, t_plus: float) -> np.ndarray:
    """Diode aperture ``a(x; t-, t+)``: symmetric C^1 quadratic spline, support [-t+, t+], unit integral."""
    ax = np.abs(np.asarray(x, dtype=float))
    K = 1.5 / (t_plus + t_minus)
    inner = K * (1.0 - ax * ax / (t_minus * t_plus))
    outer = K * np.square(np.maximum(t_plus - ax, 0.0)) / (t_plus * (t_plus - t_minus))
    return np.where(ax <= t_minus, inner, outer)


def aperture_cdf(x, t_minus: float, t_plus: float, derivatives: bool = True):
    """``A(x) = integral of a`` from -inf to x (cubic spline 0 -> 1) and, optionally, dA/dt-, dA/dt+.

    Returns ``A`` or ``(A, a, dA_dtminus, dA_dtplus)`` (``a = dA/dx``).  Odd symmetry ``A(-x) = 1 - A(x)`` is used:
    the t-derivatives are odd in x.
    """
    x = np.asarray(x, dtype=float)
    ax = np.abs(x)
    sgn = np.where(x < 0, -1.0, 1.0)
    tm, tp = t_minus, t_plus
    S = tp + tm
    K = 1.5 / S
    inner_mask = ax <= tm
    outer_mask = (ax > tm) & (ax < tp)
    g_in = ax - ax**3 / (3.0 * tm * tp)          # A - 1/2 = K g_in inside
    r = np.maximum(tp - ax, 0.0)
    F = r**3 / (3.0 * tp * (tp - tm))            # 1 - A = K F outside
    half = np.where(inner_mask, K * g_in, np.where(outer_mask, 0.5 - K * F, 0.5))
    A = 0.5 + sgn * half
    if not derivatives:
        return A
    a = aperture(x, tm, tp)
    dK = -K / S                                   # dK/dt- = dK/dt+
    dg_in_dtm = ax**3 / (3.0 * tm * tm * tp)
    dg_in_dtp = ax**3 / (3.0 * tm * tp * tp)
    dF_dtm = r**3 / (3.0 * tp * (tp - tm) ** 2)
    dF_dtp = r**2 * (3.0 * tp * (tp - tm) - r * (2.0 * tp - tm)) / (3.0 * tp * tp * (tp - tm) ** 2)
    dh_dtm = np.where(inner_mask, dK * g_in + K * dg_in_dtm, np.where(outer_mask, -dK * F - K * dF_dtm, 0.0))
    dh_dtp = np.where(inner_mask, dK * g_in + K * dg_in_dtp, np.where(outer_mask, -dK * F - K * dF_dtp, 0.0))
    return A, a, sgn * dh_dtm, sgn * dh_dtp


# --- array and frame -----------------------------------------------------------------------------------------

def diode_centres(n: int) -> np.ndarray:
    """``s_j = (2j - 1)/n - 1``, j = 1..n."""
    return (2.0 * np.arange(1, n + 1) - 1.0) / n - 1.0


def illumination_basis(s, degree: int) -> np.ndarray:
    """Legendre polynomials ``P_0..P_degree`` at ``s``: (len(s), degree + 1)."""
    s = np.asarray(s, dtype=float)
    key = (s.size, degree, float(s[0]) if s.size else 0.0, float(s[-1]) if s.size else 0.0)
    cached = _BASIS_CACHE.get(key)
    if cached is None or not np.array_equal(cached[0], s):
        cached = (s.copy(), legendre.legvander(s, degree))
        if len(_BASIS_CACHE) < 16:   # frames of a recording share one array: a handful of entries at most
            _BASIS_CACHE[key] = cached
    return cached[1]


_BASIS_CACHE: dict = {}


@dataclass
class FrameJacobians:
    """Derivatives of the frame signal (n,) with respect to every argument of :func:`frame_signal`."""

    d_alpha: np.ndarray       # (n, E_f)
    d_beta: np.ndarray        # (n,)
    d_geometry: np.ndarray    # (n, 6)
    d_aperture: np.ndarray    # (n, 2)
    d_illumination: np.ndarray  # (n, degree + 1)
    d_a0: np.ndarray          # (n,)
    d_gain: np.ndarray        # (n,) diagonal: d a_j / d g_j


def edge_weights(code: Code, edges: np.ndarray, geometry) -> np.ndarray:
    """``w_e`` of :func:`frame_signal`: +1 at the low-s end of a bar, -1 at the high-s end.

    ``s`` falls as ``alpha`` grows when ``p > 0`` (s ~ -tan(phi)/p), so a rising edge (bar start) is its
    bar's high-s end then.
    """
    rising = code.edge_rising[np.asarray(edges) % code.n_edges]
    sign = 1.0 if geometry[0] > 0 else -1.0
    return np.where(rising, -sign, sign)


def frame_signal(s_diodes, edge_alpha_rad, weights, beta_rad, geometry, aperture_t, illumination, a0,
                 gain=None, jacobians: bool = True):
    """Signal vector of one frame and (optionally) its Jacobians: ``a_j = a0 + (1 + g_j) I(s_j) T(s_j)``.

    Parameters
    ----------
    s_diodes : (n,) diode centres, increasing.
    edge_alpha_rad : (E_f,) disk angles of the edges of every bar touching the array (both edges of each bar,
        unwrapped near ``beta``).
    weights : (E_f,) ``w_e`` (:func:`edge_weights`).
    beta_rad : float, disk rotation.
    geometry : (6,) ``(p, q, u, v, x, y)``.
    aperture_t : (2,) ``(t-, t+)``.
    illumination : (degree + 1,) Legendre coefficients of ``I(s)`` (counts).
    a0 : float, dark level (counts).
    gain : (n,) per-diode gain ``g_j`` or None.

    Returns
    -------
    signal : (n,)
    FrameJacobians or None
    """
    s_diodes = np.asarray(s_diodes, dtype=float)
    n = s_diodes.size
    proj = image_coordinate(edge_alpha_rad, beta_rad, geometry)
    tm, tp = float(aperture_t[0]), float(aperture_t[1])
    P = illumination_basis(s_diodes, len(illumination) - 1)
    I = P @ np.asarray(illumination, dtype=float)
    G = np.ones(n) if gain is None else 1.0 + np.asarray(gain, dtype=float)
    w = np.asarray(weights, dtype=float)
    s_e = proj.s
    # A(s_j - s_e) is a step outside |s_j - s_e| < t+: sum the steps by a cumulative sum, and evaluate the
    # spline only on the few diodes of each edge's window (sparse: ~2 t+ / pitch diodes per edge)
    first = np.searchsorted(s_diodes, s_e)                      # first diode at or past the edge
    D = np.bincount(np.clip(first, 0, n), weights=w, minlength=n + 1)
    T = np.cumsum(D)[:n]
    lo = np.searchsorted(s_diodes, s_e - tp)
    hi = np.searchsorted(s_diodes, s_e + tp)
    width = int(np.max(hi - lo)) if s_e.size else 0
    idx = lo[:, None] + np.arange(max(width, 1))[None, :]       # (E_f, K)
    valid = (idx < hi[:, None]) & (idx < n)
    idx_c = np.minimum(idx, n - 1)
    X = s_diodes[idx_c] - s_e[:, None]
    step = (idx_c >= first[:, None]).astype(float)
    flat = idx_c[valid]
    if not jacobians:
        A = aperture_cdf(X, tm, tp, derivatives=False)
        T = T + np.bincount(flat, weights=((A - step) * w[:, None])[valid], minlength=n)
        return a0 + G * I * T, None
    A, a, dA_dtm, dA_dtp = aperture_cdf(X, tm, tp)
    T = T + np.bincount(flat, weights=((A - step) * w[:, None])[valid], minlength=n)
    GI = G * I
    dT_dse = (-a * w[:, None])                                  # (E_f, K)
    d_se = GI[idx_c] * dT_dse                                   # d signal_j / d s_e on the window
    d_alpha = np.zeros((n, s_e.size))
    cols = np.broadcast_to(np.arange(s_e.size)[:, None], idx.shape)
    d_alpha[flat, cols[valid]] = (d_se * proj.ds_dalpha[:, None])[valid]
    # float even for a frame with no edge in its window (bincount of nothing returns int zeros)
    scatter = lambda v: np.bincount(flat, weights=v[valid], minlength=n).astype(float)  # noqa: E731
    jac = FrameJacobians(
        d_alpha=d_alpha,
        d_beta=scatter(d_se * proj.ds_dbeta[:, None]),
        d_geometry=np.column_stack([scatter(d_se * proj.ds_dgeometry[:, [c]]) for c in range(6)]),
        d_aperture=GI[:, None] * np.column_stack([scatter(dA_dtm * w[:, None]), scatter(dA_dtp * w[:, None])]),
        d_illumination=(G * T)[:, None] * P,
        d_a0=np.ones(n),
        d_gain=I * T)
    return a0 + GI * T, jac


def visible_bars(code: Code, beta_rad: float, geometry, edge_alpha_rad: np.ndarray, margin_s: float = 0.05):
    """Edges of every bar that touches the array at ``beta`` (both edges of each), unwrapped near ``beta``.

    Parameters
    ----------
    edge_alpha_rad : (E,) current edge angles (nominal or calibrated), in [0, 2 pi) order of ``code``.
    margin_s : extra array half-lengths on each side (covers the aperture and the unknown geometry).

    Returns
    -------
    edges : (E_f,) edge indices (0..E-1), sorted by angle
    alpha : (E_f,) their angles, unwrapped to lie within pi of beta
    """
    E = code.n_edges
    alpha = np.asarray(edge_alpha_rad, dtype=float)
    unwrapped = beta_rad + np.remainder(alpha - beta_rad + math.pi, 2 * math.pi) - math.pi
    phi = unwrapped - beta_rad
    reach = abs(math.atan(abs(geometry[0]) * (1.0 + margin_s) / max(1.0 - abs(geometry[1]) * (1.0 + margin_s), 0.1)))
    near = np.flatnonzero(np.abs(phi) < reach)
    if near.size == 0:
        return np.array([], dtype=int), np.array([])
    # include the bar partner of every edge near the array (a bar may span the whole window's end)
    both = np.unique(np.concatenate([near, code.bar_partner(near) % E]))
    a = beta_rad + np.remainder(alpha[both] - beta_rad + math.pi, 2 * math.pi) - math.pi
    order = np.argsort(a)
    return both[order], a[order]


# --- decoding (the patent's start values) --------------------------------------------------------------------

FLAG_OK = ""
FLAG_SATURATED = "saturated"
FLAG_DARK = "dark"
FLAG_UNDECODABLE = "undecodable"
FLAG_MISMATCH = "code_mismatch"


@dataclass
class DecodedFrame:
    """Result of :func:`decode_frame`.

    ``flag`` is empty for a decoded frame, else one of ``saturated``, ``dark``, ``undecodable`` (fewer than
    ``l`` readable cells), ``code_mismatch`` (the cells read are no run of the code).  For a decoded frame,
    ``edges`` are the code's edge indices whose threshold crossings were found at ``edge_s`` (linear
    interpolation between diodes), and ``beta_rad`` is the start value: the mean over those edges of
    ``rotation_from_image(s_e, alpha_e)`` with the given edge angles and geometry.
    """

    flag: str
    beta_rad: float = float("nan")
    edges: np.ndarray = field(default_factory=lambda: np.array([], dtype=int))
    edge_s: np.ndarray = field(default_factory=lambda: np.array([]))
    first_cell: int = -1
    n_cells: int = 0
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.flag == FLAG_OK


def threshold_crossings(signal: np.ndarray, s_diodes: np.ndarray, threshold: float) -> np.ndarray:
    """Array coordinates where the signal crosses ``threshold`` (linear interpolation between diodes)."""
    above = signal > threshold
    i = np.flatnonzero(above[1:] != above[:-1])
    a0, a1 = signal[i], signal[i + 1]
    frac = (threshold - a0) / (a1 - a0)
    return s_diodes[i] + frac * (s_diodes[i + 1] - s_diodes[i])


def image_angle(s, geometry) -> np.ndarray:
    """``phi = alpha - beta`` of a point imaged at ``s`` when ``u = v = x = y = 0``: ``-arctan(p s / (1 - q s))``."""
    p, q = geometry[0], geometry[1]
    s = np.asarray(s, dtype=float)
    return -np.arctan(p * s / (1.0 - q * s))


def image_coordinate_of_angle(phi, geometry) -> np.ndarray:
    """Inverse of :func:`image_angle`: ``s = -sin(phi) / (p cos(phi) - q sin(phi))``."""
    p, q = geometry[0], geometry[1]
    return -np.sin(phi) / (p * np.cos(phi) - q * np.sin(phi))


def decode_frame(signal, code: Code, geometry, edge_alpha_rad=None, adc_max: float | None = None,
                 noise_sigma: float | None = None, edge_margin_s: float = 0.02) -> DecodedFrame:
    """Find the bar images, read the cells, locate the l-bit window, identify the edges, start beta.

    Steps (the patent's decoding and start values, eq. 15):

    1. refuse saturated (>1 % of diodes at ``adc_max``) and dark frames (bright-dark contrast below 20 noise
       sigmas, or below 5 % of the bright level);
    2. threshold halfway between the dark and bright levels (5th / 95th percentiles) and interpolate the
       crossings linearly: the bar edges' images ``s_e``;
    3. the crossings fix the phase of the cell grid (cells are ``2 pi / m`` wide); read every cell whose centre
       is on the array at its centre;
    4. the first ``l`` cells locate the window in the code (claim 4); all further cells must agree;
    5. each crossing is a code edge; ``beta = mean_e rotation_from_image(s_e, alpha_e)``.

    Parameters
    ----------
    signal : (n,) one frame.
    geometry : (6,) nominal or calibrated ``(p, q, u, v, x, y)``.
    edge_alpha_rad : (E,) edge angles for the start value (default: nominal).
    """
    a = np.asarray(signal, dtype=float)
    n = a.size
    s_diodes = diode_centres(n)
    if adc_max is not None and np.mean(a >= 0.999 * adc_max) > 0.01:
        return DecodedFrame(FLAG_SATURATED, detail=f"{int(np.sum(a >= 0.999 * adc_max))} diodes at the ADC maximum")
    lo, hi = np.percentile(a, [5, 95])
    contrast = hi - lo
    floor = max(20.0 * (noise_sigma or 0.0), 0.05 * abs(hi))
    if not contrast > floor:
        return DecodedFrame(FLAG_DARK, detail=f"bright-dark contrast {contrast:.3g} counts below {floor:.3g}")
    threshold = 0.5 * (lo + hi)
    s_cross = threshold_crossings(a, s_diodes, threshold)
    # local threshold: half-way between the dark level and a quadratic fit of the bright plateaus, so a light
    # profile falling towards the array ends does not move the crossings (~0.4 pitch at 30 % fall-off)
    pitch = 2.0 / n
    far = np.min(np.abs(s_diodes[:, None] - s_cross[None, :]), axis=1) > 4 * pitch if s_cross.size else \
        np.ones(n, dtype=bool)
    bright = far & (a > threshold)
    dark = far & (a <= threshold)
    if bright.sum() > 10 and dark.sum() > 3:
        coef = np.polynomial.polynomial.polyfit(s_diodes[bright], a[bright], 2)
        local = 0.5 * (np.median(a[dark]) + np.polynomial.polynomial.polyval(s_diodes, coef))
        above = a > local
        i = np.flatnonzero(above[1:] != above[:-1])
        d0, d1 = a[i] - local[i], a[i + 1] - local[i + 1]
        s_cross = s_diodes[i] + d0 / (d0 - d1) * pitch
    s_cross = s_cross[np.abs(s_cross) < 1.0 - edge_margin_s]
    if s_cross.size == 0:
        return DecodedFrame(FLAG_UNDECODABLE, detail="no bar edge on the array")
    cell = code.cell_rad
    phi_cross = image_angle(s_cross, geometry)
    # grid phase: crossings sit on cell boundaries, phi = k cell + theta (circular mean of the fractions)
    frac = phi_cross / cell
    theta = math.atan2(np.mean(np.sin(2 * math.pi * frac)), np.mean(np.cos(2 * math.pi * frac))) / (2 * math.pi)
    phi_lo, phi_hi = np.sort(image_angle(np.array([1.0, -1.0]), geometry))
    k_lo = math.ceil((phi_lo - theta * cell) / cell - 0.5)
    k_hi = math.floor((phi_hi - theta * cell) / cell - 0.5)
    ks = np.arange(k_lo, k_hi + 1)
    centres = (ks + 0.5 + theta) * cell
    s_centres = image_coordinate_of_angle(centres, geometry)
    inside = np.abs(s_centres) < 1.0 - 0.25 * abs(image_coordinate_of_angle(cell, geometry))
    ks, s_centres = ks[inside], s_centres[inside]
    if ks.size < code.l:
        return DecodedFrame(FLAG_UNDECODABLE, detail=f"{ks.size} readable cells, the code needs {code.l}")
    values = np.interp(s_centres, s_diodes, a)
    bits = (values > threshold).astype(np.uint8)   # ordered by increasing phi (increasing alpha)
    start = code.locate(bits[:code.l])
    if start is None:
        return DecodedFrame(FLAG_UNDECODABLE, detail="the cells read are no window of the code")
    if not np.array_equal(code.cells(start, bits.size), bits):
        return DecodedFrame(FLAG_MISMATCH, detail="cells beyond the first window disagree with the code")
    # crossing at phi = (k + theta) cell is the boundary before cell k: code cell start + (k - ks[0])
    k_cross = np.rint(frac - theta).astype(int)
    boundary = (start + k_cross - ks[0]) % code.m
    edge_of_cell = np.full(code.m, -1)
    edge_of_cell[code.edge_cell] = np.arange(code.n_edges)
    edges = edge_of_cell[boundary]
    if np.any(edges < 0) or np.unique(edges).size != edges.size:
        return DecodedFrame(FLAG_MISMATCH, detail="a crossing falls on a cell boundary without an edge")
    alpha_all = code.nominal_edge_angles() if edge_alpha_rad is None else np.asarray(edge_alpha_rad)
    # unwrap: cell boundary start + k - ks[0] may pass m
    alpha = alpha_all[edges] + 2 * math.pi * np.floor_divide(start + k_cross - ks[0], code.m)
    beta = rotation_from_image(s_cross, alpha, geometry)
    beta0 = float(np.mean(beta))
    return DecodedFrame(FLAG_OK, float(np.remainder(beta0, 2 * math.pi)), edges, s_cross, int(start), int(ks.size))

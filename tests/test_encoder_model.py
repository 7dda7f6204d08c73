"""Encoder model (patent 000): the m-sequence code, the projection derived from a central projection, the
aperture spline and the frame signal with its analytic Jacobians (against central differences)."""
import math

import numpy as np
import pytest

from selfcal.models import encoder as enc

SEEDS = [1, 2, 3, 4, 5]


@pytest.mark.parametrize("l", [4, 6, 10])
def test_m_sequence_windows_unique_and_balanced(l):
    code = enc.Code.m_sequence(l)
    m = 2**l - 1
    assert code.m == m
    assert int(code.bits.sum()) == (m + 1) // 2  # claim 4: (m+1)/2 ones, (m-1)/2 zeros
    starts = [code.locate(code.cells(k, l)) for k in range(m)]
    assert starts == list(range(m))  # every l-bit window once
    assert code.locate(np.zeros(l, dtype=np.uint8)) is None
    # edges alternate rising/falling around the ring, and 2^(l-1) runs means 2^(l-1) edges
    assert code.n_edges == 2 ** (l - 1)
    assert np.all(code.edge_rising[::2] != code.edge_rising[1::2])


def random_physical(rng, eccentric=True):
    """Light above the disk at radius ~30 mm, array 5 mm below, tangential, half-length ~1.1 mm; small tilts."""
    R = 0.03
    L = np.array([R + 1e-3 * rng.normal(), 1e-3 * rng.normal(), 0.01 + 1e-3 * rng.normal()])
    A0 = np.array([R + 1e-3 * rng.normal(), 1e-3 * rng.normal(), -0.005 + 1e-4 * rng.normal()])
    a = np.array([2e-5 * rng.normal(), 1.1e-3, 2e-5 * rng.normal()])
    ecc = 2e-5 * rng.uniform(0.2, 1.0) if eccentric else 0.0
    return enc.PhysicalGeometry(L, A0, a, ecc, rng.uniform(0, 2 * math.pi))


@pytest.mark.parametrize("seed", SEEDS)
def test_projection_equals_direct_ray_geometry(seed):
    """Formula (0) with the reduced six parameters gives the same s as intersecting rays in 3-D."""
    rng = np.random.default_rng(seed)
    phys = random_physical(rng)
    geometry, psi = phys.reduce()
    for _ in range(20):
        alpha = rng.uniform(0, 2 * math.pi)
        beta_model = alpha - rng.uniform(-0.03, 0.03)   # an edge near the array's field of view
        beta_phys = beta_model - psi
        s_direct = enc.shadow_coordinate(phys, alpha, beta_phys)
        s_model = enc.image_coordinate(alpha, beta_model, geometry).s
        assert abs(s_model - s_direct) < 1e-10 * max(1.0, abs(s_direct))


@pytest.mark.parametrize("seed", SEEDS)
def test_patent_surviving_formulas(seed):
    """s from (0) satisfies sin(phi) + z cos(phi) = z' with the patent's z, z'; beta from z, z' inverts s."""
    rng = np.random.default_rng(seed)
    geometry, _ = random_physical(rng).reduce()
    alpha = rng.uniform(0, 2 * math.pi, 50)
    beta = alpha - rng.uniform(-0.03, 0.03, 50)
    s = enc.image_coordinate(alpha, beta, geometry).s
    p, q, u, v, x, y = geometry
    z = p * s / (1 - q * s)                                                    # the patent's text, literally
    z_prime = ((u - x * s) * np.cos(alpha) + (v - y * s) * np.sin(alpha)) / (1 - q * s)
    np.testing.assert_allclose(np.sin(alpha - beta) + z * np.cos(alpha - beta), z_prime, atol=1e-14)
    assert np.all(np.abs(z_prime) < 1)
    np.testing.assert_allclose(enc.rotation_from_image(s, alpha, geometry), beta, atol=1e-13)
    # eleven parameters, six dimensionless; pure eccentricity keeps u y = v x
    assert abs(u * y - v * x) < 1e-12 * (abs(u * y) + 1e-30) + 1e-30


def test_eccentricity_is_a_once_per_revolution_edge_shift():
    """u, v act as the edge shift (u cos(alpha) + v sin(alpha)) / ((1 - q s) cos(phi) - p s sin(phi)): a
    once-per-revolution graduation error but for the factor ~(1 + q s), which alone separates them from one."""
    geometry = np.array([0.037, 0.01, 0.0, 0.0, 0.0, 0.0])
    ecc = np.array([0.037, 0.01, 2e-6, -1e-6, 0.0, 0.0])
    for alpha in np.linspace(0, 2 * math.pi, 7):
        beta = alpha - 0.01
        phi = alpha - beta
        s_ecc = enc.image_coordinate(alpha, beta, ecc).s
        shift = (2e-6 * math.cos(alpha) - 1e-6 * math.sin(alpha)) / (
            (1 - 0.01 * s_ecc) * math.cos(phi) - 0.037 * s_ecc * math.sin(phi))
        s_shifted = enc.image_coordinate(alpha - shift, beta, geometry).s
        assert abs(s_ecc - s_shifted) < 1e-9 * abs(s_ecc)   # second order in the shift (~1e-10)


def numeric(f, x, h):
    x = np.asarray(x, dtype=float)
    out = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d.flat[i] = h
        out.append((f(x + d) - f(x - d)) / (2 * h))
    return np.stack(out, axis=-1)


@pytest.mark.parametrize("seed", SEEDS)
def test_projection_jacobians(seed):
    rng = np.random.default_rng(seed)
    geometry = np.array([0.037, 0.02, 1e-3, -2e-3, 5e-4, 3e-4]) * (1 + 0.1 * rng.normal(size=6))
    alpha = rng.uniform(0, 2 * math.pi)
    beta = alpha + rng.uniform(-0.03, 0.03)
    pr = enc.image_coordinate(alpha, beta, geometry)
    h = 1e-7
    assert pr.ds_dalpha == pytest.approx(
        (enc.image_coordinate(alpha + h, beta, geometry).s - enc.image_coordinate(alpha - h, beta, geometry).s)
        / (2 * h), rel=1e-6)
    assert pr.ds_dbeta == pytest.approx(
        (enc.image_coordinate(alpha, beta + h, geometry).s - enc.image_coordinate(alpha, beta - h, geometry).s)
        / (2 * h), rel=1e-6)
    np.testing.assert_allclose(pr.ds_dgeometry,
                               numeric(lambda g: enc.image_coordinate(alpha, beta, g).s, geometry, 1e-9),
                               rtol=1e-5, atol=1e-6)


def test_aperture_is_c1_spline_with_unit_integral():
    tm, tp = 0.6e-3, 2.5e-3
    x = np.linspace(-3e-3, 3e-3, 200001)
    a = enc.aperture(x, tm, tp)
    assert np.trapezoid(a, x) == pytest.approx(1.0, rel=1e-8)
    assert np.all(a >= 0) and np.all(a[np.abs(x) >= tp] == 0)
    np.testing.assert_allclose(a, a[::-1])  # symmetric
    slope = np.diff(a) / np.diff(x)
    assert np.max(np.abs(np.diff(slope))) < 1e-3 * np.max(np.abs(slope))  # no kink: C^1
    A = enc.aperture_cdf(x, tm, tp, derivatives=False)
    cumulative = np.concatenate([[0], np.cumsum(0.5 * (a[1:] + a[:-1]) * np.diff(x))])
    np.testing.assert_allclose(A, cumulative, atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_aperture_cdf_derivatives(seed):
    rng = np.random.default_rng(seed)
    tm, tp = rng.uniform(0.3e-3, 1e-3), rng.uniform(1.5e-3, 3e-3)
    x = rng.uniform(-1.1 * tp, 1.1 * tp, 40)
    A, a, dtm, dtp = enc.aperture_cdf(x, tm, tp)
    h = 1e-9
    np.testing.assert_allclose(a, (enc.aperture_cdf(x + h, tm, tp, False) - enc.aperture_cdf(x - h, tm, tp, False))
                               / (2 * h), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(dtm, (enc.aperture_cdf(x, tm + h, tp, False) - enc.aperture_cdf(x, tm - h, tp, False))
                               / (2 * h), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(dtp, (enc.aperture_cdf(x, tm, tp + h, False) - enc.aperture_cdf(x, tm, tp - h, False))
                               / (2 * h), rtol=1e-5, atol=1e-3)


def frame_setup(rng, l=6, n=128):
    code = enc.Code.m_sequence(l)
    m = code.m
    p = math.atan(5 * code.cell_rad)  # five cells on each side of the centre
    geometry = np.array([p, 0.02, 2e-4, -1e-4, 1e-4, 2e-4]) * (1 + 0.05 * rng.normal(size=6))
    alpha_all = code.nominal_edge_angles() + 1e-5 * rng.normal(size=code.n_edges)
    beta = rng.uniform(0, 2 * math.pi)
    edges, alpha = enc.visible_bars(code, beta, geometry, alpha_all)
    weights = enc.edge_weights(code, edges, geometry)
    aperture_t = np.array([0.7, 2.2]) * 2.0 / n
    illumination = np.array([1000.0, 50.0, -80.0])
    gain = 0.01 * rng.normal(size=n)
    assert m > 0
    return enc.diode_centres(n), alpha, weights, beta, geometry, aperture_t, illumination, 20.0, gain


@pytest.mark.parametrize("seed", SEEDS)
def test_frame_signal_jacobians(seed):
    rng = np.random.default_rng(seed)
    s, alpha, w, beta, geom, t, c, a0, gain = frame_setup(rng)
    sig, jac = enc.frame_signal(s, alpha, w, beta, geom, t, c, a0, gain)
    f = lambda **kw: enc.frame_signal(**{**dict(s_diodes=s, edge_alpha_rad=alpha, weights=w, beta_rad=beta,  # noqa: E731
                                                geometry=geom, aperture_t=t, illumination=c, a0=a0, gain=gain),
                                             **kw}, jacobians=False)[0]
    scale = np.max(np.abs(sig))
    checks = [("d_alpha", lambda x: f(edge_alpha_rad=x), alpha, 1e-8),
              ("d_beta", lambda x: f(beta_rad=x[0]), np.array([beta]), 1e-8),
              ("d_geometry", lambda x: f(geometry=x), geom, 1e-9),
              ("d_aperture", lambda x: f(aperture_t=x), t, 1e-8),
              ("d_illumination", lambda x: f(illumination=x), c, 1e-3)]
    for name, fun, x0, h in checks:
        got = getattr(jac, name)
        want = numeric(fun, x0, h).reshape(got.shape)
        np.testing.assert_allclose(got, want, atol=1e-5 * scale / max(np.max(np.abs(x0)), 1e-3), rtol=1e-4,
                                   err_msg=name)
    np.testing.assert_allclose(jac.d_gain, (sig - a0) / (1 + gain), rtol=1e-12)
    # bright diodes carry ~ I, dark ones ~ a0: the transmission is a blurred 0/1 pattern
    T = (sig - a0) / ((1 + gain) * (enc.illumination_basis(s, 2) @ c))
    assert T.min() > -1e-12 and T.max() < 1 + 1e-12 and T.max() > 0.99 and T.min() < 0.01

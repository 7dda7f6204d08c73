"""Encoder frame factor: analytic Jacobians against GTSAM's numerical derivatives at seeded random points (every
variable kind), zero error on exact simulated frames, and the H=None path (inside assert_factor_jacobians)."""
import math

import gtsam
import numpy as np
import pytest

from factor_checks import assert_factor_jacobians
from selfcal.factors import encoder as fenc
from selfcal.graphs.encoder import calibration as ge
from selfcal.models import encoder as enc
from selfcal.sim.encoder import EncoderScenario

SEEDS = [1, 2, 3, 4]
N_DIODES = 64


def setup(seed, with_all=True):
    rng = np.random.default_rng(seed)
    sc = EncoderScenario(l=6, n_diodes=N_DIODES, n_positions=4, cells_per_image=14, seed=seed)
    J = 1
    geometry = sc.geometry[0] + np.array([0, 0, 1e-4, -2e-4, 3e-4, 1e-4]) * rng.normal(size=6)
    beta = sc.beta_rad[J]
    edges, alpha = enc.visible_bars(sc.code, beta, geometry, sc.edges_rad, margin_s=0.3)
    const = fenc.FrameConstants(enc.diode_centres(N_DIODES), enc.edge_weights(sc.code, edges, geometry),
                                sc.edges_rad[edges], alpha - sc.edges_rad[edges], geometry, sc.aperture[0],
                                sc.illumination[0][J], sc.a0, offset_rad=0.0, kappa=0.8,
                                temperature_deviation_degC=1.7)
    s_e = enc.image_coordinate(alpha, beta, geometry).s
    active = np.abs(s_e) < 1.1
    keys = fenc.FrameKeys(
        beta=ge.B(J), edges=tuple(ge.EDGE(int(e)) if a else None for e, a in zip(edges, active)),
        geometry=ge.GEOMETRY(0), geometry_free=(0, 1, 4), aperture=ge.APERTURE(0),
        illumination=ge.ILLUMINATION(0, J), a0=ge.A0(0),
        offset=ge.OFFSET(1) if with_all else None, eccentricity=ge.ECCENTRICITY if with_all else None,
        temperature=ge.TEMPERATURE(0) if with_all else None, gain=ge.GAIN(0) if with_all else None)
    variables = {ge.B(J): np.array([beta + 1e-5 * rng.normal()]),
                 ge.GEOMETRY(0): geometry[[0, 1, 4]] * (1 + 1e-4 * rng.normal(size=3)),
                 ge.APERTURE(0): sc.aperture[0] * (1 + 0.05 * rng.normal(size=2)),
                 ge.ILLUMINATION(0, J): sc.illumination[0][J] * (1 + 0.02 * rng.normal(size=3)),
                 ge.A0(0): np.array([sc.a0 + rng.normal()])}
    for e, a in zip(edges, active):
        if a:
            variables[ge.EDGE(int(e))] = np.array([sc.edges_rad[e] + 1e-5 * rng.normal()])
    if with_all:
        variables.update({ge.OFFSET(1): np.array([1e-5 * rng.normal()]), ge.ECCENTRICITY: 1e-4 * rng.normal(size=2),
                          ge.TEMPERATURE(0): np.array([1e-4 * rng.normal()]),
                          ge.GAIN(0): 0.01 * rng.normal(size=N_DIODES)})
    return sc, J, keys, const, variables


@pytest.mark.parametrize("seed", SEEDS)
def test_frame_factor_jacobians(seed):
    sc, J, keys, const, variables = setup(seed)
    measured = np.zeros(N_DIODES)
    factor = fenc.frame_factor(gtsam.noiseModel.Isotropic.Sigma(N_DIODES, 2.0), measured, keys, const)
    # whitened by sigma = 2 counts; derivative steps 1e-6 in every tangent direction: angles move 1e-6 rad
    # (a fraction of a diode), so central differences are accurate to ~1e-4 of the largest entries
    assert_factor_jacobians(factor, variables, delta=1e-7, atol=2e-2, rtol=1e-3)


@pytest.mark.parametrize("seed", SEEDS)
def test_frame_factor_jacobians_base_model(seed):
    sc, J, keys, const, variables = setup(seed, with_all=False)
    factor = fenc.frame_factor(gtsam.noiseModel.Isotropic.Sigma(N_DIODES, 2.0), np.zeros(N_DIODES), keys, const)
    assert_factor_jacobians(factor, variables, delta=1e-7, atol=2e-2, rtol=1e-3)


@pytest.mark.parametrize("seed", SEEDS)
def test_frame_factor_zero_on_exact_frames(seed):
    """The factor at the true values reproduces the simulator's exact frame (to float rounding)."""
    sc = EncoderScenario(l=6, n_diodes=N_DIODES, n_positions=6, cells_per_image=14, seed=seed,
                         prnu_sigma=0.01)
    frames = sc.exact_frames()
    for J in range(sc.n_positions):
        g = sc.geometry[0]
        edges, alpha = enc.visible_bars(sc.code, sc.beta_rad[J], g, sc.edges_rad, margin_s=0.3)
        const = fenc.FrameConstants(enc.diode_centres(N_DIODES), enc.edge_weights(sc.code, edges, g),
                                    sc.edges_rad[edges], alpha - sc.edges_rad[edges], g, sc.aperture[0],
                                    sc.illumination[0][J], sc.a0, gain=sc.gain[0])
        keys = fenc.FrameKeys(beta=ge.B(J), edges=tuple(ge.EDGE(int(e)) for e in edges),
                              illumination=ge.ILLUMINATION(0, J))
        factor = fenc.frame_factor(gtsam.noiseModel.Isotropic.Sigma(N_DIODES, 2.0), frames[J], keys, const)
        values = gtsam.Values()
        values.insert(ge.B(J), np.array([sc.beta_rad[J]]))
        values.insert(ge.ILLUMINATION(0, J), sc.illumination[0][J])
        for e in edges:
            values.insert(ge.EDGE(int(e)), np.array([sc.edges_rad[e]]))
        assert np.max(np.abs(factor.unwhitenedError(values))) < 1e-9 * sc.intensity
        assert math.isclose(factor.error(values), 0.0, abs_tol=1e-18)

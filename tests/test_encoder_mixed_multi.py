"""Mixed calibration (reference angles as factors) and two arrays on one disk (unknown offset), and what each
makes observable: the eccentricity is separable from the graduation errors neither with one array nor with two
(with free edges it is a once-per-revolution graduation error up to the small ``q s`` term), but is with two
arrays once the edges are known from a previous calibration (a remount, the durable case).

Geometry as the patent's (half field of view ~0.16 rad: 13 of 255 cells on the array), so the ``q s`` term is
as small as on the real instrument.  Tolerances: estimates within 3 reported sigmas (two-sided 99.7 %).
"""

import numpy as np

from selfcal.baselines.encoder import patent_calibration
from selfcal.graphs.encoder import calibration as ge
from selfcal.pipelines import encoder as pe
from selfcal.sim.encoder import EncoderScenario, nominal_aperture

NARROW = dict(l=8, n_diodes=128, n_positions=90, cells_per_image=13.0)


def problem(sc, seed=0, offsets_error=1e-4):
    arrays = [ge.ArrayData(f"array{k}", sc.perturbed_frames(seed, k), np.array([sc.p_nominal, 0, 0, 0, 0, 0.0]),
                           nominal_aperture(sc.n_diodes), sc.offsets_rad[k] + (offsets_error if k else 0.0),
                           adc_max=sc.adc_max, noise_sigma=sc.noise_sigma) for k in range(sc.n_arrays)]
    return ge.decode_problem(sc.code, arrays)


def solve(sc, prob, edges_fixed=False):
    base = patent_calibration(prob.arrays[0].frames, sc.code, prob.arrays[0].geometry_nominal, sc.adc_max,
                              sc.noise_sigma)
    start = {"edges": sc.edges_rad if edges_fixed else base.edges_rad, "beta": base.beta_rad,
             "geometry": [base.geometry] + [prob.arrays[0].geometry_nominal] * (sc.n_arrays - 1)}
    return ge.calibrate(prob, ge.EncoderModel(edges_fixed=edges_fixed), covariance=False, start=start)


def test_two_arrays_offset_and_eccentricity_observability():
    one = EncoderScenario(seed=21, **NARROW)
    est1 = solve(one, problem(one))
    obs1 = ge.eccentricity_observability(problem(one), est1)
    assert not obs1.observable
    two = EncoderScenario(seed=21, n_arrays=2, **NARROW)
    prob2 = problem(two)
    est2 = solve(two, prob2)
    a1 = est2.arrays[1]
    assert abs(a1.offset_rad - two.offsets_rad[1]) < 3 * a1.offset_sigma_rad
    obs2 = ge.eccentricity_observability(prob2, est2)
    assert not obs2.observable   # free edges absorb it, one array or two
    fixed = ge.eccentricity_observability(prob2, solve(two, prob2, edges_fixed=True))
    assert fixed.observable and fixed.information_fraction > 100 * obs2.information_fraction


def test_mixed_calibration_reference_angles(tmp_path):
    sc = EncoderScenario(seed=22, **NARROW)
    sc.write(tmp_path / "rec", seed=0, reference={"every": 3, "sigma_rad": 2e-7, "offset_rad": 0.0123})
    from selfcal.io.recording import read_recording
    rec = read_recording(tmp_path / "rec")
    mixed = pe.calibrate_encoder(rec, covariance=False)
    pure = pe.calibrate_encoder(rec, use_reference=False, covariance=False)
    est = mixed.estimate
    assert abs(est.reference_offset_rad - 0.0123) < 3 * est.reference_offset_sigma_rad + 1e-12
    z = (est.edges_rad - sc.edges_rad)[1:] / est.edges_sigma_rad[1:]
    assert np.sqrt(np.mean(z**2)) < 1.5   # correlated edges: a loose band around 1
    # the reference ties the long-range (low-harmonic) part the self-calibration determines worst
    assert np.nanmedian(est.edges_sigma_rad[1:]) < 0.8 * np.nanmedian(pure.estimate.edges_sigma_rad[1:])

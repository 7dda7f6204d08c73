"""The score tests from the normal equations (``information_form``) against the dense ones they replace.

Both compute the same statistic in exact arithmetic; the normal equations square the condition number of the
column-equilibrated Jacobian (about 1e4 on these encoder graphs), so with double precision (eps 2.2e-16) the F
statistics agree to about 1e-12 relative; 1e-8 leaves four orders of margin and still catches any real
difference (a wrong projection or degree of freedom moves F by far more).
"""
import gtsam
import numpy as np
import pytest

from selfcal.audit import engine
from selfcal.core.solve import DegenerateDataError
from selfcal.pipelines import encoder as pe
from selfcal.sim.encoder import EncoderScenario

TINY = dict(l=5, n_diodes=64, n_positions=24, cells_per_image=12.0)


@pytest.fixture(scope="module")
def encoder_audit():
    sc = EncoderScenario(seed=12, prnu_sigma=0.01, response_compression=0.05, **TINY)
    rec, _ = sc.perturbed_measurements(0)
    system = pe.audit_system(rec, frames={"array0": sc.perturbed_frames(0)})
    search = engine._Search(system, engine.FAMILY_ALPHA, None)
    return system, search


def assert_same_tests(dense, information):
    for (f_dense, dof_dense, den_dense), (f_info, dof_info, den_info) in zip(dense, information):
        assert (dof_info, den_info) == (dof_dense, den_dense)
        assert f_info == pytest.approx(f_dense, rel=1e-8, abs=1e-9)


def test_catalog_score_test_equals_the_dense_one(encoder_audit):
    system, search = encoder_audit
    prnu = system.candidates()[0]
    graph, values, columns = engine.extend_one(system, search.fit, prnu)
    dense = engine.score_test(graph, values, columns)
    assert dense[0] > 10.0  # the hidden gain pattern: a test that can tell a wrong statistic from a right one
    assert_same_tests([dense], [engine.information_score_test(graph, values, columns)])


def test_library_score_tests_equal_the_dense_ones(encoder_audit):
    system, search = encoder_audit
    generic = search.generic_candidates()
    graph, values, groups = system.extend_all(search.fit, generic)
    assert_same_tests(engine.score_tests(graph, values, groups), engine.information_score_tests(graph, values, groups))


def test_columns_the_model_already_has_add_no_degree_of_freedom(encoder_audit):
    """A cubic on top of a fitted quadratic in the same driver: two of its three columns are in the model."""
    system, search = encoder_audit
    quadratic = next(c for c in search.generic_candidates() if c.term.label == "poly2(signal)")
    cubic = next(c for c in search.generic_candidates() if c.term.label == "poly3(signal)")
    fit = system.fit((quadratic,))
    graph, values, columns = engine.extend_one(system, fit, cubic)
    dense = engine.score_test(graph, values, columns)
    assert dense[1] == 1
    assert_same_tests([dense], [engine.information_score_test(graph, values, columns)])


def test_a_singular_base_is_refused():
    """x and y seen only as their sum: the base graph leaves x - y free."""
    x, y, z = gtsam.symbol("x", 0), gtsam.symbol("y", 0), gtsam.symbol("z", 0)
    graph = gtsam.NonlinearFactorGraph()

    def sum_error(this, values, H):
        if H is not None:
            H[0], H[1], H[2] = np.ones((1, 1)), np.ones((1, 1)), np.full((1, 1), 2.0)
        return np.array([values.atVector(x)[0] + values.atVector(y)[0] + 2 * values.atVector(z)[0] - 1.0])

    noise = gtsam.noiseModel.Isotropic.Sigma(1, 1.0)
    for _ in range(3):
        graph.add(gtsam.CustomFactor(noise, [x, y, z], sum_error))
    values = gtsam.Values()
    for key in (x, y, z):
        values.insert(key, np.zeros(1))
    with pytest.raises(DegenerateDataError):
        engine.information_score_test(graph, values, [(z, np.arange(1))])

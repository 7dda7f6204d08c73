"""Shared checks for custom factors: analytic Jacobians against GTSAM's numerical derivatives."""
import gtsam
import numpy as np
from gtsam.utils.numerical_derivative import numericalDerivative11


def make_values(variables: dict) -> gtsam.Values:
    values = gtsam.Values()
    for key, value in variables.items():
        values.insert(key, value)
    return values


def assert_factor_jacobians(factor, variables: dict, delta=1e-6, atol=1e-6, rtol=1e-5):
    """Whitened Jacobians of ``factor.linearize`` equal central differences through retract, key by key.

    Also checks that the ``H is None`` path (``whitenedError``) gives the error the Jacobian path linearised.
    """
    values = make_values(variables)
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(-b, factor.whitenedError(values), atol=1e-12, rtol=1e-12)
    column = 0
    for key in factor.keys():
        def whitened_error_at(x, key=key):
            moved = dict(variables)
            moved[key] = x
            return factor.whitenedError(make_values(moved))
        numerical = numericalDerivative11(whitened_error_at, variables[key], delta)
        width = numerical.shape[1]
        np.testing.assert_allclose(A[:, column:column + width], numerical, atol=atol, rtol=rtol,
                                   err_msg=f"Jacobian block of key {key}")
        column += width
    assert column == A.shape[1]

"""Patent seed 002 baseline: the patent's least squares recovers exact rotations and equals Wahba's solution."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from selfcal.baselines import imu_pair as p

G = 9.81


def gravity_directions(n, rng):
    """n static poses: gravity in the second sensor's frame, |a| = g."""
    return G * Rotation.random(n, random_state=rng).apply([0.0, 0.0, 1.0])


def rotation_angle_rad(R_a, R_b):
    return float(np.linalg.norm(Rotation.from_matrix(R_a @ R_b.T).as_rotvec()))


def test_patent_matrices_are_the_transposed_zxz_euler_rotation():
    """B C D with the patent's (passive) matrices = (Rz(phi) Rx(theta) Rz(psi))^T, built independently by scipy."""
    rng = np.random.default_rng(0)
    for phi, theta, psi in rng.uniform([-np.pi, 0, -np.pi], [np.pi, np.pi, np.pi], size=(10, 3)):
        expected = Rotation.from_euler("ZXZ", [phi, theta, psi]).as_matrix().T
        np.testing.assert_allclose(p.patent_rotation_3d(phi, theta, psi), expected, atol=1e-15)
    t = 0.7
    np.testing.assert_allclose(p.patent_rotation_2d(t), [[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])


def truth_rotations():
    """Random rotations plus the Euler singularities: identity, near identity, theta near 0 and near/at pi."""
    cases = list(Rotation.random(12, random_state=1).as_matrix())
    cases.append(np.eye(3))
    cases.append(Rotation.from_rotvec([1e-7, -2e-7, 3e-8]).as_matrix())
    cases.append(Rotation.from_rotvec([0.0, 1e-4, 0.0]).as_matrix())  # small tilt: theta ~ 1e-4, phi ~ +-90 deg
    cases.append(Rotation.from_rotvec([0.0, 0.0, 0.8]).as_matrix())  # PCB rotation about a shared z: theta = 0
    for phi, theta, psi in [(0.4, 1e-6, -1.1), (-2.0, np.pi - 1e-6, 0.3), (1.0, np.pi, 2.0)]:
        cases.append(Rotation.from_euler("ZXZ", [phi, theta, psi]).as_matrix().T)
    return cases


@pytest.mark.parametrize("n", [3, 12])
def test_exact_data_recover_the_rotation(n):
    rng = np.random.default_rng(2)
    for R_true in truth_rotations():
        a1 = gravity_directions(n, rng)
        a0 = a1 @ R_true.T
        result = p.rotation_3d(a0, a1)
        np.testing.assert_allclose(result.R_imu0_imu1, R_true, atol=1e-9)
        assert result.residual_rms < 1e-9 * G
        assert result.n_measurements == n
        phi, theta, psi = result.euler_rad
        assert 0.0 <= theta <= np.pi and -np.pi <= phi < np.pi and -np.pi <= psi < np.pi
        np.testing.assert_allclose(Rotation.from_euler("ZXZ", result.euler_rad).as_matrix().T, R_true, atol=1e-9)


def test_noisy_data_agree_with_wahba_svd_solution():
    """Same cost sum ||a0 - R a1||^2, so the same minimiser as Kabsch/Wahba (scipy align_vectors, SVD)."""
    rng = np.random.default_rng(3)
    for R_true in truth_rotations():
        n = int(rng.integers(4, 20))
        a1 = gravity_directions(n, rng)
        a0 = a1 @ R_true.T + rng.normal(scale=0.05, size=(n, 3))
        reference, _ = Rotation.align_vectors(a0, a1)
        result = p.rotation_3d(a0, a1)
        # Both are converged to round-off: the Gauss-Newton steps zero the gradient, not only the cost change.
        assert rotation_angle_rad(result.R_imu0_imu1, reference.as_matrix()) < 1e-11
        expected_rms = np.sqrt(np.sum((a0 - reference.apply(a1)) ** 2) / n)
        assert result.residual_rms == pytest.approx(expected_rms, rel=1e-9)


def test_scale_ratio_1d():
    rng = np.random.default_rng(4)
    a1 = rng.normal(size=7)
    assert p.scale_ratio_1d(2.5 * a1, a1) == pytest.approx(2.5, rel=1e-14)
    a0 = -0.8 * a1 + rng.normal(scale=0.1, size=7)
    expected = np.linalg.lstsq(a1[:, None], a0, rcond=None)[0][0]
    assert p.scale_ratio_1d(a0, a1) == pytest.approx(expected, rel=1e-12)
    assert p.scale_ratio_1d([3.0], [1.5]) == pytest.approx(2.0)  # one measurement suffices (patent)


def test_rotation_2d_exact_and_noisy():
    rng = np.random.default_rng(5)
    for t_true in [0.0, 0.3, -1.2, 3.1, -np.pi + 1e-9]:
        a1 = rng.normal(size=(1, 2))  # one measurement suffices (patent)
        a0 = a1 @ p.patent_rotation_2d(t_true).T
        angle, R = p.rotation_2d(a0, a1)
        assert abs(np.angle(np.exp(1j * (angle - t_true)))) < 1e-12
        np.testing.assert_allclose(a1 @ R.T, a0, atol=1e-12)
    # noisy: reference is Wahba in the plane; scipy's active rotation about z by alpha is the patent's t = -alpha
    a1 = rng.normal(size=(9, 2))
    a0 = a1 @ p.patent_rotation_2d(0.9).T + rng.normal(scale=0.05, size=(9, 2))
    pad = np.zeros((9, 1))
    reference, _ = Rotation.align_vectors(np.hstack([a0, pad]), np.hstack([a1, pad]))
    alpha = reference.as_rotvec()[2]
    angle, _ = p.rotation_2d(a0, a1)
    assert angle == pytest.approx(-alpha, abs=1e-12)


@pytest.mark.parametrize("dims,expected", [((1, 1), 1), ((2, 2), 1), ((3, 3), 3), ((3, 1), 1), ((1, 3), 1),
                                           ((2, 3), 1), ((3, 2), 1), ((1, 2), 1)])
def test_minimum_measurements(dims, expected):
    assert p.minimum_measurements(*dims) == expected


def one_line_error(func, *args, match):
    with pytest.raises(ValueError, match=match) as info:
        func(*args)
    assert "\n" not in str(info.value)


def test_errors_are_one_line():
    rng = np.random.default_rng(6)
    a = gravity_directions(2, rng)
    one_line_error(p.calibrate, a, a, match="at least 3 static measurement")
    one_line_error(p.rotation_3d, a, a, match="at least 3 static measurement")
    one_line_error(p.calibrate, np.zeros((0, 2)), np.zeros((0, 2)), match="at least 1 static measurement")
    one_line_error(p.calibrate, gravity_directions(4, rng), gravity_directions(5, rng), match="equal shape")
    one_line_error(p.calibrate, np.ones((4, 4)), np.ones((4, 4)), match="1-, 2- or 3-dimensional")
    one_line_error(p.minimum_measurements, 4, 3, match="1-, 2- or 3-dimensional")
    same = np.tile([0.0, 0.0, G], (5, 1))
    one_line_error(p.calibrate, same, same, match="one direction")
    one_line_error(p.calibrate_to_reference, {"a": same}, "b", match="reference sensor 'b'")


def test_calibrate_dispatches_on_dimension():
    rng = np.random.default_rng(7)
    a1 = rng.normal(size=5)
    assert p.calibrate(3.0 * a1, a1) == pytest.approx(3.0)
    b1 = rng.normal(size=(3, 2))
    angle, R = p.calibrate(b1 @ p.patent_rotation_2d(0.4).T, b1)
    assert angle == pytest.approx(0.4, abs=1e-12)
    c1 = gravity_directions(4, rng)
    R_true = Rotation.random(random_state=8).as_matrix()
    np.testing.assert_allclose(p.calibrate(c1 @ R_true.T, c1).R_imu0_imu1, R_true, atol=1e-9)


def test_more_sensors_against_one_reference():
    rng = np.random.default_rng(9)
    a_ref = gravity_directions(6, rng)
    truths = {name: Rotation.random(random_state=seed).as_matrix() for seed, name in enumerate(["b", "c", "d"])}
    # v_ref = R v_name  =>  v_name = R^T v_ref
    measurements = {"ref": a_ref, **{name: a_ref @ R for name, R in truths.items()}}
    results = p.calibrate_to_reference(measurements, "ref")
    assert set(results) == {"b", "c", "d"}
    for name, R in truths.items():
        np.testing.assert_allclose(results[name].R_imu0_imu1, R, atol=1e-9)

"""Predicted accuracy of a corrected scan: the propagation (against sampling) and its calibration (against the
simulator's truth, chi-square)."""
import numpy as np
import pytest
from scipy import stats

from scan_helpers import scan_data
from selfcal.core import so3
from selfcal.io.pointcloud import read_point_attribute, read_point_cloud, write_point_cloud
from selfcal.models import scan as ms
from selfcal.pipelines.scan import scan_problem, solve_scan, sphere_distances
from selfcal.sim.scan import ScanScenario, simulate_scan


def test_largest_eigenvalue_closed_form_matches_lapack():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(500, 3, 3))
    C = A @ np.swapaxes(A, 1, 2)
    C[0] = np.diag([2.0, 2.0, 2.0])  # triple root: p = 0
    C[1] = np.diag([1.0, 3.0, 3.0])  # double root on top
    C[2] = np.zeros((3, 3))
    expected = np.linalg.eigvalsh(C)[:, -1]
    # the trigonometric solution loses half the digits at a double root (arccos near 1): sqrt(eps) ~ 1.5e-8
    assert np.allclose(ms.largest_eigenvalue_sym3(C), expected, rtol=1e-7, atol=1e-14)


def test_point_sigmas_match_sampled_corrections():
    """The point sigma (worst direction) equals the spread of points placed by sampled error terms.

    Error terms drawn from N(theta, Sigma) (small: the correction is linear there), the corrected poses and points
    computed exactly; the sample covariance's largest eigenvalue from n = 4000 draws has a relative standard
    error of sqrt(2 / n) = 2.2 %; 4 of them (9 %) on the variance is 4.5 % on the sigma.  Points are given in a
    shuffled clock order (the function groups them itself)."""
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 10.0, 401)
    R_true = so3.exp(np.column_stack([0.01 * np.sin(t), 0.02 * np.cos(t), 0.1 * t]))
    gyro = np.column_stack([0.01 * np.cos(t), -0.02 * np.sin(t), np.full_like(t, 0.1)])
    accel = np.column_stack([0.3 * np.sin(t), 0.1 * np.cos(t), np.full_like(t, 9.81)])
    sens = ms.error_sensitivity(t, R_true, accel, gyro)
    r_ins = np.column_stack([0.5 * t, 0.1 * np.sin(t), np.zeros_like(t)])
    clocks = np.array([20, 150, 300, 400])
    Phi = sens.Phi[clocks][:, :, :15]
    A = rng.normal(size=(15, 15)) * ms.DEFAULT_PRIOR_SIGMAS * 0.3
    Sigma = A @ A.T
    theta = rng.normal(size=15) * ms.DEFAULT_PRIOR_SIGMAS * 0.1
    jitter = np.r_[np.full(3, 1e-5), np.full(3, 5e-5)]
    R, r, J = ms.corrected_pose(R_true[clocks], r_ins[clocks], Phi, theta, with_jacobian=True)
    pose_cov = ms.corrected_pose_covariance(J, Sigma, jitter)
    p_I = rng.normal(size=(len(clocks), 5, 3)) * 2.0
    points = np.einsum("mij,mkj->mki", R, p_I) + r[:, None, :]
    clock = np.repeat(np.arange(len(clocks)), 5)
    order = rng.permutation(len(clock))
    sigma = ms.point_error_sigmas(R, r, pose_cov, points.reshape(-1, 3)[order], clock[order])
    n = 4000
    draws = rng.multivariate_normal(theta, Sigma, n)
    sampled = np.empty((n, len(clocks), 5, 3))
    for k, th in enumerate(draws):
        Rk, rk = ms.corrected_pose(R_true[clocks], r_ins[clocks], Phi, th)
        Rk = Rk @ so3.exp(rng.normal(0.0, jitter[0], (len(clocks), 3)))
        rk = rk + np.einsum("mij,mj->mi", Rk, rng.normal(0.0, jitter[3], (len(clocks), 3)))
        sampled[k] = np.einsum("mij,mkj->mki", Rk, p_I) + rk[:, None, :]
    flat = sampled.reshape(n, -1, 3)
    empirical = np.array([np.sqrt(np.linalg.eigvalsh(np.cov(flat[:, i].T))[-1]) for i in range(flat.shape[1])])
    assert np.allclose(sigma, empirical[order], rtol=0.045)


def test_distance_sigmas_match_sampled_centres():
    """sigma of |c_i - c_j| against 20000 draws of the centres from their joint covariance (rel. error 1 %)."""
    rng = np.random.default_rng(2)
    centers = np.array([[0.0, 0.0, 0.0], [2.0, 0.5, 0.1], [5.0, -0.3, 0.4]])
    A = rng.normal(size=(9, 9)) * 1e-3
    C = A @ A.T
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    d, sigma = ms.distance_sigmas(centers, C, pairs)
    draws = rng.multivariate_normal(centers.ravel(), C, 20000).reshape(-1, 3, 3)
    sampled = np.linalg.norm(draws[:, pairs[:, 0]] - draws[:, pairs[:, 1]], axis=2)
    assert np.allclose(d, np.linalg.norm(centers[pairs[:, 0]] - centers[pairs[:, 1]], axis=1))
    assert np.allclose(sigma, sampled.std(axis=0), rtol=0.04)


SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def solved_scans():
    out = []
    for seed in SEEDS:
        sim = simulate_scan(ScanScenario(length_m=8.0, n_spheres=4, pixel_step=16), seed=seed)
        data = scan_data(sim)
        problem, solution, _ = solve_scan(data, scan_problem(data))
        out.append((sim, solution))
    return out


def test_sphere_distance_sigmas_are_calibrated_against_the_truth(solved_scans):
    """The consecutive sphere distances of each scan, their errors against the truth normalised by their joint
    predicted covariance: the sum over the scans is chi-square with (S - 1) x scans degrees of freedom when the
    prediction is honest; it must lie within the two-sided 99.9 % bounds (too large: optimistic sigmas, too small:
    pessimistic)."""
    total, dof = 0.0, 0
    for sim, sol in solved_scans:
        truth = sim.sphere_centers
        match = [int(np.argmin(np.linalg.norm(truth - c, axis=1))) for c in sol.centers]
        assert sorted(match) == list(range(len(truth)))
        S = len(sol.centers)
        G = np.zeros((S - 1, 3 * S))
        errors = np.empty(S - 1)
        for i in range(S - 1):
            g = sol.centers[i] - sol.centers[i + 1]
            G[i, 3 * i:3 * i + 3], G[i, 3 * i + 3:3 * i + 6] = g / np.linalg.norm(g), -g / np.linalg.norm(g)
            errors[i] = np.linalg.norm(g) - np.linalg.norm(truth[match[i]] - truth[match[i + 1]])
        cov = G @ sol.terms_centers_cov[15:, 15:] @ G.T
        total += errors @ np.linalg.solve(cov, errors)
        dof += S - 1
        # the reported per-pair sigma is the diagonal of that covariance
        reported = {(i, j): s for i, j, _, s in sphere_distances(sol)}
        assert np.allclose([reported[(i, i + 1)] for i in range(S - 1)], np.sqrt(np.diag(cov)))
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], dof)
    assert lo < total < hi, (total, dof, lo, hi)


def test_sigma_is_written_as_a_ply_property(tmp_path):
    points = np.random.default_rng(3).normal(size=(100, 3))
    points[7] = np.nan
    sigma = np.linspace(1e-4, 2e-3, 100)
    path = write_point_cloud(tmp_path / "scan.ply", points, attributes={"sigma_m": sigma})
    loaded = read_point_cloud(path, drop_nonfinite=True)
    back = read_point_attribute(path, "sigma_m")
    assert len(back) == len(loaded.cloud.points) == 99
    assert np.allclose(back, np.delete(sigma, 7), rtol=1e-6)  # float32 in the file
    assert read_point_attribute(path, "no_such_property") is None
    with pytest.raises(Exception, match=".ply only"):
        write_point_cloud(tmp_path / "scan.pcd", points[:5], attributes={"sigma_m": sigma[:5]})


def test_the_rigid_gauge_moves_the_scan_rigidly():
    """Along the heading gauge direction the error model turns every pose about the start: attitude error z,
    position error z x (r - r_0); checked on a curved, accelerating path (relative 1e-3: Euler steps)."""
    t = np.linspace(0.0, 20.0, 4001)
    v = np.column_stack([0.5 + 0.2 * np.sin(0.3 * t), 0.3 * np.cos(0.2 * t), 0.05 * np.sin(t)])
    r = np.concatenate([[np.zeros(3)], np.cumsum(v[:-1] * np.diff(t)[:, None], axis=0)])
    acc = np.gradient(v, t, axis=0)
    R = so3.exp(np.column_stack([0.01 * np.sin(t), 0.02 * np.cos(0.5 * t), 0.1 * t]))
    f = np.einsum("kji,kj->ki", R, acc - ms.GRAVITY_W_M_S2)
    w = np.vstack([so3.log(np.einsum("kji,kjl->kil", R[:-1], R[1:])) / np.diff(t)[:, None], np.zeros((1, 3))])
    Phi = ms.error_sensitivity(t, R, f, w).Phi[:, :, :15]
    z = Phi @ ms.rigid_gauge(v[0])[:, 3]
    expected_dr = np.cross([0.0, 0.0, 1.0], r - r[0])
    assert np.allclose(z[:, 0:3], [0.0, 0.0, 1.0], atol=1e-9)
    assert np.abs(z[:, 6:9] - expected_dr).max() < 1e-3 * np.abs(expected_dr).max()


def test_shape_covariance_is_what_remains_after_the_best_rigid_fit():
    """Draws of the error terms, from each the rigid part fitted by whitened least squares (Cholesky of Sigma,
    numpy lstsq) and removed: the covariance of what remains is the shape covariance (20000 draws: 1 % on a
    variance; compared with 5 % of the largest whitened variance)."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(15, 15)) * ms.DEFAULT_PRIOR_SIGMAS[:, None]
    Sigma = A @ A.T
    G = ms.rigid_gauge([0.5, 0.1, 0.0])
    shape = ms.shape_covariance(Sigma, G)
    L = np.linalg.cholesky(Sigma)
    draws = rng.multivariate_normal(np.zeros(15), Sigma, 20000)
    alpha = np.linalg.lstsq(np.linalg.solve(L, G), np.linalg.solve(L, draws.T), rcond=None)[0]
    remaining = draws - (G @ alpha).T
    scale = np.sqrt(np.diag(Sigma))
    assert np.allclose(np.cov(remaining.T) / np.outer(scale, scale), shape / np.outer(scale, scale), atol=0.05)


def test_the_plan_predicts_the_posterior_of_the_scan_it_plans(solved_scans):
    """The planner's linear covariance analysis (noise-free sphere profiles, no tunnel, graph linearised at the
    truth) gives the distance sigmas that solving the simulated scan of the same layout reports (within 5 %:
    detection keeps slightly different points, and the linearisation point differs by the estimation error)."""
    from selfcal.pipelines.scan import planned_problem, predicted_layout
    for seed, (sim, sol) in zip(SEEDS, solved_scans):
        sc = sim.scenario
        problem = planned_problem(sc, sc.error_sigmas, np.r_[np.full(3, sc.ins_jitter_rad), np.full(3, sc.ins_jitter_m)],
                                  seed=seed)
        assert np.allclose(problem.centers0, sim.sphere_centers)  # the same layout
        pairs, planned = predicted_layout(problem)
        posterior = {(i, j): s for i, j, _, s in sphere_distances(sol)}
        assert np.allclose(planned, [posterior[(i, j)] for i, j in pairs], rtol=0.05)


def test_plan_finds_the_largest_spacing_that_meets_the_tolerance(tmp_path):
    """``selfcal plan scan``: the layout it takes meets the tolerance and every layout with fewer spheres it
    evaluated exceeds it; exit 0, and 3 when nothing meets the tolerance (4 m: at most 3 spheres)."""
    import yaml

    from selfcal.cli.main import main
    assert main(["plan", "scan", "--length", "8", "--tolerance", "0.004", "--out", str(tmp_path / "plan.yaml")]) == 0
    plan = yaml.safe_load((tmp_path / "plan.yaml").read_text())
    chosen = next(c for c in plan["cases"] if c["spheres"] == plan["spheres"])
    assert plan["feasible"] and chosen["meets"] and chosen["bound_m"] <= 0.004
    assert all(not c["meets"] and c["bound_m"] > 0.004 for c in plan["cases"] if c["spheres"] < plan["spheres"])
    assert plan["largest_spacing_m"] == pytest.approx((8.0 - 3.0) / (plan["spheres"] - 1))
    assert main(["plan", "scan", "--length", "4", "--tolerance", "1e-5"]) == 3

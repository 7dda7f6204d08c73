"""Residual diagnostics: each test rejects what it should and, on noise, no more often than its level says.

Every statistical check here states its level.  On noise, 20 seeded series are tested at level 0.01: a
correct test rejects Binomial(20, 0.01) times, so at most 2 rejections are allowed (P(X >= 3) = 0.001, a
correct test fails this one time in a thousand seed sets; the seeds are fixed, so the outcome is
deterministic).  Planted effects are sized so that a correct test rejects them every time.
"""
import numpy as np
import pytest

from selfcal.audit.diagnostics import (binned_anova, cross_correlation_lag, diagnose, dominant_period, ljung_box,
                                       linear_dependence, normality)
from selfcal.audit.engine import ResidualFamily

LEVEL = 0.01
SEEDS = range(20)
MAX_FALSE = 2  # Binomial(20, 0.01): P(X >= 3) = 0.001


def family_of(y, coordinates, sigma=1.0, unit="m s^-2"):
    y = np.asarray(y, dtype=float).reshape(len(y), -1)
    return ResidualFamily("imu0", "accel", unit, y / sigma, y, {k: np.asarray(v) for k, v in coordinates.items()})


def ar1(rng, n, phi):
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for k in range(1, n):
        x[k] = phi * x[k - 1] + e[k]
    return x


# --- Ljung-Box ---------------------------------------------------------------------------------------------------

def test_ljung_box_rejects_ar1_and_accepts_white_noise():
    # AR(1) with phi = 0.5, n = 200: rho_1 = 0.5 alone gives Q ~ 200 * 0.25 = 50 >> chi2_10(0.99) = 23.2
    assert all(ljung_box(ar1(np.random.default_rng(s), 200, 0.5))[2] < LEVEL for s in SEEDS)
    false = sum(ljung_box(np.random.default_rng(s).normal(size=200))[2] < LEVEL for s in SEEDS)
    assert false <= MAX_FALSE


def test_ljung_box_statistic_by_hand():
    x = np.array([1.0, -1.0, 2.0, 0.0, -2.0, 1.0, 0.5, -0.5])
    d = x - x.mean()
    rho = [d[k:] @ d[:-k] / (d @ d) for k in (1, 2)]
    q_by_hand = 8 * 10 * (rho[0] ** 2 / 7 + rho[1] ** 2 / 6)
    q, h, p = ljung_box(x, lags=2)
    assert h == 2 and q == pytest.approx(q_by_hand, rel=1e-12) and 0 < p < 1


def test_ljung_box_too_short_is_nan():
    assert np.isnan(ljung_box([1.0, 2.0, 3.0])[2])


# --- normality ---------------------------------------------------------------------------------------------------

def test_normality_rejects_skewed_and_accepts_gaussian():
    # exponential: skewness 2, excess kurtosis 6; D'Agostino-Pearson at n = 200 rejects it every time
    assert all(normality(np.random.default_rng(s).exponential(size=200))[1] < LEVEL for s in SEEDS)
    false = sum(normality(np.random.default_rng(s).normal(size=200))[1] < LEVEL for s in SEEDS)
    assert false <= MAX_FALSE


def test_normality_small_samples_use_shapiro():
    assert normality(np.random.default_rng(0).normal(size=6))[0] == "shapiro"
    assert normality(np.random.default_rng(0).normal(size=30))[0] == "normaltest"


# --- dependence on a coordinate ---------------------------------------------------------------------------------

def coordinates(rng, n):
    return {"time_s": np.arange(n) * 3.0, "up_x": rng.uniform(-1, 1, n), "up_y": rng.uniform(-1, 1, n)}


def test_planted_slope_is_found_on_its_coordinate():
    n = 40
    for s in SEEDS:
        rng = np.random.default_rng(s)
        coords = coordinates(rng, n)
        # slope 2 sigma per unit over a +-1 coordinate: t ~ 2 * 0.58 * sqrt(40) ~ 7
        y = 0.002 * coords["up_x"] + 0.001 * rng.normal(size=n)
        (d,) = diagnose(family_of(y, coords, sigma=0.001))
        assert d["linear_coordinate"] == "up_x"
        assert d["linear_p"] < LEVEL
        assert d["linear_slope"] == pytest.approx(0.002, abs=5 * 0.001 / np.sqrt(n) / 0.58)


def test_no_dependence_found_on_noise():
    # linear_p and anova_p are Bonferroni-adjusted over the 3 coordinates, so each is a level-0.01 test
    false_linear = false_anova = 0
    for s in SEEDS:
        rng = np.random.default_rng(100 + s)
        (d,) = diagnose(family_of(rng.normal(size=40), coordinates(rng, 40)))
        false_linear += d["linear_p"] < LEVEL
        false_anova += d["anova_p"] < LEVEL
        assert d["n_coordinates"] == 3
    assert false_linear <= MAX_FALSE and false_anova <= MAX_FALSE


def test_binned_anova_finds_a_dependence_without_slope():
    for s in SEEDS:
        rng = np.random.default_rng(s)
        c = rng.uniform(-1, 1, 60)
        y = 3.0 * (c**2 - 1 / 3) + 0.3 * rng.normal(size=60)  # symmetric in c: no linear trend
        p_anova, groups = binned_anova(y, c)
        assert p_anova < LEVEL and groups >= 2
    slope, _ = linear_dependence(3.0 * (c**2 - 1 / 3), c)
    assert abs(slope) < 0.5


def test_ljung_box_on_time_order_not_storage_order():
    rng = np.random.default_rng(3)
    n = 50
    t = rng.permutation(n).astype(float)  # stored out of time order
    x = ar1(rng, n, 0.8)
    y = np.empty(n)
    y[np.argsort(t)] = x  # AR(1) in time, shuffled in storage
    (d,) = diagnose(family_of(y, {"time_s": t}))
    assert d["ljung_box_p"] < LEVEL  # found only if the series is put back in time order
    assert ljung_box(y)[2] > LEVEL  # storage order looks white


def test_mean_offset_and_rms():
    for s in SEEDS:
        rng = np.random.default_rng(s)
        y = 1.0 + rng.normal(size=50)  # offset of 1 sigma, n = 50: t ~ 7
        (d,) = diagnose(family_of(y, {"time_s": np.arange(50.0)}))
        assert d["mean_p"] < LEVEL
        assert d["mean"] == pytest.approx(y.mean()) and d["rms"] == pytest.approx(np.sqrt(np.mean(y**2)))
    false = sum(diagnose(family_of(np.random.default_rng(s).normal(size=50), {}))[0]["mean_p"] < LEVEL
                for s in SEEDS)
    assert false <= MAX_FALSE


def test_diagnose_one_dict_per_component():
    rng = np.random.default_rng(0)
    fam = ResidualFamily("imu0", "gyro", "rad s^-1", rng.normal(size=(20, 3)), 1e-3 * rng.normal(size=(20, 3)),
                         {"time_s": np.arange(20.0), "up_x": rng.uniform(-1, 1, 20)})
    rows = diagnose(fam)
    assert [r["component"] for r in rows] == ["x", "y", "z"]
    assert all(r["family"] == "imu0/gyro" and r["n"] == 20 and r["unit"] == "rad s^-1" for r in rows)


# --- periodogram ---------------------------------------------------------------------------------------------------

def test_dominant_period_finds_planted_period_in_uneven_sampling():
    for s in range(5):
        rng = np.random.default_rng(s)
        t = np.sort(rng.uniform(0.0, 100.0, 300))
        x = 3.0 + 0.7 * np.sin(2 * np.pi * t / 7.3 + 1.0) + rng.normal(size=t.size)
        period, fap = dominant_period(t, x)
        assert abs(1 / period - 1 / 7.3) < 1 / 100.0  # within one frequency resolution 1/T
        assert fap < 1e-6


def test_dominant_period_false_alarm_on_white_noise():
    # the FAP is a probability: on white noise it is below 0.01 about 1 % of the time
    false = 0
    for s in SEEDS:
        rng = np.random.default_rng(s)
        t = np.sort(rng.uniform(0.0, 100.0, 200))
        false += dominant_period(t, rng.normal(size=t.size))[1] < LEVEL
    assert false <= MAX_FALSE


# --- cross-correlation ------------------------------------------------------------------------------------------

def smooth_signal(seed):
    rng = np.random.default_rng(seed)
    f, phase, amp = rng.uniform(0.1, 5.0, 20), rng.uniform(0, 2 * np.pi, 20), rng.normal(size=20)
    return lambda t: np.sum(amp[:, None] * np.sin(2 * np.pi * f[:, None] * np.asarray(t)[None, :] + phase[:, None]),
                            axis=0)


@pytest.mark.parametrize("lag_s", [0.0237, -0.0412, 0.0041])
def test_cross_correlation_lag_recovers_sub_sample_lag(lag_s):
    dt = 0.01
    t = np.arange(0.0, 20.0, dt)
    a = smooth_signal(1)
    # b is a delayed copy: b(t) = a(t - lag); parabolic refinement to better than 0.05 sample
    assert cross_correlation_lag(t, a(t), a(t - lag_s)) == pytest.approx(lag_s, abs=0.05 * dt)
    noisy = a(t - lag_s) + 0.3 * np.random.default_rng(2).normal(size=t.size)
    assert cross_correlation_lag(t, a(t), noisy, max_lag=0.5) == pytest.approx(lag_s, abs=0.1 * dt)


def test_cross_correlation_lag_uneven_sampling():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.008, 0.012, 2000))
    a = smooth_signal(3)
    assert cross_correlation_lag(t, a(t), a(t - 0.0315)) == pytest.approx(0.0315, abs=0.002)


def test_diagnose_reports_a_periodic_term_in_time():
    """A 12 s sinusoid hidden in a family's residual (unevenly timed, white noise 1) shows as its period with
    a small false-alarm probability; the other component (noise only) does not."""
    from selfcal.audit.diagnostics import diagnose
    from selfcal.audit.engine import ResidualFamily
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 300, 400))
    periodic = 1.0 * np.sin(2 * np.pi * t / 12.0) + rng.normal(size=t.size)
    residual = np.stack([periodic, rng.normal(size=t.size)], axis=1)
    family = ResidualFamily("imu0", "gyro", "rad s^-1", residual, residual, {"time_s": t})
    with_period, noise_only = diagnose(family)
    assert abs(with_period["period_s"] - 12.0) < 12.0**2 / 300  # within one frequency bin 1/T
    assert with_period["period_fap"] < 1e-6
    assert noise_only["period_fap"] > 1e-3

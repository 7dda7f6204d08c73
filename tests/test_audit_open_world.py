"""The audit on effects no catalog lists: does it name them by driver and form, with their size, and only them?

Each test hides an effect outside every catalog in simulated data (the raw outputs of a recording are changed
after the simulation, the audit is not told), runs the audit blind and checks that

* it names the effect ``unlisted`` on the right residual with the right driver and form,
* the estimate agrees with the truth within the audit's own reported 1-sigma (3 sigma, two-sided 99.7 %),
* a catalog effect that merely resembles it is not named (a quadratic is not a ``bias_temperature``),
* it pays: lower residual on the fitted data and on held-out data.

Null recordings (nothing outside the base model) are the existing null tests of
``tests/test_audit_hidden_effects.py``, which now run with the library search too.
"""
from __future__ import annotations

import numpy as np
import pytest

from selfcal.audit import terms as library
from selfcal.audit.engine import run_audit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
from selfcal.audit.imu.static import ImuStaticAudit
from selfcal.core.inertial import ImuNoise
from selfcal.io.recording import Recording
from selfcal.sim.imu import ImuScenario, random_intrinsics
from selfcal.sim.trajectories import MultiPositionTrajectory

WHITE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
RATE_HZ = 100.0
N_POSES = 24
Z_MAX = 3.0
ACCEL_COLUMNS = ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
GYRO_COLUMNS = ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")


def warm_and_cold(duration_s: float, mean_degC: float = 25.0, swing_degC: float = 10.0):
    """A climate chamber's cycle: 25 -> 35 -> 15 -> 25 degC over the recording (not collinear with time, and a
    quadratic in it has no linear part a catalog slope could take)."""
    return lambda t_s: mean_degC + swing_degC * np.sin(2 * np.pi * np.asarray(t_s, dtype=float) / duration_s)


def recording(seed: int, temperature=True) -> tuple[ImuScenario, Recording]:
    """A multi-position recording, intrinsics inside the ``standard`` base, white noise, a temperature column."""
    trajectory = MultiPositionTrajectory(n_poses=N_POSES, seed=seed)
    accel, gyro = random_intrinsics(seed)
    scenario = ImuScenario(trajectory, accel=accel, gyro=gyro, noise=WHITE, rate_hz=RATE_HZ,
                           temperature=warm_and_cold(trajectory.duration_s) if temperature else None)
    return scenario, scenario.perturbed_measurements(seed)


def hide(rec: Recording, columns, offset) -> Recording:
    """Add ``offset`` (N, 3) to the raw columns of imu0: an effect the simulator knows nothing of."""
    values = rec.sensors["imu0"].values
    for j, name in enumerate(columns):
        values[name] = values[name] + offset[:, j]
    return rec


def audit(rec: Recording, base: str = "standard"):
    return run_audit(ImuIntrinsicsAudit(rec.imu("imu0"), 9.80665, base=base))


def names(findings) -> list[str]:
    return [f"{f['effect']}:{f.get('form', '')}({f.get('driver', '')})@{f['target']}" for f in findings]


def unlisted(findings, target: str) -> dict:
    hits = [f for f in findings if f["effect"] == "unlisted" and f["target"] == target]
    assert len(hits) == 1, names(findings)
    return hits[0]


def within(estimate, std, truth, what: str) -> None:
    estimate, std, truth = (np.asarray(x, dtype=float) for x in (estimate, std, truth))
    assert np.all(std > 0), (what, std)
    z = (estimate - truth) / std
    assert np.all(np.abs(z) < Z_MAX), f"{what}: z = {np.round(z, 2)}, estimate {estimate}, truth {truth}"


def assert_pays(finding: dict) -> None:
    gain = finding["gain"]
    assert gain["rms_after"] < gain["rms_before"], gain
    assert gain["heldout_rms_after"] < gain["heldout_rms_before"], gain
    assert gain["delta_bic"] < 0, gain


# --- 1. an accelerometer bias quadratic in temperature (a look-alike of bias_temperature) ------------------------

ACCEL_T2 = np.array([2e-4, -1.5e-4, 2.5e-4])  # m s^-2 per degC^2 about 25 degC


@pytest.mark.parametrize("seed", [0, 1])
def test_accel_bias_quadratic_in_temperature_is_named_not_as_bias_temperature(seed):
    scenario, rec = recording(seed)
    temperature = rec.sensors["imu0"].values["temperature"]
    rec = hide(rec, ACCEL_COLUMNS, np.outer((temperature - 25.0) ** 2, ACCEL_T2))
    result = audit(rec)
    found = unlisted(result.findings, "imu0/accel")
    assert (found["driver"], found["form"]) == ("temperature", "poly2"), names(result.findings)
    assert not [f for f in result.findings if f["effect"] == "bias_temperature"], names(result.findings)
    # truth about the fitted centre x0: c (T - 25)^2 = c (T - x0)^2 + 2 c (x0 - 25) (T - x0) + const
    x0 = found["estimate"]["x0"]
    linear, quadratic = found["estimate"]["coefficients"]
    sigma_linear, sigma_quadratic = found["std"]["coefficients"]
    within(quadratic, sigma_quadratic, ACCEL_T2, "quadratic coefficient")
    within(linear, sigma_linear, 2 * ACCEL_T2 * (x0 - 25.0), "linear coefficient")
    assert found["estimate"]["unit"] == "m s^-2" and "degC" in found["estimate"]["coefficient_unit"][1]
    assert_pays(found)


# --- 2. a gyro scale factor that changes with temperature -------------------------------------------------------

GYRO_SCALE_PER_DEGC = 2e-3  # relative, per degC, x axis


def test_gyro_scale_drifting_with_temperature_is_a_product_of_rate_and_temperature():
    seed = 2
    scenario, rec = recording(seed)
    values = rec.sensors["imu0"].values
    temperature = values["temperature"]
    offset = np.zeros((len(temperature), 3))
    offset[:, 0] = GYRO_SCALE_PER_DEGC * (temperature - 25.0) * values["w_RS_S_x"]
    result = audit(hide(rec, GYRO_COLUMNS, offset))
    found = unlisted(result.findings, "imu0/gyro_motion")
    assert (found["driver"], found["second_driver"], found["form"]) == ("w_x", "temperature", "product")
    # the product is w_x (T - T0): its x coefficient is the scale drift; y and z carry nothing
    x0_temperature = found["estimate"]["x0"][1]
    within(found["estimate"]["coefficient"], found["std"]["coefficient"], [GYRO_SCALE_PER_DEGC, 0.0, 0.0],
           "scale drift per degC")
    assert abs(x0_temperature - 25.0) < 10.0
    assert not [f for f in result.findings if f["effect"] in ("gyro_scale", "bias_temperature")], \
        names(result.findings)
    assert_pays(found)


# --- 3. a bias that jumps (a static log) ------------------------------------------------------------------------

GYRO_STEP = np.array([4e-4, -3e-4, 2e-4])  # rad s^-1


def static_recording(seed: int, duration_s: float = 240.0) -> Recording:
    """An IMU at rest, white noise, gyro bias jumping by ``GYRO_STEP`` at 62 % of the log (a mode change)."""
    from selfcal.io.recording import imu_sensor
    rng = np.random.default_rng(seed)
    n = int(duration_s * RATE_HZ)
    t_ns = np.arange(n, dtype=np.int64) * int(1e9 / RATE_HZ)
    accel_sigma, gyro_sigma = WHITE.white_sigma(RATE_HZ)
    accel = np.array([0.1, -0.2, 9.80665]) + accel_sigma * rng.standard_normal((n, 3))
    gyro = np.array([1e-3, 2e-3, -1e-3]) + gyro_sigma * rng.standard_normal((n, 3))
    gyro[int(0.62 * n):] += GYRO_STEP
    return Recording(None, {"imu0": imu_sensor("imu0", t_ns, gyro, accel, meta={"rate_hz": RATE_HZ})})


def test_a_bias_jump_in_a_static_log_is_a_step_in_time_with_its_size_and_place():
    result = run_audit(ImuStaticAudit(static_recording(0).imu("imu0")))
    found = unlisted(result.findings, "imu0/gyro")
    assert (found["driver"], found["form"]) == ("time", "step"), names(result.findings)
    assert abs(found["estimate"]["at"] - 0.62 * 240.0) < 0.1 * 240.0  # the change points tried are 12.5 % apart
    within(found["estimate"]["step"], found["std"]["step"], GYRO_STEP, "step size")
    assert not [f for f in result.findings if f["target"] == "imu0/accel"], names(result.findings)


def test_static_null_names_nothing_and_says_the_residual_is_at_the_noise_floor():
    rec = static_recording(1)
    values = rec.sensors["imu0"].values
    n = len(values["w_RS_S_x"])
    for j, name in enumerate(GYRO_COLUMNS):  # undo the jump: a clean static log
        values[name][int(0.62 * n):] -= GYRO_STEP[j]
    result = run_audit(ImuStaticAudit(rec.imu("imu0")))
    assert result.findings == [] and result.rejected == [], (names(result.findings), result.rejected)
    assert {r["verdict"] for r in result.remaining.values()} == {"noise_floor"}, result.remaining


# --- 4. the null: what is left is noise -------------------------------------------------------------------------------

def test_null_multi_position_names_nothing_and_its_residuals_are_at_the_noise_floor():
    """Intrinsics inside the base model only: no finding, nothing rejected, every family at the noise floor."""
    scenario, rec = recording(3, temperature=False)
    result = audit(rec)
    assert result.findings == [] and result.rejected == [], (names(result.findings), result.rejected)
    assert set(result.remaining) == {"imu0/accel", "imu0/gyro", "imu0/gyro_motion"}
    for verdict in result.remaining.values():
        assert verdict["verdict"] == "noise_floor", result.remaining
        assert 0.0 <= verdict["strongest"]["p_value"] <= 1.0


# --- 5. a warm-up: the gyro bias decays exponentially over the recording ---------------------------------------

WARM_UP = np.array([3e-3, -2e-3, 2.5e-3])  # rad s^-1 at switch-on


@pytest.mark.parametrize("seed", [0, 1])
def test_warm_up_is_a_polynomial_in_time_and_replaces_the_linear_bias_drift(seed):
    """``b(t) = b0 exp(-t / tau)``, tau half the recording: no catalog effect has this shape.  The linear
    ``bias_drift`` takes the slope first; the library's polynomial in time then explains it better and replaces
    it (``bias_drift`` rejected as outdone).  Its size is compared with the same polynomial fitted to the truth
    at the static poses (what the form can represent), within the reported sigma and the polynomial's own
    misfit of the exponential."""
    scenario, rec = recording(seed, temperature=False)
    sensor = rec.sensors["imu0"]
    t_s = (sensor.t_ns - sensor.t_ns[0]) * 1e-9
    tau = t_s[-1] / 2
    result = audit(hide(rec, GYRO_COLUMNS, np.outer(np.exp(-t_s / tau), WARM_UP)))
    found = unlisted(result.findings, "imu0/gyro")
    assert found["driver"] == "time" and found["form"] in ("poly2", "poly3"), names(result.findings)
    assert not [f for f in result.findings if f["effect"] == "bias_drift"], names(result.findings)
    assert ("bias_drift", "outdone") in [(r["effect"], r["reason"]) for r in result.rejected], result.rejected
    pose_t = result.final_fit.family("gyro").coordinates["time_s"]
    degree = int(found["form"][-1])
    truth_at_poses = np.exp(-pose_t / tau)
    fitted = np.polyval(np.polyfit(pose_t, truth_at_poses, degree), pose_t)
    misfit = float(np.max(np.abs(fitted - truth_at_poses)))  # the form's own error, per unit of b0
    ptp_truth = np.ptp(fitted) * np.abs(WARM_UP)
    ptp, sigma = np.abs(found["estimate"]["peak_to_peak"]), np.asarray(found["std"]["peak_to_peak"])
    assert np.all(np.abs(ptp - ptp_truth) < Z_MAX * sigma + 2 * misfit * np.abs(WARM_UP)), (ptp, ptp_truth, sigma)
    assert_pays(found)


# --- 6. the pair: a second-order nonlinearity of imu1's accelerometer -------------------------------------------

ACCEL_K2 = 0.004  # per m s^-2: a_x reads f_x + K f_x^2 (a stiffening proof mass)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pair_accelerometer_nonlinearity_is_named_by_imu1_specific_force_not_as_lever_arm(seed):
    """No catalog of the pair has a nonlinear accelerometer; it must be named in imu1's own f_x, and neither a
    lever arm nor a clock offset may be claimed.  Its size: the quadratic coefficient within 3 sigma."""
    from test_audit_hidden_effects import pair_scenario
    from selfcal.audit.imu_pair import ImuPairAudit
    from selfcal.graphs import imu_pair as gp
    rec = pair_scenario(seed).perturbed_measurements(seed)
    values = rec.sensors["imu1"].values
    error_x = ACCEL_K2 * values["a_RS_S_x"] ** 2
    values["a_RS_S_x"] = values["a_RS_S_x"] + error_x
    system = ImuPairAudit(rec.imu("imu0"), rec.imu("imu1"))
    result = run_audit(system)
    found = unlisted(result.findings, "imu1/pair_accel")
    assert found["driver"] == "f_x" and found["form"] in ("poly1", "poly2", "poly3"), names(result.findings)
    assert not [f for f in result.findings if f["effect"] in ("lever_arm", "time_offset")], names(result.findings)
    if found["form"] == "poly1":  # over a range of one sign the quadratic is a line: no curvature to size
        return
    # the truth as the form sees it: the audit low-passes both IMUs (5 Hz) before pairing, and the low-passed
    # square is not the square of the low-passed signal, so the quadratic fitted to the filtered error against the
    # filtered f_x (imu1's driver) is what the term can represent
    imu1 = rec.imu("imu1")
    filtered = gp.lowpass(error_x, imu1.rate_hz, 5.0)
    at = np.interp(system.dynamic.t0_s - system.initial_dt_s, imu1.t_s, filtered)
    k_truth = np.polyfit(system._drivers["f_x"] - found["estimate"]["x0"], at, 2)[0]
    # the pair residual lives in imu0's axes: imu1's x error appears along R's first column, so the curvature is
    # the norm of the per-axis quadratic coefficients (its sigma by the delta method), whatever the rotation
    c2, s2 = (np.asarray(found[k]["coefficients"][1]) for k in ("estimate", "std"))
    k2 = float(np.linalg.norm(c2))
    sigma = float(np.sqrt(np.sum((c2 / k2 * s2) ** 2)))
    assert abs(k2 - k_truth) < Z_MAX * sigma, (k2, k_truth, ACCEL_K2, sigma)


def test_the_harmonic_of_time_at_the_periodogram_peak_is_corrected_for_the_search():
    """On white noise the peak-frequency harmonic passes a single-frequency F test at 5 % every time (it is the
    maximum over ~n/2 frequencies); corrected for the band searched (Baluev), it passes about 5 % of the time.
    300 series: a 5 % rate gives 15 +- 3.8, so at most 27 (3 sigma) and the uncorrected rate at least 0.5."""
    from selfcal.audit import terms as library
    rng = np.random.default_rng(11)
    t = np.arange(400) * 0.02
    raw = corrected = 0
    for _ in range(300):
        w = rng.normal(size=t.size)
        term = next(x for x in library.terms_for([library.Coordinate("time", t, "s", "time")], w, t, products=False)
                    if x.form == "harmonic")
        p = library.f_pvalue(*library.residual_score(w, term.columns({"time": t})))
        raw += p < 0.05
        corrected += term.search_corrected(p) < 0.05
    assert raw >= 150, raw
    assert corrected <= 27, corrected
# --- 7. the pair: imu1's gyro scale drifting with its temperature (a look-alike of gyro_relative_gain) ----------

GYRO1_SCALE_PER_DEGC = 1.5e-4  # relative, per degC, imu1's x gyro: a MEMS gyro's sensitivity tempco (~2 % over
# 125 K); the measured sigma of the product's coefficient is 9.4e-6 per degC on this 40 s log (seed 0: 16 sigma)


@pytest.mark.parametrize("seed", [0, 1])
def test_pair_gyro_scale_drifting_with_temperature_is_a_product_of_imu1_rate_and_temperature(seed):
    """imu1's x gyro reads ``w_x (1 + k (T - 25))`` while the temperature cycles 25 -> 35 -> 15 -> 25 degC: its mean
    scale error is zero, so the catalog's constant ``gyro_relative_gain`` (the look-alike) must not be named, nor a
    clock offset; the term is imu1's ``w_x`` times ``temperature``.  In the pair residual (imu0's axes) the error is
    ``-R e_x k (T - 25) w_x``: the product's coefficient vector is ``-k R[:, 0]``, within 3 reported sigma."""
    from dataclasses import replace
    from test_audit_hidden_effects import pair_scenario
    from selfcal.audit.imu_pair import ImuPairAudit
    scenario = replace(pair_scenario(seed), temperature=warm_and_cold(40.0))
    rec = scenario.perturbed_measurements(seed)
    values = rec.sensors["imu1"].values
    rate_x = values["w_RS_S_x"] - scenario.gyro1.bias[0]  # imu1 has no scale or misalignment error here
    values["w_RS_S_x"] = values["w_RS_S_x"] + GYRO1_SCALE_PER_DEGC * (values["temperature"] - 25.0) * rate_x
    result = run_audit(ImuPairAudit(rec.imu("imu0"), rec.imu("imu1")))
    found = unlisted(result.findings, "imu1/pair_gyro")
    assert (found["driver"], found["second_driver"], found["form"]) == ("w_x", "temperature", "product"), \
        names(result.findings)
    assert not [f for f in result.findings if f["effect"] in ("gyro_relative_gain", "time_offset")], \
        names(result.findings)
    assert abs(found["estimate"]["x0"][1] - 25.0) < 1.0  # the cycle's mid-range: no constant scale left over
    within(found["estimate"]["coefficient"], found["std"]["coefficient"],
           -GYRO1_SCALE_PER_DEGC * scenario.R_imu0_imu1[:, 0], "scale drift per degC in imu0's axes")
    assert_pays(found)


@pytest.mark.parametrize("span_rad, orders", [(0.07, []), (0.3, [2.0]), (2.0, [1.0, 2.0])])
def test_an_angle_is_offered_the_harmonics_its_sweep_can_show(span_rad, orders):
    """A k-th harmonic needs k * span >= 0.5 rad: over 0.07 rad (a target's pitch steered by 2 deg) sin and cos
    of it are a line and a constant to 1e-4 of their amplitude, and the polynomials stand for them."""
    angle = library.Coordinate("pitch", np.linspace(-span_rad / 2, span_rad / 2, 50), "rad", "angle")
    offered = [t.params[0] for t in library.terms_for([angle], products=False) if t.form == "harmonic"]
    assert offered == orders
    assert {"poly1", "poly2", "poly3"} <= {t.form for t in library.terms_for([angle], products=False)}


@pytest.mark.parametrize("k", [1, 2, 3, 6])
def test_chi2_log_tail_is_scipys_where_that_does_not_underflow(k):
    """The evidence of effects whose p underflows ranks them by ``ln p`` from the tail's asymptotic series; where
    scipy's own ``logsf`` still works (x up to ~1400) the two agree to the series' next term, ``O((k/2)^2 / (x/2)^2)``
    (below 1e-3 at x >= 200)."""
    from scipy import stats
    from selfcal.audit.engine import chi2_log_tail
    for x in (200.0, 500.0, 1000.0, 1400.0):
        assert abs(chi2_log_tail(x, k) - stats.chi2.logsf(x, k)) < 1e-3, (x, k)


def test_a_lower_degree_explaining_as_much_has_the_stronger_evidence():
    """Measured on a scan (seed 2006): a linear term in range explained 2931.2 of whitened chi-square, the quadratic
    2931.4.  The quadratic's extra 0.2 is far below what its extra parameter buys by chance (chi-square 1: mean 1),
    so the linear term must rank first; with the tail's leading term ``-x/2`` alone it did not."""
    from selfcal.audit.engine import chi2_log_tail
    assert chi2_log_tail(2931.2, 1) < chi2_log_tail(2931.4, 2)
    assert chi2_log_tail(2931.2, 1) > chi2_log_tail(2931.2 + 12.0, 2)  # a real curvature (12 more) still wins


def test_the_summary_names_library_rivals_and_the_degree_a_finding_stepped_down_to(capsys):
    """A library rival in ``ambiguous_with`` is printed as its term (``poly1 in range``), not as ``unlisted``, which
    names none; a cubic rejected for the lower degree says which one outdid it."""
    from selfcal.cli.audit import print_summary
    gain = {"unit": "m", "rms_before": 2.0, "rms_after": 1.0, "heldout_rms_before": 2.1, "heldout_rms_after": 1.1}
    contract = {
        "findings": [{"effect": "unlisted", "meaning": "scan0/sphere cubic in time [s]", "target": "scan0/sphere",
                      "driver": "time", "form": "poly3", "gain": gain,
                      "ambiguous_with": [{"effect": "unlisted", "target": "scan0/sphere", "driver": "range",
                                          "form": "poly1", "delta_bic_vs_accepted": 1.0,
                                          "delta_chi2_vs_accepted": 1.0}]}],
        "rejected": [{"effect": "unlisted", "target": "imu0/tilt", "driver": "roll", "form": "poly3",
                      "reason": "outdone", "evidence": {"p_value": 1e-20},
                      "outdone_by": {"driver": "roll", "form": "poly2", "meaning": "imu0/tilt quadratic in roll"}}],
        "remaining": {}}
    print_summary(contract)
    out = capsys.readouterr().out
    assert "[ambiguous with poly1 in range]" in out, out
    assert "not accepted: poly3 in roll (imu0/tilt, p=1e-20)" in out and "(poly2 in roll)" in out, out

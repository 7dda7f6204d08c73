"""The audit on simulated recordings holding effects it is not told about: does it name them, and only them?

Each test plants effects outside the base model (single IMU: base ``standard`` = bias, scale, misalignment;
pair: base ``rotation`` = rotation and constant offsets), runs the audit blind and checks that

* it names each planted effect (and the residual it acts on),
* the estimate agrees with the truth within the audit's own reported 1-sigma,
* the gain is real: lower residual on the fitted data and on held-out data,
* on data with nothing outside the base it names nothing (the contract's "no finding is a valid answer").

Tolerances come from the reported covariance, not from tuning: every entry within 3 sigma (two-sided
99.7 %), and for the 9 entries of the g-sensitivity matrix the sum of squared z-scores below the chi-square
99.9 % quantile with 9 dof (the diagonal NEES; the entries' correlations are not in the contract).
Data carry white noise only: a bias random walk is ``bias_instability``, an effect of its own.  Channels that
carry an effect are not collinear with time (rise-then-fall temperature, fan-speed steps), except in the
ambiguity test, where collinearity is the point.

The full recall / false-finding study over many seeds is ``benchmarks/audit_recall.py``.
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from selfcal.audit.engine import run_audit
from selfcal.audit.imu_pair import ImuPairAudit
from selfcal.audit.imu.intrinsics import ImuIntrinsicsAudit
from selfcal.pipelines.audit import audit_recording
from selfcal.sim.imu import AuxChannel, ImuPairScenario, ImuScenario, random_intrinsics
from selfcal.core.inertial import ImuNoise
from selfcal.sim.trajectories import HandheldTrajectory, MultiPositionTrajectory

WHITE = ImuNoise(accelerometer_random_walk=0.0, gyroscope_random_walk=0.0)
RATE_HZ = 100.0
N_POSES = 24  # 10 s initial rest + 23 x (2 s move + 3 s pose) = 125 s
NULL_SEEDS = range(20)
PAIR_NULL_SEEDS = range(6)
Z_MAX = 3.0
# physics-level magnitudes of a consumer MEMS IMU (ADIS16448 class)
G_SENSITIVITY = 1e-4  # rad s^-1 per m s^-2 (~0.006 deg/s per g)
GYRO_TEMPERATURE_SLOPE = 1e-4  # rad s^-1 per degC
FAN_ACCEL_SLOPE = np.array([3e-5, -2e-5, 4e-5])  # m s^-2 per rpm
HEATER_GYRO_SLOPE = np.array([0.02, -0.03, 0.025])  # rad s^-1 per A
TIME_OFFSET_S = 0.007
LEVER_ARM_M = 0.08


# --- scenarios ------------------------------------------------------------------------------------------------

def rise_then_fall(duration_s: float, mean_degC: float = 25.0, swing_degC: float = 10.0):
    """Temperature that warms up and cools down again over the recording: not collinear with time."""
    return lambda t_s: mean_degC + swing_degC * np.sin(np.pi * np.asarray(t_s, dtype=float) / duration_s)


def fan_steps(t_s):
    """A fan switched between set-points every 20 s (rpm): steps, not a trend."""
    levels = np.array([1800.0, 2600.0, 2200.0, 3000.0, 1500.0, 2800.0, 2000.0])
    index = np.clip((np.asarray(t_s, dtype=float) // 20.0).astype(int), 0, len(levels) - 1)
    return levels[index]


def single_scenario(seed: int, warm_up_and_cool: bool = False, channels=None, **intrinsics) -> ImuScenario:
    """One IMU on the multi-position protocol with realistic bias/scale/misalignment plus the given extras;
    ``warm_up_and_cool`` records a :func:`rise_then_fall` temperature channel."""
    trajectory = MultiPositionTrajectory(n_poses=N_POSES, seed=seed)
    accel, gyro = random_intrinsics(seed, **intrinsics)
    temperature = rise_then_fall(trajectory.duration_s) if warm_up_and_cool else None
    return ImuScenario(trajectory, accel=accel, gyro=gyro, noise=WHITE, rate_hz=RATE_HZ, temperature=temperature,
                       channels=channels or {})


def audit_single(scenario: ImuScenario, seed: int, base: str = "standard"):
    recording = scenario.perturbed_measurements(seed)
    return run_audit(ImuIntrinsicsAudit(recording.imu("imu0"), scenario.gravity_m_s2, base=base))


def pair_scenario(seed: int, lever_arm_m: float = 0.0, dt_s: float = 0.0, realistic: bool = False):
    """Two IMUs on a 40 s hand-held motion.  Each has its own constant biases (in the pair base as relative
    offsets); ``realistic`` adds each IMU's scale and misalignment errors too (outside the pair catalog)."""
    extra = {} if realistic else {"scale": (0.0, 0.0), "misalignment_rad": 0.0, "gyro_axis_rotation_rad": 0.0}
    intrinsics = {}
    for suffix, sub_seed in (("0", 10 + seed), ("1", 20 + seed)):
        intrinsics["accel" + suffix], intrinsics["gyro" + suffix] = random_intrinsics(sub_seed, **extra)
    return ImuPairScenario.random(HandheldTrajectory(duration_s=40.0, seed=seed), seed, lever_arm_m=lever_arm_m,
                                  dt_s=dt_s, noise0=WHITE, noise1=WHITE, rate_hz=RATE_HZ, **intrinsics)


def audit_pair(scenario: ImuPairScenario, seed: int):
    recording = scenario.perturbed_measurements(seed)
    return run_audit(ImuPairAudit(recording.imu("imu0"), recording.imu("imu1")))


# --- checks ---------------------------------------------------------------------------------------------------

def names(findings) -> list[str]:
    return [f"{f['effect']}@{f['target']}" for f in findings]


def the_finding(findings, effect: str, target: str | None = None) -> dict:
    hits = [f for f in findings if f["effect"] == effect and (target is None or f["target"] == target)]
    assert len(hits) == 1, f"expected one {effect} finding (target {target}), the audit named {names(findings)}"
    return hits[0]


def z_scores(finding: dict, key: str, truth) -> np.ndarray:
    estimate = np.atleast_1d(np.asarray(finding["estimate"][key], dtype=float))
    std = np.atleast_1d(np.asarray(finding["std"][key], dtype=float))
    assert np.all(std > 0), finding["std"]
    return (estimate - np.ravel(truth)) / std


def assert_within_3_sigma(finding: dict, key: str, truth) -> None:
    z = z_scores(finding, key, truth)
    assert np.all(np.abs(z) < Z_MAX), (f"{finding['effect']} {key}: z = {np.round(z, 2)} "
                                       f"(estimate {finding['estimate'][key]}, truth {np.ravel(truth).tolist()})")


def assert_nees_999(finding: dict, key: str, truth) -> None:
    z = z_scores(finding, key, truth)
    assert np.sum(z**2) < chi2.ppf(0.999, z.size), f"{finding['effect']} {key}: z = {np.round(z, 2)}"


def assert_gain(finding: dict) -> None:
    gain = finding["gain"]
    assert gain["rms_after"] < gain["rms_before"], gain
    assert gain["heldout_rms_after"] < gain["heldout_rms_before"], gain
    assert gain["delta_bic"] < 0, gain


# --- 1. gyro g-sensitivity ------------------------------------------------------------------------------------

def test_gyro_g_sensitivity_is_named_estimated_and_pays():
    seed = 0
    scenario = single_scenario(seed, g_sensitivity=G_SENSITIVITY)
    run = audit_recording(scenario.perturbed_measurements(seed), "imu", base="standard")
    findings = run.result.findings
    assert names(findings) == ["gyro_g_sensitivity@imu0/gyro"]
    found = the_finding(findings, "gyro_g_sensitivity")
    assert found["sensor"] == "imu0"
    assert_nees_999(found, "matrix", scenario.gyro.A)
    assert_gain(found)
    # the contract: JSON as written by `selfcal audit --json`
    out = json.loads(json.dumps(run.to_json()))
    assert out["final_model"] == ["standard", "gyro_g_sensitivity"]
    assert [f["effect"] for f in out["findings"]] == ["gyro_g_sensitivity"]


# --- 2. temperature-driven gyro bias ---------------------------------------------------------------------------

def test_gyro_bias_temperature_is_named_with_its_slope():
    seed = 0
    scenario = single_scenario(seed, warm_up_and_cool=True, gyro_temperature_slope=GYRO_TEMPERATURE_SLOPE)
    findings = audit_single(scenario, seed).findings
    found = the_finding(findings, "bias_temperature", "imu0/gyro")
    assert found["estimate"]["target"] == "imu0/gyro"
    assert_within_3_sigma(found, "slope", scenario.gyro.temperature_slope)
    assert_gain(found)
    assert names(findings) == ["bias_temperature@imu0/gyro"]


# --- 3. clock offset between two IMUs -------------------------------------------------------------------------

def test_pair_time_offset_is_named_with_its_dt():
    seed = 0
    scenario = pair_scenario(seed, dt_s=TIME_OFFSET_S)
    findings = audit_pair(scenario, seed).findings
    found = the_finding(findings, "time_offset")
    assert_within_3_sigma(found, "dt_s", scenario.dt_s)
    assert_gain(found)
    assert names(findings) == ["time_offset@imu1/pair_gyro"]


# --- 4. lever arm between two IMUs ----------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 3001])
def test_pair_lever_arm_is_named_with_its_vector(seed):
    """Seed 3001 (benchmarks/audit_catalog_recall.py): while the centripetal term used imu0's raw rate, its
    0.01 rad/s bias left a residual linear in the rate, named as an unlisted term in w_y beside the lever arm."""
    scenario = pair_scenario(seed, lever_arm_m=LEVER_ARM_M)
    findings = audit_pair(scenario, seed).findings
    found = the_finding(findings, "lever_arm")
    assert_within_3_sigma(found, "r_m", scenario.r_m)
    assert_gain(found)
    assert names(findings) == ["lever_arm@imu1/pair_accel"]


def pair_axis_rotation_scenario(seed: int, rho_rad: float = 5e-3) -> ImuPairScenario:
    """Each IMU's gyro triad rotated by its own ~``rho_rad`` relative to its accelerometer triad, nothing else."""
    scenario = pair_scenario(seed)
    intrinsics = {}
    for suffix, sub_seed in (("0", 10 + seed), ("1", 20 + seed)):
        _, intrinsics["gyro" + suffix] = random_intrinsics(sub_seed, scale=(0.0, 0.0), misalignment_rad=0.0,
                                                           gyro_axis_rotation_rad=rho_rad)
    return replace(scenario, gyro0=replace(scenario.gyro0, M=intrinsics["gyro0"].M),
                   gyro1=replace(scenario.gyro1, M=intrinsics["gyro1"].M))


@pytest.mark.parametrize("seed", [0, 1])
def test_pair_accel_axis_rotation_is_named_with_its_vector(seed):
    """Gyro triads rotated in their IMUs (M_g = Exp(rho_k)): the gyros fix R = Exp(-rho0) R_true Exp(rho1), so the
    accelerometers see ``a0 = R (I + [R^T rho0 - rho1]x) a1`` to first order (rho ~ 5 mrad: second order 1e-5)."""
    scenario = pair_axis_rotation_scenario(seed)
    findings = audit_pair(scenario, seed).findings
    found = the_finding(findings, "accel_axis_rotation")
    rho0, rho1 = (Rotation.from_matrix(g.M).as_rotvec() for g in (scenario.gyro0, scenario.gyro1))
    assert_within_3_sigma(found, "rho_rad", scenario.R_imu0_imu1.T @ rho0 - rho1)
    assert_gain(found)
    assert names(findings) == ["accel_axis_rotation@imu1/pair_accel"]


# --- 5. an auxiliary channel of any name ----------------------------------------------------------------------

def test_fan_speed_channel_driving_accel_bias_is_named_with_its_target():
    seed = 0
    fan = AuxChannel(fan_steps, "rpm", accel_slope=FAN_ACCEL_SLOPE, reference=2200.0)
    scenario = single_scenario(seed, channels={"fan_speed": fan})
    findings = audit_single(scenario, seed).findings
    found = the_finding(findings, "channel:fan_speed")
    assert found["target"] == "imu0/accel"
    assert found["estimate"]["target"] == "imu0/accel"
    assert "rpm" in found["estimate"]["unit"]
    assert_within_3_sigma(found, "slope", FAN_ACCEL_SLOPE)
    assert_gain(found)


# --- 6. two effects at once -----------------------------------------------------------------------------------

def two_effect_single_scenario(seed: int) -> ImuScenario:
    return single_scenario(seed, warm_up_and_cool=True, g_sensitivity=G_SENSITIVITY,
                           gyro_temperature_slope=GYRO_TEMPERATURE_SLOPE)


def test_g_sensitivity_and_temperature_are_both_found():
    seed = 1
    findings = audit_single(two_effect_single_scenario(seed), seed).findings
    assert sorted(names(findings)) == ["bias_temperature@imu0/gyro", "gyro_g_sensitivity@imu0/gyro"]
    for found in findings:
        assert_gain(found)


def test_g_sensitivity_and_temperature_estimates_within_their_sigmas():
    """Each finding's estimate is the audit's answer for that effect: it must hold once the other is found.

    (An estimate taken while the other effect was still unmodelled carries that effect's bias.)"""
    seed = 1
    scenario = two_effect_single_scenario(seed)
    findings = audit_single(scenario, seed).findings
    assert_nees_999(the_finding(findings, "gyro_g_sensitivity"), "matrix", scenario.gyro.A)
    assert_within_3_sigma(the_finding(findings, "bias_temperature", "imu0/gyro"), "slope",
                          scenario.gyro.temperature_slope)


def test_pair_time_offset_and_lever_arm_are_both_found():
    seed = 0
    scenario = pair_scenario(seed, lever_arm_m=LEVER_ARM_M, dt_s=TIME_OFFSET_S)
    findings = audit_pair(scenario, seed).findings
    assert sorted(names(findings)) == ["lever_arm@imu1/pair_accel", "time_offset@imu1/pair_gyro"]
    assert_within_3_sigma(the_finding(findings, "time_offset"), "dt_s", scenario.dt_s)
    assert_within_3_sigma(the_finding(findings, "lever_arm"), "r_m", scenario.r_m)


# --- 7. nulls: nothing outside the base model -----------------------------------------------------------------

@pytest.mark.parametrize("seed", NULL_SEEDS)
def test_null_standard_intrinsics_no_finding(seed):
    """Bias, scale and misalignment only, all inside the ``standard`` base: nothing to find."""
    assert audit_single(single_scenario(seed), seed).findings == []


def test_pair_null_no_finding():
    """Rotation and per-IMU biases only (all inside the pair base), several seeds: nothing to find."""
    named = {seed: names(audit_pair(pair_scenario(seed), seed).findings) for seed in PAIR_NULL_SEEDS}
    assert all(not n for n in named.values()), named


def test_pair_null_with_scale_and_misalignment_names_no_lever_arm_or_time_offset():
    """Each IMU with its own scale and misalignment errors, no lever arm, no clock offset.

    The different gains are real and belong to the relative-gain entries of the pair catalog, and each IMU's
    gyro triad sits rotated (1 mrad) and sheared differently from its accelerometer triad, which is the pair
    catalog's accelerometer axis rotation; they must not be named as a lever arm, a clock offset or an unlisted
    term."""
    named = {seed: names(audit_pair(pair_scenario(seed, realistic=True), seed).findings)
             for seed in PAIR_NULL_SEEDS}
    allowed = {"accel_relative_gain@imu1/pair_accel", "gyro_relative_gain@imu1/pair_gyro",
               "accel_axis_rotation@imu1/pair_accel"}
    assert all(set(n) <= allowed for n in named.values()), named


# --- 8. a channel that is pure noise --------------------------------------------------------------------------

def white_voltage(seed):
    return lambda t_s: 5.0 + 0.05 * np.random.default_rng(seed).standard_normal(np.shape(t_s))


def wandering_voltage(seed):
    """A random walk in the supply voltage: slow, irregular, unrelated to the sensor."""
    return lambda t_s: 5.0 + np.cumsum(0.002 * np.random.default_rng(seed).standard_normal(np.shape(t_s)))


@pytest.mark.parametrize("seed, make", [(0, white_voltage), (1, white_voltage), (2, wandering_voltage)])
def test_noise_channel_is_not_named(seed, make):
    scenario = single_scenario(seed, channels={"supply_voltage": (make(100 + seed), "V")})
    findings = audit_single(scenario, seed).findings
    assert not [n for n in names(findings) if n.startswith("channel:")], names(findings)


# --- 9. ambiguity: a channel collinear with time --------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1])
def test_channel_collinear_with_time_is_reported_ambiguous(seed):
    """A heater current ramping linearly drives the gyro bias: a bias drift in time explains the data as well.

    The audit cannot tell them apart from these data; it must say so rather than pick one silently."""
    heater = AuxChannel(lambda t_s: 0.1 + 0.002 * np.asarray(t_s, dtype=float), "A",
                        gyro_slope=HEATER_GYRO_SLOPE, reference=0.2)
    findings = audit_single(single_scenario(seed, channels={"heater_current": heater}), seed).findings
    rivals = {"bias_drift", "channel:heater_current"}
    hits = [f for f in findings if f["effect"] in rivals and f["target"] == "imu0/gyro"]
    assert len(hits) == 1, names(findings)
    other = (rivals - {hits[0]["effect"]}).pop()
    reported = [(r["effect"], r["target"]) for r in hits[0].get("ambiguous_with", [])]
    assert (other, "imu0/gyro") in reported, hits[0].get("ambiguous_with")


# --- slow: the null over more seeds ---------------------------------------------------------------------------

@pytest.mark.slow
def test_null_false_finding_rate_over_many_seeds():
    """60 single-IMU and 30 pair nulls: the family-wise alpha per search step is 1 %, so at most a few."""
    single = [names(audit_single(single_scenario(seed), seed).findings) for seed in range(100, 160)]
    pair = [names(audit_pair(pair_scenario(seed), seed).findings) for seed in range(100, 130)]
    false = sum(len(n) for n in single + pair)
    # Poisson(0.9) (1 % of 90 recordings): P(N >= 5) < 0.3 %
    assert false <= 4, {"single": [n for n in single if n], "pair": [n for n in pair if n]}

"""The generic term library inside the tracker audit (selfcal.audit.tracker): hidden effects no catalog lists.

Each run is the short calibration run of tests/test_tracker_audit.py (20 s, bursts) with ONE effect planted in the
recording after simulation; the audit is not told.  It must name the effect as an ``unlisted`` term with the
right driver and form, size it within 3 of its own sigmas, and never name a look-alike catalog effect instead.
"""
import gtsam
import numpy as np
import pytest

from selfcal.audit.engine import run_audit
from selfcal.audit.tracker import TrackerAudit
from selfcal.factors import tracker as ft
from selfcal.pipelines.tracker import auxiliary_channels, estimator_for_audit
from selfcal.sim.tracker import TrackerScenario
from factor_checks import assert_factor_jacobians

X = gtsam.symbol_shorthand.X
CALIBRATION_RUN = dict(duration_s=20.0, seed=3, burst_rate_per_min=6.0, steer_angle_deg=(1.0, 2.0),
                       steer_period_s=(20.0, 40.0))


def test_term_columns_enter_the_calibrated_factors_with_exact_jacobians():
    rng = np.random.default_rng(1)
    unit = gtsam.noiseModel.Unit.Create
    u0, u1, w0 = gtsam.symbol("u", 0), gtsam.symbol("u", 1), gtsam.symbol("w", 0)
    pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.05, 3)), np.array([30.0, 0.0, 0.0]))
    z = rng.normal(0, 0.01, (4, 3)) + [30.0, 0.0, 0.0]
    G0, G1 = rng.normal(0, 1, (12, 1)), rng.normal(0, 1, (12, 1))
    f = ft.calibrated_prism_factor(unit(12), X(0), z, [0.12, -0.05, 0.25], rng.normal(0, 0.05, (4, 3)),
                                   term_columns=[(u0, G0), (u1, G1)])
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(u0, np.array([0.003]))
    values.insert(u1, np.array([-0.002]))
    assert_factor_jacobians(f, {X(0): pose, u0: np.array([0.003]), u1: np.array([-0.002])})
    plain = ft.calibrated_prism_factor(unit(12), X(0), z, [0.12, -0.05, 0.25], np.zeros((4, 3)))
    # e = pred + G c - z: the terms add their columns times their coefficients, nothing else changes
    np.testing.assert_allclose(f.unwhitenedError(values) - plain.unwhitenedError(values),
                               0.003 * G0[:, 0] - 0.002 * G1[:, 0], atol=1e-15)
    g = ft.calibrated_inclinometer_factor(unit(2), X(0), [0.01, -0.02], np.zeros(2), {}, {},
                                          term_columns=[(w0, 0.7 * np.eye(2))])
    assert_factor_jacobians(g, {X(0): pose, w0: np.array([1e-3, -2e-3])}, atol=1e-5)


def test_recording_channels_become_drivers_and_a_constant_one_is_skipped():
    """Every auxiliary column of the recording is a driver of both targets, interpolated to the rows' times; a
    constant one is offered too and left to the engine to skip with a note (Coordinate.usable)."""
    sc = TrackerScenario(duration_s=6.0, seed=3, burst_rate_per_min=6.0)
    rec = sc.measurements(seed=4)
    inc = rec.sensors["incl0"]
    t = (inc.t_ns - sc.t0_ns) * 1e-9
    inc.values["temperature"], inc.units["temperature"] = 20.0 + 0.5 * t, "degC"
    rec.sensors["tracker0"].values["supply"] = np.full(len(rec.sensors["tracker0"].t_ns), 24.0)
    rec.sensors["tracker0"].units["supply"] = "V"
    audit = TrackerAudit(estimator_for_audit(rec), channels=auxiliary_channels(rec))
    coordinates = audit.term_coordinates()
    assert set(coordinates) == {("tracker0", "position"), ("incl0", "tilt")}
    for target, drivers in coordinates.items():
        by_name = {c.name: c for c in drivers}
        assert {"time", "range", "azimuth", "elevation", "roll", "pitch", "yaw", "speed", "vibration",
                "temperature", "supply"} <= set(by_name), target
        temperature = by_name["temperature"]
        assert temperature.kind == "channel" and temperature.unit == "degC"
        # a linear channel interpolated at the rows' times is that line at those times (the time driver counts from
        # the audit's first keyframe, the channel from the recording's start)
        start_s = (audit.t0_ns - sc.t0_ns) * 1e-9
        np.testing.assert_allclose(temperature.values, 20.0 + 0.5 * (by_name["time"].values + start_s), atol=1e-9)
        assert temperature.usable is None
        assert "constant" in by_name["supply"].usable


def _plant_and_audit(plant, noise_seed=4, **scenario):
    sc = TrackerScenario(**{**CALIBRATION_RUN, **scenario})
    rec = sc.measurements(seed=noise_seed)
    plant(sc, rec)
    return run_audit(TrackerAudit(estimator_for_audit(rec)))


def _only_finding(result):
    assert len(result.findings) == 1, [(f["effect"], f.get("driver"), f.get("form")) for f in result.findings]
    return result.findings[0]


@pytest.mark.parametrize("moving", [False, True])
def test_the_speed_driver_knows_its_own_noise(moving):
    """Speed is the fit's velocity smoothed over 1 s; its noise is one keyframe's velocity error, estimated from
    what the smoother takes out.  Against the truth (the simulator's velocity at the keyframes) the estimate is
    within 30 % of the fit's rms error (measured 1.07 / 1.05 mm/s at rest, 1.17 / 1.05 moving).  A target at rest
    (the calibration run: speeds of 0.5-4 mm/s, sd 0.4 mm/s) has a speed that is its noise: the driver is skipped
    with a note; steered up and down by 5-10 cm (sd 59 mm/s) it is kept."""
    motion = dict(steer_position_m=(0.05, 0.1), steer_position_period_s=(4.0, 8.0),
                  steer_position_axes=(0.0, 0.0, 1.0)) if moving else {}
    sc = TrackerScenario(**{**CALIBRATION_RUN, **motion})
    audit = TrackerAudit(estimator_for_audit(sc.measurements(seed=4)))
    speed = {c.name: c for c in audit.term_coordinates()[("tracker0", "position")]}["speed"]
    v_true = sc.kinematics(audit.t_s + (audit.t0_ns - sc.t0_ns) * 1e-9)[2]
    v_fit = np.array([audit.base_values.atVector(gtsam.symbol_shorthand.V(k)) for k in range(audit.n_keyframes)])
    error = np.sqrt(np.mean(np.sum((v_fit - v_true) ** 2, axis=1)))
    assert speed.noise == pytest.approx(error, rel=0.3), (speed.noise, error)
    if moving:
        assert speed.usable is None
    else:
        assert "its own noise" in speed.usable, speed.usable


def test_audit_names_a_tracker_distance_error_proportional_to_range():
    """The tracker reads every distance (1 + k) times too long, k = 2 %.  The station sits 10 m below the line of
    advance and the target is steered up and down (5-10 cm at 4-8 s: no horizontal acceleration, which the base
    inclinometer model does not take), so the range varies by 12 cm.  What a run shows of k: its reported sigma is
    2.1e-3 (measured on this run), so 2 % is about 9 sigma.  (A ppm-size error moves a 30 m range by less than the
    noise: a constant along the line of sight is taken by the positions.)  The velocity columns are left true."""
    k = 0.02

    def plant(sc, rec):
        tr = rec.sensors["tracker0"]
        for axis, station in zip("xyz", sc.tracker_W):
            tr.values[axis] = station + (1.0 + k) * (tr.values[axis] - station)

    result = _plant_and_audit(plant, tracker_W_m=(0.0, 0.0, -10.0), steer_position_m=(0.05, 0.1),
                              steer_position_period_s=(4.0, 8.0), steer_position_axes=(0.0, 0.0, 1.0))
    f = _only_finding(result)
    assert (f["effect"], f["driver"], f["form"], f["target"]) == ("unlisted", "range", "poly1", "tracker0/position")
    est, std = f["estimate"]["coefficients"][0][0], f["std"]["coefficients"][0][0]
    assert abs(est - k) <= 3 * std, (est, std)
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]


@pytest.mark.parametrize("scenario_seed, noise_seed", [(3, 4), (2000, 3000)])
def test_audit_does_not_call_an_inclinometer_cross_coupling_a_prism_lever_arm(scenario_seed, noise_seed):
    """The inclinometer's roll reading picks up 3 % of its pitch reading (a cross-axis coupling no catalog entry
    is).  Roll and pitch are steered with 6-15 s periods, so over 20 s they vary independently (with 20-40 s periods
    both are one smooth arc and a roll term fits as well as a pitch term).  It must not be named
    ``lever_arm_prism``; it is the unlisted term linear in pitch, roll component 0.03 within 3 sigma.  On the
    second run (the benchmark's seed 2000) it was named a first harmonic in pitch, over a sweep of 0.07 rad where
    that is a line: harmonics now need the angle to sweep k * span >= 0.5 rad."""
    coupling = 0.03

    def plant(sc, rec):
        inc = rec.sensors["incl0"]
        inc.values["roll"] = inc.values["roll"] + coupling * inc.values["pitch"]

    result = _plant_and_audit(plant, noise_seed, seed=scenario_seed, steer_period_s=(6.0, 15.0))
    assert "lever_arm_prism" not in [f["effect"] for f in result.findings]
    f = _only_finding(result)
    assert (f["effect"], f["driver"], f["form"], f["target"]) == ("unlisted", "pitch", "poly1", "incl0/tilt")
    est, std = f["estimate"]["coefficients"][0][0], f["std"]["coefficients"][0][0]  # roll component
    assert abs(est - coupling) <= 3 * std, (est, std)


YAWED_RUN = dict(steer_angle_axes=(1.0, 1.0, 14.0), steer_period_s=(6.0, 15.0))  # +-51..57 deg of yaw


@pytest.mark.parametrize("scenario_seed, noise_seed", [(3, 4), (2003, 3003), (2008, 3008), (2015, 3015)])
def test_a_yawed_run_with_nothing_planted_shows_nothing(scenario_seed, noise_seed):
    """The null of the yaw test's run.  (1) Yawing at up to ~1 rad/s, the prism's rotation velocity R (w x r)
    changes within a keyframe; when the tracker's velocity samples were moved to the keyframe without that change,
    this run read a -29 +- 2 ms clock offset (p = 1e-36) and a line-of-sight distance drift (p = 1e-49).
    (2) The benchmark's yawed null 2003: the accelerometer's spread over 0.5 s, taken in each sample's body frame,
    counted the steering's tilt ramp as vibration, the inclinometer's predicted disturbance then weighed the
    accelerometer's noise at ~0.9, and an acceleration sensitivity of -0.98 +- 0.15 was named.  The audit's weight
    now comes from the spread with the target's rotation turned out.  (3) The benchmark's yawed null 2015: a burst's
    onset (15.1 s) tilts the inclinometer by 1-6e-4 rad before the accelerometer's spread around the samples shows
    it; with the nominal 8.7e-5 rad sigma there, its aliased 3.9 Hz named a harmonic in time (p = 1e-15).  The
    audit's sigma now counts the vibration the inclinometer's own samples after it show.  (4) The yawed null 2008:
    the target barely moves (0.5-6 mm/s), so a keyframe's speed was its velocity's noise, which its own block's
    position residuals share: a distance term of 0.14 m per m/s in speed (p = 4e-8).  Speed is now the velocity
    smoothed over 1 s."""
    result = _plant_and_audit(lambda sc, rec: None, noise_seed=noise_seed, **{**YAWED_RUN, "seed": scenario_seed})
    assert result.findings == [], [(f["effect"], f.get("driver"), f.get("form")) for f in result.findings]


@pytest.mark.parametrize("scenario_seed, noise_seed", [(3, 4), (2008, 3008), (2016, 3016)])
def test_audit_names_an_inclinometer_error_harmonic_in_yaw(scenario_seed, noise_seed):
    """The inclinometer reads roll + A sin(2 yaw + 0.5) and pitch - A/2 cos(2 yaw + 0.5), A = 4e-3 rad, while the
    target is yawed +-51..57 deg (steering weights (1, 1, 14), 6-15 s periods).  Over a yaw sweep of +-30 deg the
    second harmonic is a quadratic to the noise (measured: named poly2 in yaw); over +-55 deg it is not.  The
    reported amplitude sigma is 2.2e-4 rad (roll) on this run: A is ~18 sigma.  Named unlisted, harmonic of order
    2 in yaw; amplitudes and phases within 3 sigma (pitch: A/2 sin(2 yaw + 0.5 - pi/2)).  On the benchmark's 2008 the
    target stands still: its speed, the velocity's noise, named a distance term beside the harmonic (p = 7e-9) until
    a driver within its own noise was skipped.  On 2016, with a burst's onset counted as noise on samples the online
    pass had counted vibrating already, roll's amplitude read 6.7 +- 0.7 mrad."""
    amplitude, phase = 4e-3, 0.5

    def plant(sc, rec):
        inc = rec.sensors["incl0"]
        yaw = sc.kinematics((inc.t_ns - sc.t0_ns) * 1e-9)[5][:, 2]
        inc.values["roll"] = inc.values["roll"] + amplitude * np.sin(2 * yaw + phase)
        inc.values["pitch"] = inc.values["pitch"] - 0.5 * amplitude * np.cos(2 * yaw + phase)

    result = _plant_and_audit(plant, noise_seed, **{**YAWED_RUN, "seed": scenario_seed})
    f = _only_finding(result)
    assert (f["effect"], f["driver"], f["form"], f["target"]) == ("unlisted", "yaw", "harmonic", "incl0/tilt")
    assert f["estimate"]["order"] == 2.0
    est, std = f["estimate"], f["std"]
    np.testing.assert_array_less(np.abs(np.subtract(est["amplitude"], [amplitude, 0.5 * amplitude])),
                                 3 * np.asarray(std["amplitude"]))
    np.testing.assert_array_less(np.abs(np.subtract(est["phase_rad"], [phase, phase - np.pi / 2])),
                                 3 * np.asarray(std["phase_rad"]))

"""The ship's speed against the INS (issue 16, "speed log in knots: ship gyro bias 318 deg/h, exit 0").

The surge the speed shows must be what the accelerometer's forward axis feels: the slope of the 60 s means of f_x
on those of dv/dt is 1 in m/s, 1/1.944 in knots, 1/3.6 in km/h, 1/100 in cm/s (selfcal.core.sanity, "Speed").
A speed in another unit is refused in one line naming the unit; a voyage without speed changes to judge it by is
let through with a warning that says the unit could not be checked.  Voyages at 10 Hz (the 60 s means do not
depend on the rate) and 20 minutes long, to keep each test a few seconds.
"""
from __future__ import annotations

import logging
from dataclasses import replace

import pytest

from selfcal.cli.main import main
from selfcal.io.recording import RecordingError, write_recording
from selfcal.pipelines.ship import check_speed
from selfcal.sim.ship import ShipScenario, SmoothSteps

KNOTS, KM_H, CM_S = 1.0 / 0.514444, 3.6, 100.0
CANNOT = "cannot check the speed's unit: the voyage holds no speed change"


def voyage(kind, seed, duration_s=1200.0, **kw):
    return ShipScenario(kind=kind, duration_s=duration_s, seed=seed, rate_hz=10.0, **kw)


def speed_trial(seed):
    """A calm 15-minute voyage with two accelerations by 5 m/s over 60 s and two brakings over 40 s (0.08-0.13
    m/s^2 mean, as the turning voyages' surges), at constant heading."""
    scenario = voyage("calm", seed, duration_s=900.0)
    scenario.motion.surge = SmoothSteps([60.0, 240.0, 420.0, 600.0], [60.0, 40.0, 60.0, 40.0], [5.0, -5.0, 5.0, -5.0])
    return scenario.perturbed_measurements(seed + 100)


def scaled(rec, factor, sensor="speed0", column="speed_log"):
    s = rec.sensors[sensor]
    return replace(rec, sensors={**rec.sensors, sensor: replace(s, values={**s.values, column: s.values[column]
                                                                                * factor})})


def check(rec):
    check_speed(rec, rec.imu("imu0"))


@pytest.fixture(scope="module")
def turning():
    """Seed 1: a 20-minute turning voyage whose surges the check can judge (its slope's sigma 1.3 %, under the
    4 % the check needs); asserted below, not assumed."""
    return voyage("turning", 1).perturbed_measurements(101)


def test_the_turning_voyage_in_m_s_is_judged_and_passes(turning, caplog):
    with caplog.at_level(logging.WARNING):
        check(turning)
    assert not [r for r in caplog.records if "speed" in r.getMessage()], caplog.text


@pytest.mark.parametrize("factor, words", [(KNOTS, "in knots? multiply by 0.514444"), (KM_H, "in km/h? divide by 3.6"),
                                           (CM_S, "in cm/s? multiply by 0.01")])
def test_a_speed_log_in_other_units_is_refused_on_a_turning_voyage(turning, factor, words):
    with pytest.raises(RecordingError, match="speed0: its speed changes") as err:
        check(scaled(turning, factor))
    assert words in str(err.value) and "\n" not in str(err.value)


def test_a_gps_speed_in_knots_is_refused_when_there_is_no_speed_log(turning):
    gps_only = replace(turning, sensors={k: v for k, v in turning.sensors.items() if k != "speed0"})
    check(gps_only)
    with pytest.raises(RecordingError, match="gps0: its speed changes .* in knots"):
        check(scaled(gps_only, KNOTS, "gps0", "speed"))


@pytest.mark.parametrize("seed", range(3))
def test_knots_are_refused_on_an_accelerating_voyage(seed):
    rec = speed_trial(seed)
    check(rec)
    with pytest.raises(RecordingError, match="in knots"):
        check(scaled(rec, KNOTS))


@pytest.mark.parametrize("argv, option", [(["smooth", "ship"], "--out"),
                                          (["track", "--system", "ship", "--replay"], "--out-tum")])
def test_the_command_line_refuses_knots_in_one_line_and_writes_nothing(tmp_path, capsys, argv, option):
    rec = write_recording(scaled(speed_trial(0), KNOTS), tmp_path / "rec")
    out = tmp_path / "out.tum"
    assert main([*argv, str(rec), option, str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "speed0" in err[0] and "knots" in err[0] and "Traceback" not in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["calm", "turning", "heave"])
def test_a_speed_in_m_s_is_never_refused(kind):
    """Ten 20-minute voyages of each kind, in m/s: none refused.  Where judged, a refusal takes a t-statistic of 7
    with at least 18 degrees of freedom: probability 1e-6 a voyage, 3e-5 for all thirty (on 40 turning 30-minute
    voyages the statistic measured mean -0.02, std 1.09, largest 2.65).  Judged here: 6 of the 10 turning voyages;
    the calm and heave ones, at constant speed, none (they are let through with the warning)."""
    for seed in range(10):
        check(voyage(kind, 200 + seed).perturbed_measurements(300 + seed))


def test_a_voyage_without_speed_changes_says_it_cannot_check_the_unit(caplog):
    """Calm water, constant speed: knots cannot be told from m/s by the accelerometer, and the tool says so."""
    rec = scaled(voyage("calm", 4).perturbed_measurements(104), KNOTS)
    with caplog.at_level(logging.WARNING):
        check(rec)
    assert any(CANNOT in r.getMessage() and "speed0" in r.getMessage() for r in caplog.records), caplog.text

"""Ship audit (--system ship): a lever arm or a gyro scale hidden in simulated data is named and sized; a clean
voyage gives no finding (with every candidate of the catalog open, gyro_scale included).  The audit is not told what the simulation holds (it sees only the recording)."""
import numpy as np
import pytest
from scipy import stats

from selfcal.audit.engine import run_audit
from selfcal.audit.ship import ShipAudit
from selfcal.pipelines.ship import ship_inputs
from selfcal.sim.ship import ShipScenario

KEYFRAME_S = 1.0  # coarse keyframes keep the dozen refits of a search short; the lever arm shows at wave periods


def audit(kind, duration_s, seed=3, **scenario):
    rec = ShipScenario(kind=kind, duration_s=duration_s, seed=seed, **scenario).perturbed_measurements(100 + seed)
    return run_audit(ShipAudit(ship_inputs(rec), keyframe_s=KEYFRAME_S)).to_json()


def test_hidden_lever_arm_is_named_and_sized():
    truth = np.array([2.0, 0.5, 5.0])  # an accelerometer 5 m up a mast, 2 m forward
    result = audit("heave", 90.0, lever_arm_m=tuple(truth))
    effects = [f["effect"] for f in result["findings"]]
    assert effects[0] == "lever_arm", effects
    finding = result["findings"][0]
    error = np.array(finding["estimate"]["r_m"]) - truth
    sigma = np.array(finding["std"]["r_m"])
    # the three components against their reported sigmas: chi-square with 3 dof, 99.9 % quantile
    assert np.sum((error / sigma) ** 2) < stats.chi2.ppf(0.999, 3), (error, sigma)
    assert sigma[2] < 0.5  # the height is what roll and pitch show: determined to decimetres


def test_hidden_gyro_scale_is_named_and_sized():
    """A gyro reading 2 % high on x and y (roll and pitch axes) in a 90 s heave voyage: the attitude it carries
    over-rolls the waves by 2 %, which the accelerometer's tilt shows.  z (yaw) is seen only through the waves'
    small heading swings: its sigma stays at the prior's size, and it is checked the same way."""
    truth = np.array([0.02, 0.02, 0.0])
    result = audit("heave", 90.0, lever_arm_m=(0.0, 0.0, 0.0), gyro_scale=tuple(truth))
    assert [f["effect"] for f in result["findings"]] == ["gyro_scale"], result["findings"]
    finding = result["findings"][0]
    error = np.array(finding["estimate"]["scale"]) - truth
    sigma = np.array(finding["std"]["scale"])
    assert np.all(np.abs(error) < 3 * sigma), (error, sigma)
    assert np.all(sigma[:2] < 0.01)  # the waves size x and y to a fraction of the 2 %


def test_clean_voyage_gives_no_finding():
    result = audit("calm", 90.0, lever_arm_m=(0.0, 0.0, 0.0))
    assert result["findings"] == []
    assert result["system"] == "ship" and result["base_model"] == "attitude"


@pytest.mark.slow  # four minutes of turns and surges: ~1 min on 2 busy cores
@pytest.mark.parametrize("seed", [3, 3014])
def test_hidden_speed_log_scale_is_named_and_sized(seed):
    """The log reads 10 % high.  3014 (the catalog benchmark's voyage) named a term in ``imu0/tilt`` instead while
    the scale's regressor was smoothed by a quadratic over 15 s, which took too much of the turns' ramps."""
    result = audit("turning", 240.0, seed=seed, lever_arm_m=(0.0, 0.0, 0.0), speed_log_scale=1.10)
    assert [f["effect"] for f in result["findings"]] == ["speed_log_scale"]
    finding = result["findings"][0]
    assert abs(finding["estimate"]["scale"] - 0.10) < 3 * finding["std"]["scale"], finding


# --- effects no catalog lists (the generic term library) ----------------------------------------------------

G = 9.80665


def test_accelerometer_bias_following_the_heading_is_unlisted_harmonic_in_heading():
    """A body-frame accelerometer bias a (cos psi, sin psi, 0) (a heading-locked disturbance), a = 0.1 m/s^2, in
    5 min of turns.  Turned into the level frame by the heading it reads a (cos 2psi, sin 2psi) / g: the second
    harmonic of the heading, amplitude a / g in each tilt component (the graph's heading starts at 0, which only
    shifts the phase).  No catalog entry fits it; it must not be named as one."""
    a = 0.1
    result = audit("turning", 300.0, lever_arm_m=(0.0, 0.0, 0.0),
                   accel_bias_of=lambda t, e: a * np.column_stack([np.cos(e[:, 2]), np.sin(e[:, 2]), 0 * t]))
    assert [(f["effect"], f.get("driver"), f.get("form")) for f in result["findings"]] == [
        ("unlisted", "heading", "harmonic")], result["findings"]
    found = result["findings"][0]
    assert found["estimate"]["order"] == 2.0
    amplitude, sigma = np.array(found["estimate"]["amplitude"]), np.array(found["std"]["amplitude"])
    assert np.all(np.abs(amplitude - a / G) < 3 * sigma), (amplitude, sigma, a / G)


def test_a_heading_locked_bias_at_18_sigma_is_named_and_sized_on_the_seed_the_folds_missed():
    """The heading case on noise seed 2101 (voyage seed 2001 of benchmarks/audit_open_world_systems.py), where the
    term is 18.6 of its sigmas once fitted.  Two causes hid it: the wave-correlation inflation measured on
    residuals that still held it (p = 0.009; now scored with the inflation of the model that holds it), then the
    held-out check, which re-solved the held-out blocks on their own tilts so that their attitudes absorbed half of
    the bias (RSS 430 -> 638 with the right term).  Scored by their predictive chi-square instead
    (``PredictedFit``) the term is named, sized within 3 of its sigmas."""
    from selfcal.audit.engine import run_audit as run
    a = 0.1
    sc = ShipScenario(kind="turning", duration_s=300.0, seed=2001, lever_arm_m=(0.0, 0.0, 0.0),
                      accel_bias_of=lambda t, e: a * np.column_stack([np.cos(e[:, 2]), np.sin(e[:, 2]), 0 * t]))
    result = run(ShipAudit(ship_inputs(sc.perturbed_measurements(2101)), keyframe_s=1.0)).to_json()
    heading = [f for f in result["findings"] if f.get("driver") == "heading" and f["form"] == "harmonic"]
    assert heading, (result["findings"], result["rejected"])
    amplitude, sigma = np.array(heading[0]["estimate"]["amplitude"]), np.array(heading[0]["std"]["amplitude"])
    assert np.all(np.abs(amplitude - a / G) < 3 * sigma), (amplitude, sigma, a / G)


def test_a_heading_locked_bias_on_a_braking_voyage_is_named_alone():
    """Voyage seed 2003 of the heading suite (noise seed 2103) brakes at 0.47 m/s^2.  The surge acceleration the
    tilt is corrected by is the rate of a 1 Hz speed log (5 cm/s): off by 0.011-0.015 m/s^2 RMS (1.1-1.5 mrad of tilt,
    more than the accelerometer's noise), and a driver computed from that same rate carries the same error, so
    terms in it fitted the log's own noise (a cubic and a product in surge acceleration named beside the heading
    term, with the rate's sigma in the tilt sigma already).  With the rate's sigma stated and the driver the log's
    slow rate, the heading term is named, sized within 3 sigma, and nothing else.  With the rate's error weighed
    along the heading only, a cubic in the heading scored first (p = 4.3e-12 against the harmonic's 7.4e-12) and
    the harmonic was found on top of it: the backward elimination of library terms drops the cubic."""
    a = 0.1
    sc = ShipScenario(kind="turning", duration_s=300.0, seed=2003, lever_arm_m=(0.0, 0.0, 0.0),
                      accel_bias_of=lambda t, e: a * np.column_stack([np.cos(e[:, 2]), np.sin(e[:, 2]), 0 * t]))
    result = run_audit(ShipAudit(ship_inputs(sc.perturbed_measurements(2103)), keyframe_s=1.0)).to_json()
    assert [(f.get("driver"), f.get("form")) for f in result["findings"]] == [("heading", "harmonic")], \
        result["findings"]
    finding = result["findings"][0]
    amplitude, sigma = np.array(finding["estimate"]["amplitude"]), np.array(finding["std"]["amplitude"])
    assert np.all(np.abs(amplitude - a / G) < 3 * sigma), (amplitude, sigma, a / G)


@pytest.mark.parametrize("seed", [2018, 2019])
def test_null_heave_voyages_that_showed_structure_in_time_are_silent(seed):
    """The null voyages of benchmarks/audit_open_world_systems.py (noise seed 100 + seed) where the audit named a
    harmonic in time (2018) and a quadratic in the surge acceleration (2019) with nothing planted.  Two causes,
    both the base model's: the level-ship form of the hull's known acceleration (0.48 mrad RMS of tilt on exact
    data; the exact form leaves 0.05), and the stated 2 mrad tilt floor, four times what the voyage shows, which
    made the graph follow the gyro's integrated noise (structure in time).  With the hull acceleration exact and
    the floor measured on the voyage both stay silent."""
    rec = ShipScenario(kind="heave", duration_s=120.0, seed=seed, lever_arm_m=(0.0, 0.0, 0.0)).perturbed_measurements(
        100 + seed)
    system = ShipAudit(ship_inputs(rec), keyframe_s=1.0)
    assert system.options.tilt_floor_rad < 0.001  # measured: the simulated voyage has no sway
    result = run_audit(system).to_json()
    assert result["findings"] == [], result["findings"]
    assert "tilt noise floor measured" in result["notes"][0]


@pytest.mark.parametrize("seed", [2008, 2033])
def test_null_turning_voyages_do_not_read_a_speed_log_scale(seed):
    """The null turning voyages of benchmarks/audit_open_world_systems.py where the audit named a speed-log scale
    (+5.8 +- 1.6 % and +5.7 +- 1.5 % fitted alone) with the log exact: the gyro's white noise in the known hull
    acceleration ``v w`` sat in the residual and in the scale's regressor (errors in the variables).  With the
    regressor smoothed (a quartic over 20 s) both stay silent."""
    assert audit("turning", 300.0, seed=seed, lever_arm_m=(0.0, 0.0, 0.0))["findings"] == []


def test_accelerometer_bias_quadratic_in_roll_is_unlisted_not_a_gyro_scale():
    """y accelerometer bias c roll^2 (c = 5 m/s^2 per rad^2: a cross-axis nonlinearity), heave voyage.  A gyro
    scale error also tilts the level with the roll swing, but linearly: the look-alike must not be named.  The
    term's quadratic coefficient, as a horizontal vector (the level frame is turned by the start heading), has
    the size c / g."""
    c = 5.0
    result = audit("heave", 120.0, lever_arm_m=(0.0, 0.0, 0.0),
                   accel_bias_of=lambda t, e: np.column_stack([0 * t, c * e[:, 0] ** 2, 0 * t]))
    assert [(f["effect"], f.get("driver")) for f in result["findings"]] == [("unlisted", "roll")], result["findings"]
    found = result["findings"][0]
    assert found["form"] == "poly2"
    quadratic = np.array(found["estimate"]["coefficients"][1])
    sigma = np.array(found["std"]["coefficients"][1])
    size = np.linalg.norm(quadratic)
    size_sigma = np.sqrt(np.sum((quadratic / size * sigma) ** 2))  # first order, components' sigmas
    assert abs(size - c / G) < 3 * size_sigma, (size, size_sigma, c / G)


def test_generic_terms_have_keys_of_their_own():
    """A term next to the speed log's scale (symbol k0) in one graph: the terms' keys collided with it and the
    library search of a turning voyage crashed ("key k0 already exists")."""
    from selfcal.audit.engine import generic_candidate
    from selfcal.audit.terms import terms_for
    rec = ShipScenario(kind="turning", duration_s=60.0, seed=3, lever_arm_m=(0.0, 0.0, 0.0)).perturbed_measurements(103)
    system = ShipAudit(ship_inputs(rec), keyframe_s=1.0)
    speed = next(c for c in system.candidates() if c.effect == "speed_log_scale")
    fit = system.fit((speed,))
    coordinates = system.term_coordinates(fit)[("imu0", "tilt")]
    term = next(t for t in terms_for(coordinates) if t.form == "poly1")
    graph, values, groups = system.extend_all(fit, [generic_candidate(term, "imu0", "tilt", "rad")])
    assert len(groups) == 1 and all(values.exists(key) for key, _ in groups[0])


def test_folds_interleave_blocks_on_the_whole_gyro_chain():
    """Folds are alternate FOLD_BLOCK_S blocks (a heading or a time only one half of a voyage visits made a term's
    held-out check an extrapolation); each fold's fit carries every keyframe's attitude on the gyro chain (one
    heading gauge for all blocks) but has the tilt residuals of its own blocks only, and the held-out solve
    returns the other blocks' residuals."""
    from selfcal.audit.ship import FOLD_BLOCK_S
    from selfcal.graphs.ship import R_KEY
    rec = ShipScenario(kind="heave", duration_s=60.0, seed=3, lever_arm_m=(0.0, 0.0, 0.0)).perturbed_measurements(103)
    system = ShipAudit(ship_inputs(rec), keyframe_s=1.0)
    t = np.array([f.t_s for f in system.frames])
    block = ((t - t[0]) // FOLD_BLOCK_S).astype(int)
    for fold in (0, 1):
        fit = system.fit((), fold)
        times = fit.families[0].coordinates["time_s"]
        assert set(block[np.isin(t, times)] % 2) == {fold}  # its own blocks' tilts only ...
        assert len(set(block[np.isin(t, times)])) >= 1 + (fold == 0)  # ... from blocks spread over the voyage
        assert all(fit.values.exists(R_KEY(j)) for j in range(len(t)))  # every attitude, on one gyro chain
        held = system.heldout(fit, fold)[0]
        assert len(held.whitened) + len(times) == len(t)
        assert set(block[np.isin(t, held.coordinates["time_s"])] % 2) == {1 - fold}


def test_a_gyro_stated_noiseless_is_refused_in_one_line():
    """sensor.yaml with gyroscope_noise_density 0 (a user's typo): the gyro chain would be called exact and the
    audit's least squares broke inside numpy (LinAlgError, measured); it is refused with the reason instead."""
    from selfcal.io.recording import RecordingError
    rec = ShipScenario(kind="heave", duration_s=30.0, seed=3, lever_arm_m=(0.0, 0.0, 0.0)).perturbed_measurements(103)
    rec.sensors["imu0"].meta["gyroscope_noise_density"] = 0.0
    with pytest.raises(RecordingError, match="gyroscope_noise_density must be positive"):
        ship_inputs(rec)

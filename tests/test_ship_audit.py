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


def audit(kind, duration_s, **scenario):
    rec = ShipScenario(kind=kind, duration_s=duration_s, seed=3, **scenario).perturbed_measurements(103)
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
def test_hidden_speed_log_scale_is_named_and_sized():
    result = audit("turning", 240.0, lever_arm_m=(0.0, 0.0, 0.0), speed_log_scale=1.10)  # the log reads 10 % high
    assert [f["effect"] for f in result["findings"]] == ["speed_log_scale"]
    finding = result["findings"][0]
    assert abs(finding["estimate"]["scale"] - 0.10) < 3 * finding["std"]["scale"], finding

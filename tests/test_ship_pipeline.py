"""`selfcal smooth ship` end to end on a short simulated voyage: the TUM file, and attitudes near the truth."""
import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.cli.main import main
from selfcal.sim.ship import ShipScenario


def test_smooth_ship_writes_a_tum_trajectory_near_the_truth(tmp_path, capsys):
    scenario = ShipScenario(kind="heave", duration_s=180.0, seed=5, lever_arm_m=(0.0, 0.0, 0.0))
    rec_path = scenario.write(tmp_path / "voyage", seed=6)
    out = tmp_path / "attitude.tum"
    assert main(["smooth", "ship", str(rec_path), "--out", str(out)]) == 0
    rows = np.loadtxt(out)
    assert rows.shape[1] == 8 and np.all(rows[:, 1:4] == 0)
    t_s = rows[:, 0] - scenario.t0_ns * 1e-9
    roll, pitch, _ = Rotation.from_quat(rows[:, 4:]).as_euler("ZYX")[:, ::-1].T
    true_roll, true_pitch, _ = scenario.truth_attitude(t_s)
    # heave changes |f| only and the lever arm is zero here: the tilt factors see gravity's direction plus the
    # small wave-induced horizontal accelerations (< 0.1 m/s^2 ~ 0.6 deg); smoothed with the gyro, 0.2 deg RMS
    assert np.degrees(np.sqrt(np.mean((roll - true_roll) ** 2))) < 0.2
    assert np.degrees(np.sqrt(np.mean((pitch - true_pitch) ** 2))) < 0.2
    assert "attitudes" in capsys.readouterr().out

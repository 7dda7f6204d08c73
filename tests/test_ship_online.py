"""Live ship estimation: samples pushed one by one (as `selfcal track --system ship` does) give the attitude
of a simulated voyage, close to the truth and to the replayed fixed-lag smoother."""
import json

import numpy as np

from selfcal.cli.main import main
from selfcal.io.recording import read_recording
from selfcal.io.streams import replay
from selfcal.pipelines.ship import OnlineShipTracker
from selfcal.sim.ship import ShipScenario


def test_pushed_samples_track_the_truth(tmp_path):
    scenario = ShipScenario(kind="heave", duration_s=120.0, seed=5)
    scenario.write(tmp_path / "rec", seed=6)
    rec = read_recording(tmp_path / "rec")
    tracker = OnlineShipTracker({name: s.meta for name, s in rec.sensors.items()})
    outputs = [out for name, t_ns, values in replay(rec) for out in tracker.push(name, t_ns, values)]
    t_s = np.array([o["t_ns"] for o in outputs]) * 1e-9 - scenario.t0_ns * 1e-9
    roll, pitch, _ = scenario.truth_attitude(t_s)
    late = t_s > 20.0  # after the start-up (the bias and the lever arm are unknown at first)
    err = np.degrees(np.stack([[o["roll_rad"] for o in outputs], [o["pitch_rad"] for o in outputs]], axis=1)
                     - np.stack([roll, pitch], axis=1))[late]
    # the tilt factor's floor is 0.01 rad per keyframe; the gyro chain averages 5 keyframes per second: 0.2 deg
    # RMS is a loose physics bound (the benchmark measures ~0.06 deg)
    assert np.sqrt(np.mean(err**2)) < 0.2
    assert all(o["delay_s"] < 1.1 for o in outputs)  # half the 2 s angular-acceleration window, plus one sample
    cov = np.array(outputs[-1]["covariance"])
    assert np.all(np.linalg.eigvalsh(cov[3:, 3:]) > 0)


def test_track_command_replays_a_ship_recording(tmp_path, capsys):
    ShipScenario(kind="calm", duration_s=30.0, seed=1).write(tmp_path / "rec", seed=2)
    assert main(["track", "--system", "ship", "--replay", str(tmp_path / "rec"), "--out-tum", str(tmp_path / "p.tum"),
                 "--out-jsonl", str(tmp_path / "p.jsonl")]) == 0
    lines = (tmp_path / "p.jsonl").read_text().splitlines()
    assert len(lines) > 100  # 5 keyframes per second over ~29 s
    first = json.loads(lines[0])
    assert set(first) >= {"t_ns", "position", "quaternion", "covariance"}
    assert len((tmp_path / "p.tum").read_text().splitlines()) >= len(lines)


def test_live_tracker_without_a_speed_log_reports_the_speed_the_turns_show(tmp_path):
    """Only the IMU is pushed (speed log and GPS left out): every output carries the unknown speed and its
    sigma, and over the turns (|yaw rate| > 1 deg/s, once the first 10 s of the first have shown the speed) it
    is within 5 % RMS of the truth, the accuracy the model grants a speed log (as the replayed smoother in
    tests/test_ship_graph.py, on the same voyage).  The bound does not hold on every voyage: on a 200 s one
    (first turn also at 60 s, 14.9 m/s) the filter ran 7-10 % high for 30 s, 7 % RMS -- a steady turn cannot
    tell a roll offset from a speed error, only the gyro can (docs/ship.md)."""
    scenario = ShipScenario(kind="turning", duration_s=600.0, seed=3)
    scenario.write(tmp_path / "rec", seed=103)
    rec = read_recording(tmp_path / "rec")
    tracker = OnlineShipTracker({"imu0": rec.sensors["imu0"].meta})
    outputs = [out for name, t_ns, values in replay(rec) if name == "imu0"
               for out in tracker.push(name, t_ns, values)]
    assert all("speed_m_s" in o and o["speed_sigma_m_s"] > 0 for o in outputs)
    t_s = np.array([o["t_ns"] for o in outputs]) * 1e-9 - scenario.t0_ns * 1e-9
    true_speed, _ = scenario.motion.speed(t_s)
    _, _, (_, yaw_rate, _) = scenario.motion.euler(t_s)
    turning = np.abs(yaw_rate) > np.radians(1.0)
    shown = turning & (t_s > t_s[np.argmax(turning)] + 10.0)
    assert shown.sum() > 200
    speed = np.array([o["speed_m_s"] for o in outputs])
    relative = np.sqrt(np.mean((speed[shown] - true_speed[shown]) ** 2)) / np.mean(true_speed[shown])
    assert relative < 0.05, relative

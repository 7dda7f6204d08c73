"""Use case ``selfcal smooth ship``: a vessel recording in, attitude and gyro bias out (TUM trajectory)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.graphs.ship import ShipEstimate, ShipGraphOptions, ShipInputs, ShipSmoother
from selfcal.io.recording import Recording, RecordingError
from selfcal.models import imu

SPEED_SOURCES = (("speed0", "speed_log"), ("gps0", "speed"))  # preferred first: the log measures through water


def ship_inputs(recording: Recording, imu_name: str = "imu0") -> ShipInputs:
    """IMU samples of ``imu_name`` and the speed (speed log, else GPS speed) interpolated onto their times."""
    data = recording.imu(imu_name)
    speed = None
    for sensor, column in SPEED_SOURCES:
        if sensor in recording.sensors and column in recording.sensors[sensor].values:
            s = recording.sensors[sensor]
            speed = np.interp(data.t_ns.astype(float), s.t_ns.astype(float), s.values[column])
            break
    meta = data.meta
    return ShipInputs(data.t_s, data.gyro_rad_s, data.accel_m_s2, speed,
                      float(meta.get("gravity_m_s2", imu.STANDARD_GRAVITY_M_S2)),
                      float(meta.get("gyroscope_noise_density", 1e-4)),
                      float(meta.get("gyroscope_random_walk", 1e-5)))


def smooth_ship(recording: Recording, online: bool = False, remove_known_acceleration: bool = True,
                imu_name: str = "imu0") -> ShipEstimate:
    inputs = ship_inputs(recording, imu_name)
    if len(inputs.t_s) < 10:
        raise RecordingError(f"{imu_name}: too few samples for a voyage ({len(inputs.t_s)})")
    smoother = ShipSmoother(inputs, ShipGraphOptions(remove_known_acceleration=remove_known_acceleration))
    return smoother.online() if online else smoother.batch()


def tum_text(estimate: ShipEstimate, t0_ns: int = 0) -> str:
    """TUM trajectory lines ``t x y z qx qy qz qw`` (attitude only: position 0), for evo."""
    q = Rotation.from_euler("ZYX", np.stack([estimate.yaw, estimate.pitch, estimate.roll], axis=1)).as_quat()
    lines = [f"{t0_ns * 1e-9 + t:.9f} 0 0 0 {x:.12g} {y:.12g} {z:.12g} {w:.12g}"
             for t, (x, y, z, w) in zip(estimate.t_s, q)]
    return "# t x y z qx qy qz qw (attitude of the hull, body x forward y left z up)\n" + "\n".join(lines) + "\n"

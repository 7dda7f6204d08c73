"""Time alignment: a measurement taken at ``t_m`` moved to the keyframe time ``t_k`` (0 to ``keyframe_s`` later).

The IMU-propagated motion between the two instants carries each reading across: the prism position and velocity
by the predicted displacement, the inclinometer's up direction and the camera bearing by the predicted relative
rotation.  Over 0.1 s these deltas are known to micrometres and microradians.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from selfcal.core import so3
from selfcal.models import tracker as mt

X, V = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V


@dataclass
class Pending:
    """One measurement waiting for the next keyframe, with the state propagated to its time."""

    sensor: str
    t_ns: int
    z: np.ndarray  # prism position (m, world), up direction (body) or bearing (camera)
    nav: gtsam.NavState  # propagated state at the measurement
    velocity_W: np.ndarray | None = None  # the tracker's prism velocity (m/s), when it reports one
    w_B: np.ndarray | None = None  # bias-corrected body rate (rad/s) at the measurement, with velocity_W


def navstate_values(nav: gtsam.NavState, k: int) -> gtsam.Values:
    """``X(k)``, ``V(k)`` of a NavState as gtsam.Values."""
    # by keyword: pybind11 then skips the ~50 overloads of Values.insert it would otherwise try to convert to
    # (20 us for a Pose3, 110 us for a ConstantBias, per insert)
    values = gtsam.Values()
    values.insert(j=X(k), pose3=nav.pose())
    values.insert(j=V(k), vector=nav.velocity())
    return values


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues; a and b nearly equal)."""
    axis = mt.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-15:
        return np.eye(3)
    K = so3.hat(axis / s)
    return np.eye(3) + s * K + (1.0 - c) * K @ K


def prism_positions_at_keyframe(pending: list[Pending], prism_k_W: np.ndarray, r_P_B: np.ndarray) -> np.ndarray:
    """(n, 3) prism positions moved to the keyframe: ``z + (p_k + R_k r) - (p_m + R_m r)``.

    ``prism_k_W = p_k + R_k r_P_B`` is the prism predicted at the keyframe."""
    return np.array([m.z + prism_k_W - (m.nav.position() + m.nav.attitude().matrix() @ r_P_B) for m in pending])


def prism_velocities_at_keyframe(pending: list[Pending], nav_k: gtsam.NavState, w_k_B: np.ndarray,
                                 r_P_B: np.ndarray) -> np.ndarray:
    """(n, 3) prism velocities moved to the keyframe by the predicted change of the prism's velocity:
    ``z + (v_k + R_k (w_k x r)) - (v_m + R_m (w_m x r))``, ``w_k_B`` the body rate the velocity factor uses.

    The rotation part matters: moved by the change of the body's velocity alone, a sample 50 ms before the keyframe
    keeps the rotation velocity ``R (w x r)`` of 50 ms before, which reads as a tracker clock offset (measured:
    -29 +- 2 ms on a 20 s run yawed +-55 deg, 1 rad/s, with no offset planted)."""
    at_k = nav_k.velocity() + nav_k.attitude().matrix() @ mt.cross(w_k_B, r_P_B)
    return np.array([m.velocity_W + at_k - (m.nav.velocity() + m.nav.attitude().matrix() @ mt.cross(m.w_B, r_P_B))
                     for m in pending])


def up_at_keyframe(R_W_B_m: np.ndarray, R_W_B_k: np.ndarray, up_B_m: np.ndarray) -> np.ndarray:
    """The inclinometer's up direction (body frame) turned by the body's rotation ``dR = R_m^T R_k``: ``dR^T up``."""
    dR = R_W_B_m.T @ R_W_B_k
    return dR.T @ up_B_m


def bearing_at_keyframe(m: Pending, nav_k: gtsam.NavState, r_C_B: np.ndarray, R_B_C: np.ndarray,
                        tracker_W: np.ndarray) -> np.ndarray:
    """The camera's bearing of the beam (camera frame) moved to the keyframe.

    The beam's bearing changes with the rotation AND the translation between the two instants (a target moving
    0.1 m/s at 30 m turns the beam by 3e-4 rad in 0.1 s): the measured bearing is turned by the rotation that
    takes the bearing predicted at the measurement to the one predicted at the keyframe."""
    b_m = mt.beam_direction_C(m.nav.attitude().matrix(), m.nav.position(), r_C_B, R_B_C, tracker_W)
    b_k = mt.beam_direction_C(nav_k.attitude().matrix(), nav_k.position(), r_C_B, R_B_C, tracker_W)
    return rotation_between(b_m / np.linalg.norm(b_m), b_k / np.linalg.norm(b_k)) @ m.z

"""Continuous-time rigid-body trajectories of an IMU body frame ``S`` in a local-level world ``W`` (z up).

Every trajectory is a closed-form function of time, evaluable at arbitrary instants (a second IMU with a
clock offset or another rate samples it elsewhere).  Orientation is ``R_W_S(t) = R_ref Exp(phi(t))`` with a
smooth rotation vector ``phi(t)``, so the body rate and its derivative are exact::

    w_S = J_r(phi) phi_dot                                     (Forster et al. 2017, eq. 8)
    w_dot_S = J_r(phi) phi_ddot + (d/dt J_r(phi)) phi_dot      (differentiated analytically, see
                                                               :func:`rotation_vector_kinematics`)

``w_dot_S`` is therefore exact to rounding (tests compare it with a central difference of ``w_S``).
Times ``t_s`` are seconds on the trajectory's own axis (imu0's clock, 0 at the first imu0 sample).

References
----------
C. Forster, L. Carlone, F. Dellaert, D. Scaramuzza, "On-Manifold Preintegration for Real-Time
Visual-Inertial Odometry", IEEE T-RO 33(1), 2017 (right Jacobian of SO(3)).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.core import so3

E_Z = np.array([0.0, 0.0, 1.0])
DEFAULT_T0_NS = 1_700_000_000 * 10**9  # an epoch-like start: consumers must not keep stamps in float seconds


@dataclass(frozen=True)
class TrajectorySample:
    """True kinematics of the body frame S at times ``t_s`` (N,): all arrays with a leading N axis."""

    t_s: np.ndarray
    R_W_S: np.ndarray  # (N, 3, 3), v_W = R_W_S v_S
    w_S: np.ndarray  # (N, 3) body angular rate, rad s^-1, body frame
    w_dot_S: np.ndarray  # (N, 3) its time derivative, rad s^-2, body frame
    p_W: np.ndarray  # (N, 3) position of the body origin, m
    v_W: np.ndarray  # (N, 3) velocity, m s^-1
    a_W: np.ndarray  # (N, 3) linear acceleration, m s^-2 (gravity not included)

    def specific_force_S(self, gravity_m_s2: float) -> np.ndarray:
        """``f_S = R_W_S^T (a_W + g e_z)``: at rest it points up with magnitude g, (N, 3) m s^-2."""
        return np.einsum("nji,nj->ni", self.R_W_S, self.a_W + gravity_m_s2 * E_Z)


# --- smooth scalar profiles on u in [0, 1] (clipped outside) --------------------------------------------------

def smooth_step(u):
    """Septic step ``s = 35u^4 - 84u^5 + 70u^6 - 20u^7`` and its first two u-derivatives.

    s goes 0 -> 1 with zero 1st, 2nd and 3rd derivatives at both ends, so a move glued between two static
    poses has continuous rate, angular acceleration and jerk.
    """
    u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    v = 1.0 - u
    s = u**4 * (35.0 - 84.0 * u + 70.0 * u**2 - 20.0 * u**3)
    return s, 140.0 * u**3 * v**3, 420.0 * u**2 * v**2 * (1.0 - 2.0 * u)


def smooth_bump(u):
    """Bump ``b = 256 u^4 (1-u)^4`` (0 at both ends, 1 at u = 1/2) and its first two u-derivatives.

    b, b', b'' and b''' vanish at both ends: a wobble added to a move leaves the end poses, rate, angular
    acceleration and jerk continuous.
    """
    u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    v = 1.0 - u
    return (256.0 * u**4 * v**4, 1024.0 * u**3 * v**3 * (1.0 - 2.0 * u),
            1024.0 * u**2 * v**2 * (3.0 - 14.0 * u + 14.0 * u**2))


# --- rotation-vector kinematics --------------------------------------------------------------------------------

def _right_jacobian_rate_coefficients(theta: np.ndarray):
    """``a'(t)/t`` and ``b'(t)/t`` of ``J_r = I - a K + b K^2`` (a = (1-cos t)/t^2, b = (t-sin t)/t^3).

    Closed forms lose digits to cancellation for small angles; below 0.05 rad the Taylor series (truncation
    below 1e-12) is used instead.
    """
    small = theta < 0.05
    t = np.where(small, 1.0, theta)
    one_minus_cos = 2.0 * np.sin(0.5 * t) ** 2
    da = (t * np.sin(t) - 2.0 * one_minus_cos) / t**4
    db = (t * one_minus_cos - 3.0 * (t - np.sin(t))) / t**5
    t2 = theta**2
    da = np.where(small, -1.0 / 12.0 + t2 / 180.0 - t2**2 / 6720.0, da)
    db = np.where(small, -1.0 / 60.0 + t2 / 1260.0 - t2**2 / 60480.0, db)
    t_safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - t2 / 24.0 + t2**2 / 720.0, 2.0 * np.sin(0.5 * t_safe) ** 2 / t_safe**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2**2 / 5040.0, (t_safe - np.sin(t_safe)) / t_safe**3)
    return a, b, da, db


def rotation_vector_kinematics(phi, phi_dot, phi_ddot):
    """Body rate and angular acceleration of ``R(t) = R_ref Exp(phi(t))``; all arrays (N, 3).

    ``w = J_r(phi) phi_dot`` and ``w_dot = J_r(phi) phi_ddot + dJ_r/dt phi_dot`` with, for
    ``J_r = I - a K + b K^2`` (K = [phi]x, t = |phi|, t_dot = phi.phi_dot / t)::

        dJ_r/dt = -(a'/t)(phi.phi_dot) K - a K_dot + (b'/t)(phi.phi_dot) K^2 + b (K_dot K + K K_dot)

    Valid for |phi| < 2 pi (J_r is singular at 2 pi).
    """
    phi, phi_dot, phi_ddot = (np.asarray(x, dtype=float) for x in (phi, phi_dot, phi_ddot))
    J = so3.right_jacobian(phi)
    theta = np.linalg.norm(phi, axis=-1)
    a, b, da, db = _right_jacobian_rate_coefficients(theta)
    K, K_dot = so3.hat(phi), so3.hat(phi_dot)
    phi_dot_phi = np.sum(phi * phi_dot, axis=-1)[:, None, None]
    J_dot = (-da[:, None, None] * phi_dot_phi * K - a[:, None, None] * K_dot
             + db[:, None, None] * phi_dot_phi * (K @ K) + b[:, None, None] * (K_dot @ K + K @ K_dot))
    w = np.einsum("nij,nj->ni", J, phi_dot)
    w_dot = np.einsum("nij,nj->ni", J, phi_ddot) + np.einsum("nij,nj->ni", J_dot, phi_dot)
    return w, w_dot


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation R with ``R a = b`` for unit vectors a, b (any axis normal to a if antiparallel)."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return so3.exp(np.pi * axis / np.linalg.norm(axis))
    return so3.exp(axis / s * np.arctan2(s, c))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed rotation matrix (normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def random_rotation_about_z(rng: np.random.Generator) -> np.ndarray:
    """Rotation by a uniformly random heading about the world vertical."""
    return so3.exp(rng.uniform(-np.pi, np.pi) * E_Z)


def fibonacci_sphere(n: int) -> np.ndarray:
    """n nearly evenly spread unit vectors (golden-angle spiral), shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z**2)
    azimuth = np.pi * (1.0 + np.sqrt(5.0)) * i
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def to_plain(x):
    """numpy -> lists and Python scalars, recursively (YAML-serialisable)."""
    if isinstance(x, dict):
        return {str(k): to_plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_plain(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    return x


class Trajectory:
    """Interface: ``evaluate(t_s) -> TrajectorySample``, ``duration_s``, ``static_intervals_s``, ``to_dict()``."""

    duration_s: float
    static_intervals_s: list[tuple[float, float]]

    def evaluate(self, t_s) -> TrajectorySample:
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError


class MultiPositionTrajectory(Trajectory):
    """Static poses spread over the sphere joined by smooth hand-like moves (the multi-position protocol).

    Pose k is held over ``static_intervals_s[k]`` (pose 0 for ``initial_static_s``, the others for
    ``static_s``); between poses k and k+1 a move of ``move_s``::

        R_W_S(t) = R_k Exp(s(u) phi_k + b(u) c_k)          u = (t - t_end_k) / move_s
        p_W(t) = p_k + s(u) (p_{k+1} - p_k) + b(u) lift_k e_z

    with ``Exp(phi_k) = R_k^T R_{k+1}`` (at most ``max_move_deg``), ``s`` the septic :func:`smooth_step`,
    ``b`` the :func:`smooth_bump` and ``c_k`` a wobble normal to ``phi_k`` (so the rotation axis turns during
    the move, as a hand does).  The gravity ("up") directions in the body frame, ``up_S[k] = R_k^T e_z``,
    are a randomly rotated Fibonacci set ordered into a short tour, pose 0 exactly level; the yaw changes
    randomly from pose to pose.  Before 0 and after the end the trajectory holds its first/last pose.

    Attributes
    ----------
    pose_R_W_S : (n_poses, 3, 3) true orientation of each static pose.
    pose_p_W : (n_poses, 3) true position of each static pose, m.
    up_S : (n_poses, 3) unit "up" (specific-force direction) in the body frame at each pose.
    move_rotvec : (n_poses - 1, 3) ``phi_k = Log(R_k^T R_{k+1})``, rad.
    static_intervals_s : list of (start, end), s: the body is exactly at rest on each closed interval.
    duration_s : end of the last static interval, s.
    """

    def __init__(self, n_poses: int = 12, static_s: float = 3.0, move_s: float = 2.0, seed: int = 0,
                 initial_static_s: float = 10.0, max_move_deg: float = 120.0, yaw_change_deg: float = 45.0,
                 wobble_rad: float = 0.2, translation_m: float = 0.05):
        if n_poses < 1:
            raise ValueError("n_poses must be at least 1")
        self.n_poses, self.static_s, self.move_s, self.seed = int(n_poses), float(static_s), float(move_s), seed
        self.initial_static_s, self.max_move_deg = float(initial_static_s), float(max_move_deg)
        self.yaw_change_deg, self.wobble_rad, self.translation_m = float(yaw_change_deg), float(wobble_rad), \
            float(translation_m)
        rng = np.random.default_rng(seed)
        self.up_S = self._up_directions(rng)
        self._build_poses(rng)
        starts = np.array([0.0] + [self.initial_static_s + k * self.move_s + (k - 1) * self.static_s
                                   for k in range(1, self.n_poses)])
        ends = np.concatenate([[self.initial_static_s], starts[1:] + self.static_s])
        self._starts, self._ends = starts, ends
        self.static_intervals_s = [(float(s), float(e)) for s, e in zip(starts, ends)]
        self.duration_s = float(ends[-1])

    def _up_directions(self, rng) -> np.ndarray:
        """Spread up directions ordered so that consecutive ones are close; the first one is exactly e_z."""
        max_tilt = np.radians(self.max_move_deg)
        if self.n_poses <= 3:  # too few for a spread set: level, then on two orthogonal sides (90 deg moves)
            return np.array([E_Z, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])[:self.n_poses] @ random_rotation_about_z(rng).T
        for _ in range(50):
            points = fibonacci_sphere(self.n_poses) @ random_rotation(rng).T
            first = int(np.argmax(points[:, 2]))
            points = points @ rotation_between(points[first], E_Z).T
            points[first] = E_Z
            order = _short_tour(points, first)
            tilts = np.arccos(np.clip(np.sum(points[order[:-1]] * points[order[1:]], axis=1), -1.0, 1.0))
            if self.n_poses == 1 or np.max(tilts) <= max_tilt:
                return points[order]
        raise ValueError(f"cannot order {self.n_poses} poses with moves below {self.max_move_deg} deg; "
                         "use more poses or a larger max_move_deg")

    def _build_poses(self, rng) -> None:
        n, up = self.n_poses, self.up_S
        R = [random_rotation_about_z(rng)]  # level first pose, random heading
        p = [np.zeros(3)]
        self.move_rotvec = np.zeros((max(n - 1, 0), 3))
        self._wobble = np.zeros((n, 3))
        self._lift_m = np.zeros(n)
        max_move = np.radians(self.max_move_deg)
        for k in range(n - 1):
            tilt = rotation_between(up[k + 1], up[k])  # tilt up[k+1] -> up[k]: R_{k+1}^T e_z = up[k+1]
            tilt_angle = np.linalg.norm(so3.log(tilt))
            yaw_max = min(np.radians(self.yaw_change_deg), max(max_move - tilt_angle, 0.0))
            delta = so3.exp(rng.uniform(-yaw_max, yaw_max) * up[k]) @ tilt  # yaw = turn about the vertical
            phi = so3.log(delta)
            self.move_rotvec[k] = phi
            R.append(R[k] @ so3.exp(phi))
            # a wobble normal to the move axis, 0.5..1 x wobble_rad: the rotation axis turns during the move
            normal = np.cross(phi, rng.normal(size=3))
            self._wobble[k] = self.wobble_rad * rng.uniform(0.5, 1.0) * normal / np.linalg.norm(normal)
            p.append(self.translation_m * rng.uniform(-1.0, 1.0, size=3) * [1.0, 1.0, 0.0])
            self._lift_m[k] = self.translation_m * rng.uniform(0.5, 1.0)
        self.pose_R_W_S = np.array(R)
        self.pose_p_W = np.array(p)
        self._move_phi = np.vstack([self.move_rotvec, np.zeros((1, 3))])  # last pose: no move after it
        self._move_dp = np.vstack([np.diff(self.pose_p_W, axis=0), np.zeros((1, 3))])

    def evaluate(self, t_s) -> TrajectorySample:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        k = np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, self.n_poses - 1)
        # u = 0 on a static interval (and before 0), 0 < u < 1 during the move after pose k
        u = np.clip((t - self._ends[k]) / self.move_s, 0.0, 1.0)
        s, s1, s2 = smooth_step(u)
        b, b1, b2 = smooth_bump(u)
        T = self.move_s
        phi_k, c_k = self._move_phi[k], self._wobble[k]
        phi = s[:, None] * phi_k + b[:, None] * c_k
        phi_dot = (s1[:, None] * phi_k + b1[:, None] * c_k) / T
        phi_ddot = (s2[:, None] * phi_k + b2[:, None] * c_k) / T**2
        w, w_dot = rotation_vector_kinematics(phi, phi_dot, phi_ddot)
        R = self.pose_R_W_S[k] @ so3.exp(phi)
        dp, lift = self._move_dp[k], self._lift_m[k][:, None] * E_Z
        p = self.pose_p_W[k] + s[:, None] * dp + b[:, None] * lift
        v = (s1[:, None] * dp + b1[:, None] * lift) / T
        a = (s2[:, None] * dp + b2[:, None] * lift) / T**2
        return TrajectorySample(t, R, w, w_dot, p, v, a)

    def to_dict(self) -> dict:
        return to_plain({
            "kind": "multi_position", "seed": self.seed, "n_poses": self.n_poses, "static_s": self.static_s,
            "move_s": self.move_s, "initial_static_s": self.initial_static_s, "max_move_deg": self.max_move_deg,
            "yaw_change_deg": self.yaw_change_deg, "wobble_rad": self.wobble_rad,
            "translation_m": self.translation_m, "duration_s": self.duration_s,
            "static_intervals_s": self.static_intervals_s, "pose_R_W_S": self.pose_R_W_S,
            "pose_up_S": self.up_S, "move_angle_deg": np.degrees(np.linalg.norm(self.move_rotvec, axis=1)),
        })


def _short_tour(points: np.ndarray, first: int) -> np.ndarray:
    """Open path through all points from ``first``: greedy nearest neighbour, then 2-opt on squared angles.

    Squared angles penalise one long jump more than several short ones, which keeps every move small.
    """
    n = len(points)
    D = np.arccos(np.clip(points @ points.T, -1.0, 1.0)) ** 2
    order, left = [first], set(range(n)) - {first}
    while left:
        nxt = min(left, key=lambda j: D[order[-1], j])
        order.append(nxt)
        left.remove(nxt)
    order = np.array(order)
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                before = D[order[i - 1], order[i]] + (D[order[j], order[j + 1]] if j + 1 < n else 0.0)
                after = D[order[i - 1], order[j]] + (D[order[i], order[j + 1]] if j + 1 < n else 0.0)
                if after < before - 1e-12:
                    order[i:j + 1] = order[i:j + 1][::-1].copy()
                    improved = True
    return order


class HandheldTrajectory(Trajectory):
    """Smooth random hand-held motion about all axes, optionally static at start and end.

    ``R_W_S(t) = R_0 Exp(e(t) g(t))``, ``p_W(t) = e(t) q(t)``; g and q are per-axis sums of ``n_terms``
    sinusoids with random frequencies in ``freq_hz`` and phases.  Their amplitudes are scaled so that each
    axis of ``g_dot`` has RMS ``rate_rms_rad_s`` and each axis of ``q_ddot`` RMS ``accel_rms_m_s2``
    (peaks about 2.5x the RMS); each axis of g stays below ``max_angle_rad`` (amplitudes scaled down when
    needed), which keeps |phi| well below 2 pi.  The envelope ``e(t)`` is 0 on the static pieces and rises
    to 1 over ``ramp_s`` with the septic :func:`smooth_step`.  R_0 is level within ``initial_tilt_deg`` with
    a random heading.  The default 10 s rest at the start is the initial period on which the static-interval
    detector (:mod:`selfcal.core.static_intervals`) sets its threshold.
    """

    def __init__(self, duration_s: float = 60.0, seed: int = 0, static_start_s: float = 10.0,
                 static_end_s: float = 2.0, ramp_s: float = 1.0, rate_rms_rad_s: float = 1.2,
                 accel_rms_m_s2: float = 2.0, freq_hz: tuple[float, float] = (0.4, 2.0), n_terms: int = 3,
                 max_angle_rad: float = 1.5, initial_tilt_deg: float = 20.0):
        self.duration_s, self.seed = float(duration_s), seed
        self.static_start_s, self.static_end_s, self.ramp_s = float(static_start_s), float(static_end_s), \
            float(ramp_s)
        self.rate_rms_rad_s, self.accel_rms_m_s2 = float(rate_rms_rad_s), float(accel_rms_m_s2)
        self.freq_hz, self.n_terms, self.max_angle_rad = tuple(freq_hz), int(n_terms), float(max_angle_rad)
        self.initial_tilt_deg = float(initial_tilt_deg)
        if self.static_start_s + self.static_end_s + 2 * self.ramp_s > self.duration_s:
            raise ValueError("duration_s too short for the static pieces and ramps")
        rng = np.random.default_rng(seed)
        tilt_axis = np.array([*rng.normal(size=2), 0.0])
        tilt = np.radians(self.initial_tilt_deg) * rng.uniform(0.0, 1.0) * tilt_axis / np.linalg.norm(tilt_axis)
        self.R_0 = random_rotation_about_z(rng) @ so3.exp(tilt)
        self._rot = self._sinusoids(rng, self.rate_rms_rad_s, 1, self.max_angle_rad)
        self._pos = self._sinusoids(rng, self.accel_rms_m_s2, 2, np.inf)
        self.static_intervals_s = []
        if self.static_start_s > 0:
            self.static_intervals_s.append((0.0, self.static_start_s))
        if self.static_end_s > 0:
            self.static_intervals_s.append((self.duration_s - self.static_end_s, self.duration_s))

    def _sinusoids(self, rng, rms, order, max_sum):
        """(amplitude, omega, phase), each (n_terms, 3); the order-th derivative has the given RMS per axis."""
        omega = 2 * np.pi * rng.uniform(*self.freq_hz, size=(self.n_terms, 3))
        phase = rng.uniform(0.0, 2 * np.pi, size=(self.n_terms, 3))
        weight = rng.uniform(0.5, 1.0, size=(self.n_terms, 3))
        derivative_amplitude = weight * rms * np.sqrt(2.0) / np.linalg.norm(weight, axis=0)
        amplitude = derivative_amplitude / omega**order
        amplitude *= np.minimum(1.0, max_sum / np.sum(amplitude, axis=0))
        return amplitude, omega, phase

    @staticmethod
    def _series(params, t):
        A, om, ph = params
        arg = t[:, None, None] * om + ph
        sin, cos = np.sin(arg), np.cos(arg)
        return (np.sum(A * sin, axis=1), np.sum(A * om * cos, axis=1), -np.sum(A * om**2 * sin, axis=1))

    def envelope(self, t):
        """``e(t)`` and its first two time derivatives (each (N,))."""
        one, zero = np.ones_like(t), np.zeros_like(t)
        rise = smooth_step((t - self.static_start_s) / self.ramp_s) if self.static_start_s > 0 else (one, zero, zero)
        end_motion = self.duration_s - self.static_end_s
        fall = smooth_step((end_motion - t) / self.ramp_s) if self.static_end_s > 0 else (one, zero, zero)
        r0, r1, r2 = rise[0], rise[1] / self.ramp_s, rise[2] / self.ramp_s**2
        f0, f1, f2 = fall[0], -fall[1] / self.ramp_s, fall[2] / self.ramp_s**2
        return r0 * f0, r1 * f0 + r0 * f1, r2 * f0 + 2 * r1 * f1 + r0 * f2

    def evaluate(self, t_s) -> TrajectorySample:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        e0, e1, e2 = (x[:, None] for x in self.envelope(t))
        g0, g1, g2 = self._series(self._rot, t)
        q0, q1, q2 = self._series(self._pos, t)
        phi, phi_dot, phi_ddot = e0 * g0, e1 * g0 + e0 * g1, e2 * g0 + 2 * e1 * g1 + e0 * g2
        w, w_dot = rotation_vector_kinematics(phi, phi_dot, phi_ddot)
        R = self.R_0 @ so3.exp(phi)
        return TrajectorySample(t, R, w, w_dot, e0 * q0, e1 * q0 + e0 * q1, e2 * q0 + 2 * e1 * q1 + e0 * q2)

    def to_dict(self) -> dict:
        return to_plain({
            "kind": "handheld", "seed": self.seed, "duration_s": self.duration_s,
            "static_start_s": self.static_start_s, "static_end_s": self.static_end_s, "ramp_s": self.ramp_s,
            "rate_rms_rad_s": self.rate_rms_rad_s, "accel_rms_m_s2": self.accel_rms_m_s2,
            "freq_hz": list(self.freq_hz), "n_terms": self.n_terms, "max_angle_rad": self.max_angle_rad,
            "static_intervals_s": self.static_intervals_s, "R_W_S_start": self.R_0,
        })

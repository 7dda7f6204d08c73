"""Patent 004's own method, as written: the SMFAFKF error-state Kalman filter with chi-square / eigenvalue
fault detection and a switched measurement matrix (CN 115574815 A, steps 1-4).

State (15, the patent's list)::

    x = [phi (3), dv (3), dp (3), eps_g (3), eps_a (3)]

attitude, velocity and position errors of the strapdown solution and the gyro and accelerometer biases.  The
patent names a static and a dynamic part of each bias (eps_gb + eps_gr, eps_ab + eps_ar) but counts 15 states,
so each pair is one 3-vector here, modelled as a random walk whose density matches the dynamic (Gauss-Markov)
part (``q = 2 sigma^2 / tau``) and whose initial covariance covers the static part.

Conventions: ``R_sins = Exp(phi) R_true``, ``dv = v_sins - v``, ``dp = p_sins - p``, ``eps = b_true - b_hat``::

    phi' = R eps_g,    dv' = -[f_W]x phi + R eps_a,    dp' = dv,    eps' = w

Measurements (step 1): ``Z = [phi_s - phi_p; v_s - v_p; p_s - p_p]`` with ``H = [I 0 0 0 0; 0 I 0 0 0;
0 0 I 0 0]``; ``phi_p`` is the target's attitude from the inclinometer's roll and pitch and the camera's beam
azimuth (double-vector attitude, :func:`selfcal.models.tracker.attitude_from_tilt_and_beam`), ``v_p, p_p`` the
tracker's.  The patent's prism is its reference point; here the prism sits at ``r_P_B`` from the IMU, so the
position rows carry the lever-arm term ``-[R r]x`` on phi (without it the baseline would be wrong by design,
not by method).  The text's formulas were lost in extraction; each rule below follows its words.

Step 2, fault detection: the innovation's chi-square ``r^T S^-1 r > chi2(m).ppf(1 - alpha)`` declares a fault;
otherwise a *state recursor* (the filter's prediction without updates, restarted from the filter's state every
``n`` attitude epochs) gives pseudo-innovations of the attitude rows, normalised by their covariance; the
largest eigenvalue of ``D = sum nu nu^T`` over the recursor's window is compared with ``lambda_D`` (here the
Wishart quantile for the same stated false-alarm rate the library uses: the patent gives no value).  The patent
treats any fault as an inclinometer fault (its text: system normal <=> inclinometer normal).

Step 3, multiple sub-optimal fading factors: ``P- = L^1/2 Phi P Phi^T L^1/2 + Q``, ``L = diag(lambda_i)``; for
each measurement component, ``r_i^2 / (lambda_i M_ii + N_ii) <= chi2(1).ppf(1 - alpha_f)`` (``M = H Phi P
Phi^T H^T``, ``N = H Q H^T + R``) gives ``lambda_i >= (r_i^2 / eps_i - N_ii) / M_ii``; the filter takes
``lambda_i = max(1, that)`` for the state the component observes and 1 for unobserved states.  When the
inclinometer is judged faulty the attitude rows are removed from ``H`` (the switched measurement matrix).

Step 4: the estimated errors correct the strapdown solution (closed loop) and are reset to zero.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import stats

from selfcal.core import inertial
from selfcal.core.stats import wishart_lambda_max_quantile
from selfcal.core import so3
from selfcal.models import tracker as mt

log = logging.getLogger(__name__)
E_Z = np.array([0.0, 0.0, 1.0])


@dataclass
class Patent004Params:
    tracker_sigma_m: float = 0.5e-3
    tracker_velocity_sigma_m_s: float = 2e-3
    incl_sigma_rad: float = 8.7e-5
    cam_sigma_rad: float = 1.7e-4
    gyro_noise_density: float = 1.7e-4
    accel_noise_density: float = 2e-3
    gyro_random_walk: float = 1.6e-5
    accel_random_walk: float = 1.6e-4
    gravity_m_s2: float = 9.80665
    r_P_B: np.ndarray = None
    r_C_B: np.ndarray = None
    R_B_C: np.ndarray = None
    camera_matrix: np.ndarray = None
    dist_coeffs: np.ndarray = None
    tracker_W: np.ndarray = None
    chi2_alpha: float = 1e-4  # innovation test (same per-test rate as the library's gate)
    fading_alpha: float = 0.05  # per-component test that sets the fading factors
    window: int = 50  # recursor length n (attitude epochs)
    false_alarms_per_hour: float = 1.0
    attitude_rate_hz: float = 10.0
    use_fading: bool = True
    use_fault_detection: bool = True


@dataclass
class Patent004Result:
    t_ns: np.ndarray
    R_W_B: np.ndarray  # (K, 3, 3)
    p_W: np.ndarray  # (K, 3)
    decisions: list


class Patent004Filter:
    """Runs the filter over time-ordered samples (arrays per sensor)."""

    def __init__(self, params: Patent004Params):
        self.p = params
        self.chi2_thr = {m: float(stats.chi2.ppf(1 - params.chi2_alpha, m)) for m in range(1, 10)}
        self.eps_fading = float(stats.chi2.ppf(1 - params.fading_alpha, 1))
        tests_per_hour = 3600.0 * params.attitude_rate_hz / params.window
        self.lambda_D = wishart_lambda_max_quantile(3, params.window, round(params.false_alarms_per_hour
                                                                              / tests_per_hour, 12))

    def _initialise(self, p_P, up_B, bearing_C, v_P):
        pr = self.p
        roll, pitch = inertial.tilt_from_specific_force(up_B)
        beam_W = pr.tracker_W - p_P
        self.R = mt.attitude_from_tilt_and_beam(float(roll), float(pitch), pr.R_B_C @ bearing_C,
                                                beam_W / np.linalg.norm(beam_W))
        self.pos = p_P - self.R @ pr.r_P_B
        self.vel = np.zeros(3) if v_P is None else np.array(v_P, dtype=float)
        self.bg, self.ba = np.zeros(3), np.zeros(3)
        self.P = np.diag(np.r_[[2e-3, 2e-3, 5e-3], [0.02] * 3, [0.01] * 3, [5e-3] * 3, [0.05] * 3] ** 2)
        self._reset_accumulators()
        self.rec_x, self.rec_P, self.rec_Y = np.zeros(15), self.P.copy(), []
        self.faulty = False

    def _reset_accumulators(self):
        self.Phi = np.eye(15)
        self.Q = np.zeros((15, 15))

    def _propagate(self, gyro, accel, dt):
        pr = self.p
        w = gyro - self.bg
        f = accel - self.ba
        R0 = self.R
        f_W = R0 @ f
        self.R = R0 @ so3.exp(w * dt)
        v0 = self.vel
        self.vel = v0 + (f_W - pr.gravity_m_s2 * E_Z) * dt
        self.pos = self.pos + 0.5 * (v0 + self.vel) * dt
        F = np.zeros((15, 15))
        F[0:3, 9:12] = R0
        F[3:6, 0:3] = -so3.hat(f_W)
        F[3:6, 12:15] = R0
        F[6:9, 3:6] = np.eye(3)
        Phi = np.eye(15) + F * dt
        q = np.r_[[pr.gyro_noise_density**2] * 3, [pr.accel_noise_density**2] * 3, [0.0] * 3,
                  [pr.gyro_random_walk**2] * 3, [pr.accel_random_walk**2] * 3] * dt
        self.Phi = Phi @ self.Phi
        self.Q = Phi @ self.Q @ Phi.T + np.diag(q)
        # state recursor: prediction only
        self.rec_x = Phi @ self.rec_x
        self.rec_P = Phi @ self.rec_P @ Phi.T + np.diag(q)

    def _update(self, t_ns, tracker, attitude, decisions):
        """One measurement epoch: tracker (p, v or None) and optionally the attitude measurement R_p."""
        pr = self.p
        p_meas, v_meas, w_B = tracker
        rows_z, rows_H, rows_R, kinds = [], [], [], []
        if attitude is not None:
            R_p = attitude
            rows_z.append(so3.log(self.R @ R_p.T))
            Ha = np.zeros((3, 15))
            Ha[:, 0:3] = np.eye(3)
            rows_H.append(Ha)
            rows_R.append(np.array([pr.incl_sigma_rad, pr.incl_sigma_rad, pr.cam_sigma_rad]) ** 2)
            kinds.append("att")
        if v_meas is not None:
            rows_z.append(mt.prism_velocity_W(self.R, self.vel, w_B, pr.r_P_B) - v_meas)
            Hv = np.zeros((3, 15))
            Hv[:, 3:6] = np.eye(3)
            rows_H.append(Hv)
            rows_R.append(np.full(3, pr.tracker_velocity_sigma_m_s**2))
            kinds.append("vel")
        rows_z.append(self.pos + self.R @ pr.r_P_B - p_meas)
        Hp = np.zeros((3, 15))
        Hp[:, 0:3] = -so3.hat(self.R @ pr.r_P_B)
        Hp[:, 6:9] = np.eye(3)
        rows_H.append(Hp)
        rows_R.append(np.full(3, pr.tracker_sigma_m**2))
        kinds.append("pos")
        z, H, Rm = np.concatenate(rows_z), np.vstack(rows_H), np.diag(np.concatenate(rows_R))
        PhiPPhi = self.Phi @ self.P @ self.Phi.T
        P_pred = PhiPPhi + self.Q
        S = H @ P_pred @ H.T + Rm
        gamma = float(z @ np.linalg.solve(S, z))
        fault = False
        if pr.use_fault_detection:
            thr = self.chi2_thr[len(z)]
            if gamma > thr:
                fault = True
                decisions.append({"t_ns": int(t_ns), "test": "chi2", "statistic": gamma, "threshold": thr,
                                  "decision": "fault"})
            elif attitude is not None:  # eigenvalue test on the recursor's normalised pseudo-innovations
                Sr = Ha @ self.rec_P @ Ha.T + np.diag(rows_R[0])
                L = np.linalg.cholesky(Sr)
                self.rec_Y.append(np.linalg.solve(L, rows_z[0] - Ha @ self.rec_x))
                if len(self.rec_Y) >= pr.window:
                    Y = np.array(self.rec_Y)
                    lam = float(np.linalg.eigvalsh(Y.T @ Y)[-1])
                    self.faulty = lam > self.lambda_D
                    decisions.append({"t_ns": int(t_ns), "test": "eigen", "statistic": lam,
                                      "threshold": self.lambda_D, "decision": "fault" if self.faulty else "normal"})
                    self.rec_Y = []
                    self.rec_x, self.rec_P = np.zeros(15), None  # restarted below from the filter's state
        if (fault or self.faulty) and attitude is not None:  # switched H: no attitude rows
            keep = slice(3, None)
            z, H, Rm = z[keep], H[keep], Rm[keep, keep]
            kinds = kinds[1:]
            S = H @ P_pred @ H.T + Rm
        if pr.use_fading:
            M = H @ PhiPPhi @ H.T
            N = H @ self.Q @ H.T + Rm
            lam_state = np.ones(15)
            offset = 0
            for kind in kinds:
                states = {"att": slice(0, 3), "vel": slice(3, 6), "pos": slice(6, 9)}[kind]
                for i in range(3):
                    j = offset + i
                    bound = (z[j] ** 2 / self.eps_fading - N[j, j]) / max(M[j, j], 1e-300)
                    s = states.start + i
                    lam_state[s] = max(lam_state[s], bound, 1.0)
                offset += 3
            sl = np.sqrt(lam_state)
            P_pred = sl[:, None] * PhiPPhi * sl[None, :] + self.Q
            S = H @ P_pred @ H.T + Rm
        K = np.linalg.solve(S, H @ P_pred).T
        x = K @ z
        IKH = np.eye(15) - K @ H
        self.P = IKH @ P_pred @ IKH.T + K @ Rm @ K.T  # Joseph form: stays symmetric positive definite
        self.R = so3.exp(-x[0:3]) @ self.R
        self.vel = self.vel - x[3:6]
        self.pos = self.pos - x[6:9]
        self.bg = self.bg + x[9:12]
        self.ba = self.ba + x[12:15]
        self._reset_accumulators()
        # the recursor predicts the error of the corrected solution: its estimate moves by the correction
        if self.rec_P is None:
            self.rec_x, self.rec_P = np.zeros(15), self.P.copy()
        else:
            self.rec_x = self.rec_x - x

    def run(self, imu_t_ns, gyro, accel, tracker_t_ns, tracker_p, tracker_v, incl_t_ns, incl_rp, cam_t_ns,
            cam_uv) -> Patent004Result:
        """Filter a whole run.  ``tracker_v`` may be None.  Returns the pose after every tracker epoch."""
        pr = self.p
        bearings = mt.bearing_from_pixel(cam_uv, pr.camera_matrix, pr.dist_coeffs) if len(cam_uv) else np.zeros((0, 3))
        ups = mt.up_direction_B(incl_rp[:, 0], incl_rp[:, 1])
        it = ic = 0  # next unused incl / cam sample
        jt = 0
        out_t, out_R, out_p, decisions = [], [], [], []
        initialised = False
        n_imu = len(imu_t_ns)
        for i in range(n_imu - 1):
            t = imu_t_ns[i]
            # measurement epochs at this IMU instant (all sensors share the clock; tolerance half an IMU period)
            half = (imu_t_ns[i + 1] - t) // 2
            while it < len(incl_t_ns) and incl_t_ns[it] < t - half:
                it += 1
            while ic < len(cam_t_ns) and cam_t_ns[ic] < t - half:
                ic += 1
            while jt < len(tracker_t_ns) and tracker_t_ns[jt] < t - half:
                jt += 1
            has_tr = jt < len(tracker_t_ns) and tracker_t_ns[jt] <= t + half
            has_att = (it < len(incl_t_ns) and incl_t_ns[it] <= t + half and ic < len(cam_t_ns)
                       and cam_t_ns[ic] <= t + half)
            if not initialised:
                if has_tr and has_att:
                    self._initialise(tracker_p[jt], ups[it], bearings[ic],
                                     None if tracker_v is None else tracker_v[jt])
                    initialised = True
            elif has_tr:
                attitude = None
                if has_att:
                    roll, pitch = incl_rp[it]
                    p_cam = tracker_p[jt] + self.R @ (pr.r_C_B - pr.r_P_B)
                    beam_W = pr.tracker_W - p_cam
                    attitude = mt.attitude_from_tilt_and_beam(roll, pitch, pr.R_B_C @ bearings[ic],
                                                              beam_W / np.linalg.norm(beam_W))
                w_B = gyro[i] - self.bg
                self._update(t, (tracker_p[jt], None if tracker_v is None else tracker_v[jt], w_B), attitude,
                             decisions)
                out_t.append(t)
                out_R.append(self.R.copy())
                out_p.append(self.pos.copy())
            if initialised:
                self._propagate(gyro[i], accel[i], (imu_t_ns[i + 1] - t) * 1e-9)
        return Patent004Result(np.array(out_t, dtype=np.int64), np.array(out_R), np.array(out_p), decisions)

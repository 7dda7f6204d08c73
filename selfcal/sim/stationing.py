"""Simulated stationing runs with known truth (:mod:`selfcal.models.stationing` equations, exact or with the
dataset's stated noise), for tests of the stationing graph."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.models.stationing import E_Z, prism_position_W, specific_force_A


@dataclass
class StationingScenario:
    """A robot on a tilted base, column extended to a few heights, the arm visiting waypoints.

    Tool poses (tip -> tool) are drawn like the dataset's: positions in a 1.4 m x 1.4 m x 0.5 m box in front of
    the column, the tool turned about the vertical by a random yaw, a quarter of them upside down.
    """

    seed: int = 0
    heights_m: tuple = (2.0, 3.0)
    waypoints_per_height: int = 30
    stationing_per_height: int = 8
    tool_t_prism: np.ndarray = field(default_factory=lambda: np.array([0.001, -0.101, 0.336]))
    pivot_fraction: float = 0.67
    mount_column_rotvec: np.ndarray = field(default_factory=lambda: np.array([-0.001, 0.015, -0.3]))
    mount_base_rotvec: np.ndarray = field(default_factory=lambda: np.array([0.019, 0.010, 0.0]))
    base_tilt_rad: np.ndarray = field(default_factory=lambda: np.array([0.01, -0.03]))
    base_position_m: tuple = (7.0, 5.5, -2.0)  # the column's foot in the total-station frame
    tilt_sigma_rad: float = 0.002  # the column's bend per waypoint
    gravity_m_s2: float = 9.8077
    prism_sigma_m: float = 0.75e-3
    accel_sigma_m_s2: float = 4.3610059e-4
    # effects outside the model (for the audit's tests; zero: the model's own world)
    range_error_per_m: float = 0.0  # the total station reads a distance r as r + k (r - r_mean): a scale error
    # whose zero point was calibrated at the mean range of the run
    base_rock_rad_per_m: float = 0.0  # the base accelerometer tilts about the tip's y axis by k * (arm x reach)
    column_bias_harmonic_m_s2: float = 0.0  # column accelerometer x bias A sin(arm angle) (a cable's pull)

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        n_h, k = len(self.heights_m), self.waypoints_per_height
        self.station = np.repeat(np.arange(n_h), k)
        self.column_height = np.repeat(np.asarray(self.heights_m, float), k)
        self.stationing = np.tile(np.arange(k) < self.stationing_per_height, n_h)
        n = n_h * k
        yaw = rng.uniform(-np.pi, np.pi, n)
        yaw[self.stationing] = -np.pi / 2  # the dataset's stationing points keep one tool orientation
        upside = (rng.uniform(size=n) < 0.25) & ~self.stationing
        R = Rotation.from_euler("z", yaw[:, None])
        R = Rotation.from_rotvec(np.where(upside[:, None], [np.pi, 0.0, 0.0], 0.0)) * R
        self.R_T_tool = R.as_matrix()
        self.t_T_tool = rng.uniform([0.0, -0.7, -0.1], [1.4, 0.7, 0.4], (n, 3))
        self.tilt_rad = rng.normal(0.0, self.tilt_sigma_rad, (n, 2))
        base_R = Rotation.from_rotvec([*self.base_tilt_rad, 0.3]).as_matrix()
        self.W_T_B = (base_R, np.asarray(self.base_position_m, dtype=float))
        self.R_T_Acol = Rotation.from_rotvec(self.mount_column_rotvec).as_matrix()
        self.R_B_Abase = Rotation.from_rotvec(self.mount_base_rotvec).as_matrix()
        # station poses: the tip at height h above the base, with a small static lean per height
        lean = rng.normal(0.0, 0.002, (n_h, 3))
        self.station_R = [base_R @ Rotation.from_rotvec(l).as_matrix() for l in lean]
        self.station_t = [self.W_T_B[1] + base_R @ (h * E_Z) for h in self.heights_m]

    def exact(self) -> dict:
        """Noise-free prism positions and accelerometer readings."""
        n = len(self.station)
        prism = np.empty((n, 3))
        accel_col = np.empty((n, 3))
        for s in range(len(self.heights_m)):
            idx = self.station == s
            prism[idx] = prism_position_W(self.station_R[s], self.station_t[s], self.tilt_rad[idx],
                                          self.R_T_tool[idx], self.t_T_tool[idx], self.tool_t_prism,
                                          self.column_height[idx], self.pivot_fraction)[0]
            accel_col[idx] = specific_force_A(self.station_R[s], self.tilt_rad[idx], self.R_T_Acol,
                                              np.full(idx.sum(), self.gravity_m_s2))[0]
        # the base rocks under the arm's moment: a tilt about y in proportion to the tool's x reach
        rock = np.column_stack([np.zeros(n), self.base_rock_rad_per_m * self.t_T_tool[:, 0]])
        accel_base = specific_force_A(self.W_T_B[0], rock, self.R_B_Abase, np.full(n, self.gravity_m_s2))[0]
        r = np.linalg.norm(prism, axis=1)  # the total station sits at the origin of W
        prism = prism + (self.range_error_per_m * (r - r.mean()) / r)[:, None] * prism
        arm_angle = np.arctan2(self.t_T_tool[:, 1], self.t_T_tool[:, 0])
        accel_col[:, 0] += self.column_bias_harmonic_m_s2 * np.sin(arm_angle)
        return {"prism_W": prism, "accel_column": accel_col, "accel_base": accel_base}

    def perturbed(self, seed) -> dict:
        """The exact measurements plus white noise at the stated sigmas."""
        rng = np.random.default_rng(seed)
        out = self.exact()
        out["prism_W"] = out["prism_W"] + rng.normal(0.0, self.prism_sigma_m, out["prism_W"].shape)
        for key in ("accel_column", "accel_base"):
            out[key] = out[key] + rng.normal(0.0, self.accel_sigma_m_s2, out[key].shape)
        return out

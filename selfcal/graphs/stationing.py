"""Stationing calibration graph: prism lever arm, column pivot and tilt-accelerometer mountings from static
waypoints measured by a total station (:mod:`selfcal.models.stationing` for the equations).

Per dataset file: a base pose ``W_T_B`` (the tracked base does not move within a file), one station pose
``W_T_S`` per column height (the column tip's pose at that height), and a tilt per waypoint (the column's bend
under the arm's load, measured by the column accelerometer).  Shared by all files (the calibration): the prism
in the tool frame, the pivot fraction and the two accelerometer mountings.

What the data determine, and what they do not
---------------------------------------------
* prism lever arm: the evaluation waypoints turn the tool about the vertical and upside down; the stationing
  points alone keep one tool orientation and cannot (the station's translation absorbs the lever arm).
* column accelerometer mounting (roll, pitch about the tip's axes): against the station's attitude, which the
  prism positions fix through the arm's kinematics.  Its yaw only acts through the tilt the tip sees (at most
  3 deg here), so it is weakly determined (a prior of 0.05 rad keeps it bounded; its sigma says how weakly).
* base accelerometer mounting: the base is only linked to the column by the URDF's nominal column (prior on the
  column's lean, ``lean_sigma_rad``); so the base mounting is estimated *relative to the column tip's mean
  attitude over the stations* -- the relative mounting of the two accelerometers, which is what a tilt
  monitor needs.
* accelerometer biases: not separable from the mounting tilt (see the models module); folded into it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np

from selfcal.factors.stationing import accel_block_factor, prism_block_factor
from selfcal.core.solve import DegenerateDataError, marginal_covariances
from selfcal.models.stationing import chain_transforms

log = logging.getLogger(__name__)

PRISM = gtsam.symbol("p", 0)
PIVOT = gtsam.symbol("l", 0)
MOUNT_COLUMN = gtsam.symbol("m", 0)
MOUNT_BASE = gtsam.symbol("n", 0)


def base_key(f: int) -> int:
    return gtsam.symbol("b", f)


def station_key(f: int, s: int) -> int:
    return gtsam.symbol("s", 100 * f + s)


def tilt_key(f: int, i: int) -> int:
    return gtsam.symbol("d", 10_000 * f + i)


@dataclass
class StationingSigmas:
    """Measurement sigmas (the dataset's stated datasheet values) and the priors' widths."""

    prism_m: float = 0.75e-3
    accel_m_s2: float = 4.3610059e-4
    base_accel_m_s2: float | None = None  # the base accelerometer's, where it differs (None: accel_m_s2)
    tilt_prior_rad: float = 0.01  # column bend per waypoint: weak, the column accelerometer fixes it
    lean_sigma_rad: float = 0.01  # column tip vs base at a station: URDF nominal +- this
    lean_sigma_m: float = 0.01
    mount_yaw_sigma_rad: float = 0.05  # column accelerometer: its yaw acts through the bend direction
    base_mount_yaw_sigma_rad: float = 0.05  # base accelerometer: a rigid base sees one tilt per file
    pivot_prior_sigma: float = 1.0  # pivot fraction 0.5 +- this (cantilever: 0.5 end moment, 2/3 end force)


@dataclass
class Calibration:
    """The shared unknowns; ``cov`` holds the 1-sigma marginal covariances where estimated."""

    tool_t_prism: np.ndarray
    pivot_fraction: float = 0.5
    R_T_Acol: np.ndarray = field(default_factory=lambda: np.eye(3))
    R_B_Abase: np.ndarray = field(default_factory=lambda: np.eye(3))
    cov: dict = field(default_factory=dict)


@dataclass
class FileGeometry:
    """One dataset file prepared for the graph: kinematics evaluated, waypoints grouped by column height."""

    name: str
    heights: np.ndarray  # (K,) the station heights
    station: np.ndarray  # (N,) index into heights
    column_height: np.ndarray  # (N,) m (the prismatic joint)
    R_T_tool: np.ndarray  # (N, 3, 3)
    t_T_tool: np.ndarray  # (N, 3)
    prism_W: np.ndarray
    accel_base: np.ndarray
    accel_column: np.ndarray
    stationing: np.ndarray  # (N,) bool


def file_geometry(data, arm_chain) -> FileGeometry:
    """Evaluate the arm's kinematics (tip -> tool) for every waypoint of a :class:`StationingData`."""
    T = chain_transforms(arm_chain, data.joints[:, 1:])
    heights_by_station = np.array([h for h, _ in data.stations])
    heights = np.unique(heights_by_station)
    station = np.searchsorted(heights, heights_by_station[data.station])
    return FileGeometry(data.name, heights, station, data.joints[:, 0], T[:, :3, :3], T[:, :3, 3], data.prism_W,
                        data.accel_base, data.accel_column, data.stationing)


def _kabsch(P, Q):
    """R, t minimising |Q - (R P + t)|; used only to initialise station poses."""
    pm, qm = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - pm).T @ (Q - qm))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, qm - R @ pm


def _value(values: gtsam.Values, key: int):
    """The value of ``key`` whatever its type (the graph holds poses, rotations, points and vectors)."""
    char = chr(gtsam.Symbol(key).chr())
    if char in "bs":
        return values.atPose3(key)
    if char in "mn":
        return values.atRot3(key)
    if char == "p":
        return values.atPoint3(key)
    return values.atVector(key)


@dataclass
class StationingFit:
    values: gtsam.Values
    calibration: Calibration
    files: list[FileGeometry]
    use_tilt: bool
    graph: gtsam.NonlinearFactorGraph

    def compute_marginals(self) -> None:
        """1-sigma covariances of the calibration (``calibration.cov``, by key)."""
        keys = [PRISM, MOUNT_COLUMN, MOUNT_BASE] + ([PIVOT] if self.use_tilt else [])
        self.calibration.cov = marginal_covariances(self.graph, self.values, keys,
                                                    "the prism lever arm and the accelerometer mountings")

    def predict_prism(self, f: int) -> np.ndarray:
        """Predicted prism positions (N, 3) of file ``f``'s waypoints from the fitted stations and tilts."""
        from selfcal.models.stationing import prism_position_W
        g = self.files[f]
        out = np.empty_like(g.prism_W)
        for s in range(len(g.heights)):
            idx = np.flatnonzero(g.station == s)
            pose = self.values.atPose3(station_key(f, s))
            tilt = np.array([self.values.atVector(tilt_key(f, i)) for i in idx]) if self.use_tilt \
                else np.zeros((len(idx), 2))
            out[idx] = prism_position_W(pose.rotation().matrix(), pose.translation(), tilt, g.R_T_tool[idx],
                                        g.t_T_tool[idx], self.calibration.tool_t_prism, g.column_height[idx],
                                        self.calibration.pivot_fraction if self.use_tilt else 0.0)[0]
        return out

    def accel_residuals(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(column, base) accelerometer residuals predicted - measured (N, 3), m s^-2."""
        from selfcal.models.stationing import specific_force_A
        g = self.files[f]
        col = np.empty_like(g.accel_column)
        for s in range(len(g.heights)):
            idx = np.flatnonzero(g.station == s)
            R = self.values.atPose3(station_key(f, s)).rotation().matrix()
            tilt = np.array([self.values.atVector(tilt_key(f, i)) for i in idx]) if self.use_tilt \
                else np.zeros((len(idx), 2))
            col[idx] = specific_force_A(R, tilt, self.calibration.R_T_Acol,
                                        np.linalg.norm(g.accel_column[idx], axis=1))[0] - g.accel_column[idx]
        R_B = self.values.atPose3(base_key(f)).rotation().matrix()
        base = specific_force_A(R_B, np.zeros((len(g.accel_base), 2)), self.calibration.R_B_Abase,
                                np.linalg.norm(g.accel_base, axis=1))[0] - g.accel_base
        return col, base


def stationing_graph(files: list[FileGeometry], prism_points: list[np.ndarray], initial: Calibration,
                     estimate: bool = True, use_tilt: bool = True, sigmas: StationingSigmas | None = None,
                     rezero: bool = False, waypoints: list[np.ndarray] | None = None,
                     corrections: list[dict] | None = None, start: gtsam.Values | None = None):
    """The graph of :func:`fit_stationing` and its starting values, unsolved: ``(graph, values)``."""
    sig = sigmas or StationingSigmas()
    base_sigma = sig.base_accel_m_s2 or sig.accel_m_s2
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    fixed = gtsam.noiseModel.Isotropic.Sigma
    values.insert(PRISM, gtsam.Point3(*initial.tool_t_prism))
    values.insert(PIVOT, np.array([initial.pivot_fraction]))
    values.insert(MOUNT_COLUMN, gtsam.Rot3(initial.R_T_Acol))
    values.insert(MOUNT_BASE, gtsam.Rot3(initial.R_B_Abase))
    if estimate:
        graph.add(gtsam.PriorFactorRot3(MOUNT_COLUMN, gtsam.Rot3(), gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1.0, 1.0, sig.mount_yaw_sigma_rad]))))
        graph.add(gtsam.PriorFactorRot3(MOUNT_BASE, gtsam.Rot3(), gtsam.noiseModel.Diagonal.Sigmas(
            np.array([1.0, 1.0, sig.base_mount_yaw_sigma_rad]))))
        graph.add(gtsam.PriorFactorVector(PIVOT, np.array([0.5]), fixed(1, sig.pivot_prior_sigma)))
    else:
        graph.add(gtsam.PriorFactorPoint3(PRISM, gtsam.Point3(*initial.tool_t_prism), fixed(3, 1e-9)))
        graph.add(gtsam.PriorFactorVector(PIVOT, np.array([initial.pivot_fraction]), fixed(1, 1e-9)))
        mount = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0, 1.0, 1e-9])) if rezero else fixed(3, 1e-9)
        graph.add(gtsam.PriorFactorRot3(MOUNT_COLUMN, gtsam.Rot3(initial.R_T_Acol), mount))
        graph.add(gtsam.PriorFactorRot3(MOUNT_BASE, gtsam.Rot3(initial.R_B_Abase), mount))
    if not use_tilt:
        graph.add(gtsam.PriorFactorVector(PIVOT, np.array([initial.pivot_fraction]), fixed(1, 1e-9)))
        graph.add(gtsam.PriorFactorRot3(MOUNT_COLUMN, gtsam.Rot3(initial.R_T_Acol), fixed(3, 1e-9)))
    lean = gtsam.noiseModel.Diagonal.Sigmas(np.array([sig.lean_sigma_rad] * 3 + [sig.lean_sigma_m] * 3))
    tilt_prior = fixed(2, sig.tilt_prior_rad)
    for f, (g, use) in enumerate(zip(files, prism_points)):
        rows = np.ones(len(g.station), bool) if waypoints is None else np.asarray(waypoints[f], bool)
        terms = (corrections[f] if corrections is not None else None) or {}
        for key, _ in [c for family in terms.values() for c in family]:
            if not values.exists(key):
                values.insert(key, np.zeros(3))

        def sub(family, idx):
            return [(key, M[idx]) for key, M in terms.get(family, ())]
        for s, h in enumerate(g.heights):
            idx = np.flatnonzero((g.station == s) & rows)
            used = idx[use[idx]]
            if len(used) < 3:
                raise DegenerateDataError(f"{g.name}: column height {h} m has {len(used)} prism points; a station "
                                          f"needs 3 or more")
            p_T = np.einsum("nij,j->ni", g.R_T_tool[used], initial.tool_t_prism) + g.t_T_tool[used]
            R, t = _kabsch(p_T, g.prism_W[used])
            values.insert(station_key(f, s), gtsam.Pose3(gtsam.Rot3(R), t))
            tilts = [tilt_key(f, i) for i in idx] if use_tilt else None
            if use_tilt:
                for i in idx:
                    values.insert(tilt_key(f, i), np.zeros(2))
                    graph.add(gtsam.PriorFactorVector(tilt_key(f, i), np.zeros(2), tilt_prior))
                graph.add(accel_block_factor(fixed(3 * len(idx), sig.accel_m_s2), station_key(f, s), tilts,
                                             MOUNT_COLUMN, g.accel_column[idx], sub("accel_column", idx)))
            used_tilts = [tilt_key(f, i) for i in used] if use_tilt else None
            graph.add(prism_block_factor(fixed(3 * len(used), sig.prism_m), station_key(f, s), used_tilts, PRISM,
                                         PIVOT, g.R_T_tool[used], g.t_T_tool[used], g.column_height[used],
                                         g.prism_W[used], sub("prism", used)))
            graph.add(gtsam.BetweenFactorPose3(base_key(f), station_key(f, s),
                                               gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, h])), lean))
        first = values.atPose3(station_key(f, 0))
        values.insert(base_key(f), first.compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, -g.heights[0]]))))
        base_rows = np.flatnonzero(rows)
        graph.add(accel_block_factor(fixed(3 * len(base_rows), base_sigma), base_key(f), None, MOUNT_BASE,
                                     g.accel_base[base_rows], sub("accel_base", base_rows)))
    if start is not None:
        for key in values.keys():
            if start.exists(key):
                values.update(key, _value(start, key))
    return graph, values


def fit_stationing(files: list[FileGeometry], prism_points: list[np.ndarray], initial: Calibration,
                   estimate: bool = True, use_tilt: bool = True, sigmas: StationingSigmas | None = None,
                   marginals: bool = True, rezero: bool = False, waypoints: list[np.ndarray] | None = None,
                   corrections: list[dict] | None = None, start: gtsam.Values | None = None) -> StationingFit:
    """Build and solve the stationing graph.

    Parameters
    ----------
    files : list of FileGeometry
    prism_points : list of (N,) bool
        Per file, which waypoints' prism positions enter the graph (the rest are held out).
    initial : Calibration
        Starting values; with ``estimate=False`` they are held fixed (held-out stationing with a calibration).
    use_tilt : bool
        Column tilt per waypoint from the column accelerometer (the library's model); False: rigid stations
        from the prism alone (the baseline, as the dataset's own Kabsch example).
    rezero : bool
        With ``estimate=False``: re-estimate the accelerometers' zero (mounting roll and pitch, which hold the
        horizontal bias) at this site, keeping their yaw, the lever arm and the pivot.  An ADXL355's zero moves
        with temperature (datasheet: up to 0.15 mg/K, i.e. ~1.5e-4 rad/K of apparent tilt), so a site's
        stationing re-zeroes the tilt sensors as a levelled instrument would; the accelerometers then carry the
        column's *bend* between waypoints, the prism positions the station's attitude.
    waypoints : list of (N,) bool, optional
        Per file, the waypoints that enter the graph at all (every factor; default all): the audit's folds.
    corrections : list of dict, optional
        Per file, ``{"prism" | "accel_column" | "accel_base": [(key, M (N, 3, 3)), ...]}``: generic corrections
        ``M[i] c`` added to the predictions (:mod:`selfcal.factors.stationing`); their keys start at zero.
    start : gtsam.Values, optional
        Starting values for the keys it holds (a previous fit: fewer iterations).
    """
    graph, values = stationing_graph(files, prism_points, initial, estimate, use_tilt, sigmas, rezero, waypoints,
                                     corrections, start)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    log.info("stationing LM: error %.6g -> %.6g", graph.error(values), graph.error(result))
    cal = Calibration(np.asarray(result.atPoint3(PRISM)), float(result.atVector(PIVOT)[0]),
                      result.atRot3(MOUNT_COLUMN).matrix(), result.atRot3(MOUNT_BASE).matrix())
    fit = StationingFit(result, cal, files, use_tilt, graph)
    if estimate and marginals:
        fit.compute_marginals()
    return fit

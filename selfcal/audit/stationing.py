"""A stationing run for the audit (``--system stationing``, base ``bend``): prism + tilt sensors, one file.

Base model (``bend``): :mod:`selfcal.graphs.stationing` -- per column height a station pose, per waypoint the
column's bend, the prism lever arm, the pivot and both accelerometer mountings; the base is rigid.

Catalog: none.  What this setup gets wrong beyond the base model is searched with the generic term library
only: a correction ``sum_j phi_j(x) M c_j`` added to one residual family's prediction, ``c_j`` a 3-vector per
basis column, ``M`` the family's components:

=========================  =========================================  ===================================
family                     components of ``c``                        unit
=========================  =========================================  ===================================
``<sensor>/prism``         along the line of sight (range), across it   m
                           horizontally, across it vertically
``<sensor>/accel_column``  the column accelerometer's x, y, z           m s^-2
``<sensor>/accel_base``    the base accelerometer's x, y, z             m s^-2
=========================  =========================================  ===================================

Drivers (one value per waypoint): ``time`` (s), ``column_height`` (m, the station), the tool flange in the
column-tip frame ``arm_x``, ``arm_y``, ``arm_z`` (m; the arm's load moment on the column and base goes with
``arm_x``, ``arm_y``), ``arm_reach`` (m) and ``arm_angle`` (rad, about the column), the total station's
reading of the prism ``ts_range`` (m), ``ts_horizontal`` and ``ts_vertical`` (rad), the column's bend as the base fit
estimates it ``column_bend_x/y`` (rad; a rigid base has one tilt per file: no driver), the arm joints (rad, angles) and
every other column of the recording (auxiliary channels, e.g. a temperature).  A driver that is constant or not
finite is skipped with a note.

Sigmas: the dataset's stated ones, each family's raised to the RMS its base fit leaves where that is larger (a
variance component per family: the prism residuals are 3-6x their stated sigma from the arm's unmodelled
kinematics, and one pooled residual variance would make the score tests of the other families meaningless).
Folds: waypoints interleaved within each station (each half holds every station); a held-out waypoint's bend is
re-fitted from its own prism and column-accelerometer readings (the training fit's stations, calibration and
terms held), its three families then predicted.
"""
from __future__ import annotations

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.audit import terms as library
from selfcal.audit.engine import Fit, ResidualFamily, variance_factor
from selfcal.audit.terms import Coordinate
from selfcal.core.solve import joint_covariance
from selfcal.graphs import stationing as gs
from selfcal.models.stationing import prism_position_W, specific_force_A

FAMILIES = ("prism", "accel_column", "accel_base")
UNITS = {"prism": "m", "accel_column": "m s^-2", "accel_base": "m s^-2"}
COMPONENTS = {"prism": ("range", "horizontal", "vertical"), "accel_column": ("x", "y", "z"),
              "accel_base": ("x", "y", "z")}
SYMBOLS = {"prism": "u", "accel_column": "v", "accel_base": "w"}  # letters the stationing graph does not use
HELDOUT_ITERATIONS = 6  # Gauss-Newton steps of a held-out waypoint's bend (2 unknowns, converges in 2-3)


def line_of_sight_frames(prism_W: np.ndarray) -> np.ndarray:
    """(N, 3, 3): columns the unit line of sight, the horizontal across it, and the third axis (up-ish)."""
    p = np.asarray(prism_W, dtype=float)
    los = p / np.linalg.norm(p, axis=1, keepdims=True)
    hz = np.arctan2(p[:, 1], p[:, 0])
    across = np.column_stack([-np.sin(hz), np.cos(hz), np.zeros(len(p))])
    up = np.cross(los, across)
    return np.stack([los, across, up], axis=2)


def waypoint_drivers(geometry: gs.FileGeometry, time_s, bend_rad, angles: dict | None = None,
                     channels: dict | None = None) -> tuple[list[Coordinate], list[str]]:
    """The drivers of the module's docstring, and notes on those not offered.

    The tilt drivers are the column's bend as the base fit estimates it, never an accelerometer's own reading:
    a reading carries the very noise its residual does (on a rigid base the base accelerometer's residual IS its
    reading's noise), and a term in it would fit that noise."""
    g = geometry
    arm = g.t_T_tool
    p = g.prism_W
    horizontal = np.hypot(p[:, 0], p[:, 1])
    coords = [Coordinate("time", np.asarray(time_s, float), "s", "time"),
              Coordinate("column_height", g.column_height, "m"),
              Coordinate("arm_x", arm[:, 0], "m"), Coordinate("arm_y", arm[:, 1], "m"),
              Coordinate("arm_z", arm[:, 2], "m"), Coordinate("arm_reach", np.hypot(arm[:, 0], arm[:, 1]), "m"),
              Coordinate("arm_angle", np.arctan2(arm[:, 1], arm[:, 0]), "rad", "angle"),
              Coordinate("ts_range", np.linalg.norm(p, axis=1), "m"),
              Coordinate("ts_horizontal", np.arctan2(p[:, 1], p[:, 0]), "rad", "angle"),
              Coordinate("ts_vertical", np.arctan2(p[:, 2], horizontal), "rad", "angle"),
              Coordinate("column_bend_x", bend_rad[:, 0], "rad"), Coordinate("column_bend_y", bend_rad[:, 1], "rad")]
    coords += [Coordinate(name, np.asarray(v, float), "rad", "angle") for name, v in (angles or {}).items()]
    coords += [Coordinate(name, np.asarray(v, float), unit, "channel") for name, (v, unit) in (channels or {}).items()]
    notes = []
    if not any("temperature" in name.lower() for name in (channels or {})):
        notes.append("temperature: not in the recording; not offered as a driver")
    return coords, notes


class StationingAudit:
    name = "stationing"
    base_model = "bend"
    base_effects: tuple = ()
    folds = 2

    def __init__(self, geometry: gs.FileGeometry, tool_t_prism0, time_s, sensor: str = "stationing0",
                 angles: dict | None = None, channels: dict | None = None, sigmas: gs.StationingSigmas | None = None,
                 yaw_starts_deg=(0.0, 180.0)):
        self.g, self.sensor = geometry, sensor
        self._frames = {"prism": line_of_sight_frames(geometry.prism_W),
                        "accel_column": np.broadcast_to(np.eye(3), (len(geometry.station), 3, 3)),
                        "accel_base": np.broadcast_to(np.eye(3), (len(geometry.station), 3, 3))}
        self._measured = {"prism": geometry.prism_W, "accel_column": geometry.accel_column,
                          "accel_base": geometry.accel_base}
        self._keys = {f: library.TermKeys(SYMBOLS[f]) for f in FAMILIES}
        n = len(geometry.station)
        self._folds = [np.zeros(n, bool), np.zeros(n, bool)]
        for s in range(len(geometry.heights)):
            idx = np.flatnonzero(geometry.station == s)
            self._folds[0][idx[0::2]] = True
            self._folds[1][idx[1::2]] = True
        stated = sigmas or gs.StationingSigmas()
        # the column accelerometer's yaw on its mount is found from the bend's direction: two starts (see
        # pipelines.stationing.calibrate_stationing), the better kept and every later fit started from it
        loose = gs.StationingSigmas(**{**stated.__dict__, "mount_yaw_sigma_rad": 10.0})
        best = None
        for yaw in yaw_starts_deg:
            init = gs.Calibration(np.asarray(tool_t_prism0, float), 0.5,
                                  Rotation.from_euler("z", yaw, degrees=True).as_matrix())
            fit = gs.fit_stationing([geometry], [np.ones(n, bool)], init, sigmas=loose, marginals=False)
            if best is None or fit.graph.error(fit.values) < best.graph.error(best.values):
                best = fit
        self._initial, self._start = best.calibration, best.values
        coords, self.notes = waypoint_drivers(geometry, time_s, self._tilts(best.values, np.arange(n)), angles,
                                              channels)
        self._coordinates = coords
        self._drivers = {c.name: c.values for c in coords}
        self._units = {c.name: c.unit for c in coords}
        self.sigma = {"prism": stated.prism_m, "accel_column": stated.accel_m_s2,
                      "accel_base": stated.base_accel_m_s2 or stated.accel_m_s2}
        raised = []
        for family, physical in self._predict(best.values, (), np.arange(n), self._tilts(best.values,
                                                                                         np.arange(n))).items():
            residual = physical - self._measured[family]
            dof = 3 if family == "prism" else 2  # an accelerometer's residual holds its direction only
            rms = float(np.sqrt(np.sum(residual**2) / (dof * n)))
            if rms > self.sigma[family]:
                raised.append(f"{family} {self.sigma[family]:.3g} -> {rms:.3g} {UNITS[family]}")
                self.sigma[family] = rms
        if raised:
            self.notes.append("sigmas raised to the base fit's RMS (a variance component per family): "
                              + "; ".join(raised))
        self._sigmas = gs.StationingSigmas(**{**loose.__dict__, "prism_m": self.sigma["prism"],
                                              "accel_m_s2": self.sigma["accel_column"],
                                              "base_accel_m_s2": self.sigma["accel_base"]})

    # --- the generic term library -----------------------------------------------------------------------------

    def candidates(self) -> list:
        return []

    def term_coordinates(self, fit: Fit | None = None) -> dict:
        return {(self.sensor, family): self._coordinates for family in FAMILIES}

    def catalog_term(self, candidate) -> None:
        return None

    def _corrections(self, effects) -> dict:
        """``{family: [(key, M (N, 3, 3))]}`` of the effects' terms, over all waypoints."""
        out = {f: [] for f in FAMILIES}
        for c in effects:
            columns = c.term.columns(self._drivers)
            for key, column in zip(self._keys[c.target](c.term), columns.T):
                out[c.target].append((key, column[:, None, None] * self._frames[c.target]))
        return out

    # --- fits -------------------------------------------------------------------------------------------------

    def _rows(self, fold) -> np.ndarray:
        return np.ones(len(self.g.station), bool) if fold is None else self._folds[fold]

    def _graph(self, effects, fold, start):
        rows = self._rows(fold)
        return gs.stationing_graph([self.g], [np.ones(len(rows), bool)], self._initial, sigmas=self._sigmas,
                                   waypoints=[rows], corrections=[self._corrections(effects)], start=start)

    def fit(self, effects, fold=None) -> Fit:
        graph, values = self._graph(effects, fold, self._start)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        params.setRelativeErrorTol(1e-10)
        params.setAbsoluteErrorTol(1e-12)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        rows = np.flatnonzero(self._rows(fold))
        families = self._families(values, effects, rows, self._tilts(values, rows))
        return Fit(tuple(effects), graph, values, families, {"rows": rows})

    def _tilts(self, values, rows) -> np.ndarray:
        return np.array([values.atVector(gs.tilt_key(0, i)) for i in rows]).reshape(-1, 2)

    def _predict(self, values, effects, rows, tilt, jacobians: bool = False):
        """Predicted prism / column / base readings of ``rows`` from ``values`` (their tilts given)."""
        g = self.g
        prism, pivot = np.asarray(values.atPoint3(gs.PRISM)), float(values.atVector(gs.PIVOT)[0])
        R_col, R_base = values.atRot3(gs.MOUNT_COLUMN).matrix(), values.atRot3(gs.MOUNT_BASE).matrix()
        out = {f: np.empty((len(rows), 3)) for f in FAMILIES}
        H = {f: np.zeros((len(rows), 3, 2)) for f in ("prism", "accel_column")}
        station = g.station[rows]
        for s in np.unique(station):
            k = np.flatnonzero(station == s)
            i = rows[k]
            pose = values.atPose3(gs.station_key(0, s))
            R = pose.rotation().matrix()
            p, _, Hp, _, _ = prism_position_W(R, pose.translation(), tilt[k], g.R_T_tool[i], g.t_T_tool[i], prism,
                                              g.column_height[i], pivot)
            f, _, Hf, _ = specific_force_A(R, tilt[k], R_col, np.linalg.norm(g.accel_column[i], axis=1))
            out["prism"][k], out["accel_column"][k], H["prism"][k], H["accel_column"][k] = p, f, Hp, Hf
        R_B = values.atPose3(gs.base_key(0)).rotation().matrix()
        out["accel_base"] = specific_force_A(R_B, np.zeros((len(rows), 2)), R_base,
                                             np.linalg.norm(g.accel_base[rows], axis=1))[0]
        for family, terms in self._corrections(effects).items():
            for key, M in terms:
                out[family] = out[family] + np.einsum("nij,j->ni", M[rows], values.atVector(key))
        return (out, H) if jacobians else out

    def _families(self, values, effects, rows, tilt) -> list[ResidualFamily]:
        predicted = self._predict(values, effects, rows, tilt)
        coords = {c.name: c.values[rows] for c in self._coordinates}
        channels = tuple(c.name for c in self._coordinates if c.kind == "channel")
        angles = tuple(c.name for c in self._coordinates if c.kind == "angle")
        out = []
        for family in FAMILIES:
            physical = predicted[family] - self._measured[family][rows]
            if family == "prism":  # in the components the terms use: range, across horizontally, across vertically
                physical = np.einsum("nji,nj->ni", self._frames["prism"][rows], physical)
            out.append(ResidualFamily(self.sensor, family, UNITS[family], physical / self.sigma[family], physical,
                                      coords, channels, angles))
        return out

    def extend_all(self, fit: Fit, candidates):
        """One graph holding every candidate (new variables at zero): (graph, values, new columns each)."""
        graph, values = self._graph(fit.effects + tuple(candidates), None, fit.values)  # the engine scores full fits
        groups = [[(key, np.arange(3)) for key in self._keys[c.target](c.term)] for c in candidates]
        return graph, values, groups

    def heldout(self, fit: Fit, fold: int) -> list[ResidualFamily]:
        """The other half's waypoints: each one's bend re-fitted from its prism and column readings (Gauss-Newton,
        with the graph's bend prior), everything else held from ``fit``; its three families predicted."""
        rows = np.flatnonzero(~self._rows(fold))
        tilt = np.zeros((len(rows), 2))
        prior = self._sigmas.tilt_prior_rad
        for _ in range(HELDOUT_ITERATIONS):
            predicted, H = self._predict(fit.values, fit.effects, rows, tilt, jacobians=True)
            r = np.concatenate([(predicted["prism"] - self.g.prism_W[rows]) / self.sigma["prism"],
                                (predicted["accel_column"] - self.g.accel_column[rows]) / self.sigma["accel_column"],
                                tilt / prior], axis=1)  # (n, 8)
            J = np.concatenate([H["prism"] / self.sigma["prism"], H["accel_column"] / self.sigma["accel_column"],
                                np.broadcast_to(np.eye(2) / prior, (len(rows), 2, 2))], axis=1)  # (n, 8, 2)
            step = np.linalg.solve(np.einsum("nki,nkj->nij", J, J), np.einsum("nki,nk->ni", J, r)[:, :, None])[:, :, 0]
            tilt = tilt - step
        return self._families(fit.values, fit.effects, rows, tilt)

    # --- estimates --------------------------------------------------------------------------------------------

    def estimate(self, fit: Fit, candidate) -> tuple[dict, dict]:
        """Coefficients per component (see the module's table) and 1-sigma, the covariance scaled by the fit's
        variance factor where that exceeds 1."""
        vf = max(1.0, variance_factor(fit))
        keys = self._keys[candidate.target](candidate.term)
        joint = joint_covariance(fit.graph, fit.values, keys, "the audited term") * vf
        estimate, std = library.describe(candidate.term, np.array([fit.values.atVector(k) for k in keys]), joint,
                                         self._drivers, UNITS[candidate.target],
                                         self._units.get(candidate.term.driver, ""))
        estimate["target"] = f"{self.sensor}/{candidate.target}"
        estimate["components"] = list(COMPONENTS[candidate.target])
        return estimate, std

"""``selfcal calibrate stationing``: prism lever arm, column pivot and tilt-sensor mountings of a mobile
manipulator from total-station stationing datasets (graph: :mod:`selfcal.graphs.stationing`).

Two uses:

* :func:`calibrate_stationing` fits the calibration to one or several dataset files (every waypoint: the
  evaluation points turn the tool, which the lever arm needs) and reports the residuals against the stated
  sigmas;
* :func:`heldout_stationing` applies a calibration the way a site would: each column height is stationed from
  its stationing points (prism + both accelerometers) and the evaluation points are predicted (their column
  tilt from the column accelerometer alone) and compared with the total station.  The same is done with the
  URDF's nominal lever arm and no accelerometers (rigid stations, as the dataset's own Kabsch example) as the
  baseline.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from selfcal.graphs.stationing import (MOUNT_BASE, MOUNT_COLUMN, PIVOT, PRISM, Calibration, StationingSigmas,
                                       file_geometry, fit_stationing)
from selfcal.io.stationing import default_urdf, read_stationing_dataset, read_urdf_chain

log = logging.getLogger(__name__)

ARM_FROM, ARM_TO = "column_tip", "tool_link"


def _urdf_prism(urdf) -> np.ndarray:
    """The URDF's own (CAD / earlier calibration) prism position in the tool frame: the starting value."""
    chain = read_urdf_chain(urdf, "tool_link", "prism")
    return chain[-1].origin[:3, 3].copy()


def load_files(paths, urdf=None):
    paths = [Path(p) for p in paths]
    datasets = [read_stationing_dataset(p) for p in paths]  # the dataset's own errors first
    urdf = Path(urdf) if urdf else default_urdf(paths[0])
    chain = read_urdf_chain(urdf, ARM_FROM, ARM_TO)
    return [file_geometry(d, chain) for d in datasets], urdf


@dataclass
class ResidualSummary:
    """RMS residuals of one file, per axis, and normalised by the stated sigmas."""

    name: str
    prism_rms_m: np.ndarray
    column_accel_rms_m_s2: np.ndarray
    base_accel_rms_m_s2: np.ndarray
    sigmas: StationingSigmas

    def to_dict(self) -> dict:
        s = self.sigmas
        return {"prism_rms_mm": (self.prism_rms_m * 1e3).tolist(),
                "prism_rms_over_sigma": (self.prism_rms_m / s.prism_m).tolist(),
                "column_accel_rms_over_sigma": (self.column_accel_rms_m_s2 / s.accel_m_s2).tolist(),
                "base_accel_rms_over_sigma": (self.base_accel_rms_m_s2 / s.accel_m_s2).tolist()}


@dataclass
class StationingCalibration:
    files: list[str]
    calibration: Calibration
    residuals: list[ResidualSummary]
    seconds: float
    sigmas: StationingSigmas = field(default_factory=StationingSigmas)

    def to_dict(self) -> dict:
        c = self.calibration

        def sig(key, n):
            return np.sqrt(np.diag(c.cov[key]))[:n].tolist() if key in c.cov else None

        def mount(R, key):
            return {"R": R.tolist(), "rotvec_rad": Rotation.from_matrix(R).as_rotvec().tolist(),
                    "rotvec_rad_sigma": sig(key, 3)}
        return {
            "datasets": self.files,
            "tool_t_prism_m": c.tool_t_prism.tolist(), "tool_t_prism_m_sigma": sig(PRISM, 3),
            "pivot_fraction": c.pivot_fraction, "pivot_fraction_sigma": sig(PIVOT, 1)[0] if PIVOT in c.cov else None,
            "R_column_tip_accel": mount(c.R_T_Acol, MOUNT_COLUMN),
            "R_base_accel": mount(c.R_B_Abase, MOUNT_BASE),
            "notes": ("R_x_accel maps accelerometer axes into the body frame (v_body = R v_accel); the mounting "
                      "tilt includes the accelerometer's horizontal bias (not separable at small tilts); the base "
                      "mounting is relative to the column tip's mean attitude over the stations; sigmas are "
                      "1-sigma from the graph's marginals at the stated measurement sigmas, which the prism "
                      "residuals exceed (arm kinematics errors), so they are optimistic for the lever arm"),
            "residuals": {r.name: r.to_dict() for r in self.residuals},
            "seconds": self.seconds,
        }

    def summary(self) -> str:
        c = self.calibration
        lines = [f"prism in tool frame [mm]: {np.round(c.tool_t_prism * 1e3, 2).tolist()}",
                 f"pivot fraction: {c.pivot_fraction:.3f}",
                 f"column accel mounting roll/pitch/yaw [deg]: "
                 f"{np.round(Rotation.from_matrix(c.R_T_Acol).as_euler('xyz', degrees=True), 3).tolist()}",
                 f"base accel mounting roll/pitch/yaw [deg]: "
                 f"{np.round(Rotation.from_matrix(c.R_B_Abase).as_euler('xyz', degrees=True), 3).tolist()}"]
        for r in self.residuals:
            d = r.to_dict()
            lines.append(f"{r.name}: prism RMS {np.round(d['prism_rms_mm'], 2).tolist()} mm "
                         f"({np.round(d['prism_rms_over_sigma'], 1).tolist()} sigma); column accel "
                         f"{np.round(d['column_accel_rms_over_sigma'][:2], 2).tolist()} sigma, base accel "
                         f"{np.round(d['base_accel_rms_over_sigma'][:2], 2).tolist()} sigma (x, y)")
        return "\n".join(lines)


def _rms(a, axis=0):
    return np.sqrt(np.mean(np.square(a), axis=axis))


def calibrate_stationing(paths, urdf=None, sigmas: StationingSigmas | None = None,
                         yaw_starts_deg=(0.0, 180.0)) -> StationingCalibration:
    """Fit the calibration to every waypoint of the given dataset files (jointly).

    The column accelerometer's yaw on its mount is found from the direction of the column's bend under load;
    the fit is started from each of ``yaw_starts_deg`` and the lowest cost kept (the cost has a second minimum
    near the opposite yaw).
    """
    sig = sigmas or StationingSigmas(mount_yaw_sigma_rad=10.0, base_mount_yaw_sigma_rad=0.05 if len(paths) == 1
                                     else 10.0)
    start = time.perf_counter()
    files, urdf = load_files(paths, urdf)
    prism0 = _urdf_prism(urdf)
    best = None
    for yaw in yaw_starts_deg:
        init = Calibration(prism0, 0.5, Rotation.from_euler("z", yaw, degrees=True).as_matrix())
        fit = fit_stationing(files, [np.ones(len(g.station), bool) for g in files], init, sigmas=sig,
                             marginals=False)
        err = fit.graph.error(fit.values)
        log.info("column accel yaw start %.0f deg: cost %.6g", yaw, err)
        if best is None or err < best[0]:
            best = (err, fit)
    fit = best[1]
    fit.compute_marginals()
    residuals = []
    for f, g in enumerate(files):
        col, base = fit.accel_residuals(f)
        residuals.append(ResidualSummary(g.name, _rms(fit.predict_prism(f) - g.prism_W), _rms(col), _rms(base), sig))
    return StationingCalibration([str(p) for p in paths], fit.calibration, residuals,
                                 time.perf_counter() - start, sig)


@dataclass
class HeldOut:
    """Evaluation points predicted from stationing points: RMS per axis (m), library vs baseline."""

    name: str
    n_evaluation: int
    rms_m: np.ndarray
    baseline_rms_m: np.ndarray
    station_rms_m: np.ndarray  # the stationing points' own fit (in-sample)

    def to_dict(self) -> dict:
        return {"n_evaluation": self.n_evaluation, "rms_mm": (self.rms_m * 1e3).tolist(),
                "rms_3d_mm": float(np.linalg.norm(self.rms_m) * 1e3),
                "baseline_rms_mm": (self.baseline_rms_m * 1e3).tolist(),
                "baseline_rms_3d_mm": float(np.linalg.norm(self.baseline_rms_m) * 1e3),
                "stationing_rms_mm": (self.station_rms_m * 1e3).tolist()}


def heldout_stationing(calibration: Calibration, path, urdf=None, sigmas: StationingSigmas | None = None,
                       rezero: bool = True) -> HeldOut:
    """Station each column height from its stationing points with ``calibration`` fixed, predict the rest.

    The baseline stations rigidly from the same points with the URDF's lever arm and no accelerometer.
    With ``rezero`` the accelerometers' zero (mounting roll/pitch) is re-estimated at the site (see
    :func:`selfcal.graphs.stationing.fit_stationing`).
    """
    (g,), urdf = load_files([path], urdf)
    use = [g.stationing]
    lib = fit_stationing([g], use, calibration, estimate=False, sigmas=sigmas, marginals=False, rezero=rezero)
    base = fit_stationing([g], use, Calibration(_urdf_prism(urdf)), estimate=False, use_tilt=False,
                          sigmas=sigmas, marginals=False)
    ev = ~g.stationing
    e_lib = lib.predict_prism(0) - g.prism_W
    e_base = base.predict_prism(0) - g.prism_W
    return HeldOut(g.name, int(ev.sum()), _rms(e_lib[ev]), _rms(e_base[ev]), _rms(e_lib[g.stationing]))


# --- the audit (``selfcal audit REC --system stationing``) ------------------------------------------------------

RECORDING_COLUMNS = {"column_height", "stationing", "upside_down", "waypoint_id"}  # bookkeeping, not drivers


def audit_system(recording, base: str = "bend", sensors: list[str] | None = None):
    """The audit's view of a stationing recording (``selfcal import hilti-stationing``): the sensor with
    ``sensor_type: stationing`` (or ``sensors[0]``), its URDF beside it."""
    from selfcal.audit.stationing import StationingAudit
    from selfcal.graphs.stationing import file_geometry
    from selfcal.io.recording import RecordingError
    from selfcal.io.stationing import stationing_data_of
    where = recording.path if recording.path is not None else "<recording>"
    if sensors:
        if sensors[0] not in recording.sensors:
            raise RecordingError(f"{where}: no sensor {sensors[0]!r}")
        name = sensors[0]
    else:
        found = [n for n, s in recording.sensors.items() if s.meta.get("sensor_type") == "stationing"]
        if not found:
            raise RecordingError(f"{where}: no sensor with sensor_type: stationing (import a dataset with "
                                 "`selfcal import hilti-stationing`)")
        name = found[0]
    sensor = recording.sensors[name]
    data, urdf = stationing_data_of(sensor, f"{where}/{name}")
    geometry = file_geometry(data, read_urdf_chain(urdf, ARM_FROM, ARM_TO))
    joints = list(sensor.meta["joint_names"])
    measured = {f"{p}_{a}" for p in ("prism", "base_accel", "column_accel") for a in "xyz"}
    angles = {n: sensor.values[n] for n in joints[1:]}
    channels = {n: (v, sensor.units.get(n, "")) for n, v in sensor.values.items()
                if n not in measured and n not in joints and n not in RECORDING_COLUMNS}
    return StationingAudit(geometry, _urdf_prism(urdf), data.time_s, name, angles, channels)

"""``selfcal audit REC --system qc``: one sphere target scanned in several scenes (base model ``sphere``).

The recording holds one ranging sensor (``sensor_type: lidar``; columns and keys in docs/qc.md): ``data.csv``
one row per scene (``#timestamp [ns]`` and any auxiliary columns), one point file per scene
(``file_pattern``, default ``{timestamp}.ply``), ``sphere_radius_m`` the target's nominal radius and an optional
``qc_spec`` mapping (the keys of ``selfcal qc``'s spec) for the detection.  Each scene's sphere is detected as
``selfcal qc`` detects it, its returns within the spec's gate kept; a scene without the sphere is left out with
a note, fewer than three scenes are refused.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from selfcal.audit.qc import SphereScansAudit
from selfcal.core.sphere import sphere_residuals_m
from selfcal.graphs import qc as gq
from selfcal.io.pointcloud import read_point_cloud
from selfcal.io.recording import Recording, RecordingError
from selfcal.pipelines.qc.checks import run_qc
from selfcal.pipelines.qc.spec import QCSpec



def _lidar_sensor(recording: Recording, sensors: list[str] | None) -> str:
    where = recording.path if recording.path is not None else "<recording>"
    if sensors:
        if sensors[0] not in recording.sensors:
            raise RecordingError(f"{where}: no sensor {sensors[0]!r}")
        return sensors[0]
    lidars = [n for n, s in recording.sensors.items() if s.meta.get("sensor_type") == "lidar"]
    if not lidars:
        raise RecordingError(f"{where}: no sensor with sensor_type: lidar (the qc audit needs point files of a "
                             "sphere in several scenes)")
    return lidars[0]


def read_sphere_scans(recording: Recording, sensors: list[str] | None = None) -> tuple[gq.SphereScans, list[str]]:
    """The scenes' returns on the sphere and the notes on scenes left out."""
    name = _lidar_sensor(recording, sensors)
    sensor = recording.sensors[name]
    where = f"{recording.path if recording.path is not None else '<recording>'}/{name}"
    if "sphere_radius_m" not in sensor.meta:
        raise RecordingError(f"{where}/sensor.yaml: missing 'sphere_radius_m' (the target's nominal radius)")
    nominal = sensor.meta["sphere_radius_m"]
    if isinstance(nominal, bool) or not isinstance(nominal, (int, float)) or not 0 < nominal < float("inf"):
        raise RecordingError(f"{where}/sensor.yaml: sphere_radius_m is {nominal!r}; it must be a radius in m > 0")
    nominal = float(nominal)
    spec = QCSpec.from_dict({"spheres": {"nominal_radius_m": nominal, "count": 1},
                             **(sensor.meta.get("qc_spec") or {})}, f"{where}/sensor.yaml")
    pattern = sensor.meta.get("file_pattern", "{timestamp}.ply")
    scenes, notes = [], []
    for row, ts in enumerate(sensor.t_ns):
        file = Path(sensor.folder or ".") / pattern.format(timestamp=int(ts))
        if not file.is_file():
            raise RecordingError(f"{where}: missing point file {file.name}")
        loaded = read_point_cloud(file, drop_nonfinite=True)
        found = run_qc(loaded, spec).spheres
        if not found:
            notes.append(f"{file.name}: no sphere found; scene left out")
            continue
        fit = found[0].fit
        points = np.asarray(loaded.cloud.points)
        near = points[np.abs(sphere_residuals_m(points, fit.center_m, fit.radius_m)) <= spec.spheres.gate()]
        channels = {c: float(v[row]) for c, v in sensor.values.items()}
        scenes.append(gq.scene_of(near, (ts - sensor.t_ns[0]) * 1e-9, channels))
    return gq.scans_of(name, scenes, nominal, dict(sensor.units)), notes


def sphere_scans_audit(recording: Recording, sensors: list[str] | None = None) -> SphereScansAudit:
    scans, notes = read_sphere_scans(recording, sensors)
    meta = recording.sensors[scans.sensor].meta
    audit = SphereScansAudit(scans, time_is_order=bool(meta.get("timestamps_are_scene_order", False)))
    audit.notes = notes + audit.notes
    return audit

"""Read construction-robot stationing datasets (Hilti format) and the URDF kinematic chain, in place.

Dataset YAML: ``joint_names``, ``column_heights: {h: {solution_spaces: {s: {stationing_measurements: [...],
evaluation_measurements: [...]}}}}``; each measurement holds ``id``, ``time`` (unix s), ``upside_down``,
``doosan_cmd``, ``joint_states`` (prismatic m, 6 revolute rad), ``prism_position`` (m, total-station frame),
``tilt_sensor_base_accel`` and ``tilt_sensor_column_accel`` (m s^-2).  The data are licensed CC BY-NC-SA:
read where they lie, never copied into ``data/``.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from selfcal.io.recording import Recording, RecordingError, SensorData
from selfcal.models.stationing import Joint, origin_transform

COLUMN_JOINT = "column_prismatic_joint"


@dataclass
class StationingData:
    """One dataset file as arrays, one row per static waypoint, in file order."""

    path: Path
    station: np.ndarray  # (N,) int: index into ``stations``
    stations: list[tuple[float, int]]  # (column height m, solution space)
    stationing: np.ndarray  # (N,) bool: a stationing point (else an evaluation point)
    joints: np.ndarray  # (N, 7): prismatic m, 6 arm joints rad
    prism_W: np.ndarray  # (N, 3) m
    accel_base: np.ndarray  # (N, 3) m s^-2
    accel_column: np.ndarray  # (N, 3) m s^-2
    time_s: np.ndarray  # (N,)
    ids: np.ndarray  # (N,)
    upside_down: np.ndarray  # (N,) bool

    @property
    def name(self) -> str:
        return self.path.stem

    def __len__(self) -> int:
        return len(self.station)


def read_stationing_dataset(path) -> StationingData:
    """Read one dataset YAML; RecordingError naming the file on anything unexpected."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such dataset file")
    try:
        doc = yaml.load(path.read_text(encoding="utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise RecordingError(f"{path}: invalid YAML ({' '.join(str(err).split())[:200]})") from None
    if not isinstance(doc, dict) or "column_heights" not in doc:
        raise RecordingError(f"{path}: not a stationing dataset (no 'column_heights' mapping)")
    names = doc.get("joint_names") or []
    if not names or names[0] != COLUMN_JOINT or len(names) != 7:
        raise RecordingError(f"{path}: joint_names must be [{COLUMN_JOINT}, 6 arm joints], found {names}")
    rows, stations = [], []
    for h, per_h in doc["column_heights"].items():
        for s, per_s in (per_h or {}).get("solution_spaces", {}).items():
            stations.append((float(h), int(s)))
            for kind in ("stationing_measurements", "evaluation_measurements"):
                for m in per_s.get(kind) or []:
                    rows.append((len(stations) - 1, kind.startswith("stationing"), m))
    if not rows:
        raise RecordingError(f"{path}: no measurements")
    try:
        def col(key):
            return np.array([m[key] for _, _, m in rows], dtype=float)
        data = StationingData(
            path=path, station=np.array([r[0] for r in rows]), stations=stations,
            stationing=np.array([r[1] for r in rows]), joints=col("joint_states"), prism_W=col("prism_position"),
            accel_base=col("tilt_sensor_base_accel"), accel_column=col("tilt_sensor_column_accel"),
            time_s=col("time"), ids=col("id").astype(int),
            upside_down=np.array([bool(m.get("upside_down", False)) for _, _, m in rows]))
    except (KeyError, TypeError, ValueError) as err:
        raise RecordingError(f"{path}: measurement field missing or malformed ({err})") from None
    for label, a, width in (("joint_states", data.joints, 7), ("prism_position", data.prism_W, 3),
                            ("tilt_sensor_base_accel", data.accel_base, 3),
                            ("tilt_sensor_column_accel", data.accel_column, 3)):
        if a.ndim != 2 or a.shape[1] != width or not np.isfinite(a).all():
            raise RecordingError(f"{path}: {label} must be {width} finite numbers per measurement")
    return data


def read_urdf_chain(path, from_link: str, to_link: str) -> list[Joint]:
    """The serial chain of joints from ``from_link`` down to ``to_link`` (mimic joints are not followed).

    Raises RecordingError if the file is not a URDF or the links are not connected parent-to-child.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as err:
        raise RecordingError(f"{path}: cannot read URDF ({err})") from None
    by_child = {}
    for j in root.findall("joint"):
        by_child[j.find("child").get("link")] = j
    chain = []
    link = to_link
    while link != from_link:
        j = by_child.get(link)
        if j is None:
            raise RecordingError(f"{path}: no joint chain from {from_link!r} to {to_link!r}")
        o = j.find("origin")
        xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
        rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        axis = j.find("axis")
        chain.append(Joint(j.get("name"), j.get("type"), origin_transform(xyz, rpy),
                           np.array([float(v) for v in (axis.get("xyz") if axis is not None else "1 0 0").split()])))
        link = j.find("parent").get("link")
    return chain[::-1]


def default_urdf(dataset_path) -> Path:
    """``trailblazer.urdf`` next to the dataset file (where the upstream repository keeps it)."""
    return Path(dataset_path).parent / "trailblazer.urdf"


# --- as a recording (``selfcal import hilti-stationing``) ------------------------------------------------------

SENSOR = "stationing0"
URDF_PAYLOAD = "robot.urdf"
_VECTORS = {"prism": ("prism_W", "m"), "base_accel": ("accel_base", "m s^-2"),
            "column_accel": ("accel_column", "m s^-2")}


def import_hilti_stationing(yaml_file, urdf=None) -> Recording:
    """One Hilti stationing dataset file as a recording: sensor ``stationing0``, one row per waypoint in time order.

    Columns: ``column_height [m]`` and ``solution_space [1]`` (the station the waypoint belongs to),
    ``stationing [1]`` (1: a stationing point, 0: an evaluation point), ``upside_down [1]``, ``waypoint_id [1]``,
    the 7 joint states under their URDF names (m, rad), ``prism_x/y/z [m]`` (total-station frame),
    ``base_accel_x/y/z`` and ``column_accel_x/y/z [m s^-2]``.  The robot's URDF (``trailblazer.urdf`` next to the
    file unless given) is copied beside them as ``robot.urdf``: the kinematics belong to the recording.
    """
    data = read_stationing_dataset(yaml_file)
    urdf = Path(urdf) if urdf else default_urdf(yaml_file)
    read_urdf_chain(urdf, "column_tip", "tool_link")  # refuse a URDF without the arm's chain now, not at audit
    order = np.argsort(data.time_s, kind="stable")
    t_ns = np.round(data.time_s[order] * 1e9).astype(np.int64)
    if np.any(np.diff(t_ns) <= 0):
        raise RecordingError(f"{data.path}: two waypoints share a time stamp; a recording needs them distinct")
    doc = yaml.load(data.path.read_text(encoding="utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    joint_names = [str(n) for n in doc["joint_names"]]
    heights = np.array([h for h, _ in data.stations])[data.station]
    spaces = np.array([s for _, s in data.stations])[data.station]
    values = {"column_height": heights, "solution_space": spaces, "stationing": data.stationing,
              "upside_down": data.upside_down, "waypoint_id": data.ids}
    units = {"column_height": "m", "solution_space": "1", "stationing": "1", "upside_down": "1", "waypoint_id": "1"}
    for j, name in enumerate(joint_names):
        values[name], units[name] = data.joints[:, j], "m" if j == 0 else "rad"
    for prefix, (field, unit) in _VECTORS.items():
        for k, axis in enumerate("xyz"):
            values[f"{prefix}_{axis}"], units[f"{prefix}_{axis}"] = getattr(data, field)[:, k], unit
    values = {k: np.asarray(v, dtype=float)[order] for k, v in values.items()}
    meta = {"sensor_type": "stationing", "urdf": URDF_PAYLOAD, "joint_names": joint_names,
            "source": f"hilti_stationing_totalstation_accelerometers/{data.path.name} (CC BY-NC-SA 3.0)",
            "prism_sigma_m": 0.75e-3, "accel_sigma_m_s2": 4.3610059e-4}
    sensor = SensorData(SENSOR, t_ns, values, units, meta)
    return Recording(path=None, sensors={SENSOR: sensor},
                     payloads={f"{SENSOR}/{URDF_PAYLOAD}": urdf.read_bytes()})


def stationing_data_of(sensor, where: str) -> tuple[StationingData, Path]:
    """A recording's stationing sensor as :class:`StationingData` (rows in time order) and its URDF's path."""
    meta = sensor.meta
    names = meta.get("joint_names")
    needed = ["column_height", "solution_space", "stationing"] + list(names or []) + \
        [f"{p}_{a}" for p in _VECTORS for a in "xyz"]
    if not names or len(names) != 7:
        raise RecordingError(f"{where}/sensor.yaml: 'joint_names' must list the column joint and 6 arm joints")
    missing = [c for c in needed if c not in sensor.values]
    if missing:
        raise RecordingError(f"{where}/data.csv: missing column(s) {', '.join(missing)}")
    urdf = Path(sensor.folder or ".") / str(meta.get("urdf", URDF_PAYLOAD))
    if not urdf.is_file():
        raise RecordingError(f"{where}: no robot URDF {urdf.name} beside data.csv")
    v = sensor.values
    pairs = list(zip(v["column_height"], v["solution_space"].astype(int)))
    stations = list(dict.fromkeys((float(h), int(s)) for h, s in pairs))
    station = np.array([stations.index((float(h), int(s))) for h, s in pairs])

    def vec(prefix):
        return np.column_stack([v[f"{prefix}_{a}"] for a in "xyz"])
    data = StationingData(
        path=Path(where), station=station, stations=stations, stationing=v["stationing"] > 0.5,
        joints=np.column_stack([v[n] for n in names]), prism_W=vec("prism"), accel_base=vec("base_accel"),
        accel_column=vec("column_accel"), time_s=(sensor.t_ns - sensor.t_ns[0]) * 1e-9,
        ids=v.get("waypoint_id", np.arange(len(station))).astype(int),
        upside_down=v.get("upside_down", np.zeros(len(station))) > 0.5)
    for label, a in (("joint states", data.joints), ("prism", data.prism_W), ("base_accel", data.accel_base),
                     ("column_accel", data.accel_column)):
        if not np.isfinite(a).all():
            raise RecordingError(f"{where}/data.csv: {label} columns must be finite")
    return data, urdf

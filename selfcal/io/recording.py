"""Recordings in the EuRoC/ASL folder layout (the library's one data contract; see ARCHITECTURE.md).

``REC/<sensor>/data.csv`` starts with ``#timestamp [ns]``; every further column is ``name [unit]``.
IMU sensors carry the six EuRoC columns; any other column is an auxiliary channel, kept and offered to the
audit.  ``REC/<sensor>/sensor.yaml`` holds the sensor's metadata (Kalibr noise keys, rate, ...).
``REC/truth/`` (simulated recordings only) is never read by :func:`read_recording`.
"""
from __future__ import annotations

import io
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from selfcal.core.sanity import imu_problems

from selfcal.core.errors import SelfcalError
from selfcal.io.atomic import atomic_directory

log = logging.getLogger(__name__)

GYRO_COLUMNS = ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")
ACCEL_COLUMNS = ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
GYRO_UNIT = "rad s^-1"
ACCEL_UNIT = "m s^-2"

IMU_UNITS = {**{c: GYRO_UNIT for c in GYRO_COLUMNS}, **{c: ACCEL_UNIT for c in ACCEL_COLUMNS}}
TIMESTAMP_FIELD = "#timestamp [ns]"
TRUTH_FOLDER = "truth"

# "name [unit]": name and unit non-empty, neither holds brackets or commas (a dimensionless column uses "[1]")
_FIELD_RE = re.compile(r"^([^\[\],]*[^\[\],\s])\s*\[([^\[\],]+)\]$")
_INT_RE = re.compile(r"^\s*[+-]?[0-9]+\s*$")


class RecordingError(SelfcalError):
    """Bad recording input; the message is one line naming the file (and line, where there is one)."""


class ForeignSensorError(RecordingError):
    """A ``data.csv`` whose header is not a recording sensor's and names no IMU column (EuRoC's
    ``cam0/data.csv`` with ``#timestamp [ns],filename``, its ground truth with ``#timestamp, p_RS_R_x [m]``):
    :func:`read_recording` skips such a folder, as it skips a folder without ``data.csv``."""


@dataclass
class SensorData:
    """One sensor folder: timestamps, named columns (without unit) in file order, units, sensor.yaml."""

    name: str
    t_ns: np.ndarray  # int64, strictly increasing
    values: dict[str, np.ndarray]  # column name (no unit) -> float64 (N,)
    units: dict[str, str]  # column name -> unit string as in the header
    meta: dict = field(default_factory=dict)
    folder: Path | None = None  # where it was read from: sensors with binary payloads (array0/frames.npy,
    # scan0/*.ply) load those themselves from here


@dataclass
class ImuData:
    """An IMU sensor as arrays: gyro (N, 3) rad/s, accel (N, 3) m/s^2, auxiliary channels (N,) each."""

    name: str
    t_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    channel_units: dict[str, str] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def t_s(self) -> np.ndarray:
        """Timestamps in s relative to the first sample (float64 keeps ns resolution over days)."""
        return (self.t_ns - self.t_ns[0]) * 1e-9

    @property
    def rate_hz(self) -> float:
        """Nominal rate from sensor.yaml, else from the median sample spacing."""
        if "rate_hz" in self.meta:
            return float(self.meta["rate_hz"])
        return 1e9 / float(np.median(np.diff(self.t_ns)))


@dataclass
class Recording:
    path: Path | None
    sensors: dict[str, SensorData]
    payloads: dict[str, bytes] = field(default_factory=dict)  # files beside the CSVs ("lidar0/<t>.xyz.gz"), by
    # relative path: what an importer writes with the recording (a read recording loads them from the folders)
    skipped: dict[str, str] = field(default_factory=dict)  # folder -> why it is no sensor (foreign data.csv)

    def imu_names(self) -> list[str]:
        """Names of the sensors that carry the six IMU columns, sorted."""
        return sorted(name for name, s in self.sensors.items() if all(c in s.values for c in IMU_UNITS))

    def imu(self, name: str, gaps_allowed: bool = False, gyro_saturation_allowed: bool = False) -> ImuData:
        """The IMU view of sensor ``name``; RecordingError if it is missing, not an IMU, or fails the physical
        checks (:func:`selfcal.core.sanity.imu_problems`; ``gaps_allowed`` for an online replay,
        ``gyro_saturation_allowed`` for a caller that excludes saturated gyro samples itself)."""
        where = self.path if self.path is not None else "<recording>"
        if name not in self.sensors:
            why = f"; {name} skipped: {self.skipped[name]}" if name in self.skipped else ""
            raise RecordingError(f"{where}: no sensor {name!r} (sensors: {', '.join(sorted(self.sensors)) or 'none'}"
                                 f"{why})")
        s = self.sensors[name]
        missing = [c for c in IMU_UNITS if c not in s.values]
        if missing:
            raise RecordingError(f"{where}/{name}: not an IMU sensor (missing columns {', '.join(missing)})")
        problems = imu_problems((s.t_ns - s.t_ns[0]) * 1e-9, np.column_stack([s.values[c] for c in GYRO_COLUMNS]),
                                np.column_stack([s.values[c] for c in ACCEL_COLUMNS]), GYRO_COLUMNS + ACCEL_COLUMNS,
                                gaps_allowed, s.meta.get("rate_hz"), gyro_saturation_allowed)
        if problems:
            raise RecordingError(f"{where}/{name}: {problems[0]}")
        channels = {c: v for c, v in s.values.items() if c not in IMU_UNITS}
        return ImuData(name=name, t_ns=s.t_ns,
                       gyro_rad_s=np.column_stack([s.values[c] for c in GYRO_COLUMNS]),
                       accel_m_s2=np.column_stack([s.values[c] for c in ACCEL_COLUMNS]),
                       channels=channels, channel_units={c: s.units[c] for c in channels}, meta=s.meta)


def imu_sensor(name, t_ns, gyro_rad_s, accel_m_s2, channels=None, meta=None) -> SensorData:
    """Build an IMU SensorData; ``channels`` maps name -> (values (N,), unit).

    Parameters
    ----------
    name : str
        Sensor folder name (``imu0``, ...).
    t_ns : array_like (N,)
        Integer timestamps in ns, strictly increasing.  A float array is accepted only if it holds integers.
    gyro_rad_s, accel_m_s2 : array_like (N, 3)
        Angular rate in rad/s and specific force in m/s^2, sensor frame.
    channels : dict, optional
        Auxiliary channels, ``name -> (values (N,), unit)``.
    meta : dict, optional
        Content of sensor.yaml.

    Returns
    -------
    SensorData
    """
    t = _as_timestamps(t_ns, name)
    gyro = np.asarray(gyro_rad_s, dtype=np.float64)
    accel = np.asarray(accel_m_s2, dtype=np.float64)
    for label, a in (("gyro_rad_s", gyro), ("accel_m_s2", accel)):
        if a.shape != (t.size, 3):
            raise RecordingError(f"sensor {name}: {label} has shape {a.shape}, expected ({t.size}, 3)")
    values = {c: gyro[:, i].copy() for i, c in enumerate(GYRO_COLUMNS)}
    values.update({c: accel[:, i].copy() for i, c in enumerate(ACCEL_COLUMNS)})
    units = dict(IMU_UNITS)
    for ch, (v, unit) in (channels or {}).items():
        if ch in values:
            raise RecordingError(f"sensor {name}: channel {ch!r} clashes with an IMU column")
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (t.size,):
            raise RecordingError(f"sensor {name}: channel {ch!r} has shape {v.shape}, expected ({t.size},)")
        values[ch] = v
        units[ch] = str(unit)
    return SensorData(name=name, t_ns=t, values=values, units=units, meta=dict(meta or {}))


# ----------------------------------------------------------------------------------------------------- reading

def read_recording(path) -> Recording:
    """Read every sensor folder of REC (not ``truth/``); RecordingError with file:line on bad input.

    Parameters
    ----------
    path : str or Path
        The recording folder.  Every subfolder holding a ``data.csv`` is a sensor; other subfolders (and
        ``truth/``) are ignored, and so is a folder whose ``data.csv`` header is not a recording sensor's and
        names no IMU column (a camera's ``#timestamp [ns],filename`` in an EuRoC ``mav0``): it is listed in
        ``Recording.skipped`` with the reason, and logged.

    Returns
    -------
    Recording
        Sensors in sorted folder order.

    Raises
    ------
    RecordingError
        One line naming the file (and the 1-based line number) of the first problem found.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such recording folder")
    if not path.is_dir():
        raise RecordingError(f"{path}: not a folder (a recording is a folder with one subfolder per sensor)")
    simulated = (path / TRUTH_FOLDER).is_dir()
    sensors, skipped = {}, {}
    for sub in sorted(p for p in path.iterdir() if p.is_dir()):
        if sub.name == TRUTH_FOLDER or sub.name.startswith(".") or not (sub / "data.csv").is_file():
            continue
        try:
            sensors[sub.name] = read_sensor(sub, simulated)
        except ForeignSensorError as err:
            skipped[sub.name] = str(err)
            log.warning("skipped folder %s, not a recording sensor: %s", sub.name, err)
    if not sensors:
        hint = ("; an EuRoC dataset? point at its mav0 folder, or convert it with 'selfcal import euroc'"
                if (path / "mav0").is_dir() else "")
        foreign = f" (skipped: {', '.join(skipped)})" if skipped else ""
        raise RecordingError(f"{path}: no sensor folder with a data.csv in this recording{foreign}{hint}")
    return Recording(path=path, sensors=sensors, skipped=skipped)


def read_sensor(folder, simulated: bool = False) -> SensorData:
    """One sensor folder (``data.csv`` and its optional ``sensor.yaml``), checked as :func:`read_recording` does.

    ``simulated`` admits noise densities of zero in sensor.yaml.  ForeignSensorError (a RecordingError) for a
    ``data.csv`` that is no recording sensor's.
    """
    folder = Path(folder)
    t_ns, values, units = _read_data_csv(folder / "data.csv")
    return SensorData(folder.name, t_ns, values, units, _read_sensor_yaml(folder / "sensor.yaml", simulated), folder)


def read_truth(path) -> dict:
    """truth/truth.yaml of a simulated recording (for tests and benchmarks only, never for estimators).

    ``path`` is the recording folder (or the truth.yaml file itself).
    """
    path = Path(path)
    file = path / TRUTH_FOLDER / "truth.yaml" if path.is_dir() else path
    if not file.is_file():
        raise RecordingError(f"{file}: no ground truth (only simulated recordings have truth/truth.yaml)")
    truth = _load_yaml(file)
    return truth if truth is not None else {}


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _load_yaml(file: Path):
    try:
        return yaml.safe_load(file.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{file}:{mark.line + 1}" if mark is not None else f"{file}"
        problem = getattr(err, "problem", None) or err
        raise RecordingError(f"{where}: invalid YAML ({_one_line(problem)})") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RecordingError(f"{file}: cannot read ({_one_line(err)})") from None


POSITIVE_KEYS = ("rate_hz", "accelerometer_noise_density", "gyroscope_noise_density")  # a zero noise density
# claims a perfect sensor (every residual infinitely significant); a zero rate has no sample period
NON_NEGATIVE_KEYS = ("accelerometer_random_walk", "gyroscope_random_walk")  # zero: a constant bias


def _read_sensor_yaml(file: Path, simulated: bool = False) -> dict:
    """sensor.yaml as a mapping, its noise and rate keys checked; ``simulated`` (the recording holds ``truth/``)
    admits noise densities of zero (a simulation's exact data), which no measured sensor has."""
    if not file.exists():
        return {}
    meta = _load_yaml(file)
    if meta is None:
        return {}
    if not isinstance(meta, dict):
        raise RecordingError(f"{file}: expected a mapping of keys (sensor_type, rate_hz, ...), "
                             f"found a {type(meta).__name__}")
    for key in POSITIVE_KEYS + NON_NEGATIVE_KEYS:
        if key not in meta:
            continue
        value = meta[key]
        number = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None
        zero_allowed = key in NON_NEGATIVE_KEYS or (simulated and key != "rate_hz")
        if number is None or not np.isfinite(number) or number < 0 or (number == 0 and not zero_allowed):
            need = "a number >= 0" if zero_allowed else "a positive number (no measured sensor is noise-free)"
            raise RecordingError(f"{file}: {key} is {value!r}; it must be {need}")
    return meta


def _parse_header(file: Path, line: str) -> tuple[list[str], list[str]]:
    """Column names and units (without the timestamp column) from the header line.

    A header not of the recording form raises ForeignSensorError when none of its fields looks like an IMU
    column (the folder is some other tool's: skipped), RecordingError when one does (a broken IMU: refused).
    """
    fields = [f.strip() for f in line.lstrip("\ufeff").split(",")]
    imu_like = any(f.lower().startswith(("w_rs_s_", "a_rs_s_")) for f in fields)
    error = RecordingError if imu_like else ForeignSensorError
    first = _FIELD_RE.match(fields[0])
    if first is None or first.group(1) != "#timestamp":
        raise error(f"{file}:1: header must start with {TIMESTAMP_FIELD!r}, found {fields[0]!r}")
    if first.group(2).strip() != "ns":
        raise error(f"{file}:1: timestamp unit must be ns, found {first.group(2).strip()!r}")
    names, units = [], []
    for k, f in enumerate(fields[1:], start=2):
        m = _FIELD_RE.match(f)
        if m is None:
            raise error(f"{file}:1: header field {k} {f!r} is not of the form 'name [unit]'")
        name, unit = m.group(1).strip(), m.group(2).strip()
        if name in names:
            raise error(f"{file}:1: column {name!r} appears twice in the header")
        names.append(name)
        units.append(unit)
    _check_imu_columns(file, names, units)
    return names, units


def _check_imu_columns(file: Path, names: list[str], units: list[str]) -> None:
    """If the header looks like an IMU (any column resembling w_RS_S_* / a_RS_S_*), require all six exactly."""
    lower = {n.lower(): n for n in names}
    imu_like = [n for n in names if n.lower().startswith(("w_rs_s_", "a_rs_s_"))]
    if not imu_like:
        return
    for col, unit in IMU_UNITS.items():
        if col not in names:
            near = lower.get(col.lower())
            found = f"found {near!r} instead" if near else f"IMU columns found: {', '.join(imu_like)}"
            raise RecordingError(f"{file}:1: IMU column '{col} [{unit}]' missing ({found})")
        got = units[names.index(col)]
        if got != unit:
            raise RecordingError(f"{file}:1: column {col} has unit [{got}], expected [{unit}]")


def _read_data_csv(file: Path) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, str]]:
    try:
        raw = file.read_bytes()
    except OSError as err:
        raise RecordingError(f"{file}: cannot read ({_one_line(err.strerror or err)})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw[:err.start].count(b"\n") + 1
        raise RecordingError(f"{file}:{line}: not UTF-8 text") from None
    lines = text.replace("\r\n", "\n").split("\n")
    while lines and not lines[-1].strip():  # the final newline (and trailing blank lines) end no row
        lines.pop()
    if not lines:
        raise RecordingError(f"{file}: empty file (expected a '{TIMESTAMP_FIELD},...' header)")
    names, units = _parse_header(file, lines[0])
    rows = lines[1:]
    if not rows:
        raise RecordingError(f"{file}:1: header only, no data rows")
    t_ns, table = _parse_rows_fast(rows, len(names))
    if t_ns is None:
        _locate_bad_row(file, rows, names)  # raises
        raise RecordingError(f"{file}: cannot parse the data rows")  # not reached unless the parsers disagree
    bad = ~np.isfinite(table)
    if bad.any():
        i = int(np.argmax(bad.any(axis=1)))
        j = int(np.argmax(bad[i]))
        v = table[i, j]
        kind = "NaN" if np.isnan(v) else ("-inf" if v < 0 else "inf")
        raise RecordingError(f"{file}:{i + 2}: {kind} in column {names[j]}")
    steps = np.diff(t_ns)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1  # row index of the offending timestamp
        line = i + 2
        if steps[i - 1] == 0:
            raise RecordingError(f"{file}:{line}: duplicate timestamp {t_ns[i]} (same as line {line - 1})")
        raise RecordingError(f"{file}:{line}: timestamp {t_ns[i]} is earlier than {t_ns[i - 1]} on line "
                             f"{line - 1} (timestamps must increase)")
    values = {n: np.ascontiguousarray(table[:, j]) for j, n in enumerate(names)}
    return t_ns, values, dict(zip(names, units))


def _parse_rows_fast(rows: list[str], n_values: int):
    """(t_ns int64, values float64 (N, n_values)), or (None, None) if any row is malformed.

    Timestamps are parsed as Python ints, never through float64 (ns epochs ~1.7e18 exceed its 2^53 integers).
    """
    if any(r.count(",") != n_values for r in rows):
        return None, None
    stamps = [r[:r.index(",")] if n_values else r for r in rows]
    if not all(_INT_RE.match(s) for s in stamps):
        return None, None
    try:
        t_ns = np.array([int(s) for s in stamps], dtype=np.int64)
        if n_values == 0:
            return t_ns, np.empty((len(rows), 0))
        # comments=None: '#' is not a comment inside the data; loadtxt is numpy's C parser (fast, strict)
        table = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", comments=None, dtype=np.float64,
                           usecols=range(1, n_values + 1), ndmin=2)
    except (ValueError, OverflowError):
        return None, None
    if table.shape != (len(rows), n_values):
        return None, None
    return t_ns, table


def _locate_bad_row(file: Path, rows: list[str], names: list[str]) -> None:
    """Scan line by line (slow path, only after the fast parser failed) and raise for the first bad line."""
    n_fields = len(names) + 1
    for i, row in enumerate(rows):
        line = i + 2
        if not row.strip():
            raise RecordingError(f"{file}:{line}: empty line")
        fields = row.split(",")
        if len(fields) != n_fields:
            hint = " (truncated line?)" if len(fields) < n_fields and i == len(rows) - 1 else ""
            raise RecordingError(f"{file}:{line}: {len(fields)} fields, expected {n_fields} as in the header{hint}")
        stamp = fields[0]
        if not _INT_RE.match(stamp):
            raise RecordingError(f"{file}:{line}: timestamp {stamp.strip()!r} is not an integer number of ns")
        if not -2**63 <= int(stamp) < 2**63:
            raise RecordingError(f"{file}:{line}: timestamp {stamp.strip()} does not fit in int64")
        for name, f in zip(names, fields[1:]):
            try:
                if "_" in f:  # float() accepts '1_0'; a CSV reader must not
                    raise ValueError(f)
                v = float(f)
            except ValueError:
                raise RecordingError(f"{file}:{line}: non-numeric value {f.strip()!r} in column {name}") from None
            if not math.isfinite(v):
                kind = "NaN" if math.isnan(v) else ("-inf" if v < 0 else "inf")
                raise RecordingError(f"{file}:{line}: {kind} in column {name}")


# ----------------------------------------------------------------------------------------------------- writing

def write_recording(recording: Recording, path, truth: dict | None = None, overwrite: bool = False,
                    extra_files: dict[str, bytes] | None = None) -> Path:
    """Write REC atomically (temporary sibling folder, then rename); ``truth`` goes to truth/truth.yaml.

    Parameters
    ----------
    recording : Recording
        Sensors to write; each is checked first (strictly increasing int64 timestamps, finite values, column
        names and units that fit the header syntax), so that what is written can be read back.
    path : str or Path
        Recording folder to create.
    truth : dict, optional
        Ground truth of a simulated recording (numpy values are converted to plain Python).
    overwrite : bool
        Replace an existing folder; otherwise FileExistsError.
    extra_files : dict, optional
        Binary payloads by relative path (``"array0/frames.npy"``, ``"scan0/000001.ply"``), written inside the
        same atomic folder.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Floats are written with Python's shortest repr, which reads back to the identical float64.
    """
    path = Path(path)
    files = {}
    for name, sensor in recording.sensors.items():
        files[f"{name}/data.csv"] = _data_csv_text(name, sensor)
        files[f"{name}/sensor.yaml"] = _yaml_text(sensor.meta, f"{name}/sensor.yaml")
    if truth is not None:
        files[f"{TRUTH_FOLDER}/truth.yaml"] = _yaml_text(truth, f"{TRUTH_FOLDER}/truth.yaml")
    with atomic_directory(path, overwrite=overwrite) as tmp:
        for rel, text in files.items():
            target = tmp / rel
            target.parent.mkdir(exist_ok=True)
            target.write_text(text, encoding="utf-8", newline="\n")
        for rel, data in {**recording.payloads, **(extra_files or {})}.items():
            target = tmp / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
    return path


def _as_timestamps(t_ns, sensor: str) -> np.ndarray:
    t = np.asarray(t_ns)
    if t.ndim != 1 or t.size == 0:
        raise RecordingError(f"sensor {sensor}: timestamps must be a non-empty 1-D array, got shape {t.shape}")
    if t.dtype.kind == "f":
        if not (np.isfinite(t).all() and (t == np.round(t)).all() and np.abs(t).max() < 2**53):
            raise RecordingError(f"sensor {sensor}: timestamps must be integer ns")
    elif t.dtype.kind not in "iu":
        raise RecordingError(f"sensor {sensor}: timestamps must be integer ns, got dtype {t.dtype}")
    t = t.astype(np.int64)
    if (np.diff(t) <= 0).any():
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise RecordingError(f"sensor {sensor}: timestamps not strictly increasing at sample {i} "
                             f"({t[i - 1]} -> {t[i]})")
    return t


def _data_csv_text(name: str, sensor: SensorData) -> str:
    if not name or name == TRUTH_FOLDER or name.startswith(".") or "/" in name or "\\" in name:
        raise RecordingError(f"sensor name {name!r} cannot be a sensor folder")
    t = _as_timestamps(sensor.t_ns, name)
    header = [TIMESTAMP_FIELD]
    columns = [list(map(str, t.tolist()))]
    for col, v in sensor.values.items():
        unit = sensor.units.get(col)
        if unit is None:
            raise RecordingError(f"sensor {name}: column {col!r} has no unit")
        field_text = f"{col} [{unit}]"
        m = _FIELD_RE.match(field_text)
        if m is None or m.group(1) != col or m.group(2) != unit or col.startswith("#"):
            raise RecordingError(f"sensor {name}: {field_text!r} cannot be written as a 'name [unit]' header field")
        v = np.asarray(v, dtype=np.float64)
        if v.shape != t.shape:
            raise RecordingError(f"sensor {name}: column {col} has shape {v.shape}, expected {t.shape}")
        if not np.isfinite(v).all():
            raise RecordingError(f"sensor {name}: column {col} holds NaN or inf at sample "
                                 f"{int(np.argmax(~np.isfinite(v)))} (a recording holds finite values only)")
        header.append(field_text)
        columns.append(list(map(repr, v.tolist())))  # Python float repr: shortest string that round-trips
    lines = [",".join(header)]
    lines.extend(map(",".join, zip(*columns)))
    return "\n".join(lines) + "\n"


def to_plain(obj, where: str = "value"):
    """``obj`` with numpy scalars/arrays, tuples and Paths turned into plain Python (for yaml.safe_dump)."""
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, (str, int)) else k: to_plain(v, where) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v, where) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist(), where)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise RecordingError(f"{where}: cannot store a value of type {type(obj).__name__}")


class _Dumper(yaml.SafeDumper):
    """Block style for mappings, flow style for lists of scalars (``bias: [0.1, 0.2, 0.3]``): readable YAML."""


def _represent_list(dumper: yaml.SafeDumper, data: list):
    flat = all(not isinstance(v, (list, dict)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


_Dumper.add_representer(list, _represent_list)


def _yaml_text(data: dict, where: str) -> str:
    return yaml.dump(to_plain(data or {}, where), Dumper=_Dumper, sort_keys=False, default_flow_style=False,
                     allow_unicode=True)

"""An IMU from any text table, driven by a small YAML map of columns and units (``selfcal import imu-table``).

The map names the file(s), the delimiter and header, the time column and its unit, and each of the six
channels' column and unit; the format is documented in docs/importers.md.  Example (imu_tk's own files: two
tables, time in s then x y z)::

    files: {accel: acc.txt, gyro: gyro.txt}
    time: {column: 0, unit: s}
    accel: {x: {column: 1, unit: m/s^2}, y: {column: 2, unit: m/s^2}, z: {column: 3, unit: m/s^2}}
    gyro: {x: {column: 1, unit: rad/s}, y: {column: 2, unit: rad/s}, z: {column: 3, unit: rad/s}}

Raw counts become SI units through ``value = (counts - offset) / scale`` (``scale`` in counts per SI unit, or
per the unit named by ``per``), the numbers kept in sensor.yaml under ``raw_counts`` as the dataset importers
keep them.  Timestamps are converted from their text with exact decimal arithmetic (no float64 rounding of
epoch times) and rounded to the nearest ns.
"""
from __future__ import annotations

import gzip
import math
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np
import yaml

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.io.recording import Recording, RecordingError, imu_sensor

TIME_UNIT_NS = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}
# unit -> factor to the recording's SI unit; "g" is standard gravity by definition (not the local gravity)
GROUP_UNITS = {
    "gyro": {"rad/s": 1.0, "rad s^-1": 1.0, "deg/s": math.pi / 180.0, "deg s^-1": math.pi / 180.0},
    "accel": {"m/s^2": 1.0, "m s^-2": 1.0, "g": STANDARD_GRAVITY_M_S2},
}
COUNTS = "counts"
RAW_COUNTS_NAMES = {"accel": ("accelerometer", "m s^-2"), "gyro": ("gyroscope", "rad s^-1")}
NOISE_KEYS = ("accelerometer_noise_density", "gyroscope_noise_density",
              "accelerometer_random_walk", "gyroscope_random_walk")
MAP_KEYS = ("sensor", "files", "delimiter", "header", "skip_rows", "time", "gyro", "accel", "rate_hz", "noise",
            "gravity_m_s2")
AXES = ("x", "y", "z")


# ------------------------------------------------------------------------------------------ raw-count helpers

def counts_to_si(counts: np.ndarray, offset, per_unit) -> np.ndarray:
    """``(counts - offset) / counts_per_unit``: the transfer function stored under ``raw_counts`` in sensor.yaml."""
    return (counts - np.asarray(offset, dtype=np.float64)) / np.asarray(per_unit, dtype=np.float64)


def raw_counts_meta(accel_offset, accel_per_unit, gyro_offset, gyro_per_unit) -> dict:
    """sensor.yaml's ``raw_counts``: ``counts = offset_counts + counts_per_unit * value`` per axis."""
    return {
        "accelerometer": {"offset_counts": [float(v) for v in accel_offset],
                          "counts_per_unit": [float(v) for v in accel_per_unit], "unit": "m s^-2"},
        "gyroscope": {"offset_counts": [float(v) for v in gyro_offset],
                      "counts_per_unit": [float(v) for v in gyro_per_unit], "unit": "rad s^-1"},
    }


# ------------------------------------------------------------------------------------------------- the map

def read_imu_map(path) -> dict:
    """Load and check a map file; RecordingError in one line naming the file and the key."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such map file" if not path.exists() else f"{path}: not a file")
    try:
        spec = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else f"{path}"
        raise RecordingError(f"{where}: invalid YAML ({' '.join(str(getattr(err, 'problem', err)).split())})") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RecordingError(f"{path}: cannot read ({' '.join(str(err).split())})") from None
    check_imu_map(spec, str(path))
    return spec


def _number(value, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise RecordingError(f"{where} is {value!r}; it must be a {'positive ' if positive else ''}number")
    return float(value)


def _column_ref(value, where: str):
    if isinstance(value, bool) or not isinstance(value, (int, str)) or (isinstance(value, int) and value < 0):
        raise RecordingError(f"{where}: column is {value!r}; give a header name or a 0-based column number")
    return value


def check_imu_map(spec, where: str = "map") -> None:
    """Refuse a map that cannot be read as documented: one line naming ``where`` and the key at fault."""
    if not isinstance(spec, dict):
        raise RecordingError(f"{where}: expected a mapping (files, time, gyro, accel, ...), found "
                             f"{type(spec).__name__}")
    unknown = [k for k in spec if k not in MAP_KEYS]
    if unknown:
        raise RecordingError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(MAP_KEYS)})")
    for key in ("time", "gyro", "accel"):
        if key not in spec:
            raise RecordingError(f"{where}: missing {key!r}")
    files = spec.get("files")
    if isinstance(files, dict):
        for group in ("gyro", "accel"):
            if group not in files:
                raise RecordingError(f"{where}: files names no file for {group!r} (give 'files: {{accel: FILE, "
                                     "gyro: FILE}' or one file)")
        extra = [k for k in files if k not in ("gyro", "accel")]
        if extra:
            raise RecordingError(f"{where}: files: unknown group {extra[0]!r} (known: accel, gyro)")
    elif files is not None and not isinstance(files, str):
        raise RecordingError(f"{where}: files is {files!r}; give a file name or {{accel: FILE, gyro: FILE}}")
    if "delimiter" in spec and not (isinstance(spec["delimiter"], str) and len(spec["delimiter"]) == 1):
        raise RecordingError(f"{where}: delimiter is {spec['delimiter']!r}; give one character (omit it for "
                             "whitespace)")
    if not isinstance(spec.get("header", False), bool):
        raise RecordingError(f"{where}: header is {spec['header']!r}; give true or false")
    skip = spec.get("skip_rows", 0)
    if isinstance(skip, bool) or not isinstance(skip, int) or skip < 0:
        raise RecordingError(f"{where}: skip_rows is {skip!r}; give a number of lines >= 0")
    time = spec["time"]
    if not isinstance(time, dict) or set(time) != {"column", "unit"}:
        raise RecordingError(f"{where}: time must be {{column: ..., unit: s|ms|us|ns}}, found {time!r}")
    _column_ref(time["column"], f"{where}: time")
    if time["unit"] not in TIME_UNIT_NS:
        raise RecordingError(f"{where}: time: unknown unit {time['unit']!r} (known: {', '.join(TIME_UNIT_NS)})")
    header = spec.get("header", False)
    for group in ("gyro", "accel"):
        channels = spec[group]
        if not isinstance(channels, dict) or set(channels) != set(AXES):
            raise RecordingError(f"{where}: {group} must map x, y and z to {{column: ..., unit: ...}}, found "
                                 f"{channels!r}")
        for axis in AXES:
            _check_channel(channels[axis], group, f"{where}: {group}.{axis}")
            if isinstance(channels[axis]["column"], str) and not header:
                raise RecordingError(f"{where}: {group}.{axis}: column {channels[axis]['column']!r} is a name but "
                                     "the map says header: false (give a 0-based number, or header: true)")
    if isinstance(time["column"], str) and not header:
        raise RecordingError(f"{where}: time: column {time['column']!r} is a name but the map says header: false")
    if "rate_hz" in spec:
        _number(spec["rate_hz"], f"{where}: rate_hz", positive=True)
    if "gravity_m_s2" in spec:
        _number(spec["gravity_m_s2"], f"{where}: gravity_m_s2", positive=True)
    noise = spec.get("noise", {})
    if not isinstance(noise, dict):
        raise RecordingError(f"{where}: noise must map Kalibr keys ({', '.join(NOISE_KEYS)}) to numbers")
    for key, value in noise.items():
        if key not in NOISE_KEYS:
            raise RecordingError(f"{where}: noise: unknown key {key!r} (known: {', '.join(NOISE_KEYS)})")
        _number(value, f"{where}: noise.{key}", positive=key.endswith("noise_density"))


def _check_channel(channel, group: str, where: str) -> None:
    units = GROUP_UNITS[group]
    if not isinstance(channel, dict) or "column" not in channel or "unit" not in channel:
        raise RecordingError(f"{where}: give {{column: ..., unit: ...}}, found {channel!r}")
    _column_ref(channel["column"], where)
    unit = channel["unit"]
    if unit == COUNTS:
        allowed = {"column", "unit", "scale", "offset", "per"}
        if "scale" not in channel:
            raise RecordingError(f"{where}: unit counts needs 'scale' (counts per {next(iter(units))}, or per the "
                                 "unit named by 'per')")
        _number(channel["scale"], f"{where}: scale", positive=True)
        _number(channel.get("offset", 0), f"{where}: offset")
        if channel.get("per", next(iter(units))) not in units:
            raise RecordingError(f"{where}: per: unknown unit {channel['per']!r} (known: {', '.join(units)})")
    else:
        allowed = {"column", "unit"}
        if unit not in units:
            raise RecordingError(f"{where}: unknown unit {unit!r} (known: {', '.join(units)}, counts)")
    extra = [k for k in channel if k not in allowed]
    if extra:
        raise RecordingError(f"{where}: unknown key {extra[0]!r} (known here: {', '.join(sorted(allowed))})")


# ----------------------------------------------------------------------------------------------- the tables

class _Table:
    """One text file: its column names (with a header) and its data lines, split lazily per column."""

    def __init__(self, file: Path, delimiter: str | None, header: bool, skip_rows: int):
        self.file, self.delimiter = file, delimiter
        try:
            raw = gzip.open(file, "rt", encoding="utf-8") if file.name.endswith(".gz") else \
                open(file, encoding="utf-8")
            with raw as f:
                lines = f.read().splitlines()
        except (OSError, EOFError, UnicodeDecodeError) as err:
            raise RecordingError(f"{file}: cannot read ({' '.join(str(err).split())})") from None
        while lines and not lines[-1].strip():
            lines.pop()
        self.first_data_line = skip_rows + int(header) + 1  # 1-based line number of the first data row
        self.names = None
        if header:
            if len(lines) <= skip_rows:
                raise RecordingError(f"{file}: no header line after {skip_rows} skipped lines")
            self.names = [n.strip() for n in lines[skip_rows].split(delimiter)]
        self.lines = lines[self.first_data_line - 1:]
        if not self.lines:
            raise RecordingError(f"{file}: no data rows")

    def index(self, column, where: str) -> int:
        n_fields = len(self.lines[0].split(self.delimiter))
        if isinstance(column, str):
            if column not in self.names:
                raise RecordingError(f"{self.file}:{self.first_data_line - 1}: {where}: no column {column!r} "
                                     f"(columns: {', '.join(self.names)})")
            return self.names.index(column)
        if column >= n_fields:
            raise RecordingError(f"{self.file}:{self.first_data_line}: {where}: column {column} does not exist "
                                 f"({n_fields} columns, numbered from 0)")
        return column

    def values(self, columns: list[int]) -> np.ndarray:
        try:
            # numpy's C parser: correctly rounded float64, strict about the field count
            table = np.loadtxt(self.lines, delimiter=self.delimiter, usecols=columns, ndmin=2, comments=None,
                               dtype=np.float64)
        except ValueError as err:
            raise RecordingError(f"{self.file}: cannot parse the data rows ({' '.join(str(err).split())})") from None
        bad = ~np.isfinite(table)
        if bad.any():
            i = int(np.argmax(bad.any(axis=1)))
            raise RecordingError(f"{self.file}:{self.first_data_line + i}: NaN or inf in column "
                                 f"{columns[int(np.argmax(bad[i]))]}")
        return table

    def time_ns(self, column: int, unit: str) -> np.ndarray:
        """Timestamps from their text, exactly: Decimal(text) x ns per unit, rounded half-even to int ns."""
        factor = TIME_UNIT_NS[unit]
        t_ns = np.empty(len(self.lines), dtype=np.int64)
        for i, line in enumerate(self.lines):
            fields = line.split(self.delimiter)
            text = fields[column].strip() if column < len(fields) else ""
            try:
                t_ns[i] = int((Decimal(text) * factor).to_integral_value(rounding=ROUND_HALF_EVEN))
            except (InvalidOperation, ValueError, OverflowError):
                raise RecordingError(f"{self.file}:{self.first_data_line + i}: time {text!r} is not a number of "
                                     f"{unit}") from None
        steps = np.diff(t_ns)
        if (steps <= 0).any():
            i = int(np.argmax(steps <= 0)) + 1
            raise RecordingError(f"{self.file}:{self.first_data_line + i}: time does not increase "
                                 f"({t_ns[i - 1]} -> {t_ns[i]} ns)")
        return t_ns


def import_imu_table(source, imu_map: dict, where: str = "map") -> Recording:
    """An IMU sensor from the text table(s) ``imu_map`` describes (see the module docstring, docs/importers.md).

    Parameters
    ----------
    source : str or Path
        The one table (a file; then the map has no ``files``), or the folder holding the files the map names.
    imu_map : dict
        The map (as :func:`read_imu_map` returns it); checked again here.
    where : str
        Name of the map in error messages (its file).

    Returns
    -------
    Recording
        One IMU sensor (``sensor``, default ``imu0``) in rad/s and m/s^2; sensor.yaml holds ``rate_hz`` (the map's,
        else 1e9 / median step), the map's ``noise`` and ``gravity_m_s2`` where given, ``raw_counts`` where a
        group is in counts, and ``source``.
    """
    check_imu_map(imu_map, where)
    source = Path(source)
    if not source.exists():
        raise RecordingError(f"{source}: no such file or folder")
    files = imu_map.get("files")
    if source.is_dir():
        if files is None:
            raise RecordingError(f"{where}: SOURCE {source} is a folder: the map must name the files ('files')")
        paths = {g: source / (files[g] if isinstance(files, dict) else files) for g in ("accel", "gyro")}
    else:
        if files is not None:
            raise RecordingError(f"{where}: SOURCE {source} is a file but the map names files: give their folder")
        paths = {"accel": source, "gyro": source}
    tables = {}
    for path in dict.fromkeys(paths.values()):  # accel's file first, each file read once
        if not path.is_file():
            raise RecordingError(f"{path}: no such file (named by {where})")
        tables[path] = _Table(path, imu_map.get("delimiter"), imu_map.get("header", False),
                              imu_map.get("skip_rows", 0))

    time = imu_map["time"]
    t_ns = None
    si, raw = {}, {}
    for group in ("accel", "gyro"):
        table = tables[paths[group]]
        group_t_ns = table.time_ns(table.index(time["column"], "time"), time["unit"])
        if t_ns is None:
            t_ns, t_file = group_t_ns, table.file
        elif not np.array_equal(group_t_ns, t_ns):
            raise RecordingError(f"{table.file}: time column differs from {t_file.name}'s (the map's files must "
                                 "share their timestamps; resampling is not done)")
        channels = [imu_map[group][axis] for axis in AXES]
        values = table.values([table.index(c["column"], f"{group}.{a}") for c, a in zip(channels, AXES)])
        si[group], raw[group] = _to_si(values, channels, group)

    rate_hz = imu_map.get("rate_hz", 1e9 / float(np.median(np.diff(t_ns))) if len(t_ns) > 1 else None)
    meta = {"sensor_type": "imu"}
    if rate_hz is not None:
        meta["rate_hz"] = rate_hz if "rate_hz" in imu_map else float(f"{rate_hz:.6g}")
    if "gravity_m_s2" in imu_map:
        meta["gravity_m_s2"] = imu_map["gravity_m_s2"]
    meta.update(imu_map.get("noise", {}))
    if raw["accel"] or raw["gyro"]:
        meta["raw_counts"] = {RAW_COUNTS_NAMES[g][0]: {"offset_counts": raw[g][0], "counts_per_unit": raw[g][1],
                                                        "unit": RAW_COUNTS_NAMES[g][1]} for g in raw if raw[g]}
    meta["source"] = ", ".join(sorted({p.name for p in paths.values()}))
    name = imu_map.get("sensor", "imu0")
    sensor = imu_sensor(name, t_ns, si["gyro"], si["accel"], meta=meta)
    return Recording(path=None, sensors={name: sensor})


def _to_si(values: np.ndarray, channels: list[dict], group: str) -> tuple[np.ndarray, tuple | None]:
    """The three columns in the recording's unit, and (offsets, counts per SI unit) when all are counts."""
    units = GROUP_UNITS[group]
    out = np.empty_like(values)
    offsets, per_si = [], []
    for j, c in enumerate(channels):
        if c["unit"] == COUNTS:
            offset = float(c.get("offset", 0.0))
            factor = units[c.get("per", next(iter(units)))]
            out[:, j] = counts_to_si(values[:, j], offset, float(c["scale"]))
            if factor != 1.0:
                out[:, j] *= factor
            offsets.append(offset)
            per_si.append(float(c["scale"]) / factor)
        else:
            factor = units[c["unit"]]
            out[:, j] = values[:, j] * factor if factor != 1.0 else values[:, j]
    all_counts = len(offsets) == len(channels)
    return out, ((offsets, per_si) if all_counts else None)

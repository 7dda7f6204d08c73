"""CAN frames decoded through a DBC file (cantools), into the samples of :mod:`selfcal.io.streams`.

A DBC says how to read a frame's signals (bit position, scale, offset, unit); a small YAML map says which signal is
which quantity, with the recording's own sensor folders and column names (docs/streams.md)::

    incl0:                       # sensor folder
      roll: INCL_Roll            # column: DBC signal (or MESSAGE.SIGNAL when the name is not unique)
      pitch: INCL_Pitch
    imu0:
      w_RS_S_x: IMU_RateX        # gyro and accelerometer may come in different frames
      ...
      a_RS_S_z: IMU_AccZ

A sensor maps every column of one sensor kind of the serial protocol (:data:`selfcal.io.streams.SENTENCES`:
IMU, INC, TRK with or without velocity, CAM).  cantools applies each signal's scale and offset; the value is then
converted from the signal's DBC unit to the unit the column needs (:data:`selfcal.io.streams.COLUMN_UNITS`) when
the conversion is one of :data:`UNIT_FACTORS` (deg -> rad, mm -> m, g -> m s^-2, ...), and the signal is refused
otherwise.  A signal without a unit is taken to be in the column's unit.

A sample is emitted when the frame that completes its columns arrives, stamped with that frame's time (the bus
or log time; a DBC sensor clock signal is not used).  A column arriving again before the sample is complete means
a frame was lost: the partial sample is counted as malformed and dropped.  A signal decoded to one of its DBC
value names (``VAL_``, e.g. ``NoValidReading``) is not a number: the sample is dropped and counted as malformed,
as the fixed layout's ``0x7FFF`` marker is.  Frames whose ID carries no mapped signal are counted (``ignored``)
and skipped, as on the live bus.
"""
from __future__ import annotations

import difflib
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from selfcal.core.inertial import STANDARD_GRAVITY_M_S2
from selfcal.io.streams import COLUMN_UNITS, SENTENCES, Sample, StreamError, StreamStats, bus_messages

DEG = math.pi / 180.0

# the column's unit (recording contract) -> {DBC unit as written (lower case, one space between words): factor}
UNIT_FACTORS: dict[str, dict[str, float]] = {
    "rad": {"rad": 1.0, "mrad": 1e-3, "deg": DEG, "°": DEG, "degree": DEG, "degrees": DEG},
    "rad s^-1": {"rad/s": 1.0, "rad s^-1": 1.0, "deg/s": DEG, "°/s": DEG, "deg s^-1": DEG, "dps": DEG},
    # g: standard gravity, as accelerometer datasheets define it (ISO 80000-3), not the local gravity
    "m s^-2": {"m/s^2": 1.0, "m/s²": 1.0, "m/s2": 1.0, "m s^-2": 1.0, "g": STANDARD_GRAVITY_M_S2,
               "mg": 1e-3 * STANDARD_GRAVITY_M_S2},
    "m": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6},
    "m s^-1": {"m/s": 1.0, "m s^-1": 1.0, "mm/s": 1e-3},
    "px": {"px": 1.0, "pixel": 1.0, "pixels": 1.0, "pix": 1.0},
}


class DbcError(StreamError):
    """A DBC or its map cannot be used (fails to load, unknown signal, unit that contradicts the quantity)."""


def unit_factor(dbc_unit: str | None, column: str, where: str) -> float:
    """Factor from a signal's DBC unit to ``column``'s unit; an empty unit is the column's own."""
    needed = COLUMN_UNITS[column]
    text = " ".join((dbc_unit or "").split()).lower()
    if not text:
        return 1.0
    factors = UNIT_FACTORS[needed]
    if text not in factors:
        raise DbcError(f"{where}: DBC unit {dbc_unit!r} cannot be read as {column} [{needed}] "
                       f"(accepted: {', '.join(factors)})")
    return factors[text]


def load_dbc(path):
    """The cantools database of ``path`` (DBC, or any format cantools reads: KCD, SYM, ARXML)."""
    import cantools

    path = Path(path)
    if not path.is_file():
        raise DbcError(f"{path}: no such DBC file")
    try:
        return cantools.database.load_file(str(path))
    except (cantools.database.UnsupportedDatabaseFormatError, ValueError, UnicodeDecodeError) as err:
        raise DbcError(f"{path}: not a DBC cantools can load ({' '.join(str(err).split())})") from None


def load_dbc_map(path) -> dict[str, dict[str, str]]:
    """``{sensor: {column: signal}}`` from the YAML map file (see the module docstring)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise DbcError(f"{path}: no such DBC map file")
    try:
        content = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise DbcError(f"{path}: invalid YAML ({' '.join(str(err).split())})") from None
    if not isinstance(content, dict) or not content or not all(
            isinstance(cols, dict) and cols and all(isinstance(c, str) and isinstance(s, str) for c, s in cols.items())
            for cols in content.values()):
        raise DbcError(f"{path}: a DBC map is 'sensor: {{column: DBC signal name}}' (e.g. incl0: {{roll: INCL_Roll}})")
    return {str(sensor): dict(cols) for sensor, cols in content.items()}


def sensor_columns(sensor: str, columns) -> tuple[str, ...]:
    """The mapped columns in protocol order, if they are exactly the columns of one sensor kind."""
    unknown = [c for c in columns if c not in COLUMN_UNITS]
    if unknown:
        raise DbcError(f"DBC map: {sensor}: unknown column {unknown[0]!r}; known: {', '.join(COLUMN_UNITS)}")
    for kind_columns, optional in SENTENCES.values():
        for full in {kind_columns, kind_columns[:len(kind_columns) - optional]}:
            if set(columns) == set(full):
                return full
    kinds = "; ".join(", ".join(cols) + (f" (last {opt} optional)" if opt else "") for cols, opt in SENTENCES.values())
    raise DbcError(f"DBC map: {sensor} maps {', '.join(columns)}; a sensor maps all the columns of one kind: {kinds}")


@dataclass(frozen=True)
class MappedSignal:
    """One DBC signal read as one column of one sensor: ``value [column unit] = decoded [DBC unit] * factor``."""

    sensor: str
    column: str
    signal: str
    factor: float


class DbcDecoder:
    """Frames (``can.Message``) -> samples, through a cantools database and a column map.

    Parameters
    ----------
    database : cantools.database.can.Database
    mapping : dict
        ``{sensor: {column: signal name or MESSAGE.SIGNAL}}``.
    name : str
        Name of the counters (``stats``).
    """

    def __init__(self, database, mapping: dict[str, dict[str, str]], name: str = "DBC"):
        self.stats = StreamStats(name)
        self.columns = {sensor: sensor_columns(sensor, list(cols)) for sensor, cols in mapping.items()}
        by_name: dict[str, list] = {}
        for message in database.messages:
            for signal in message.signals:
                by_name.setdefault(signal.name, []).append((message, signal))
                by_name.setdefault(f"{message.name}.{signal.name}", []).append((message, signal))
        # (frame id, extended) -> (cantools message, the signals mapped from it)
        self.frames: dict[tuple[int, bool], tuple[object, list[MappedSignal]]] = {}
        for sensor, cols in mapping.items():
            for column, wanted in cols.items():
                where = f"DBC map: {sensor} {column} -> {wanted}"
                found = by_name.get(wanted, [])
                if not found:
                    close = difflib.get_close_matches(wanted, list(by_name), n=1)
                    raise DbcError(f"{where}: no such signal in the DBC" + (f" (did you mean {close[0]}?)" if close
                                                                            else ""))
                if len(found) > 1:
                    raise DbcError(f"{where}: the signal is in messages {', '.join(m.name for m, _ in found)}; "
                                   f"write MESSAGE.SIGNAL")
                message, signal = found[0]
                key = (message.frame_id, bool(message.is_extended_frame))
                self.frames.setdefault(key, (message, []))[1].append(
                    MappedSignal(sensor, column, signal.name, unit_factor(signal.unit, column, where)))
        self._pending: dict[str, dict[str, float]] = {}

    def decode(self, msg) -> list[Sample]:
        """The samples that ``msg`` completes (most often none or one); counts what it skips."""
        entry = None
        if not (msg.is_remote_frame or msg.is_error_frame):
            entry = self.frames.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if entry is None:
            self.stats.ignored += 1
            return []
        import cantools
        message, mapped = entry
        try:
            decoded = message.decode(bytes(msg.data[:msg.dlc]), decode_choices=True)
        except (cantools.database.DecodeError, ValueError, KeyError, IndexError) as err:
            self.stats.bad(f"{message.name}: {' '.join(str(err).split())}")
            return []
        # bus/log time to the microsecond: the resolution of candump and ASC logs (a float of epoch seconds holds
        # 0.24 us, so the float's last digits are noise, not time)
        host = msg.timestamp if msg.timestamp else time.time()
        t_ns = int(round(host * 1e6)) * 1000
        out = []
        for sensor in dict.fromkeys(m.sensor for m in mapped):
            pending = self._pending.setdefault(sensor, {})
            parts = [m for m in mapped if m.sensor == sensor and m.signal in decoded]
            if any(m.column in pending for m in parts):  # a frame of the sample never came
                missing = [c for c in self.columns[sensor] if c not in pending]
                self.stats.bad(f"{sensor}: incomplete sample dropped (no {', '.join(missing)})")
                pending.clear()
            for m in parts:
                value = decoded[m.signal]
                if not isinstance(value, (int, float)):
                    self.stats.bad(f"{sensor}: {message.name}.{m.signal} reads {str(value)!r}")
                    pending.clear()
                    break
                pending[m.column] = float(value) * m.factor
            else:
                if len(pending) == len(self.columns[sensor]):
                    out.append((sensor, t_ns, {c: pending[c] for c in self.columns[sensor]}))
                    pending.clear()
                    self.stats.samples += 1
        return out


def dbc_decoder(dbc_path, map_path, name: str) -> DbcDecoder:
    """A decoder from a DBC file and its YAML map (one-line errors for either)."""
    if map_path is None:
        raise DbcError(f"{dbc_path}: a DBC needs its map (which signal is which column; docs/streams.md)")
    return DbcDecoder(load_dbc(dbc_path), load_dbc_map(map_path), name=name)


class CanDbcSource:
    """Samples from a live python-can bus, decoded through a :class:`DbcDecoder` (``selfcal track --can --dbc``)."""

    def __init__(self, decoder: DbcDecoder, bus=None, channel: str | None = None, interface: str = "socketcan",
                 timeout_s: float = 0.05):
        if bus is None:
            import can
            try:
                bus = can.Bus(channel=channel, interface=interface)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                raise StreamError(f"CAN {interface}:{channel}: {' '.join(str(err).split())}") from None
        self.bus, self.decoder, self.timeout_s = bus, decoder, timeout_s
        self.stats = decoder.stats

    def samples(self, stop: threading.Event | None = None) -> Iterator[Sample]:
        for msg in bus_messages(self.bus, self.timeout_s, self.stats, stop):
            yield from self.decoder.decode(msg)

    def close(self) -> None:
        self.bus.shutdown()

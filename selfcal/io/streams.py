"""Live sample streams: serial lines (pyserial), CAN frames (python-can) and recording replay.

Every source yields ``(sensor_name, t_ns, values)`` with ``values`` keyed by the recording's column names
without units (``w_RS_S_x``, ``x``, ``roll``, ...), so that what a live system sees is exactly what a recording
holds.  The protocols are documented in ``docs/streams.md``; in short:

Serial line protocol (ASCII, one sentence per line, NMEA-style)::

    $IMU,<t_ns>,<wx>,<wy>,<wz>,<ax>,<ay>,<az>*<CS>      rad/s, m/s^2 (EuRoC imu columns)
    $INC,<t_ns>,<roll>,<pitch>*<CS>                       rad
    $TRK,<t_ns>,<x>,<y>,<z>[,<vx>,<vy>,<vz>]*<CS>         m, m/s
    $CAM,<t_ns>,<u>,<v>*<CS>                              px (beam spot)

``CS`` is the XOR of every byte between ``$`` and ``*``, two hex digits (as NMEA 0183).  The line ends with
``\\n`` (``\\r\\n`` accepted).

CAN frame (CANopen-style inclinometer, TPDO1, COB-ID ``0x180 + node_id``, DLC 8, little-endian)::

    bytes 0-1  roll   int16, 0.001 deg per LSB (+-32.767 deg); 0x7FFF = no valid reading
    bytes 2-3  pitch  int16, 0.001 deg per LSB;                  0x7FFF = no valid reading
    bytes 4-7  sensor time stamp, uint32, microseconds (wraps every 71.6 min; unwrapped here)

A malformed line or frame is counted and skipped with a warning (rate-limited); the stream goes on.
"""
from __future__ import annotations

import heapq
import logging
import math
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from selfcal.core.errors import SelfcalError
from selfcal.io.recording import ACCEL_COLUMNS, GYRO_COLUMNS, IMU_UNITS, Recording

log = logging.getLogger(__name__)

Sample = tuple[str, int, dict[str, float]]

# sentence type -> (column names in line order, number of optional trailing columns)
SENTENCES: dict[str, tuple[tuple[str, ...], int]] = {
    "IMU": (GYRO_COLUMNS + ACCEL_COLUMNS, 0),
    "INC": (("roll", "pitch"), 0),
    "TRK": (("x", "y", "z", "vx", "vy", "vz"), 3),
    "CAM": (("u", "v"), 0),
}
DEFAULT_SENSORS = {"IMU": "imu0", "INC": "incl0", "TRK": "tracker0", "CAM": "cam0"}

# column -> unit, for writing what a stream yields into a recording (the recording contract's units)
COLUMN_UNITS: dict[str, str] = {
    **IMU_UNITS,
    "x": "m", "y": "m", "z": "m", "vx": "m s^-1", "vy": "m s^-1", "vz": "m s^-1",
    "roll": "rad", "pitch": "rad", "u": "px", "v": "px",
}
SENSOR_TYPES = {"IMU": "imu", "INC": "inclinometer", "TRK": "laser_tracker", "CAM": "camera"}

CAN_TPDO1_BASE = 0x180
CAN_ANGLE_LSB_RAD = math.radians(0.001)
CAN_INVALID = 0x7FFF
_CAN_LAYOUT = struct.Struct("<hhI")


class StreamError(SelfcalError):
    """A stream cannot be opened or configured (bad port, unknown sentence type, ...)."""


@dataclass
class StreamStats:
    """Counters of one source: good samples, malformed input skipped, input ignored (not for us)."""

    name: str
    samples: int = 0
    malformed: int = 0
    ignored: int = 0
    late: int = 0  # dropped by a merger because it arrived after samples with later timestamps were released
    reanchored: int = 0  # sensor clock stepped back or reset: time re-anchored to the host clock
    _last_warning_s: float = field(default=-math.inf, repr=False)
    _suppressed: int = field(default=0, repr=False)

    def bad(self, reason: str, min_interval_s: float = 1.0) -> None:
        """Count a malformed input and warn, at most once per ``min_interval_s`` (a noisy line floods no log)."""
        self.malformed += 1
        now = time.monotonic()
        if now - self._last_warning_s >= min_interval_s:
            extra = f" ({self._suppressed} more since the last warning)" if self._suppressed else ""
            log.warning("%s: skipped malformed input: %s%s", self.name, reason, extra)
            self._last_warning_s, self._suppressed = now, 0
        else:
            self._suppressed += 1


# ------------------------------------------------------------------------------------------------ serial lines

def nmea_checksum(body: str) -> int:
    """XOR of the bytes of ``body`` (the text between ``$`` and ``*``)."""
    cs = 0
    for b in body.encode("ascii"):
        cs ^= b
    return cs


def format_sentence(kind: str, t_ns: int, values: Iterable[float]) -> bytes:
    """One protocol line, checksum and ``\\r\\n`` included (for simulators, tests and sensor firmware).

    Floats use Python's shortest round-trip repr, so a parsed value is the identical float64.
    """
    body = ",".join([kind, str(int(t_ns)), *(repr(float(v)) for v in values)])
    return f"${body}*{nmea_checksum(body):02X}\r\n".encode("ascii")


def parse_sentence(line: bytes | str, sensors: dict[str, str] | None = None) -> Sample:
    """Parse one protocol line into ``(sensor_name, t_ns, values)``.

    Parameters
    ----------
    line : bytes or str
        One line, with or without its line ending.
    sensors : dict, optional
        Sentence type -> sensor name (default :data:`DEFAULT_SENSORS`).

    Raises
    ------
    ValueError
        The line is malformed (no ``$``, bad checksum, unknown type, wrong field count, non-finite value); the
        message says which.
    """
    sensors = DEFAULT_SENSORS if sensors is None else sensors
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            raise ValueError("not ASCII") from None
    line = line.strip()
    if not line.startswith("$"):
        raise ValueError(f"no leading '$' in {line[:40]!r}")
    star = line.rfind("*")
    if star < 0 or len(line) - star != 3:
        raise ValueError(f"no '*<2 hex digits>' checksum in {line[:40]!r}")
    body = line[1:star]
    try:
        expected = int(line[star + 1:], 16)
    except ValueError:
        raise ValueError(f"checksum {line[star + 1:]!r} is not hex") from None
    if nmea_checksum(body) != expected:
        raise ValueError(f"checksum mismatch ({nmea_checksum(body):02X} != {expected:02X}) in {line[:40]!r}")
    fields = body.split(",")
    kind = fields[0]
    if kind not in SENTENCES:
        raise ValueError(f"unknown sentence type {kind!r}")
    if kind not in sensors:
        raise ValueError(f"sentence type {kind!r} is not mapped to a sensor on this port")
    columns, optional = SENTENCES[kind]
    n = len(fields) - 2
    if n not in (len(columns), len(columns) - optional):
        raise ValueError(f"{kind}: {n} values, expected {len(columns)}"
                         + (f" or {len(columns) - optional}" if optional else ""))
    try:
        t_ns = int(fields[1])
        values = [float(f) for f in fields[2:]]
    except ValueError:
        raise ValueError(f"{kind}: non-numeric field in {line[:60]!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{kind}: non-finite value")
    return sensors[kind], t_ns, dict(zip(columns, values))


def parse_serial_spec(spec: str) -> tuple[str, int | None, dict[str, str]]:
    """``PORT[:BAUD][,TYPE=sensor...]`` -> (port, baud or None, sentence type -> sensor name).

    A trailing ``:BAUD`` is read as a baud rate only when it is one of pyserial's standard rates, so that a
    ``socket://host:7777`` port keeps its TCP port.  Without a mapping every sentence type goes to its default
    sensor (``IMU=imu0,INC=incl0,TRK=tracker0,CAM=cam0``); with one, only the listed types are accepted.
    """
    import serial

    port, *pairs = spec.split(",")
    sensors = {}
    for pair in pairs:
        kind, sep, name = pair.partition("=")
        kind = kind.strip().upper()
        if not sep or kind not in SENTENCES or not name.strip():
            raise StreamError(f"--serial {spec!r}: mapping {pair!r} is not TYPE=sensor with TYPE one of "
                              f"{', '.join(SENTENCES)}")
        sensors[kind] = name.strip()
    baud = None
    head, sep, tail = port.rpartition(":")
    if sep and tail.isdigit() and int(tail) in serial.Serial.BAUDRATES and head and not head.endswith("/"):
        port, baud = head, int(tail)
    if not port:
        raise StreamError(f"--serial {spec!r}: no port")
    return port, baud, sensors or dict(DEFAULT_SENSORS)


class SerialLineSource:
    """Samples from one serial port speaking the line protocol.

    Parameters
    ----------
    port : str or serial.Serial
        A pyserial URL / device name (opened with ``serial_for_url``), or an open port object (anything with
        ``read(n)`` and ``in_waiting``; tests pass ``serial_for_url("loop://")``).
    baudrate : int, optional
    sensors : dict, optional
        Sentence type -> sensor name.
    timeout_s : float
        Read timeout: how often :meth:`samples` checks its stop flag when the line is quiet.
    max_line : int
        A line longer than this without a newline is garbage: dropped and counted.
    """

    def __init__(self, port, baudrate: int | None = None, sensors: dict[str, str] | None = None,
                 timeout_s: float = 0.05, max_line: int = 512):
        if isinstance(port, str):
            import serial
            try:
                kwargs = {"timeout": timeout_s}
                if baudrate:
                    kwargs["baudrate"] = baudrate
                self.port = serial.serial_for_url(port, **kwargs)
            except (serial.SerialException, ValueError) as err:
                raise StreamError(f"serial port {port}: {' '.join(str(err).split())}") from None
            self.name = port
        else:
            self.port = port
            self.name = getattr(port, "name", None) or getattr(port, "portstr", None) or "serial"
        self.sensors = dict(DEFAULT_SENSORS if sensors is None else sensors)
        self.max_line = max_line
        self.stats = StreamStats(f"serial {self.name}")
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Sample]:
        """Split ``data`` (appended to what is buffered) into lines and parse each complete one."""
        self._buffer.extend(data)
        out = []
        while True:
            nl = self._buffer.find(b"\n")
            if nl < 0:
                if len(self._buffer) > self.max_line:  # no newline for too long: noise on the line
                    self.stats.bad(f"{len(self._buffer)} bytes without a line end")
                    self._buffer.clear()
                return out
            line = bytes(self._buffer[:nl])
            del self._buffer[:nl + 1]
            if not line.strip():
                continue
            try:
                out.append(parse_sentence(line, self.sensors))
                self.stats.samples += 1
            except ValueError as err:
                self.stats.bad(str(err))

    def poll(self) -> list[Sample]:
        """Read what the port holds (blocking at most its timeout) and return the complete samples."""
        data = self.port.read(max(1, self.port.in_waiting))
        return self.feed(data) if data else []

    def samples(self, stop: threading.Event | None = None) -> Iterator[Sample]:
        """Yield samples until ``stop`` is set or the port closes."""
        while stop is None or not stop.is_set():
            try:
                batch = self.poll()
            except (OSError, ValueError) as err:  # pyserial raises SerialException (an OSError) on unplug
                log.warning("%s: port closed (%s)", self.name, " ".join(str(err).split()))
                return
            yield from batch

    def close(self) -> None:
        self.port.close()


# ------------------------------------------------------------------------------------------------------- CAN

def encode_inclinometer_frame(roll_rad: float, pitch_rad: float, sensor_time_us: int) -> bytes:
    """The 8-byte TPDO1 payload for (roll, pitch) and the sensor's microsecond clock (see module docstring)."""
    counts = [int(round(a / CAN_ANGLE_LSB_RAD)) for a in (roll_rad, pitch_rad)]
    if any(abs(c) >= CAN_INVALID for c in counts):
        raise ValueError("angle outside the +-32.766 deg range of the frame")
    return _CAN_LAYOUT.pack(counts[0], counts[1], int(sensor_time_us) & 0xFFFFFFFF)


def decode_inclinometer_frame(data: bytes) -> tuple[float, float, int]:
    """(roll_rad, pitch_rad, sensor_time_us) from a TPDO1 payload; ValueError if malformed or invalid."""
    if len(data) != _CAN_LAYOUT.size:
        raise ValueError(f"DLC {len(data)}, expected {_CAN_LAYOUT.size}")
    roll, pitch, t_us = _CAN_LAYOUT.unpack(bytes(data))
    if CAN_INVALID in (roll, pitch) or -CAN_INVALID - 1 in (roll, pitch):
        raise ValueError("sensor flags no valid reading (0x7FFF)")
    return roll * CAN_ANGLE_LSB_RAD, pitch * CAN_ANGLE_LSB_RAD, t_us


class CanInclinometerSource:
    """Samples ``(sensor, t_ns, {"roll", "pitch"})`` from a CANopen-style inclinometer on a python-can bus.

    Time: the frame's 32-bit microsecond counter is unwrapped and anchored to the host receive time of the first
    frame, ``t_ns = t_host_first_ns + (t_sensor_us - t_sensor_first_us) * 1000``: the sensor clock keeps the
    spacing (no bus jitter), the host clock gives the epoch.  A wrap is a modular step the host clock agrees
    with; a step the host clock does not show (more than ``REANCHOR_SLACK_S`` beyond the host's elapsed time: the
    counter stepped back, or the sensor reset) re-anchors the time to the host's receive time, never earlier than
    the previous sample, and is counted (``stats.reanchored``): a 1 us step back read as a wrap had thrown every
    later sample 4294.97 s into the future.

    Parameters
    ----------
    bus : can.BusABC or None
        An open bus; or None with ``channel`` and ``interface`` (``virtual``, ``socketcan``, ...).
    node_id : int
        CANopen node id 1..127; frames with COB-ID ``0x180 + node_id`` are read, other frames ignored.
    sensor : str
        Sensor name of the samples (``incl0``).
    """

    def __init__(self, bus=None, channel: str | None = None, interface: str = "socketcan", node_id: int = 1,
                 sensor: str = "incl0", timeout_s: float = 0.05):
        if bus is None:
            import can
            try:
                bus = can.Bus(channel=channel, interface=interface)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                raise StreamError(f"CAN {interface}:{channel}: {' '.join(str(err).split())}") from None
        if not 1 <= node_id <= 127:
            raise StreamError(f"CANopen node id {node_id} outside 1..127")
        self.bus = bus
        self.cob_id = CAN_TPDO1_BASE + node_id
        self.sensor = sensor
        self.timeout_s = timeout_s
        self.stats = StreamStats(f"CAN {getattr(bus, 'channel_info', 'bus')} node {node_id}")
        self._anchor_ns: int | None = None
        self._first_us = 0
        self._unwrapped_us = 0
        self._last_raw_us: int | None = None
        self._last_host_s = 0.0
        self._last_t_ns = 0

    REANCHOR_SLACK_S = 1.0  # host receive times jitter by milliseconds; a wrap's step matches them within this

    def handle(self, msg) -> Sample | None:
        """Turn one received ``can.Message`` into a sample (None if it is not ours or is malformed)."""
        if msg.arbitration_id != self.cob_id or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            self.stats.ignored += 1
            return None
        try:
            roll, pitch, t_us = decode_inclinometer_frame(msg.data[:msg.dlc])
        except ValueError as err:
            self.stats.bad(str(err))
            return None
        host = msg.timestamp if msg.timestamp else time.time()
        step_us = (t_us - self._last_raw_us) & 0xFFFFFFFF if self._last_raw_us is not None else None
        if step_us is not None and step_us * 1e-6 > host - self._last_host_s + self.REANCHOR_SLACK_S:
            self.stats.reanchored += 1
            log.warning("%s: sensor clock stepped back or reset (%d us -> %d us); time re-anchored to the host",
                        self.stats.name, self._last_raw_us, t_us)
            step_us = None
        if step_us is None:
            anchor = max(int(round(host * 1e9)), self._last_t_ns + 1000)
            self._anchor_ns, self._first_us, self._unwrapped_us = anchor, t_us, t_us
        else:
            self._unwrapped_us += step_us  # modular step: survives the wrap
        self._last_raw_us, self._last_host_s = t_us, host
        self.stats.samples += 1
        t_ns = self._anchor_ns + (self._unwrapped_us - self._first_us) * 1000
        self._last_t_ns = t_ns
        return self.sensor, t_ns, {"roll": roll, "pitch": pitch}

    def samples(self, stop: threading.Event | None = None) -> Iterator[Sample]:
        """Yield samples until ``stop`` is set."""
        for msg in bus_messages(self.bus, self.timeout_s, self.stats, stop):
            sample = self.handle(msg)
            if sample is not None:
                yield sample

    def close(self) -> None:
        self.bus.shutdown()


# ------------------------------------------------------------------------------------------------------ replay

def replay(recording: Recording, realtime: bool = False, speed: float = 1.0,
           sensors: Iterable[str] | None = None, clock: Callable[[], float] = time.monotonic,
           sleep: Callable[[float], None] = time.sleep) -> Iterator[Sample]:
    """Every sample of a recording, merged in timestamp order (ties: sensor name order).

    Parameters
    ----------
    recording : Recording
    realtime : bool
        Pace the samples by their timestamps (divided by ``speed``) against ``clock``; else as fast as possible.
    sensors : iterable of str, optional
        Only these sensors (default: all).
    """
    names = sorted(sensors) if sensors is not None else sorted(recording.sensors)
    missing = [n for n in names if n not in recording.sensors]
    if missing:
        raise StreamError(f"replay: no sensor {', '.join(missing)} in the recording")

    def one(name):
        s = recording.sensors[name]
        cols = list(s.values)
        table = np.column_stack([s.values[c] for c in cols]) if cols else np.empty((s.t_ns.size, 0))
        for t, row in zip(s.t_ns.tolist(), table.tolist()):
            yield t, name, dict(zip(cols, row))

    t0 = wall0 = None
    for t, name, values in heapq.merge(*(one(n) for n in names), key=lambda item: (item[0], item[1])):
        if realtime:
            if t0 is None:
                t0, wall0 = t, clock()
            wait = wall0 + (t - t0) * 1e-9 / speed - clock()
            if wait > 0:
                sleep(wait)
        yield name, t, values


# --------------------------------------------------------------------------------------------- live merging

def merge_live(sources: list, reorder_window_s: float = 0.05, stop: threading.Event | None = None,
               max_samples: int | None = None) -> Iterator[Sample]:
    """Merge live sources (each with ``samples(stop)``) into one stream in timestamp order.

    Each source runs in its own thread.  A sample is released once a sample at least ``reorder_window_s`` later
    has been seen from any source, so samples from different ports that arrive out of order by less than the
    window come out in order; a sample older than one already released is dropped and counted (``late``).

    Parameters
    ----------
    sources : list
        Objects with ``samples(stop) -> Iterator[Sample]`` and ``stats``.
    reorder_window_s : float
        Reordering latency budget, s.
    stop : threading.Event, optional
        Set it to end the stream; the buffered samples are flushed in order.
    max_samples : int, optional
        End after this many samples.
    """
    stop = stop or threading.Event()
    inbox: queue.Queue = queue.Queue(maxsize=100_000)
    alive = [True] * len(sources)

    def pump(k, src):
        try:
            for sample in src.samples(stop):
                inbox.put((k, sample))
        finally:
            alive[k] = False
            inbox.put((k, None))

    threads = [threading.Thread(target=pump, args=(k, s), daemon=True, name=f"stream-{k}")
               for k, s in enumerate(sources)]
    for th in threads:
        th.start()
    heap: list = []
    seq = 0
    newest = None
    released = None
    count = 0
    window_ns = int(reorder_window_s * 1e9)
    try:
        while any(alive) or not inbox.empty():
            try:
                k, sample = inbox.get(timeout=0.05)
            except queue.Empty:
                k, sample = None, None
            if sample is not None:
                name, t, values = sample
                if released is not None and t < released:
                    sources[k].stats.late += 1
                    log.warning("%s: sample %s at %d ns arrived after %d ns was released; dropped",
                                sources[k].stats.name, name, t, released)
                else:
                    heapq.heappush(heap, (t, seq, sample))
                    seq += 1
                    newest = t if newest is None else max(newest, t)
            while heap and (heap[0][0] <= newest - window_ns or stop.is_set()):
                t, _, sample = heapq.heappop(heap)
                released = t
                yield sample
                count += 1
                if max_samples is not None and count >= max_samples:
                    stop.set()
                    return
        while heap:
            yield heapq.heappop(heap)[2]
    finally:
        stop.set()
        for th in threads:
            th.join(timeout=1.0)


# ------------------------------------------------------------------------------------------- command-line glue

@dataclass
class OpenStream:
    """The merged sample stream of the sources a command line names, with their counters."""

    samples: Iterator[Sample]
    sources: list
    stop: threading.Event

    def stats(self) -> list[StreamStats]:
        return [s.stats for s in self.sources]

    def close(self) -> None:
        self.stop.set()
        for s in self.sources:
            close = getattr(s, "close", None)
            if close is not None:
                close()


class _ReplaySource:
    """A recording replay as a source (same ``stats`` as the live ones)."""

    def __init__(self, recording: Recording, realtime: bool, speed: float):
        self.recording, self.realtime, self.speed = recording, realtime, speed
        self.stats = StreamStats(f"replay {recording.path}")

    def samples(self, stop: threading.Event | None = None) -> Iterator[Sample]:
        for sample in replay(self.recording, realtime=self.realtime, speed=self.speed):
            if stop is not None and stop.is_set():
                return
            self.stats.samples += 1
            yield sample


def open_stream(serial: list[str] | None = None, can_channel: str | None = None, can_interface: str = "socketcan",
                can_node: int = 1, can_sensor: str = "incl0", replay_path=None, realtime: bool = False,
                speed: float = 1.0, reorder_window_s: float = 0.05, max_samples: int | None = None,
                can_log=None, dbc=None, dbc_map=None, replay_recording: Recording | None = None) -> OpenStream:
    """Open every source named on a command line and merge them in timestamp order.

    A replay alone is merged exactly (it is already sorted); live sources (and a replay mixed with them) go
    through :func:`merge_live` with its reordering window.  A CAN log (``can_log``, :mod:`selfcal.io.canlog`) is a
    file like a replay: alone or with a replay it is merged exactly, never with live sources.  ``dbc`` and
    ``dbc_map`` decode the CAN frames (live or logged) through a DBC (:mod:`selfcal.io.dbc`) instead of the fixed
    inclinometer TPDO1.  ``replay_recording``: the recording at ``replay_path`` when the caller has read it already.
    """
    from selfcal.io.recording import read_recording

    if can_log is not None and (serial or can_channel is not None):
        raise StreamError("--can-log replays a file: it cannot be merged with live --serial/--can sources")
    sources: list = []
    stop = threading.Event()
    try:
        for spec in serial or []:
            port, baud, sensors = parse_serial_spec(spec)
            sources.append(SerialLineSource(port, baud, sensors))
        if can_channel is not None and dbc is not None:
            from selfcal.io.dbc import CanDbcSource, dbc_decoder
            sources.append(CanDbcSource(dbc_decoder(dbc, dbc_map, f"CAN {can_interface}:{can_channel} (DBC)"),
                                        channel=can_channel, interface=can_interface))
        elif can_channel is not None:
            sources.append(CanInclinometerSource(channel=can_channel, interface=can_interface, node_id=can_node,
                                                 sensor=can_sensor))
        if replay_path is not None:
            recording = replay_recording if replay_recording is not None else read_recording(replay_path)
            sources.append(_ReplaySource(recording, realtime and can_log is None, speed))
        if can_log is not None:
            from selfcal.io.canlog import CanLogSource, merge_offline
            from selfcal.io.dbc import dbc_decoder
            decoder = dbc_decoder(dbc, dbc_map, "DBC") if dbc is not None else None
            sources.append(CanLogSource(can_log, decoder, node_id=can_node, sensor=can_sensor))
            return OpenStream(merge_offline(sources, stop, max_samples, realtime, speed), sources, stop)
    except BaseException:
        for opened in sources:
            if hasattr(opened, "close"):
                opened.close()
        raise
    if not sources:
        raise StreamError("no source: give --serial PORT, --can CHANNEL and/or --replay REC")
    if len(sources) == 1 and isinstance(sources[0], _ReplaySource):
        def only(src=sources[0]):
            for k, sample in enumerate(src.samples(stop)):
                if max_samples is not None and k >= max_samples:
                    return
                yield sample
        return OpenStream(only(), sources, stop)
    return OpenStream(merge_live(sources, reorder_window_s, stop, max_samples), sources, stop)


def bus_messages(bus, timeout_s: float, stats: StreamStats, stop: threading.Event | None = None):
    """Frames of a live python-can bus until ``stop`` is set; a bus error is counted and skipped, never fatal
    (shared by the fixed-layout and the DBC sources)."""
    import can
    while stop is None or not stop.is_set():
        try:
            msg = bus.recv(timeout=timeout_s)
        except can.CanError as err:
            stats.bad(f"bus error: {' '.join(str(err).split())}")
            continue
        if msg is not None:
            yield msg

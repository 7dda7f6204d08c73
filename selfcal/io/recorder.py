"""Append-safe recording of live samples into the ASL layout (``selfcal record``).

Each sensor's ``data.csv`` gets its header once, then one line per sample, written in a single ``write`` and
flushed to the operating system at once: a recorder killed at any instant loses at most the line it was
writing (the kernel keeps what was flushed, even after SIGKILL).  ``fsync_every_s`` also pushes the data to
the disk periodically, so a power cut loses at most that much.

A restart appends, never overwrites: the existing header must hold the same columns, a trailing partial line
(from a kill mid-write) is cut off, and samples not later than the last one on file are dropped (counted) so
the timestamps keep increasing, as :func:`selfcal.io.recording.read_recording` requires.  ``sensor.yaml`` is
written once, atomically, when the sensor folder is created.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from selfcal.io.atomic import atomic_write_text
from selfcal.io.recording import TIMESTAMP_FIELD, RecordingError, _FIELD_RE
from selfcal.io.streams import COLUMN_UNITS

log = logging.getLogger(__name__)


@dataclass
class SensorWriter:
    """One open ``data.csv`` in append mode."""

    name: str
    path: Path
    columns: list[str]
    file: object
    last_t_ns: int | None
    written: int = 0
    dropped: int = 0
    repaired_bytes: int = 0


@dataclass
class Recorder:
    """Write samples ``(sensor, t_ns, values)`` into ``folder/<sensor>/data.csv`` as they come.

    Parameters
    ----------
    folder : Path
        Recording folder (created if missing; an existing one is appended to).
    units : dict, optional
        Column -> unit for columns outside :data:`selfcal.io.streams.COLUMN_UNITS`.
    meta : dict, optional
        Sensor name -> sensor.yaml content for new sensors (``sensor_type``, ``rate_hz``, noise keys).
    fsync_every_s : float
        Call ``fsync`` at most this often (0: after every line; slow on real disks).
    """

    folder: Path
    units: dict[str, str] = field(default_factory=dict)
    meta: dict[str, dict] = field(default_factory=dict)
    fsync_every_s: float = 1.0
    writers: dict[str, SensorWriter] = field(default_factory=dict)
    _last_sync: float = field(default=0.0, repr=False)

    def __post_init__(self):
        self.folder = Path(self.folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise RecordingError(f"{self.folder}: exists and is not a folder")
        self.folder.mkdir(parents=True, exist_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def write(self, sensor: str, t_ns: int, values: dict[str, float]) -> bool:
        """Append one sample; False if it was dropped (timestamp not increasing, or columns that do not fit)."""
        w = self.writers.get(sensor) or self._open(sensor, values)
        if w.last_t_ns is not None and t_ns <= w.last_t_ns:
            w.dropped += 1
            log.warning("%s: sample at %d ns is not after the last one on file (%d ns); dropped",
                        sensor, t_ns, w.last_t_ns)
            return False
        try:
            row = [repr(float(values[c])) for c in w.columns]
        except (KeyError, TypeError, ValueError) as err:
            w.dropped += 1
            log.warning("%s: sample at %d ns does not fit the columns %s (%s); dropped", sensor, t_ns,
                        ",".join(w.columns), err)
            return False
        if any(v in ("nan", "inf", "-inf") for v in row):
            w.dropped += 1
            log.warning("%s: non-finite value at %d ns; dropped", sensor, t_ns)
            return False
        w.file.write(",".join([str(int(t_ns)), *row]) + "\n")  # one write of a whole line ...
        w.file.flush()  # ... handed to the kernel at once: a SIGKILL later cannot take it back
        w.last_t_ns = int(t_ns)
        w.written += 1
        now = time.monotonic()
        if now - self._last_sync >= self.fsync_every_s:
            for other in self.writers.values():
                os.fsync(other.file.fileno())
            self._last_sync = now
        return True

    def close(self) -> None:
        for w in self.writers.values():
            if not w.file.closed:
                w.file.flush()
                os.fsync(w.file.fileno())
                w.file.close()

    def counts(self) -> dict[str, dict[str, int]]:
        return {n: {"written": w.written, "dropped": w.dropped, "repaired_bytes": w.repaired_bytes}
                for n, w in self.writers.items()}

    # ------------------------------------------------------------------------------------------------------
    def _unit(self, column: str) -> str:
        unit = self.units.get(column) or COLUMN_UNITS.get(column)
        if unit is None:
            raise RecordingError(f"column {column!r} has no known unit (pass units={{{column!r}: ...}})")
        return unit

    def _open(self, sensor: str, values: dict[str, float]) -> SensorWriter:
        if not sensor or sensor.startswith(".") or "/" in sensor or sensor == "truth":
            raise RecordingError(f"sensor name {sensor!r} cannot be a sensor folder")
        sub = self.folder / sensor
        sub.mkdir(exist_ok=True)
        path = sub / "data.csv"
        columns = list(values)
        header = ",".join([TIMESTAMP_FIELD, *(f"{c} [{self._unit(c)}]" for c in columns)])
        last_t, repaired = None, 0
        if path.exists() and path.stat().st_size > 0:
            columns, last_t, repaired = _prepare_append(path, header)
        else:
            with open(path, "w", encoding="utf-8", newline="\n") as f:
                f.write(header + "\n")
                f.flush()
                os.fsync(f.fileno())
        if not (sub / "sensor.yaml").exists():
            meta = self.meta.get(sensor) or {"sensor_type": _guess_type(columns)}
            atomic_write_text(sub / "sensor.yaml", yaml.safe_dump(meta, sort_keys=False))
        w = SensorWriter(sensor, path, columns, open(path, "a", encoding="utf-8", newline="\n"), last_t,
                         repaired_bytes=repaired)
        self.writers[sensor] = w
        log.info("%s: %s %s", sensor, "appending to" if last_t is not None else "created", path)
        return w


def _guess_type(columns: list[str]) -> str:
    cols = set(columns)
    if {"w_RS_S_x", "a_RS_S_x"} <= cols:
        return "imu"
    if {"roll", "pitch"} <= cols:
        return "inclinometer"
    if {"x", "y", "z"} <= cols:
        return "laser_tracker"
    if {"u", "v"} <= cols:
        return "camera"
    return "generic"


def _prepare_append(path: Path, header: str) -> tuple[list[str], int | None, int]:
    """Check an existing data.csv for appending: (its columns, last timestamp, bytes cut from a partial line).

    A file killed while its header was being written (no complete first line) is restarted from the header.
    """
    with open(path, "rb+") as f:
        data = f.read()
        cut = 0
        if not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1  # 0 if not even the header is complete
            cut = len(data) - keep
            f.seek(keep)
            f.truncate()
            data = data[:keep]
            log.warning("%s: cut a partial last line (%d bytes) left by an interrupted recorder", path, cut)
        if not data:
            f.write(header.encode("utf-8") + b"\n")
            f.flush()
            os.fsync(f.fileno())
            return [c.split(" [")[0] for c in header.split(",")[1:]], None, cut
    lines = data.decode("utf-8", errors="replace").splitlines()
    fields = [s.strip() for s in lines[0].split(",")]
    if fields[0] != TIMESTAMP_FIELD:
        raise RecordingError(f"{path}:1: not a recording data.csv (header starts with {fields[0]!r})")
    columns = []
    for k, text in enumerate(fields[1:], start=2):
        m = _FIELD_RE.match(text)
        if m is None:
            raise RecordingError(f"{path}:1: header field {k} {text!r} is not 'name [unit]'")
        columns.append(m.group(1).strip())
    new = [c.split(" [")[0] for c in header.split(",")[1:]]
    if set(new) != set(columns):
        raise RecordingError(f"{path}: the file has columns {','.join(columns)} but the stream brings "
                             f"{','.join(new)}; record into a new folder")
    last_t = None
    for line in reversed(lines[1:]):
        if line.strip():
            try:
                last_t = int(line.split(",", 1)[0])
            except ValueError:
                raise RecordingError(f"{path}:{len(lines)}: last line has no integer timestamp") from None
            break
    return columns, last_t, cut


def record_stream(samples, folder, duration_s: float | None = None, max_samples: int | None = None,
                  clock=time.monotonic, stop: threading.Event | None = None,
                  **recorder_options) -> dict[str, dict[str, int]]:
    """Write ``samples`` into ``folder`` until they end, ``duration_s`` passes or ``max_samples`` are written.

    With the stream's ``stop`` event, the duration ends the stream even when no sample comes (a silent port), and
    the stream is then read to its end: a live merger flushes the samples its reordering window still holds
    (breaking out of the loop had thrown them away).  Returns the per-sensor counters (written, dropped,
    repaired_bytes).  Interrupting (Ctrl-C) is a normal end: the files are flushed and closed.
    """
    start = clock()
    n = 0
    timer = None
    if stop is not None and duration_s is not None:
        timer = threading.Timer(duration_s, stop.set)
        timer.daemon = True
        timer.start()
    with Recorder(Path(folder), **recorder_options) as rec:
        try:
            for sensor, t_ns, values in samples:
                n += rec.write(sensor, t_ns, values)
                if max_samples is not None and n >= max_samples:
                    break
                if duration_s is not None and clock() - start >= duration_s:
                    if stop is None:
                        break
                    stop.set()  # the stream ends once it has flushed what it holds
        except KeyboardInterrupt:
            log.info("interrupted: closing the recording")
        finally:
            if timer is not None:
                timer.cancel()
        return rec.counts()
